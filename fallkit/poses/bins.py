"""Orientation bins and sides of settled poses, and how the kept poses are split into train and test.

Settled poses are binned by the direction of gravity in the root frame (an
equal-area grid on the unit sphere, `OrientationBins`) and classed by the side
facing the ground (`side_index`); `fallkit.poses.balance` decides how many poses
each side's part of a bin keeps (paper Sec. IV-C, step 5). `format_histogram`
prints the bins as a table; `pick_and_split` takes the kept poses of each bin and
splits them into train and test, every bin proportionally represented in both.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from fallkit.pose_format import _SIDE_AXES, ground_sides
from fallkit.rotations import gravity_in_frame, quat_mul


class OrientationBins:
    """Equal-area bins of the unit sphere for the ground direction in the root frame.

    The ground direction d = -R(q)ᵀ e_z names the side of the robot that faces
    the ground (+x front, -x back, +y left, -y right, -z feet, +z head). Bands
    are equal steps of d_z (Archimedes: equal areas), sectors equal steps of the
    azimuth with sector 0 centred on +x (lying on the front), so front, back and
    both sides each sit in the middle of a sector. With an even number of bands,
    lying flat (d_z = 0) is on a band boundary: slight tilts towards head or feet
    land in the two neighbouring bands.
    """

    def __init__(self, bands: int, sectors: int):
        self.bands, self.sectors = bands, sectors

    @property
    def count(self) -> int:
        return self.bands * self.sectors

    def down(self, root_quat: torch.Tensor) -> torch.Tensor:
        return -gravity_in_frame(root_quat.double())

    def index(self, root_quat: torch.Tensor) -> torch.Tensor:
        """Bin [n] (long) of each orientation [n, 4]."""
        return self.index_down(self.down(root_quat))

    def index_down(self, d: torch.Tensor) -> torch.Tensor:
        """Bin [n] (long) of each ground direction [n, 3] (unit vectors in the root frame)."""
        band = ((d[:, 2] + 1.0) * 0.5 * self.bands).long().clamp(0, self.bands - 1)
        azimuth = torch.atan2(d[:, 1], d[:, 0]) + math.pi / self.sectors  # sector 0 centred on +x
        sector = (torch.remainder(azimuth, 2 * math.pi) / (2 * math.pi) * self.sectors).long()
        return band * self.sectors + sector.clamp(0, self.sectors - 1)

    def sample(self, bins: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Root orientations [n, 4] whose ground direction is uniform within each given bin [n]
        (equal area: d_z uniform in the band, azimuth uniform in the sector), heading random."""
        n = len(bins)
        u = torch.rand(n, 3, generator=generator, dtype=torch.float64)
        band, sector = (bins // self.sectors).double(), (bins % self.sectors).double()
        dz = -1.0 + 2.0 * (band + u[:, 0]) / self.bands
        phi = (sector + u[:, 1] - 0.5) * (2 * math.pi / self.sectors)
        r = torch.sqrt((1.0 - dz * dz).clamp(min=0.0))
        down = torch.stack((r * torch.cos(phi), r * torch.sin(phi), dz), dim=-1)
        # the rotation taking the root-frame vector -down (up, as the root sees it) to world +z ...
        up = -down
        w = 1.0 + up[:, 2]  # quaternion of the shortest arc from `up` to e_z, unnormalised: (1 + u·e_z, u × e_z)
        xyz = torch.stack((up[:, 1], -up[:, 0], torch.zeros_like(w)), dim=-1)
        flip = w < 1e-9  # up = -e_z exactly: half a turn about x
        q = torch.cat((w[:, None], xyz), dim=-1)
        q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64)
        q = q / q.norm(dim=-1, keepdim=True)
        # ... then a random heading about world z (left-multiplied: it does not change the bin)
        yaw = (2.0 * u[:, 2] - 1.0) * math.pi
        heading = torch.stack((torch.cos(yaw / 2), torch.zeros_like(yaw), torch.zeros_like(yaw), torch.sin(yaw / 2)), -1)
        return quat_mul(heading, q)

    def cell(self, root_quat: torch.Tensor) -> torch.Tensor:
        """Cell [n] (long) of each orientation [n, 4]: side × count + bin, one side's part of one bin."""
        return side_index(root_quat) * self.count + self.index(root_quat)

    def sample_cells(self, cells: torch.Tensor, generator: torch.Generator, tries: int = 200) -> torch.Tensor:
        """Root orientations [n, 4] in the given cells [n]: drawn in the cell's bin until its side is
        right too (only the misses are drawn again; a bin's corner, 9 % of it, is missed 200 times with
        probability 1e-8; the last draw stays when a sliver keeps being missed)."""
        quat = self.sample(cells % self.count, generator)
        for _ in range(tries):
            miss = torch.nonzero(side_index(quat) != cells // self.count).squeeze(1)
            if len(miss) == 0:
                break
            quat[miss] = self.sample(cells[miss] % self.count, generator)
        return quat

    def cell_areas(self) -> np.ndarray:
        """[sides, bins]: the share of the sphere of ground directions in each side's part of each bin
        (a cell), from a fine midpoint grid of (d_z, azimuth): uniform in both is uniform in area."""
        nz, nphi = 120 * self.bands, 120 * self.sectors
        z = torch.linspace(-1, 1, nz + 1, dtype=torch.float64)[:-1] + 1.0 / nz
        phi = torch.linspace(-math.pi, math.pi, nphi + 1, dtype=torch.float64)[:-1] + math.pi / nphi
        z, phi = torch.meshgrid(z, phi, indexing="ij")
        r = torch.sqrt(1 - z * z)
        d = torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), -1).reshape(-1, 3)
        cell = side_of_down(d) * self.count + self.index_down(d)
        return np.bincount(cell.numpy(), minlength=len(SIDES) * self.count).reshape(len(SIDES), -1) / len(d)

    def sector_labels(self) -> list[str]:
        """The side facing the ground in each sector (degrees where there are not 8 sectors)."""
        if self.sectors == 8:
            return ["front", "front-left", "left", "back-left", "back", "back-right", "right", "front-right"]
        return [f"{360 * s / self.sectors:.0f}°" for s in range(self.sectors)]

    def describe(self) -> dict[str, Any]:
        return {
            "bands": self.bands,
            "sectors": self.sectors,
            "vector": "ground direction in the root frame, -R(q)^T e_z",
            "band": "equal steps of its z component from -1 (feet down) to +1 (head down)",
            "sector": "equal steps of atan2(y, x), sector 0 centred on +x (front down), counter-clockwise",
        }


