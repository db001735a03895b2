"""Contact solve: impulses along the line of action, one contact at a time (Gauss-Seidel).

Sweeps visit the pairs, then the particles touching each wall plane, until
no contact approaches faster than the tolerance or the iteration budget is
spent. Each impulse is the law's (``law/primitives.py``): a scene without
effects (e = 1, no threshold) gets exactly the lecture's impulses. What
the solve adds to the law:

- e and mu per contact by the combine rule, e set to 0 below the
  restitution threshold: an impulse gets e only if its contact closes
  faster than the threshold and either did so before the solve (an
  impact) or touches a particle that an impact struck within it;
- friction right after each normal impulse, bounded by mu times it;
- speculative contacts (under a restitution threshold): a pair or wall
  contact found within its speculative distance before it touches, gap
  g > 0, may close at most by g / dt (``closing_allowance``): it touches at
  the end of the next drift instead of overlapping; an impact found so is
  left to the swept stage, at its time of impact, so isolated impacts keep
  the lecture's impulse there; without a swept stage (``early_impacts``,
  ``fast``) it gets the lecture's impulse at once, before it overlaps;
- every impulse between two particles is equal and opposite: momentum
  changes only at walls and static particles;
- resting contact (below the threshold) is solved with accumulated
  impulses, clamped >= 0 and into the Coulomb cone, kept per contact in
  ``ContactCache`` by stable particle ids and applied first in the next
  step where the contact persists (warm starting); impact impulses are
  never cached;
- the energy removed is booked per effect ('restitution', 'walls',
  'friction'), and with an impact log each contact that received impulses
  is recorded once per solve.

The whole solve, its set-up included, is one compiled call per step
(``contact_kernels.solve_step``), visiting the pairs in the broadphase's
sorted order (the order Gauss-Seidel walks a chain such as Newton's cradle
from its low end in one sweep). With ``visit='colours'`` it visits them
colour by colour instead, the order of the vectorised reference the tests
compare it with.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...law import coloring
from ...law.primitives import Bodies, FRICTION, RESTITUTION, WALLS
from ...model.effects import Walls
from ...model.impacts import record_pairs, record_walls
from ...model.tunables import (COLD_START_SWEEPS, PARALLEL_MIN_ITEMS, RESIDUAL_FRACTION,
                               SPECULATIVE_MARGIN, STRIKE_FACTOR)
from ...step.pipeline import Contacts, Stage, StepContext
from .contact_kernels import (Coefficients, MAX_CACHED_ID, solve_step, SolverSettings,
                              StepContacts, support_shift, WarmStartCache)
from .wall_kernels import WallPlanes
from .walls import wall_planes

# Orders the kernel visits contacts in: 'pairs' (the broadphase's sorted
# (i, j) order) or 'colours' (the reference's).
VISITS = ('pairs', 'colours')

# Empty arrays handed to the kernel where a scene has no such data.
_NO_ROWS = np.zeros(0, dtype=np.int64)
_NO_VALUES = np.zeros(0)


def solve_order(i: np.ndarray, j: np.ndarray, dynamic: np.ndarray) -> list[np.ndarray]:
    """Return the colour batches of the pairs: one per colour, then each overflow pair alone."""
    batches, overflow = coloring.color_pairs(i, j, dynamic, coloring.MAX_COLORS)
    return batches + [overflow[k:k + 1] for k in range(overflow.size)]


def colour_order(i: np.ndarray, j: np.ndarray, dynamic: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Return (visit order, colour starts): ``solve_order``'s batches as the kernel takes them.

    Colour c is order[start[c]:start[c + 1]]; the overflow pairs follow the
    last colour, visited one at a time.
    """
    batches, overflow = coloring.color_pairs(i, j, dynamic, coloring.MAX_COLORS)
    start = np.zeros(len(batches) + 1, dtype=np.int64)
    start[1:] = np.cumsum([batch.size for batch in batches], dtype=np.int64)
    order = np.concatenate(batches + [overflow]) if batches else overflow
    return np.ascontiguousarray(order, dtype=np.int64), start


