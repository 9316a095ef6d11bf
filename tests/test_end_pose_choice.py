"""eval.poses=auto (issue 17, part 2): each fall's end pose chosen from candidates when the fall begins,
by the trained critic or by where the fall's tilt is heading, in eval, sim2sim and the deployed controller."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import TINY, composed_config, fallkit_cli

from fallkit.config import ConfigError
from fallkit.deploy import DeployError, EndPose, FallController, RobotState
from fallkit.deploy.sim2sim import _estimate
from fallkit.env.fall_env import FallEnv
from fallkit.eval import evaluate as ev
from fallkit.eval.choice import PoseChoice, candidate_values, choose_end_poses, start_states
from fallkit.pose_choice import predicted_ground
from fallkit.pose_format import ground_sides, root_quat_from_pitch_roll
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.sim import make_sim
from fallkit.sim.base import Layout

EXAMPLE = Path(__file__).parents[1] / "examples" / "biped20_quick"  # a trained export that ships with fallkit
SEED = 4242
SIDE_WORDS = ["front", "back", "left", "right", "bottom", "top"]
SIDE_AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A briefly trained biped20 policy with its critic (TINY: 2×16 networks, 0.2 s episodes)."""
    from fallkit.rl.trainer import Trainer

    run = tmp_path_factory.mktemp("choice") / "run"
    Trainer(composed_config(*TINY, "train.iterations=2"), run).run()
    return run


@pytest.fixture(scope="module")
def tiny_run_gravity(tmp_path_factory) -> Path:
    """The same, trained with env.observe_gravity (the goal is in two parts of the observation)."""
    from fallkit.rl.trainer import Trainer

    run = tmp_path_factory.mktemp("choice_gravity") / "run"
    Trainer(composed_config(*TINY, "train.iterations=2", "env.observe_gravity=true"), run).run()
    return run


def eval_env(spec, worlds: int, poses: int = 9, gravity: bool = False) -> FallEnv:
    """mode=eval's env settings, 0.2 s falls, `poses` random (unsettled) end poses as the candidates."""
    cfg = ev.eval_run_config(composed_config("robot=biped20", f"env.observe_gravity={gravity}"), 0.2)
    candidates = random_end_poses(spec, poses, torch.Generator().manual_seed(1))
    return FallEnv(spec, cfg.env, cfg.reward, candidates, make_sim(spec, worlds, body_state=True), seed=3)


@pytest.mark.parametrize("gravity", [False, True], ids=["plain", "observe_gravity"])
def test_the_critic_scorer_chooses_the_argmax_of_the_critic_over_the_candidates(biped, gravity, request):
    """V(s, g) scored in one batch equals the critic on the env's own observation with each candidate
    set as the fall's real goal (env.reset_to toward it), and the chosen pose is its argmax."""
    from fallkit.rl.policy import load_policy

    critic = load_policy(request.getfixturevalue("tiny_run_gravity" if gravity else "tiny_run")).critic
    n, p = 5, 9
    env = eval_env(biped, n, p, gravity)
    trials = ev.draw_trials(env, n, SEED)
    batched = candidate_values(env, critic, start_states(env, trials))
    direct = torch.empty(n, p)
    with torch.no_grad():
        for c in range(p):  # the env encodes the goal itself: tilt of the settled quaternion, joints
            td = env.reset_to(trials.qpos, trials.qvel, torch.full((n,), c))
            direct[:, c] = critic(td["critic"]).sum(-1)  # V(s, g): the sum of the value heads
    assert (direct.std(dim=1) > 1e-4).all()  # the critic does depend on the goal: the choice is not a constant
    torch.testing.assert_close(batched, direct, atol=1e-5, rtol=1e-5)
    chosen = choose_end_poses(env, trials, PoseChoice("critic", critic=critic))
    best = direct.gather(1, chosen.pose_ids[:, None]).squeeze(1)
    assert torch.all(best >= direct.max(dim=1).values - 1e-5)
    assert torch.equal(chosen.qpos, trials.qpos) and torch.equal(chosen.qvel, trials.qvel)  # the same falls


