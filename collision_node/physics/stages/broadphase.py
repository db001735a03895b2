"""Broadphase: candidate pairs whose spheres may overlap.

A k-d tree (scipy's cKDTree, C code) finds all pairs within twice the
largest radius in O(n log n); per-step cost grows about linearly with the
particle count. Particles much larger than the typical one would widen
that search radius for everybody, so they are split off and queried
against the tree of the small ones with their own radius.

The stage does not search every step. It keeps a Verlet list: the pairs
within r_i + r_j + skin at the last search, valid as long as no two
particles have together moved more than the skin since (two particles
each moved at most skin/2 cannot have closed a gap larger than the skin).
The check uses the actual positions, so it covers drift, separation, walls
and any other stage. The few fast particles that moved more than skin/2
("movers") are queried on their own against the tree of the last search
instead of forcing a full search; only when movers become common is the
tree rebuilt. The result is exactly the set a fresh search would need.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ..step import Stage, StepContext

# A particle whose radius exceeds this multiple of the median is "large":
# its pairs are found by a query of its own instead of widening the
# shared search radius.
LARGE_RADIUS_FACTOR = 4.0
# Skin of the Verlet list: about SKIN_STEPS steps of travel at the rms speed,
# at most SKIN_MAX_RADII median radii (a wider skin costs more pairs than
# the searches it saves), at least SKIN_MIN_RADII of them.
SKIN_STEPS = 20.0
SKIN_MAX_RADII = 1.5
SKIN_MIN_RADII = 0.05
# Search afresh once more than this share of the particles are movers.
MAX_MOVER_SHARE = 0.02
# Up to this many particles every pair is a candidate: cheaper than any
# search for the handful of bodies of a cradle or a billiards table.
ALL_PAIRS_UP_TO = 48

_EMPTY = np.zeros(0, dtype=np.int64)


@dataclass
class PairSearch:
    """One k-d tree search: its pairs and what a later mover query needs."""

    i: np.ndarray
    j: np.ndarray
    small: np.ndarray                   # indices of the particles in the tree
    large: np.ndarray                   # indices of the large particles
    tree: Optional[cKDTree]             # tree of position[small] (None if < 2)


def search_pairs(position: np.ndarray, reach: np.ndarray) -> PairSearch:
    """Search all pairs with |p_i - p_j| <= reach_i + reach_j (a superset of them)."""
    n = position.shape[0]
    if n < 2:
        return PairSearch(_EMPTY, _EMPTY, np.arange(n), _EMPTY, None)
    large = reach > LARGE_RADIUS_FACTOR * _upper_median(reach)
    small_idx = np.flatnonzero(~large)
    large_idx = np.flatnonzero(large)
    parts_i, parts_j = [], []
    tree = None
    if small_idx.size:
        tree = cKDTree(position[small_idx])
    if small_idx.size >= 2:
        pairs = tree.query_pairs(2.0 * float(reach[small_idx].max()), output_type='ndarray')
        parts_i.append(small_idx[pairs[:, 0]])
        parts_j.append(small_idx[pairs[:, 1]])
    if large_idx.size:
        # Large against large: few by construction, so all pairs.
        a, b = np.triu_indices(large_idx.size, k=1)
        parts_i.append(large_idx[a])
        parts_j.append(large_idx[b])
        if small_idx.size:
            max_small = float(reach[small_idx].max())
            hits = tree.query_ball_point(position[large_idx], reach[large_idx] + max_small)
            partner_i, partner_j = _flatten_hits(large_idx, hits)
            parts_i.append(partner_i)
            parts_j.append(small_idx[partner_j])
    # Tree pairs, large-large and large-small pairs are disjoint sets of distinct pairs.
    i, j = _sorted_unique_pairs(parts_i, parts_j, n, repeats=False)
    return PairSearch(i, j, small_idx, large_idx, tree)


def candidate_pairs(position: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return index arrays (i < j) of pairs with |p_i - p_j| <= reach_i + reach_j.

    ``reach`` is each particle's radius plus any margin (for example the
    distance it may travel in a step). Pairs come sorted by (i, j) so that
    every later stage sees them in a deterministic order. The result may
    hold more pairs than that (everything a k-d tree search within twice
    the largest small reach finds); the narrowphase keeps the real contacts.
    """
    search = search_pairs(position, reach)
    return search.i, search.j


