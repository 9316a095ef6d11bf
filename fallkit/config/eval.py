"""`eval:` — evaluation of a policy against the standard fall strategies (mode=eval)."""

from __future__ import annotations

from pydantic import Field

from fallkit.config.section import Section


class EvalConfig(Section):
    """Evaluation of a policy (top-level `checkpoint`) and the standard fall strategies."""

    trials: int = Field(256, gt=0, description="falls per strategy (the paper: 32768)")
    seconds: float | None = Field(None, gt=0, description="length of each fall [s]; null = the env's episode length")
    seed: int = Field(12345, description="seed of the initial states and end-pose draws; never a training seed")
    poses: str | None = Field(
        None, description="end poses: null = the env's (training run's) source; 'default', a .npz dataset or a .yaml pose file"
    )
    split: str = Field("test", description="dataset split of the end poses (test = unseen in training)")
    seek_reference: bool = Field(
        True,
        description="also fall 'seek': setpoints blended open-loop from the starting joints to the target joints "
        "by u(t), nominal gains — a reference for what learning adds, not one of the paper's strategies",
    )
