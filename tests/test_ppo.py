"""PPO pieces: the adaptive learning-rate rule, the running normaliser, checkpoints."""

from __future__ import annotations

import pytest
import torch

from fallkit.config import PPOConfig
from fallkit.rl.checkpoint import CheckpointError, load_checkpoint, run_checkpoints, save_checkpoint
from fallkit.rl.models import RunningNorm
from fallkit.rl.optimizer import adapt_learning_rate
from fallkit.rl.ppo import gaussian_kl


def test_adaptive_learning_rate_follows_rsl_rl():
    """The rule on the device gives what rsl_rl's on Python floats gives, to the bit."""
    cfg = PPOConfig(desired_kl=0.01, lr_min=1e-5, lr_max=1e-2)

    def rule(lr: float, kl: float, c: PPOConfig = cfg) -> float:
        return adapt_learning_rate(torch.tensor(lr, dtype=torch.float64), torch.tensor(kl), c).item()

    assert rule(1e-3, 0.05) == 1e-3 / 1.5  # KL > 2 x target: smaller steps
    assert rule(1e-3, 0.001) == 1e-3 * 1.5  # KL < target / 2: larger steps
    assert rule(1e-3, 0.01) == 1e-3  # in between: unchanged
    assert rule(1e-3, 0.0) == 1e-3  # no move at all (the first minibatch): unchanged
    assert rule(1e-3, float("nan")) == 1e-3  # a NaN KL changes nothing
    assert rule(1.2e-5, 1.0) == 1e-5  # floor
    assert rule(9e-3, 0.0001) == 1e-2  # ceiling
    assert rule(1e-3, 1.0, PPOConfig(desired_kl=None)) == 1e-3  # fixed rate


def test_gaussian_kl_matches_torch():
    loc0, s0 = torch.randn(64, 5), torch.rand(64, 5) + 0.2
    loc1, s1 = torch.randn(64, 5), torch.rand(64, 5) + 0.2
    p = torch.distributions.Independent(torch.distributions.Normal(loc0, s0), 1)
    q = torch.distributions.Independent(torch.distributions.Normal(loc1, s1), 1)
    assert gaussian_kl(loc0, s0, loc1, s1).item() == pytest.approx(torch.distributions.kl_divergence(p, q).mean().item(), rel=1e-5)


