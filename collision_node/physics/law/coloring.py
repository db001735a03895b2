"""Colour a contact graph greedily: batches of pairs that share no dynamic particle.

Box2D v3's constraint graph (``constraint_graph.c``): each pair, in pair
order, takes the lowest colour that neither of its dynamic particles has
yet; static particles never conflict (their velocity never changes). At
most ``max_colors`` colours: a pair that finds none free (a particle in
more contacts than colours, only in dense clusters) is overflow, solved
one contact at a time after the colours. The number of colours is bounded
by the busiest particle's contacts (at most 2 per chain, 3-4 in a 2-D
pile, 6 in a hexagonal lattice), not by the longest chain of contacts.

The compiled solve visits contacts one at a time, so it needs no
colouring; its ``visit='colours'`` order and the tests' vectorised
reference (one colour per numpy call) use it.
"""

from __future__ import annotations

import numpy as np

from ..step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)
from ..model.tunables import MAX_COLORS


@njit(cache=True, nogil=True)
def greedy_colors(i, j, dynamic, max_colors):
    """Return each pair's colour (0 .. max_colors - 1), -1 for overflow, in pair order."""
    used = np.zeros(dynamic.size, dtype=np.uint64)
    colors = np.full(i.size, -1, dtype=np.int64)
    for k in range(i.size):
        a, b = i[k], j[k]
        taken = np.uint64(0)
        if dynamic[a]:
            taken |= used[a]
        if dynamic[b]:
            taken |= used[b]
        for c in range(max_colors):
            bit = np.uint64(1) << np.uint64(c)
            if not taken & bit:
                colors[k] = c
                if dynamic[a]:
                    used[a] |= bit
                if dynamic[b]:
                    used[b] |= bit
                break
    return colors


def color_pairs(i: np.ndarray, j: np.ndarray, dynamic: np.ndarray,
                max_colors: int = MAX_COLORS) -> tuple[list[np.ndarray], np.ndarray]:
    """Return (batches, overflow): pair-index arrays, one batch per colour, in pair order.

    ``overflow`` holds the pairs that found no free colour among
    ``max_colors``; a solver visits them one at a time after the batches.
    """
    if not 0 < max_colors <= 64:
        raise ValueError(f'max_colors must be in 1..64, got {max_colors}')
    if i.size == 0:
        return [], np.zeros(0, dtype=np.int64)
    colors = greedy_colors(np.ascontiguousarray(i, dtype=np.int64),
                           np.ascontiguousarray(j, dtype=np.int64),
                           np.ascontiguousarray(dynamic, dtype=np.bool_), max_colors)
    order = np.argsort(colors, kind='stable')
    counts = np.bincount(colors + 1, minlength=max_colors + 1)
    overflow = order[:counts[0]]
    bounds = np.cumsum(counts)
    batches = [order[bounds[c]:bounds[c + 1]] for c in range(max_colors) if counts[c + 1]]
    return batches, overflow
