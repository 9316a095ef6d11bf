"""What a real user's mistakes, crashes and parallel runs do (issue 19): each test failed before its fix."""

from __future__ import annotations

import numpy as np

from fallkit.config import DatasetConfig
from fallkit.poses.generator import EndPoseGenerator


def test_a_small_dataset_is_made_with_the_default_pool(biped):
    """50 poses at 6 drops each is a budget of 300 < the 1024 worlds of the pool: the pool must
    shrink to the budget and let the drops land, not stop after the first step."""
    gen = EndPoseGenerator(biped, DatasetConfig(train=40, test=10)).run(progress=False)
    assert len(gen.joint_pos) == 50 and (gen.split == "test").sum() == 10
    assert gen.stats["drops"] <= 6 * 50
    assert np.isfinite(gen.joint_pos.numpy()).all()
