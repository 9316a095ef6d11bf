"""The figures of mode=detect: lead times, missed falls and false triggers, over the detector's threshold.

From a PushRecord (recorded by fallkit.deploy.fall_detection), every threshold is judged by the detector's own
rule (`first_trigger`) over the recorded signals:

- a **fall** is a trial with a non-foot floor contact within the horizon; it is **detected** when the
  detector said "fall" at an update before that contact, with **lead time** = contact − trigger [s];
  otherwise it is **missed** (no trigger, or only after the contact: too late for the fall policy);
- a **survived** push has no such contact; a trigger within the horizon (or while the robot stood
  before the push) is a **false trigger**. Survivors that touch down in the extra watching time are
  reported apart (late falls): the protocol still counts them as survived.

The ROC plots the true-positive rate (detected falls / falls) against the false-trigger rate (false
triggers / survived pushes) over `detector.capture_margin`, the tilt backstop fixed; beside it the
ROC of each signal alone (its largest value over a trial against a threshold), so the choice of
signal is visible in the same figure.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fallkit.config.detector import PushTestConfig
from fallkit.deploy.detector import DetectorSettings, first_trigger
from fallkit.eval.plots import plt, save_figure  # matplotlib, headless

SIGNALS = {"capture": "capture point outside the support [m]", "tilt": "tilt [rad]", "tilt_rate": "tilt rate [rad/s]"}

@dataclass
class PushRecord:
    """Every trial's push, outcome and the detector's signals at every update (NaN after the trial ended)."""

    impulse: np.ndarray  # [n] N·s
    direction: np.ndarray  # [n] rad, world frame: 0 = the robot's front (+x), π/2 its left
    time: np.ndarray  # [T] s of each update from the push's start (negative while standing before it)
    tilt: np.ndarray  # [n, T] rad
    tilt_rate: np.ndarray  # [n, T] rad/s
    capture: np.ndarray  # [n, T] m: capture point outside the support polygon
    contact_time: np.ndarray  # [n] s from the push's start to the first non-foot floor contact; NaN: none
    live_trigger: np.ndarray  # [n] update index at which the live detector said "fall"; -1: never

def analyse(record: PushRecord, settings: DetectorSettings, pushes: PushTestConfig) -> dict:
    """The report: the table at the configured settings, the sweep of capture_margin, each signal's ROC."""
    fall = np.nan_to_num(record.contact_time, nan=np.inf) <= pushes.horizon
    ends = _window_ends(record, fall, pushes.horizon)
    margins = np.linspace(*pushes.sweep, pushes.sweep_points)
    rows = [_judge(record, fall, ends, settings, float(m)) for m in margins]
    sweep = {k: [r[k] for r in rows] for k in rows[0]}
    sweep["capture_margin"] = margins.tolist()
    return {
        "settings": vars(settings),
        "table": _judge(record, fall, ends, settings, settings.capture_margin),
        "sweep": sweep,
        "signals": {name: _signal(record, name, fall, ends) for name in SIGNALS},
        "falls_by_impulse": _by_impulse(record.impulse, fall),
    }

def _window_ends(record: PushRecord, fall: np.ndarray, horizon: float) -> np.ndarray:
    """Per trial, the updates that count: a fall's up to its contact (the record stops there), a
    survivor's up to the horizon."""
    recorded = (~np.isnan(record.capture)).sum(axis=1)
    within = int(np.searchsorted(record.time, horizon, side="right"))
    return np.where(fall, recorded, np.minimum(recorded, within))

def _judge(record: PushRecord, fall: np.ndarray, ends: np.ndarray, settings: DetectorSettings, margin: float) -> dict:
    """The figures of one capture_margin (the other settings as configured)."""
    trigger = np.full(len(fall), np.nan)
    for i, end in enumerate(ends):
        k = first_trigger(record.capture[i, :end], record.tilt[i, :end], margin, settings.max_tilt, settings.confirm_steps)
        trigger[i] = np.nan if k < 0 else record.time[k]
    triggered = ~np.isnan(trigger)
    lead = (record.contact_time - trigger)[fall & triggered]
    survived = ~fall
    late = survived & ~np.isnan(record.contact_time)
    n_falls, n_survived = int(fall.sum()), int(survived.sum())
    false = survived & triggered
    return {
        "capture_margin": margin,
        "pushes": len(fall),
        "falls": n_falls,
        "detected": int(len(lead)),
        "missed_falls": n_falls - int(len(lead)),
        "lead_time_median_s": _stat(np.median, lead),
        "lead_time_p5_s": _stat(lambda x: np.percentile(x, 5), lead),
        "lead_time_min_s": _stat(np.min, lead),
        "survived": n_survived,
        "false_triggers": int(false.sum()),
        "pre_push_triggers": int((triggered & (trigger < 0)).sum()),
        "late_falls": int(late.sum()),
        "false_triggers_on_late_falls": int((false & late).sum()),
        "false_triggers_never_down": int((false & ~late).sum()),
        "true_positive_rate": len(lead) / n_falls if n_falls else float("nan"),
        "false_trigger_rate": int(false.sum()) / n_survived if n_survived else float("nan"),
        "false_trigger_rate_never_down": int((false & ~late).sum()) / max(1, n_survived - int(late.sum())),
    }

