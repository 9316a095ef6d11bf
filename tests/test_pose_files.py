"""End-pose files: the dataset format and the artist pose YAML (paper Sec. V-B "Data")."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from fallkit.errors import PoseFileError
from fallkit.poses import load_end_poses
from fallkit.poses.artist import artist_file, ground_side, read_artist_poses, root_quat_from_pitch_roll
from fallkit.poses.dataset import FORMAT, PoseDataset, load_dataset, read_meta, save_dataset
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.rotations import gravity_in_frame


def _dataset(spec, n: int = 200, test: int = 20, seed: int = 0) -> PoseDataset:
    """A dataset-shaped set of poses (the format test does not need physics)."""
    rng = np.random.default_rng(seed)
    lim = spec.joint_limits
    q = rng.normal(size=(n, 4))
    split = np.array(["train"] * (n - test) + ["test"] * test)
    return PoseDataset(
        robot=spec.name,
        model_hash=spec.model_hash(),
        joint_names=list(spec.joint_names),
        joint_pos=rng.uniform(lim[:, 0], lim[:, 1], size=(n, len(lim))).astype(np.float32),
        root_quat=(q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
        root_height=rng.uniform(0.05, 0.2, n).astype(np.float32),
        split=split,
        bin=rng.integers(0, 48, n).astype(np.int16),
        meta={"seed": seed, "generator": {"train": n - test, "test": test}},
    )


def _other_robot(spec, tmp_path: Path, name: str = "biped20_heavy"):
    """biped20 with a heavier head: another model hash."""
    from fallkit.api import make_robot_spec

    xml = tmp_path / f"{name}.xml"
    text = spec.mjcf.read_text()
    assert 'mass="0.6"' in text
    xml.write_text(text.replace('mass="0.6"', 'mass="0.9"', 1))
    fields = spec.model_dump(exclude={"name", "mjcf"})
    return make_robot_spec(name, mjcf=xml, **fields)


# ---- datasets ----------------------------------------------------------------------------------


def test_dataset_round_trip_keeps_arrays_and_provenance(biped, tmp_path):
    ds = _dataset(biped)
    path = save_dataset(tmp_path / "d.npz", ds)
    back = load_dataset(path)
    for k in ("joint_pos", "root_quat", "root_height", "split", "bin"):
        assert np.array_equal(getattr(back, k), getattr(ds, k)), k
    assert back.joint_names == biped.joint_names
    meta = read_meta(path)
    assert meta["format"] == FORMAT and meta["version"] == 1
    assert meta["robot"] == "biped20" and meta["model_hash"] == biped.model_hash() and meta["seed"] == 0

    train = load_end_poses(path, biped, "train")
    test = load_end_poses(path, biped, split="test")
    assert isinstance(train, EndPoseSet) and len(train) == 180 and len(test) == 20
    assert train.joint_names == biped.joint_names and train.robot == "biped20"
    assert torch.equal(train.joint_pos, torch.from_numpy(ds.joint_pos[:180]))
    assert torch.equal(test.root_quat, torch.from_numpy(ds.root_quat[180:]))


def test_fraction_subsets_are_deterministic_nested_prefixes(biped, tmp_path):
    path = save_dataset(tmp_path / "d.npz", _dataset(biped, n=1020, test=20))
    full = load_end_poses(path, biped, "train")
    sizes = {f: len(load_end_poses(path, biped, "train", fraction=f)) for f in (0.01, 0.06, 0.5, 1.0)}
    assert sizes == {0.01: 10, 0.06: 60, 0.5: 500, 1.0: 1000}
    six = load_end_poses(path, biped, "train", fraction=0.06)
    assert torch.equal(six.joint_pos, full.joint_pos[:60])  # nested: 1 % ⊂ 6 % ⊂ 100 %
    assert torch.equal(six.joint_pos, load_end_poses(path, biped, "train", fraction=0.06).joint_pos)
    assert len(load_end_poses(path, biped, "test", fraction=0.001)) == 1  # at least one pose
    for bad in (0.0, -0.5, 1.5):
        with pytest.raises(PoseFileError, match=r"fraction must be in \(0, 1\]"):
            load_end_poses(path, biped, "train", fraction=bad)
    with pytest.raises(PoseFileError, match="split must be one of"):
        load_end_poses(path, biped, "validation")


def test_dataset_for_another_robot_or_model_is_refused(biped, tmp_path):
    path = save_dataset(tmp_path / "d.npz", _dataset(biped))
    other = _other_robot(biped, tmp_path)
    assert other.model_hash() != biped.model_hash()
    with pytest.raises(PoseFileError) as err:
        load_end_poses(path, other)
    msg = str(err.value)
    assert str(path) in msg and "'biped20'" in msg and "'biped20_heavy'" in msg
    assert biped.model_hash() in msg and other.model_hash() in msg and "mode=poses robot=biped20_heavy" in msg
    # same robot name, changed model: "changed since"
    renamed = _other_robot(biped, tmp_path, name="biped20")
    with pytest.raises(PoseFileError, match="changed since"):
        load_end_poses(path, renamed)
    # a robot with the same body under another name (a sensitivity variant) may use it
    from fallkit.api import get_robot

    battery = get_robot("biped20_battery")
    assert battery.model_hash() == biped.model_hash()
    assert len(load_end_poses(path, battery)) == 180


def test_broken_dataset_files_are_clear_errors(biped, tmp_path):
    with pytest.raises(PoseFileError, match="not found"):
        load_end_poses(tmp_path / "missing.npz", biped)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(PoseFileError, match="not a fallkit pose dataset"):
        load_end_poses(junk, biped)
    ds = _dataset(biped)
    path = save_dataset(tmp_path / "v9.npz", ds)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    meta["version"] = 9
    arrays["meta"] = np.array(json.dumps(meta))
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    with pytest.raises(PoseFileError, match="version 9 is not supported"):
        load_end_poses(path, biped)
    with pytest.raises(PoseFileError, match="unknown end-pose source"):
        load_end_poses(tmp_path / "poses.csv", biped)
    with pytest.raises(PoseFileError, match="test"):
        load_end_poses(save_dataset(tmp_path / "no_test.npz", _dataset(biped, n=30, test=0)), biped, "test")


def test_default_dataset_is_shipped_for_biped20(biped):
    meta = read_meta(Path(biped.mjcf).parent / "biped20_poses.npz")
    assert meta["robot"] == "biped20" and meta["model_hash"] == biped.model_hash()
    assert meta["generator"]["train"] == 24000 and meta["generator"]["test"] == 2000
    assert meta["stats"]["uniform_within_tolerance"]
    train = load_end_poses("default", biped)
    assert len(train) == 24000 and len(load_end_poses("default", biped, "test")) == 2000
    lim = torch.as_tensor(biped.joint_limits, dtype=torch.float32)
    assert ((train.joint_pos >= lim[:, 0] - 1e-6) & (train.joint_pos <= lim[:, 1] + 1e-6)).all()
    assert torch.allclose(train.root_quat.norm(dim=1), torch.ones(len(train)), atol=1e-5)
    # the sensitivity variant with the same body finds and uses it
    from fallkit.api import get_robot

    assert len(load_end_poses("default", get_robot("biped20_battery"))) == 24000


def test_default_dataset_missing_says_how_to_make_one(biped, tmp_path):
    other = _other_robot(biped, tmp_path)
    with pytest.raises(PoseFileError, match=r"python -m fallkit mode=poses robot=biped20_heavy"):
        load_end_poses("default", other)


# ---- artist poses --------------------------------------------------------------------------------


def test_shipped_artist_poses_settle_near_their_authored_orientation(biped):
    path = artist_file(biped)
    poses = read_artist_poses(path, biped)
    assert len(poses) == 10 and len({p.name for p in poses}) == 10
    lim = biped.joint_limits
    for p in poses:
        assert ((p.joint_pos >= lim[:, 0]) & (p.joint_pos <= lim[:, 1])).all(), p.name
    assert {p.ground for p in poses} >= {"front", "back", "left", "right", "bottom"}
    settled = load_end_poses("artist", biped)
    assert settled.names == [p.name for p in poses] and len(settled) == 10
    for p, q in zip(poses, settled.root_quat):
        assert ground_side(q) == p.ground, p.name  # still on the side it was authored on
        tilt = math.degrees(math.acos(float((gravity_in_frame(torch.tensor(p.root_quat)) * gravity_in_frame(q.double())).sum())))
        assert tilt < 10.0, (p.name, tilt)


def test_pitch_roll_words_and_numbers_agree():
    assert ground_side(root_quat_from_pitch_roll(math.radians(90), 0)) == "front"
    assert ground_side(root_quat_from_pitch_roll(math.radians(-90), 0)) == "back"
    assert ground_side(root_quat_from_pitch_roll(0, math.radians(90))) == "right"
    assert ground_side(root_quat_from_pitch_roll(0, math.radians(-90))) == "left"
    assert ground_side(root_quat_from_pitch_roll(0, 0)) == "bottom"
    assert ground_side(root_quat_from_pitch_roll(math.pi, 0)) == "top"
    # roll turns about the world forward axis after the pitch: prone, then rolled onto the right side
    assert ground_side(root_quat_from_pitch_roll(math.radians(90), math.radians(80))) == "right"


JOINTS_DEG = {
    "neck_yaw": 0, "neck_pitch": 0,
    "left_shoulder_pitch": 0, "left_shoulder_roll": 10, "left_shoulder_yaw": 0, "left_elbow": -20,
    "right_shoulder_pitch": 0, "right_shoulder_roll": -10, "right_shoulder_yaw": 0, "right_elbow": -20,
    "left_hip_yaw": 0, "left_hip_roll": 0, "left_hip_pitch": 0, "left_knee": 5, "left_ankle_pitch": 0,
    "right_hip_yaw": 0, "right_hip_roll": 0, "right_hip_pitch": 0, "right_knee": 5, "right_ankle_pitch": 0,
}  # fmt: skip


def _pose_file(tmp_path: Path, joints: dict | None = None, root: str = "{ground: back}", unit: str = "unit: deg",
               extra: str = "") -> Path:  # fmt: skip
    joints = JOINTS_DEG if joints is None else joints
    lines = "\n".join(f"      {k}: {v}" for k, v in joints.items())
    text = f"robot: biped20\n{unit}\nposes:\n  - name: lying\n    root: {root}\n{extra}    joints:\n{lines}\n"
    path = tmp_path / "poses.yaml"
    path.write_text(text)
    return path


def _line_of(path: Path, needle: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if needle in line)


def test_a_valid_pose_file_with_mixed_units(biped, tmp_path):
    path = _pose_file(tmp_path, {**JOINTS_DEG, "left_knee": "'0.5 rad'", "right_knee": "'30°'"}, root="{ground: back, pitch: -90}")
    (pose,) = read_artist_poses(path, biped)
    names = biped.joint_names
    assert pose.joint_pos[names.index("left_knee")] == pytest.approx(0.5)
    assert pose.joint_pos[names.index("right_knee")] == pytest.approx(math.radians(30))
    assert pose.joint_pos[names.index("left_elbow")] == pytest.approx(math.radians(-20))
    rad = _pose_file(tmp_path, {k: math.radians(v) for k, v in JOINTS_DEG.items()}, unit="unit: rad", root="{ground: back, pitch: -1.5708}")
    (pose_rad,) = read_artist_poses(rad, biped)
    assert np.allclose(pose_rad.joint_pos, np.radians(list(JOINTS_DEG.values())))
    settled = load_end_poses(path, biped)
    assert len(settled) == 1 and ground_side(settled.root_quat[0]) == "back"


def test_unknown_joint_names_file_line_and_a_suggestion(biped, tmp_path):
    joints = {**JOINTS_DEG}
    joints["left_kne"] = joints.pop("left_knee")
    path = _pose_file(tmp_path, joints)
    with pytest.raises(PoseFileError) as err:
        read_artist_poses(path, biped)
    msg = str(err.value)
    assert msg.startswith(f"{path}:{_line_of(path, 'left_kne:')}:")
    assert "unknown joint 'left_kne'" in msg and "did you mean 'left_knee'" in msg


def test_value_outside_limits_says_by_how_much(biped, tmp_path):
    path = _pose_file(tmp_path, {**JOINTS_DEG, "left_knee": 150})
    with pytest.raises(PoseFileError) as err:
        read_artist_poses(path, biped)
    msg = str(err.value)
    hi = math.degrees(biped.joint_limits[biped.joint_names.index("left_knee"), 1])
    assert msg.startswith(f"{path}:{_line_of(path, 'left_knee:')}:") and "joints.left_knee" in msg
    assert "above the upper limit" in msg and f"by {150 - hi:.3g} deg" in msg
    path = _pose_file(tmp_path, {**JOINTS_DEG, "right_elbow": "'0.3 rad'"})
    with pytest.raises(PoseFileError, match=r"0\.3 rad is above the upper limit 0 rad by 0\.3 rad"):
        read_artist_poses(path, biped)


@pytest.mark.parametrize(
    "change, pattern",
    [
        (dict(unit=""), r":1: missing field 'unit'"),
        (dict(unit="unit: grad"), r":2: unit: must be deg or rad"),
        (dict(root="{pitch: 10}"), r":5: poses\[0\] 'lying'.root: missing field 'ground'"),
        (dict(root="{ground: sideways}"), r"root.ground: must be one of front, back, left, right, bottom, top"),
        (dict(root="{ground: front, pitch: -90}"), r"ground: front disagrees with pitch -90 deg.*back side"),
        (dict(root="{ground: back, yaw: 3}"), r"unknown key 'yaw'; allowed: ground, pitch, roll"),
        (dict(root="{ground: back, pitch: ninety}"), r"root.pitch: expected an angle"),
        (dict(extra="    extra_field: 1\n"), r":6: poses\[0\] 'lying': unknown key 'extra_field'"),
    ],
)
def test_pose_file_errors_name_the_line_and_key(biped, tmp_path, change, pattern):
    path = _pose_file(tmp_path, **change)
    with pytest.raises(PoseFileError) as err:
        read_artist_poses(path, biped)
    assert re.search(pattern, str(err.value)), str(err.value)
    assert str(err.value).startswith(str(path))


def test_missing_joints_and_fields(biped, tmp_path):
    joints = {k: v for k, v in JOINTS_DEG.items() if k != "right_knee"}
    with pytest.raises(PoseFileError, match=r"joints: missing joints right_knee"):
        read_artist_poses(_pose_file(tmp_path, joints), biped)
    path = tmp_path / "nojoints.yaml"
    path.write_text("unit: deg\nposes:\n  - name: a\n    root: {ground: back}\n")
    with pytest.raises(PoseFileError, match=rf"{re.escape(str(path))}:3: poses\[0\] 'a': missing field 'joints'"):
        read_artist_poses(path, biped)
    path.write_text("unit: deg\nposes:\n  - root: {ground: back}\n")
    with pytest.raises(PoseFileError, match=r":3: poses\[0\]: missing field 'name'"):
        read_artist_poses(path, biped)
    path.write_text("unit: deg\n")
    with pytest.raises(PoseFileError, match=r"missing field 'poses'"):
        read_artist_poses(path, biped)


def test_malformed_yaml_and_duplicates_name_the_line(biped, tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("unit: deg\nposes:\n  - name: a\n    joints: {left_knee: 3\n    root: [\n")
    with pytest.raises(PoseFileError, match=rf"{re.escape(str(path))}:\d+: malformed YAML"):
        read_artist_poses(path, biped)
    good = _pose_file(tmp_path)
    text = good.read_text().replace("      left_knee: 5\n", "      left_knee: 5\n      left_knee: 6\n")
    good.write_text(text)
    with pytest.raises(PoseFileError, match=rf":{_line_of(good, 'left_knee: 6')}: duplicate key 'left_knee'"):
        read_artist_poses(good, biped)
    two = _pose_file(tmp_path)
    body = two.read_text().split("poses:\n", 1)[1]
    two.write_text("unit: deg\nposes:\n" + body + body)
    with pytest.raises(PoseFileError, match="name 'lying' is used twice"):
        read_artist_poses(two, biped)
    with pytest.raises(PoseFileError, match="not found"):
        read_artist_poses(tmp_path / "nope.yaml", biped)


def test_self_colliding_pose_is_refused_naming_the_geoms(biped, tmp_path):
    path = _pose_file(tmp_path, {**JOINTS_DEG, "right_shoulder_roll": 0, "right_shoulder_yaw": 32, "right_elbow": -46})
    with pytest.raises(PoseFileError, match=rf"{re.escape(str(path))}:4: pose 'lying': the robot collides with itself \(.*right_forearm"):
        read_artist_poses(path, biped)


def test_shipped_artist_file_can_be_copied_and_edited(biped, tmp_path):
    copy = tmp_path / "mine.yaml"
    shutil.copy(artist_file(biped), copy)
    copy.write_text(copy.read_text().replace("left_knee: 110", "left_knee: 2.5 rad", 1))
    with pytest.raises(PoseFileError, match=r"poses\[1\] 'fetal_left'.joints.left_knee: 2.5 rad is above the upper limit"):
        read_artist_poses(copy, biped)
