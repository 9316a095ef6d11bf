"""The page's controls and read-outs (viser's GUI): what a fall starts from, how it is shown,
the peak contact force per component as it happens and the paper's metrics once it is over.

The read-outs are small HTML tables whose cells carry their exact value in `data-value`
(the text rounds it): a person reads the text, a test (tests/test_play.py) the attributes.
"""

from __future__ import annotations

import html
from typing import Callable

import numpy as np
import viser

from fallkit.config import FallkitConfig
from fallkit.play.session import FallResult, PlaySession

SIDE_BY_SIDE = "side by side"
# the paper's metrics (fallkit.eval.metrics.TrialMetrics) as the page shows them: key, heading, format
METRICS = (
    ("max_impact_force", "max impact [N]", "{:.0f}"),
    ("mean_impact_force", "mean impact [N]", "{:.0f}"),
    ("fall_mean_impact_force", "fall-phase mean [N]", "{:.0f}"),
    ("mroe", "MROE [rad]", "{:.3f}"),
    ("mje", "MJE [rad]", "{:.3f}"),
    ("rest_time", "rest [s]", "{:.2f}"),
)
_CELL = "padding:1px 2px;text-align:right;white-space:nowrap;overflow:hidden"
# fixed layout: the columns share the panel's width, the first (the row names) a third of it
_TABLE = "border-collapse:collapse;font-size:0.75em;width:97%;table-layout:fixed;margin-bottom:0.6em"
_FIRST = '<col style="width:31%">'
_HEAD = "padding:1px 2px;text-align:right;vertical-align:bottom"


def label(strategy: str) -> str:
    return strategy.replace("_", " ")


class Panel:
    """Every control of the page; callbacks are wired by fallkit.play.server."""

    def __init__(self, server: viser.ViserServer, session: PlaySession, config: FallkitConfig, threshold: float):
        gui, play = server.gui, config.play
        self.session = session
        self.threshold = threshold
        gui.configure_theme(control_layout="fixed", control_width="large", show_share_button=False)
        self.status = gui.add_html(status_html("ready", "Choose an end pose, then press Random fall or Push."))
        with gui.add_folder("Fall"):
            names = [session.pose_label(i) for i in range(len(session.poses))]
            start = session.pose_id(play.pose)
            if session.poses.names:
                self.pose = gui.add_dropdown("end pose", names, initial_value=names[start])
            else:
                self.pose = gui.add_number("end pose #", start, min=0, max=len(names) - 1, step=1)
            self.choose = None  # eval.poses=auto: leave the end pose to the fall
            if session.choice is not None:
                self.choose = gui.add_checkbox("choose for the fall", True,
                                               hint=f"eval.poses=auto, {session.choice.describe()}")  # fmt: skip
            self.seed = gui.add_number("seed", config.eval.seed, step=1, hint="initial state of the next random fall")
            self.random = gui.add_button("Random fall", hint="an initial falling state of paper Table II from the seed")
            self.push_size = gui.add_slider("push [N·s]", 0.0, 100.0, 1.0, play.push)
            self.push_direction = gui.add_slider("push toward [°]", -180.0, 180.0, 5.0, play.push_direction,
                                                 hint="0 = the robot's front, 90 = its left")  # fmt: skip
            self.push = gui.add_button("Push", hint="push the standing robot")
            self.replay = gui.add_button("Replay", disabled=True, hint="show the last fall again")
            self.speed = gui.add_slider("speed [x real time]", 0.1, 1.0, 0.05, play.speed)
            self.paused = gui.add_checkbox("pause", False)
        self.metrics = gui.add_html("")
        self.bars = gui.add_html(bars_html(session, np.zeros((len(session.strategies), len(session.spec.components))), threshold))
        with gui.add_folder("View"):
            self.view = gui.add_dropdown("strategies", [SIDE_BY_SIDE, *map(label, session.strategies)])
            self.robots = gui.add_checkbox("robots", True)
            self.ghost = gui.add_checkbox("ghost (end pose)", True)
            self.forces = gui.add_checkbox("contact forces", True)
            self.limit = gui.add_number("bars red above [N]", round(threshold), min=1, step=50)
        self.sensitivity = self._sensitivity_sliders(gui)

    def _sensitivity_sliders(self, gui: viser.GuiApi) -> dict[str, viser.GuiSliderHandle]:
        """One slider per component where the policy observes sensitivity weights, over the range it was
        trained on (env.sensitivity_inputs: the robot's weight × [low, high])."""
        if not self.session.observes_sensitivity():
            return {}
        trained = self.session.setup.config.env.sensitivity_inputs
        with gui.add_folder("Sensitivity"):
            return {
                c: gui.add_slider(c, 0.0, round(max(comp.weight, 1.0) * trained.high, 1), 0.1, float(comp.weight))
                for c, comp in self.session.spec.components.items()
            }

    def pose_id(self) -> int:
        """The end pose chosen in the page (an index out of range is a one-line error there)."""
        names = self.session.poses.names
        return names.index(self.pose.value) if names else self.session.pose_id(int(self.pose.value), "end pose #")

    def shown(self) -> list[int]:
        """The worlds shown: all, or the one strategy chosen."""
        names = [label(s) for s in self.session.strategies]
        return list(range(len(names))) if self.view.value == SIDE_BY_SIDE else [names.index(self.view.value)]

    def on_change(self, handles: list, callback: Callable[[], None]) -> None:
        for h in handles:
            h.on_update(lambda _event: callback())

    def set_status(self, state: str, text: str, fall: int | None = None) -> None:
        self.status.content = status_html(state, text, fall)

    def show_peaks(self, peak: np.ndarray) -> None:
        self.bars.content = bars_html(self.session, peak, self.threshold)

    def show_metrics(self, result: FallResult, pose: str) -> None:
        self.metrics.content = metrics_html(result, self.session.strategies, pose, self.session.env.max_steps * self.session.env.dt)


