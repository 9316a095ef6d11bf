"""Pictures of end poses: a PNG contact sheet and the orientation-bin histogram.

The sheet draws each pose with MuJoCo's offscreen renderer (`fallkit.eval.render.FallPainter`,
OSMesa or EGL; see fallkit/__init__.py), seen from the side of the robot's long
axis, labelled, tiled into a grid. The histogram shows the orientation bins
(`OrientationBins`) before and after rebalancing as two heat maps.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless; before pyplot is imported anywhere
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from fallkit.errors import FallkitError  # noqa: E402
from fallkit.eval.render import FallPainter, label  # noqa: E402
from fallkit.poses.artist import artist_file, read_artist_poses, settle_artist_poses  # noqa: E402
from fallkit.poses.bins import OrientationBins  # noqa: E402
from fallkit.poses.checker import PoseChecker  # noqa: E402
from fallkit.robots import get_robot  # noqa: E402
from fallkit.robots.spec import RobotSpec  # noqa: E402


def _view(model: mujoco.MjModel, data: mujoco.MjData, root_body: int) -> tuple[np.ndarray, float]:
    """Look-at point (whole-body centre of mass) and an azimuth facing the side of the long axis."""
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    com = data.subtree_com[root_body].copy()
    axis = data.xmat[root_body].reshape(3, 3)
    long_axis = axis[:, 2]  # root z: head to feet
    if np.hypot(long_axis[0], long_axis[1]) < 0.5:  # upright or head down: look at the front
        long_axis = axis[:, 0]
        return com, math.degrees(math.atan2(long_axis[1], long_axis[0])) + 180.0 + 35.0
    return com, math.degrees(math.atan2(long_axis[1], long_axis[0])) + 90.0 + 25.0


def render_poses(
    spec: RobotSpec, qpos: np.ndarray, titles: list[str], width: int = 240, height: int = 180, distance: float = 1.5
) -> list[np.ndarray]:
    """One labelled picture [H, W, 3] per MuJoCo-layout pose qpos [n, nq] (robot at rest, no forces drawn)."""
    qpos = np.asarray(qpos, dtype=np.float64)
    images = []
    with FallPainter(spec, width, height, distance=distance) as painter:
        painter.option.flags[mujoco.mjtVisFlag.mjVIS_CONTACTFORCE] = False
        root = painter.layout.root_body
        zero_v = np.zeros(painter.model.nv)
        zero_t = np.zeros(len(spec.joints))
        for q, title in zip(qpos, titles):
            painter.data.qpos[:] = q
            point, azimuth = _view(painter.model, painter.data, root)
            painter.look_at(point, azimuth)
            painter.camera.elevation = -30.0
            images.append(label(painter.frame(q, zero_v, zero_t), [title]))
    return images


def tile(images: list[np.ndarray], cols: int, gap: int = 2) -> np.ndarray:
    """Images of one size in a grid, row by row, on a white background."""
    h, w, _ = images[0].shape
    rows = math.ceil(len(images) / cols)
    sheet = np.full((rows * (h + gap) - gap, cols * (w + gap) - gap, 3), 255, np.uint8)
    for i, im in enumerate(images):
        r, c = divmod(i, cols)
        sheet[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = im
    return sheet


def write_png(image: np.ndarray, path: Path) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)
    return path


def contact_sheet(spec: RobotSpec, qpos: np.ndarray, titles: list[str], path: Path, cols: int = 6) -> Path:
    """Render poses [n, nq] and write them as one PNG grid."""
    return write_png(tile(render_poses(spec, qpos, titles), cols=min(cols, len(titles))), Path(path))


def histogram_plot(
    before: np.ndarray, after: np.ndarray, rare: list[int], bands: int, sectors: int, path: Path, title: str = ""
) -> Path:
    """Heat maps of the orientation bins (bands × sectors) before and after rebalancing, counts written in."""
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), constrained_layout=True)
    edges = np.linspace(-1, 1, bands + 1)
    band_labels = [f"{edges[b]:+.2f}..{edges[b + 1]:+.2f}" for b in range(bands)]
    rare_mask = np.zeros(bands * sectors, bool)
    rare_mask[list(rare)] = True
    for ax, counts, name in ((axes[0], before, "before (every drop)"), (axes[1], after, "after rebalancing (kept)")):
        grid = np.asarray(counts).reshape(bands, sectors)
        im = ax.imshow(grid, cmap="viridis", origin="lower", aspect="auto")
        for b in range(bands):
            for s in range(sectors):
                rare_bin = rare_mask[b * sectors + s]
                txt = f"{grid[b, s]}" + ("*" if rare_bin else "")
                color = "white" if grid[b, s] < 0.6 * grid.max() else "black"
                ax.text(s, b, txt, ha="center", va="center", fontsize=8, color=color)
        ax.set_xticks(range(sectors), OrientationBins(bands, sectors).sector_labels(), rotation=30, fontsize=8)
        ax.set_yticks(range(bands), band_labels, fontsize=8)
        ax.set_xlabel("side facing the ground (azimuth of the ground direction in the root frame)")
        ax.set_ylabel("ground direction z (−1 feet down, +1 head down)")
        ax.set_title(f"{name}: {int(np.sum(counts))} poses", fontsize=10)
        fig.colorbar(im, ax=ax, shrink=0.85)
    fig.suptitle((title + "   " if title else "") + "* rare bin: reached too seldom to be levelled, outside the uniformity test", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def artist_sheet(spec: RobotSpec, source: str | Path, path: Path) -> Path:
    """Each pose of an artist file as authored (left) and after settling (right), one pair per row."""
    file = artist_file(spec) if str(source) == "artist" else Path(source)
    poses = read_artist_poses(file, spec)
    _, settled = settle_artist_poses(file, spec, poses)
    n = len(poses)
    authored, _ = PoseChecker(spec).on_ground(
        np.stack([p.root_quat for p in poses]), np.stack([p.joint_pos for p in poses]), 0.0
    )
    images = render_poses(
        spec,
        np.concatenate([authored.numpy(), settled.numpy()])[np.arange(2 * n).reshape(2, n).T.ravel()],
        [t for p in poses for t in (f"{p.name} (authored)", f"{p.name} (settled)")],
    )
    return write_png(tile(images, cols=4), Path(path))


def main(argv: list[str] | None = None) -> None:
    """`python -m fallkit.eval.contact_sheet POSES.yaml [--robot biped20] [--out sheet.png]`: look at artist poses."""
    import argparse


    ap = argparse.ArgumentParser(description="Render artist poses as authored and after settling (PNG).")
    ap.add_argument("poses", help="an artist pose file (.yaml), or 'artist' for the robot's own")
    ap.add_argument("--robot", default="biped20")
    ap.add_argument("--out", default="poses.png")
    args = ap.parse_args(argv)
    try:
        print(artist_sheet(get_robot(args.robot), args.poses, Path(args.out)))
    except FallkitError as exc:  # PoseFileError: one line naming file and line
        raise SystemExit(f"fallkit: error: {exc}") from None


if __name__ == "__main__":
    main()
