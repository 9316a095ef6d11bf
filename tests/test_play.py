"""mode=play (issue 18) as a person uses it: the real CLI serves the page, a real headless Chromium
clicks a fall, and what the page draws and reports is checked against the pixels and against a
mode=eval evaluation of the same fall; plus the simulation side in-process and the one-line errors."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import TINY, composed_config

from fallkit.eval.evaluate import make_eval_env, prepare
from fallkit.eval.rollout import Trials, draw_trials, evaluate

SECONDS = 1.5  # falls of 75 steps: the robots are down when the fall ends, and the page shows it at 1x in 1.5 s
CHROMIUM = next((p for p in (shutil.which("chromium"), shutil.which("chromium-browser"), "/usr/bin/chromium")
                 if p and Path(p).is_file()), None)  # fmt: skip
BROWSER_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]  # fmt: skip
METRIC_KEYS = ("max_impact_force", "mean_impact_force", "fall_mean_impact_force", "mroe", "mje", "rest_time")


@pytest.fixture(scope="module")
def policy_run(tmp_path_factory) -> Path:
    """A one-iteration biped20 policy (tiny networks) trained toward the artist poses."""
    from fallkit.rl.trainer import Trainer

    run = tmp_path_factory.mktemp("play") / "train"
    Trainer(composed_config(*TINY, "train.iterations=1", "env.poses=artist"), run).run()
    return run


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _play(*args: str, cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "fallkit", "mode=play", *args], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)  # fmt: skip


class _Output:
    """Everything a process prints, read on a thread while it runs."""

    def __init__(self, proc: subprocess.Popen):
        self.proc, self.lines = proc, []
        self._reader = threading.Thread(target=lambda: self.lines.extend(proc.stdout), daemon=True)
        self._reader.start()

    def wait_for_url(self, timeout: float) -> str:
        """The URL play prints."""
        end = time.monotonic() + timeout
        while time.monotonic() < end and self.proc.poll() is None:
            for line in list(self.lines):
                if line.startswith("play: open "):
                    return line.split()[2]
            time.sleep(0.2)
        raise AssertionError(f"mode=play printed no URL within {timeout:.0f} s:\n{self.text()[-3000:]}")

    def stop(self) -> str:
        """SIGTERM, as a service manager stops it; all it printed."""
        self.proc.terminate()
        self.proc.wait(timeout=30)
        self._reader.join(timeout=10)
        return self.text()

    def text(self) -> str:
        return "".join(self.lines)


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[H, W] pixels that differ clearly between two screenshots."""
    return np.abs(a.astype(int) - b.astype(int)).sum(axis=-1) > 30


