"""A Python event loop for the exact preset, the tests' reference for the compiled one.

A ``heapq`` of (time, seq, kind, p, q, stamps) tuples, a dict of cell sets
and vectorised predictions with the numpy contact law: the same rules as
``collision_node/physics/stages/events/event_driven.py``, written the plain
way. ``test/test_event_kernels.py`` runs it and the compiled stage on the
same worlds and asserts the same impacts at the same times to round-off
(the compiled loop predicts on another schedule, see its module doc). The
cell size is a parameter so that both can be run on the same grid.
"""

from __future__ import annotations

import heapq
import itertools
from typing import Callable, Optional

import numpy as np

from collision_node.physics.model.accuracy import (AccuracySettings, check_event_mode,
                                                   EVENT_FALLBACK, MIN_EVENT_BUDGET, PRESETS)
from oracles.contact_law import (apply_pair_impulses, apply_wall_impulses,
                                 pair_coefficient, record_pairs, record_walls,
                                 thresholded, wall_coefficient)
from collision_node.physics.model.effects import Effects
from oracles.paths import entering_time
from collision_node.physics.step.pipeline import Pipeline, Stage, StepContext
from collision_node.physics.model.state import ParticleState
from collision_node.physics.model.tunables import MAX_FALLBACK_HOLD, PARTICLES_PER_CELL
from collision_node.physics.stages.detection.narrowphase import line_of_action
from swept_reference import pair_impact_times

PAIR, WALL, CELL = 0, 1, 2


class NotExactable(Exception):
    """An event the TC model would have to alter under gravity: resting contact."""