def test_chosen_poses_keep_the_strategies_paired(biped):
    """Every strategy falls from the same states toward the same chosen pose, the one the choice named."""
    k, names = 4, ["zero_torque", "damping", "freeze"]
    env = eval_env(biped, len(names) * k)
    random = ev.draw_trials(env, k, SEED)
    chosen = choose_end_poses(env, random, PoseChoice("heading"))
    assert not torch.equal(chosen.pose_ids, random.pose_ids)  # the choice differs from the random draw here
    out = ev.rollout(env, chosen, names, steps=2, record_states=True)
    q0 = out.qpos[0].view(len(names), k, -1)
    want = env.end_poses.joint_pos[chosen.pose_ids]
    for i, name in enumerate(names):
        assert torch.equal(q0[i], q0[0])
        assert torch.equal(out.traces[name].target_joint_pos, want)
        assert torch.equal(out.traces[name].target_root_quat, env.end_poses.root_quat[chosen.pose_ids])


def test_heading_follows_the_lean_and_the_push():
    """A robot leaning forward, or upright and pushed forward, heads for its front; leaning forward but pushed
    back hard enough to move its capture point behind the feet, for its back; to the left, its left side."""

    def heading(pitch_deg: float, roll_deg: float, velocity: list[float]) -> str:
        quat = root_quat_from_pitch_roll(math.radians(pitch_deg), math.radians(roll_deg))[None]
        return SIDE_WORDS[int(np.argmax(predicted_ground(quat, np.array([velocity]), 0.5) @ SIDE_AXES.T))]

    assert heading(10, 0, [0.0, 0.0, 0.0]) == "front"
    assert heading(0, 0, [0.3, 0.0, 0.0]) == "front"
    # lean 0.5 m · sin 10° = 0.087 m forward; 0.5 m/s back over ω₀ = √(9.81 / 0.5) = 4.43 /s is 0.113 m back
    assert heading(10, 0, [-0.5, 0.0, 0.0]) == "back"
    assert heading(10, 0, [-0.3, 0.0, 0.0]) == "front"
    assert heading(0, -10, [0.0, 0.0, 0.0]) == "left" and heading(0, 0, [0.0, -0.2, 0.0]) == "right"
    side = predicted_ground(root_quat_from_pitch_roll(math.radians(20), 0.0)[None], np.zeros((1, 3)))[0]
    np.testing.assert_allclose(side, [1.0, 0.0, 0.0], atol=1e-12)  # lying: across the long axis, a unit vector


def test_the_deployed_controller_chooses_as_eval_does_from_a_robot_state(biped):
    """FallController.choose_end_pose, given the estimator's RobotState at each fall's start, names the same
    candidate as eval's heading scorer on the simulator's state; sides restrict it; bad input is one line."""
    controller = FallController.load(EXAMPLE)
    n = 6
    env = eval_env(biped, n, poses=40)
    trials = ev.draw_trials(env, n, SEED)
    choice = PoseChoice("heading")
    chosen = choose_end_poses(env, trials, choice)
    names = [f"c{i}" for i in range(len(env.end_poses))]
    controller.add_end_poses({
        name: EndPose(joints=dict(zip(biped.joint_names, q.tolist())), root_quat=quat.tolist())
        for name, q, quat in zip(names, env.end_poses.joint_pos.double(), env.end_poses.root_quat.double())
    })  # fmt: skip
    model, lay = biped.mj_model(), Layout(biped)
    import mujoco

    data = mujoco.MjData(model)
    sides = ground_sides(env.end_poses.root_quat.double().numpy())
    for i in range(n):
        data.qpos[:], data.qvel[:] = trials.qpos[i].numpy(), trials.qvel[i].numpy()
        state = _estimate(data, lay)
        assert controller.choose_end_pose(state, names) == names[int(chosen.pose_ids[i])]
        back = controller.choose_end_pose(state, names, sides=["back"])
        assert sides[names.index(back)] == "back"
    controller.reset(back)  # a chosen name starts the fall
    assert controller.step(state).source == "policy"

    # the shipped artist poses: tipping forward lands prone, backward supine, to the left on the left side
    shipped = FallController.load(EXAMPLE)
    still = dict(joint_pos={n: 0.0 for n in shipped.joint_names}, joint_vel={n: 0.0 for n in shipped.joint_names})
    tilt = lambda p, r: root_quat_from_pitch_roll(math.radians(p), math.radians(r)).tolist()  # noqa: E731
    ground = {name: ground_sides(np.array(pose.resolve(shipped.joint_names, shipped.limits)[1]))[0]
              for name, pose in shipped.end_poses.items()}  # fmt: skip
    for pitch, roll, side in ((20, 0, "front"), (-20, 0, "back"), (0, -20, "left"), (0, 20, "right")):
        state = RobotState(base_quat=tilt(pitch, roll), base_ang_vel=[0.0] * 3, base_lin_vel=[0.0] * 3, **still)
        assert ground[shipped.choose_end_pose(state)] == side, (pitch, roll)
    with pytest.raises(DeployError, match=r"^choose_end_pose: unknown side 'under'; sides are front, back"):
        shipped.choose_end_pose(state, sides=["under"])
    with pytest.raises(DeployError, match=r"none of the 2 candidates lies on top; they lie on: front 2"):
        shipped.choose_end_pose(state, names=["prone_superman", "all_fours"], sides=["top"])


