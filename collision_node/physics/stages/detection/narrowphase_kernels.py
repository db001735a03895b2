"""The narrowphase kernel: which candidate pairs overlap, with their normals."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit, prange  # noqa: E402,I100 (after the cache directory is chosen)

from ...law.primitives import dot3, line_of_action  # noqa: E402
from ...step.step_kernels import ParticleArrays  # noqa: E402
from ...model.tunables import PARALLEL_BLOCK_ITEMS  # noqa: E402


class ContactArrays(NamedTuple):
    """Overlapping pairs: first[k] and second[k] touch along normal[k], penetration[k] deep.

    The narrowphase's result and what the separation kernels take.
    """

    first: np.ndarray           # (m,) int64
    second: np.ndarray          # (m,) int64
    normal: np.ndarray          # (m, 3) unit line of action, from second to first
    penetration: np.ndarray     # (m,) r_first + r_second - |p_first - p_second|, m


@njit(cache=True, nogil=True)
def find_overlaps(particles, candidate_first, candidate_second, ahead, margin, sweep):
    """Return the ``ContactArrays`` of the candidate pairs that overlap, in candidate order.

    Contact when |p1 - p2| < r1 + r2 and at least one can move; the normal
    and distance are ``line_of_action``'s (scale-robust, with its fallback
    for coincident centres). With ``ahead`` (m) and ``margin`` (of the mean
    radius) a pair is kept while |p1 - p2| < (r1 + r2) (1 + margin / 2) +
    ahead: speculative contacts, with a negative penetration (their gap).
    With ``sweep`` (s) the gap may also be what the two particles' speeds
    cover in that time, (|v1| + |v2|) sweep: impacts found before they
    touch, also where the solve's impulses turn a pair towards each other.
    """
    m = candidate_first.size
    out = ContactArrays(np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64),
                        np.empty((m, 3)), np.empty(m))
    kept = _overlaps_in(particles, candidate_first, candidate_second, (ahead, margin, sweep),
                        out, np.int64(0), m, np.int64(0))
    return ContactArrays(out.first[:kept], out.second[:kept], out.normal[:kept],
                         out.penetration[:kept])


@njit(cache=True, nogil=True, parallel=True)
def find_overlaps_parallel(particles, candidate_first, candidate_second, ahead, margin,
                           sweep):
    """Return ``find_overlaps``' result, blocks of candidates tested on the threads.

    Each block writes its contacts into its own rows; the blocks are then
    joined in order, so the result is the serial one's whatever the thread count.
    """
    m = candidate_first.size
    out = ContactArrays(np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64),
                        np.empty((m, 3)), np.empty(m))
    blocks = (m + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    ends = np.empty(blocks, dtype=np.int64)
    for block in prange(blocks):
        start = block * PARALLEL_BLOCK_ITEMS
        ends[block] = _overlaps_in(particles, candidate_first, candidate_second,
                                   (ahead, margin, sweep), out, start,
                                   min(start + PARALLEL_BLOCK_ITEMS, m), start)
    return _joined(out, ends)


@njit(cache=True)
def _joined(out, ends):
    """Return the rows block b wrote (b * PARALLEL_BLOCK_ITEMS .. ends[b] - 1), in block order."""
    kept = 0
    first, second, normal, penetration = out
    for block in range(ends.size):
        for row in range(block * PARALLEL_BLOCK_ITEMS, ends[block]):
            first[kept], second[kept], penetration[kept] = first[row], second[row], \
                penetration[row]
            for d in range(3):
                normal[kept, d] = normal[row, d]
            kept += 1
    return ContactArrays(first[:kept], second[:kept], normal[:kept], penetration[:kept])


@njit(cache=True)
def _overlaps_in(particles, candidate_first, candidate_second, gaps, out, start, stop, kept):
    """Write the contacts among candidates start .. stop - 1 from row ``kept`` of ``out``.

    ``gaps`` is (ahead, margin, sweep) as ``find_overlaps`` takes them;
    returns the row after the last one written. A function of its own
    (never inlined): numba's parallel loops lose the stores of inlined code.
    """
    ahead, margin, sweep = gaps
    first, second, normal, penetration = out
    position, velocity = particles.position, particles.velocity
    radius, inv_mass = particles.radius, particles.inv_mass
    speculative = ahead > 0.0 or margin > 0.0 or sweep > 0.0
    # Most candidates fail the distance test: the relative velocity (another
    # cache miss per candidate in a large world) is read only for the rest.
    for k in range(start, stop):
        a, b = candidate_first[k], candidate_second[k]
        ox = position[a, 0] - position[b, 0]
        oy = position[a, 1] - position[b, 1]
        oz = position[a, 2] - position[b, 2]
        reach = radius[a] + radius[b]
        near = reach + (0.5 * margin * reach + ahead) if speculative else reach
        if sweep > 0.0:
            near += sweep * (
                math.sqrt(dot3(velocity[a, 0], velocity[a, 1], velocity[a, 2], velocity[a, 0],
                               velocity[a, 1], velocity[a, 2]))
                + math.sqrt(dot3(velocity[b, 0], velocity[b, 1], velocity[b, 2], velocity[b, 0],
                                 velocity[b, 1], velocity[b, 2])))
        # A cheap, slightly generous prefilter on the squared distance (offsets
        # that underflow square to 0 and pass; the exact test follows).
        if not dot3(ox, oy, oz, ox, oy, oz) <= near * near * (1.0 + 1e-9):
            continue
        if not (inv_mass[a] + inv_mass[b]) > 0.0:
            continue
        ux = velocity[a, 0] - velocity[b, 0]
        uy = velocity[a, 1] - velocity[b, 1]
        uz = velocity[a, 2] - velocity[b, 2]
        nx, ny, nz, distance = line_of_action(ox, oy, oz, ux, uy, uz)
        if not distance < near:
            continue
        first[kept], second[kept] = a, b
        normal[kept, 0], normal[kept, 1], normal[kept, 2] = nx, ny, nz
        penetration[kept] = reach - distance
        kept += 1
    return kept


def warm_up() -> None:
    """Call this module's kernels once on a tiny problem (compiles or loads the cache)."""
    # A pair 1.9 m apart with radii 1 m overlaps.
    particles = ParticleArrays(np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]]),
                               np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]), np.ones(2),
                               np.ones(2))
    for kernel in (find_overlaps, find_overlaps_parallel):
        kernel(particles, np.array([1], dtype=np.int64), np.array([0], dtype=np.int64), 0.0,
               0.0, 0.0)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [find_overlaps, find_overlaps_parallel]