def test_running_norm_matches_whole_batch_statistics_and_updates_in_place():
    norm = RunningNorm(3)
    mean_buffer = norm.mean
    data = torch.randn(1000, 3) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([2.0, -1.0, 0.0])
    for chunk in data.split(137):
        norm.update(chunk)
    assert norm.mean is mean_buffer  # in place: collecting code sees the new statistics
    torch.testing.assert_close(norm.mean, data.mean(0), atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(norm.var, data.var(0, unbiased=False), atol=1e-5, rtol=1e-4)
    z = norm(data)
    assert z.mean(0).abs().max() < 1e-4 and (z.std(0) - 1).abs().max() < 1e-2


def test_checkpoint_roundtrip_and_run_dir(tmp_path):
    path = save_checkpoint(tmp_path / "checkpoints" / "last.pt", {"iteration": 7, "w": torch.arange(3)})
    assert run_checkpoints(tmp_path) == [path]
    data = load_checkpoint(tmp_path)
    assert data["iteration"] == 7 and data["w"].tolist() == [0, 1, 2] and data["path"] == str(path)
    assert not list((tmp_path / "checkpoints").glob("*.tmp"))  # nothing left behind


def test_a_killed_run_resumes_from_its_newest_intact_checkpoint(tmp_path, caplog):
    """kill -9 leaves no last.pt, only iter_*.pt, and at worst a damaged newest one."""
    run = tmp_path / "run"
    for it in (10, 20, 30):
        save_checkpoint(run / "checkpoints" / f"iter_{it:06d}.pt", {"iteration": it})
    assert load_checkpoint(run)["iteration"] == 30
    newest = run / "checkpoints" / "iter_000030.pt"
    newest.write_bytes(newest.read_bytes()[:40])
    with caplog.at_level("WARNING", logger="fallkit.rl.checkpoint"):
        assert load_checkpoint(run)["iteration"] == 20
    assert "skipped a damaged checkpoint: checkpoint " in caplog.text and "iter_000030.pt" in caplog.text
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match=r"no checkpoint in .*empty/checkpoints: the run stopped before"):
        load_checkpoint(tmp_path / "empty")


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty"])
def test_damaged_checkpoint_is_a_clear_error(tmp_path, damage):
    path = save_checkpoint(tmp_path / "c.pt", {"iteration": 1, "w": torch.randn(1000)})
    raw = path.read_bytes()
    path.write_bytes({"truncate": raw[: len(raw) // 2], "garbage": b"not a checkpoint" * 10, "empty": b""}[damage])
    with pytest.raises(CheckpointError, match=r"c\.pt is corrupt or truncated"):
        load_checkpoint(path)


def test_missing_checkpoint_and_foreign_file(tmp_path):
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_checkpoint(tmp_path / "nope.pt")
    torch.save({"some": "dict"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="is not a fallkit checkpoint"):
        load_checkpoint(tmp_path / "other.pt")


def _prior_observation(spec, blends: list[float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Actor observations (up to the blend) with random joints q and goals, one row per blend u: (obs, q, goal)."""
    from fallkit.env.observations import actor_slices

    cols, j = actor_slices(spec), len(spec.joints)
    obs = torch.zeros(len(blends), cols["blend"].stop)
    q, goal = torch.randn(len(blends), j) * 0.3, torch.randn(len(blends), j) * 0.3
    obs[:, cols["joint_pos"]], obs[:, cols["goal_joint_pos"]] = q, goal
    obs[:, cols["blend"]] = torch.tensor(blends).view(-1, 1)
    return obs, q, goal


def test_joint_prior_holds_then_seeks_the_target_joints(biped):
    from fallkit.rl.models import JointPrior

    scale, nominal = 0.5, torch.as_tensor(biped.nominal_q()).float()
    obs, q, goal = _prior_observation(biped, [0.0, 0.5, 1.0])
    hold = JointPrior(biped, scale, seek=False)(obs)
    seek = JointPrior(biped, scale, seek=True)(obs)
    torch.testing.assert_close(hold, (q - nominal) / scale)
    torch.testing.assert_close(seek[0], hold[0])  # u = 0: the hold
    torch.testing.assert_close(seek[1], ((q[1] + goal[1]) / 2 - nominal) / scale)
    torch.testing.assert_close(seek[2], (goal[2] - nominal) / scale)  # u = 1: the target joints


def test_faded_residual_leaves_the_end_of_the_fall_to_the_prior(biped):
    from fallkit.env.observations import actor_slices
    from fallkit.rl.models import GaussianPolicyNet, JointPrior

    cols = actor_slices(biped)
    dim, j = cols["blend"].stop, len(biped.joints)
    prior = JointPrior(biped, 0.5, seek=True, fade=True)
    net = GaussianPolicyNet(dim, j, [8], 0.3, prior)
    torch.nn.init.normal_(net.mean[-1].weight)  # a residual that is not ~0
    obs = torch.randn(2, dim)
    obs[:, cols["blend"]] = torch.tensor([[0.0], [1.0]])
    loc, _ = net(obs)
    assert not torch.allclose(loc[0], prior(obs)[0])  # u = 0: the MLP acts
    torch.testing.assert_close(loc[1], prior(obs)[1])  # u = 1: the prior alone
    torch.testing.assert_close(loc, prior(obs) + net.deviation(obs))  # what the benchmarks read as the deviation


def test_prior_power_keeps_the_hold_and_the_residual_longer_and_still_ends_at_the_target(biped):
    """train.prior_power: the prior seeks and fades by u^p, so mid-fall it is nearer the hold and keeps
    more of the learned deviation, and at u = 1 it is the target joints alone, as with p = 1."""
    from fallkit.rl.models import JointPrior

    scale, nominal = 0.5, torch.as_tensor(biped.nominal_q()).float()
    obs, q, goal = _prior_observation(biped, [0.5, 1.0])
    prior = JointPrior(biped, scale, seek=True, fade=True, power=3.0)
    torch.testing.assert_close(prior(obs)[0], (q[0] + 0.125 * (goal[0] - q[0]) - nominal) / scale)  # 0.5³
    torch.testing.assert_close(prior.residual_weight(obs)[0], torch.tensor([0.875]))
    torch.testing.assert_close(prior(obs)[1], (goal[1] - nominal) / scale)
    torch.testing.assert_close(prior.residual_weight(obs)[1], torch.tensor([0.0]))


def test_faded_noise_follows_the_residual_down_to_its_floor(biped):
    """train.fade_noise: full std where the MLP has its say, std × floor where the mean is the prior's."""
    from fallkit.config import validate
    from fallkit.rl.models import GaussianPolicyNet, JointPrior

    obs, _, _ = _prior_observation(biped, [0.0, 0.5, 1.0])
    j = len(biped.joints)
    prior = JointPrior(biped, 0.5, seek=True, fade=True, power=2.0)
    _, scale = GaussianPolicyNet(obs.shape[-1], j, [8], 0.3, prior, noise_floor=0.1)(obs)
    torch.testing.assert_close(scale[:, 0], torch.tensor([0.3, 0.3 * (0.1 + 0.9 * 0.75), 0.03]))
    _, plain = GaussianPolicyNet(obs.shape[-1], j, [8], 0.3, prior)(obs)
    torch.testing.assert_close(plain, torch.full_like(plain, 0.3))  # off: one std throughout
    with pytest.raises(ValueError, match="train.fade_noise .* needs train.fade_residual=true"):
        validate({"robot": {"name": "biped20"}, "train": {"fade_residual": False, "fade_noise": 0.1}})


def test_checkpoints_get_the_users_normal_file_mode(tmp_path):
    import os

    mask = os.umask(0o022)
    try:
        path = save_checkpoint(tmp_path / "c.pt", {"iteration": 1})
    finally:
        os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o644  # not mkstemp's 0600


def test_a_checkpoint_saved_before_prior_power_precision_and_value_heads_keeps_what_it_was_trained_with(tmp_path):
    from fallkit.config import validate

    config = validate({"robot": {"name": "biped20"}}).model_dump(mode="json")
    del config["train"]["prior_power"], config["train"]["precision"], config["train"]["ppo"]["value_per_term"]
    save_checkpoint(tmp_path / "old.pt", {"iteration": 1, "config": config})  # as a run of an earlier day wrote it
    old = validate(load_checkpoint(tmp_path / "old.pt")["config"]).train
    assert old.prior_power == 1.0 and old.precision == "float32"  # as it was trained, whatever "auto" means today
    assert not old.ppo.value_per_term  # one value of the whole return: its critic has one head
    assert validate({"robot": {"name": "biped20"}}).train.prior_power == 8.0  # today's default


def test_value_target_statistics_move_without_changing_a_predicted_value():
    from fallkit.rl.models import ValueNet

    torch.manual_seed(0)
    net = ValueNet(5, [8, 8], normalize_target=True)
    obs = torch.randn(64, 5)
    before = net(obs)
    for mean in (-50.0, -20.0):  # returns of a run that improves
        net.update_target_statistics(mean + 10.0 * torch.randn(512))
        torch.testing.assert_close(net(obs), before, atol=1e-4, rtol=1e-5)  # PopArt's preserving step
    assert -45.0 < net.target.mean.item() < -25.0 and net.target_std().item() > 10.0
    assert ValueNet(5, [8]).target is None  # off: the network and its state_dict are the old ones


def test_bfloat16_networks_act_alike_in_collection_and_update_and_close_to_float32():
    """train.precision=bfloat16: the products run in bfloat16, the outputs and weights stay float32; a row
    gives the same bits in a collection batch and in a shuffled minibatch (so PPO's ratio is exactly 1
    before the first step), and the values stay within bfloat16's rounding of the float32 network's."""
    from fallkit.rl.models import GaussianPolicyNet, ValueNet

    torch.manual_seed(0)
    net = GaussianPolicyNet(30, 6, [64, 64], 0.3, precision="bfloat16")
    torch.nn.init.normal_(net.mean[-1].weight, std=0.1)  # a trained-looking last layer, not the tiny initial one
    obs = 2.0 * torch.randn(512, 30)
    loc, scale = net(obs[:64])
    perm = torch.randperm(512)
    shuffled, _ = net(obs[perm])
    assert loc.dtype == scale.dtype == torch.float32 and net.mean[0].weight.dtype == torch.float32
    assert torch.equal(shuffled[torch.argsort(perm)][:64], loc)
    net.precision = "float32"
    exact, _ = net(obs[:64])
    assert not torch.equal(loc, exact)  # the option does change the arithmetic
    torch.testing.assert_close(loc, exact, atol=0.02 * exact.abs().max().item(), rtol=0.02)
    net.precision = "bfloat16"
    loc.square().sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in net.mean.parameters())

    value = ValueNet(30, [64, 64], precision="bfloat16")
    v = value(obs)
    value.precision = "float32"
    torch.testing.assert_close(v, value(obs), atol=0.02 * value(obs).abs().max().item(), rtol=0.02)


def test_auto_precision_is_bfloat16_only_where_it_was_measured_to_pay():
    from fallkit.rl.models import resolve_precision

    assert resolve_precision("float32", "cpu") == "float32" and resolve_precision("bfloat16", "cpu") == "bfloat16"
    assert resolve_precision("auto", "cuda:0") == "float32"  # unmeasured on a GPU: set by hand there
    assert resolve_precision("auto", "cpu") == ("bfloat16" if torch.cpu._is_avx512_bf16_supported() else "float32")
