"""Training end to end at tiny sizes: determinism, resume, signals, sweeps, torchrun."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from helpers import TINY, composed_config, fallkit_cli, host_reads

from fallkit.rl.checkpoint import load_checkpoint


def tiny_config(*overrides: str):
    return composed_config(*TINY, *overrides)


def train(run_dir: Path, *overrides: str) -> Path:
    from fallkit.rl.trainer import Trainer

    return Trainer(tiny_config(*overrides), run_dir).run()


def actor_of(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["actor"]


def assert_same_weights(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), f"{k} differs"


def test_same_seed_same_iterations_bit_for_bit(tmp_path):
    a = train(tmp_path / "a", "train.iterations=2", "seed=3")
    b = train(tmp_path / "b", "train.iterations=2", "seed=3")
    assert_same_weights(actor_of(a), actor_of(b))
    c = train(tmp_path / "c", "train.iterations=2", "seed=4")
    assert any(not torch.equal(actor_of(a)[k], actor_of(c)[k]) for k in actor_of(a))  # the seed matters


REPLAY = ["train.level_replay.share=0.5", "train.level_replay.size=4"]
SELF_IMITATION = ["train.early_reward_factor=null", "train.self_imitation.steps=4", "train.self_imitation.size=64", "train.self_imitation.minibatch=4"]
# the orientation weight x5 for iterations 0-1 (32 env steps each), x3 for 2, x1 from 3: the checkpoint at
# iteration 2 lies inside the fade
EARLY_FACTOR = ["++train.early_reward_factor.orientation=5", "train.early_until_env_steps=32",
                "train.early_fade_env_steps=64"]  # fmt: skip
# a schedule of 64 + 256 env steps in a 4-iteration run: its position is the budget's share (80 when iteration 2 is
# saved, 160 at the next), which the checkpoint keeps; the env steps (64) would put it back at x5
EARLY_IN_BUDGET = ["++train.early_reward_factor.orientation=5", "train.early_until_env_steps=64",
                   "train.early_fade_env_steps=256", "train.early_within_budget=true"]  # fmt: skip


@pytest.mark.parametrize(
    "noise",
    [[], ["train.noise_correlation_time=0.1"], REPLAY, SELF_IMITATION, EARLY_FACTOR, EARLY_IN_BUDGET],
    ids=["white", "correlated", "level-replay", "self-imitation", "early-reward-factor", "early-within-budget"],
)
def test_resume_continues_exactly(tmp_path, noise):
    straight = train(tmp_path / "straight", "train.iterations=4", "train.checkpoint_every=2", *noise)
    assert (tmp_path / "straight" / "checkpoints" / "iter_000002.pt").is_file()
    assert (tmp_path / "straight" / "metrics.csv").read_text().count("\n") == 5  # header + 4 iterations
    half = tmp_path / "half"
    (half / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "straight" / "checkpoints" / "iter_000002.pt", half / "checkpoints" / "last.pt")
    resumed = train(tmp_path / "resumed", "train.iterations=4", f"resume={half}", *noise)
    assert load_checkpoint(resumed)["iteration"] == 4
    assert_same_weights(actor_of(straight), actor_of(resumed))
    assert_same_weights(load_checkpoint(straight)["critic"], load_checkpoint(resumed)["critic"])
    if noise == REPLAY:  # stored falls were replayed, and the figures say so
        last = (tmp_path / "straight" / "metrics.csv").read_text().splitlines()
        row = dict(zip(last[0].split(","), last[-1].split(",")))
        assert float(row["level_replay/stored"]) == 4 and float(row["level_replay/replayed"]) > 0
    if noise == SELF_IMITATION:  # the store filled with finished falls' steps and the actor learned from it
        last = (tmp_path / "straight" / "metrics.csv").read_text().splitlines()
        row = dict(zip(last[0].split(","), last[-1].split(",")))
        # it learns once a minibatch (4) is stored; how many steps beat a fresh critic is up to the draws
        assert float(row["self_imitation/stored"]) >= 4 and float(row["self_imitation/loss"]) != 0


def test_normalized_values_train_log_their_statistics_and_load_with_the_policy(tmp_path):
    from fallkit.rl.policy import load_policy

    run = train(tmp_path / "run", "train.iterations=2", "train.ppo.normalize_value=true", "train.ppo.value_per_term=false")
    critic = load_checkpoint(run)["critic"]
    assert critic["module.target.count"] > 0 and critic["module.target.mean"] < 0  # returns are penalties
    header = (tmp_path / "run" / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {"value_target_mean", "value_target_std", "actor_grad_norm", "critic_grad_norm"} <= set(header)
    loaded = load_policy(run)
    assert torch.equal(loaded.critic.target.mean, critic["module.target.mean"])


def test_a_critic_with_layer_norm_trains_resumes_and_loads_with_the_policy(tmp_path):
    """train.critic_layer_norm: each hidden layer of the critic is Linear, LayerNorm, ELU; the actor is untouched;
    the checkpoint's critic loads with the policy (eval.poses=auto reads it) and predicts what it did in training."""
    from fallkit.rl.models import value_net
    from fallkit.rl.policy import load_policy
    from fallkit.rl.trainer import Trainer

    # Table I's weights: a critic saved inside train=quick's reward schedule loads rescaled to them (test_reward_schedule)
    trainer = Trainer(tiny_config("train.iterations=2", "train.critic_layer_norm=true", "train.early_reward_factor=null"),
                      tmp_path / "run")
    layers = value_net(trainer.critic).value
    hidden = trainer.config.train.critic_hidden
    assert [type(m).__name__ for m in layers] == ["Linear", "LayerNorm", "ELU"] * len(hidden) + ["Linear"]
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in trainer.actor.modules())
    last = trainer.run()
    loaded = load_policy(last).critic
    net = value_net(trainer.critic)
    net.precision = "float32"  # as loaded policies compute
    obs = torch.randn(3, net.norm.mean.shape[0])
    with torch.no_grad():
        torch.testing.assert_close(loaded(obs), net(obs))
    resumed = train(tmp_path / "resumed", "train.iterations=3", "train.critic_layer_norm=true", f"resume={last}")
    assert load_checkpoint(resumed)["iteration"] == 3


