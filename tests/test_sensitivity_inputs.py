"""Sensitivity weights as policy inputs (issue 17, part 1; env.sensitivity_inputs): drawn per episode in
training, observed by actor and critic, the robot's own (or the user's) in evaluation, carried by the
export and set on the robot."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from helpers import TINY, composed_config
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from fallkit.config import EnvConfig
from fallkit.deploy import DeployError, EndPose, FallController, RobotState
from fallkit.env.fall_env import FallEnv
from fallkit.env.mirror import observation_mirror
from fallkit.env.observations import actor_layout, actor_slices, critic_layout
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.rotations import quat_rotate_inverse
from fallkit.sim import make_sim

QUIET = dict(noise={"scale": 0.0}, disturbances={"enabled": False})


def inputs(**r) -> EnvConfig:
    return EnvConfig(**QUIET, sensitivity_inputs={"enabled": True, **r})


@pytest.fixture(scope="module")
def poses(biped):
    return random_end_poses(biped, 16, torch.Generator().manual_seed(0))


def make_env(spec, poses, env_cfg: EnvConfig, n: int = 8) -> FallEnv:
    from fallkit.config import RewardConfig

    return FallEnv(spec, env_cfg, RewardConfig(), poses, make_sim(spec, n, "mujoco", body_state=True), seed=0)


def test_off_by_default_and_the_layout_without_it_unchanged(biped):
    assert EnvConfig().sensitivity_inputs.enabled is False
    assert [n for n, _ in actor_layout(biped)][-1] == "blend"
    with_inputs = actor_layout(biped, sensitivity=True)
    assert with_inputs[:-1] == actor_layout(biped) and with_inputs[-1] == ("sensitivity", len(biped.components))
    assert sum(s for _, s in critic_layout(biped, True)) == sum(s for _, s in critic_layout(biped)) + 5


def test_episodes_draw_weights_log_uniformly_and_actor_and_critic_observe_them(biped, poses):
    env = make_env(biped, poses, inputs(low=0.5, high=4.0), n=64)
    check_env_specs(env, seed=0)
    td = env.reset()
    robot = torch.as_tensor(biped.sensitivity, dtype=torch.float32)
    factor = env.sensitivity / robot
    assert factor.min() >= 0.5 and factor.max() <= 4.0
    assert factor.log().std() > 0.3  # spread over the range, each world and component its own
    assert (factor[:, 0] != factor[:, 1]).all() and (factor[0] != factor[1]).all()
    cols = actor_slices(biped, True)["sensitivity"]
    torch.testing.assert_close(td["policy"][:, cols], env.sensitivity.log())
    torch.testing.assert_close(td["critic"][:, cols], env.sensitivity.log())  # the critic starts with the actor's
    # a partial reset draws new weights for the worlds it resets, and only for those
    before = env.sensitivity.clone()
    mask = torch.zeros(64, 1, dtype=torch.bool)
    mask[:3] = True
    env.reset(TensorDict({"_reset": mask}, batch_size=[64]))
    assert (env.sensitivity[3:] == before[3:]).all() and (env.sensitivity[:3] != before[:3]).all()


def test_draw_one_changes_one_component_per_episode_and_keeps_the_others(biped, poses):
    env = make_env(biped, poses, inputs(low=0.5, high=4.0, draw="one"), n=256)
    env.reset()
    factor = env.sensitivity / torch.as_tensor(biped.sensitivity, dtype=torch.float32)
    changed = factor != 1.0
    assert (changed.sum(dim=1) == 1).all()  # exactly one component per world (a draw of exactly 1.0 is measure zero)
    assert (changed.sum(dim=0) > 256 / len(biped.components) / 2).all()  # every component is chosen, about evenly
    assert factor.min() >= 0.5 and factor.max() <= 4.0


@pytest.mark.parametrize("draw", ["each", "one"])
def test_only_the_named_components_are_drawn(biped, poses, draw):
    names = biped.component_names
    env = make_env(biped, poses, inputs(low=0.5, high=4.0, draw=draw, components=[names[0], names[-1]]), n=256)
    env.reset()
    changed = env.sensitivity / torch.as_tensor(biped.sensitivity, dtype=torch.float32) != 1.0
    assert not changed[:, 1:-1].any()  # the others keep the robot's weights
    assert changed[:, 0].sum() > 64 and changed[:, -1].sum() > 64
    if draw == "one":
        assert (changed.sum(dim=1) == 1).all()
    else:
        assert changed[:, [0, -1]].all()


def test_components_that_are_not_the_robots_are_one_line_errors(biped, poses):
    from fallkit.errors import ConfigError

    with pytest.raises(ConfigError, match=r"\['tail'\] are not components of this robot; its components are \["):
        make_env(biped, poses, inputs(components=["head", "tail"]))
    with pytest.raises(ValueError, match="at least 1 item"):
        inputs(components=[])


def test_the_export_says_which_weights_were_drawn(biped):
    from fallkit.rl.export import _sensitivity_inputs

    on = ["env.sensitivity_inputs.enabled=true", "env.sensitivity_inputs.low=0.5", "env.sensitivity_inputs.high=2"]
    meta = _sensitivity_inputs(biped, composed_config(*on, "env.sensitivity_inputs.components=[head]"))
    w = dict(zip(biped.component_names, biped.sensitivity.tolist()))
    assert meta["trained_range"]["head"] == pytest.approx([w["head"] / 2, w["head"] * 2])
    assert meta["trained_range"]["pelvis"] == pytest.approx([w["pelvis"]] * 2)  # a controller warns if it is set
    assert "only ['head'] drawn" in meta["trained_draw"]


def test_the_impact_reward_weighs_each_world_by_its_own_weights(biped, poses):
    """Every weight doubled (low = high = 2) quadruples the impact term on the same falls."""
    impact = []
    for cfg in (EnvConfig(**QUIET), inputs(low=2.0, high=2.0)):
        env = make_env(biped, poses, cfg)
        td = env.reset()
        hold = env.action_for_setpoint(env.sim.state.joint_pos.clone())
        for _ in range(40):  # 0.8 s: every fall has hit the floor
            td["action"] = hold
            td = env.step(td)["next"]
        impact.append(env.pop_reward_terms()["impact"])
    assert impact[0] < -1e-3
    assert impact[1] == pytest.approx(4.0 * impact[0], rel=1e-4)


def test_the_mirror_swaps_the_weights_of_mirrored_components(biped):
    mirror = observation_mirror(biped, sensitivity=True)
    x = torch.randn(4, sum(s for _, s in actor_layout(biped, True)))
    cols = actor_slices(biped, True)["sensitivity"]
    torch.testing.assert_close(mirror.actor(x)[:, cols], x[:, cols])  # biped20's components are their own mirrors
    torch.testing.assert_close(mirror.actor(mirror.actor(x)), x)
    c = torch.randn(4, sum(s for _, s in critic_layout(biped, True)))
    torch.testing.assert_close(mirror.critic(mirror.critic(c)), c)


# ---- one trained policy, evaluated, exported and run with other weights ----------------------------


@pytest.fixture(scope="module")
def conditioned(tmp_path_factory):
    """A 1-iteration policy trained with sensitivity inputs, and its export."""
    from fallkit.rl.export import run_export
    from fallkit.rl.trainer import Trainer

    tmp = tmp_path_factory.mktemp("sensitivity")
    on = ["env.sensitivity_inputs.enabled=true", "train.iterations=1"]
    Trainer(composed_config(*TINY, *on), tmp / "run").run()
    (tmp / "export").mkdir()
    run_export(composed_config(*TINY, *on, f"checkpoint={tmp / 'run'}", "mode=export"), tmp / "export")
    return tmp / "run", tmp / "export"


def test_evaluation_observes_the_weights_given_on_the_command_line(conditioned):
    from fallkit.eval.evaluate import make_eval_env, prepare

    setup = prepare(composed_config(f"checkpoint={conditioned[0]}", "mode=eval", "robot.sensitivity.head=9"))
    assert setup.config.robot.sensitivity["head"] == 9.0 and setup.config.robot.sensitivity["legs"] == 1.0
    env = make_eval_env(setup, 4, None, seed=7)
    td = env.reset()
    head = env.spec.component_names.index("head")
    assert (env.sensitivity[:, head] == 9.0).all()  # evaluation draws none: the user's weight in every world
    cols = actor_slices(env.spec, True)["sensitivity"]
    assert torch.allclose(td["policy"][:, cols][:, head], torch.tensor(math.log(9.0)))


def test_the_export_carries_the_weights_and_the_controller_observes_them_as_the_env_does(conditioned):
    from fallkit.eval.evaluate import make_eval_env, prepare

    meta = json.loads((conditioned[1] / "policy.json").read_text())
    assert meta["observation_layout"][-1]["name"] == "sensitivity"
    assert meta["sensitivity"]["defaults"]["head"] == 4.0  # biped20's own
    assert meta["sensitivity"]["trained_range"]["head"] == pytest.approx([0.8, 20.0])
    controller = FallController.load(conditioned[1], sensitivity={"head": 9.0})

    setup = prepare(composed_config(f"checkpoint={conditioned[0]}", "mode=eval", "robot.sensitivity.head=9"))
    env = make_eval_env(setup, 1, None, seed=3)
    td = env.reset()
    st, names, pose = env.sim.state, env.spec.joint_names, int(env.end_pose_ids[0])
    controller.reset(EndPose(joints=dict(zip(names, env.end_poses.joint_pos[pose].tolist())),
                             root_quat=env.end_poses.root_quat[pose].tolist()))  # fmt: skip
    controller.step(RobotState(
        base_quat=st.root_quat[0].tolist(), base_ang_vel=st.root_ang_vel[0].tolist(),
        base_lin_vel=quat_rotate_inverse(st.root_quat, st.root_lin_vel)[0].tolist(),
        joint_pos=dict(zip(names, st.joint_pos[0].tolist())), joint_vel=dict(zip(names, st.joint_vel[0].tolist())),
    ))  # fmt: skip
    np.testing.assert_allclose(controller.observation[0], td["policy"][0].numpy(), atol=1e-5, rtol=0)


@pytest.mark.parametrize(
    "weights, message",
    [
        ({"tail": 1.0}, r"set_sensitivity: unknown components \['tail'\]; components are \['pelvis'"),
        ({"head": -1.0}, r"the weight of 'head' must be a finite number >= 0, got -1.0"),
        ({"head": float("nan")}, r"the weight of 'head' must be a finite number >= 0, got nan"),
        ({"legs": 2.0, "head": "heavy"}, r"the weight of 'head' must be a finite number >= 0, got 'heavy'"),
    ],
)
def test_bad_weights_on_the_robot_are_one_line_errors(conditioned, weights, message):
    controller = FallController.load(conditioned[1])
    with pytest.raises(DeployError, match=message):
        controller.set_sensitivity(weights)
    assert controller.sensitivity == FallController.load(conditioned[1]).sensitivity  # all or nothing: untouched


def test_a_weight_outside_the_trained_range_is_used_with_a_warning(conditioned, caplog):
    controller = FallController.load(conditioned[1])
    controller.set_sensitivity({"head": 100.0})
    assert controller.sensitivity["head"] == 100.0
    assert "outside the range the policy was trained on [0.8, 20]" in caplog.text


def test_evaluating_with_a_weight_that_was_never_drawn_warns(tmp_path, caplog):
    from fallkit.eval.evaluate import prepare
    from fallkit.rl.trainer import Trainer

    on = ["env.sensitivity_inputs.enabled=true", "env.sensitivity_inputs.components=[head]", "train.iterations=1"]
    Trainer(composed_config(*TINY, *on), tmp_path / "run").run()
    prepare(composed_config(f"checkpoint={tmp_path / 'run'}", "mode=eval", "robot.sensitivity.head=9"))
    assert "never saw" not in caplog.text  # the head's weight was drawn in training
    prepare(composed_config(f"checkpoint={tmp_path / 'run'}", "mode=eval", "robot.sensitivity.pelvis=3"))
    assert "trained with only ['head'] drawn" in caplog.text and "another weight of ['pelvis']" in caplog.text