def _own(values: Optional[np.ndarray]) -> np.ndarray:
    """Return per-particle coefficients as the kernel takes them (empty: none)."""
    return _NO_VALUES if values is None else np.ascontiguousarray(values, dtype=float)


class ContactCache:
    """Accumulated resting impulses of the last solve, keyed by stable particle ids.

    Pairs are keyed by (lower id, higher id), wall contacts by (id, plane:
    axis * 2 + 1 for a plane facing +axis); tangential impulses are stored as
    the impulse on the lower id. Ids never change or get reused (``World``:
    a spawn takes new ids, a delete leaves a gap), so a contact between
    particles that survive a delete or spawn finds its entry, and one with a
    deleted particle is simply never looked up again. A world reset builds a
    new pipeline and with it an empty cache.
    """

    # Keys are lower * stride + higher in int64: ids up to 2**31 are safe.
    MAX_ID = MAX_CACHED_ID

    def __init__(self) -> None:
        """Start empty."""
        self.clear()

    def clear(self) -> None:
        """Forget every contact."""
        none = np.zeros(0, dtype=np.int64)
        self.adopt(WarmStartCache(none, np.zeros(0), np.zeros((0, 3)), none, np.zeros(0),
                                  np.zeros((0, 3))))

    def adopt(self, kept: WarmStartCache) -> None:
        """Hold the contacts a compiled solve kept (``contact_kernels.solve_step``).

        Pair keys and wall keys (id * 8 + plane code) come sorted ascending,
        each with its normal and tangential impulse.
        """
        self.kept = kept
        stride = self.MAX_ID + 1
        self.lo, self.hi = kept.key // stride, kept.key % stride

    key = property(lambda self: self.kept.key, doc='Pair keys, ascending.')
    normal = property(lambda self: self.kept.normal, doc='Normal impulse per pair, N s.')
    tangential = property(lambda self: self.kept.tangential,
                          doc='Tangential impulse on the lower id per pair, N s.')
    wall_key = property(lambda self: self.kept.wall_key, doc='Wall keys, ascending.')
    wall_normal = property(lambda self: self.kept.wall_normal,
                           doc='Normal impulse per wall contact, N s.')
    wall_tangential = property(lambda self: self.kept.wall_tangential,
                               doc='Tangential impulse per wall contact, N s.')

    def __len__(self) -> int:
        """Return the number of contacts held (pairs and wall contacts)."""
        return int(self.lo.size + self.kept.wall_key.size)


