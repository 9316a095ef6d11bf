"""`dataset:` — the end-pose dataset generator of mode=poses (paper Sec. IV-C, V-B).

The section is called `dataset` so that "poses" means one thing: where end poses come
from (`env.poses`, `eval.poses`).
"""

from __future__ import annotations

from pydantic import Field

from fallkit.config.section import Section


class SettleConfig(Section):
    """The drop: height, frozen gains, and when a robot counts as at rest."""

    drop_height: float = Field(0.04, ge=0, description="[m] gap between the lowest geom and the floor at release")
    gain_scale: float = Field(10.0, gt=0, description="kp, kd × this while dropping (the 'freeze' strategy)")
    lin_vel: float = Field(0.02, gt=0, description="[m/s] root speed below which the robot may be at rest")
    ang_vel: float = Field(0.05, gt=0, description="[rad/s] root angular speed threshold")
    joint_vel: float = Field(0.1, gt=0, description="[rad/s] largest joint speed threshold")
    rest_time: float = Field(0.1, gt=0, description="[s] all thresholds held this long = at rest")
    max_time: float = Field(3.0, gt=0, description="[s] drops not at rest by then are discarded (counted)")


class DatasetConfig(Section):
    """`mode=poses`: the end-pose dataset of the chosen robot (paper Sec. IV-C, V-B)."""

    out: str | None = Field(None, description="dataset file; default <run dir>/<robot>_poses.npz")
    train: int = Field(24000, ge=1, description="training poses (paper: 24k)")
    test: int = Field(2000, ge=0, description="test poses (paper: 2k)")
    seed: int = 0
    num_worlds: int = Field(1024, ge=1, description="drops simulated in parallel")
    settle: SettleConfig = Field(default_factory=SettleConfig)
    bands: int = Field(6, ge=1, description="orientation bins: equal-area bands along the root z axis")
    sectors: int = Field(8, ge=1, description="orientation bins: sectors around the root z axis")
    tolerance: float = Field(
        0.1,
        ge=0,
        lt=1,
        description="uniform within: the smallest covered side holds >= (1 - tolerance) × the largest, and "
        "within each covered side so does every covered bin part per area",
    )
    side_min_share: float = Field(
        0.25,
        ge=0,
        le=1,
        description="sides (the root axis nearest to straight down) settled onto less often than this fraction "
        "of a uniform share (1/6) are 'rare': left out of the uniformity test; the others hold equal shares",
    )
    min_share: float = Field(
        0.5,
        ge=0,
        le=1,
        description="side parts of bins settled into less often than this fraction of a uniform share (by area) "
        "are 'rare': left out of the uniformity test (thinned only above their side's level)",
    )
    max_drops: float = Field(6.0, gt=1, description="give up rebalancing after this many drops per pose")
    targeted: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="share of the drops started with an orientation inside a covered cell still short of poses "
        "(0: every drop uniform, as the paper samples them; the rarity of a bin is judged on the uniform drops)",
    )
    abort_steps: int = Field(
        2, ge=0, description="policy steps a drop may lie slowly in an over-full bin before it is stopped (0 = never)"
    )
    abort_lin_vel: float = Field(1.0, gt=0, description="[m/s] 'slowly' for the early stop")
    abort_ang_vel: float = Field(3.0, gt=0, description="[rad/s] 'slowly' for the early stop")
    artist: str | None = Field(
        "artist", description="artist poses for the contact sheet: a pose file, 'artist' (the robot's own) or null"
    )
    sheet: int = Field(30, ge=0, description="generated poses drawn on the contact sheet")
