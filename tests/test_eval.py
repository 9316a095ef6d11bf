"""Paired evaluation: the same falls for every strategy, the strategies' gains, chunking, eval.json."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from helpers import fallkit_cli
from tensordict.nn import TensorDictModule
from torch import nn

from fallkit.config import ConfigError, FallkitConfig
from fallkit.env.fall_env import FallEnv
from fallkit.eval import evaluate as ev
from fallkit.eval.rollout import gain_scales
from fallkit.eval.strategies import STRATEGIES
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.sim import make_sim

STEPS = 10  # 0.2 s falls: enough for the strategies to diverge, cheap on 2 cores
SEED = 777


def make_env(spec, worlds: int) -> FallEnv:
    """An evaluation env with mode=eval's settings (eval_run_config), short falls, random end poses."""
    cfg = ev.eval_run_config(FallkitConfig(robot={"name": spec.name}), STEPS * spec.policy_dt)
    poses = random_end_poses(spec, 7, torch.Generator().manual_seed(0))
    sim = make_sim(spec, worlds, body_state=True)
    return FallEnv(spec, cfg.env, cfg.reward, poses, sim, seed=1)


class HoldNominal(nn.Module):
    """A policy that always asks for the nominal pose (action 0), and checks its batch."""

    def __init__(self, expected_batch: int, joints: int):
        super().__init__()
        self.expected_batch, self.joints = expected_batch, joints

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        assert obs.shape[0] == self.expected_batch  # only the policy's own worlds are run through it
        return torch.zeros(obs.shape[0], self.joints)


def _gains(env: FallEnv, world: int) -> tuple[np.ndarray, np.ndarray]:
    m = env.sim.batch.get_model(world)  # the world's model, with its per-world actuator parameters
    return m.actuator_gainprm[:, 0].copy(), -m.actuator_biasprm[:, 2].copy()


def test_strategies_fall_from_the_same_states_with_scaled_gains(biped):
    k = 3
    names = list(STRATEGIES)
    env = make_env(biped, len(names) * k)
    trials = ev.draw_trials(env, k, SEED)
    out = ev.rollout(env, trials, names, record_states=True)

    # pairing: every strategy block starts from the same states toward the same end poses
    q0 = out.qpos[0].view(len(names), k, -1)
    v0 = out.qvel[0].view(len(names), k, -1)
    for i in range(1, len(names)):
        assert torch.equal(q0[i], q0[0]) and torch.equal(v0[i], v0[0])
        a, b = out.traces[names[0]], out.traces[names[i]]
        assert torch.equal(a.target_joint_pos, b.target_joint_pos) and torch.equal(a.target_root_quat, b.target_root_quat)
    assert torch.allclose(q0[0].double(), trials.qpos.float().double())

    # gain scaling: kp and kd of every actuator × 0, 0.1, 10 in each block
    kp = np.array([j.kp for j in biped.joints])
    kd = np.array([j.kd for j in biped.joints])
    for i, name in enumerate(names):
        for w in (i * k, i * k + k - 1):
            got_kp, got_kd = _gains(env, w)
            assert got_kp == pytest.approx(STRATEGIES[name] * kp) and got_kd == pytest.approx(STRATEGIES[name] * kd)
    assert torch.count_nonzero(out.joint_torque[:, :k]) == 0  # zero torque is exactly zero

    # every strategy holds the setpoint the fall began with
    start = out.qpos[0][:, env.sim.layout.joint_qpos]
    assert torch.allclose(out.setpoint[1:], start.expand_as(out.setpoint[1:]), atol=1e-5)
    # and the gains matter: the strategies' falls diverge
    final = out.qpos[-1].view(len(names), k, -1)
    assert not torch.allclose(final[0], final[2], atol=1e-3)


def test_policy_block_acts_with_nominal_gains(biped):
    k = 2
    names = ev.EvalSetup(None, object(), None, "", "").strategies
    assert names == ["policy", *STRATEGIES]
    env = make_env(biped, len(names) * k)
    policy = TensorDictModule(HoldNominal(k, len(biped.joints)), in_keys=["policy"], out_keys=["action"])
    trials = ev.draw_trials(env, k, SEED)
    out = ev.rollout(env, trials, names, policy, steps=3, record_states=True)
    nominal = env.setpoint(torch.zeros(1, len(biped.joints)))
    assert torch.allclose(out.setpoint[1:, :k], nominal.expand(3, k, -1))
    kp = np.array([j.kp for j in biped.joints])
    assert _gains(env, 0)[0] == pytest.approx(kp)
    assert set(out.traces) == set(names)
    with pytest.raises(ValueError, match="needs a policy"):
        ev.rollout(env, trials, names, None)