class SequentialImpulseStage(Stage):
    """Resolve approaching contacts with restitution, one contact at a time."""

    name = 'contact_impulses'

    def __init__(self, restitution: float, iterations: int,
                 friction: Optional[float] = None, walls: Optional[Walls] = None,
                 gravity: Optional[np.ndarray] = None, visit: str = 'pairs') -> None:
        """Keep the particle-particle restitution, the sweep budget, friction mu and walls.

        With walls, particles touching a wall plane are solved together with
        the pairs in every sweep, so a pile rests on its floor. The
        restitution threshold comes from the step's effects
        (``Effects.threshold(dt)``), since its default depends on dt.
        """
        if visit not in VISITS:
            raise ValueError(f'visit must be one of {VISITS}, got {visit!r}')
        self.restitution = restitution
        self.iterations = iterations
        self.friction = friction
        self.walls = walls
        self.gravity = gravity
        self.visit = visit
        # Speculative contacts under a restitution threshold (see the module doc);
        # with early impacts (no swept stage) an impact found before it touches
        # bounces at once.
        self.speculative = True
        self.early_impacts = False
        # Accumulated resting impulses, warm-started from the previous step
        # where contacts persist (under a restitution threshold).
        self.warm_start = True
        self.cache = ContactCache()
        # The wall planes as the kernel takes them, built on first use.
        self._plane_arrays: Optional[tuple] = None
        # The spin the kernel gets in a world without spin: zeros, never changed.
        self._no_spin = np.zeros((0, 3))
        # Sweeps run, summed over the solves, and in the last solve.
        self.sweeps = self.solves = self.last_sweeps = 0

    @staticmethod
    def _fall(ctx: StepContext) -> tuple:
        """Return g dt of the (sub)step, m/s per axis (zeros without gravity)."""
        gravity = ctx.effects.gravity
        if gravity is None:
            return (0.0, 0.0, 0.0)
        g = np.asarray(gravity, dtype=float)
        return (float(g[0] * ctx.dt), float(g[1] * ctx.dt), float(g[2] * ctx.dt))

    def run(self, ctx: StepContext) -> None:
        """Apply the law's impulses in place, count the contacts hit, book and record them.

        The restitution threshold (Box2D's idea: slow contacts are resting,
        so e = 0) is judged per impulse: a pair closing faster than it before
        the solve is an impact; an impulse with e > 0 on a pair closing at
        STRIKE_FACTOR thresholds marks both particles struck, and a pair
        touching a struck particle keeps its e. So the shock of an impact
        travels through resting contacts with their e, as in the sequential
        impact model (a ball dropped at e = 1 on a resting column leaves at
        its impact speed, whatever the column's height), while the sweeps'
        own back-and-forth in a resting pile stays inelastic.
        """
        contacts = ctx.contacts if ctx.contacts is not None else Contacts.empty()
        if self.walls is None and len(contacts) == 0:
            return
        state = ctx.state
        threshold = float(ctx.effects.threshold(ctx.dt))
        friction = self.friction is not None
        speculative = self.speculative and threshold > 0.0
        i = np.ascontiguousarray(contacts.i, dtype=np.int64)
        j = np.ascontiguousarray(contacts.j, dtype=np.int64)
        normal = np.ascontiguousarray(contacts.normal, dtype=float)
        n = len(state)
        # The kernel works on contiguous float arrays; write back if copies were made.
        velocity = np.ascontiguousarray(state.velocity, dtype=float)
        spin = state.angular_velocity
        # Without spin (no friction) the kernel gets a zero array it never reads
        # or writes, kept from step to step.
        if spin is None and self._no_spin.shape[0] != n:
            self._no_spin = np.zeros((n, 3))
        angular = (self._no_spin if spin is None
                   else np.ascontiguousarray(spin, dtype=float))
        # Colour by colour with visit='colours', and in any solve large enough to
        # share among threads, at every thread count (one result for all).
        colours = self.visit == 'colours' or i.size >= PARALLEL_MIN_ITEMS
        order = colour_start = _NO_ROWS
        # Gaps (> 0: found before touching) of the narrowphase's speculative pairs.
        gap = (np.ascontiguousarray(-contacts.penetration, dtype=float) if speculative
               else _NO_VALUES)
        # With colours the kernel gets the pairs rearranged in visit order, so every
        # sweep reads each pair's data in sequence rather than colour by colour across
        # the whole array; ``rank`` maps them back for the impact log.
        rank = None
        if colours:
            visit, colour_start = colour_order(i, j, state.dynamic)
            rank = np.empty_like(visit)
            rank[visit] = np.arange(visit.size, dtype=np.int64)
            i, j, normal = i[visit], j[visit], np.ascontiguousarray(normal[visit])
            gap = gap[visit] if gap.size else gap
            order = np.arange(visit.size, dtype=np.int64)
        settings = SolverSettings(
            threshold > 0.0, threshold, float(RESIDUAL_FRACTION * threshold),
            float(STRIKE_FACTOR), int(self.iterations), friction, ctx.dimensions == 2,
            self.warm_start and threshold > 0.0, colours, float(ctx.dt),
            float(threshold * ctx.dt) if speculative else 0.0,
            float(SPECULATIVE_MARGIN) if speculative else 0.0, bool(self.early_impacts),
            *self._fall(ctx), int(ctx.threads))
        coefficients = Coefficients(
            _own(state.restitution), _own(state.friction) if friction else _NO_VALUES,
            float(self.restitution),
            float(self.walls.restitution) if self.walls is not None else 0.0,
            float(self.friction) if friction else 0.0)
        bodies = Bodies(velocity, angular, np.ascontiguousarray(state.inv_mass, dtype=float),
                        np.ascontiguousarray(state.radius, dtype=float))
        # The records as plain tuples: the compiled dispatcher types those fast.
        step_contacts = tuple(StepContacts(i, j, normal, order, gap, colour_start))
        result = solve_step(
            tuple(bodies), np.ascontiguousarray(state.position, dtype=float),
            np.ascontiguousarray(state.ids, dtype=np.int64), step_contacts,
            tuple(self._planes(ctx.dimensions)), tuple(coefficients), tuple(settings),
            tuple(self.cache.kept), ctx.losses if ctx.losses is not None else _NO_VALUES,
            (ctx.near_walls is not None,
             _NO_ROWS if ctx.near_walls is None else ctx.near_walls))
        self.cache.adopt(result.cache)
        if ctx.effects.gravity is not None:
            # How far the resting contacts held each particle up: the separation
            # stage moves them by it (see ``contact_kernels.support_shift``).
            ctx.support_shift = support_shift(
                bodies.inv_mass, step_contacts, tuple(result.pairs), tuple(result.walls),
                tuple(result.wall_impulses), self._fall(ctx), float(ctx.dt))
        self.sweeps += int(result.sweeps)
        self.solves += 1
        self.last_sweeps = int(result.sweeps)
        if velocity is not state.velocity:
            state.velocity[...] = velocity
        if spin is not None and angular is not spin:
            spin[...] = angular
        walls, wall_impulses, pairs = result.walls, result.wall_impulses, result.pairs
        effects = [(RESTITUTION, 'restitution')]
        if walls.particle.size:
            effects.append((WALLS, 'walls'))
        if friction:
            effects.append((FRICTION, 'friction'))
        for row, effect in effects:
            ctx.stats.add_dissipated(effect, float(result.totals[row]))
        ctx.stats.collisions += int(np.count_nonzero(pairs.hit))
        ctx.stats.wall_collisions += int(np.count_nonzero(wall_impulses.hit))
        if ctx.impacts is None:
            return
        if rank is not None:
            # Back to the narrowphase's order: the log lists pairs as it found them.
            i, j, normal = i[rank], j[rank], normal[rank]
            pairs = type(pairs)(*(field[rank] for field in pairs))
        pushed = pairs.normal > 0.0
        record_pairs(ctx.impacts, ctx.time, state.position, state.radius, i[pushed], j[pushed],
                     normal[pushed], pairs.normal[pushed], pairs.tangential[pushed],
                     np.maximum(pairs.approach[pushed], 0.0))
        planes = [] if self.walls is None else self.walls.planes(ctx.dimensions)
        for (axis, plane, inward), lo, hi in zip(planes, walls.start[:-1], walls.start[1:]):
            pushed = wall_impulses.normal[lo:hi] > 0.0
            record_walls(ctx.impacts, ctx.time, state.position, walls.particle[lo:hi][pushed],
                         axis, plane, inward, wall_impulses.normal[lo:hi][pushed],
                         wall_impulses.tangential[lo:hi][pushed],
                         np.maximum(wall_impulses.approach[lo:hi][pushed], 0.0))

    def _planes(self, dimensions: int) -> WallPlanes:
        """Return the wall planes as the kernel takes them (``WallPlanes``), built once."""
        if self._plane_arrays is None or self._plane_arrays[0] != (self.walls, dimensions):
            planes = [] if self.walls is None else self.walls.planes(dimensions)
            self._plane_arrays = ((self.walls, dimensions), wall_planes(planes))
        return self._plane_arrays[1]

    def describe(self) -> str:
        """Say what the stage does."""
        text = (f'impulse j = -(1+e) vn / (w1+w2) along N, e = {self.restitution:g}, '
                f'contact by contact, up to {self.iterations} sweeps')
        if self.walls is not None:
            text += '; wall contacts in every sweep'
        if self.friction is not None:
            text += (f'; Coulomb friction mu = {self.friction:g} with spin '
                     '(|J_t| <= mu j, I = 2/5 m r^2)')
        if self.gravity is not None:
            text += ('; e = 0 below the restitution threshold; speculative contacts close by '
                     'at most their gap in the next step')
        if self.warm_start:
            text += ('; resting impulses accumulated (clamped) and warm-started from the '
                     f'previous step, up to {COLD_START_SWEEPS} sweeps when most start cold')
        return text
