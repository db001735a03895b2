"""The broadphase's searches, compiled: a hashed cell grid per size class.

``broadphase.size_classes`` splits particles into classes whose reaches
differ by less than a factor of two. Each class gets a uniform grid of
cubic cells, twice its largest reach wide, built by a counting sort: cells
are hashed into about twice as many buckets as the class has particles, so
the grid costs O(n) memory whatever the scene's extent (a particle at 1e9 m
next to a cluster at the origin adds one bucket, not 1e9 / cell cells), and
each bucket's particles are stored contiguously with their cell and
position (cache-friendly scans). A class whose occupied box is small gets a
dense table instead (one bucket per cell, no hashing).

A particle of reach r is searched in its own class and in every larger
class k, within r + R_k of its centre (R_k the class's largest reach): at
most 3 cells per axis, because r <= R_k and the cells are 2 R_k wide. A
large particle is never searched with a small one's grid, nor a small one
with a large one's reach, so the work stays proportional to the number of
near pairs for any mix of sizes. A pair is kept only if
|p_i - p_j|^2 <= (reach_i + reach_j)^2 (1 + PAIR_SLACK); pairs come out
sorted by (i, j) (a counting sort by i, then each row sorted by j).

One size class in a dense table (a gas) takes a shorter path,
``_dense_pairs``: cells are a little wider than any search (CELL_MARGIN),
so each item scans its own row of cells from itself on and the next four
rows in cell order, without computing a search box, and every candidate is
written and kept by the count (no branch on the near test).

Cell indices are measured from the lowest corner of all particles and a
cell is never narrower than the scene's extent / 2^40, so they fit in
64-bit integers at any scale. A query box with more cells than the class
has particles (a very fast mover) scans the class's particles directly.

Every search is bounded (``SearchLimit``): its buffers never grow past
the most pairs the step's memory budget allows, and a search along paths
(``PathMotion``: fast movers kept only if their straight paths meet)
makes a bounded number of tests. Over a bound a search gives up and
returns an estimate of what it would need (``Found``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401 (chooses numba's cache directory first)
from ...law.primitives import dot3

from numba import njit, prange  # noqa: E402,I100 (after the cache directory is chosen)
from ...model.tunables import (PAIR_SLACK, SCAN_SLACK, MAX_CELLS_PER_AXIS, CELL_REACHES,
                               DENSE_CELLS_PER_ITEM, CELL_MARGIN, DENSE_AXIS_CELLS, PATH_SLACK,
                               PARALLEL_BLOCK_ITEMS)

# Multipliers of the cell hash (large odd constants: neighbouring cells
# land in unrelated buckets).
_H1, _H2, _H3 = 0x9E3779B97F4A7C15 - (1 << 64), 0xC2B2AE3D27D4EB4F - (1 << 64), 0x165667B19E3779F9


class Grid(NamedTuple):
    """One grid per size class; classes in ``order``, ``class_start`` slices."""

    corner: np.ndarray          # (3,) lowest corner of all particles, m
    cell: np.ndarray            # (classes,) cell width, m
    class_reach: np.ndarray     # (classes,) largest reach of each class, m
    class_start: np.ndarray     # (classes + 1,) each class's slice of the items
    low: np.ndarray             # (classes, 3) lowest occupied cell index per axis
    high: np.ndarray            # (classes, 3) highest occupied cell index per axis
    dense: np.ndarray           # (classes,) one bucket per cell (else hashed cells)
    table_start: np.ndarray     # (classes + 1,) each class's slice of ``bucket``
    bucket: np.ndarray          # bucket b's items are bucket[b] .. bucket[b + 1] - 1
    item: np.ndarray            # particle index of each item
    item_cell: np.ndarray       # (n, 3) cell index of each item
    item_position: np.ndarray   # (n, 3) position of each item, m


class Pairs(NamedTuple):
    """Particle index pairs (first[k], second[k]): what a search returns."""

    first: np.ndarray
    second: np.ndarray


@njit(cache=True, inline='always')
def _hash(cx, cy, cz, mask):
    """Return the bucket of cell (cx, cy, cz) in a table of mask + 1 buckets."""
    h = cx * _H1 + cy * _H2 + cz * _H3
    h ^= h >> 31
    return h & mask


@njit(cache=True, inline='always')
def _dense_bucket(cx, cy, cz, lx, ly, lz, nx, ny):
    """Return the bucket of cell (cx, cy, cz) in a dense table (x fastest)."""
    return ((cz - lz) * ny + (cy - ly)) * nx + (cx - lx)


@njit(cache=True)
def _extent_in(position, begin, end, lowest, highest, row):
    """Write the least and greatest coordinate per axis of rows begin .. end - 1 to ``row``."""
    for d in range(3):
        lo, hi = position[begin, d], position[begin, d]
        for p in range(begin + 1, end):
            x = position[p, d]
            if x < lo:
                lo = x
            elif x > hi:
                hi = x
        lowest[row, d], highest[row, d] = lo, hi


@njit(cache=True)
def _cells_in(position, order, corner, width, begin, end, own_cell, low, high, row):
    """Write the cells of members begin .. end - 1 and their least and greatest to ``row``."""
    for d in range(3):
        low[row, d], high[row, d] = np.iinfo(np.int64).max, np.iinfo(np.int64).min
    for m in range(begin, end):
        p = order[m]
        for d in range(3):
            c = np.int64(np.floor((position[p, d] - corner[d]) / width))
            own_cell[m, d] = c
            low[row, d] = min(low[row, d], c)
            high[row, d] = max(high[row, d], c)


@njit(cache=True)
def _buckets_in(own_cell, dense, low, nx, ny, mask, begin, end, own_bucket):
    """Write the bucket of members begin .. end - 1 (dense: by cell; else hashed)."""
    for m in range(begin, end):
        if dense:
            own_bucket[m] = _dense_bucket(own_cell[m, 0], own_cell[m, 1], own_cell[m, 2],
                                          low[0], low[1], low[2], nx, ny)
        else:
            own_bucket[m] = _hash(own_cell[m, 0], own_cell[m, 1], own_cell[m, 2], mask)


@njit(cache=True)
def _place_in(position, order, own_cell, at, begin, end, item, item_cell, item_position):
    """Copy members begin .. end - 1 to their rows ``at`` of the grid's item arrays."""
    for m in range(begin, end):
        p = order[m]
        item[at[m]] = p
        for d in range(3):
            item_cell[at[m], d] = own_cell[m, d]
            item_position[at[m], d] = position[p, d]


