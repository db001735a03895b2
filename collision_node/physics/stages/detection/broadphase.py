"""Broadphase: candidate pairs whose spheres may overlap.

Particles are sorted into size classes by their reach (radius plus any
margin): class k holds reaches in [m * 2^k, m * 2^(k+1)), m the smallest
reach. Each class gets a uniform cell grid, cells twice the class's largest
reach wide (``grid_kernels``). Each particle is searched in its own class
and in every larger class within its own reach plus that class's largest,
and every pair found is checked against its own reach_i + reach_j, so the
result is exactly the set of near pairs and the work stays proportional to
it, whatever the mix of sizes.

The stage does not search every step. It keeps a Verlet list: the pairs
within r_i + r_j + skin at the last search, valid as long as no two
particles have together moved more than the skin since. The check uses the
actual positions, so it covers every stage. The few fast particles that
moved more than skin/2 ("movers") are queried on their own against the
class grids of the last search; only when movers become common is the grid
rebuilt. The result is exactly the set a fresh search would need.

Memory is bounded by the step's budget (``STEP_MEMORY_BUDGET`` over
``PAIR_BYTES`` per pair: ``MAX_PAIRS``). An allowance (a swept stage's
|v| dt) much wider than the particles can make the sphere of reach hold
far more pairs than can meet: then the particles are searched along their
paths, keeping a pair only if their straight paths over the step come
within their radii (plus what the allowance adds beyond |v| dt, the sag
under gravity) at the same moment. A world whose pairs still do not fit is
refused with ``StepTooLarge`` (a ``SceneError`` and a ``MemoryError``)
that says how many pairs it would need and why: ``check_pair_budget`` does
this at a request (scene load, spawn, accuracy), the stage at a step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, TYPE_CHECKING

import numpy as np

from . import grid_kernels
from .grid_kernels import Found, Grid, PathMotion, SearchLimit
from ...step.pipeline import Stage, StepContext
from ...step.threads import parallel
from ...model.validation import SceneError
from ...model.tunables import (CLASS_RATIO, SKIN_STEPS, SKIN_MAX_RADII, SKIN_MIN_RADII,
                               MAX_MOVER_SHARE, ALL_PAIRS_UP_TO, STEP_MEMORY_BUDGET, PAIR_BYTES,
                               MAX_PATH_TESTS, SPECULATIVE_MARGIN)

if TYPE_CHECKING:
    from ..ordering.spatial_order import SpatialOrder

# The pair test |p_i - p_j|^2 <= (reach_i + reach_j)^2 (1 + QUERY_SLACK) is a
# little generous, so that rounding never drops a pair; the grid's cell
# search is wider still (``grid_kernels.SCAN_SLACK``).
QUERY_SLACK = grid_kernels.PAIR_SLACK

_EMPTY = np.zeros(0, dtype=np.int64)

# The most candidate pairs one search may hold: the step's memory budget.
MAX_PAIRS = int(STEP_MEMORY_BUDGET // PAIR_BYTES)


class StepTooLarge(SceneError, MemoryError):
    """A world whose step would need more candidate pairs than the memory budget holds."""


def _limit() -> SearchLimit:
    """Return the bounds of one search (read here, so a test may lower ``MAX_PAIRS``)."""
    return SearchLimit(int(MAX_PAIRS), int(MAX_PATH_TESTS))


def _still() -> PathMotion:
    """Return the ``PathMotion`` of a search of spheres only."""
    return PathMotion(False, np.zeros((0, 3)), np.zeros(0), np.zeros(1, dtype=np.int64))


def _too_large(found: Found, position: np.ndarray, reach: np.ndarray,
               along_paths: bool) -> StepTooLarge:
    """Return the refusal of a search that gave up, saying what it would need and why.

    ``found`` is the sphere search's (its estimate of the pairs needed);
    ``along_paths``: the search along paths gave up as well.
    """
    points = grid_kernels.as_points(position)
    extent = float(np.max(points.max(axis=0) - points.min(axis=0)))
    paths = ' (too many along their paths too)' if along_paths else ''
    amount = 'about' if found.estimated else 'more than'
    return StepTooLarge(
        f'the contact search needs {amount} {max(found.needed, float(MAX_PAIRS)):.2g} '
        f'candidate pairs{paths}, over the step memory budget of {MAX_PAIRS:.2g} '
        f'(STEP_MEMORY_BUDGET): {len(reach)} particles reach {float(reach.max()):.2g} m '
        f'(radius + travel per step) across {extent:.2g} m; use fewer, smaller or slower '
        'particles or a shorter dt')


@dataclass
class PairSearch:
    """One search: its pairs and the class grids a later mover query needs."""

    i: np.ndarray
    j: np.ndarray
    grid: Optional[Grid] = None


def size_classes(reach: np.ndarray) -> list[np.ndarray]:
    """Split particle indices into classes whose reaches differ by < CLASS_RATIO.

    Class k holds reaches in [m * CLASS_RATIO^k, m * CLASS_RATIO^(k+1)),
    m the smallest positive reach (reaches of 0 join the first class).
    Returns the non-empty classes, smallest reach first, indices ascending.
    """
    largest = float(reach.max()) if reach.size else 0.0
    if largest > 0.0 and largest < 1.9 * float(reach.min()):
        # All reaches within a factor 1.9 (a gas of one size): one class, the
        # logarithms below would give every particle level 0.
        return [np.arange(reach.shape[0])]
    positive = reach[reach > 0.0]
    if positive.size == 0:
        return [np.arange(reach.shape[0])]
    smallest = float(positive.min())
    with np.errstate(divide='ignore'):
        level = np.floor(np.log(np.maximum(reach, smallest) / smallest)
                         / np.log(CLASS_RATIO)).astype(np.int64)
    if level.max() == 0:
        return [np.arange(reach.shape[0])]
    order = np.argsort(level, kind='stable')           # ascending index within a level
    bounds = np.flatnonzero(np.diff(level[order])) + 1
    return np.split(order, bounds)


def _search(position: np.ndarray, reach: np.ndarray,
            paths: Optional[tuple[np.ndarray, np.ndarray]] = None,
            threads: int = 1) -> tuple[Found, Grid]:
    """Search the pairs within reach (and, with ``paths``, whose paths meet); may give up.

    ``paths`` is (shift, path reach) per particle: its displacement over
    the step and its reach about that straight path. ``threads``: how many
    threads may share a sphere search (the same pairs for any count).
    """
    reach = np.ascontiguousarray(reach, dtype=np.float64)
    grid = grid_kernels.make_grid(position, reach, size_classes(reach),
                                  parallel(threads, reach.shape[0]))
    if paths is None and parallel(threads, reach.shape[0]):
        return grid_kernels.grid_pairs_shared(reach, grid, _limit()), grid
    motion = _still()
    if paths is not None:
        shift, path_reach = paths
        motion = PathMotion(True, grid_kernels.as_points(shift)[grid.item],
                            np.ascontiguousarray(path_reach, dtype=np.float64)[grid.item],
                            np.zeros(1, dtype=np.int64))
    return grid_kernels.grid_pairs(reach, grid, _limit(), motion), grid


def search_pairs(position: np.ndarray, reach: np.ndarray, threads: int = 1) -> PairSearch:
    """Search all pairs with |p_i - p_j| <= reach_i + reach_j, exactly those.

    Raises ``StepTooLarge`` when they would be more than ``MAX_PAIRS``.
    ``threads``: how many threads may share the search (the same pairs).
    """
    n = position.shape[0]
    if n < 2:
        return PairSearch(_EMPTY, _EMPTY, None)
    found, grid = _search(position, reach, threads=threads)
    if not found.complete:
        raise _too_large(found, position, reach, False)
    return PairSearch(found.pairs.first, found.pairs.second, grid)


def candidate_pairs(position: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return index arrays (i < j) of the pairs with |p_i - p_j| <= reach_i + reach_j.

    ``reach`` is each particle's radius plus any margin (for example the
    distance it may travel in a step). Pairs come sorted by (i, j) so that
    every later stage sees them in a deterministic order. The set is exact
    up to a relative slack of 1e-9 on the reach (and offsets whose squares
    underflow); the narrowphase keeps the real contacts. Raises
    ``StepTooLarge`` when they would be more than ``MAX_PAIRS``.
    """
    search = search_pairs(position, reach)
    return search.i, search.j


