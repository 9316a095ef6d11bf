"""`eval:` — evaluation of a policy against the standard fall strategies (mode=eval)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from fallkit.config.section import Section
from fallkit.pose_choice import PIVOT_HEIGHT, SIDES


class EvalConfig(Section):
    """Evaluation of a policy (top-level `checkpoint`) and the standard fall strategies."""

    trials: int = Field(256, gt=0, description="falls per strategy (the paper: 32768)")
    seconds: float | None = Field(None, gt=0, description="length of each fall [s]; null = the env's episode length")
    seed: int = Field(12345, description="seed of the initial states and end-pose draws; never a training seed")
    poses: str | None = Field(
        None,
        description="end poses: null = the env's (training run's) source; 'default', 'artist', a .npz dataset or a "
        ".yaml pose file; 'auto' = each fall's end pose chosen from eval.candidates by eval.scorer when the fall "
        "begins, reported against random assignment on the same falls (docs/end_pose_choice.md)",
    )
    split: str = Field("test", description="dataset split of the end poses (test = unseen in training)")
    seek_reference: bool = Field(
        True,
        description="also fall 'seek': setpoints blended open-loop from the starting joints to the target joints "
        "by u(t), nominal gains — a reference for what learning adds, not one of the paper's strategies",
    )
    # ---- eval.poses=auto (docs/end_pose_choice.md) ----
    candidates: str | None = Field(
        None,
        description="eval.poses=auto: the end poses to choose from; null = the env's (training run's) source; "
        "'default', 'artist', a .npz dataset (its eval.split) or a .yaml pose file",
    )
    candidate_side: list[str] | None = Field(
        None,
        description=f"eval.poses=auto: only candidates lying on this side (or these sides): {', '.join(SIDES)}; "
        "a pose lies on the side whose axis is nearest to straight down; null = every candidate",
    )
    scorer: Literal["critic", "heading"] = Field(
        "critic",
        description="eval.poses=auto: 'critic' = the candidate of the highest value V(s, g) of the checkpoint's "
        "critic at the fall's first state (privileged: simulation only); 'heading' = the candidate lying closest "
        "to where the fall is heading, its capture point (what a robot measures; the deployed controller's choice)",
    )
    heading_pivot_height: float = Field(
        PIVOT_HEIGHT,
        gt=0,
        description="scorer=heading: [m] height of the inverted pendulum (base above feet) whose capture point, "
        "lean + v / sqrt(g / height), says where the fall is heading",
    )

    @field_validator("candidate_side", mode="before")
    @classmethod
    def _one_or_more_sides(cls, v: object) -> object:
        """`eval.candidate_side=back` or `eval.candidate_side=[back,left]`; every word checked."""
        sides = [v] if isinstance(v, str) else v
        if isinstance(sides, list):
            unknown = [s for s in sides if s not in SIDES]
            if unknown:
                raise ValueError(f"unknown side {unknown[0]!r}; sides are {', '.join(SIDES)}")
            if not sides:
                raise ValueError("name at least one side, or null for every candidate")
        return sides

    @model_validator(mode="after")
    def _candidates_need_auto(self) -> "EvalConfig":
        if self.poses != "auto":
            for key in ("candidates", "candidate_side"):
                if getattr(self, key) is not None:
                    raise ValueError(f"{key} applies to poses=auto only (poses is {self.poses}): add eval.poses=auto")
        if self.candidates == "auto":
            raise ValueError(
                "candidates: name the poses to choose from ('default', 'artist', a .npz or .yaml), not 'auto'"
            )
        return self
