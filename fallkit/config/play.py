"""`play:` — the live viewer in the browser (mode=play).

Falls in play come from the same settings as evaluation (`eval.seed` starts the seeds of
random falls, `eval.seconds` is the length of a fall, `eval.split` the dataset split), so a
fall watched in the browser is a fall `mode=eval` would run; only what is specific to
watching and steering lives here.
"""

from __future__ import annotations

from pydantic import Field

from fallkit.config.section import Section


class PlayConfig(Section):
    """The browser viewer of `mode=play`: where it listens, what it shows first, how it draws."""

    host: str = Field(
        "127.0.0.1",
        description="address the viewer listens on; 127.0.0.1 = this machine only (reach it from elsewhere "
        "through an SSH port forward), 0.0.0.0 = every network interface",
    )
    port: int = Field(8080, ge=0, le=65535, description="TCP port of the viewer; 0 = any free port")
    speed: float = Field(1.0, ge=0.1, le=1.0, description="playback speed at start, a fraction of real time (0.1-1)")
    poses: str | None = Field(
        None,
        description="end poses to choose from: 'artist', 'default', a .npz dataset or a .yaml pose file; "
        "null = the robot's artist poses when it ships them, else eval.poses (or the training run's)",
    )
    pose: str | int | None = Field(
        None, description="end pose at start: a pose name (artist poses) or an index into the poses; null = the first"
    )
    strategies: list[str] | None = Field(
        None,
        description="what falls side by side: policy, zero_torque, damping, freeze, seek; "
        "null = the policy (with a checkpoint) and the three standard strategies",
    )
    force_threshold: float | None = Field(
        None, gt=0, description="[N] a component's peak-force bar turns red above this; null = 5 x the robot's weight"
    )
    push: float = Field(20.0, ge=0, description="[N·s] size of a push at start (an impulse on the root body)")
    push_direction: float = Field(
        0.0, ge=-180, le=180, description="[deg] direction of a push at start: 0 = the robot's front, 90 = its left"
    )
    push_time: float = Field(0.1, gt=0, le=1.0, description="[s] how long a push acts, the standing robot holding its pose")
    fps: float = Field(50.0, gt=0, le=120, description="most frames per second sent to the browser (at most one per policy step)")
    spacing: float = Field(1.6, gt=0, description="[m] between robots shown side by side")
