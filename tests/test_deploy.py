"""The deploy controller (issue 16): it rebuilds the environment's observation and the policy's
setpoints from what a robot's estimator provides, step for step, for a biped and a quadruped."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import TINY_RUN, composed_config

from fallkit.deploy import DeployError, EndPose, FallController, RobotState
from fallkit.rotations import quat_rotate_inverse

# full-length falls (the parity runs 3 s), a 32-wide actor so the last layer stands out
TINY = [*(o for o in TINY_RUN if not o.startswith(("env.episode_length", "reward.blend_time"))),
        "train.actor_hidden=[32,32]", "train.critic_hidden=[16,16]", "train.iterations=1"]  # fmt: skip
config = composed_config


def exported(tmp_path: Path, *overrides: str) -> tuple[Path, Path]:
    """A 1-iteration policy whose MLP is made to matter (its last layer scaled up: every part of the
    observation then moves the action), exported. (run dir, export dir)"""
    from fallkit.rl.checkpoint import load_checkpoint, save_checkpoint
    from fallkit.rl.export import run_export
    from fallkit.rl.trainer import Trainer

    run = tmp_path / "run"
    last = Trainer(config(*TINY, *overrides), run).run()
    ckpt = load_checkpoint(last)
    g = torch.Generator().manual_seed(0)
    for k, v in ckpt["actor"].items():
        if ".mean." in k and v.is_floating_point() and v.dim() == 2 and v.shape[0] != 32:  # the last layer
            ckpt["actor"][k] = torch.randn(v.shape, generator=g) * 0.1
    ckpt.pop("path")
    save_checkpoint(last, ckpt)
    out = tmp_path / "export"
    out.mkdir()
    run_export(config(*TINY, *overrides, f"checkpoint={run}", "mode=export"), out)
    return run, out


def _parity(run: Path, export: Path, poses: str | None = None, worlds: int = 3) -> int:
    """Full falls in fallkit's env (noise and disturbances off) with the torch policy acting; at every
    step the controller, fed the state as an estimator would give it (joints by name, shuffled),
    must give the env's observation and the setpoints of the policy's action to 1e-5."""
    from fallkit.env.build import make_env
    from fallkit.eval.evaluate import eval_run_config
    from fallkit.rl.policy import load_policy

    policy = load_policy(run)
    cfg = eval_run_config(policy.config, None)
    env = make_env(cfg, policy.spec, split="test", seed=5, num_envs=worlds, poses=poses)
    names = policy.spec.joint_names
    shuffled = list(np.random.default_rng(0).permutation(names))
    controllers = [FallController.load(export, joint_order=shuffled) for _ in range(worlds)]
    td = env.reset()
    for i, c in enumerate(controllers):
        pose = int(env.end_pose_ids[i])
        c.reset(EndPose(joints=dict(zip(names, env.end_poses.joint_pos[pose].tolist())),
                        root_quat=env.end_poses.root_quat[pose].tolist()))  # fmt: skip
    compared = 0
    for _ in range(env.max_steps):
        with torch.no_grad():
            td = policy.module(td)
        setpoint = env.setpoint(td["action"])
        st = env.sim.state
        lin_vel = quat_rotate_inverse(st.root_quat, st.root_lin_vel)
        for i, c in enumerate(controllers):
            state = RobotState(
                base_quat=st.root_quat[i].tolist(), base_ang_vel=st.root_ang_vel[i].tolist(),
                base_lin_vel=lin_vel[i].tolist(),
                joint_pos={n: float(st.joint_pos[i, names.index(n)]) for n in shuffled},
                joint_vel={n: float(st.joint_vel[i, names.index(n)]) for n in reversed(shuffled)},
            )  # fmt: skip
            command = c.step(state)
            np.testing.assert_allclose(c.observation[0], td["policy"][i].numpy(), atol=1e-5, rtol=0)
            by_name = dict(zip(shuffled, command.setpoint))
            np.testing.assert_allclose([by_name[n] for n in names], setpoint[i].numpy(), atol=1e-5, rtol=0)
            compared += 1
        td = env.step(td).get("next")
    return compared


@pytest.mark.parametrize("options", [[], ["env.observe_gravity=true"]], ids=["plain", "observe_gravity"])
def test_controller_equals_env_and_policy_over_full_falls_biped20(tmp_path, options):
    run, export = exported(tmp_path, "robot=biped20", *options)
    assert _parity(run, export) == 3 * 150  # 3 falls of 3 s at 50 Hz
    meta = json.loads((export / "policy.json").read_text())
    assert meta["clip_setpoints"] is True and meta["base_body"]
    assert len(json.loads((export / "end_poses.json").read_text())) == 10  # biped20's artist poses, settled


def test_export_records_the_checkpoint_as_an_absolute_path(tmp_path, monkeypatch):
    """checkpoint=<relative path>: policy.json still says which file the policy came from, from anywhere."""
    from fallkit.rl.export import run_export

    run, _ = exported(tmp_path, "robot=biped20")
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "export_relative"
    out.mkdir()
    run_export(config(*TINY, "robot=biped20", "checkpoint=run", "mode=export"), out)
    recorded = Path(json.loads((out / "policy.json").read_text())["checkpoint"])
    assert recorded.is_absolute() and recorded.parent.parent == run.resolve()


def test_controller_equals_env_and_policy_over_full_falls_go1(tmp_path):
    pytest.importorskip("fallkit_go1", reason="install plugins/fallkit-go1 (scripts/setup.sh does)")
    from fallkit.api import get_robot
    from fallkit.config import DatasetConfig
    from fallkit.poses.dataset import save_dataset
    from fallkit.poses.generator import EndPoseGenerator, to_dataset

    spec = get_robot("go1")
    cfg = DatasetConfig(train=16, test=8, num_worlds=32, bands=2, sectors=2)
    poses = save_dataset(tmp_path / "go1.npz", to_dataset(spec, EndPoseGenerator(spec, cfg).run(progress=False), cfg, "mujoco"))
    run, export = exported(tmp_path, "robot=go1", f"env.poses={poses}")
    assert _parity(run, export, poses=str(poses)) == 3 * 150
    assert not (export / "end_poses.json").exists()  # go1 ships no artist poses


# ---- inputs a robot engineer gets wrong --------------------------------------------------------------


@pytest.fixture(scope="module")
def biped_run(tmp_path_factory):
    return exported(tmp_path_factory.mktemp("deploy"), "robot=biped20")


@pytest.fixture(scope="module")
def biped_export(biped_run):
    return biped_run[1]


def _state(c: FallController, **change) -> RobotState:
    fields = dict(base_quat=[1.0, 0.0, 0.0, 0.0], base_ang_vel=[0.0] * 3, base_lin_vel=[0.0] * 3,
                  joint_pos={n: 0.0 for n in c.joint_names}, joint_vel={n: 0.0 for n in c.joint_names})  # fmt: skip
    return RobotState(**{**fields, **change})


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(base_quat=[0.5, 0.0, 0.0, 0.0]), r"state.base_quat: norm 0.5 is not 1"),
        (dict(base_ang_vel=[0.0, float("nan"), 0.0]), r"state.base_ang_vel\[1\] is nan \(not finite\)"),
        (dict(base_lin_vel=[0.0, 0.0]), r"state.base_lin_vel: expected 3 numbers, got 2"),
        (dict(joint_pos={"neck_yaw": 0.0}), r"state.joint_pos: missing joints \["),
        (dict(joint_vel=np.zeros(3)), r"state.joint_vel: expected 20 values in the controller's joint_order, got 3"),
    ],
)
def test_bad_states_are_one_clear_error(biped_export, change, message):
    c = FallController.load(biped_export)
    c.reset("prone_shield_head")
    with pytest.raises(DeployError, match=message):
        c.step(_state(c, **change))


def test_nan_joint_is_named_and_end_poses_are_checked(biped_export):
    c = FallController.load(biped_export)
    c.reset("prone_shield_head")
    bad = {n: 0.0 for n in c.joint_names} | {"left_knee": float("nan")}
    with pytest.raises(DeployError, match="state.joint_pos: joint 'left_knee' is not finite"):
        c.step(_state(c, joint_pos=bad))
    with pytest.raises(DeployError, match="no end pose named 'nosuch' in the export; its end poses: "):
        c.reset("nosuch")
    joints = {n: 0.0 for n in c.joint_names}
    with pytest.raises(DeployError, match="EndPose.joints: unknown joint 'left_kne'; did you mean 'left_knee'"):
        c.reset(EndPose(joints={**joints, "left_kne": 0.1}, ground="back"))
    with pytest.raises(DeployError, match=r"EndPose.joints.left_knee = 9 rad is outside its limits"):
        c.reset(EndPose(joints={**joints, "left_knee": 9.0}, ground="back"))
    with pytest.raises(DeployError, match="EndPose: ground=back disagrees with pitch"):
        c.reset(EndPose(joints=joints, ground="back", pitch=1.5))
    c.reset(EndPose(joints=joints, ground="back"))
    from fallkit.poses.artist import artist_file
    from fallkit.robots import get_robot

    pose = c.pose_from_file(artist_file(get_robot("biped20")), "fetal_left")
    assert set(pose.joints) == set(c.joint_names)


def test_missing_estimate_holds_or_damps_and_step_reuses_its_arrays(biped_export):
    hold = FallController.load(biped_export)
    hold.reset("prone_shield_head")
    first = hold.step(_state(hold))
    setpoint, arrays = first.setpoint.copy(), (first.setpoint, first.kp, hold.observation, hold.action)
    missed = hold.step(None)
    assert missed.source == "hold" and np.array_equal(missed.setpoint, setpoint) and (missed.kp > 0).all()
    assert hold.missed == 1 and hold.steps == 2
    again = hold.step(_state(hold))
    assert again.source == "policy" and all(a is b for a, b in zip(arrays, (again.setpoint, again.kp, hold.observation,
                                                                             hold.action)))  # fmt: skip
    damp = FallController.load(biped_export, on_missing="damp")
    damp.reset("prone_shield_head")
    damp.step(_state(damp))
    out = damp.step(None)
    assert out.source == "damp" and (out.kp == 0).all() and (out.kd > 0).all()
    assert damp.step(_state(damp)).kp.min() > 0  # the gains come back with the estimate


def test_a_missing_or_foreign_export_is_named(biped_export, tmp_path):
    with pytest.raises(DeployError, match=r"policy.json not found: export the policy with python -m fallkit mode=export"):
        FallController.load(tmp_path)
    (tmp_path / "policy.onnx").write_bytes((biped_export / "policy.onnx").read_bytes())
    meta = json.loads((biped_export / "policy.json").read_text())
    del meta["pd_gains"]
    (tmp_path / "policy.json").write_text(json.dumps(meta))
    with pytest.raises(DeployError, match=r"policy.json: lacks \['pd_gains'\]; export the policy with this fallkit"):
        FallController.load(tmp_path)
    (tmp_path / "policy.json").write_text("{not json")
    with pytest.raises(DeployError, match=r"policy.json: not a policy.json"):
        FallController.load(tmp_path)


def test_the_shipped_example_runs(biped):
    example = Path(__file__).parents[1] / "examples" / "biped20_quick"
    c = FallController.load(example)
    assert c.meta["robot"] == "biped20" and c.meta["model_hash"] == biped.model_hash()
    assert len(c.end_poses) == 10
    c.reset("prone_shield_head")
    state = RobotState(base_quat=[0.9, 0.0, 0.43589, 0.0], base_ang_vel=[0.0, 1.0, 0.0], base_lin_vel=[0.3, 0.0, -0.2],
                       joint_pos={n: 0.0 for n in c.joint_names}, joint_vel={n: 0.0 for n in c.joint_names})  # fmt: skip
    for _ in range(10):
        command = c.step(state)
    assert command.source == "policy" and np.isfinite(command.setpoint).all()
    lo, hi = c.limits[:, 0], c.limits[:, 1]
    assert ((command.setpoint >= lo - 1e-9) & (command.setpoint <= hi + 1e-9)).all()


def test_deploy_imports_neither_torch_nor_mujoco():
    code = ("import sys, fallkit.deploy; heavy = [m for m in ('torch', 'mujoco', 'hydra', 'torchrl', 'tensordict') "
            "if m in sys.modules]; print(heavy); sys.exit(bool(heavy))")  # fmt: skip
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


def test_mode_sim2sim_agrees_with_mode_eval(biped_run, tmp_path):
    """The exported controller in a plain MuJoCo loop (its own PD, one MjData) against the batch
    evaluation of the same falls: every metric's paired mean difference within its 95 % interval."""
    r = subprocess.run([sys.executable, "-m", "fallkit", "mode=sim2sim", f"checkpoint={biped_run[0]}", "eval.trials=24",
                        f"hydra.run.dir={tmp_path}"], capture_output=True, text=True, timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((tmp_path / "sim2sim.json").read_text())
    assert set(report["metrics"]) >= {"max_impact_force", "fall_mean_impact_force", "mroe", "mje"}
    assert report["all_agree"], (tmp_path / "sim2sim.md").read_text()
    assert "All metrics agree within sampling noise." in r.stdout


def test_setting_weights_of_a_policy_without_sensitivity_inputs_is_a_one_line_error(biped_export):
    with pytest.raises(DeployError, match=r"trained without env.sensitivity_inputs, its weights are fixed"):
        FallController.load(biped_export).set_sensitivity({"head": 8.0})
