"""train.init_from: a new run whose networks start as a trained policy's, new inputs at zero weight."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from helpers import TINY, composed_config

from fallkit.env.observations import actor_layout, actor_slices, critic_layout
from fallkit.errors import ConfigError
from fallkit.rl.models import policy_net, value_net
from fallkit.rl.trainer import Trainer

SENSITIVITY = "env.sensitivity_inputs.enabled=true"


def trainer(run_dir: Path, *overrides: str) -> Trainer:
    return Trainer(composed_config(*TINY, *overrides), run_dir)


def without(obs: torch.Tensor, layout: list[tuple[str, int]], part: str) -> torch.Tensor:
    """The observation with one part's columns taken out (what a run without that option observes)."""
    keep, at = [], 0
    for name, size in layout:
        if name != part:
            keep.extend(range(at, at + size))
        at += size
    return obs[..., keep]


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A tiny policy without sensitivity inputs, trained 3 iterations (its weights and statistics moved)."""
    run = tmp_path_factory.mktemp("base")
    trainer(run, "train.iterations=3").run()
    return run


def test_a_run_started_from_a_policy_acts_as_it_and_learns_its_new_inputs(tmp_path, trained):
    loaded = trainer(tmp_path / "loaded")  # the trained policy, loaded as evaluation would
    from fallkit.rl.checkpoint import load_checkpoint

    ckpt = load_checkpoint(trained)
    loaded.actor.load_state_dict(ckpt["actor"])
    loaded.critic.load_state_dict(ckpt["critic"])
    new = trainer(tmp_path / "new", f"train.init_from={trained}", SENSITIVITY, "train.iterations=2")
    assert float(new.ppo.optimizer.learning_rate) == ckpt["ppo"]["learning_rate"]  # the rule goes on from there

    td = new._first_observation()
    spec = new.spec
    weights = actor_slices(spec, sensitivity=True)["sensitivity"]
    # the new columns' statistics are the first observations' (not mean 0, variance 1 of a long count)
    norm = policy_net(new.actor).norm
    obs = td["policy"][..., weights]
    torch.testing.assert_close(norm.mean[weights], obs.mean(0))
    loaded_count = next(v for k, v in ckpt["actor"].items() if k.endswith("norm.count"))
    assert norm.count == loaded_count + td.batch_size[0]  # the loaded statistics go on, not a fresh count
    # acting as the loaded policy on the same state: the new inputs start at zero weight
    actor_obs = without(td["policy"], actor_layout(spec, sensitivity=True), "sensitivity")
    critic_obs = without(td["critic"], critic_layout(spec, sensitivity=True), "actor.sensitivity")
    policy_net(loaded.actor).norm.update(actor_obs)  # the first observations join both runs' statistics
    value_net(loaded.critic).norm.update(critic_obs)
    for a, b in zip(policy_net(new.actor)(td["policy"]), policy_net(loaded.actor)(actor_obs)):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(value_net(new.critic)(td["critic"]), value_net(loaded.critic)(critic_obs),
                               rtol=1e-5, atol=1e-5)  # fmt: skip

    first = policy_net(new.actor).mean[0].weight
    assert torch.count_nonzero(first[:, weights]) == 0
    new.td = td
    new.run()
    assert torch.count_nonzero(first[:, weights]) > 0  # the inputs it did not have are being learned


@pytest.mark.parametrize(
    ("overrides", "says"),
    [
        (["train.prior_power=1"], "train.prior_power=8.0"),
        (["train.actor_hidden=[32,32]"], "network sizes"),
        (["train.critic_layer_norm=true"], "train.critic_layer_norm"),
    ],
    ids=["another prior", "other sizes", "a critic with LayerNorm"],
)
def test_what_would_change_the_loaded_weights_meaning_is_one_line(tmp_path, trained, overrides, says):
    with pytest.raises(ConfigError, match="train.init_from") as err:
        trainer(tmp_path, f"train.init_from={trained}", *overrides)
    assert says in str(err.value) and "\n" not in str(err.value)


def test_a_part_the_loaded_policy_observed_cannot_be_dropped(tmp_path):
    base = tmp_path / "conditioned"
    trainer(base, SENSITIVITY, "train.iterations=1").run()
    with pytest.raises(ConfigError, match="part 'sensitivity', which this run does not observe"):
        trainer(tmp_path / "new", f"train.init_from={base}")


def test_a_policy_of_another_robot_model_is_refused(tmp_path, trained):
    from fallkit.rl.checkpoint import load_checkpoint, save_checkpoint

    ckpt = load_checkpoint(trained)
    ckpt.update(robot="go1", model_hash="0123abcd")  # what a go1 checkpoint says of itself
    other = save_checkpoint(tmp_path / "go1.pt", {k: v for k, v in ckpt.items() if k not in ("path", "format_version")})
    with pytest.raises(ConfigError, match="trained on robot 'go1', another model than this run's 'biped20'"):
        trainer(tmp_path / "new", f"train.init_from={other}")


def test_a_missing_checkpoint_says_which_setting_named_it(tmp_path):
    from fallkit.errors import CheckpointError

    with pytest.raises(CheckpointError, match=r"^train.init_from: checkpoint not found: .*nowhere$"):
        trainer(tmp_path / "new", f"train.init_from={tmp_path / 'nowhere'}")
