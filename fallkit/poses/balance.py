"""Rebalancing: how many of the settled poses each orientation cell keeps (paper Sec. IV-C, step 5).

A settled pose is classed twice: by its side, the root axis nearest to straight down
(front, back, left, right, bottom, top; `side_index`, the words of an artist file's
`ground`), and by its equal-area orientation bin (`OrientationBins`). A cell is one
side's part of one bin. The poses are levelled in two steps, both "water filling":

1. sides: every side gets the same quota; the sides the robot reaches less often than
   `side_min_share` × a uniform share (1/6) are rare (sitting upright, on the head):
   they keep what they get and stay out of the test;
2. cells of a side: the side's quota is spread over its cells in proportion to their
   areas, so within a side the poses are uniform over the orientations; the cells a
   side reaches less often than `min_share` × their uniform share of all drops (by area),
   and slivers of bins, stay out of the test.

Why sides first: a falling robot rolls off its sides onto its front or back (biped20:
11 % of the settled drops on each side, 37-38 % on each of front and back; flat on a side with
the head low, 0.2 %). A common level over all bins (the paper's words) leaves the sides at
half the share of front and back unless ~450 000 drops fill those bins; levelling the
sides as wholes needs only the drops that land anywhere on a side (docs/poses.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_BIG = 1e15  # "as many poses as wanted": a covered side or cell when bounding the final level
# Where a side's boundary grazes the corner of a bin, the side's part of it is a sliver (0.2 % of the
# bin for 6 x 8 bins: a pose or two at the level); the next smallest parts are 9 % of a bin.
_SLIVER = 0.01  # of a bin's area: such parts are left out of the test


def water_level(counts: np.ndarray, weight: np.ndarray, need: float) -> float:
    """The largest level L with sum(min(counts, L × weight)) <= need (weights > 0); inf when all counts fit."""
    counts, weight = np.asarray(counts, np.float64), np.asarray(weight, np.float64)
    if counts.sum() <= need:
        return math.inf
    order = np.argsort(counts / weight, kind="stable")
    ratio, c, w = counts[order] / weight[order], counts[order], weight[order]
    below = np.concatenate(([0.0], np.cumsum(c)[:-1]))  # kept whole: the cells with a lower ratio
    at_level = np.cumsum(w[::-1])[::-1]  # weight of the cells from i on, each at L × weight
    level = (need - below) / at_level
    return float(level[np.argmax(level <= ratio)])  # the first segment that holds its own solution


def fill(counts: np.ndarray, weight: np.ndarray, need: int) -> np.ndarray:
    """Poses to keep per cell: min(counts, L × weight) summing to `need` (all counts when fewer);
    the remainder of the rounding goes one each to the cells still above it, in cell order."""
    level = water_level(counts, weight, need)
    if math.isinf(level):
        return np.asarray(counts, np.int64).copy()
    keep = np.minimum(counts, np.floor(level * np.asarray(weight) * (1 - 1e-12)).astype(np.int64))
    rest = int(need - keep.sum())
    keep[np.flatnonzero(counts > keep)[:rest]] += 1
    return keep


def _spread(values: np.ndarray) -> float:
    """Smallest / largest (1 = even); 1 for nothing to compare."""
    return float(values.min() / values.max()) if len(values) and values.max() > 0 else 1.0


def _spread_per_area(keep: np.ndarray, area: np.ndarray) -> float:
    """Smallest / largest kept per area, give or take one pose each: the water filling rounds each part
    to whole poses, and a small part (a bin's corner: ~70 poses at the level, a dozen in a small run)
    must not fail on that rounding alone."""
    if len(keep) == 0:
        return 1.0
    top = (np.maximum(keep - 1, 0) / area).max()
    return float(min(1.0, ((keep + 1) / area).min() / top)) if top > 0 else 1.0


@dataclass
class Balance:
    """The rebalancing decision for the poses settled so far; arrays are [sides, bins]."""

    keep: np.ndarray  # poses to keep per cell
    rare: np.ndarray  # bool: cells outside the uniformity test (in a rare side, too rarely reached, or a sliver)
    rare_side: np.ndarray  # [sides] bool
    cap: np.ndarray  # the most a cell can keep once the sides are level: a drop ending in a cell that holds it is lost
    feasible: bool  # enough poses settled
    uniformity: float  # the worse of: covered sides' smallest / largest kept; covered cells' per area, side by side
    done: bool  # feasible and uniform within the tolerance

    @classmethod
    def of(cls, counts: np.ndarray, seen: np.ndarray, area: np.ndarray, total: int, *, min_share: float,
           side_min_share: float, tolerance: float) -> "Balance":  # fmt: skip
        """counts: settled poses per cell; seen: drops per cell, those stopped early included (the robot's
        natural frequencies: they decide what is rare); area: each cell's share of the sphere."""
        sides = counts.shape[0]
        side_seen = seen.sum(1)
        rare_side = side_seen < side_min_share * side_seen.sum() / sides
        uniform = seen.sum() * area / area.sum()  # each cell's uniform share of the drops
        sliver = area < _SLIVER * area.sum() / area.shape[1]
        rare = sliver | rare_side[:, None] | (seen < min_share * uniform)
        weight = np.maximum(area, 1e-12)
        quota = fill(counts.sum(1), np.ones(sides), total)
        keep = np.stack([fill(counts[s], weight[s], int(quota[s])) for s in range(sides)])
        tests = [_spread(quota[~rare_side])]
        tests += [_spread_per_area(keep[s][~rare[s]], weight[s][~rare[s]]) for s in np.flatnonzero(~rare_side)]
        uniformity = min(tests)
        feasible = int(counts.sum()) >= total
        cap = _caps(counts, weight, rare, rare_side, total)
        return cls(keep, rare, rare_side, cap, feasible, uniformity, feasible and uniformity >= 1 - tolerance)

    def full(self, counts: np.ndarray) -> np.ndarray:
        """Cells [sides, bins] that already hold their cap."""
        return counts >= self.cap

    def useful(self, counts: np.ndarray) -> int:
        """Settled poses that rebalancing can keep (progress)."""
        return int(np.minimum(counts, self.cap).sum())


def _caps(counts: np.ndarray, weight: np.ndarray, rare: np.ndarray, rare_side: np.ndarray, total: int) -> np.ndarray:
    """Per cell, the most it keeps once done (covered sides and cells at their level, rare ones keeping
    what they have): the level of a side, or of a side's cells, only falls as more poses settle."""
    quota = water_level(np.where(rare_side, counts.sum(1), _BIG), np.ones(len(rare_side)), total)
    cap = np.full(counts.shape, np.inf)
    for s in range(len(rare_side)):
        level = water_level(np.where(rare[s], counts[s], _BIG), weight[s], quota)
        cap[s] = level * weight[s]
    return cap