def test_resume_from_corrupt_checkpoint_is_a_clear_error(tmp_path):
    from fallkit.rl.checkpoint import CheckpointError

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00" * 100)
    with pytest.raises(CheckpointError, match="bad.pt is corrupt or truncated"):
        train(tmp_path / "run", f"resume={bad}")


def test_sigterm_saves_and_stops(tmp_path):
    """A run asked to stop (SIGTERM) finishes its iteration and leaves a usable checkpoint."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "fallkit", *TINY, "train.iterations=100000", "hydra.run.dir=run"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    csv = tmp_path / "run" / "metrics.csv"
    deadline = time.time() + 120
    while time.time() < deadline and not (csv.exists() and csv.read_text().count("\n") >= 3):
        time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    ckpt = load_checkpoint(tmp_path / "run")
    assert ckpt["iteration"] >= 2
    assert "stopping on SIGTERM" in out


def test_multirun_gives_each_run_its_own_directory(tmp_path):
    r = fallkit_cli("-m", *TINY, "train.iterations=1", "seed=0,1", "hydra.sweep.dir=sweep", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    runs = sorted(p for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert len(runs) == 2
    for run in runs:
        assert (run / "checkpoints" / "last.pt").is_file() and (run / "resolved_config.yaml").is_file()


def test_torchrun_two_ranks_on_gloo(tmp_path):
    torchrun = Path(sys.executable).with_name("torchrun")
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    r = subprocess.run(
        [str(torchrun), "--standalone", "--nproc_per_node=2", "-m", "fallkit", *TINY, "train.iterations=2",
         "train.ppo.normalize_value=true",  # its target statistics are merged over the ranks too
         "hydra.run.dir=run"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    assert load_checkpoint(tmp_path / "run")["iteration"] == 2
    assert "weights identical on 2 ranks" in r.stdout + r.stderr


_AGREE = """
import json, sys
import torch.distributed as dist
from fallkit.rl.ranks import any_over_ranks
dist.init_process_group("gloo")
rank = dist.get_rank()
# rank 1 alone ran out of time, rank 0 alone diverged; nobody was signalled. A file per rank: two ranks
# printing to the one stdout torchrun forwards can interleave their lines ('{...}{...}' was seen in CI)
with open(f"rank{rank}.json", "w") as f:
    json.dump({"rank": rank, "agreed": any_over_ranks((False, rank == 1, rank == 0))}, f)