def _stat(f, x: np.ndarray) -> float | None:
    return float(f(x)) if len(x) else None

def _signal(record: PushRecord, name: str, fall: np.ndarray, ends: np.ndarray) -> dict:
    """One signal alone, 'fall when it exceeds τ': its ROC over every τ that changes an outcome, and its
    lead times at the lowest τ that no push which never touched down reached (the earliest quiet trigger)."""
    signal = getattr(record, name)
    peaks = np.array([np.max(signal[i, :end]) if end else -np.inf for i, end in enumerate(ends)])
    taus = np.concatenate([[np.inf], np.unique(peaks)[::-1], [-np.inf]])
    tpr = [float((peaks[fall] >= t).mean()) if fall.any() else 0.0 for t in taus]
    fpr = [float((peaks[~fall] >= t).mean()) if (~fall).any() else 0.0 for t in taus]
    out = {"tpr": tpr, "fpr": fpr, "auc": float(np.trapezoid(tpr, fpr))}
    never = np.isnan(record.contact_time)
    if never.any() and fall.any():
        quiet = float(np.nanmax(signal[never]))  # never down: their whole record counts, after the horizon too
        lead = []
        for i in np.flatnonzero(fall):
            over = np.flatnonzero(signal[i, : ends[i]] > quiet)
            if len(over):
                lead.append(record.contact_time[i] - record.time[over[0]])
        out.update(quiet_threshold=quiet, quiet_detected=len(lead), quiet_lead_median_s=_stat(np.median, np.array(lead)),
                   quiet_lead_p5_s=_stat(lambda x: np.percentile(x, 5), np.array(lead)))  # fmt: skip
    return out

def _by_impulse(impulse: np.ndarray, fall: np.ndarray) -> dict:
    """Where the falls begin: the smallest push that fell, the largest that was survived [N·s]."""
    return {"smallest_fall": float(impulse[fall].min()) if fall.any() else None,
            "largest_survived": float(impulse[~fall].max()) if (~fall).any() else None}  # fmt: skip

# ---- what a person reads -------------------------------------------------------------------------

