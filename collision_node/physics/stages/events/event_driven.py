"""Exact event-driven mode (``mode: event``, preset ``exact``).

Between impacts every particle moves on a closed-form path,
x(t) = x0 + v0 t + g t^2 / 2, so the world can jump from impact to impact
instead of stepping:

- two particles share the same g, so their relative motion is a straight
  line and their impact time is the smaller root of |d + u s| = r1 + r2
  (the same quadratic as ``swept_contacts.pair_impact_times``);
- a wall is reached when a quadratic in s (the gap to the wall) falls
  to zero; the root is taken in its cancellation-free form.

Impact times and post-impact states are therefore exact to round-off; the
velocity update is the one contact law's (``contact_law``): the lecture's
impulse along the line of action at contact, per-particle restitution by
the combine rule, e = 0 below the restitution threshold, the wall as a
side of w = 0, losses from the impulses, impacts recorded at their time.

Bookkeeping: the stage keeps its own copy of the particles, in the order
of their cells (neighbours near in memory), each at its own reference
time. Each particle holds its next wall event, its next cell crossing and
a short list of predicted pair impacts, each stamped with the partner's
change counter (a partner that changed since is dropped when it comes up:
lazy invalidation); a heap of the particles orders them by their earliest
event. Neighbours come from a hash grid of cells at least one contact
diameter wide (``PARTICLES_PER_CELL`` on average); crossing a cell is
itself an event. An impact re-predicts its one or two particles against
the particles of the 3^d neighbouring cells; a crossing changes no path
and predicts the particle against the newly entered layer of 3^(d-1)
cells only. At the end of each step every particle is brought to the
step's end time and written to the world's state, so that state is a
snapshot like in step mode; a step handed to the fallback leaves it
untouched. The loop itself (grid, heap, predictions, impacts) runs
compiled, one call per step (``collision_node.physics.stages.events.event_kernels``);
this stage owns its arrays between steps and the rules around it
(rebuild, fallback, bookings, the impact log). ``events`` counts what the
loop took: impacts, cell crossings and wall visits without an impact;
``impacts`` and ``crossings`` count the first two.

Inelastic collapse (infinitely many impacts in finite time when e < 1)
without gravity is stopped with the TC model: an impact within
``collapse_time`` (t_c) of either particle's previous impact is elastic.

Resting contact under gravity: a particle resting on a wall or on others
would meet them again at once with zero speed, again and again (the TC
model would make it hop every t_c, hundreds of events a step, adding
energy). So at the start of every step under gravity the stage finds the
resting contacts (touching, normal speed below the restitution threshold:
the declared one, or 2 |g| dt), sets their normal speeds to zero (the
energy this takes is booked to their contacts) and solves their
frictionless support forces (``resting_kernels``). A particle they hold
(a supported one) moves for the step with its own constant acceleration
(g plus its support forces over its mass: 0 in a column or a packed pile
at rest) and its resting contacts are not predicted; a pair whose
accelerations differ meets at the first root of a quartic
(``event_kernels.curved_delay``). Supports are held for the step: exact
for a cluster at rest, first order in dt for one that slides. An impact
that would change a support's normal speed (a ball dropped on a resting
pile, say) is what this cannot do exactly, and so is an event in the
collapse regime that the TC model would alter under gravity (e < 1, or a
particle pushed into a wall with about no speed) and a step that needs
more events than its budget (``event_budget`` per particle, at least
``MIN_EVENT_BUDGET``: a dense cluster, say). Such a step is rolled back
(state and counters; the resting contacts' zeroed speeds stay, with their
bookings) and solved by the ``accurate`` step solver instead, counted in
``fallback_steps``; after k fallbacks in a row the next 2^k - 1 steps (at
most ``MAX_FALLBACK_HOLD``) go straight to the step solver before event
mode is tried again. A particle struck sideways while it rests on walls
only (a ball rolling on a floor) keeps its supports: that impact is exact.

Static particles (mass .inf) under gravity do not fall: every step under
gravity with one gives each particle its own acceleration (0 for a static
one), so a falling particle meets a static one at a quartic's root, and a
particle resting on a static one is supported like one on a wall.

Scenes with an effect other than particles, walls, restitution and gravity
are refused (:func:`collision_node.physics.model.accuracy.check_event_mode`).
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from . import event_kernels as ek
from . import resting_kernels as rk
from ...model.accuracy import (AccuracySettings, check_event_mode, EVENT_FALLBACK,
                               MIN_EVENT_BUDGET, PRESETS)
from ...model.effects import Effects
from ...step.pipeline import Pipeline, Stage, StepContext
from ..detection.broadphase import candidate_pairs
from ...model.state import ParticleState
from ...model.tunables import (ACCELERATION_TOLERANCE, MAX_FALLBACK_HOLD, PARTICLES_PER_CELL,
                               SLOTS_PER_PARTICLE, VELOCITY_TOLERANCE)


# What the loop is handed when it records no impacts and books no losses
# (never written: not worth fresh arrays every step).
_NO_RECORDS = (np.empty((0, ek.RECORD_COLUMNS)), np.empty((0, 2), dtype=np.int64))
_NO_LOSSES = np.zeros(0)


class EventDrivenStage(Stage):
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
        self.half_g = 0.5 * self.gravity
        if self.walls is not None:
            self.low_walls = np.asarray(self.walls.low, float)
            self.high_walls = np.asarray(self.walls.high, float)
        else:
            self.low_walls, self.high_walls = np.full(3, -np.inf), np.full(3, np.inf)
        self.under_gravity = bool(np.any(self.gravity != 0.0))
        self.particles_per_cell = float(particles_per_cell)
        # A declared restitution threshold is part of the contact law. The
        # default one under gravity (2 |g| dt) is the step solvers' device for
        # resting contact, which this mode hands to them: exact impacts keep e.
        self.threshold = effects.restitution_threshold or 0.0
        self.time = 0.0
        # Events taken (impacts, wall visits, cell crossings), and of them the
        # particle and wall impacts and the crossings (``bench exact``).
        # Refreshes: a full candidate list made a particle predict again.
        self.events = self.impacts = self.crossings = self.refreshes = 0
        self._state: Optional[ParticleState] = None
        self._fallback: Optional[Pipeline] = None
        self._build_fallback = fallback
        self._fallback_streak = 0
        self._hold = 0
        # Resting contact (under gravity): this step's accelerations and
        # supports in the world's order (None: nobody is supported), whether
        # the last step had any, and the last step's partners and forces
        # (world indices; the next solve's warm start). Steps with supports.
        self._supports: Optional[tuple] = None
        self._varied_last = False
        self._old_partner = np.full((0, rk.PARTNERS), -1, dtype=np.int64)
        self._old_force = np.zeros((0, rk.PARTNERS))
        self.supported_steps = 0

    # -- bookkeeping -------------------------------------------------------

    def _rebuild(self, state: ParticleState, dimensions: int, end: float) -> None:
        """Set up clocks, grid and predictions for ``state`` at ``self.time`` (step to ``end``)."""
        n = len(state)
        self._state = state
        self.dims = dimensions
        self.cell_size = self._choose_cell_size(state, dimensions) if n else 1.0
        # Columns: the cell's coordinates, then its slot's in the table.
        cell = np.zeros((n, 6), dtype=np.int64)
        cell[:, :dimensions] = np.floor(state.position[:, :dimensions] / self.cell_size)
        # The stage's own copy of the particles, in cell order so that
        # neighbours are near in memory (the loop is bound by memory, not by
        # arithmetic): stage particle k is the world's perm[k]. The loop moves
        # it lazily and publishes to the world's arrays only at a step's end,
        # so a step handed to the fallback leaves the world's state untouched.
        self.perm = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0])).astype(np.int64)
        self.cell = cell[self.perm]
        self.position = state.position[self.perm]
        self.velocity = state.velocity[self.perm]
        self.inv_mass = state.inv_mass[self.perm]
        self.radius = state.radius[self.perm]
        (self.clock, self.book, self.cand_time, self.cand_int, self.heap_key,
         self.heap_int) = ek.new_arrays(n)
        self.clock[:, ek.C_REF] = self.time
        self.table = self._table_shape(n, dimensions)
        self.cell[:, 3:] = self.cell[:, :3] % self.table
        slots = int(np.prod(self.table))
        self.head = np.full(slots, -1, dtype=np.int64)
        self.occupancy = np.zeros(slots, dtype=np.int64)
        self.next = np.full(n, -1, dtype=np.int64)
        self.previous = np.full(n, -1, dtype=np.int64)
        self.meta = np.zeros(ek.META_SIZE, dtype=np.int64)
        self.low, self.high = self.low_walls, self.high_walls
        own = state.restitution
        self.own_e = np.full(n, np.nan) if own is None else np.asarray(own, float)[self.perm]
        self.params = np.array([self.collapse_time, self.threshold, self.restitution,
                                1.0 if self.walls is None else self.walls.restitution,
                                self.cell_size, end])
        self.flags = np.array([dimensions, self.under_gravity, self.walls is not None,
                               own is not None, 0, 0, self._supports is not None],
                              dtype=np.int64)
        self.accel, self.rest = self._stage_supports(n)
        ek.build_events(self.time, self.position, self.velocity, self.inv_mass, self.radius,
                        self.gravity, self.accel, self.rest, self.low, self.high, self.params,
                        self.flags, self.cell, self.table, self.head, self.next, self.previous,
                        self.occupancy, self.clock, self.book, self.cand_time, self.cand_int,
                        self.heap_key, self.heap_int, self.meta)

    def _stage_supports(self, n: int) -> tuple:
        """Return this step's (accel, rest) in the stage's order (no rows: nobody supported)."""
        if self._supports is None:
            return ek.new_supports(0, rk.PARTNERS)
        accel, rest = self._supports
        inverse = np.empty(n, dtype=np.int64)
        inverse[self.perm] = np.arange(n)
        rest = rest[self.perm]
        partners = rest[:, ek.S_PARTNERS:]
        # Partners are particles (world index, >= 0) or walls (< -1); -1 ends a list.
        partners[partners >= 0] = inverse[partners[partners >= 0]]
        return np.ascontiguousarray(accel[self.perm]), rest

    def _find_supports(self, ctx: StepContext) -> bool:
        """Find the resting contacts and supports of this step (``resting_kernels``).

        Sets their normal speeds to zero in the world's state, books the
        energy that takes to their contacts and keeps each particle's
        acceleration and supports for the step in ``self._supports`` (None
        when nobody is supported and no particle is static: then every
        particle falls with g). Returns False when a particle rests on more
        than ``resting_kernels.PARTNERS`` others (the step falls back).
        """
        state = ctx.state
        n, dims = len(state), ctx.dimensions
        self._supports = None
        position, velocity = state.position, state.velocity
        inv_mass, radius = state.inv_mass, state.radius
        scale = float(np.max(np.abs(position))) if n else 0.0
        reach = radius * (1.0 + 4.0 * rk.RESTING_GAP) + 2.0 * rk.RESTING_ULPS * np.spacing(scale)
        cand_i, cand_j = candidate_pairs(position, reach)
        size = cand_i.size + 2 * dims * n
        c_i, c_j = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
        c_normal = np.empty((size, 3))
        rest_speed = ctx.effects.threshold(ctx.dt)
        m = rk.collect(position, velocity, inv_mass, radius, cand_i, cand_j, self.low_walls,
                       self.high_walls, dims, rest_speed, c_i, c_j, c_normal)
        # A static particle does not fall: its own acceleration is 0.
        any_static = bool(np.any(inv_mass == 0.0))
        if m == 0:
            self._old_partner = np.full((0, rk.PARTNERS), -1, dtype=np.int64)
            if any_static:
                accel, rest = ek.new_supports(n, rk.PARTNERS)
                accel[inv_mass > 0.0] = self.gravity
                self._supports = (accel, rest)
            return True
        info = np.zeros(rk.INFO_SIZE)
        removed = np.empty(m)
        rk.project_velocities(velocity, inv_mass, m, c_i, c_j, c_normal,
                              VELOCITY_TOLERANCE * rest_speed, removed, info)
        pairs = c_j[:m] >= 0
        if np.any(removed[pairs] != 0.0):
            ctx.book('restitution', removed[pairs], c_i[:m][pairs], c_j[:m][pairs])
        if np.any(removed[~pairs] != 0.0):
            ctx.book('walls', removed[~pairs], c_i[:m][~pairs])
        force = np.empty(m)
        rk.warm_forces(m, c_i, c_j, self._old_partner, self._old_force, force)
        accel = np.empty((n, 3))
        rk.support_forces(accel, inv_mass, self.gravity, m, c_i, c_j, c_normal, force,
                          ACCELERATION_TOLERANCE * float(np.linalg.norm(self.gravity)), info)
        rest = np.empty((n, ek.S_PARTNERS + rk.PARTNERS), dtype=np.int64)
        partner_force = np.zeros((n, rk.PARTNERS))
        supported, walls = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
        partner = np.empty((n, rk.PARTNERS), dtype=np.int64)
        status = rk.supports(accel, inv_mass, self.gravity, m, c_i, c_j, force, supported,
                             partner, partner_force, walls)
        self._old_partner, self._old_force = partner, partner_force
        self.resting_info = info
        if status != rk.FOUND:
            return False
        if supported.any() or any_static:
            rest[:, ek.S_SUPPORTED], rest[:, ek.S_WALLS] = supported, walls
            rest[:, ek.S_PARTNERS:] = partner
            self._supports = (accel, rest)
        return True

    def _choose_cell_size(self, state: ParticleState, dimensions: int) -> float:
        """Cells at least one contact diameter wide, ``particles_per_cell`` each."""
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

    def _table_shape(self, n: int, dimensions: int) -> np.ndarray:
        """Slots per axis: the cells the particles (and a box) span, plus one each side."""
        table = np.ones(3, dtype=np.int64)
        if n:
            low = self.cell.min(axis=0)[:dimensions].astype(float)
            high = self.cell.max(axis=0)[:dimensions].astype(float)
            if self.walls is not None:
                # A box bounds where particles go: cover it whole.
                lo = np.floor(self.walls.low[:dimensions] / self.cell_size)
                hi = np.floor(self.walls.high[:dimensions] / self.cell_size)
                low = np.where(np.isfinite(lo), np.minimum(low, lo), low)
                high = np.where(np.isfinite(hi), np.maximum(high, hi), high)
            span = np.minimum(high - low + 3.0, 2.0 ** 20)
            table[:dimensions] = np.maximum(span, 3.0).astype(np.int64)
        limit = max(4096, SLOTS_PER_PARTICLE * n)
        while int(np.prod(table)) > limit:
            axis = int(np.argmax(table))
            table[axis] = max(3, table[axis] // 2)
        return table

    def _still_valid(self, state: ParticleState) -> bool:
        """Return whether ``state`` is the one left by the last step, untouched."""
        return (state is self._state and len(state) == self.book.shape[0]
                and state.position.shape == self.position.shape
                and ek.matches(state.position, state.velocity, state.inv_mass, state.radius,
                               self.position, self.velocity, self.inv_mass, self.radius,
                               self.perm))

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
        end = self.time + ctx.dt
        if self.under_gravity and len(state):
            if not self._find_supports(ctx):
                self._fall_back(ctx)
                return
            varied = self._supports is not None
            if varied or self._varied_last:
                # Accelerations are the step's: every path is predicted afresh.
                self._state = None
            self._varied_last = varied
            self.supported_steps += varied
        if not self._still_valid(state):
            self._rebuild(state, ctx.dimensions, end)
        self.params[ek.P_END] = end
        n = len(state)
        budget = max(MIN_EVENT_BUDGET, self.event_budget * n)
        record = ctx.impacts is not None
        self.flags[ek.F_RECORD] = record
        self.flags[ek.F_LOSSES] = ctx.losses is not None
        meta = self.meta
        meta[ek.MAX_OCC + 1:] = 0       # this step's counters (the largest occupancy stays)
        dissipated = ctx.stats.dissipated
        totals = np.array([dissipated.get('restitution', 0.0), dissipated.get('walls', 0.0)])
        losses = np.zeros(n) if ctx.losses is not None else _NO_LOSSES
        own = state.restitution         # read each step, as the law reads it at each impact
        self.flags[ek.F_OWN_E] = own is not None
        if own is not None:
            self.own_e = np.asarray(own, float)[self.perm]
        if record:
            rec_f, rec_ij = np.empty((64, ek.RECORD_COLUMNS)), np.empty((64, 2), dtype=np.int64)
        else:
            rec_f, rec_ij = _NO_RECORDS
        while True:
            status = ek.run_events(
                end, budget, self.position, self.velocity, self.inv_mass, self.radius,
                self.own_e, self.gravity, self.half_g, self.accel, self.rest, self.low,
                self.high, self.params,
                self.flags, self.cell, self.table, self.head, self.next, self.previous,
                self.occupancy, self.clock, self.book, self.cand_time, self.cand_int,
                self.heap_key, self.heap_int, meta, totals, losses, rec_f, rec_ij, self.perm,
                state.position, state.velocity)
            if status != ek.GROW:
                break
            # The impact records are full: double them and let the loop go on.
            rec_f = np.concatenate([rec_f, np.empty_like(rec_f)])
            rec_ij = np.concatenate([rec_ij, np.empty_like(rec_ij)])
        if status != ek.DONE:
            # The world's state is untouched: let the step solver take the step.
            self._fall_back(ctx)
            return
        self._fallback_streak = 0
        self.events += int(meta[ek.EVENTS])
        self.impacts += int(meta[ek.COLLISIONS] + meta[ek.WALL_COLLISIONS])
        self.crossings += int(meta[ek.CROSSINGS])
        self.refreshes += int(meta[ek.REFRESHES])
        ctx.stats.collisions += int(meta[ek.COLLISIONS])
        ctx.stats.wall_collisions += int(meta[ek.WALL_COLLISIONS])
        # The totals were summed impact after impact, as bookings one by one would.
        if meta[ek.BOOKED_PAIRS]:
            dissipated['restitution'] = float(totals[0])
        if meta[ek.BOOKED_WALLS]:
            dissipated['walls'] = float(totals[1])
        if ctx.losses is not None:
            ctx.losses += losses
        if record and meta[ek.RECORDED]:
            k = int(meta[ek.RECORDED])
            rows_f, ij = rec_f[:k], rec_ij[:k]
            ctx.impacts.record(rows_f[:, ek.R_TIME], ij[:, 0], ij[:, 1],
                               rows_f[:, ek.R_POINT:ek.R_POINT + 3],
                               rows_f[:, ek.R_NORMAL:ek.R_NORMAL + 3],
                               rows_f[:, ek.R_IMPULSE], 0.0, rows_f[:, ek.R_APPROACH])
        self.time = end

    def _fall_back(self, ctx: StepContext) -> None:
        """Hand this step to the step solver and hold the next ones there a while."""
        self._fallback_streak += 1
        self._hold = min(2 ** self._fallback_streak - 1, MAX_FALLBACK_HOLD)
        self._varied_last = True        # the paths predicted are stale
        self._fallback_step(ctx)

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
                f'per-particle event lists in a heap of particles, lazy invalidation, '
                f'hash grid (a crossing predicts the new layer of cells), TC model t_c = '
                f'{self.collapse_time:g} s; resting contact under gravity held by support '
                f'forces (own accelerations, quartic pair times); a step with an impact onto '
                f'resting particles, a collapsing bounce or more than {self.event_budget} '
                f'events per particle is solved by the {EVENT_FALLBACK} step solver')