dist.destroy_process_group()
"""


def test_ranks_stop_together_whichever_rank_decided(tmp_path):
    """A time budget, a signal or a NaN seen by one rank stops every rank at the same iteration: a rank
    that stopped alone would leave the others waiting forever in the next all-reduce."""
    script = tmp_path / "agree.py"
    script.write_text(_AGREE)
    torchrun = Path(sys.executable).with_name("torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(
        [str(torchrun), "--standalone", "--nproc_per_node=2", str(script)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    lines = [json.loads(p.read_text()) for p in sorted(tmp_path.glob("rank*.json"))]
    assert sorted(d["rank"] for d in lines) == [0, 1]
    assert all(d["agreed"] == [False, True, True] for d in lines)


@pytest.mark.slow
def test_training_on_the_warp_backend(tmp_path):
    """The same training code on mujoco_warp (Warp's CPU device here; a GPU in real use)."""
    last = train(tmp_path / "warp", "sim=warp", "sim.device=cpu", "sim.num_envs=8", "train.iterations=2")
    ckpt = load_checkpoint(last)
    assert ckpt["iteration"] == 2 and ckpt["config"]["sim"]["backend"] == "warp"
    assert all(torch.isfinite(v).all() for v in ckpt["actor"].values() if v.is_floating_point())


def test_export_onnx_reproduces_the_policy(tmp_path):
    train(tmp_path / "run", "train.iterations=1")
    out = tmp_path / "export"
    out.mkdir()
    _exported_policy_matches_the_loaded_one(tmp_path / "run", out)


def _exported_policy_matches_the_loaded_one(run: Path, out: Path) -> None:
    import json

    import numpy as np
    import onnxruntime

    from fallkit.rl.export import run_export
    from fallkit.rl.policy import load_policy

    onnx_path = run_export(tiny_config(f"checkpoint={run}", "mode=export"), out)
    meta = json.loads((out / "policy.json").read_text())
    policy = load_policy(run)
    assert policy.module.module.net.precision == policy.critic.precision == "float32"
    assert meta["joint_names"] == policy.spec.joint_names and meta["policy_hz"] == 50.0
    assert sum(part["size"] for part in meta["observation_layout"]) == meta["observation_size"]
    obs = torch.randn(4, meta["observation_size"])
    want = policy.module.module(obs).detach().numpy()
    got = onnxruntime.InferenceSession(str(onnx_path)).run(["action"], {"observation": obs.numpy()})[0]
    np.testing.assert_allclose(got, want, atol=1e-4)


def test_a_bfloat16_run_is_evaluated_and_exported_in_float32(tmp_path):
    """train.precision=bfloat16 trains; the checkpoint says so; the loaded policy and critic compute in
    float32, so evaluation and the ONNX export are the same function of the same weights."""
    import json

    run = train(tmp_path / "run", "train.iterations=2", "train.precision=bfloat16")
    assert load_checkpoint(run)["config"]["train"]["precision"] == "bfloat16"
    out = tmp_path / "export"
    out.mkdir()
    _exported_policy_matches_the_loaded_one(tmp_path / "run", out)
    assert json.loads((out / "policy.json").read_text())["trained_precision"] == "bfloat16"


def test_the_kl_that_sets_the_learning_rate_is_the_exact_kl_of_the_current_policy(tmp_path, monkeypatch):
    """The KL that adapts the learning rate is the exact KL between the collecting policy and the policy
    about to step: 0 before the first step, and after one step the KL of the stepped policy (read from
    the loss's own forward pass, `_ActorOutputs`, not a second one)."""
    import copy

    from fallkit.rl import optimizer as optimizer_module
    from fallkit.rl import ppo as ppo_module
    from fallkit.rl.models import policy_net
    from fallkit.rl.trainer import Trainer

    cfg = tiny_config("train.ppo.num_minibatches=1", "train.ppo.epochs=2")
    trainer = Trainer(cfg, tmp_path / "run")
    trainer.td = trainer.env.reset()
    batch = trainer.collect()
    seen: list[float] = []
    real = optimizer_module.adapt_learning_rate
    monkeypatch.setattr(optimizer_module, "adapt_learning_rate", lambda lr, kl, c: seen.append(kl.item()) or real(lr, kl, c))
    actor, critic = copy.deepcopy(trainer.actor), copy.deepcopy(trainer.critic)
    trainer.ppo.update(batch.clone(), generator=torch.Generator().manual_seed(0))
    assert seen[0] == 0.0 and seen[1] > 0.0
    one_step = ppo_module.PPO(actor, critic, cfg.train.ppo.model_copy(update={"epochs": 1}), rewards=trainer.env.rewards)
    one_step.update(batch.clone(), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        loc, scale = policy_net(actor)(batch["policy"].reshape(-1, batch["policy"].shape[-1]))
        kl = ppo_module.gaussian_kl(batch["loc"].reshape(loc.shape), batch["scale"].reshape(loc.shape), loc, scale)
    assert seen[1] == pytest.approx(kl.item(), rel=1e-4)


def test_the_prior_penalty_pulls_the_learned_deviation_toward_the_prior(tmp_path):
    """train.ppo.prior_coef adds β·Σ_j d_j² of the learned deviation d = mean − prior to the loss: from the same
    weights and batch, an update with it leaves a smaller deviation than one without, and `prior_deviation`
    logs that sum (mean over the update's minibatches); without a prior it is a one-line error of the config."""
    import copy

    from fallkit.errors import ConfigError
    from fallkit.rl import ppo as ppo_module
    from fallkit.rl.models import policy_net
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(tiny_config(), tmp_path / "run")
    trainer.td = trainer.env.reset()
    batch = trainer.collect()
    with torch.no_grad():
        policy_net(trainer.actor).mean[-1].bias.fill_(0.5)  # a deviation to pull back: 0.5 per joint early on
    obs = batch["policy"].reshape(-1, batch["policy"].shape[-1])
    left, logged = [], []
    for coef in (0.0, 1.0):
        actor, critic = copy.deepcopy(trainer.actor), copy.deepcopy(trainer.critic)
        cfg = trainer.config.train.ppo.model_copy(update={"prior_coef": coef, "desired_kl": None, "kl_stop": None, "learning_rate": 0.01, "epochs": 25})
        stats = ppo_module.PPO(actor, critic, cfg, rewards=trainer.env.rewards).update(
            batch.clone(), generator=torch.Generator().manual_seed(0)
        )
        with torch.no_grad():
            left.append(policy_net(actor).deviation(obs).square().sum(-1).mean().item())
        logged.append(stats["prior_deviation"].item())
    assert left[1] < 0.5 * left[0]
    assert logged[1] > left[1] > 0.0  # logged before each step, while the penalty shrinks it
    with pytest.raises(ConfigError, match="train.prior=none leaves no prior for train.ppo.prior_coef"):
        tiny_config("train.prior=none", "train.fade_residual=false", "train.ppo.prior_coef=0.1")


@pytest.mark.parametrize("per_network", [False, True])
def test_gradients_are_clipped_over_both_networks_or_each_by_its_own_norm(tmp_path, per_network):
    """max_grad_norm bounds the norm over both networks (the paper's, rsl_rl's), so each network gets a fraction
    of the bound, set by the other's gradient (in training runs the critic's is 10-200x the actor's); with
    train.ppo.clip_per_network each network's own norm is bounded. Read at every optimizer step, after the clip."""
    from fallkit.rl import ppo as ppo_module
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(tiny_config(), tmp_path / "run")
    trainer.td = trainer.env.reset()
    batch = trainer.collect()
    cfg = trainer.config.train.ppo.model_copy(update={"max_grad_norm": 1e-3, "clip_per_network": per_network})
    ppo = ppo_module.PPO(trainer.actor, trainer.critic, cfg, rewards=trainer.env.rewards)
    norms = []

    def record(optimizer, args, kwargs):
        norms.append([torch.nn.utils.get_total_norm([p.grad for p in g["params"]]).item() for g in optimizer.param_groups])

    ppo.optimizer.optimizer.register_step_pre_hook(record)
    ppo.update(batch.clone(), generator=torch.Generator().manual_seed(0))
    actor, critic = torch.tensor(norms).T
    assert len(norms) == cfg.epochs * cfg.num_minibatches
    if per_network:
        assert torch.allclose(actor, torch.full_like(actor, 1e-3), rtol=1e-3)
        assert torch.allclose(critic, torch.full_like(critic, 1e-3), rtol=1e-3)
    else:
        assert torch.allclose(actor.hypot(critic), torch.full_like(actor, 1e-3), rtol=1e-3)
        assert (actor < 0.999e-3).all() and (critic < 0.999e-3).all()


@pytest.mark.parametrize("kl_stop", [None, 2.0])
def test_kl_stop_ends_the_actors_steps_and_the_critic_steps_on(tmp_path, kl_stop):
    """train.ppo.kl_stop: at the first minibatch whose KL passes kl_stop × desired_kl the actor takes no more
    steps in the update — its weights stay as they were before that minibatch — while the critic takes every
    step; the rate is lr_min, where the rule's remaining steps would have taken it, and `actor_step_share`
    logs the actor's share. Without it both networks take every step. Without desired_kl: a one-line error."""
    from fallkit.errors import ConfigError
    from fallkit.rl import ppo as ppo_module

    from fallkit.rl.trainer import Trainer

    trainer = Trainer(tiny_config(), tmp_path / "run")
    trainer.td = trainer.env.reset()
    batch = trainer.collect()
    # a KL limit of 2e-6: the first minibatch (KL 0) steps, the second one's KL passes it
    cfg = trainer.config.train.ppo.model_copy(update={"kl_stop": kl_stop, "desired_kl": 1e-6, "epochs": 3})
    ppo = ppo_module.PPO(trainer.actor, trainer.critic, cfg, rewards=trainer.env.rewards)
    actor_params, critic_params = (ppo.optimizer.param_groups[k]["params"] for k in (0, 1))
    steps = []  # per optimizer step: (actor stepped, critic stepped, the actor's weights before the step)

    def record(optimizer, args, kwargs):
        stepped = [all(p.grad is not None for p in params) for params in (actor_params, critic_params)]
        steps.append((*stepped, [p.detach().clone() for p in actor_params]))

    ppo.optimizer.optimizer.register_step_pre_hook(record)
    stats = ppo.update(batch.clone(), generator=torch.Generator().manual_seed(0))
    count = cfg.epochs * cfg.num_minibatches
    assert len(steps) == count and all(critic for _, critic, _ in steps)
    actor_steps = sum(actor for actor, _, _ in steps)
    assert stats["actor_step_share"].item() == pytest.approx(actor_steps / count)
    if kl_stop is None:
        assert actor_steps == count
        return
    assert [actor for actor, _, _ in steps] == [True] + [False] * (count - 1)
    for before, after in zip(steps[1][2], actor_params):  # the weights after the first step are the update's
        assert torch.equal(before, after)
    assert ppo.optimizer.learning_rate.item() == cfg.lr_min  # where the rule's remaining steps would take it
    with pytest.raises(ConfigError, match="train.ppo.kl_stop=2 is a multiple of desired_kl, which is null"):
        tiny_config("train.ppo.kl_stop=2", "train.ppo.desired_kl=null")


def _reads_by_fallkit(fn) -> list[str]:
    """The host reads that fallkit's own code makes while `fn` runs."""
    return [read for read in host_reads(fn) if f"{os.sep}fallkit{os.sep}" in read]


def test_the_update_and_the_logged_figures_read_nothing_back_per_minibatch(tmp_path):
    """On a GPU every read of a device value waits for the launch queue. The PPO update (the KL rule
    included: a tensor learning rate), the episode statistics and the logged figures stay on the
    device; `Trainer.iterate` reads them once per iteration (one `.tolist()`) and returns floats. Without
    train.ppo.kl_stop, which reads the KL at every minibatch by design (train=quick's; off in train=quick_gpu)."""
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(tiny_config("train.ppo.kl_stop=null"), tmp_path / "run")
    trainer.td = trainer._first_observation()  # staggered clocks: episodes end and restart within a batch
    batch = trainer.collect()
    assert _reads_by_fallkit(lambda: trainer.learn(batch)) == []
    assert _reads_by_fallkit(lambda: trainer.diagnostics(batch)) == []
    stats = trainer.iterate()
    assert all(isinstance(v, float) for v in stats.values())
    assert stats["episode/count"] > 0 and stats["episode/max_impact_force"] >= 0.0
    assert {"kl", "learning_rate", "learning_rate_mean", "reward", "reward_terms/impact", "collect_s", "update_s"} <= stats.keys()
    lr = trainer.config.train.ppo
    assert lr.lr_min <= stats["learning_rate_mean"] <= lr.lr_max


def test_the_minibatch_count_switches_at_its_env_steps(tmp_path):
    """train.ppo.late_num_minibatches: the updates before late_from_env_steps take num_minibatches steps an
    epoch, those after it the late count, each logged; the optimizer counts every step."""
    import csv

    from fallkit.rl.trainer import Trainer

    # 8 envs x 4 steps = 32 env steps an iteration: iterations 0-1 in 2 minibatches, 2-3 in 4
    trainer = Trainer(tiny_config("train.iterations=4", "train.ppo.late_num_minibatches=4",
                                  "train.ppo.late_from_env_steps=64"), tmp_path / "run")  # fmt: skip
    steps = []
    trainer.ppo.optimizer.optimizer.register_step_pre_hook(lambda *_: steps.append(trainer.iteration))
    trainer.run()
    rows = list(csv.DictReader((tmp_path / "run" / "metrics.csv").open()))
    assert [float(r["num_minibatches"]) for r in rows] == [2, 2, 4, 4]
    assert [steps.count(k) for k in range(4)] == [2 * 2, 2 * 2, 2 * 4, 2 * 4]  # 2 epochs each


def test_resume_from_an_optimizer_saved_with_a_float_rate(tmp_path):
    """Checkpoints saved before the rates were device tensors and Adam fused (a float rate, no `fused`)
    resume into the tensor rates and continue exactly as the new form does."""
    import copy

    from fallkit.rl.trainer import Trainer

    trainer = Trainer(tiny_config(), tmp_path / "run")
    trainer.td = trainer.env.reset()
    trainer.learn(trainer.collect())
    state = trainer.ppo.state_dict()
    old = copy.deepcopy(state)
    for group in old["optimizer"]["param_groups"]:
        group.update(lr=float(group["lr"]), fused=None)
    batch = trainer.collect()
    weights = []
    for saved in (state, old):
        ppo = trainer.ppo
        actor = copy.deepcopy(trainer.actor.state_dict())
        critic = copy.deepcopy(trainer.critic.state_dict())
        ppo.load_state_dict(copy.deepcopy(saved))
        assert all(isinstance(g["lr"], torch.Tensor) and g["fused"] for g in ppo.optimizer.param_groups)
        ppo.update(batch.clone(), generator=torch.Generator().manual_seed(0))
        weights.append(copy.deepcopy(trainer.actor.state_dict()))
        trainer.actor.load_state_dict(actor)
        trainer.critic.load_state_dict(critic)
    assert_same_weights(*weights)


def test_a_diverged_run_stops_with_one_line_and_keeps_its_checkpoints(tmp_path):
    """NaN weights make every later iteration (and a last.pt of them) worthless: training stops at the first
    NaN loss with a TrainingError naming the iteration and the last checkpoint before it."""
    from fallkit.errors import TrainingError
    from fallkit.rl.models import policy_net
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(tiny_config("train.iterations=4", "train.checkpoint_every=1"), tmp_path / "run")
    trainer.td = trainer._first_observation()
    trainer.learn(trainer.collect())
    trainer.iteration = 1
    trainer.save(tmp_path / "run" / "checkpoints" / "iter_000001.pt")
    with torch.no_grad():
        policy_net(trainer.actor).mean[0].weight.fill_(float("nan"))  # a diverged network
    with pytest.raises(TrainingError, match="diverged at iteration 2: .*iter_000001.pt"):
        trainer.run()
    assert not (tmp_path / "run" / "checkpoints" / "last.pt").exists()
    assert "nan" in (tmp_path / "run" / "metrics.csv").read_text().splitlines()[-1]
