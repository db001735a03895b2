"""Broadphase: candidate pairs whose spheres may overlap.

A k-d tree (scipy's cKDTree, C code) finds all pairs within twice the
largest radius in O(n log n); per-step cost grows about linearly with the
particle count. Particles much larger than the typical one would widen
that search radius for everybody, so they are split off and queried
against the tree of the small ones with their own radius.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..pipeline import Stage, StepContext

# A particle whose radius exceeds this multiple of the median is "large":
# its pairs are found by a query of its own instead of widening the
# shared search radius.
LARGE_RADIUS_FACTOR = 4.0


def candidate_pairs(position: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return index arrays (i < j) of pairs with |p_i - p_j| <= reach_i + reach_j.

    ``reach`` is each particle's radius plus any margin (for example the
    distance it may travel in a step). Pairs come sorted by (i, j) so that
    every later stage sees them in a deterministic order.
    """
    n = position.shape[0]
    if n < 2:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    large = reach > LARGE_RADIUS_FACTOR * np.median(reach)
    small_idx = np.flatnonzero(~large)
    parts_i, parts_j = [], []
    if small_idx.size >= 2:
        tree = cKDTree(position[small_idx])
        pairs = tree.query_pairs(2.0 * float(reach[small_idx].max()), output_type='ndarray')
        parts_i.append(small_idx[pairs[:, 0]])
        parts_j.append(small_idx[pairs[:, 1]])
    large_idx = np.flatnonzero(large)
    if large_idx.size:
        # Large against large: few by construction, so all pairs.
        a, b = np.triu_indices(large_idx.size, k=1)
        parts_i.append(large_idx[a])
        parts_j.append(large_idx[b])
        if small_idx.size:
            tree = cKDTree(position[small_idx])
            max_small = float(reach[small_idx].max())
            hits = tree.query_ball_point(position[large_idx], reach[large_idx] + max_small)
            counts = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
            if counts.sum():
                parts_i.append(np.repeat(large_idx, counts))
                parts_j.append(small_idx[np.concatenate([h for h in hits if h]).astype(np.int64)])
    if not parts_i:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    i = np.concatenate(parts_i).astype(np.int64)
    j = np.concatenate(parts_j).astype(np.int64)
    i, j = np.minimum(i, j), np.maximum(i, j)
    order = np.lexsort((j, i))
    return i[order], j[order]


class BroadphaseStage(Stage):
    """Find candidate pairs with a k-d tree."""

    name = 'broadphase'

    def run(self, ctx: StepContext) -> None:
        """Store candidate pairs on the context."""
        ctx.pair_i, ctx.pair_j = candidate_pairs(ctx.state.position, ctx.state.radius)

    def describe(self) -> str:
        """Say what the stage does."""
        return 'k-d tree pairs within r_i + r_j (large particles queried on their own)'