def test_eval_auto_restricted_to_back_poses_reports_against_random(tiny_run, tmp_path):
    """mode=eval eval.poses=auto eval.candidate_side=back: every chosen pose lies on the back, eval.json and
    eval.md carry the comparison with random assignment on the same falls (zero torque's impacts are the
    same falls, so unchanged), and the tables are the chosen poses'."""
    overrides = ["mode=eval", "eval.poses=auto", "eval.candidate_side=back", "eval.trials=6", "sim.num_envs=30"]
    r = fallkit_cli(f"checkpoint={tiny_run}", *overrides, "hydra.run.dir=eval", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((tmp_path / "eval" / "eval.json").read_text())
    c = data["end_pose_choice"]
    assert c["scorer"] == "critic" and c["candidate_side"] == ["back"] and c["chosen_sides"] == {"back": 1.0}
    assert 0 < c["candidate_count"] < 2000  # the back poses of the test split only
    zt = c["strategies"]["zero_torque"]
    assert zt["max_impact_force"]["diff"] == 0.0 and zt["fall_mean_impact_force"]["diff"] == 0.0
    pol = c["strategies"]["policy"]
    assert pol["trials"] == 6 and pol["mje"]["auto"] == pytest.approx(data["policy"]["mje"]["mean"])
    md = (tmp_path / "eval" / "eval.md").read_text()
    assert "## End pose chosen (auto) vs random assignment on the same falls" in md
    assert "end pose chosen by critic vs random, policy: MJE" in r.stdout
    trials = np.load(tmp_path / "eval" / "eval_trials.npz")
    np.testing.assert_array_equal(trials["random/zero_torque/max_impact_force"], trials["zero_torque/max_impact_force"])


def test_sim2sim_controller_makes_the_heading_choice_itself(tiny_run, tmp_path):
    """mode=sim2sim eval.poses=auto eval.scorer=heading: the exported controller chooses each fall's pose from
    its own state estimate, the same pose as mode=eval in every fall."""
    r = fallkit_cli(f"checkpoint={tiny_run}", "mode=sim2sim", "eval.poses=auto", "eval.scorer=heading",
                    "eval.candidates=artist", "eval.trials=4", "hydra.run.dir=s2s", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    c = json.loads((tmp_path / "s2s" / "sim2sim.json").read_text())["end_pose_choice"]
    assert c == {"scorer": "heading", "chosen_by": "the controller", "same_as_eval": 4, "of": 4}


def test_auto_without_a_checkpoint_for_the_critic_is_one_line_naming_the_fix(tmp_path):
    r = fallkit_cli("mode=eval", "eval.poses=auto", "eval.trials=2", "hydra.run.dir=x", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "eval.poses=auto with eval.scorer=critic" in r.stderr and "checkpoint=<run dir>" in r.stderr
    assert "eval.scorer=heading" in r.stderr


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["eval.candidate_side=back"], r"eval: candidate_side applies to poses=auto only .*add eval.poses=auto"),
        (
            ["eval.poses=auto", "eval.candidate_side=[back,under]"],
            r"eval.candidate_side: unknown side 'under'; sides are",
        ),
        (["eval.poses=auto", "eval.scorer=value"], r"eval.scorer: Input should be 'critic' or 'heading'"),
    ],
)
def test_bad_choice_settings_are_named(overrides, message):
    with pytest.raises(ConfigError, match=message):
        composed_config(*overrides)
