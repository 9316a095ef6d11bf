"""`mode=play`: watch and steer falls live in the browser (viser).

`python -m fallkit mode=play [checkpoint=<run>]` starts a local web viewer and prints its URL.
The simulation runs here, on a background thread (`Player`), on the run's backend (`sim=mujoco`
by default, `sim=warp` on a GPU); the browser only draws what it is sent (fallkit.play.scene)
and stays responsive while a fall runs: viser serves the page from its own thread, and a click
only hands a request to the player (the newest request wins and ends the fall under way).

A fall is paced to `speed` × real time (0.1-1, a slider) by sleeping between policy steps, and
frames are sent at most `play.fps` times a second. Mistakes (an unknown pose, a checkpoint of
another robot, a port in use) are one line on the console before the page starts, or one line
in the page's status for what is chosen there.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import torch
import viser

from fallkit.config import FallkitConfig
from fallkit.errors import ConfigError, FallkitError
from fallkit.play.panel import Panel, label
from fallkit.play.scene import FallScene
from fallkit.play.session import FallResult, FallStart, Frame, PlaySession

log = logging.getLogger(__name__)

__all__ = ["Player", "check_port", "run_play"]


class _Cancelled(Exception):
    """A newer request from the page ends the fall under way."""


class Player:
    """Runs the page's requests one at a time on a background thread, paced and drawn."""

    def __init__(self, session: PlaySession, scene: FallScene, panel: Panel, fps: float, log_file: Path | None = None):
        self.session, self.scene, self.panel = session, scene, panel
        self.min_frame_gap = 1.0 / fps  # [s] of wall time
        self.log_file = log_file
        self.last: FallResult | None = None
        self.busy = False  # a fall (or replay) is being shown: the ghost is its end pose, whatever is chosen
        self._request: FallStart | str | None = None
        self._wake = threading.Condition()
        self._cancel = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._loop, name="fallkit-play", daemon=True)
        self._thread.start()

    def request(self, what: FallStart | str) -> None:
        """Start a fall (or "replay" the last) as soon as the one under way has stopped."""
        with self._wake:
            self._request = what
            self._cancel.set()
            self._wake.notify()

    def close(self) -> None:
        with self._wake:
            self._closed = True
            self._cancel.set()
            self._wake.notify()
        self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        while True:
            with self._wake:
                while self._request is None and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                what, self._request = self._request, None
                self._cancel.clear()
            self.busy = True
            try:
                self._replay() if what == "replay" else self._fall(what)
            except _Cancelled:
                continue
            except FallkitError as exc:  # something chosen in the page that cannot be used
                self.panel.set_status("error", str(exc))
            except Exception as exc:  # a bug: the traceback on the console, one line in the page
                log.exception("play: the fall failed")
                self.panel.set_status("error", f"internal error: {type(exc).__name__}: {exc} (traceback on the console)")
            finally:
                self.busy = False

    def _fall(self, start: FallStart) -> None:
        s = self.session
        number = s.falls + 1
        self.panel.replay.disabled = True
        self.panel.show_peaks(np.zeros((len(s.strategies), len(s.spec.components))))

        def steering_toward(pose_id: int) -> None:  # known after a push; chosen for the fall with start.choose
            how = f"chosen by {s.choice.scorer}: " if start.choose else ""
            text = f"fall {number}: {start.describe()}, end pose {how}{s.pose_label(pose_id)} …"
            self.panel.set_status("running", text, number)
            self.show_ghost(pose_id)

        if start.choose:
            self.panel.set_status("running", f"fall {number}: {start.describe()}, end pose chosen as it begins …", number)
        else:
            steering_toward(start.pose_id)
        self._begin()
        result = s.run(start, self._show, steering_toward if start.choose else None)
        pose = s.pose_label(result.pose_id)
        self._finish(result.frames[-1])
        self.last = result
        self.panel.show_metrics(result, pose)
        self.panel.replay.disabled = False
        self.panel.set_status("done", f"fall {number} done: {self._timing(result.frames[-1].time)}", number)
        self._record(result, pose)

    def _replay(self) -> None:
        if self.last is None:
            return
        n = self.last.number
        self.panel.set_status("running", f"replaying fall {n} …", n)
        self.show_ghost(self.last.pose_id)
        self._begin()
        for frame in self.last.frames:
            self._show(frame)
        self._finish(self.last.frames[-1])
        self.panel.set_status("done", f"fall {n} replayed: {self._timing(self.last.frames[-1].time)}", n)

    def show_ghost(self, pose_id: int) -> None:
        self.scene.set_ghost(self.session.ghost_qpos(pose_id), self.session.poses.root_quat[pose_id].cpu().numpy())

    # ---- pacing and drawing ------------------------------------------------------------------

    def _begin(self) -> None:
        self._deadline = self._started = time.perf_counter()
        self._prev_time: float | None = None
        self._drawn, self._last_drawn = 0, -np.inf  # frames sent; simulated time of the last one

    def _show(self, frame: Frame) -> None:
        """Wait until this frame is due at the chosen speed, then draw it (at most play.fps a second)."""
        if self._cancel.is_set():
            raise _Cancelled
        while self.panel.paused.value:
            if self._cancel.wait(0.05):
                raise _Cancelled
            self._deadline = time.perf_counter()
        step = 0.0 if self._prev_time is None else max(0.0, frame.time - self._prev_time)
        self._prev_time = frame.time
        self._deadline += step / float(self.panel.speed.value)
        late = time.perf_counter() - self._deadline
        if late < 0:
            if self._cancel.wait(-late):
                raise _Cancelled
        elif late > 0.1:  # the simulation fell behind: go on from now instead of rushing to catch up
            self._deadline = time.perf_counter()
        # spaced in simulated time, so sleeping's jitter cannot skip every other frame
        if (frame.time - self._last_drawn) / float(self.panel.speed.value) >= self.min_frame_gap - 1e-6:
            self._draw(frame)

    def _draw(self, frame: Frame) -> None:
        self.scene.draw(frame)
        self.panel.show_peaks(frame.peak)
        self._drawn += 1
        self._last_drawn = frame.time

    def _finish(self, frame: Frame) -> None:
        self._draw(frame)  # the end of the fall is always shown
        self._wall = time.perf_counter() - self._started

    def _timing(self, seconds: float) -> str:
        wall = max(self._wall, 1e-9)
        return (f"{seconds:.2f} s of simulated time in {wall:.2f} s ({seconds / wall:.2f}x real time), "
                f"{self._drawn / wall:.0f} frames/s sent to the browser")  # fmt: skip

    def _record(self, result: FallResult, pose: str) -> None:
        """One line per fall on the console and in falls.jsonl of the run directory."""
        figures = {s: {k: float(v[0]) for k, v in m.arrays().items() if v.ndim == 1} for s, m in result.metrics.items()}
        impacts = ", ".join(f"{label(s)} {f['max_impact_force']:.0f} N" for s, f in figures.items())
        print(f"play: fall {result.number} ({result.start.describe()}, end pose {pose}): max impact {impacts}", flush=True)
        if self.log_file is not None:
            entry = {"fall": result.number, "start": vars(result.start), "pose": pose, "metrics": figures}
            with self.log_file.open("a") as f:
                f.write(json.dumps(entry) + "\n")