class GridWork(NamedTuple):
    """``build_grid``'s per-particle arrays and each block's extremes (one row per block)."""

    lowest: np.ndarray          # (blocks, 3) least coordinate per block, m
    highest: np.ndarray         # (blocks, 3) greatest coordinate per block, m
    block_low: np.ndarray       # (blocks, 3) least cell per block
    block_high: np.ndarray      # (blocks, 3) greatest cell per block
    own_cell: np.ndarray        # (n, 3) each member's cell
    own_bucket: np.ndarray      # (n,) each member's bucket
    at: np.ndarray              # (n,) each member's row among the items
    item: np.ndarray            # the grid's item arrays, filled by placing
    item_cell: np.ndarray
    item_position: np.ndarray


@njit(cache=True, nogil=True, parallel=True)
def _blocks_shared(task, position, order, corner, width, begin, end, work, table):
    """Run one of ``build_grid``'s loops over members begin .. end - 1 in blocks on the threads.

    ``task`` 0: extents (``_extent_in``), 1: cells (``_cells_in``), 2:
    buckets (``_buckets_in``, ``table`` is (dense, low cell, nx, ny, mask)),
    3: placing (``_place_in``). Block b writes row b of the ``GridWork``'s
    extremes (combined in block order by the caller).
    """
    blocks = (end - begin + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    dense, low, nx, ny, mask = table
    for b in prange(blocks):
        first = begin + b * PARALLEL_BLOCK_ITEMS
        last = min(first + PARALLEL_BLOCK_ITEMS, end)
        if task == 0:
            _extent_in(position, first, last, work.lowest, work.highest, b)
        elif task == 1:
            _cells_in(position, order, corner, width, first, last, work.own_cell,
                      work.block_low, work.block_high, b)
        elif task == 2:
            _buckets_in(work.own_cell, dense, low, nx, ny, mask, first, last,
                        work.own_bucket)
        else:
            _place_in(position, order, work.own_cell, work.at, first, last, work.item,
                      work.item_cell, work.item_position)


@njit(cache=True)
def _least_greatest(lowest, highest, rows):
    """Return the least of ``lowest`` and the greatest of ``highest`` over their first rows."""
    lo, hi = lowest[0].copy(), highest[0].copy()
    for r in range(1, rows):
        for d in range(3):
            lo[d] = min(lo[d], lowest[r, d])
            hi[d] = max(hi[d], highest[r, d])
    return lo, hi


@njit(cache=True, nogil=True)
def build_grid(position, reach, order, class_start, shared):
    """Return every class's grid (``Grid``).

    ``order`` lists the particles class by class (``class_start`` slices);
    within a class the items are sorted by bucket, in ``order``'s order. A
    class whose occupied box has at most DENSE_CELLS_PER_ITEM cells per
    particle gets a dense table (one bucket per cell, rows of cells along
    x contiguous), any other a hashed one. ``shared``: the per-particle
    loops run in blocks on the threads (least and greatest are exact, and
    the bucket counts stay in order: the same grid).
    """
    n = position.shape[0]
    classes = class_start.size - 1
    blocks = (n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS if shared else 1
    work = GridWork(np.empty((blocks, 3)), np.empty((blocks, 3)),
                    np.empty((blocks, 3), dtype=np.int64), np.empty((blocks, 3), dtype=np.int64),
                    np.empty((n, 3), dtype=np.int64), np.empty(n, dtype=np.int64),
                    np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64),
                    np.empty((n, 3), dtype=np.int64), np.empty((n, 3)))
    own_cell, own_bucket, at = work.own_cell, work.own_bucket, work.at
    no_table = (False, np.zeros(3, dtype=np.int64), np.int64(0), np.int64(0), np.int64(0))
    if shared:
        _blocks_shared(0, position, order, np.zeros(3), 1.0, 0, n, work, no_table)
    else:
        _extent_in(position, np.int64(0), n, work.lowest, work.highest, np.int64(0))
    corner, high_corner = _least_greatest(work.lowest, work.highest, blocks)
    extent = 0.0
    for d in range(3):
        extent = max(extent, high_corner[d] - corner[d])
    cell, class_reach = np.empty(classes), np.empty(classes)
    low = np.empty((classes, 3), dtype=np.int64)
    high = np.empty((classes, 3), dtype=np.int64)
    dense = np.zeros(classes, dtype=np.bool_)
    table_start = np.zeros(classes + 1, dtype=np.int64)
    for k in range(classes):
        begin, end = class_start[k], class_start[k + 1]
        largest = 0.0
        for m in range(begin, end):
            largest = max(largest, reach[order[m]])
        class_reach[k] = largest
        width = max(CELL_REACHES * largest * (1.0 + CELL_MARGIN),
                    extent / MAX_CELLS_PER_AXIS)
        cell[k] = width if width > 0.0 else 1.0
        if shared:
            _blocks_shared(1, position, order, corner, cell[k], begin, end, work, no_table)
            rows = (end - begin + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
        else:
            _cells_in(position, order, corner, cell[k], begin, end, own_cell, work.block_low,
                      work.block_high, 0)
            rows = 1
        for d in range(3):
            low[k, d], high[k, d] = work.block_low[0, d], work.block_high[0, d]
            for r in range(1, rows):
                low[k, d] = min(low[k, d], work.block_low[r, d])
                high[k, d] = max(high[k, d], work.block_high[r, d])
        members = end - begin
        cells = 1.0
        for d in range(3):
            cells *= high[k, d] - low[k, d] + 1.0
        if cells <= DENSE_CELLS_PER_ITEM * members + 64.0:
            dense[k] = True
            size = np.int64(cells)
        else:
            size = 2
            while size < 2 * members:
                size *= 2
        table_start[k + 1] = table_start[k] + size + 1
    bucket = np.zeros(table_start[classes], dtype=np.int64)
    for k in range(classes):
        begin, end = class_start[k], class_start[k + 1]
        base, mask = table_start[k], table_start[k + 1] - table_start[k] - 2
        nx, ny = high[k, 0] - low[k, 0] + 1, high[k, 1] - low[k, 1] + 1
        if shared:
            _blocks_shared(2, position, order, corner, 1.0, begin, end, work,
                           (dense[k], low[k].copy(), nx, ny, mask))
        else:
            _buckets_in(own_cell, dense[k], low[k], nx, ny, mask, begin, end, own_bucket)
        for m in range(begin, end):
            bucket[base + own_bucket[m] + 1] += 1
        for b in range(base + 1, table_start[k + 1]):
            bucket[b] += bucket[b - 1]
        # bucket[base + b] is now where bucket b starts (relative to the class).
        for m in range(begin, end):
            b = base + own_bucket[m]
            at[m] = begin + bucket[b]
            bucket[b] += 1
        if shared:
            _blocks_shared(3, position, order, corner, 1.0, begin, end, work, no_table)
        else:
            _place_in(position, order, own_cell, at, begin, end, work.item, work.item_cell,
                      work.item_position)
        # Filling moved each start to the next bucket's: shift back by one.
        for b in range(table_start[k + 1] - 1, base, -1):
            bucket[b] = bucket[b - 1] + begin
        bucket[base] = begin
    return Grid(corner, cell, class_reach, class_start, low, high, dense, table_start, bucket,
                work.item, work.item_cell, work.item_position)


@njit(cache=True, inline='always')
def _near(ax, ay, az, bx, by, bz, limit):
    """Return |a - b|^2 <= limit^2 (1 + PAIR_SLACK), the offset's square summed as einsum does."""
    ox, oy, oz = ax - bx, ay - by, az - bz
    return dot3(ox, oy, oz, ox, oy, oz) <= limit * limit * (1.0 + PAIR_SLACK)


class SearchLimit(NamedTuple):
    """How much one search may hold and do before it gives up (see ``Found``)."""

    max_pairs: int              # pairs kept at most (their buffers never grow past it)
    max_tests: int              # pair tests at most, in a search along paths


class PathMotion(NamedTuple):
    """Straight paths over the step, for a search along paths (``active``; else unused).

    A pair is kept only if the two particles, each moving by its ``shift``
    over the step, come within their path reaches of each other at the same
    moment (the sphere test of their whole reach must pass as well).
    """

    active: bool
    shift: np.ndarray           # (n, 3) each item's displacement over the step (v dt), m
    reach: np.ndarray           # (n,) each item's reach about its path, m
    tested: np.ndarray          # (1,) int64: pair tests made so far


class Probe(NamedTuple):
    """One particle's search of one class: the box and the test's own terms."""

    point: tuple                # (x, y, z) of the particle, m
    search: float               # half width of the box searched, m
    particle: int               # its index
    after: int                  # only items after this one (-1: all)
    own_reach: float            # its reach in the sphere test, m
    shift: tuple                # its displacement over the step (path search), m
    path_reach: float           # its reach about its path (path search), m


class Found(NamedTuple):
    """A search's result: its pairs, or how many it would need when it gave up."""

    pairs: Pairs                # the pairs (empty when not ``complete``)
    complete: bool              # False: over ``SearchLimit``, pairs left out
    needed: float               # pairs found; when given up, a lower bound or an estimate
    estimated: bool             # ``needed`` extrapolated to the whole search
    tested: int                 # pair tests made along paths


@njit(cache=True, inline='always')
def _paths_meet(probe, t, item_position, motion):
    """Return whether the probe and item t come within their path reaches at one moment.

    Relative motion over the step is d + s u, s in [0, 1] (d the offset, u
    the difference of the shifts); its closest approach is at s* = -d.u / u.u
    clipped to [0, 1]. The limit gets a slack of PATH_SLACK |u| for rounding.
    """
    motion.tested[0] += 1
    x, y, z = probe.point
    dx, dy, dz = x - item_position[t, 0], y - item_position[t, 1], z - item_position[t, 2]
    sx, sy, sz = probe.shift
    ux, uy, uz = sx - motion.shift[t, 0], sy - motion.shift[t, 1], sz - motion.shift[t, 2]
    uu = dot3(ux, uy, uz, ux, uy, uz)
    s = 0.0
    if uu > 0.0:
        s = min(max(-dot3(dx, dy, dz, ux, uy, uz) / uu, 0.0), 1.0)
    cx, cy, cz = dx + s * ux, dy + s * uy, dz + s * uz
    limit = probe.path_reach + motion.reach[t] + PATH_SLACK * math.sqrt(uu)
    return dot3(cx, cy, cz, cx, cy, cz) <= limit * limit * (1.0 + PAIR_SLACK)


@njit(cache=True, inline='always')
def _keep(probe, t, item_position, limit, motion):
    """Return whether item t passes the sphere test (and, searching paths, the path test)."""
    x, y, z = probe.point
    if not _near(x, y, z, item_position[t, 0], item_position[t, 1], item_position[t, 2],
                 limit):
        return False
    return not motion.active or _paths_meet(probe, t, item_position, motion)


@njit(cache=True, inline='always')
def _cell_range(value, search, corner, cell, low, high):
    """Return the first and last cell index (clipped to low..high) within value +- search."""
    first = max(np.floor((value - search - corner) / cell), float(low))
    last = min(np.floor((value + search - corner) / cell), float(high))
    return first, last


@njit(cache=True, inline='always')
def _scan_class(grid, k, probe, partner, motion, out_a, out_b, count):
    """Write (particle, j) for every item j of class k the probe keeps; return the new count.

    The box searched is ``probe.search`` around its point; each candidate
    (item t, particle j) is kept when |point - p_j| is within own_reach +
    partner[t] (``partner`` in item order) and, with ``motion`` active,
    their paths meet (``_paths_meet``); only items t > ``probe.after`` are
    taken (a class searched against itself: each pair once). Pairs beyond
    the buffers' size are counted, not written: the caller grows the
    buffers and searches again.
    """
    x, y, z = probe.point
    search, query, own_reach = probe.search, probe.particle, probe.own_reach
    item, item_cell, item_position = grid.item, grid.item_cell, grid.item_position
    bucket, low, high = grid.bucket, grid.low, grid.high
    width = grid.cell[k]
    ax, bx = _cell_range(x, search, grid.corner[0], width, low[k, 0], high[k, 0])
    ay, by = _cell_range(y, search, grid.corner[1], width, low[k, 1], high[k, 1])
    az, bz = _cell_range(z, search, grid.corner[2], width, low[k, 2], high[k, 2])
    if ax > bx or ay > by or az > bz:
        return count
    capacity = out_a.size
    start, stop = max(grid.class_start[k], probe.after + 1), grid.class_start[k + 1]
    if (bx - ax + 1.0) * (by - ay + 1.0) * (bz - az + 1.0) > stop - start:
        # A box with more cells than there are particles to test: test them all.
        for t in range(start, stop):
            if _keep(probe, t, item_position, own_reach + partner[t], motion):
                if count < capacity:
                    out_a[count], out_b[count] = query, item[t]
                count += 1
        return count
    base = grid.table_start[k]
    mask = grid.table_start[k + 1] - base - 2
    if grid.dense[k]:
        # One range of items per row of cells along x (the cells are exact).
        # Items are sorted by row, so rows before ``after``'s are empty of
        # items past it: the scan starts at the later of az and its layer.
        lx, ly, lz = low[k, 0], low[k, 1], low[k, 2]
        nx, ny = high[k, 0] - lx + 1, high[k, 1] - ly + 1
        first, last = np.int64(ax), np.int64(bx)
        for cz in range(np.int64(az), np.int64(bz) + 1):
            for cy in range(np.int64(ay), np.int64(by) + 1):
                row = base + _dense_bucket(0, cy, cz, lx, ly, lz, nx, ny)
                for t in range(max(bucket[row + first], start), bucket[row + last + 1]):
                    if _keep(probe, t, item_position, own_reach + partner[t], motion):
                        if count < capacity:
                            out_a[count], out_b[count] = query, item[t]
                        count += 1
        return count
    for cz in range(np.int64(az), np.int64(bz) + 1):
        for cy in range(np.int64(ay), np.int64(by) + 1):
            for cx in range(np.int64(ax), np.int64(bx) + 1):
                b = base + _hash(cx, cy, cz, mask)
                for t in range(max(bucket[b], start), bucket[b + 1]):
                    if item_cell[t, 0] != cx or item_cell[t, 1] != cy or item_cell[t, 2] != cz:
                        continue
                    if _keep(probe, t, item_position, own_reach + partner[t], motion):
                        if count < capacity:
                            out_a[count], out_b[count] = query, item[t]
                        count += 1
    return count


@njit(cache=True)
def _grown(out, count, size):
    """Return a buffer of ``size`` holding the first ``count`` entries of ``out``."""
    grown = np.empty(size, dtype=np.int64)
    grown[:count] = out[:count]
    return grown


@njit(cache=True, nogil=True)
def sort_pairs(a, b, count, n):
    """Return the ``Pairs`` (min, max) of the first ``count`` of (a, b), sorted by (i, j).

    A counting sort by i, then each row sorted by j (insertion sort for
    short rows). Pairs are assumed distinct.
    """
    row = np.zeros(n + 1, dtype=np.int64)
    for p in range(count):
        row[min(a[p], b[p]) + 1] += 1
    for r in range(n):
        row[r + 1] += row[r]
    fill = row[:n].copy()
    first, second = np.empty(count, dtype=np.int64), np.empty(count, dtype=np.int64)
    for p in range(count):
        lo, hi = min(a[p], b[p]), max(a[p], b[p])
        first[fill[lo]], second[fill[lo]] = lo, hi
        fill[lo] += 1
    _sort_rows(second, row, 0, n)
    return Pairs(first, second)


@njit(cache=True)
def _sort_rows(second, row, begin, end):
    """Sort ``second`` within each of rows begin .. end - 1 (row r: row[r] .. row[r + 1] - 1)."""
    for r in range(begin, end):
        start, stop = row[r], row[r + 1]
        if stop - start > 32:
            second[start:stop] = np.sort(second[start:stop])
            continue
        for s in range(start + 1, stop):
            value = second[s]
            t = s - 1
            while t >= start and second[t] > value:
                second[t + 1] = second[t]
                t -= 1
            second[t + 1] = value


@njit(cache=True, nogil=True, parallel=True)
def _sort_block_rows(out_a, out_b, offset, ends, n):
    """Return the ``Pairs`` (min, max) of every block's rows, sorted by (i, j), on the threads.

    Block b's pairs are rows offset[b] .. ends[b] - 1 of (out_a, out_b). A
    parallel radix sort: each block counts its pairs per range of
    PARALLEL_BLOCK_ITEMS first particles, the counts are summed range by
    range in block order, each block moves its pairs into its slots of
    their range, and each range is then sorted on its own (a counting sort
    by i, each row by j). The pairs are distinct, so their sorted order is
    one: ``sort_pairs``' result for any thread count.
    """
    blocks = ends.size
    ranges = (n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    slots = np.zeros((blocks, ranges), dtype=np.int64)
    for b in prange(blocks):
        for p in range(offset[b], ends[b]):
            slots[b, min(out_a[p], out_b[p]) // PARALLEL_BLOCK_ITEMS] += 1
    range_start = np.zeros(ranges + 1, dtype=np.int64)
    at = 0
    for r in range(ranges):
        range_start[r] = at
        for b in range(blocks):
            size = slots[b, r]
            slots[b, r] = at
            at += size
    range_start[ranges] = at
    low, high = np.empty(at, dtype=np.int64), np.empty(at, dtype=np.int64)
    for b in prange(blocks):
        _scatter_block(out_a, out_b, offset[b], ends[b], slots[b], low, high)
    first, second = np.empty(at, dtype=np.int64), np.empty(at, dtype=np.int64)
    for r in prange(ranges):
        _sort_range(low, high, range_start[r], range_start[r + 1], r * PARALLEL_BLOCK_ITEMS,
                    min((r + 1) * PARALLEL_BLOCK_ITEMS, n), first, second)
    return Pairs(first, second)


@njit(cache=True)
def _scatter_block(out_a, out_b, begin, end, slot, low, high):
    """Move rows begin .. end - 1 as (min, max) to the next ``slot`` of their range."""
    for p in range(begin, end):
        lo, hi = min(out_a[p], out_b[p]), max(out_a[p], out_b[p])
        r = lo // PARALLEL_BLOCK_ITEMS
        low[slot[r]], high[slot[r]] = lo, hi
        slot[r] += 1


@njit(cache=True)
def _sort_range(low, high, begin, end, first_row, last_row, first, second):
    """Sort the pairs begin .. end - 1, whose i are first_row .. last_row - 1, into place."""
    rows = last_row - first_row
    row = np.zeros(rows + 1, dtype=np.int64)
    for p in range(begin, end):
        row[low[p] - first_row + 1] += 1
    row[0] = begin
    for r in range(rows):
        row[r + 1] += row[r]
    fill = row[:rows].copy()
    for p in range(begin, end):
        r = low[p] - first_row
        first[fill[r]], second[fill[r]] = low[p], high[p]
        fill[r] += 1
    _sort_rows(second, row, 0, rows)


@njit(cache=True)
def _given_up(needed, estimated, tested):
    """Return the ``Found`` of a search over its limit: no pairs, what it would need."""
    none = np.zeros(0, dtype=np.int64)
    return Found(Pairs(none, none.copy()), False, needed, estimated, tested)


@njit(cache=True, inline='always')
def _append_near(first, stop, point, own_reach, query, item, item_position, partner, out_a,
                 out_b, count):
    """Append (query, item[t]) for items first <= t < stop near ``point``; return the count.

    Branch-free: every candidate is written and the count advances only
    for a near one (the caller guarantees room for stop - first more
    pairs), so a near test that is true one time in six costs no
    mispredicted branch.
    """
    x, y, z = point
    for t in range(first, stop):
        out_a[count] = query
        out_b[count] = item[t]
        count += _near(x, y, z, item_position[t, 0], item_position[t, 1], item_position[t, 2],
                       own_reach + partner[t])
    return count


@njit(cache=True, inline='always')
def _half_row(bucket, base, m, cell, shape, r):
    """Return the item range (first, stop) of row ``r`` of item m's half neighbourhood.

    The rows are (cy, cz), (cy + 1, cz), then (cy - 1 .. cy + 1, cz + 1),
    each over columns cx - 1 .. cx + 1; row 0 starts after item m itself. A
    row outside the grid is empty, (0, 0). ``cell`` is m's cell and
    ``shape`` the grid's cells per axis, both from the grid's low corner.
    """
    cx, cy, cz = cell
    nx, ny, nz = shape
    ry, rz = (cy + r, cz) if r < 2 else (cy + r - 3, cz + 1)
    if ry < 0 or ry >= ny or rz >= nz:
        return 0, 0
    row = base + (rz * ny + ry) * nx
    first = m + 1 if r == 0 else bucket[row + max(cx - 1, 0)]
    return first, bucket[row + min(cx + 1, nx - 1) + 1]


@njit(cache=True)
def _dense_pairs(grid, item_reach, out_a, out_b):
    """Write the unsorted pairs of a grid of one dense class; return (count, items done).

    Stops early, with fewer than all items done, when ``out_a`` / ``out_b``
    may be too short (the caller grows them and calls again): growing them
    here would make numba count references to the buffers at every
    candidate, which doubles the cost. Cells are wider than any search
    (CELL_MARGIN), so the items t > m of the neighbour cells of item m's
    cell are exactly those of five rows of cells along x: its own (from m
    on) and the next four in cell order (the half of the 3 x 3 rows around
    it that comes later), each one range of items. The exact test is
    ``_near``'s, so the set is ``_scan_class``'s.
    """
    return _dense_range(grid, item_reach, out_a, out_b, np.int64(0), grid.item.size,
                        np.int64(0), out_a.size)


@njit(cache=True)
def _dense_range(grid, item_reach, out_a, out_b, begin, end, count, capacity):
    """``_dense_pairs`` for items begin .. end - 1, writing from row ``count`` below ``capacity``.

    Returns (the row after the last written, the first item not done). A
    function of its own (never inlined): numba's parallel loops lose the
    stores of inlined code.
    """
    item, item_cell, item_position = grid.item, grid.item_cell, grid.item_position
    low, high, bucket = grid.low, grid.high, grid.bucket
    lx, ly, lz = low[0, 0], low[0, 1], low[0, 2]
    nx, ny, nz = high[0, 0] - lx + 1, high[0, 1] - ly + 1, high[0, 2] - lz + 1
    base = grid.table_start[0]
    for m in range(begin, end):
        point = (item_position[m, 0], item_position[m, 1], item_position[m, 2])
        own_reach = item_reach[m]
        query = item[m]
        cx, cy, cz = item_cell[m, 0] - lx, item_cell[m, 1] - ly, item_cell[m, 2] - lz
        for r in range(5):
            first, stop = _half_row(bucket, base, m, (cx, cy, cz), (nx, ny, nz), r)
            if count + (stop - first) > capacity:
                return count, m
            count = _append_near(first, stop, point, own_reach, query, item, item_position,
                                 item_reach, out_a, out_b, count)
    return count, end


@njit(cache=True)
def _items_reach(reach, item):
    """Return ``reach`` in the grid's item order."""
    item_reach = np.empty(item.size)
    for m in range(item.size):
        item_reach[m] = reach[item[m]]
    return item_reach


@njit(cache=True)
def _dense_candidates(grid, items):
    """Return how many candidates ``_dense_pairs`` writes for its first ``items`` items."""
    return float(_dense_candidates_in(grid, np.int64(0), items))


@njit(cache=True)
def _dense_candidates_in(grid, begin, end):
    """Return how many candidates ``_dense_range`` writes for items begin .. end - 1."""
    item_cell, low, high, bucket = grid.item_cell, grid.low, grid.high, grid.bucket
    lx, ly, lz = low[0, 0], low[0, 1], low[0, 2]
    nx, ny, nz = high[0, 0] - lx + 1, high[0, 1] - ly + 1, high[0, 2] - lz + 1
    base = grid.table_start[0]
    total = 0
    for m in range(begin, end):
        cx, cy, cz = item_cell[m, 0] - lx, item_cell[m, 1] - ly, item_cell[m, 2] - lz
        for r in range(5):
            first, stop = _half_row(bucket, base, m, (cx, cy, cz), (nx, ny, nz), r)
            total += stop - first
    return total


@njit(cache=True)
def _dense_grid_pairs(reach, grid, limit):
    """Return the ``Found`` of ``grid_pairs`` on a grid of one dense class (sorted by (i, j)).

    The buffers grow fourfold while they are too short, up to the limit's
    pairs plus one item's candidates; past that the search gives up, with
    an estimate of the pairs it would find: all its candidates (counted
    from the table), times the share of them kept so far.
    """
    n = grid.item.size
    item_reach = _items_reach(reach, grid.item)
    largest = limit.max_pairs + n
    size = min(4 * n + 64, largest)
    while True:
        out_a, out_b = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
        count, done = _dense_pairs(grid, item_reach, out_a, out_b)
        if done == n and count <= limit.max_pairs:
            return Found(sort_pairs(out_a, out_b, count, n), True, float(count), False, 0)
        if done == n:
            return _given_up(float(count), False, 0)
        if size >= largest:
            share = count / max(_dense_candidates(grid, done), 1.0)
            return _given_up(max(share * _dense_candidates(grid, n), float(count)), True, 0)
        size = min(4 * size, largest)


@njit(cache=True)
def _one_dense_class(grid):
    """Say whether ``grid`` is one dense class whose cells hold every search (a gas)."""
    return (grid.class_start.size == 2 and grid.dense[0]
            and grid.cell[0] >= CELL_REACHES * grid.class_reach[0] * (1.0 + CELL_MARGIN)
            and np.max(grid.high[0] - grid.low[0]) < DENSE_AXIS_CELLS)


@njit(cache=True, nogil=True, parallel=True)
def _dense_blocks_parallel(grid, item_reach, out_a, out_b, offset, ends, blocks):
    """Write the pairs of blocks blocks[0] .. blocks[1] - 1 into their own rows, on the threads.

    Block b is items b * PARALLEL_BLOCK_ITEMS onwards; its candidates fit
    rows offset[b] - offset[blocks[0]] .. offset[b + 1] - offset[blocks[0]]
    - 1 exactly, and ends[b] is the row after its last pair.
    """
    n = grid.item.size
    first, base = blocks[0], offset[blocks[0]]
    for k in prange(blocks[1] - first):
        block = first + k
        begin = block * PARALLEL_BLOCK_ITEMS
        ends[block] = _dense_range(grid, item_reach, out_a, out_b, begin,
                                   min(begin + PARALLEL_BLOCK_ITEMS, n), offset[block] - base,
                                   offset[block + 1] - base)[0]


@njit(cache=True, nogil=True, parallel=True)
def _kept_rows(out_a, out_b, offset, ends, blocks, kept, kept_a, kept_b):
    """Copy the pairs of blocks blocks[0] .. blocks[1] - 1 to their rows ``kept`` onwards.

    Block b's pairs (rows offset[b] - offset[blocks[0]] .. ends[b] - 1 of
    a wave's buffers) move to rows kept[b] .. kept[b + 1] - 1, on the threads.
    """
    first, base = blocks[0], offset[blocks[0]]
    for k in prange(blocks[1] - first):
        block = first + k
        row = kept[block]
        for p in range(offset[block] - base, ends[block]):
            kept_a[row], kept_b[row] = out_a[p], out_b[p]
            row += 1


@njit(cache=True, nogil=True, parallel=True)
def _dense_counts_parallel(grid, counts):
    """Fill counts[b + 1] with block b's candidates (``_dense_candidates_in``), on the threads."""
    n = grid.item.size
    for block in prange(counts.size - 1):
        begin = block * PARALLEL_BLOCK_ITEMS
        counts[block + 1] = _dense_candidates_in(grid, begin,
                                                 min(begin + PARALLEL_BLOCK_ITEMS, n))


@njit(cache=True, nogil=True)
def grid_pairs_shared(reach, grid, limit):
    """Return ``grid_pairs``' ``Found`` of a sphere search, a gas's shared among the threads.

    On one dense class (``_one_dense_class``) the items are split into
    blocks of PARALLEL_BLOCK_ITEMS: the candidates of each block are counted
    from the table, each block writes its pairs into its own rows, and the
    rows are sorted by (i, j) on the threads (``_sort_block_rows``), so
    the result is ``grid_pairs``' whatever the thread count. Where the
    candidates pass ``limit.max_pairs`` plus one per item, the blocks run in
    waves within that many rows, each wave's pairs kept before the next.
    Any other grid, and a search whose pairs pass ``limit``, is
    ``grid_pairs``' own (which gives up with its estimate).
    """
    motion = PathMotion(False, np.zeros((0, 3)), np.zeros(0), np.zeros(1, dtype=np.int64))
    n = grid.item.size
    if not _one_dense_class(grid):
        return grid_pairs(reach, grid, limit, motion)
    blocks = (n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    offset = np.zeros(blocks + 1, dtype=np.int64)
    _dense_counts_parallel(grid, offset)
    room = limit.max_pairs + n
    for block in range(blocks):
        if offset[block + 1] > room:
            return grid_pairs(reach, grid, limit, motion)
        offset[block + 1] += offset[block]
    item_reach = _items_reach(reach, grid.item)
    out_a = np.empty(min(offset[blocks], room), dtype=np.int64)
    out_b = np.empty(min(offset[blocks], room), dtype=np.int64)
    ends = np.empty(blocks, dtype=np.int64)
    kept = np.zeros(blocks + 1, dtype=np.int64)
    kept_a = np.empty(0, dtype=np.int64)
    kept_b = np.empty(0, dtype=np.int64)
    first = np.int64(0)
    while first < blocks:
        last = first + 1
        while last < blocks and offset[last + 1] - offset[first] <= room:
            last += 1
        _dense_blocks_parallel(grid, item_reach, out_a, out_b, offset, ends, (first, last))
        for block in range(first, last):
            kept[block + 1] = kept[block] + ends[block] - (offset[block] - offset[first])
        if kept[last] > limit.max_pairs:
            return grid_pairs(reach, grid, limit, motion)
        if first == 0 and last == blocks:
            # One wave: its rows are sorted where they were written.
            return Found(_sort_block_rows(out_a, out_b, offset, ends, n), True,
                         float(kept[blocks]), False, 0)
        if kept[last] > kept_a.size:
            size = min(max(2 * kept_a.size, kept[last] * blocks // last), limit.max_pairs)
            kept_a, kept_b = _grown(kept_a, kept[first], size), _grown(kept_b, kept[first], size)
        _kept_rows(out_a, out_b, offset, ends, (first, last), kept, kept_a, kept_b)
        first = last
    return Found(_sort_block_rows(kept_a, kept_b, kept[:-1], kept[1:], n), True,
                 float(kept[blocks]), False, 0)


@njit(cache=True, nogil=True)
def grid_pairs(reach, grid, limit, motion):
    """Return the ``Found`` pairs (i < j, sorted) with |p_i - p_j| <= reach_i + reach_j (+ slack).

    Positions are the grid's (as built). Each particle is searched in its
    own class (each pair once, from its earlier item) and in every larger
    class. With ``motion`` active a pair must also pass the path test
    (``motion`` in item order). Past ``limit`` the search gives up.
    """
    item_position, class_start, class_reach = grid.item_position, grid.class_start, \
        grid.class_reach
    n = grid.item.size
    if not motion.active and _one_dense_class(grid):
        # One dense class (a gas): the neighbour-cell scan, no search boxes.
        return _dense_grid_pairs(reach, grid, limit)
    item_reach = _items_reach(reach, grid.item)
    size = min(2 * n + 16, limit.max_pairs)
    out_a, out_b = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
    count = np.int64(0)
    classes = class_start.size - 1
    no_shift = (0.0, 0.0, 0.0)
    for k in range(classes):
        # Items in cell order: neighbouring queries touch the same memory.
        for m in range(class_start[k], class_start[k + 1]):
            particle = grid.item[m]
            point = (item_position[m, 0], item_position[m, 1], item_position[m, 2])
            own_reach = reach[particle]
            shift, path_reach = no_shift, 0.0
            if motion.active:
                shift = (motion.shift[m, 0], motion.shift[m, 1], motion.shift[m, 2])
                path_reach = motion.reach[m]
                if motion.tested[0] > limit.max_tests:
                    return _given_up(float(count), False, motion.tested[0])
            for other in range(k, classes):
                search = (own_reach + class_reach[other]) * (1.0 + SCAN_SLACK)
                probe = Probe(point, search, particle, m if other == k else -1, own_reach,
                              shift, path_reach)
                before = count
                count = _scan_class(grid, other, probe, item_reach, motion, out_a, out_b, count)
                if count > out_a.size:
                    if count > limit.max_pairs:
                        return _given_up(float(count), False, motion.tested[0])
                    size = min(2 * count, limit.max_pairs)
                    out_a = _grown(out_a, before, size)
                    out_b = _grown(out_b, before, size)
                    if motion.active:
                        motion.tested[0] -= count - before     # the same tests again
                    count = _scan_class(grid, other, probe, item_reach, motion, out_a, out_b,
                                        before)
    return Found(sort_pairs(out_a, out_b, count, n), True, float(count), False,
                 motion.tested[0])


class Partners(NamedTuple):
    """What a mover query adds to its own reach, in the grid's item order."""

    item_reach: np.ndarray      # (n,) each item's listed reach, m
    class_reach: np.ndarray     # (classes,) the largest of each class, m


@njit(cache=True, nogil=True)
def grid_query(position, query, query_reach, partners, grid, limit):
    """Return the ``Found`` (a, b): each query particle a = query[q] against every item b near it.

    Near: |position[a] - p_b| <= query_reach[q] + partners.item_reach[t]
    (p_b the grid's position of b, item t). Pairs come in query order,
    unsorted, a == b included. Past ``limit.max_pairs`` the query gives up.
    """
    size = min(16 * query.size + 16, limit.max_pairs)
    out_a, out_b = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
    partner, class_partner = partners.item_reach, partners.class_reach
    motion = PathMotion(False, np.zeros((0, 3)), np.zeros(0), np.zeros(1, dtype=np.int64))
    no_shift = (0.0, 0.0, 0.0)
    count = 0
    for q in range(query.size):
        particle = query[q]
        point = (position[particle, 0], position[particle, 1], position[particle, 2])
        own_reach = query_reach[q]
        for k in range(grid.class_start.size - 1):
            search = (own_reach + class_partner[k]) * (1.0 + SCAN_SLACK)
            probe = Probe(point, search, particle, -1, own_reach, no_shift, 0.0)
            before = count
            count = _scan_class(grid, k, probe, partner, motion, out_a, out_b, count)
            if count > out_a.size:
                if count > limit.max_pairs:
                    return _given_up(float(count), False, 0)
                size = min(2 * count, limit.max_pairs)
                out_a = _grown(out_a, before, size)
                out_b = _grown(out_b, before, size)
                count = _scan_class(grid, k, probe, partner, motion, out_a, out_b, before)
    return Found(Pairs(out_a[:count], out_b[:count]), True, float(count), False, 0)


def partner_terms(values: np.ndarray, grid: Grid) -> Partners:
    """Return ``values`` in the grid's item order and the largest of each class."""
    in_order = np.ascontiguousarray(values, dtype=np.float64)[grid.item]
    return Partners(in_order, np.maximum.reduceat(in_order, grid.class_start[:-1]))


@njit(cache=True, nogil=True)
def movers(position, built, extra, half_skin):
    """Return the particles with |position - built| + extra > half_skin (ascending)."""
    n = position.shape[0]
    out = np.empty(n, dtype=np.int64)
    count = 0
    for p in range(n):
        if _moved(position, built, extra, half_skin, p):
            out[count] = p
            count += 1
    return out[:count]


@njit(cache=True, inline='always')
def _moved(position, built, extra, half_skin, p):
    """Say whether particle p's |position - built| + extra exceeds half_skin."""
    dx, dy, dz = position[p, 0] - built[p, 0], position[p, 1] - built[p, 1], \
        position[p, 2] - built[p, 2]
    return math.sqrt(dot3(dx, dy, dz, dx, dy, dz)) + extra[p] > half_skin


@njit(cache=True, nogil=True, parallel=True)
def movers_shared(position, built, extra, half_skin):
    """Return ``movers``' list, the particles tested in blocks on the threads.

    Each block marks and counts its movers in one pass over the positions;
    the counts are summed in block order and each block lists its own
    marked particles in its own slice: the serial list for any thread count.
    """
    n = position.shape[0]
    blocks = (n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    offset = np.zeros(blocks + 1, dtype=np.int64)
    moved = np.empty(n, dtype=np.bool_)
    for block in prange(blocks):
        count = 0
        for p in range(block * PARALLEL_BLOCK_ITEMS, min((block + 1) * PARALLEL_BLOCK_ITEMS, n)):
            moved[p] = _moved(position, built, extra, half_skin, p)
            if moved[p]:
                count += 1
        offset[block + 1] = count
    for block in range(blocks):
        offset[block + 1] += offset[block]
    out = np.empty(offset[blocks], dtype=np.int64)
    for block in prange(blocks):
        at = offset[block]
        for p in range(block * PARALLEL_BLOCK_ITEMS, min((block + 1) * PARALLEL_BLOCK_ITEMS, n)):
            if moved[p]:
                out[at] = p
                at += 1
    return out


@njit(cache=True, nogil=True)
def merge_pairs(keys, listed, extra, n):
    """Return the listed ``Pairs`` joined with ``extra``: sorted by (i, j), i != j, no repeats.

    ``keys`` are the sorted i * n + j of the ``listed`` pairs. The listed
    pairs are copied, not split from their keys: two integer divisions per
    pair cost more than the whole merge.
    """
    a, b = extra.first, extra.second
    added = np.empty(a.size, dtype=np.int64)
    count = 0
    for p in range(a.size):
        if a[p] != b[p]:
            added[count] = min(a[p], b[p]) * n + max(a[p], b[p])
            count += 1
    added = np.sort(added[:count])
    out_i = np.empty(keys.size + count, dtype=np.int64)
    out_j = np.empty(keys.size + count, dtype=np.int64)
    s = t = m = 0
    last = -1
    while s < keys.size or t < count:
        if t == count or (s < keys.size and keys[s] <= added[t]):
            value = keys[s]
            if value != last:
                out_i[m], out_j[m] = listed.first[s], listed.second[s]
                m += 1
            s += 1
        else:
            value = added[t]
            if value != last:
                out_i[m], out_j[m] = value // n, value % n
                m += 1
            t += 1
        last = value
    return Pairs(out_i[:m], out_j[:m])


def as_points(position: np.ndarray) -> np.ndarray:
    """Return positions as a contiguous (n, 3) float array (2-D sets get z = 0)."""
    position = np.ascontiguousarray(position, dtype=np.float64)
    if position.shape[1] == 3:
        return position
    points = np.zeros((position.shape[0], 3))
    points[:, :position.shape[1]] = position
    return points


def make_grid(position: np.ndarray, reach: np.ndarray, classes: list,
              shared: bool = False) -> Grid:
    """Build the grid of every size class (``classes``: index arrays, smallest reach first).

    ``shared``: the per-particle loops on the threads (the same grid).
    """
    order = np.concatenate(classes).astype(np.int64) if len(classes) > 1 else \
        np.ascontiguousarray(classes[0], dtype=np.int64)
    class_start = np.zeros(len(classes) + 1, dtype=np.int64)
    class_start[1:] = np.cumsum([members.size for members in classes])
    return build_grid(as_points(position), np.ascontiguousarray(reach, dtype=np.float64),
                      order, class_start, shared)


def warm_up() -> None:
    """Call every kernel once on a tiny problem (compiles or loads from the cache)."""
    position = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [9.0, 0.0, 0.0]])
    reach = np.array([1.0, 1.0, 3.0])
    limit = SearchLimit(1000, 1000)
    grid = make_grid(position, reach, [np.array([0, 1]), np.array([2])])
    still = PathMotion(False, np.zeros((0, 3)), np.zeros(0), np.zeros(1, dtype=np.int64))
    grid_pairs(reach, grid, limit, still)
    moving = PathMotion(True, np.ones((3, 3)), np.ones(3), np.zeros(1, dtype=np.int64))
    grid_pairs(reach, grid, limit, moving)
    gas = make_grid(position[:2], reach[:2], [np.array([0, 1])])
    make_grid(position, reach, [np.array([0, 1]), np.array([2])], True)
    grid_pairs(reach[:2], gas, limit, still)
    grid_pairs_shared(reach[:2], gas, limit)
    grid_pairs_shared(reach, grid, limit)
    query = np.array([0], dtype=np.int64)
    near = grid_query(position, query, reach[query], partner_terms(reach, grid), grid, limit)
    keys = np.array([1], dtype=np.int64)
    merge_pairs(keys, Pairs(keys // 3, keys % 3), near.pairs, 3)
    movers(position, position, np.zeros(3), 0.5)
    movers_shared(position, position, np.zeros(3), 0.5)


def kernels() -> list:
    """Return the compiled kernels of this module (for the cache check)."""
    return [build_grid, grid_pairs, grid_pairs_shared, grid_query, movers, movers_shared,
            merge_pairs, sort_pairs]
