"""The fall detector on biped20's push test (issue 17, part 3): lead time, missed falls, false triggers.

Runs `python -m fallkit mode=detect` (docs/fall_detection.md: the robot standing at its nominal pose
under its PD controller, pushed once per trial by impulses growing from 0 to 12 N·s from random
horizontal directions; a fall = a non-foot floor contact within 2 s) and reads its detection.json:

  pushes, falls         trials, and those that fell within the horizon
  threshold             detector.capture_margin [m] the figures are for (the configured default)
  lead_time_median_s    trigger to the first non-foot contact, median over the detected falls [s]
  lead_time_p5_s        its 5th percentile [s]
  missed_falls          falls without a trigger before the contact
  false_triggers        survived pushes during which the detector said "fall"
  update_median_ms      one FallDetector.update on this CPU, one thread [ms]

    python benchmarks/fall_detection.py [--pushes 512] [--out DIR] [-- key=value …]

`--out` keeps the run (detection.md, the plots) in DIR. Overrides after `--` go to mode=detect (e.g. `-- detector.capture_margin=0.06` or `-- robot=go1`).
The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from fallkit_cli import fallkit


def update_time_ms(repeats: int = 20) -> float:
    """Median time of one update over the states of a pushed biped20 (recorded once, replayed)."""
    import mujoco

    from fallkit.config.detector import DetectorConfig
    from fallkit.deploy.detector import FallDetector
    from fallkit.deploy.fall_detection import estimate, standing_qpos
    from fallkit.robots import get_robot
    from fallkit.robots.kinematics import detector_export
    from fallkit.sim.base import Layout

    spec = get_robot("biped20")
    detector = FallDetector(detector_export(spec, DetectorConfig()))
    model, lay = spec.mj_model(), Layout(spec)
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = standing_qpos(spec), spec.nominal_q()
    mujoco.mj_forward(model, data)
    states = []
    for k in range(50):  # 1 s: a 6 N·s push forward over the first 0.1 s
        data.xfrc_applied[model.body(spec.root_body).id, 0] = 60.0 if k < 5 else 0.0
        states.append(estimate(data, lay))
        for _ in range(spec.substeps):
            mujoco.mj_step(model, data)
    times = []
    for _ in range(repeats):
        for s in states:
            t = time.perf_counter()
            detector.update(s)
            times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pushes", type=int, default=512)
    parser.add_argument("--out", type=Path, default=None, help="keep the run directory here")
    parser.add_argument("overrides", nargs="*", help="key=value for mode=detect (after --)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        start = time.perf_counter()
        stdout = fallkit("mode=detect", f"detector.pushes.count={args.pushes}", f"hydra.run.dir={out}", *args.overrides,
                         quiet=True)  # fmt: skip
        seconds = time.perf_counter() - start
        print(stdout)
        report = json.loads((out / "detection.json").read_text())
    t = {k: round(v, 4) if isinstance(v, float) else v for k, v in report["table"].items()}
    print(json.dumps({
        "pushes": t["pushes"], "falls": t["falls"], "threshold": t["capture_margin"],
        "lead_time_median_s": t["lead_time_median_s"], "lead_time_p5_s": t["lead_time_p5_s"],
        "missed_falls": t["missed_falls"], "false_triggers": t["false_triggers"], "survived": t["survived"],
        "late_falls": t["late_falls"], "update_median_ms": round(update_time_ms(), 4), "seconds": round(seconds, 1),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