# ---- the app ---------------------------------------------------------------------------------


def check_port(host: str, port: int) -> None:
    """A port another program listens on is a ConfigError (viser would quietly take the next one)."""
    if port == 0:
        return
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no obstacle
        try:
            s.bind((host, port))
        except socket.gaierror as exc:
            raise ConfigError(f"play.host: cannot listen on '{host}': {exc.strerror}") from None
        except OSError as exc:
            raise ConfigError(
                f"play.port: {host}:{port} is in use ({exc.strerror}), perhaps by another mode=play: "
                f"choose another with play.port=<port>, or play.port=0 for any free one"
            ) from None


def _robot_named() -> bool:
    """Whether robot= was given on the command line (then a checkpoint of another robot is an error)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return False
    return any(o.lstrip("+").split("=", 1)[0] == "robot" for o in HydraConfig.get().overrides.task)


def _wire(player: Player, panel: Panel, scene: FallScene, session: PlaySession) -> None:
    """Connect the page's controls to the player and the scene."""

    def fall(push: bool) -> None:
        try:
            pose = panel.pose_id()
        except FallkitError as exc:
            panel.set_status("error", str(exc))
            return
        choose = panel.choose is not None and bool(panel.choose.value)
        if push:
            size, toward = float(panel.push_size.value), float(panel.push_direction.value)
            player.request(FallStart(pose, push=size, direction=toward, choose=choose))
        else:
            seed = int(panel.seed.value)
            panel.seed.value = seed + 1  # the next click falls from a new state; type a seed to see one again
            player.request(FallStart(pose, seed=seed, choose=choose))

    def pose_changed() -> None:
        try:
            i = panel.pose_id()
        except FallkitError as exc:
            panel.set_status("error", str(exc))
            return
        if not player.busy:  # during a fall the ghost stays the pose that fall steers toward
            player.show_ghost(i)

    def threshold_changed() -> None:
        panel.threshold = max(1.0, float(panel.limit.value))
        panel.show_peaks(scene.last.peak if scene.last is not None else np.zeros((len(session.strategies), len(session.spec.components))))

    def forces_changed() -> None:
        scene.show_forces = bool(panel.forces.value)
        if scene.last is not None:
            scene.draw(scene.last)

    panel.random.on_click(lambda _e: fall(push=False))
    panel.push.on_click(lambda _e: fall(push=True))
    panel.replay.on_click(lambda _e: player.request("replay"))
    panel.on_change([panel.pose], pose_changed)
    panel.on_change([panel.view], lambda: scene.set_shown(panel.shown()))
    panel.on_change([panel.robots], lambda: scene.show_robots(bool(panel.robots.value)))
    panel.on_change([panel.ghost], lambda: scene.show_ghosts(bool(panel.ghost.value)))
    panel.on_change([panel.forces], forces_changed)
    panel.on_change([panel.limit], threshold_changed)
    for component, slider in panel.sensitivity.items():
        slider.on_update(lambda _e, c=component, s=slider: session.set_sensitivity(c, float(s.value)))
    pose_changed()