def _upper_median(values: np.ndarray) -> float:
    """Return the upper median (np.median costs ten times more on small arrays)."""
    middle = values.shape[0] // 2
    return float(np.partition(values, middle)[middle])


def _flatten_hits(queried: np.ndarray, hits) -> tuple[np.ndarray, np.ndarray]:
    """Turn query_ball_point's list of index lists into two index arrays."""
    counts = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
    if not counts.sum():
        return _EMPTY, _EMPTY
    found = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits if h])
    return np.repeat(queried, counts), found


def _sorted_unique_pairs(parts_i: list, parts_j: list, n: int,
                         repeats: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate pair parts, order each pair (i < j), sort by (i, j).

    With ``repeats`` the parts may share pairs (and hold i == j), which are
    dropped; without, they are known to be distinct and a sort suffices.
    """
    if not parts_i:
        return _EMPTY, _EMPTY
    i = np.concatenate(parts_i).astype(np.int64)
    j = np.concatenate(parts_j).astype(np.int64)
    if repeats:
        keep = i != j
        i, j = i[keep], j[keep]
    keys = np.minimum(i, j) * n + np.maximum(i, j)
    keys = np.unique(keys) if repeats else np.sort(keys)
    return keys // n, keys % n


class BroadphaseStage(Stage):
    """Find candidate pairs: a Verlet list over k-d tree searches.

    The list is tied to the state's ``radius`` array object and particle
    count: spawning (a new, longer state) or assigning a new radius array
    starts a fresh search. Radii changed in place would not be seen; no
    stage does that. Positions may change in any way between steps.
    """

    name = 'broadphase'

    def __init__(self) -> None:
        """Start without a list; the first step searches."""
        self._search: Optional[PairSearch] = None
        self._keys = _EMPTY            # sorted i * n + j of the listed pairs
        self._built_position: Optional[np.ndarray] = None
        self._built_radius: Optional[np.ndarray] = None
        self._half_skin = 0.0
        self._all_pairs = (_EMPTY, _EMPTY)
        self._all_pairs_count = -1
        self._direct = False           # allowances too large for the skin: search each step
        self.searches = 0              # full searches so far (for tests and benchmarks)
        self.mover_updates = 0         # steps that patched the list with mover pairs

    def run(self, ctx: StepContext) -> None:
        """Store candidate pairs on the context."""
        state = ctx.state
        ctx.pair_i, ctx.pair_j = self.find(state.position, state.radius, state.velocity,
                                           state.inv_mass, ctx.dt)

    def find(self, position: np.ndarray, radius: np.ndarray, velocity: np.ndarray,
             inv_mass: np.ndarray, dt: float, extra: Optional[np.ndarray] = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Return every pair (i < j, sorted) with |p_i - p_j| <= r_i + e_i + r_j + e_j.

        ``extra`` (e, default 0) is a per-particle allowance on top of the
        radius, e.g. |v| dt for swept contacts. It counts against the skin
        like a displacement: a particle whose displacement since the search
        plus e exceeds skin/2 is a mover, and movers are queried with their
        allowance, so the list stays exactly what a fresh search would need.
        """
        n = position.shape[0]
        if n <= ALL_PAIRS_UP_TO:
            if self._all_pairs_count != n:
                self._all_pairs = np.triu_indices(n, k=1)   # sorted by (i, j)
                self._all_pairs_count = n
            return self._all_pairs
        if extra is None:
            extra = np.zeros(n)
        if self._direct and self._list_matches(position, radius):
            # Allowances outgrew the skin last step: search directly until
            # they fit again, instead of rebuilding a list nobody can reuse.
            if np.count_nonzero(extra > self._half_skin) > MAX_MOVER_SHARE * n:
                return candidate_pairs(position, radius + extra)
            self._direct = False
            self._built_position = None
        if not self._list_matches(position, radius):
            self._rebuild(position, radius, velocity, inv_mass, dt)
        movers = self._movers(position, extra)
        if movers.size > MAX_MOVER_SHARE * n:
            self._rebuild(position, radius, velocity, inv_mass, dt)
            movers = self._movers(position, extra)
            if movers.size > MAX_MOVER_SHARE * n:
                self._direct = True
                return candidate_pairs(position, radius + extra)
        if movers.size == 0:
            return self._search.i, self._search.j
        keys = self._with_mover_pairs(position, radius, movers, extra)
        self.mover_updates += 1
        return keys // n, keys % n

    def _movers(self, position: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """Return the particles whose displacement plus allowance exceeds skin/2."""
        moved = position - self._built_position
        return np.flatnonzero(np.sqrt(np.einsum('ij,ij->i', moved, moved)) + extra
                              > self._half_skin)

    def _list_matches(self, position: np.ndarray, radius: np.ndarray) -> bool:
        """Return whether the list was built for these particles (count and radii)."""
        return (self._built_position is not None
                and self._built_position.shape == position.shape
                and self._built_radius is radius)

    def _rebuild(self, position: np.ndarray, radius: np.ndarray, velocity: np.ndarray,
                 inv_mass: np.ndarray, dt: float) -> None:
        """Search afresh with reach = radius + skin / 2 and remember the positions."""
        n = position.shape[0]
        median_radius = _upper_median(radius)
        dynamic = inv_mass > 0.0
        rms_speed = float(np.sqrt(np.mean(np.einsum('ij,ij->i', velocity[dynamic],
                                                    velocity[dynamic])))) \
            if dynamic.any() else 0.0
        skin = min(SKIN_MAX_RADII * median_radius,
                   max(SKIN_STEPS * dt * rms_speed, SKIN_MIN_RADII * median_radius))
        self._half_skin = 0.5 * skin
        self._search = search_pairs(position, radius + self._half_skin)
        self._keys = self._search.i * n + self._search.j
        self._built_position = position.copy()
        self._built_radius = radius
        self.searches += 1

    def _with_mover_pairs(self, position: np.ndarray, radius: np.ndarray,
                          movers: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """Return the listed pair keys plus every pair a mover may now overlap."""
        n = position.shape[0]
        search = self._search
        parts_i, parts_j = [], []
        if search.tree is not None:
            # A mover against a particle that moved <= skin/2: that particle's
            # listed position is within r_i + r_j + skin/2 of the mover now.
            max_small = float(radius[search.small].max())
            # With an allowance e_j <= skin/2 - displacement_j for non-movers,
            # the same bound holds with the mover's own e added.
            hits = search.tree.query_ball_point(
                position[movers], radius[movers] + extra[movers] + max_small + self._half_skin)
            mover_i, found = _flatten_hits(movers, hits)
            parts_i.append(mover_i)
            parts_j.append(search.small[found])
        if search.large.size:
            # Movers against the (few) large particles: all pairs.
            parts_i.append(np.repeat(movers, search.large.size))
            parts_j.append(np.tile(search.large, movers.size))
        # Movers against movers, at their current positions (all pairs if few).
        if movers.size <= ALL_PAIRS_UP_TO:
            between_i, between_j = np.triu_indices(movers.size, k=1)
        else:
            between = search_pairs(position[movers], radius[movers] + extra[movers])
            between_i, between_j = between.i, between.j
        parts_i.append(movers[between_i])
        parts_j.append(movers[between_j])
        extra_i, extra_j = _sorted_unique_pairs(parts_i, parts_j, n)
        extra = extra_i * n + extra_j
        keys = self._keys
        at = np.searchsorted(keys, extra)
        listed = keys[np.minimum(at, keys.size - 1)] == extra if keys.size else \
            np.zeros(extra.size, dtype=bool)
        return np.insert(keys, at[~listed], extra[~listed])

    def describe(self) -> str:
        """Say what the stage does."""
        return ('k-d tree pairs within r_i + r_j + skin, reused while no particle pair moved '
                'a skin (fast movers queried alone; large particles queried on their own)')