def test_chunked_evaluation_equals_one_batch_and_json_schema(biped, tmp_path):
    names = list(STRATEGIES)
    n = 5
    big = make_env(biped, len(names) * n)
    trials = ev.draw_trials(big, n, SEED)
    whole = ev.evaluate(big, trials, names, show_progress=False)
    k, chunks = ev.chunking(n, len(names), 6)  # 2 trials per chunk, the last one padded
    assert (k, chunks) == (2, 3)
    small = make_env(biped, len(names) * k)
    chunked = ev.evaluate(small, trials, names, show_progress=False)
    for name in names:
        assert len(chunked[name]) == n
        for key, value in whole[name].arrays().items():
            np.testing.assert_allclose(getattr(chunked[name], key), value, rtol=1e-5, atol=1e-4, err_msg=f"{name}.{key}")

    info = {"robot": biped.name, "checkpoint": None, "trials": n, "seconds": 0.2, "seed": SEED, "poses": "random", "elapsed": 1.0}
    ev.write_results(whole, biped.component_names, info, tmp_path)
    data = json.loads((tmp_path / "eval.json").read_text())
    assert list(data) == names
    stats = {"mean", "std", "median", "p95"}
    for name in names:
        s = data[name]
        for metric in ("max_impact_force", "mean_impact_force", "fall_mean_impact_force", "mroe", "mje"):
            assert set(s[metric]) == stats and all(np.isfinite(list(s[metric].values())))
        assert s["trials"] == n and s["gain_scale"] == STRATEGIES[name]
        assert list(s["per_component"]) == biped.component_names
        for comp in s["per_component"].values():
            assert set(comp) == {"max_impact_force", "mean_impact_force", "fall_mean_impact_force"}
            assert set(comp["max_impact_force"]) == stats
        assert s["max_impact_force"]["mean"] > 100.0  # 0.2 s after the drop every robot has touched down
    md = (tmp_path / "eval.md").read_text()
    assert all(name in md for name in names) and "MROE" in md
    # each component's fall-phase mean, the figures whose largest per fall is the fall-phase mean
    fall_table = md.split("## Per component: fall-phase mean impact force")[1].split("##")[0]
    for name in names:
        per_component = data[name]["per_component"]
        cells = [f"{per_component[c]['fall_mean_impact_force']['mean']:.1f}" for c in biped.component_names]
        assert f"| {name} | " + " | ".join(cells) + " |" in fall_table
    for png in ("impact_boxplot.png", "component_impact.png", "tracking_boxplot.png"):
        assert (tmp_path / png).stat().st_size > 10_000
    arrays = np.load(tmp_path / "eval_trials.npz")
    assert arrays["freeze/max_impact_force"].shape == (n,)
    # a strategy none of whose falls stayed stable (a diverged policy's NaN actions) is left out of the plots
    whole[names[0]].unstable[:] = True
    (tmp_path / "all_unstable").mkdir()
    ev.write_results(whole, biped.component_names, info, tmp_path / "all_unstable")
    assert json.loads((tmp_path / "all_unstable" / "eval.json").read_text())[names[0]]["unstable_trials"] == n
    assert (tmp_path / "all_unstable" / "component_impact.png").is_file()


def test_trials_are_reproducible_and_use_every_pose(biped):
    env = make_env(biped, 3)
    a, b = ev.draw_trials(env, 14, SEED), ev.draw_trials(env, 14, SEED)
    assert torch.equal(a.qpos, b.qpos) and torch.equal(a.pose_ids, b.pose_ids)
    assert not torch.equal(ev.draw_trials(env, 14, SEED + 1).qpos, a.qpos)
    assert torch.bincount(a.pose_ids, minlength=7).tolist() == [2] * 7  # 7 poses, each twice


@pytest.mark.parametrize("trials,strategies,num_envs", [(1000, 4, 256), (1024, 4, 4096), (5, 3, 2), (32768, 4, 1024)])
def test_chunking_fits_the_worlds_with_little_padding(trials, strategies, num_envs):
    k, chunks = ev.chunking(trials, strategies, num_envs)
    assert strategies * k <= max(num_envs, strategies)
    assert k * chunks >= trials and k * chunks - trials < chunks


