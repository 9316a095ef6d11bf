"""Exploration noise correlated in time (train.noise_correlation_time): each step's action is still
N(loc, scale) with its Gaussian log-probability, successive steps correlate by ρ, episodes restart it."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import TINY, composed_config
from torchrl.modules import IndependentNormal

from fallkit.rl.exploration import CorrelatedNoise


def test_the_noise_is_unit_gaussian_at_every_step_and_correlates_by_rho():
    torch.manual_seed(0)
    noise = CorrelatedNoise(20_000, 3, correlation_time=0.1, dt=0.02, device="cpu")
    never = torch.zeros(20_000, dtype=torch.bool)
    first = noise.step(never).clone()
    second = noise.step(never).clone()
    rho = math.exp(-0.02 / 0.1)
    for eps in (first, second):
        assert eps.mean().abs() < 0.02 and (eps.std() - 1.0).abs() < 0.02  # stationary: N(0, 1) throughout
    assert ((first * second).mean() - rho).abs() < 0.02


def test_a_fresh_episode_restarts_its_world_and_only_its_own():
    torch.manual_seed(0)
    noise = CorrelatedNoise(4000, 2, correlation_time=10.0, dt=0.02, device="cpu")  # ρ ≈ 0.998
    before = noise.eps.clone()
    fresh = torch.arange(4000) % 2 == 0
    after = noise.step(fresh)
    assert (after[~fresh] - before[~fresh]).abs().max() < 0.3  # the others carry on
    assert torch.corrcoef(torch.stack([after[fresh].flatten(), before[fresh].flatten()]))[0, 1].abs() < 0.05


def test_collected_actions_carry_their_gaussian_log_probability_and_correlate_in_time():
    from fallkit.env.build import make_env
    from fallkit.rl.models import joint_prior, make_actor
    from fallkit.rl.trainer import collect
    from fallkit.robots import robot_spec

    torch.manual_seed(0)
    config = composed_config(*TINY, "sim.num_envs=64", "env.episode_length=1.0")  # no episode ends in 12 steps
    spec = robot_spec(config.robot)
    env = make_env(config, spec, "train", seed=0)
    obs_dim, act_dim = env.observation_spec["policy"].shape[-1], env.action_spec.shape[-1]
    actor = make_actor(obs_dim, act_dim, [32], 0.3, joint_prior(config, spec))
    noise = CorrelatedNoise(env.num_envs, act_dim, correlation_time=0.2, dt=env.dt, device="cpu")
    batch, _ = collect(env, actor, env.reset(), 12, noise)
    loc, scale, action = batch["loc"], batch["scale"], batch["action"]
    torch.testing.assert_close(batch["action_log_prob"], IndependentNormal(loc, scale).log_prob(action))
    eps = (action - loc) / scale  # [N, T, A]
    lag1 = (eps[:, 1:] * eps[:, :-1]).mean()
    assert lag1 == pytest.approx(math.exp(-env.dt / 0.2), abs=0.1)


def test_zero_or_negative_correlation_time_is_refused():
    with pytest.raises(ValueError, match="correlation_time"):
        CorrelatedNoise(4, 2, correlation_time=0.0, dt=0.02, device="cpu")
