"""Left–right mirror augmentation (train.ppo.mirror): the derived map, the observation and action
mirrors, and the proof on the real simulator that they are the physics' own mirror image."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
from helpers import TINY, fallkit_cli
from tensordict import TensorDict

from fallkit.config import EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.mirror import observation_mirror
from fallkit.env.observations import actor_slices, critic_layout
from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.errors import ConfigError
from fallkit.poses.end_pose_set import EndPoseSet, random_end_poses
from fallkit.rl.models import GaussianPolicyNet, JointPrior
from fallkit.rl.mirror_samples import mirror_error
from fallkit.robots.mirror import mirror_name
from fallkit.robots.spec import ComponentSpec, JointSpec, make_robot_spec
from fallkit.sim import make_sim

QUIET = EnvConfig(noise={"scale": 0.0}, disturbances={"enabled": False})


@pytest.mark.parametrize(
    "name, partner",
    [("left_hip_roll", "right_hip_roll"), ("l_knee", "r_knee"), ("knee_L", "knee_R"), ("Left_Arm", "Right_Arm"),
     ("arm_right", "arm_left"), ("FL_calf_joint", "FR_calf_joint"), ("RR_foot", "RL_foot"), ("L1_coxa", "R1_coxa"),
     ("neck_yaw", "neck_yaw"), ("leftover", "leftover"), ("rear", "rear"), ("world", "world")],
)  # fmt: skip
def test_side_names_pair(name, partner):
    assert mirror_name(name) == partner
    assert mirror_name(partner) == name


def test_biped20_map_is_the_one_its_axes_give(biped):
    """Read off the MJCF by hand: pitch axes (0, 1, 0) on both sides reflect onto each other (+1); roll
    (1, 0, 0) and yaw (0, 0, 1) axes reflect onto their negation (−1), neck_yaw onto its own negation."""
    mirror = biped.mirror_map
    assert mirror is not None and biped.mirror_reason is None
    names = biped.joint_names
    for i, name in enumerate(names):
        partner, sign = names[mirror.joint_perm[i]], mirror.joint_sign[i]
        assert partner == name.replace("left", "@").replace("right", "left").replace("@", "right")
        assert sign == (-1 if any(k in name for k in ("roll", "yaw")) else 1), name
    m = biped.mj_model()
    bodies = {m.body(i).name: m.body(int(p)).name for i, p in enumerate(mirror.body_perm)}
    assert bodies["left_foot"] == "right_foot" and bodies["pelvis"] == "pelvis" and bodies["battery"] == "battery"
    # the free joint: position (x, −y, z), orientation (w, −x, y, −z); velocities (x, −y, z), (−x, y, −z)
    assert mirror.qpos_sign[:7].tolist() == [1, -1, 1, 1, -1, 1, -1]
    assert mirror.qvel_sign[:6].tolist() == [1, -1, 1, -1, 1, -1]


def test_go1_is_close_to_symmetric_but_not_exactly():
    pytest.importorskip("fallkit_go1", reason="install plugins/fallkit-go1 (scripts/setup.sh does)")
    from fallkit.robots import get_robot

    go1 = get_robot("go1")
    # its legs pair by name (FL/FR, RL/RR) and its joint axes mirror; its URDF's inertials do not:
    # the trunk's centre of mass lies 1.86 mm to the right of the mirror plane
    assert go1.mirror_map is None
    assert go1.mirror_reason == "at the nominal pose: body 'trunk': centre of mass differs from its own mirror image by 3.72 mm"
    with pytest.raises(ConfigError, match=r"^train.ppo.mirror=true: robot 'go1' is not left-right symmetric \(.*trunk"):
        observation_mirror(go1)


def test_mirroring_twice_is_the_identity(biped):
    mirror = observation_mirror(biped)
    gen = torch.Generator().manual_seed(0)
    for f in (mirror.actor, mirror.critic, mirror.action):
        x = torch.randn(5, len(f.index), generator=gen)
        assert not torch.equal(f(x), x)  # it does something
        assert torch.equal(f(f(x)), x)
    qpos, qvel = InitialStateSampler(biped).sample(3, gen)
    m = biped.mirror_map
    assert torch.equal(m.mirror_qpos(m.mirror_qpos(qpos)), qpos) and torch.equal(m.mirror_qvel(m.mirror_qvel(qvel)), qvel)


def critic_slices(spec, gravity: bool = False) -> list[tuple[str, slice]]:
    out, start = [], 0
    for name, size in critic_layout(spec, gravity=gravity):
        out.append((name, slice(start, start + size)))
        start += size
    return out


def mirrored_poses(spec, poses: EndPoseSet) -> EndPoseSet:
    """The poses followed by their mirror images (joints by the map, root orientation (w, −x, y, −z))."""
    m = spec.mirror_map
    quat = poses.root_quat * torch.tensor([1.0, -1.0, 1.0, -1.0])
    return EndPoseSet(spec.name, spec.joint_names, torch.cat((poses.joint_pos, m.mirror_joints(poses.joint_pos))),
                      torch.cat((poses.root_quat, quat)))  # fmt: skip


@pytest.mark.parametrize("gravity", [False, True], ids=["plain", "observe_gravity"])
def test_the_mirrored_fall_is_the_mirror_image_of_the_fall(biped, gravity):
    """The strongest check: the real simulator, a fall and its mirror image side by side.

    Worlds 0..n-1 start from drawn falling states with drawn end poses and take random actions a;
    worlds n..2n-1 start from the mirrored states with the mirrored end poses and take mirror(a).
    Every actor and critic observation of the second half must be the mirror of the first's, and the
    rewards equal. biped20's MJCF is exactly symmetric (the derivation finds no deviation at all), so
    what is left is floating point. Measured (these seeds, 30 steps = 0.6 s, every world landing):
    the first 5 steps are bit-exact, first contacts included; from the first step with several
    contacts on, MuJoCo's solver meets the mirrored contacts in another order, and the worlds differ
    by up to 5e-6 in qpos, 1.4e-4 in the actor observation, 1.5e-4 in the critic's velocities, 1.5e-3
    in its body accelerations (Δv / 20 ms, during impacts) and 3.4e-6 in the reward (each relative to
    max(1, |x|)), without growing over the fall. The bounds below are those, with room; a wrong rule is
    an error of order 1 (the next test).
    """
    n = 4
    mirror, m = observation_mirror(biped, gravity=gravity), biped.mirror_map
    poses = mirrored_poses(biped, random_end_poses(biped, n, torch.Generator().manual_seed(1)))
    cfg = QUIET.model_copy(update={"observe_gravity": gravity})
    env = FallEnv(biped, cfg, RewardConfig(), poses, make_sim(biped, 2 * n, "mujoco", body_state=True), seed=0)
    qpos, qvel = InitialStateSampler(biped).sample(n, torch.Generator().manual_seed(2))
    td = env.reset_to(torch.cat((qpos, m.mirror_qpos(qpos))), torch.cat((qvel, m.mirror_qvel(qvel))), torch.arange(2 * n))
    acc = dict(critic_slices(biped, gravity))["body_acc"]
    rest = torch.ones(len(mirror.critic.index), dtype=torch.bool)
    rest[acc] = False

    def errors(td) -> dict[str, float]:
        out = {}
        for key, f in (("actor", mirror.actor), ("critic", mirror.critic)):
            a, b = f(td["policy" if key == "actor" else "critic"][:n]), td["policy" if key == "actor" else "critic"][n:]
            out[key] = (a - b).abs() / a.abs().clamp(min=1.0)
        return {"actor": out["actor"].max().item(), "critic": out["critic"][:, rest].max().item(),
                "body_acc": out["critic"][:, acc].max().item()}  # fmt: skip

    at_reset = errors(td)
    assert max(at_reset.values()) < 1e-6, at_reset
    gen = torch.Generator().manual_seed(3)
    worst = dict.fromkeys(("actor", "critic", "body_acc", "reward", "qpos"), 0.0)
    landed = torch.zeros(2 * n, dtype=torch.bool)
    for _ in range(30):
        action = 0.5 * torch.randn(n, len(biped.joints), generator=gen)
        td = env.step(TensorDict({"action": torch.cat((action, mirror.action(action)))}, batch_size=[2 * n]))["next"]
        landed |= td["contact_force"].sum(-1) > 0
        reward = td["reward"].view(-1)
        state = env.sim.state.qpos.double()
        step = {**errors(td), "reward": ((reward[:n] - reward[n:]).abs() / reward[:n].abs().clamp(min=1.0)).max().item(),
                "qpos": (m.mirror_qpos(state[:n]) - state[n:]).abs().max().item()}  # fmt: skip
        worst = {k: max(v, step[k]) for k, v in worst.items()}
    assert env.num_unstable == 0
    assert landed.all()  # every world hit the floor: contacts are part of what was compared
    bounds = {"actor": 1e-3, "critic": 1e-3, "body_acc": 1e-2, "reward": 1e-4, "qpos": 1e-4}
    assert all(worst[k] < bounds[k] for k in bounds), worst


def test_a_mirror_with_one_wrong_sign_is_caught_by_the_simulator(biped):
    """The check above can fail: flip the sign of one joint (left_hip_roll's) in the action mirror and
    the mirrored world no longer mirrors the first (what a hand-written map with one slip would do)."""
    n = 2
    mirror, m = observation_mirror(biped), biped.mirror_map
    poses = mirrored_poses(biped, random_end_poses(biped, n, torch.Generator().manual_seed(1)))
    env = FallEnv(biped, QUIET, RewardConfig(), poses, make_sim(biped, 2 * n, "mujoco", body_state=True), seed=0)
    qpos, qvel = InitialStateSampler(biped).sample(n, torch.Generator().manual_seed(2))
    td = env.reset_to(torch.cat((qpos, m.mirror_qpos(qpos))), torch.cat((qvel, m.mirror_qvel(qvel))), torch.arange(2 * n))
    wrong = mirror.action.sign.clone()
    wrong[biped.joint_names.index("left_hip_roll")] *= -1
    action = 0.5 * torch.randn(n, len(biped.joints), generator=torch.Generator().manual_seed(3))
    for _ in range(5):
        image = action[:, mirror.action.index] * wrong
        td = env.step(TensorDict({"action": torch.cat((action, image))}, batch_size=[2 * n]))["next"]
    assert (mirror.critic(td["critic"][:n]) - td["critic"][n:]).abs().max() > 0.1


# ---- robots that are not symmetric ------------------------------------------------------------

_TOY = """
<mujoco>
  <compiler angle="radian" autolimits="true"/>
  <worldbody>
    <body name="torso">
      <geom type="box" size="0.1 0.15 0.1" mass="{torso_mass}" pos="0 {torso_y} 0"/>
      <body name="left_leg" pos="0 0.1 -0.1">
        <joint name="left_roll" axis="1 0 0" range="-0.5 1.0"/>
        <joint name="left_pitch" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="1"/>
      </body>
      <body name="right_leg" pos="0 {right_y} -0.1">
        <joint name="{right_roll}" axis="{right_roll_axis}" range="{right_roll_range}"/>
        <joint name="right_pitch" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.03" mass="{right_mass}"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""
_SYMMETRIC = dict(torso_mass=5, torso_y=0, right_y=-0.1, right_roll="right_roll", right_roll_axis="1 0 0",
                  right_roll_range="-1.0 0.5", right_mass=1)  # fmt: skip


def toy_robot(tmp_path, nominal=None, weights=(1.0, 1.0), **changes):
    xml = _TOY.format(**{**_SYMMETRIC, **changes})
    path = tmp_path / f"toy_{abs(hash(xml))}.xml"
    path.write_text(xml)
    joints = ["left_roll", "left_pitch", changes.get("right_roll", "right_roll"), "right_pitch"]
    return make_robot_spec(
        "toy", mjcf=path, root_body="torso",
        joints=[JointSpec(name=j, kp=10, kd=1, torque_limit=5) for j in joints],
        components={"torso": ComponentSpec(bodies=["torso"], weight=1.0),
                    "left": ComponentSpec(bodies=["left_leg"], weight=weights[0]),
                    "right": ComponentSpec(bodies=["right_leg"], weight=weights[1])},
        nominal_pose=nominal or {"left_pitch": 0.2, "right_pitch": 0.2},
    )  # fmt: skip


def test_the_toy_robot_is_symmetric_as_written(tmp_path):
    """The baseline of the cases below: each of them changes one thing of this symmetric robot."""
    toy = toy_robot(tmp_path)
    assert toy.mirror_reason is None
    assert toy.mirror_map.joint_sign.tolist() == [-1, 1, -1, 1] and toy.mirror_map.joint_perm.tolist() == [2, 3, 0, 1]


@pytest.mark.parametrize(
    "changes, reason",
    [
        (dict(right_roll_axis="0 0 1"), "joint 'left_roll': its axis (1, 0, 0) reflects to (-1, 0, 0), but its partner 'right_roll' turns about (0, 0, 1)"),
        (dict(right_roll_axis="1 0 0.01"), "joint 'left_roll': its axis"),
        (dict(right_roll="other_roll"), "joint 'left_roll' has no mirror partner 'right_roll'"),
        (dict(right_roll_range="-1.0 0.6"), "joint 'left_roll': range (-0.5, 1) is not the mirror (-0.6, 1) of 'right_roll''s"),
        (dict(right_y=-0.101), "body 'right_leg': position differs from the mirror image of 'left_leg''s by 1 mm"),
        (dict(right_mass=1.01), "body 'right_leg': mass differs from the mirror image of 'left_leg''s by 0.01 (relative)"),
        (dict(torso_y=0.002), "body 'torso': centre of mass differs from its own mirror image by 4 mm"),
        (dict(nominal={"left_pitch": 0.2, "right_pitch": 0.3}), "nominal_pose is not mirror-symmetric: left_pitch = 0.2 rad"),
        (dict(weights=(1.0, 2.0)), "components 'left' and 'right' mirror each other but weigh 1 and 2"),
    ],
)  # fmt: skip
def test_an_asymmetric_robot_has_no_mirror_and_mirror_true_says_why(tmp_path, changes, reason):
    toy = toy_robot(tmp_path, **changes)
    assert toy.mirror_map is None
    assert reason in toy.mirror_reason, toy.mirror_reason
    with pytest.raises(ConfigError) as info:
        observation_mirror(toy)
    message = str(info.value)
    assert "\n" not in message and message.startswith("train.ppo.mirror=true: robot 'toy' is not left-right symmetric")
    assert reason in message


# ---- PPO --------------------------------------------------------------------------------------


def test_mirror_error_is_zero_exactly_for_a_symmetric_policy(biped):
    """The diagnostic measures what it says: the joint prior alone (hold and seek) is mirror-equivariant
    (its nominal pose is symmetric), so π(mirror(o)) = mirror(π(o)); a random residual is not."""
    mirror = observation_mirror(biped)
    obs = torch.randn(64, len(mirror.actor.index), generator=torch.Generator().manual_seed(0))
    obs[:, actor_slices(biped)["blend"]] = torch.rand(64, 1)  # u(t) in [0, 1]
    for seek in (False, True):
        net = GaussianPolicyNet(obs.shape[1], len(biped.joints), [16], 0.3, JointPrior(biped, 0.5, seek=seek, fade=True))
        torch.nn.init.zeros_(net.mean[-1].weight)
        with torch.no_grad():
            assert mirror_error(mirror, net(obs)[0], net(mirror.actor(obs))[0]).item() < 1e-10
    torch.nn.init.normal_(net.mean[-1].weight)
    with torch.no_grad():
        assert mirror_error(mirror, net(obs)[0], net(mirror.actor(obs))[0]).item() > 1e-3


def test_tiny_training_with_mirror_logs_the_mirror_loss(tmp_path):
    r = fallkit_cli(*TINY, "train.iterations=3", "train.ppo.mirror=true", "hydra.run.dir=run", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = list(csv.DictReader((tmp_path / "run" / "metrics.csv").open()))
    assert len(rows) == 3
    losses = [float(row["mirror_loss"]) for row in rows]
    assert all(math.isfinite(x) and x >= 0 for x in losses) and losses[-1] > 0, losses
    assert np.isfinite([float(row["loss_objective"]) for row in rows]).all()


def test_mirror_on_a_robot_without_a_mirror_map_is_a_one_line_error(tmp_path):
    pytest.importorskip("fallkit_go1", reason="install plugins/fallkit-go1 (scripts/setup.sh does)")
    r = fallkit_cli("robot=go1", *TINY, "train.ppo.mirror=true", "hydra.run.dir=run", cwd=tmp_path)
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "train.ppo.mirror=true: robot 'go1' is not left-right symmetric" in lines[0], lines
    assert "centre of mass differs from its own mirror image by 3.72 mm" in lines[0]
