"""Colour a contact graph: split pairs into batches that share no particle.

Applying every impulse of a step at once (Jacobi) loses energy whenever a
particle touches two others (three equal balls [1, 0, -1] end at
[0, 0, 0]). Pairs that share a particle must be solved one after another,
so the solver walks these batches in order; inside a batch no two pairs
share a dynamic particle and the batch is applied vectorised.

A batch takes, among the pairs not yet placed, each pair that comes first
(in pair order) at both of its dynamic particles. Pair order is the
broadphase's sorted (i, j) order, so a chain such as Newton's cradle is
walked from its low end. Static particles never conflict: their velocity
never changes.
"""

from __future__ import annotations

import numpy as np


def color_pairs(i: np.ndarray, j: np.ndarray, dynamic: np.ndarray, max_batches: int
                ) -> tuple[list[np.ndarray], np.ndarray]:
    """Return (batches, leftover): pair-index arrays in solve order.

    ``leftover`` holds the pairs that did not fit in ``max_batches``
    batches (only in very dense clusters); the solver shares their
    impulses out instead of ordering them.
    """
    count = i.shape[0]
    # Give each static endpoint a key of its own so it never blocks.
    key_i = np.where(dynamic[i], i, -1 - np.arange(count))
    key_j = np.where(dynamic[j], j, -1 - np.arange(count))
    _, inverse = np.unique(np.concatenate([key_i, key_j]), return_inverse=True)
    node_i, node_j = inverse[:count], inverse[count:]
    nodes = int(inverse.max()) + 1 if count else 0
    remaining = np.arange(count)
    batches: list[np.ndarray] = []
    while remaining.size and len(batches) < max_batches:
        a, b = node_i[remaining], node_j[remaining]
        rank = np.arange(remaining.size)
        first = np.full(nodes, remaining.size, dtype=np.int64)
        np.minimum.at(first, a, rank)
        np.minimum.at(first, b, rank)
        chosen = (first[a] == rank) & (first[b] == rank)
        batches.append(remaining[chosen])
        remaining = remaining[~chosen]
    return batches, remaining