def swept_pairs(position: np.ndarray, radius: np.ndarray, extra: np.ndarray,
                velocity: np.ndarray, dt: float, threads: int = 1
                ) -> tuple[np.ndarray, np.ndarray]:
    """Return the pairs within r + extra of each other, or along paths when they are too many.

    The sphere search (``candidate_pairs`` with reach radius + extra) first;
    if it would hold more than ``MAX_PAIRS``, the pairs whose straight paths
    (velocity * dt) come within radius + (extra - |v| dt) of each other at
    one moment: a subset, those that can meet in the step. Raises
    ``StepTooLarge`` when even those are too many (or too costly to find).
    ``threads``: how many threads may share the sphere search.
    """
    n = position.shape[0]
    if n < 2:
        return _EMPTY, _EMPTY
    reach = radius + extra
    found, _ = _search(position, reach, threads=threads)
    if found.complete:
        return found.pairs.first, found.pairs.second
    if not np.any(extra > 0.0):
        raise _too_large(found, position, reach, False)
    travel = np.sqrt(np.einsum('ij,ij->i', velocity, velocity)) * dt
    path_reach = radius + np.maximum(extra - travel, 0.0)
    along, _ = _search(position, reach, (velocity * dt, path_reach))
    if not along.complete:
        raise _too_large(found, position, reach, True)
    return along.pairs.first, along.pairs.second