def run_play(config: FallkitConfig, run_dir: Path) -> None:
    """`mode=play`: serve the viewer until Ctrl-C (or SIGTERM); every fall is logged to run_dir/falls.jsonl."""
    play = config.play
    torch.set_num_threads(1)  # a few worlds: the physics threads are MuJoCo's, and the page needs a core
    check_port(play.host, play.port)
    session = PlaySession(config, _robot_named())
    threshold = play.force_threshold or 5.0 * session.weight
    logging.getLogger("websockets").setLevel(logging.WARNING)  # a line per browser connection is noise here
    with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the one URL to open is printed below
        server = viser.ViserServer(host=play.host, port=play.port, verbose=False)
    if play.port and server.get_port() != play.port:  # taken in the seconds since check_port
        server.stop()
        check_port(play.host, play.port)
    try:
        _frame_the_row(server, len(session.strategies), play.spacing)
        scene = FallScene(server, session.spec, session.strategies, play.spacing, config.render.force_scale, session.weight)
        panel = Panel(server, session, config, threshold)
        player = Player(session, scene, panel, play.fps, Path(run_dir) / "falls.jsonl")
        _wire(player, panel, scene, session)
        scene.draw(Frame(0.0, session.standing_qpos().expand(len(session.strategies), -1).numpy(),
                         np.zeros((len(session.strategies), len(session.spec.components), 3)),
                         np.zeros((len(session.strategies), len(session.spec.components)))))  # fmt: skip
        _serve(server, player, session, play.host)
    finally:
        server.stop()


def _frame_the_row(server: viser.ViserServer, robots: int, spacing: float) -> None:
    """The first view: in front of the row of robots and above it, all of them in sight
    (viser's 75° vertical field of view, the canvas about 1.2 times wider than high)."""
    half_width = (robots - 1) / 2 * spacing + 0.9  # a lying robot reaches about 0.9 m from where it fell
    distance = half_width / (math.tan(math.radians(75.0) / 2) * 1.2)
    server.initial_camera.position = (0.82 * distance, -0.1 * distance, 0.56 * distance)  # 34° above the floor
    server.initial_camera.look_at = (0.0, 0.0, 0.1)


def _serve(server: viser.ViserServer, player: Player, session: PlaySession, host: str) -> None:
    """Print where to look, then wait for Ctrl-C or SIGTERM."""
    port = server.get_port()
    shown = "localhost" if host in ("0.0.0.0", "::", "127.0.0.1") else host
    what = ", ".join(label(s) for s in session.strategies)
    print(f"play: {session.spec.name}: {what}; end poses from {session.source} ({len(session.poses)})", flush=True)
    print(f"play: open http://{shown}:{port} (from another machine: ssh -L {port}:localhost:{port} <this host>); "
          "Ctrl-C stops", flush=True)  # fmt: skip
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(0.5):  # with a timeout, so Ctrl-C (KeyboardInterrupt) arrives between waits
            continue
    except KeyboardInterrupt:
        print("play: stopped (Ctrl-C)", flush=True)
    finally:
        signal.signal(signal.SIGTERM, previous)
        player.close()
        print("play: stopped", flush=True)