def _blue(image: np.ndarray) -> np.ndarray:
    """Pixels of biped20's blue arms (paler in the scene's light)."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return (b > r + 30) & (b > g + 10)


def _grow(mask: np.ndarray, px: int) -> np.ndarray:
    """The mask widened by px pixels in every direction."""
    out = mask.copy()
    for dy in range(-px, px + 1):
        for dx in range(-px, px + 1):
            out |= np.roll(np.roll(mask, dy, axis=0), dx, axis=1)
    return out


def _png(data: bytes) -> np.ndarray:
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


# ---- in the browser ---------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium: scripts/setup.sh installs Debian's chromium (as root)")
def test_a_fall_clicked_in_the_browser_is_drawn_and_scored_as_mode_eval_scores_it(policy_run, tmp_path):
    from playwright.sync_api import sync_playwright

    port, pose_name = _free_port(), "fetal_left"
    proc = _play(f"checkpoint={policy_run}", f"play.port={port}", f"eval.seconds={SECONDS}", "play.speed=0.1",
                 f"hydra.run.dir={tmp_path / 'play'}", cwd=tmp_path)  # fmt: skip
    out = _Output(proc)
    try:
        url = out.wait_for_url(timeout=180)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=BROWSER_ARGS)
            page = browser.new_page(viewport={"width": 1400, "height": 800})
            page.goto(f"{url}/?fixedDpr=1")  # viser's adaptive resolution would change pixels between screenshots
            page.get_by_role("combobox", name="end pose").click()  # Mantine's select: open it, pick the pose
            page.get_by_role("option", name=pose_name).click()
            page.get_by_role("button", name="Random fall").click()
            status = page.locator("#fallkit-status")
            # the page answers while a fall runs (at 0.1x: 15 s, room for a slow machine): pause it, nothing
            # ends; full speed, go on
            page.wait_for_selector("#fallkit-status[data-state='running']", timeout=60_000)
            page.wait_for_timeout(500)
            page.get_by_label("pause", exact=True).click()
            page.wait_for_timeout(2500)
            assert status.get_attribute("data-state") == "running" and page.locator("#fallkit-metrics").count() == 0
            speed = page.locator("label", has_text="speed [x real time]").get_attribute("for")
            page.locator(f"[id='{speed}'] [role=slider]").press("End")  # the slider's maximum: 1x
            page.get_by_label("pause", exact=True).click()
            page.wait_for_selector("#fallkit-metrics[data-fall='1']", timeout=120_000)
            assert status.get_attribute("data-state") == "done", status.inner_text()
            done = status.inner_text()
            shown = page.eval_on_selector_all(
                "#fallkit-metrics td[data-metric]",
                "els => els.map(e => [e.dataset.strategy, e.dataset.metric, e.dataset.value])",
            )
            seed = int(page.locator("#fallkit-metrics").get_attribute("data-seed"))
            pose = int(page.locator("#fallkit-metrics").get_attribute("data-pose"))
            page.wait_for_timeout(1000)  # the last frame reaches the canvas
            canvas = page.locator("canvas").first
            full = _png(canvas.screenshot())
            page.screenshot(path=str(tmp_path / "play.png"))
            page.get_by_label("ghost (end pose)").click()
            page.wait_for_timeout(1000)
            no_ghost = _png(canvas.screenshot())
            page.get_by_label("robots", exact=True).click()
            page.wait_for_timeout(1000)
            nothing = _png(canvas.screenshot())
            browser.close()
    finally:
        printed = out.stop()
    assert proc.returncode == 0, printed
    assert "play: fall 1 (random initial state, seed" in printed and "play: stopped" in printed, printed
    assert f"{SECONDS:.2f} s of simulated time" in done, done

    # pixels: the ghost is translucent green where it was drawn; the robots are drawn, with their blue arms
    ghost = _changed(full, no_ghost)
    r, g, b = (full[..., i].astype(int) for i in range(3))
    assert ghost.sum() > 300, f"the ghost changed {ghost.sum()} pixels"
    assert ((g > r + 20) & (g > b + 20))[ghost].mean() > 0.5, "the ghost's pixels are not green"
    robots = _changed(no_ghost, nothing)
    assert robots.sum() > 2000, f"the robots changed {robots.sum()} pixels"
    arms, still = _blue(no_ghost), _blue(nothing)  # biped20's arms (0.35, 0.6, 0.85); the axes gizmo stays
    near = _grow(robots, 3)  # with the robots' soft edges
    assert arms[robots].sum() > 100 and not (arms & ~still & ~near).any(), "no blue arms where the robots are"

    # the page's figures are mode=eval's for the same initial state, end pose and strategies
    assert pose_name in (tmp_path / "play" / "falls.jsonl").read_text()
    config = composed_config(f"checkpoint={policy_run}", "mode=eval", f"eval.seconds={SECONDS}", "eval.poses=artist")
    torch.set_num_threads(1)  # as mode=eval
    setup = prepare(config)
    env = make_eval_env(setup, len(setup.strategies), SECONDS, config.eval.seed)
    first = draw_trials(env, 1, seed)
    expected = evaluate(env, Trials(first.qpos, first.qvel, torch.tensor([pose])), setup.strategies, setup.policy,
                        show_progress=False)  # fmt: skip
    assert env.end_poses.names[pose] == pose_name
    assert sorted({s for s, _, _ in shown}) == sorted(setup.strategies) and len(shown) == 4 * len(METRIC_KEYS)
    for strategy, key, value in shown:
        assert float(value) == float(getattr(expected[strategy], key)[0]), (strategy, key)


# ---- the simulation side ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def session():
    from fallkit.play.session import PlaySession

    return PlaySession(composed_config("mode=play", f"eval.seconds={SECONDS}"))


def test_a_push_fall_is_scored_as_mode_eval_scores_its_initial_state(session):
    from fallkit.play.session import FallStart

    frames = []
    start = FallStart(pose_id=3, push=40.0, direction=90.0)
    result = session.run(start, frames.append)
    steps = session.env.max_steps
    push_steps = round(session.config.play.push_time / session.env.dt)
    assert len(frames) == push_steps + 1 + steps and frames[push_steps].time == 0.0 and frames[-1].time == pytest.approx(SECONDS)
    assert all(f.push is not None for f in frames[:push_steps]) and frames[-1].push is None
    # the push toward the robot's left (+y) sets the standing robot moving that way
    trials = session.push_trials(start)
    v = trials.qvel[0, session.layout.root_qvel : session.layout.root_qvel + 3].numpy()
    assert v[1] > 0.3 and abs(v[0]) < 0.5 * v[1], v
    # ... and its fall is scored exactly as mode=eval scores that state
    expected = evaluate(session.env, trials, session.strategies, None, show_progress=False)
    for s in session.strategies:
        for k in METRIC_KEYS:
            assert float(getattr(result.metrics[s], k)[0]) == float(getattr(expected[s], k)[0]), (s, k)
    # the peak bars end at the per-component maxima the metrics report
    assert np.allclose(frames[-1].peak, np.stack([result.metrics[s].component_max_force[0] for s in session.strategies]), rtol=1e-6)


def test_end_poses_by_name_or_index_and_one_line_errors(session):
    from fallkit.errors import ConfigError
    from fallkit.play.session import choose_strategies

    assert session.source == "artist" and session.pose_id("fetal_left") == 1 and session.pose_id(4) == 4 == session.pose_id("4")
    assert session.strategies == ["zero_torque", "damping", "freeze"]  # no checkpoint: the standard strategies
    with pytest.raises(ConfigError, match=r"play.pose: no end pose 'nosuch' in artist; poses: prone_shield_head, fetal_left"):
        session.pose_id("nosuch")
    with pytest.raises(ConfigError, match=r"play.pose: pose index 10 is out of range: artist has poses 0..9"):
        session.pose_id(10)
    with pytest.raises(ConfigError, match="'policy' needs a trained policy"):
        choose_strategies(["policy", "freeze"], have_policy=False)
    with pytest.raises(ConfigError, match="unknown"):
        choose_strategies(["freez"], have_policy=True)
    assert not session.observes_sensitivity()  # no policy observes weights yet: the sliders stay hidden


def test_a_fall_left_to_choose_its_end_pose_steers_toward_the_pose_mode_eval_would_choose(session):
    from fallkit.errors import ConfigError
    from fallkit.eval.choice import choose_end_poses
    from fallkit.play.session import FallStart, PlaySession

    with pytest.raises(ConfigError, match="choosing the end pose for the fall needs eval.poses=auto"):
        session.run(FallStart(pose_id=0, seed=1, choose=True), lambda f: None)
    auto = PlaySession(composed_config("mode=play", f"eval.seconds={SECONDS}", "eval.poses=auto", "eval.scorer=heading",
                                       "eval.candidate_side=[left,right]"))  # fmt: skip
    assert auto.choice is not None and auto.choice.scorer == "heading"
    told = []
    for start in (FallStart(pose_id=0, seed=s, choose=True) for s in range(4)):
        result = auto.run(start, lambda f: None, told.append)
        trials = auto.random_trials(start)
        chosen = choose_end_poses(auto.env, trials, auto.choice)
        assert result.pose_id == int(chosen.pose_ids[0]) == told[-1]
        expected = evaluate(auto.env, chosen, auto.strategies, None, show_progress=False)
        for s in auto.strategies:
            for k in METRIC_KEYS:
                assert float(getattr(result.metrics[s], k)[0]) == float(getattr(expected[s], k)[0]), (s, k)
    # the candidates are the play poses lying on the sides asked for; a push is chosen for after the push
    assert len(auto.poses) < 10 and set(auto.poses.names) <= set(session.poses.names)
    pushed = auto.run(FallStart(pose_id=0, push=40.0, direction=90.0, choose=True), lambda f: None)
    after_push = choose_end_poses(auto.env, auto.push_trials(FallStart(pose_id=0, push=40.0, direction=90.0)), auto.choice)
    assert pushed.pose_id == int(after_push.pose_ids[0])
    by_hand = auto.run(FallStart(pose_id=1, seed=0), lambda f: None)
    assert by_hand.pose_id == 1


def test_the_scene_sends_mujocos_poses_and_one_arrow_per_component_in_contact(session):
    """What the browser is sent for a frame: geom poses from MuJoCo, side by side; the ghost at each
    robot; an arrow per component in contact, as long as its force says."""
    import mujoco
    import viser

    from fallkit.play.scene import FallScene
    from fallkit.play.session import FallStart

    frames = []
    session.run(FallStart(pose_id=0, seed=5), frames.append)
    last = frames[-1]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        scene = FallScene(server, session.spec, session.strategies, 1.6, 0.3, session.weight)
        scene.set_ghost(session.ghost_qpos(0), session.poses.root_quat[0].numpy())
        scene.draw(last)
        m = session.spec.mj_model()
        d = mujoco.MjData(m)
        d.qpos[:] = last.qpos[2]
        mujoco.mj_fwdPosition(m, d)
        first = scene.geoms[0].gid
        assert np.allclose(scene.robots[0].batched_positions[2], d.geom_xpos[first] + [0.0, 1.6, 0.0], atol=1e-5)
        r = session.layout.root_qpos
        assert np.allclose(scene.ghost_frames[2].position[:2], last.qpos[2, r : r + 2] + [0.0, 1.6], atol=1e-6)
        in_contact = 0
        for w in range(3):  # every component touching something, with a force worth drawing
            dw = scene.data[w]
            comps = scene.component[dw.contact.geom[: dw.ncon]].max(axis=1)
            in_contact += len({c for c in comps if c >= 0 and np.linalg.norm(last.force[w, c]) >= 1.0})
        assert in_contact > 0 and len(scene.arrows.points) == in_contact
        newtons = np.linalg.norm(scene.arrows.points[:, 1] - scene.arrows.points[:, 0], axis=-1) * session.weight / 0.3
        forces = np.linalg.norm(last.force, axis=-1).ravel()
        assert all(np.isclose(f, forces, rtol=1e-4).any() for f in newtons)
        scene.set_shown([1])  # one strategy alone sits in the middle
        assert np.allclose(scene.robots[0].batched_positions[0, 1], scene.data[1].geom_xpos[first, 1], atol=1e-5)
    finally:
        server.stop()


# ---- mistakes on the command line -------------------------------------------------------------------------


def test_bad_input_is_one_line_on_the_console(policy_run, tmp_path):
    """A port in use, an unknown pose and a checkpoint of another robot: one line, exit status 2."""
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        cases = [
            ([f"play.port={port}"], f"fallkit: error: play.port: 127.0.0.1:{port} is in use"),
            (["play.port=0", "play.pose=nosuch"], "fallkit: error: play.pose: no end pose 'nosuch' in artist; poses: "),
            (["play.port=0", f"checkpoint={policy_run}", "robot=biped20_battery"],
             "fallkit: error: checkpoint=", "is a policy for robot 'biped20', not robot=biped20_battery"),
        ]  # fmt: skip
        for args, *messages in cases:
            proc = _play(*args, f"hydra.run.dir={tmp_path / 'bad'}", cwd=tmp_path)
            out = proc.communicate(timeout=180)[0]
            assert proc.returncode == 2, out
            last = out.strip().splitlines()[-1]
            assert all(m in last for m in messages) and "Traceback" not in out, out