def swept_allowance(velocity: np.ndarray, dynamic: np.ndarray, dt: float,
                    gravity: Optional[np.ndarray]) -> np.ndarray:
    """Return how far each particle may travel in a step of ``dt``: |v| dt (+ |g| dt^2 / 2)."""
    travel = np.sqrt(np.einsum('ij,ij->i', velocity, velocity)) * dt
    if gravity is not None:
        sag = float(np.linalg.norm(gravity))
        travel = travel + np.where(dynamic, 0.5 * sag * dt * dt, 0.0)
    return travel


def check_pair_budget(position: np.ndarray, radius: np.ndarray, velocity: np.ndarray,
                      inv_mass: np.ndarray, dt: float, extra: Optional[np.ndarray],
                      added: Optional[int] = None) -> None:
    """Raise ``StepTooLarge`` if a step's broadphase would need more than ``MAX_PAIRS``.

    Runs the search a first step would make (a fresh ``BroadphaseStage``
    with the allowance ``extra``, None for discrete detection) and keeps
    nothing. Free when every pair of the world fits the budget anyway, or
    when the last ``added`` particles (a spawn into a world checked before)
    can add at most half the budget's pairs.
    """
    n = position.shape[0]
    if n * (n - 1) // 2 <= MAX_PAIRS or (added is not None and added * n <= MAX_PAIRS // 2):
        return
    BroadphaseStage().find(position, radius, velocity, inv_mass, dt, extra)


def _rms_speed(velocity: np.ndarray, dynamic: np.ndarray) -> float:
    """Return the root mean square speed of the dynamic particles (0 with none).

    Each row's v . v is the same sum whether the rows are picked first or
    after, so the squares are taken over all rows, without copying them.
    """
    if not dynamic.any():
        return 0.0
    squares = np.einsum('ij,ij->i', velocity, velocity)
    return float(np.sqrt(np.mean(squares if dynamic.all() else squares[dynamic])))


def _upper_median(values: np.ndarray) -> float:
    """Return the upper median (np.median costs ten times more on small arrays)."""
    middle = values.shape[0] // 2
    return float(np.partition(values, middle)[middle])


