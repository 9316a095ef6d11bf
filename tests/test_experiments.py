"""The paper's experiments: each one command (a real Hydra multirun of real trainings) plus its report,
and the report again on existing run directories, naming the jobs that are missing or failed."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import TINY, composed_config, fallkit_cli

from fallkit.experiments.report import REPORTS

# A tiny sweep: TINY trainings of 2 iterations, each evaluated on 4 falls of 0.2 s.
TINY_EXPERIMENT = [*TINY, "train.iterations=2", "train.evaluate=true", "eval.trials=4", "eval.seek_reference=false"]

# experiment -> command-line sweep that keeps it to two jobs (None: the preset's own, already small)
SMALL_SWEEP = {
    "comparison": None,
    "impact_tracking": "reward.impact=50,800",
    "data_source": None,
    "dataset_size": "env.pose_fraction=0.5,1.0",
    "battery": None,
}


def test_every_experiment_has_a_config_and_a_report():
    conf = Path(__file__).parents[1] / "fallkit" / "conf" / "experiment"
    assert sorted(p.stem for p in conf.glob("*.yaml")) == sorted(REPORTS) == sorted(SMALL_SWEEP)


@pytest.mark.parametrize("name", sorted(REPORTS))
def test_presets_compose_on_the_cpu_and_at_the_paper_scale(name):
    cpu = composed_config(f"experiment={name}")
    assert cpu.experiment == name and cpu.sim.backend == "mujoco" and cpu.train.max_minutes is None
    assert cpu.train.iterations <= 750  # sized for the 2-core machine
    paper = composed_config(f"experiment={name}", "scale=paper")
    assert paper.sim.backend == "warp" and paper.sim.num_envs == 4096 and paper.train.iterations == 75_000
    assert paper.train.actor_hidden == [512, 512, 512] and paper.eval.trials == 4096


def test_an_experiment_without_multirun_is_one_line(tmp_path):
    r = fallkit_cli("experiment=battery", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == (
        "fallkit: error: experiment=battery is a sweep of runs with a report: add -m "
        "(python -m fallkit -m experiment=battery)"
    )


def test_a_directory_that_is_no_experiment_is_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fallkit.experiments", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "not an experiment directory (no multirun.yaml)" in r.stderr


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(REPORTS))
def test_experiment_runs_and_reports(tmp_path, name):
    out = tmp_path / "exp"
    sweep = [SMALL_SWEEP[name]] if SMALL_SWEEP[name] else []
    r = fallkit_cli("-m", f"experiment={name}", *TINY_EXPERIMENT, *sweep, f"hydra.sweep.dir={out}", cwd=tmp_path,
                    timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    jobs = 1 if name == "comparison" else 2
    assert [j["status"] for j in report["runs"]] == ["done"] * jobs
    assert f"{jobs} of {jobs} runs finished" in (out / "report.md").read_text()
    assert (out / f"{name}.png").stat().st_size > 10_000  # a drawn figure, not an empty canvas
    assert report["findings"] and all(f["reproduced"] in (True, False, None) for f in report["findings"])
    if name == "data_source":  # the 2 x 2 grid: each policy also evaluated on the poses it did not train on
        assert set(report["grid"]) == {"generated", "artist"}
        assert all(set(row) == {"generated", "artist"} for row in report["grid"].values())
        assert (out / "1_poses=artist" / "eval_on_default" / "eval.json").is_file()
    if name == "battery":
        weights = {r: v["battery_weight"] for r, v in report["table"].items()}
        assert weights == {"biped20_battery": 5.0, "biped20_battery_baseline": 1.0}


@pytest.mark.slow
def test_report_again_names_missing_and_failed_runs(tmp_path):
    out = tmp_path / "exp"
    r = fallkit_cli("-m", "experiment=impact_tracking", *TINY_EXPERIMENT, "reward.impact=50,200,800",
                    f"hydra.sweep.dir={out}", cwd=tmp_path, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    first = json.loads((out / "report.json").read_text())["points"]
    assert [p["weight"] for p in first] == [50, 200, 800]

    (out / "1_impact=200" / "eval.json").unlink()  # a job that did not finish
    shutil.rmtree(out / "2_impact=800")  # a job that never started
    r = subprocess.run([sys.executable, "-m", "fallkit.experiments", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "1 of 3 runs finished" in r.stdout
    assert "failed: reward.impact=200: 1_impact=200 has no eval.json (its newest checkpoint is" in r.stdout
    assert "missing: reward.impact=800: no run directory" in r.stdout
    again = json.loads((out / "report.json").read_text())
    assert [j["status"] for j in again["runs"]] == ["done", "failed", "missing"]
    assert again["points"] == first[:1]  # the figure from what finished, unchanged
    md = (out / "report.md").read_text()
    assert "Not in the figures:" in md and "missing: reward.impact=800" in md
