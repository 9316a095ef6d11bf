"""train.teachers: a policy with sensitivity inputs imitates policies trained at fixed weights of one component."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from helpers import TINY, composed_config

from fallkit.env.observations import actor_slices
from fallkit.errors import ConfigError
from fallkit.rl.checkpoint import load_checkpoint, save_checkpoint
from fallkit.rl.models import policy_net
from fallkit.rl.policy import load_policy
from fallkit.rl.trainer import Trainer

DRAW_HEAD = ["env.sensitivity_inputs.enabled=true", "env.sensitivity_inputs.components=[head]",
             "env.sensitivity_inputs.low=0.5", "env.sensitivity_inputs.high=8.0"]  # fmt: skip


def trainer(run_dir: Path, *overrides: str) -> Trainer:
    return Trainer(composed_config(*TINY, *overrides), run_dir)


@pytest.fixture(scope="module")
def teachers(tmp_path_factory) -> tuple[Path, Path]:
    """Two teachers of biped20: one trained 2 iterations at the robot's weights (the head at 4), and the same
    policy with the head weighted 16 whose mean action is 0.5 higher in every joint before the prior's fade
    (its last bias moved), so the two act measurably differently on the same state."""
    root = tmp_path_factory.mktemp("teachers")
    trainer(root / "head4", "train.iterations=2").run()
    ckpt = load_checkpoint(root / "head4")
    bias = max((k for k in ckpt["actor"] if k.endswith(".bias") and ".mean." in k), key=lambda k: int(k.split(".")[-2]))
    ckpt["actor"][bias] = ckpt["actor"][bias] + 0.5
    ckpt["config"]["robot"]["sensitivity"] = {**ckpt["config"]["robot"].get("sensitivity", {}), "head": 16.0}
    head16 = save_checkpoint(root / "head16.pt", {k: v for k, v in ckpt.items() if k not in ("path", "format_version")})
    return root / "head4", Path(head16)


def taught(teachers: tuple[Path, Path]) -> str:
    return f"train.teachers.runs=[{teachers[1]},{teachers[0]}]"  # out of order: sorted by the weight they teach


def test_the_target_is_the_teacher_of_the_drawn_weight_blended_in_ln_w(tmp_path, teachers):
    student = trainer(tmp_path, *DRAW_HEAD, taught(teachers))
    obs = student._first_observation()["policy"]
    weights = actor_slices(student.spec, sensitivity=True)["sensitivity"]
    column = weights.start + student.spec.component_names.index("head")
    unweighted = [c for c in range(obs.shape[-1]) if not weights.start <= c < weights.stop]  # what a teacher observes
    head4, head16 = (load_policy(t).module.module.net(obs[:, unweighted])[0] for t in teachers)
    assert (head16 - head4).abs().max() > 0.1  # the two teachers disagree on these states

    def target(weight: float) -> torch.Tensor:
        drawn = obs.clone()
        drawn[:, column] = math.log(weight)
        return student.ppo.teachers.targets(drawn)

    torch.testing.assert_close(target(4.0), head4)
    torch.testing.assert_close(target(16.0), head16)
    torch.testing.assert_close(target(8.0), (head4 + head16) / 2)  # halfway in ln w
    torch.testing.assert_close(target(2.0), head4)  # beyond the ends: the nearest teacher
    torch.testing.assert_close(target(32.0), head16)
    assert target(4.0).shape == head4.shape


def test_a_taught_run_moves_toward_its_teachers_and_logs_how_far(tmp_path, teachers):
    # without train=quick's stop at the KL limit, as docs/sensitivity_inputs.md measured it: the stop bounds the
    # imitation's pull by the KL limit too (the gap 5.0 -> 3.6 with it)
    student = trainer(
        tmp_path, *DRAW_HEAD, taught(teachers), "train.teachers.coef=10", "train.iterations=10", "train.ppo.kl_stop=null"
    )
    obs = student._first_observation()["policy"].clone()
    head = actor_slices(student.spec, sensitivity=True)["sensitivity"].start + student.spec.component_names.index("head")
    obs[:, head] = math.log(16.0)

    @torch.no_grad()
    def gap() -> float:  # how far the student's mean is from the head-16 teacher's on these states
        return float((policy_net(student.actor)(obs)[0] - student.ppo.teachers.targets(obs)).square().sum(-1).mean())

    before = gap()
    student.run()
    assert gap() < 0.6 * before, (before, gap())  # 5.1 -> 2.2 when measured
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert len(rows) == 10 and all(float(r["teacher_loss"]) > 0 for r in rows)


@pytest.mark.parametrize(
    ("overrides", "says"),
    [
        (["env.sensitivity_inputs.enabled=false"], "set env.sensitivity_inputs.enabled=true"),
        (["env.sensitivity_inputs.components=null"], "'env.sensitivity_inputs.components=[head]'"),
        (["robot.sensitivity.pelvis=3"], "pelvis 1 vs 3"),
        (["robot=biped20_battery_baseline"], "use teachers of the same"),
    ],
    ids=["no weight inputs", "every weight drawn", "another robot weighting", "another robot"],
)
def test_teachers_that_cannot_teach_this_run_are_one_line(tmp_path, teachers, overrides, says):
    with pytest.raises(ConfigError, match="train.teachers") as err:
        trainer(tmp_path, *DRAW_HEAD, taught(teachers), *overrides)
    assert says in str(err.value) and "\n" not in str(err.value)


def test_teachers_along_two_components_teach_the_drawn_one(tmp_path, teachers):
    base, head16 = teachers
    ckpt = load_checkpoint(base)  # a third teacher: the elbows at 8 instead of 2, its actions 0.5 lower
    bias = max((k for k in ckpt["actor"] if k.endswith(".bias") and ".mean." in k), key=lambda k: int(k.split(".")[-2]))
    ckpt["actor"][bias] = ckpt["actor"][bias] - 0.5
    ckpt["config"]["robot"]["sensitivity"] = {**ckpt["config"]["robot"].get("sensitivity", {}), "elbows": 8.0}
    kept = {k: v for k, v in ckpt.items() if k not in ("path", "format_version")}
    elbows8 = save_checkpoint(tmp_path / "elbows8.pt", kept)
    runs = f"train.teachers.runs=[{head16},{elbows8},{base}]"
    draw = [*DRAW_HEAD, "env.sensitivity_inputs.components=[head,elbows]"]
    with pytest.raises(ConfigError, match="set env.sensitivity_inputs.draw=one"):
        trainer(tmp_path / "each", *draw, runs)
    student = trainer(tmp_path / "one", *draw, "env.sensitivity_inputs.draw=one", runs)
    obs = student._first_observation()["policy"]
    names = student.spec.component_names
    weights = actor_slices(student.spec, sensitivity=True)["sensitivity"]
    unweighted = [c for c in range(obs.shape[-1]) if not weights.start <= c < weights.stop]
    act = {t: load_policy(t).module.module.net(obs[:, unweighted])[0] for t in (base, head16, elbows8)}

    def target(**drawn: float) -> torch.Tensor:
        x = obs.clone()
        x[:, weights] = torch.log(torch.as_tensor(student.spec.sensitivity, dtype=x.dtype))  # the robot's weights
        for name, w in drawn.items():
            x[:, weights.start + names.index(name)] = math.log(w)
        return student.ppo.teachers.targets(x)

    torch.testing.assert_close(target(), act[base])
    torch.testing.assert_close(target(head=16.0), act[head16])
    torch.testing.assert_close(target(elbows=8.0), act[elbows8])
    torch.testing.assert_close(target(elbows=4.0), (act[base] + act[elbows8]) / 2)  # halfway from 2 to 8 in ln w
    torch.testing.assert_close(target(head=8.0), (act[base] + act[head16]) / 2)


def test_one_teacher_points_to_init_from(tmp_path, teachers):
    with pytest.raises(ConfigError, match="train.init_from"):
        composed_config(*TINY, *DRAW_HEAD, f"train.teachers.runs=[{teachers[0]}]")


def test_a_teacher_that_observes_its_weights_is_refused(tmp_path, teachers):
    conditioned = tmp_path / "conditioned"
    trainer(conditioned, *DRAW_HEAD, "train.iterations=1").run()
    with pytest.raises(ConfigError, match="observes its sensitivity weights"):
        trainer(tmp_path / "new", *DRAW_HEAD, f"train.teachers.runs=[{teachers[0]},{conditioned}]")
