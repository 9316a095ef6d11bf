"""What a real user's mistakes, crashes and parallel runs do (issue 19): each test failed before its fix."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import TINY, fallkit_cli

from fallkit.config import DatasetConfig
from fallkit.errors import PoseFileError
from fallkit.poses import load_end_poses
from fallkit.poses.dataset import default_dataset, load_dataset, save_dataset
from fallkit.poses.generator import EndPoseGenerator
from fallkit.sim import make_sim


def test_a_small_dataset_is_made_with_the_default_pool(biped):
    """50 poses at 6 drops each is a budget of 300 < the 1024 worlds of the pool: the pool must
    shrink to the budget and let the drops land, not stop after the first step."""
    gen = EndPoseGenerator(biped, DatasetConfig(train=40, test=10)).run(progress=False)
    assert len(gen.joint_pos) == 50 and (gen.split == "test").sum() == 10
    assert gen.stats["drops"] <= 6 * 50
    assert np.isfinite(gen.joint_pos.numpy()).all()


# ---- item 5: artist poses are optional --------------------------------------------------------------


def test_mode_poses_for_a_robot_without_artist_poses_succeeds(tmp_path):
    """go1 ships no artist poses (as every new plugin): the dataset is the product, exit 0."""
    r = fallkit_cli("mode=poses", "robot=go1", "dataset.train=24", "dataset.test=8", "dataset.num_worlds=32",
                    "dataset.bands=2", "dataset.sectors=2", "dataset.sheet=0", f"dataset.out={tmp_path / 'go1.npz'}",
                    f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert "artist poses: skipped (robot 'go1' ships none" in r.stdout
    assert (tmp_path / "go1.npz").is_file()


# ---- item 2: every array a dataset brings is checked at load --------------------------------------


def _broken_dataset(biped, tmp_path, name: str, row: int, value) -> Path:
    ds = load_dataset(default_dataset(biped))
    keep = np.r_[ds.rows("train")[:20], ds.rows("test")[:5]]
    arrays = {k: getattr(ds, k)[keep].copy() for k in ("joint_pos", "root_quat", "root_height", "split", "bin")}
    arrays[name][row] = value
    return save_dataset(tmp_path / f"bad_{name}.npz", replace(ds, **arrays))


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("joint_pos", np.nan, "array 'joint_pos' row 3 is not finite"),
        ("root_quat", np.inf, "array 'root_quat' row 3 is not finite"),
        ("root_height", np.nan, "array 'root_height' row 3 is not finite"),
        ("root_quat", [0.5, 0.0, 0.0, 0.0], "array 'root_quat' row 3 is not a unit quaternion"),
        ("split", "valid", "array 'split' row 3 is not one of"),
        ("joint_pos", 9.0, "array 'joint_pos' row 3: joint '.*' = 9.0000 rad is outside its limits"),
    ],
)
def test_a_dataset_with_bad_values_is_refused_at_load(biped, tmp_path, name, value, message):
    path = _broken_dataset(biped, tmp_path, name, 3, value)
    with pytest.raises(PoseFileError, match=f"{path}: {message}"):
        load_end_poses(path, biped)


# ---- item 7: user mistakes that were tracebacks ---------------------------------------------------


def test_a_binary_pose_file_and_a_directory_are_named(biped, tmp_path):
    binary = tmp_path / "poses.yaml"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(PoseFileError, match="poses.yaml: not a text file"):
        load_end_poses(binary, biped)
    folder = tmp_path / "x.yaml"
    folder.mkdir()
    with pytest.raises(PoseFileError, match="x.yaml: is a directory, not an artist pose file"):
        load_end_poses(folder, biped)
    (tmp_path / "d.npz").mkdir()
    with pytest.raises(PoseFileError, match="d.npz: is a directory"):
        load_end_poses(tmp_path / "d.npz", biped)


def test_blend_time_longer_than_the_episode_is_one_line(tmp_path):
    r = fallkit_cli("reward.blend_time=9", "env.episode_length=2", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [
        "fallkit: error: reward.blend_time=9 s is longer than env.episode_length=2 s, so u(t) would never reach 1 "
        "(paper: T_blend <= T): shorten reward.blend_time or lengthen env.episode_length"
    ]


# ---- item 3: requests that were silently ignored ---------------------------------------------------


def test_a_gpu_asked_of_the_cpu_backend_is_refused(tmp_path):
    r = fallkit_cli("sim.device=cuda:0", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "fallkit: error: sim: device=cuda:0 needs the warp backend (the mujoco backend runs on the CPU): "
        "add sim=warp, or drop sim.device"
    ]


# ---- item 4: MJCF files as they come from the wild ------------------------------------------------


def test_an_mjcf_with_its_own_actuators_floor_sensors_and_keyframe_is_used(biped, tmp_path, caplog):
    """A model from a public collection: its actuators, sensors, keyframe and floor are dropped with
    one warning; the robot simulates with fallkit's 20 PD actuators and one floor."""
    text = Path(biped.mjcf).read_text()
    own = "".join(f'<motor joint="{j}" gear="1"/>' for j in biped.joint_names)
    text = text.replace("<worldbody>", '<worldbody><geom name="ground" type="plane" size="5 5 0.1"/>', 1)
    text = text.replace("</mujoco>", f'<actuator>{own}</actuator><sensor><jointpos joint="{biped.joint_names[0]}"/>'
                                     f'</sensor><keyframe><key name="home" qpos="{" 0" * 27}"/></keyframe></mujoco>')  # fmt: skip
    path = tmp_path / "wild.xml"
    path.write_text(text)
    wild = biped.model_copy(update={"name": "wild", "mjcf": path})
    with caplog.at_level(logging.WARNING, logger="fallkit.robots.spec"):
        model = wild.mj_model()
    assert model.nu == biped.mj_model().nu == 20 and model.ngeom == biped.mj_model().ngeom and model.nkey == 0
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and "20 <actuator>, 1 <sensor>, 1 <keyframe>, 1 floor): dropped" in warned[0]
    sim = make_sim(wild, 2)
    for _ in range(5):
        state = sim.step(torch.as_tensor(biped.nominal_q(), dtype=torch.float32).expand(2, -1))
    assert torch.isfinite(state.joint_pos).all()