def markdown(report: dict) -> str:
    """detection.md: the protocol in one line, the table at the configured settings, each signal, the sweep."""
    t, s, info = report["table"], report["settings"], report.get("info", {})
    p = info.get("pushes", {})
    lines = [
        f"# Fall detection: {info.get('robot', '')} standing, {t['pushes']} pushes",
        "",
        f"Pushes of 0–{p.get('max_impulse', '?')} N·s over {p.get('duration', '?')} s on {info.get('pushed_body', '?')}, "
        f"random horizontal directions; a fall = a non-foot floor contact within {p.get('horizon', '?')} s of the push. "
        f"Detector: capture_margin {s['capture_margin']:g} m, max_tilt {s['max_tilt']:g} rad, confirm_steps "
        f"{s['confirm_steps']}. Falls begin at {_f(report['falls_by_impulse']['smallest_fall'])} N·s; the largest "
        f"push survived was {_f(report['falls_by_impulse']['largest_survived'])} N·s.",
        "",
        "| pushes | falls | detected | missed falls | lead time median [s] | lead time p5 [s] | lead time min [s] "
        "| survived | false triggers | of them touched down later | survived and never down |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        f"| {t['pushes']} | {t['falls']} | {t['detected']} | {t['missed_falls']} | {_f(t['lead_time_median_s'])} | "
        f"{_f(t['lead_time_p5_s'])} | {_f(t['lead_time_min_s'])} | {t['survived']} | {t['false_triggers']} | "
        f"{t['false_triggers_on_late_falls']} of {t['late_falls']} | {t['survived'] - t['late_falls']} "
        f"({t['false_triggers_never_down']} triggered) |",
        "",
        f"'Touched down later': survived the {p.get('horizon', '?')} s of the protocol but touched the floor in the "
        f"{p.get('after', '?')} s watched after it (the protocol counts them as survived).",
        "",
        "Each signal alone, 'fall when it exceeds τ': ROC area by the protocol, and the falls it detects at the "
        "lowest τ that no push which never touched down reached:",
        "",
        "| signal | ROC area | that τ | detected | lead time median [s] | lead time p5 [s] |",
        "|---|---|---|---|---|---|",
    ]
    for k, v in report["signals"].items():
        lines.append(f"| {SIGNALS[k]} | {v['auc']:.3f} | {_f(v.get('quiet_threshold'))} | {v.get('quiet_detected', '–')} "
                     f"| {_f(v.get('quiet_lead_median_s'))} | {_f(v.get('quiet_lead_p5_s'))} |")  # fmt: skip
    lines += ["", "The sweep of capture_margin (the other settings as configured):", "",
              "| capture_margin [m] | detected | missed | lead median [s] | lead p5 [s] | false triggers | of them "
              "touched down later | triggered before the push |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    sw = report["sweep"]
    for i in range(0, len(sw["capture_margin"]), max(1, len(sw["capture_margin"]) // 15)):
        lines.append(f"| {sw['capture_margin'][i]:+.3f} | {sw['detected'][i]} | {sw['missed_falls'][i]} | "
                     f"{_f(sw['lead_time_median_s'][i])} | {_f(sw['lead_time_p5_s'][i])} | {sw['false_triggers'][i]} | "
                     f"{sw['false_triggers_on_late_falls'][i]} | {sw['pre_push_triggers'][i]} |")  # fmt: skip
    return "\n".join(lines) + "\n"

def _f(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"

def plots(report: dict, run_dir: Path) -> list[Path]:
    """detection_roc.png and detection_lead_time.png."""
    sw, t, robot = report["sweep"], report["table"], report.get("info", {}).get("robot", "")
    fig, ax = plt.subplots(figsize=(5.8, 5.0))
    for name, roc in report["signals"].items():
        ax.step(roc["fpr"], roc["tpr"], where="post", alpha=0.6, label=f"{SIGNALS[name]} alone (area {roc['auc']:.3f})")
    ax.plot(sw["false_trigger_rate"], sw["true_positive_rate"], "k.-", ms=5, label="detector over capture_margin")
    ax.plot(sw["false_trigger_rate_never_down"], sw["true_positive_rate"], "k.:", ms=3, alpha=0.6,
            label="the same, false = survived pushes never down")  # fmt: skip
    ax.plot([t["false_trigger_rate"]], [t["true_positive_rate"]], "r*", ms=14,
            label=f"default: capture_margin {t['capture_margin']:g} m")  # fmt: skip
    ax.set(xlabel="false-trigger rate (survived pushes that triggered)", ylabel="falls detected before the contact",
           xlim=(-0.02, 1.02), ylim=(-0.02, 1.02))  # fmt: skip
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    roc = save_figure(fig, run_dir / "detection_roc.png", f"{robot}: fall detection over the threshold")
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    m = np.array(sw["capture_margin"])
    values = lambda k: np.array([np.nan if v is None else v for v in sw[k]], dtype=float)  # noqa: E731
    ax.plot(m, values("lead_time_median_s"), "b-", label="lead time, median")
    ax.plot(m, values("lead_time_p5_s"), "b--", label="lead time, 5th percentile")
    ax.axvline(t["capture_margin"], color="r", lw=1, label="default")
    ax.set(xlabel="capture_margin [m]", ylabel="lead time [s]")
    ax.grid(alpha=0.3)
    counts = ax.twinx()
    counts.plot(m, sw["missed_falls"], "g-", label="missed falls")
    counts.plot(m, sw["false_triggers"], "m-", label="false triggers")
    counts.plot(m, sw["pre_push_triggers"], "y:", label="triggered before the push")
    counts.set_ylabel("pushes")
    handles = ax.get_legend_handles_labels()[0] + counts.get_legend_handles_labels()[0]
    ax.legend(handles=handles, fontsize=7, loc="upper right")
    lead = save_figure(fig, run_dir / "detection_lead_time.png", f"{robot}: lead time and errors over the threshold")
    return [roc, lead]
