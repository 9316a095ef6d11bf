"""The warp backend's first run says what it compiles, and mode=warmup fills the cache on purpose."""

from __future__ import annotations

import logging
import time

from helpers import fallkit_cli

from fallkit.sim.warp_setup import preparing_kernels, warp_cache_dir


def test_a_long_preparation_says_what_where_and_how_far(caplog, tmp_path, monkeypatch):
    monkeypatch.setenv("FALLKIT_WARP_CACHE", str(tmp_path))
    with caplog.at_level(logging.INFO, logger="fallkit.sim.warp_setup"):
        with preparing_kernels("biped20", "cpu", notice_after=0.05, every=0.1) as prepared:
            for k in range(3):  # modules appearing in the cache as Warp compiles them
                time.sleep(0.1)
                (tmp_path / "1.19.0" / f"wp_module_{k}").mkdir(parents=True)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0].startswith("warp: compiling biped20's kernels for cpu (once per machine and Warp version")
    assert str(tmp_path) in lines[0] and "mode=warmup sim=warp" in lines[0]
    assert any(line.startswith("warp: still compiling:") for line in lines[1:-1])
    assert lines[-1].startswith("warp: biped20's kernels ready on cpu in ") and "(3 modules compiled" in lines[-1]
    assert prepared.compiled == 3 and prepared.seconds >= 0.3


def test_loading_from_the_cache_says_nothing_loud(caplog, tmp_path, monkeypatch):
    monkeypatch.setenv("FALLKIT_WARP_CACHE", str(tmp_path))
    with caplog.at_level(logging.INFO, logger="fallkit.sim.warp_setup"):
        with preparing_kernels("biped20", "cpu") as prepared:
            pass  # loading: done long before the notice would be due
    assert [r.levelno for r in caplog.records] == [logging.INFO] and prepared.compiled == 0


def test_warmup_fills_the_cache_and_a_second_one_compiles_nothing(tmp_path):
    first = fallkit_cli("mode=warmup", "sim=warp", "sim.device=cpu", "sim.num_envs=4", cwd=tmp_path, timeout=900)
    assert first.returncode == 0, first.stderr[-2000:]
    again = fallkit_cli("mode=warmup", "sim=warp", "sim.device=cpu", "sim.num_envs=4", cwd=tmp_path, timeout=300)
    assert again.returncode == 0, again.stderr[-2000:]
    line = again.stdout.strip().splitlines()[-1]
    assert line.startswith("warmup: biped20 on cpu: everything was already in the cache, ready in ")
    assert line.endswith(f"cache {warp_cache_dir()}")


def test_warmup_on_the_mujoco_backend_is_one_line(tmp_path):
    r = fallkit_cli("mode=warmup", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1] == (
        "fallkit: error: mode=warmup prepares the warp backend's kernels: add sim=warp (mujoco compiles nothing)"
    )