# ---- item 8: Hydra's own errors in fallkit's one-line form ----------------------------------------


@pytest.mark.parametrize(
    "args, line",
    [
        (["reward.impcat=5"], "reward.impcat: no such reward term; did you mean reward.impact? +reward.impcat=5 adds "
                              "a term registered by a plugin (python -m fallkit mode=list lists them)"),
        (["sim=nosuch"], "unknown sim 'nosuch'; available: mujoco, warp (choose with sim=<name>)"),
        (["train.iteratons=3"], "train.iteratons: no such key; did you mean train.iterations? "
                                "python -m fallkit --cfg job prints every key"),
        (["sim=mujoco,warp"], "sim=mujoco,warp: a comma-separated value is a sweep: add -m to run one job per value; "
                              "for a list write key=[a,b], for a string with commas quote it"),
        (["-m", "train=quick", "sim=mujoco,nosuch"], "unknown sim 'nosuch'; available: mujoco, warp (choose with sim=<name>)"),
        (["seed=["], "cannot parse the override 'seed=[': no viable alternative at input '[' "
                     "(grammar: https://hydra.cc/docs/advanced/override_grammar/basic)"),
    ],
)  # fmt: skip
def test_hydra_composition_errors_are_one_line_exit_2(tmp_path, args, line):
    r = fallkit_cli(*args, cwd=tmp_path)
    assert (r.returncode, r.stderr.strip().splitlines()) == (2, [f"fallkit: error: {line}"])


# ---- item 6: resume after a crash -------------------------------------------------------------------

