"""Exact event-driven mode (``mode: event``, preset ``exact``).

Between impacts every particle moves on a closed-form path,
x(t) = x0 + v0 t + g t^2 / 2, so the world jumps from impact to impact
instead of stepping: impact times and post-impact states are exact to
round-off, and the velocity update is the one contact law's (impulse along
the line of action, the combine rule, e = 0 below the restitution
threshold, walls, losses from the impulses, impacts recorded at their time).

The loop (grid, heap, predictions, impacts) runs compiled, one call per step
(``event_kernels``); this stage owns its records between steps, in the order
of the particles' cells (neighbours near in memory), and the rules around
the loop: when to rebuild, when to fall back, what to book and record. At
the end of each step every particle is brought to the step's end and
written to the world's state, a snapshot as in step mode.

Inelastic collapse (infinitely many impacts in finite time when e < 1)
without gravity is stopped with the TC model: an impact within
``collapse_time`` of either particle's previous impact is elastic.

Resting contact under gravity cannot be stepped through event by event.
So each step under gravity first finds the resting contacts, zeroes their
normal speeds (booking the energy) and solves their support forces
(``resting_kernels``); a supported particle moves for the step with its own
constant acceleration and its resting contacts are not predicted. Static
particles (mass inf) get acceleration 0 the same way. A step the loop
cannot do exactly (an impact that would change a support's normal speed, a
collapsing bounce under gravity, more events than ``event_budget`` per
particle) is rolled back and solved by the ``EVENT_FALLBACK`` step solver,
counted in ``fallback_steps``; after k fallbacks in a row the next 2^k - 1
steps (at most ``MAX_FALLBACK_HOLD``) go straight to the step solver.

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
_NO_IMPACTS = ek.new_impact_buffer(0)
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
        self._entries: dict = {}        # compiled entry points (``_compiled``)
        # Resting contact (under gravity): this step's supports in the world's
        # order (None: nobody is supported), whether the last step had any, and
        # the last step's partners and forces (world indices; the next solve's
        # warm start). Steps with supports.
        self._supports: Optional[rk.Supports] = None
        self._varied_last = False
        self._old_partner = np.full((0, rk.PARTNERS), -1, dtype=np.int64)
        self._old_force = np.zeros((0, rk.PARTNERS))
        self.supported_steps = 0

    # -- bookkeeping -------------------------------------------------------

    def _rebuild(self, state: ParticleState, dimensions: int, end: float) -> None:
        """Set up the records for ``state`` at ``self.time`` (the step ends at ``end``)."""
        n = len(state)
        self._state = state
        self.dims = dimensions
        self.cell_size = self._choose_cell_size(state, dimensions) if n else 1.0
        cell = np.zeros((n, 3), dtype=np.int64)
        cell[:, :dimensions] = np.floor(state.position[:, :dimensions] / self.cell_size)
        # The stage's own copy of the particles, in cell order so that
        # neighbours are near in memory (the loop is bound by memory, not by
        # arithmetic): stage particle k is the world's order[k]. The loop moves
        # it lazily and publishes to the world's arrays only at a step's end,
        # so a step handed to the fallback leaves the world's state untouched.
        self.order = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0])).astype(np.int64)
        own = state.restitution
        self.particles = ek.Particles(
            state.position[self.order], state.velocity[self.order], state.inv_mass[self.order],
            state.radius[self.order],
            np.full(n, np.nan) if own is None else np.asarray(own, float)[self.order])
        self.schedule = ek.new_schedule(n, self.time)
        self.candidates, self.heap = ek.new_candidates(n), ek.new_heap(n)
        cell = np.ascontiguousarray(cell[self.order])
        self.grid = ek.new_grid(cell, self._table_shape(cell, dimensions))
        self.tally = np.zeros(1, dtype=ek.TALLY)
        self.supports = self._stage_supports(n)
        self.settings = ek.Settings(
            end=float(end), budget=self._budget(n), own_restitution=own is not None,
            record=False, book_losses=False, dimensions=int(dimensions),
            cell_size=float(self.cell_size), collapse_time=float(self.collapse_time),
            threshold=float(self.threshold), pair_restitution=float(self.restitution),
            wall_restitution=1.0 if self.walls is None else float(self.walls.restitution),
            gravity=self.gravity, half_gravity=self.half_g, low_walls=self.low_walls,
            high_walls=self.high_walls, under_gravity=self.under_gravity,
            has_walls=self.walls is not None, own_acceleration=self._supports is not None)
        records = (self.settings, self.particles, self.supports, self.grid, self.schedule,
                   self.candidates, self.heap, self.tally)
        self._compiled(ek.build_events, records, state)(*records)

    def _budget(self, n: int) -> int:
        """Return the events a step of ``n`` particles may take."""
        return int(max(MIN_EVENT_BUDGET, self.event_budget * n))

    def _stage_supports(self, n: int) -> rk.Supports:
        """Return this step's supports in the stage's order (no rows: nobody supported)."""
        if self._supports is None:
            return rk.new_supports(0)
        found = self._supports
        inverse = np.empty(n, dtype=np.int64)
        inverse[self.order] = np.arange(n)
        partners = found.partners[self.order]
        # Partners are particles (world index, >= 0) or walls (< -1); -1 ends a list.
        partners[partners >= 0] = inverse[partners[partners >= 0]]
        return rk.Supports(np.ascontiguousarray(found.acceleration[self.order]),
                           found.supported[self.order], found.wall_mask[self.order], partners)

    def _find_supports(self, ctx: StepContext) -> bool:
        """Find the resting contacts and supports of this step (``resting_kernels``).

        Sets their normal speeds to zero in the world's state, books the
        energy that takes to their contacts and keeps each particle's
        acceleration and supports for the step in ``self._supports`` (None
        when nobody is supported and no particle is static: then every
        particle falls with g). Returns False when a particle rests on more
        than ``PARTNERS`` others (the step falls back).
        """
        state = ctx.state
        n, dims = len(state), ctx.dimensions
        self._supports = None
        position, velocity = state.position, state.velocity
        inv_mass, radius = state.inv_mass, state.radius
        scale = float(np.max(np.abs(position))) if n else 0.0
        reach = radius * (1.0 + 4.0 * rk.RESTING_GAP) + 2.0 * rk.RESTING_ULPS * np.spacing(scale)
        pair_first, pair_second = candidate_pairs(position, reach)
        contacts = rk.new_contacts(pair_first.size + 2 * dims * n)
        rest_speed = ctx.effects.threshold(ctx.dt)
        m = rk.collect(position, velocity, inv_mass, radius, pair_first, pair_second,
                       self.low_walls, self.high_walls, dims, rest_speed, contacts)
        # A static particle does not fall: its own acceleration is 0.
        any_static = bool(np.any(inv_mass == 0.0))
        if m == 0:
            self._old_partner = np.full((0, rk.PARTNERS), -1, dtype=np.int64)
            if any_static:
                found = rk.new_supports(n)
                found.acceleration[inv_mass > 0.0] = self.gravity
                self._supports = found
            return True
        info = np.zeros(1, dtype=rk.SWEEPS)
        removed = np.empty(m)
        rk.project_velocities(velocity, inv_mass, contacts, m, VELOCITY_TOLERANCE * rest_speed,
                              removed, info)
        first, second = contacts.first[:m], contacts.second[:m]
        pairs = second >= 0
        if np.any(removed[pairs] != 0.0):
            ctx.book('restitution', removed[pairs], first[pairs], second[pairs])
        if np.any(removed[~pairs] != 0.0):
            ctx.book('walls', removed[~pairs], first[~pairs])
        force = np.empty(m)
        rk.warm_forces(contacts, m, self._old_partner, self._old_force, force)
        found = rk.new_supports(n)
        rk.support_forces(found.acceleration, inv_mass, self.gravity, contacts, m, force,
                          ACCELERATION_TOLERANCE * float(np.linalg.norm(self.gravity)), info)
        partner_force = np.zeros((n, rk.PARTNERS))
        status = rk.supports(inv_mass, self.gravity, contacts, m, force, found, partner_force)
        self._old_partner, self._old_force = found.partners, partner_force
        self.resting_info = info[0]
        if status != rk.FOUND:
            return False
        if found.supported.any() or any_static:
            self._supports = found
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

    def _table_shape(self, cell: np.ndarray, dimensions: int) -> np.ndarray:
        """Slots per axis: the cells the particles (and a box) span, plus one each side."""
        n = cell.shape[0]
        table = np.ones(3, dtype=np.int64)
        if n:
            low = cell.min(axis=0)[:dimensions].astype(float)
            high = cell.max(axis=0)[:dimensions].astype(float)
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
        return (state is self._state and len(state) == len(self.schedule)
                and state.position.shape == self.particles.position.shape
                and ek.matches(state.position, state.velocity, state.inv_mass, state.radius,
                               self.particles.position, self.particles.velocity,
                               self.particles.inv_mass, self.particles.radius, self.order))

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
        n = len(state)
        record = ctx.impacts is not None
        own = state.restitution         # read each step, as the law reads it at each impact
        if own is not None:
            self.particles = self.particles._replace(
                restitution=np.asarray(own, float)[self.order])
        # The step's five settings, then the ones of the last rebuild.
        settings = ek.Settings(float(end), self._budget(n), own is not None, record,
                               ctx.losses is not None, *self.settings[5:])
        tally = self.tally
        dissipated = ctx.stats.dissipated
        ek.start_tally(tally, dissipated.get('restitution', 0.0), dissipated.get('walls', 0.0))
        losses = np.zeros(n) if ctx.losses is not None else _NO_LOSSES
        world = ek.WorldArrays(self.order, state.position, state.velocity, losses)
        impacts = ek.new_impact_buffer(64) if record else _NO_IMPACTS
        records = (settings, self.particles, self.supports, self.grid, self.schedule,
                   self.candidates, self.heap, tally)
        run_events = self._compiled(ek.run_events, records + (impacts, world), state)
        while True:
            outcome = run_events(*records, impacts, world)
            if outcome.status != ek.GROW:
                break
            impacts = ek.grown(impacts)     # the buffer is full: the loop goes on
        if outcome.status != ek.DONE:
            # The world's state is untouched: let the step solver take the step.
            self._fall_back(ctx)
            return
        self._fallback_streak = 0
        self.events += outcome.events
        self.impacts += outcome.collisions + outcome.wall_collisions
        self.crossings += outcome.crossings
        self.refreshes += outcome.refreshes
        ctx.stats.collisions += outcome.collisions
        ctx.stats.wall_collisions += outcome.wall_collisions
        # The totals were summed impact after impact, as bookings one by one would.
        if outcome.booked_pairs:
            dissipated['restitution'] = outcome.restitution_dissipated
        if outcome.booked_walls:
            dissipated['walls'] = outcome.walls_dissipated
        if ctx.losses is not None:
            ctx.losses += losses
        k = outcome.recorded
        if record and k:
            ctx.impacts.record(impacts.time[:k], impacts.first[:k], impacts.second[:k],
                               impacts.point[:k], impacts.normal[:k], impacts.impulse[:k], 0.0,
                               impacts.approach[:k])
        self.time = end

    def _compiled(self, kernel: Callable, args: tuple, state: ParticleState) -> Callable:
        """Return ``kernel``'s compiled entry point for ``args`` (``event_kernels.entry_point``).

        Every array the stage hands a kernel is its own, of fixed types,
        except the world's (``state``'s) and the copies of them: an entry
        point is kept per kernel and type of the world's arrays.
        """
        position, velocity, inv_mass, radius = (state.position, state.velocity,
                                                state.inv_mass, state.radius)
        key = (kernel, position.dtype, position.ndim, position.flags.num, velocity.dtype,
               velocity.ndim, velocity.flags.num, inv_mass.dtype, radius.dtype)
        entry = self._entries.get(key)
        if entry is None:
            entry = self._entries[key] = ek.entry_point(kernel, args)
        return entry

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
                                           time=ctx.time + k * sub_dt, impacts=ctx.impacts,
                                           threads=ctx.threads))
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