class BroadphaseStage(Stage):
    """Find candidate pairs: a Verlet list over cell-grid searches.

    The list is tied to the state's ``radius`` array object and particle
    count: spawning (a new, longer state) or assigning a new radius array
    starts a fresh search. Radii changed in place would not be seen; no
    stage does that. Positions may change in any way between steps.
    """

    name = 'broadphase'

    def __init__(self, speculative: bool = False, impacts: bool = False) -> None:
        """Start without a list; the first step searches.

        ``speculative``: under a restitution threshold the pairs reach as far
        as the narrowphase's speculative contacts (``NarrowphaseStage``);
        ``impacts``: and as far as each particle moves in a step, |v| dt.
        """
        self.speculative = speculative
        self.impacts = impacts
        self._extra_floor = 0.0        # the largest allowance asked for (keeps the skin wider)
        self._search: Optional[PairSearch] = None
        self._keys = _EMPTY            # sorted i * n + j of the listed pairs
        self._built_position: Optional[np.ndarray] = None
        self._built_radius: Optional[np.ndarray] = None
        self._half_skin = 0.0
        # The listed radii in the grid's item order, and each size class's largest.
        self._partners = grid_kernels.Partners(np.zeros(0), np.zeros(0))
        self._all_pairs = (_EMPTY, _EMPTY)
        self._all_pairs_count = -1
        self._median_radius, self._median_of = 0.0, None
        self._direct = False           # allowances too large for the skin: search each step
        self.searches = 0              # full searches so far (for tests and benchmarks)
        self.threads = 1               # threads a search may share (the step's count)
        self.mover_updates = 0         # steps that patched the list with mover pairs
        # Puts a large world's rows in cell order before each full search
        # (``stages/ordering``; set by the plan on the step's first pair list).
        self.order: Optional[SpatialOrder] = None

    def run(self, ctx: StepContext) -> None:
        """Store candidate pairs on the context."""
        state = ctx.state
        extra = None
        if self.speculative:
            threshold = float(ctx.effects.threshold(ctx.dt))
            if threshold > 0.0:
                # Half of each pair's speculative distance on each side.
                extra = 0.5 * (threshold * ctx.dt + SPECULATIVE_MARGIN * state.radius)
                # The standing part widens the skin (``_rebuild``).
                self._extra_floor = float(np.max(extra)) if extra.size else 0.0
                if self.impacts:
                    extra = extra + ctx.dt * np.sqrt(
                        np.einsum('ij,ij->i', state.velocity, state.velocity))
        self.threads = ctx.threads
        ctx.pair_i, ctx.pair_j = self.find(state.position, state.radius, state.velocity,
                                           state.inv_mass, ctx.dt, extra, ctx=ctx)

    def find(self, position: np.ndarray, radius: np.ndarray, velocity: np.ndarray,
             inv_mass: np.ndarray, dt: float, extra: Optional[np.ndarray] = None,
             ctx: Optional[StepContext] = None) -> tuple[np.ndarray, np.ndarray]:
        """Return every pair (i < j, sorted) with |p_i - p_j| <= r_i + e_i + r_j + e_j.

        ``extra`` (e, default 0) is a per-particle allowance on top of the
        radius, e.g. |v| dt for swept contacts. It counts against the skin
        like a displacement: a particle whose displacement since the search
        plus e exceeds skin/2 is a mover, and movers are queried with their
        allowance, so the list stays exactly what a fresh search would need.
        Where those pairs would be more than ``MAX_PAIRS``, the movers' are
        those whose straight paths meet (``swept_pairs``); ``StepTooLarge``
        where even those are too many. With ``order`` and ``ctx`` (whose
        state's arrays the others are), a full search first puts the rows
        in cell order: the pairs returned name the new rows.
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
                return swept_pairs(position, radius, extra, velocity, dt, self.threads)
            self._direct = False
            self._built_position = None
        if not self._list_matches(position, radius):
            extra = self._in_cell_order(ctx, extra)
            self._rebuild(position, radius, velocity, inv_mass, dt)
        movers = self._movers(position, extra)
        if movers.size > MAX_MOVER_SHARE * n:
            extra = self._in_cell_order(ctx, extra)
            self._rebuild(position, radius, velocity, inv_mass, dt)
            movers = self._movers(position, extra)
            if movers.size > MAX_MOVER_SHARE * n:
                self._direct = True
                return swept_pairs(position, radius, extra, velocity, dt, self.threads)
        if movers.size == 0:
            return self._search.i, self._search.j
        self.mover_updates += 1
        pairs = self._with_mover_pairs(position, radius, movers, extra)
        if pairs is None:
            # The movers' reach holds too many pairs: search along their paths.
            return swept_pairs(position, radius, extra, velocity, dt, self.threads)
        return pairs

    def _in_cell_order(self, ctx: Optional[StepContext], extra: np.ndarray) -> np.ndarray:
        """Put the rows in cell order before a full search (if ordered here); rename ``extra``."""
        if self.order is None or ctx is None:
            return extra
        moved = self.order.apply(ctx)
        return extra if moved is None else extra[moved]

    def rows_moved(self, order: np.ndarray) -> None:
        """Drop the list: it names rows (the next ``find`` searches afresh)."""
        self._built_position = None
        self._direct = False

    def _movers(self, position: np.ndarray, extra: np.ndarray) -> np.ndarray:
        """Return the particles whose displacement plus allowance exceeds skin/2."""
        find = (grid_kernels.movers_shared if parallel(self.threads, position.shape[0])
                else grid_kernels.movers)
        return find(grid_kernels.as_points(position), self._built_position,
                    np.ascontiguousarray(extra, dtype=np.float64), self._half_skin)

    def _list_matches(self, position: np.ndarray, radius: np.ndarray) -> bool:
        """Return whether the list was built for these particles (count and radii)."""
        return (self._built_position is not None
                and self._built_position.shape == position.shape
                and self._built_radius is radius)

    def _rebuild(self, position: np.ndarray, radius: np.ndarray, velocity: np.ndarray,
                 inv_mass: np.ndarray, dt: float) -> None:
        """Search afresh with reach = radius + skin / 2 and remember the positions."""
        n = position.shape[0]
        if self._median_of is not radius:
            # The list is tied to this radius array: its median is computed once.
            self._median_radius, self._median_of = _upper_median(radius), radius
        median_radius = self._median_radius
        rms_speed = _rms_speed(velocity, inv_mass > 0.0)
        skin = min(SKIN_MAX_RADII * median_radius,
                   max(SKIN_STEPS * dt * rms_speed, SKIN_MIN_RADII * median_radius))
        # Wide enough that a standing allowance (speculative contacts) leaves
        # room for displacement before particles count as movers.
        skin = max(skin, 4.0 * self._extra_floor)
        self._half_skin = 0.5 * skin
        self._search = search_pairs(position, radius + self._half_skin, self.threads)
        self._keys = self._search.i * n + self._search.j
        self._built_position = grid_kernels.as_points(position).copy()
        self._built_radius = radius
        self._partners = grid_kernels.partner_terms(radius, self._search.grid)
        self.searches += 1

    def _with_mover_pairs(self, position: np.ndarray, radius: np.ndarray,
                          movers: np.ndarray, extra: np.ndarray
                          ) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """Return the listed pairs plus every pair a mover may now overlap (i < j, sorted).

        Returns None when the movers' pairs would be more than ``MAX_PAIRS``.
        """
        n = position.shape[0]
        mover_reach = radius[movers] + extra[movers] + self._half_skin
        # A mover against a particle that moved <= skin/2: that particle's
        # listed position is within r_i + r_j + skin/2 of the mover now.
        # With an allowance e_j <= skin/2 - displacement_j for non-movers,
        # the same bound holds with the mover's own e added.
        found = grid_kernels.grid_query(grid_kernels.as_points(position), movers, mover_reach,
                                        self._partners, self._search.grid, _limit())
        if not found.complete:
            return None
        near = found.pairs
        # Movers against movers, at their current positions (all pairs if few).
        if movers.size <= ALL_PAIRS_UP_TO:
            between_i, between_j = np.triu_indices(movers.size, k=1)
        else:
            between, _ = _search(position[movers], radius[movers] + extra[movers],
                                 threads=self.threads)
            if not between.complete:
                return None
            between_i, between_j = between.pairs.first, between.pairs.second
        listed = grid_kernels.Pairs(self._search.i, self._search.j)
        extra_pairs = grid_kernels.Pairs(np.concatenate([near.first, movers[between_i]]),
                                         np.concatenate([near.second, movers[between_j]]))
        merged = grid_kernels.merge_pairs(self._keys, listed, extra_pairs, n)
        return merged.first, merged.second

    def describe(self) -> str:
        """Say what the stage does."""
        return ('hashed cell grid per size class (compiled), pairs within r_i + r_j + skin, '
                'reused while no particle pair moved a skin (fast movers queried alone)')
