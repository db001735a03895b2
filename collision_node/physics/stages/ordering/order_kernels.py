"""Compiled kernel of the spatial order: the rows sorted by cell, in one counting sort.

Serial on purpose: a counting sort's placement is sequential, and one
pass over the particles costs a few per cent of the full pair search it
comes with. The order depends on the positions alone, never on threads.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from ...model.tunables import SPATIAL_ORDER_CELLS_PER_PARTICLE


class CellOrder(NamedTuple):
    """The rows in cell order: new row k holds old row ``order[k]``."""

    order: np.ndarray           # (n,) int64, a permutation of 0..n-1
    moved: bool                 # False: already in cell order (``order`` is 0..n-1)


@njit(cache=True, nogil=True)
def _cells_per_axis(extent, side, n):
    """Return the cell side and cells per axis, widening the side until cells <= share * n."""
    most = SPATIAL_ORDER_CELLS_PER_PARTICLE * n + 8.0
    counts = np.ones(3)
    while True:
        for axis in range(3):
            counts[axis] = np.floor(extent[axis] / side) + 1.0
        total = counts[0] * counts[1] * counts[2]
        if total <= most:
            return side, counts
        # Widen by the cube root of the excess (at least 25 %): a few rounds at most.
        side *= max(1.25, (total / most) ** (1.0 / 3.0))


@njit(cache=True, nogil=True)
def cell_order(points, side):
    """Return the rows of ``points`` (n, 3) sorted by cell of ``side`` metres: z, y, x.

    A stable counting sort: rows of one cell keep their relative order, so
    a world already in order gets 0..n-1 back (``moved`` False).
    """
    n = points.shape[0]
    order = np.arange(n)
    if n < 2:
        return CellOrder(order, False)
    low = points[0].copy()
    high = points[0].copy()
    for k in range(1, n):
        for axis in range(3):
            value = points[k, axis]
            if value < low[axis]:
                low[axis] = value
            if value > high[axis]:
                high[axis] = value
    side, counts = _cells_per_axis(high - low, side, n)
    nx, ny = np.int64(counts[0]), np.int64(counts[1])
    cells = nx * ny * np.int64(counts[2])
    key = np.empty(n, dtype=np.int64)
    start = np.zeros(cells + 1, dtype=np.int64)
    for k in range(n):
        cx = min(np.int64((points[k, 0] - low[0]) / side), nx - 1)
        cy = min(np.int64((points[k, 1] - low[1]) / side), ny - 1)
        cz = min(np.int64((points[k, 2] - low[2]) / side), np.int64(counts[2]) - 1)
        key[k] = (cz * ny + cy) * nx + cx
        start[key[k] + 1] += 1
    for c in range(cells):
        start[c + 1] += start[c]
    moved = False
    for k in range(n):
        at = start[key[k]]
        start[key[k]] = at + 1
        order[at] = k
        if at != k:
            moved = True
    return CellOrder(order, moved)


def warm_up() -> None:
    """Call the kernel once on a tiny problem (compiles or loads from the cache)."""
    cell_order(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), 0.5)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [cell_order]