def test_a_run_killed_with_sigkill_resumes_with_its_own_configuration(tmp_path):
    """kill -9 leaves iter_*.pt only, and metrics rows past the newest of them. `resume=<run dir>`
    without repeating the run's overrides takes the newest checkpoint and the run's configuration,
    names what the command line changes, and keeps every iteration once in metrics.csv."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "fallkit", *TINY, "train.iterations=100000",
                             "train.checkpoint_every=2", "hydra.run.dir=run"], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    csv_path = tmp_path / "run" / "metrics.csv"
    try:
        deadline = time.time() + 180
        while time.time() < deadline and not (csv_path.exists() and csv_path.read_text().count("\n") >= 6):
            time.sleep(0.2)
    finally:
        proc.kill()
        proc.wait()
    ckpts = sorted((tmp_path / "run" / "checkpoints").glob("iter_*.pt"))
    assert ckpts and not (tmp_path / "run" / "checkpoints" / "last.pt").exists()
    newest = int(ckpts[-1].stem.split("_")[1])
    target = newest + 2

    r = fallkit_cli("resume=run", f"train.iterations={target}", "hydra.run.dir=run", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"resumed from run/checkpoints/{ckpts[-1].name} at iteration {newest}; training to {target}" in r.stdout
    assert f"the command line changes the run's train.iterations: 100000 -> {target}" in r.stdout
    iterations = [int(line.split(",")[0]) for line in csv_path.read_text().splitlines()[1:]]
    assert iterations == list(range(1, target + 1))

    r = fallkit_cli("resume=run", "robot=go1", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "fallkit: error: resume: run/checkpoints/last.pt was trained on robot 'biped20', "
        "but this run asks for robot 'go1': drop robot= to continue that run, or drop resume= to start a new one"
    ]
    r = fallkit_cli("resume=run", "train.actor_hidden=[8]", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "resume: the actor network of run/checkpoints/last.pt differs from this run's: " in r.stderr
    assert "is [16] there and [8] here; the run had train.actor_hidden=[16, 16]: drop the override" in r.stderr


# ---- item 9: parallel runs share the cores ----------------------------------------------------------


def test_fallkit_processes_share_the_cores(tmp_path, monkeypatch):
    """Each CPU-heavy fallkit process registers; the share is the usable cores over those alive,
    and a killed process's entry is ignored and removed (it cannot hold cores forever)."""
    from fallkit import machine

    monkeypatch.setenv("FALLKIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(machine, "usable_cores", lambda: 8)
    assert machine.running_processes() == 0 and machine.core_share() == 8
    with machine.running():
        assert machine.running_processes() == 1 and machine.core_share() == 8
        other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        try:
            entry = tmp_path / "running" / f"{other.pid}.pid"
            entry.write_text(machine._start_time(other.pid))
            assert machine.running_processes() == 2 and machine.core_share() == 4
            (tmp_path / "running" / "999999999.pid").write_text("0")  # a pid that cannot exist
            assert machine.running_processes() == 2
        finally:
            other.kill()
            other.wait()
        assert machine.running_processes() == 1 and not entry.exists()
    assert machine.running_processes() == 0


_SUBNORMALS = """
import logging, sys, torch
from fallkit.machine import subnormals_flushed
logging.basicConfig(level=logging.WARNING)
torch.set_num_threads(2)
if sys.argv[1] == "pool-first":
    torch.full((1 << 16,), 1.0).mul_(2.0)  # torch's threads started outside the block
# the smallest subnormal float32 from its bits, times 1, read back as bits: non-zero where a thread did not flush
tiny = lambda n: int(torch.ones(n, dtype=torch.int32).view(torch.float32).mul_(1.0).view(torch.int32).count_nonzero())
with subnormals_flushed():
    inside = tiny(1 << 16)
print(inside, tiny(8))  # 8 elements: the calling thread alone, after the block
"""


@pytest.mark.parametrize("start", ["pool-inside", "pool-first"])
def test_the_update_flushes_subnormals_in_every_torch_thread_or_says_it_cannot(start):
    """The trainer's update runs in subnormals_flushed (a trained critic's ELUs make subnormals, which x86 computes
    an order of magnitude slower). Real threads, so a fresh interpreter: the mode is per thread, inherited at start."""
    if not torch.set_flush_denormal(True):
        pytest.skip("this CPU has no flush-to-zero mode")
    torch.set_flush_denormal(False)
    out = subprocess.run([sys.executable, "-c", _SUBNORMALS, start], capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    inside, after = map(int, out.stdout.split())
    assert after == 8  # the calling thread computes subnormals again after the block
    if start == "pool-inside":
        assert inside == 0 and "do not flush subnormal floats" not in out.stderr
    else:  # the pool's thread keeps its half; said once, in one line
        assert inside > 0 and out.stderr.count("do not flush subnormal floats") == 1
