"""Shared fixtures: real robots, real simulators."""

from __future__ import annotations

import os

import pytest
import torch

# Tests run on 2 cores beside MuJoCo's threads: keep torch from oversubscribing.
torch.set_num_threads(1)
os.environ.setdefault("MUJOCO_GL", "osmesa")

# Simulator backends the shared simulator tests run against. warp runs on Warp's CPU
# device here (a GPU when present); its kernels compile once into the kernel cache
# (~/.cache/fallkit/warp: 1-3 min cold on 2 busy cores, ~1-10 s to load warm).
SIM_BACKENDS = ["mujoco", "warp"]


@pytest.fixture(scope="session")
def biped():
    from fallkit.api import get_robot

    return get_robot("biped20")


@pytest.fixture(params=SIM_BACKENDS)
def backend(request) -> str:
    return request.param