def test_cli_evaluates_a_trained_policy_against_the_strategies(tmp_path):
    """mode=eval end to end: a (tiny, briefly trained) checkpoint, artist end poses, eval.json with four strategies."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    from fallkit.app import register_configs
    from fallkit.config import validate
    from fallkit.rl.trainer import Trainer

    tiny = [
        "train=quick", "train.iterations=1", "train.num_steps=4", "train.actor_hidden=[16,16]",
        "train.critic_hidden=[16,16]", "train.evaluate=false", "sim.num_envs=8", "sim.threads=1",
        "env.poses=artist", "env.episode_length=0.3", "reward.blend_time=0.2",
    ]  # fmt: skip
    GlobalHydra.instance().clear()
    register_configs()
    with initialize_config_module(config_module="fallkit.conf", version_base="1.3"):
        raw = OmegaConf.to_container(compose(config_name="config", overrides=tiny), resolve=False)
    raw.pop("hydra", None)
    trained = validate(raw)
    Trainer(trained, tmp_path / "train").run()

    r = fallkit_cli(f"checkpoint={tmp_path / 'train'}", "mode=eval", "eval.trials=3", "sim.num_envs=8", "hydra.run.dir=eval", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert list(data) == ["policy", *STRATEGIES, "seek"]
    assert all(data[s]["trials"] == 3 and data[s]["max_impact_force"]["p95"] > 0 for s in data)
    assert "policy" in (tmp_path / "eval" / "eval.md").read_text()
    # the training run's seed is refused: its initial states were seen in training
    same_seed = trained.model_copy(update={"checkpoint": str(tmp_path / "train"), "eval": trained.eval.model_copy(update={"seed": trained.seed})})
    with pytest.raises(ConfigError, match="eval.seed"):
        ev.prepare(same_seed)


def test_seek_reference_blends_from_the_start_joints_to_the_target(biped):
    """'seek': nominal gains, setpoints lerp(start joints, target joints, u(t)) — open loop, no policy."""
    k = 2
    names = ["damping", ev.SEEK]
    env = make_env(biped, len(names) * k)
    trials = ev.draw_trials(env, k, SEED)
    out = ev.rollout(env, trials, names, record_states=True)
    seek = slice(k, 2 * k)
    start = out.qpos[0, seek][:, env.sim.layout.joint_qpos].float()
    target = env.end_poses.joint_pos[trials.pose_ids].float()
    t = torch.arange(1, STEPS + 1) * env.dt - env.dt  # each step's action is taken at the step's start
    u = (t / env.reward_cfg.blend_time).clamp(0, 1)
    u = u * u * (3 - 2 * u)
    want = start[None] + u[:, None, None] * (target - start)[None]
    low, high = torch.as_tensor(biped.joint_limits, dtype=torch.float32).unbind(-1)
    torch.testing.assert_close(out.setpoint[1:, seek], want.clamp(low, high), atol=1e-5, rtol=0)
    assert gain_scales(names) == [STRATEGIES["damping"], 1.0]
    assert ev.EvalSetup(None, None, None, "", "", seek_reference=True).compared == [*STRATEGIES, ev.SEEK]


def test_ratios_are_over_the_best_standard_strategy():
    from fallkit.eval.report import ratio_line, ratios

    def row(impact, mje):
        stat = lambda v: {"mean": v}  # noqa: E731
        return {"max_impact_force": stat(impact), "fall_mean_impact_force": stat(impact / 10), "mroe": stat(1.0),
                "mje": stat(mje)}  # fmt: skip

    summary = {"policy": row(900, 0.1), "zero_torque": row(1000, 0.8), "damping": row(1200, 0.5), "freeze": row(2000, 0.9)}
    r = ratios(summary)
    assert r["max_impact_ratio"] == pytest.approx(0.9) and r["mje_ratio"] == pytest.approx(0.2)
    assert r["mroe_ratio"] == pytest.approx(1.0) and r["fall_mean_impact_ratio"] == pytest.approx(0.9)
    assert ratio_line(summary) == (
        "policy / best standard strategy: max impact 0.90x, fall-phase mean impact 0.90x, MROE 1.00x, MJE 0.20x "
        "(lower is better)"
    )
    summary["zero_torque"] = row(float("nan"), float("nan"))  # every trial unstable: no mean, not the best
    assert ratios(summary)["max_impact_ratio"] == pytest.approx(900 / 1200)


def test_report_cli_prints_the_ratio_lines_or_one_clear_error(tmp_path):
    stat = {"mean": 1.0}
    row = {m: stat for m in ("max_impact_force", "fall_mean_impact_force", "mroe", "mje")}
    (tmp_path / "eval.json").write_text(json.dumps({"policy": row, **{s: row for s in STRATEGIES}, "seek": row}))
    cmd = [sys.executable, "-m", "fallkit.eval.report"]
    ok = subprocess.run([*cmd, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and ok.stdout.splitlines() == [
        "policy / best standard strategy: max impact 1.00x, fall-phase mean impact 1.00x, MROE 1.00x, MJE 1.00x "
        "(lower is better)",
        "seek / best standard strategy: max impact 1.00x, fall-phase mean impact 1.00x, MROE 1.00x, MJE 1.00x "
        "(lower is better)",
    ]
    missing = subprocess.run([*cmd, str(tmp_path / "nosuch")], capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1 and "no eval.json here" in missing.stderr


def test_learning_curve_smoothing_keeps_the_ends(tmp_path):
    """The learning curve's moving average must not bend toward 0 at the ends (zero padding did): a
    run's last iterations are what a reader looks at. Gaps are filled, the mean of a ramp is kept."""
    from fallkit.eval.plots import learning_curve, moving_average

    assert np.allclose(moving_average(np.full(40, -0.25), 5), -0.25)
    ramp = np.arange(40.0)
    smooth = moving_average(ramp, 5)
    assert np.allclose(smooth[2:-2], ramp[2:-2]) and smooth[-1] == pytest.approx(38.0)  # mean of 37, 38, 39
    gap = ramp.copy()
    gap[10] = np.nan
    assert np.allclose(moving_average(gap, 1), ramp)
    rows = ["iteration,reward,episode/max_impact_force,reward_terms/impact"]
    rows += [f"{i},{-1 + i / 100},{1500 - i},{-0.5}" for i in range(60)]
    csv = tmp_path / "metrics.csv"
    csv.write_text("\n".join(rows) + "\n")
    assert learning_curve(csv, tmp_path / "curve.png").stat().st_size > 0
