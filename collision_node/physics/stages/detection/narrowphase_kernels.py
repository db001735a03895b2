"""The narrowphase kernel: which candidate pairs overlap, with their normals."""

from __future__ import annotations

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)

from ...law.primitives import dot3, line_of_action  # noqa: E402


@njit(cache=True)
def find_overlaps(position, velocity, radius, inv_mass, ci, cj, out_i, out_j, normal,
                  penetration):
    """Keep the candidate pairs that overlap (``narrowphase.find_contacts``); return how many.

    Writes the kept pairs, their normals and penetrations to the front of the
    output arrays (sized for every candidate), in candidate order.
    """
    kept = 0
    for k in range(ci.size):
        a, b = ci[k], cj[k]
        ox = position[a, 0] - position[b, 0]
        oy = position[a, 1] - position[b, 1]
        oz = position[a, 2] - position[b, 2]
        reach = radius[a] + radius[b]
        # The numpy path's generous prefilter, kept so both keep the same pairs.
        if not dot3(ox, oy, oz, ox, oy, oz) <= reach * reach * (1.0 + 1e-9):
            continue
        if not (inv_mass[a] + inv_mass[b]) > 0.0:
            continue
        nx, ny, nz, distance = line_of_action(
            ox, oy, oz, velocity[a, 0] - velocity[b, 0], velocity[a, 1] - velocity[b, 1],
            velocity[a, 2] - velocity[b, 2])
        if not distance < reach:
            continue
        out_i[kept], out_j[kept] = a, b
        normal[kept, 0], normal[kept, 1], normal[kept, 2] = nx, ny, nz
        penetration[kept] = reach - distance
        kept += 1
    return kept


def warm_up() -> None:
    """Call this module's kernels once on a tiny problem (compiles or loads the cache)."""
    # A pair 1.9 m apart with radii 1 m overlaps.
    position = np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]])
    v = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    radius, inv_mass = np.ones(2), np.ones(2)
    pi, pj = np.array([1], dtype=np.int64), np.array([0], dtype=np.int64)
    out_i, out_j = np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)
    find_overlaps(position, v, radius, inv_mass, pi, pj, out_i, out_j, np.zeros((1, 3)),
                  np.zeros(1))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [find_overlaps]