SIDES = tuple(_SIDE_AXES)  # front, back, left, right, bottom, top: the sides of `side_index`
_AXES = torch.tensor(list(_SIDE_AXES.values()), dtype=torch.float64)


def side_of_down(d: torch.Tensor) -> torch.Tensor:
    """Side [n] (index into SIDES) of ground directions [n, 3]: the root axis nearest to straight down,
    first of SIDES on a tie (as `ground_sides`)."""
    return (d.double() @ _AXES.T).argmax(dim=1)


def side_index(root_quat: torch.Tensor) -> torch.Tensor:
    """Side [n] (index into SIDES) of each orientation [n, 4]: `ground_sides`, the side_shares' classes."""
    words = ground_sides(torch.as_tensor(root_quat).double().reshape(-1, 4).numpy())
    return torch.from_numpy((words[:, None] == np.array(SIDES)).argmax(axis=1))


def side_shares(root_quat: torch.Tensor) -> dict[str, float]:
    """Share of the poses lying on each side (front, back, left, right, bottom, top): the side
    whose axis is nearest to straight down, as an artist file's `ground` names it."""
    sides = ground_sides(torch.as_tensor(root_quat).double().reshape(-1, 4).numpy())
    return {name: float((sides == name).sum()) / max(1, len(sides)) for name in _SIDE_AXES}


def format_histogram(counts: list[int] | np.ndarray, bins: OrientationBins, rare: list[int] = ()) -> str:
    """The bins as a text table (bands as rows, head-down band first), rare bins marked *."""
    grid = np.asarray(counts).reshape(bins.bands, bins.sectors)
    edges = np.linspace(-1, 1, bins.bands + 1)
    head = " " * 13 + "".join(f"{s:>12s}" for s in bins.sector_labels())
    rows = [head]
    for b in reversed(range(bins.bands)):
        cells = "".join(f"{grid[b, s]:>11d}{'*' if b * bins.sectors + s in rare else ' '}" for s in range(bins.sectors))
        rows.append(f"z {edges[b]:+.2f}..{edges[b + 1]:+.2f}" + cells)
    return "\n".join(rows)


# ---- keeping and splitting ----------------------------------------------------------------------


def pick_and_split(bins: np.ndarray, keep: np.ndarray, test: int, g: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rows to keep and their split: keep[b] of each bin b, the train rows first, each split in random order."""
    pick = _take_per_bin(bins, keep)  # the first poses of each bin, in drop order
    split = _stratified_split(bins[pick], test, g)
    order = torch.randperm(len(pick), generator=g).numpy()  # random order: any prefix is a random subset
    order = np.concatenate([order[split[order] == "train"], order[split[order] == "test"]])
    return pick[order], split[order]


def _take_per_bin(bins: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Indices of the first keep[b] poses of every bin b (drop order), ascending."""
    order = np.argsort(bins, kind="stable")
    start = np.searchsorted(bins[order], np.arange(len(keep)))
    rank = np.empty(len(bins), np.int64)
    rank[order] = np.arange(len(bins)) - start[bins[order]]
    return np.flatnonzero(rank < keep[bins])


def _stratified_split(bins: np.ndarray, test: int, g: torch.Generator) -> np.ndarray:
    """'train'/'test' per pose, with every bin's share of the test set proportional to its size."""
    n = len(bins)
    split = np.full(n, "train", dtype="<U5")
    if test == 0:
        return split
    sizes = np.bincount(bins, minlength=int(bins.max()) + 1)
    exact = sizes * test / n
    quota = np.floor(exact).astype(np.int64)
    extra = test - int(quota.sum())
    quota[np.argsort(-(exact - quota), kind="stable")[:extra]] += 1  # largest remainders
    shuffled = torch.randperm(n, generator=g).numpy()
    taken = np.zeros_like(sizes)
    for i in shuffled:
        b = bins[i]
        if taken[b] < quota[b]:
            split[i] = "test"
            taken[b] += 1
    return split
