"""`mode=poses`: generate a robot's end-pose dataset, then report it.

The report is the statistics and bin histograms printed to the terminal, the
orientation-bin heat maps, and contact sheets of a random sample of the generated
poses and of the robot's artist poses (settled). Rendering problems only warn: the
dataset is the product.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fallkit.config import DatasetConfig, FallkitConfig
from fallkit.errors import RenderError
from fallkit.eval.contact_sheet import contact_sheet, histogram_plot
from fallkit.poses.artist import read_artist_poses, settle_artist_poses, shipped_artist_file
from fallkit.poses.bins import OrientationBins, format_histogram
from fallkit.poses.dataset import load_dataset, save_dataset
from fallkit.poses.generator import EndPoseGenerator, to_dataset
from fallkit.robots import robot_spec
from fallkit.robots.spec import RobotSpec
from fallkit.sim import Layout, sim_options

log = logging.getLogger(__name__)


def run_poses(config: FallkitConfig, run_dir: Path) -> Path:
    """`mode=poses`: generate the dataset, then draw its contact sheets and bin histogram into the run dir."""
    spec = robot_spec(config.robot)
    pc: DatasetConfig = config.dataset
    backend = config.sim.backend
    torch.set_num_threads(1)  # the cores belong to MuJoCo's physics threads (torch's beside them slow it down)
    log.info(
        "end poses for %s: %d train + %d test, seed %d, %d worlds on %s",
        spec.name, pc.train, pc.test, pc.seed, pc.num_worlds, backend,
    )  # fmt: skip
    gen = EndPoseGenerator(spec, pc, backend, **sim_options(config.sim)).run()
    st = gen.stats
    out = Path(pc.out) if pc.out else run_dir / f"{spec.name}_poses.npz"
    save_dataset(out, to_dataset(spec, gen, pc, backend))
    (run_dir / "poses_stats.json").write_text(json.dumps(st, indent=2))
    bins = OrientationBins(pc.bands, pc.sectors)
    rate = st["physics_steps"] / max(st["seconds"], 1e-9)
    print(
        f"\n{spec.name}: {st['kept']} end poses ({pc.train} train, {pc.test} test) from {st['drops']} drops in "
        f"{st['seconds']:.0f} s ({rate / 1e3:.0f}k physics steps/s)\n"
        f"  settled {st['settled']} (mean {st['mean_settle_seconds']:.2f} s), stopped early in over-full bins "
        f"{st['aborted_overfull']}, never at rest {st['unsettled']}, unstable {st['unstable']}, "
        f"settled but over-full {st['discarded_overfull']}, in flight at the end {st['in_flight_at_stop']}\n"
        f"  covered bins uniform to {st['uniformity']:.2f} (tolerance {pc.tolerance}: >= {1 - pc.tolerance:.2f}); "
        f"{len(st['rare_bins'])} of {bins.count} bins rare (reached < {pc.min_share} of a uniform share: outside the "
        "uniformity test)\n"
        f"  lying on (front/back/left/right/bottom/top): {st.get('sides_after', 'n/a')}; rare sides {st.get('rare_sides', [])}"
    )
    print("orientation bins before rebalancing (every drop, by where it came to rest or was stopped):")
    print(format_histogram(st["hist_before"], bins, st["rare_bins"]))
    print("after rebalancing (kept poses; * rare):")
    print(format_histogram(st["hist_after"], bins, st["rare_bins"]))
    print(f"dataset: {out}")
    _pictures(spec, pc, load_dataset(out), st, run_dir)
    return out


def _pictures(spec: RobotSpec, pc: DatasetConfig, ds, st: dict[str, Any], run_dir: Path) -> None:
    """Contact sheets (generated sample, artist poses) and the histogram plot; rendering problems only warn."""
    hist = histogram_plot(
        np.array(st["hist_before"]), np.array(st["hist_after"]), st["rare_bins"], pc.bands, pc.sectors,
        run_dir / "orientation_bins.png", title=f"{spec.name}: orientation bins",
    )  # fmt: skip
    print(f"bin histogram: {hist}")
    try:
        if pc.sheet:
            k = min(pc.sheet, len(ds))  # rows are stored in random order: the first k are a random sample
            lay = Layout(spec)
            q = lay.qpos(
                torch.zeros(k, 3, dtype=torch.float64),
                torch.from_numpy(ds.root_quat[:k]).double(),
                torch.from_numpy(ds.joint_pos[:k]).double(),
            )
            q[:, lay.root_qpos + 2] = torch.from_numpy(ds.root_height[:k]).double()
            titles = [f"#{i} {ds.split[i]}, bin {ds.bin[i]}" for i in range(k)]
            sheet = contact_sheet(spec, q.numpy(), titles, run_dir / "poses_generated.png")
            print(f"contact sheet (generated sample): {sheet}")
        path = shipped_artist_file(spec) if pc.artist == "artist" else Path(pc.artist) if pc.artist else None
        if pc.artist == "artist" and path is None:
            print(f"artist poses: skipped (robot '{spec.name}' ships none; dataset.artist=<file.yaml> draws yours)")
        elif path is not None:
            poses = read_artist_poses(path, spec)
            _, settled = settle_artist_poses(path, spec, poses)
            sheet = contact_sheet(spec, settled.numpy(), [p.name for p in poses], run_dir / "poses_artist.png", cols=5)
            print(f"contact sheet (artist poses, settled): {sheet}")
    except RenderError as exc:
        log.warning("contact sheets skipped: %s", exc)
