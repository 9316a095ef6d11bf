"""`detector:` — the fall detector that tells the fall policy when to take over, and its push test.

The detector (fallkit.deploy.detector.FallDetector, docs/fall_detection.md) runs on the robot
beside its own controller and says when a fall has begun. Its settings here are exported with
the policy (`mode=export` writes them into policy.json); `detector.pushes` is the evaluation in
simulation (`mode=detect`), which is not exported.
"""

from __future__ import annotations

import math

from pydantic import Field, field_validator

from fallkit.config.section import Section


class PushTestConfig(Section):
    """mode=detect: the robot standing at its nominal pose under its PD controller, pushed once per trial.

    Push sizes grow evenly from 0 to `max_impulse` over the trials (the 1st push is the smallest),
    each from its own random horizontal direction, so small pushes (survived) and large ones (falls)
    are both well represented. A trial is a fall when a body other than the feet touches the ground
    within `horizon` seconds of the push's start.
    """

    count: int = Field(512, gt=0, description="pushes, each on a fresh robot standing at the nominal pose")
    max_impulse: float = Field(
        12.0, ge=0, description="[N·s] the largest push; sizes grow evenly from 0 to this (0: the robot only stands)"
    )
    duration: float = Field(0.1, gt=0, le=1.0, description="[s] how long a push's constant horizontal force acts")
    body: str | None = Field(None, description="the body pushed, at its centre of mass; null = the robot's root body")
    settle: float = Field(0.5, ge=0, description="[s] standing before the push; the detector already watches")
    horizon: float = Field(2.0, gt=0, description="[s] from the push's start: a non-foot contact within it is a fall")
    after: float = Field(
        2.0, ge=0, description="[s] watched past the horizon only to report survivors that fall later (never a fall)"
    )
    seed: int = Field(0, description="seed of the push directions")
    sweep: tuple[float, float] = Field(
        (-0.06, 0.24), description="[m] range of detector.capture_margin swept for the ROC and lead-time plots"
    )
    sweep_points: int = Field(61, ge=2, le=1000, description="thresholds in the sweep, evenly spaced")

    @field_validator("sweep")
    @classmethod
    def _ordered(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not value[0] < value[1]:
            raise ValueError("need low < high")
        return value


class DetectorConfig(Section):
    """When a fall has begun: the capture point outside the feet's support polygon, or too much tilt.

    Every update the detector places the centre of mass (COM) and the soles of the feet relative to
    the base by forward kinematics of the joint angles, turns them upright with the IMU's orientation,
    and computes the capture point x_cp = x_com + v_com / ω0, ω0 = sqrt(g / z_com) (z_com above the
    lowest sole point). Its signed distance outside the support polygon (the convex hull of the sole
    points touching the ground) is the main signal, because it says that a fall is unavoidable
    without a step before the robot tilts far; a large tilt is a backstop for states the capture
    point misreads (both feet lifted, a slipping foot).
    """

    feet: list[str] | None = Field(
        None,
        description="bodies whose collision geoms are the soles that support the robot; null = the robot's "
        "disturbance_bodies['feet'] (biped20: left_foot, right_foot; go1: its four feet)",
    )
    capture_margin: float = Field(
        0.04,
        ge=-0.5,
        le=1.0,
        description="[m] THE threshold: a fall has begun when the capture point lies more than this outside the "
        "support polygon (negative: inside it); lower triggers earlier and more often (mode=detect sweeps it). "
        "0.04: the edge, exact in simulation, plus room for COM-model and velocity errors (docs/fall_detection.md)",
    )
    max_tilt: float = Field(
        0.7, gt=0, le=math.pi, description="[rad] a fall has begun when the base's up axis is tilted more than this"
    )
    confirm_steps: int = Field(
        1, ge=1, le=50, description="consecutive updates a condition must hold before it triggers (against noise)"
    )
    contact_height: float = Field(
        0.01, gt=0, le=0.2, description="[m] sole points within this height of the lowest one touch the ground"
    )
    pushes: PushTestConfig = Field(default_factory=PushTestConfig)

    @field_validator("feet")
    @classmethod
    def _some_feet(cls, value: list[str] | None) -> list[str] | None:
        if value is not None and (not value or len(set(value)) != len(value)):
            raise ValueError("name each foot body once, at least one")
        return value

    def exported(self) -> dict:
        """The settings the robot needs (policy.json's fall_detector), without the push test."""
        return self.model_dump(mode="json", exclude={"pushes", "feet"})