def status_html(state: str, text: str, fall: int | None = None) -> str:
    colour = {"error": "#c92a2a", "running": "#1864ab"}.get(state, "#2b8a3e" if state == "done" else "#495057")
    attr = f' data-fall="{fall}"' if fall is not None else ""
    return f'<div id="fallkit-status" data-state="{state}"{attr} style="color:{colour};font-size:0.85em">{html.escape(text)}</div>'


def bars_html(session: PlaySession, peak: np.ndarray, threshold: float) -> str:
    """Peak contact force of each component [W, C] so far: a bar per strategy, red above `threshold`."""
    head = "".join(f'<th style="{_HEAD}">{label(s)}</th>' for s in session.strategies)
    rows = []
    for c, (name, comp) in enumerate(session.spec.components.items()):
        cells = []
        for w in range(len(session.strategies)):
            f = float(peak[w, c])
            over = f > threshold
            width = min(100.0, 50.0 * f / threshold)  # the threshold sits at half the bar
            bar = (f'<div style="height:6px;background:#e9ecef"><div style="height:6px;width:{width:.1f}%;'
                   f'background:{"#e03131" if over else "#2f9e44"}"></div></div>')  # fmt: skip
            cells.append(f'<td style="{_CELL}" data-component="{name}" data-strategy="{session.strategies[w]}" '
                         f'data-value="{f!r}" data-over="{str(over).lower()}">{bar}{f:.0f}</td>')  # fmt: skip
        rows.append(f'<tr><td style="{_CELL};text-align:left">{name} <small>w={comp.weight:g}</small></td>{"".join(cells)}</tr>')
    return (f'<div style="font-size:0.85em;font-weight:600">Peak contact force so far [N] '
            f'<small style="font-weight:400">(red above {threshold:.0f} N)</small></div>'
            f'<table id="fallkit-peaks" style="{_TABLE}">{_FIRST}<tr><th></th>{head}</tr>{"".join(rows)}</table>')  # fmt: skip


def metrics_html(result: FallResult, strategies: list[str], pose: str, seconds: float) -> str:
    """The paper's metrics of one fall (fallkit.eval.metrics, as mode=eval): a row per metric, a column per strategy."""
    head = "".join(f'<th style="{_HEAD}">{label(s)}{" ⚠" if bool(result.metrics[s].unstable[0]) else ""}</th>' for s in strategies)
    rows = []
    for key, heading, fmt in METRICS:
        cells = "".join(
            f'<td style="{_CELL}" data-strategy="{s}" data-metric="{key}" data-value="{float(getattr(result.metrics[s], key)[0])!r}">'
            f"{fmt.format(float(getattr(result.metrics[s], key)[0]))}</td>"
            for s in strategies
        )
        rows.append(f'<tr><td style="{_CELL};text-align:left">{heading}</td>{cells}</tr>')
    unstable = [label(s) for s in strategies if bool(result.metrics[s].unstable[0])]
    note = f"<div style='font-size:0.75em;color:#c92a2a'>⚠ unstable, restarted by the simulator: {', '.join(unstable)}</div>" if unstable else ""
    caption = f"Fall {result.number}: {result.start.describe()}, end pose {pose}, {seconds:.2f} s"
    return (f'<div style="font-size:0.85em;font-weight:600">{html.escape(caption)}</div>'
            f'<table id="fallkit-metrics" data-fall="{result.number}" data-seed="{result.start.seed}" '
            f'data-pose="{result.pose_id}" style="{_TABLE}">{_FIRST}<tr><th></th>{head}</tr>{"".join(rows)}</table>{note}')  # fmt: skip