class PythonEventStage(Stage):
    """Advance the world by dt exactly, impact by impact."""

    name = 'event_driven'

    def __init__(self, effects: Effects, accuracy: AccuracySettings,
                 fallback: Callable[[], Pipeline],
                 particles_per_cell: float = PARTICLES_PER_CELL) -> None:
        """Keep the effects it simulates; refuse any it cannot do exactly.

        ``fallback`` builds the step-solver pipeline for the steps this stage
        hands over (the plan passes it in, so no stage imports the plan).
        """
        check_event_mode(accuracy, effects, 'accuracy')
        self.gravity = np.zeros(3) if effects.gravity is None else np.asarray(effects.gravity,
                                                                              float)
        self.walls = effects.walls
        self.restitution = effects.particle_restitution
        self.collapse_time = accuracy.collapse_time
        self.event_budget = accuracy.event_budget
        self.accuracy, self.effects = accuracy, effects
        self.under_gravity = bool(np.any(self.gravity != 0.0))
        self.particles_per_cell = float(particles_per_cell)
        # A declared restitution threshold is part of the contact law. The
        # default one under gravity (2 |g| dt) is the step solvers' device for
        # resting contact, which this mode hands to them: exact impacts keep e.
        self.threshold = effects.restitution_threshold or 0.0
        self.time = 0.0
        self.events = 0
        self._state: Optional[ParticleState] = None
        self._fallback: Optional[Pipeline] = None
        self._build_fallback = fallback
        self._fallback_streak = 0
        self._hold = 0

    # -- bookkeeping -------------------------------------------------------

    def _rebuild(self, state: ParticleState, dimensions: int) -> None:
        """Set up clocks, grid and predictions for ``state`` at ``self.time``."""
        n = len(state)
        # This loop's paths are straight relative to each other only when every
        # particle falls: static particles under gravity are the stage's.
        assert self.effects.gravity is None or np.all(state.inv_mass > 0.0)
        self._state = state
        self.dims = dimensions
        self.ref_time = np.full(n, self.time)
        self.last_impact = np.full(n, -np.inf)
        self.count = np.zeros(n, dtype=np.int64)
        self.heap: list = []
        self.seq = itertools.count()
        offsets = np.zeros((3 ** dimensions, 3), dtype=np.int64)
        offsets[:, :dimensions] = list(itertools.product((-1, 0, 1), repeat=dimensions))
        self.offsets = offsets
        if n == 0:
            self.cell_size = 1.0
            self.cell = np.zeros((0, 3), dtype=np.int64)
            self.grid: dict = {}
            return
        self.cell_size = self._choose_cell_size(state, dimensions)
        self.cell = np.zeros((n, 3), dtype=np.int64)
        self.cell[:, :dimensions] = np.floor(state.position[:, :dimensions] / self.cell_size)
        keys, inverse = np.unique(self.cell, axis=0, return_inverse=True)
        order = np.argsort(inverse.ravel(), kind='stable')
        bounds = np.searchsorted(inverse.ravel()[order], np.arange(keys.shape[0] + 1))
        self.grid = {tuple(keys[k].tolist()): set(order[bounds[k]:bounds[k + 1]].tolist())
                     for k in range(keys.shape[0])}
        for p in np.flatnonzero(state.dynamic):
            self._predict(int(p), self.time)

    def _choose_cell_size(self, state: ParticleState, dimensions: int) -> float:
        """Cells at least one contact diameter wide, about 8 particles each."""
        diameter = 2.0 * float(state.radius.max()) * (1.0 + 1e-9)
        pos = state.position[:, :dimensions]
        extent = pos.max(axis=0) - pos.min(axis=0) + diameter
        if self.walls is not None:
            # A box side bounds the cells' region; an open side (an infinite
            # plane) does not, and must not make the cells infinitely wide.
            between = (self.walls.high - self.walls.low)[:dimensions]
            extent = np.where(np.isfinite(between), between, extent)
        volume = float(np.prod(np.maximum(extent, diameter)))
        spacing = (self.particles_per_cell * volume / len(state)) ** (1.0 / dimensions)
        return max(diameter, spacing)

    def _still_valid(self, state: ParticleState) -> bool:
        """Return whether ``state`` is the one left by the last step, untouched."""
        return (state is self._state and len(state) == self.count.size
                and np.array_equal(state.position, self._position_after)
                and np.array_equal(state.velocity, self._velocity_after))

    # -- motion ------------------------------------------------------------

    def _advance(self, index, when: float) -> None:
        """Bring particle(s) ``index`` to time ``when`` on their exact paths."""
        s = self._state
        tau = np.asarray(when - self.ref_time[index], float)[..., None]
        s.position[index] += s.velocity[index] * tau + 0.5 * self.gravity * tau * tau
        s.velocity[index] += self.gravity * tau
        self.ref_time[index] = when

    def _sync_all(self, when: float) -> None:
        """Bring every particle to time ``when`` (one vectorised update)."""
        self._advance(slice(None), when)

    def _neighbours(self, p: int) -> np.ndarray:
        """Return the particles in the 3^d cells around particle ``p``'s cell."""
        found: list[int] = []
        get = self.grid.get
        for key in (self.offsets + self.cell[p]).tolist():
            members = get(tuple(key))
            if members:
                found.extend(members)
        out = np.fromiter(found, dtype=np.int64, count=len(found))
        return out[out != p]

    def _boundary_times(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """Return per-column (low x, high x, ...) times to reach walls and cell faces."""
        s = self._state
        d = self.dims
        x, v, g = s.position[p, :d], s.velocity[p, :d], self.gravity[:d]
        low_face = self.cell[p, :d] * self.cell_size
        gaps = [x - low_face, (low_face + self.cell_size) - x]
        if self.walls is not None:
            r = s.radius[p]
            gaps += [x - (self.walls.low[:d] + r), (self.walls.high[:d] - r) - x]
        k = len(gaps) // 2
        times = entering_time(np.concatenate(gaps), np.concatenate([v, -v] * k),
                              np.concatenate([g, -g] * k))
        # Columns in (low x, high x, low y, ...) order, cells then walls.
        cells = np.empty(2 * d)
        cells[0::2], cells[1::2] = times[:d], times[d:2 * d]
        walls = np.full(2 * d, np.inf)
        if k == 2:
            walls[0::2], walls[1::2] = times[2 * d:3 * d], times[3 * d:]
        return walls, cells

    def _predict(self, p: int, when: float) -> None:
        """Invalidate particle ``p``'s events and push its new ones (p is at ``when``)."""
        self.count[p] += 1
        stamp = int(self.count[p])
        walls, cells = self._boundary_times(p)
        push = heapq.heappush
        if np.isfinite(walls).any():
            col = int(np.argmin(walls))
            push(self.heap, (when + float(walls[col]), next(self.seq), WALL, p, col, stamp, 0))
        col = int(np.argmin(cells))
        if np.isfinite(cells[col]):
            push(self.heap, (when + float(cells[col]), next(self.seq), CELL, p, col, stamp, 0))
        others = self._neighbours(p)
        if not others.size:
            return
        self._advance(others, when)
        s = self._state
        a = np.full(others.size, p, dtype=np.int64)
        times = pair_impact_times(s.position, s.velocity, s.radius, np.zeros(s.radius.size),
                                  a, others)
        for k in np.flatnonzero(np.isfinite(times)):
            q = int(others[k])
            push(self.heap, (when + float(times[k]), next(self.seq), PAIR, p, q, stamp,
                             int(self.count[q])))

    # -- events ------------------------------------------------------------

    def _in_collapse(self, when: float, *particles: int) -> bool:
        """Return whether any particle had an impact within t_c before ``when``."""
        return any(when - self.last_impact[p] < self.collapse_time for p in particles)

    def _pair_event(self, ctx: StepContext, when: float, p: int, q: int) -> None:
        """Apply the impulse of particles p and q at their contact."""
        s = self._state
        both = np.array([p, q])
        self._advance(both, when)
        a, b = both[:1], both[1:]
        normal, _ = line_of_action(s.position[a] - s.position[b],
                                   s.velocity[a] - s.velocity[b])
        approach = -float((s.velocity[p] - s.velocity[q]) @ normal[0])
        e = thresholded(pair_coefficient(s.restitution, a, b, self.restitution),
                        np.array([approach]), self.threshold)
        e = float(np.asarray(e).reshape(-1)[0])
        if self._in_collapse(when, p, q) and e < 1.0:
            if self.under_gravity:
                raise NotExactable
            e = 1.0
        result = apply_pair_impulses(s.velocity, s.inv_mass, a, b, normal, e)
        if result.hit[0]:
            ctx.stats.collisions += 1
            ctx.book('restitution', result.removed, a, b)
            record_pairs(ctx.impacts, when, s.position, s.radius, a, b, normal,
                         result.magnitude, 0.0, result.approach)
        self.last_impact[both] = when
        for k in (p, q):
            if s.inv_mass[k] > 0.0:  # a static particle's events stay valid
                self._predict(k, when)

    def _wall_event(self, ctx: StepContext, when: float, p: int, col: int) -> None:
        """Reflect particle p's normal velocity at a wall (TC model near collapse)."""
        s = self._state
        self._advance(p, when)
        axis, high = divmod(col, 2)
        toward = 1.0 if high else -1.0      # direction of the wall along the axis
        speed_in = toward * s.velocity[p, axis]
        pushed_in = toward * self.gravity[axis]
        if speed_in > 0.0 or (speed_in == 0.0 and pushed_in > 0.0):
            index = np.array([p])
            e = thresholded(wall_coefficient(s.restitution, index, self.walls.restitution),
                            np.array([speed_in]), self.threshold)
            e = float(np.asarray(e).reshape(-1)[0])
            if self._in_collapse(when, p):
                resting = pushed_in > 0.0 and speed_in < 0.5 * pushed_in * self.collapse_time
                if self.under_gravity and (e < 1.0 or resting):
                    raise NotExactable      # resting on the wall: the step solver takes it
                e = 1.0
            plane = float(self.walls.high[axis] if high else self.walls.low[axis])
            _, magnitude, approach, removed = apply_wall_impulses(
                s.velocity, s.inv_mass, index, axis, -toward, e, tolerance=-np.inf)
            ctx.book('walls', removed, index)
            s.position[p, axis] = plane - toward * s.radius[p]  # exact contact, no drift
            ctx.stats.wall_collisions += 1
            record_walls(ctx.impacts, when, s.position, index, axis, plane, -toward,
                         magnitude, 0.0, approach)
            self.last_impact[p] = when
        self._predict(p, when)

    def _cell_event(self, when: float, p: int, col: int) -> None:
        """Move particle p into the next cell and predict against its new neighbours."""
        self._advance(p, when)
        axis, high = divmod(col, 2)
        old = tuple(self.cell[p].tolist())
        self.cell[p, axis] += 1 if high else -1
        new = tuple(self.cell[p].tolist())
        members = self.grid[old]
        members.discard(p)
        if not members:
            del self.grid[old]
        self.grid.setdefault(new, set()).add(p)
        self._predict(p, when)

    # -- the stage ---------------------------------------------------------

    def run(self, ctx: StepContext) -> None:
        """Process every event up to the end of the step, then sync all particles.

        A step that meets resting contact under gravity, or would take more
        events than its budget, is rolled back and solved by the step solver
        (see the module doc).
        """
        if self._hold:
            self._hold -= 1
            self._fallback_step(ctx)
            return
        state = ctx.state
        if not self._still_valid(state):
            self._rebuild(state, ctx.dimensions)
        budget = max(MIN_EVENT_BUDGET, self.event_budget * len(state))
        saved = (state.position.copy(), state.velocity.copy(), ctx.stats.copy(), self.events)
        # The impacts of an attempt that is rolled back are taken out of the log
        # again (the compiled stage never records them; this loop used to).
        logged = None if ctx.impacts is None else len(ctx.impacts._chunks)
        end = self.time + ctx.dt
        heap, count = self.heap, self.count
        taken = 0
        while heap and heap[0][0] <= end:
            when, _, kind, p, q, stamp_p, stamp_q = heapq.heappop(heap)
            if count[p] != stamp_p or (kind == PAIR and count[q] != stamp_q):
                continue
            taken += 1
            self.events += 1
            try:
                if taken > budget:
                    raise NotExactable
                if kind == PAIR:
                    self._pair_event(ctx, when, p, q)
                elif kind == WALL:
                    self._wall_event(ctx, when, p, q)
                else:
                    self._cell_event(when, p, q)
            except NotExactable:
                # Roll the step back and let the step solver take it.
                state.position[:], state.velocity[:] = saved[0], saved[1]
                ctx.stats.restore(saved[2])
                if logged is not None:
                    del ctx.impacts._chunks[logged:]
                self.events = saved[3]
                self._fallback_streak += 1
                self._hold = min(2 ** self._fallback_streak - 1, MAX_FALLBACK_HOLD)
                self._fallback_step(ctx)
                return
        self._fallback_streak = 0
        self._sync_all(end)
        self.time = end
        self._position_after = state.position.copy()
        self._velocity_after = state.velocity.copy()

    def _fallback_step(self, ctx: StepContext) -> None:
        """Advance this step with the step solver (``EVENT_FALLBACK`` preset)."""
        settings = PRESETS[EVENT_FALLBACK]
        if self._fallback is None:
            self._fallback = self._build_fallback()
        sub_dt = ctx.dt / settings.substeps
        for k in range(settings.substeps):
            self._fallback.run(StepContext(state=ctx.state, dt=sub_dt,
                                           dimensions=ctx.dimensions, effects=ctx.effects,
                                           accuracy=settings, stats=ctx.stats,
                                           time=ctx.time + k * sub_dt, impacts=ctx.impacts))
        ctx.stats.fallback_steps += 1
        self.time += ctx.dt
        self._state = None      # event mode starts afresh from the new state

    def describe(self) -> str:
        """Say what the stage does."""
        return ('exact event-driven: closed-form impact times (pairs, walls, gravity), '
                f'heap with lazy invalidation, hash grid, TC model t_c = '
                f'{self.collapse_time:g} s; a step with resting contact under gravity or '
                f'more than {self.event_budget} events per particle is solved by the '
                f'{EVENT_FALLBACK} step solver')
