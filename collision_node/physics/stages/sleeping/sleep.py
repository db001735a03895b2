"""Sleeping islands: a settled pile costs little while it rests.

An island is a connected component of the contact graph: particles of
finite mass linked by pairs whose gap is at most ``CONTACT_MARGIN`` of the
radii sum plus the travel both can make in a step. Walls and static
particles carry islands but do not link them (two piles on one floor sleep
apart). A particle is still while its speed and its spin times radius stay
below the sleep speed 2 |g| dt (the default restitution threshold: below
it a contact is resting contact); its timer counts the seconds it has been
still. An island falls asleep as a whole when every member has been still
for ``sleep_time`` (the accuracy setting): velocities and spins are set to
zero (the kinetic energy removed is booked as ``sleep``) and the members
are recorded as asleep (``state.asleep``, ``state.island``).

Two stages frame the pipeline. ``wake`` runs first: every awake particle
within waking reach of a sleeping one (the radii sum plus the margin plus
its travel this step, |v| dt + |g| dt^2 / 2) wakes that particle's whole
island (keeping its timers, so the island sleeps again once the newcomer
is still as well); a dropped ball therefore hits an awake pile. Sleeping
particles then become static for the step (inverse mass 0; velocity and
spin already 0), so motion, gravity, drag, the ccd stage, the solve and
separation leave them alone and treat them as immovable supports. If no
particle is awake the other stages are skipped altogether: nothing could
move. ``sleep`` runs last: it restores the real inverse masses (energy,
messages and commands always see the real mass), advances the timers and
decides the islands in one compiled call (``sleep_kernels``). An island
touched during the step by a particle that is not yet still wakes there.

Commands wake: a teleport or an impulse wakes the particle's island, a
delete the islands of the deleted particles and of sleeping particles
touching them (timers reset to 0); a spawned particle is awake and wakes
what it lands on at the next step (``wake_islands``, used by the world).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ...model import energy
from ...model.effects import GRAVITY_THRESHOLD_STEPS
from .sleep_kernels import (IslandParticles, Islands, near_sleepers, settle_islands,
                            sleepers_within_reach, Stillness, WakeReach)
from ...model.state import ParticleState, rows_named
from ...step.pipeline import Pipeline, Stage, StepContext
from ...model.tunables import CONTACT_MARGIN, DIRECT_PAIRS

_NO_PAIRS = np.zeros(0, dtype=np.int64)
_NO_SPIN = np.zeros((0, 3))


def _rows(a: np.ndarray) -> bool:
    """Say whether ``a`` is a C-contiguous float64 (n, 3) array (what the kernels take)."""
    return a.dtype == np.float64 and a.ndim == 2 and a.shape[1] == 3 and a.flags.c_contiguous


def sleep_speed(gravity: np.ndarray, dt: float) -> float:
    """Return the speed (m/s) below which a particle is still: 2 |g| dt."""
    return GRAVITY_THRESHOLD_STEPS * float(np.linalg.norm(gravity)) * dt


def ensure_sleep_arrays(state: ParticleState) -> None:
    """Give ``state`` its sleeping arrays (everyone awake, timers 0) if it has none."""
    n = len(state)
    if state.asleep is None:
        state.asleep = np.zeros(n, dtype=bool)
    if state.still_time is None:
        state.still_time = np.zeros(n)
    if state.island is None:
        state.island = np.full(n, -1, dtype=np.int64)


def wake_islands(state: ParticleState, rows: np.ndarray, reset: bool) -> int:
    """Wake, in place, the islands of the sleeping particles ``rows``; return how many woke.

    ``reset`` also sets the woken particles' and ``rows``' timers to 0 (a
    command disturbs them: the island then rests ``sleep_time`` again
    before sleeping).
    """
    if state.asleep is None:
        return 0
    rows = np.asarray(rows, dtype=np.int64)
    if reset:
        state.still_time[rows] = 0.0
    labels = state.island[rows[state.asleep[rows]]]
    if not labels.size:
        return 0
    woken = state.asleep & np.isin(state.island, labels)
    state.asleep[woken] = False
    state.island[woken] = -1
    if reset:
        state.still_time[woken] = 0.0
    return int(np.count_nonzero(woken))


class _Shared:
    """What the two stages of one pipeline share during a step."""

    def __init__(self) -> None:
        """Start with nothing swapped."""
        # The state's real inverse masses while sleepers are static, else None.
        self.real_inv_mass: Optional[np.ndarray] = None
        # Whether an awake particle of finite mass exists this step.
        self.anyone_awake = True


class WakeStage(Stage):
    """First stage: wake islands within reach of awake particles; make sleepers static."""

    name = 'wake'

    def __init__(self, shared: _Shared, gravity: np.ndarray) -> None:
        """Keep g (for the travel bound) and the state shared with the sleep stage."""
        self.shared = shared
        self.sag = 0.5 * float(np.linalg.norm(gravity))
        self._tree: Optional[cKDTree] = None
        self._tree_ids = np.zeros(0, dtype=np.int64)

    def run(self, ctx: StepContext) -> None:
        """Wake what awake particles reach this step, then hide the sleepers' mass."""
        s = ctx.state
        ensure_sleep_arrays(s)
        self.shared.real_inv_mass = None
        if not s.asleep.any():
            self.shared.anyone_awake = bool((s.inv_mass > 0.0).any())
            return
        awake = np.flatnonzero((s.inv_mass > 0.0) & ~s.asleep)
        self.shared.anyone_awake = bool(awake.size)
        if awake.size:
            self._wake_near(ctx, awake)
        if s.asleep.any():
            self.shared.real_inv_mass = s.inv_mass
            s.inv_mass = np.where(s.asleep, 0.0, s.inv_mass)

    def _wake_near(self, ctx: StepContext, awake: np.ndarray) -> None:
        """Wake the islands of sleeping particles within waking reach of ``awake``."""
        s = ctx.state
        sleepers = np.flatnonzero(s.asleep)
        dt = ctx.dt
        sag = self.sag * dt * dt
        wake_reach = WakeReach(CONTACT_MARGIN, float(dt), float(sag))
        if awake.size * sleepers.size <= DIRECT_PAIRS and _rows(s.position) \
                and _rows(s.velocity):
            # Few particles: test every pair in one compiled loop (the same
            # test as below, without the tree's query and its Python lists).
            near = sleepers_within_reach(s.position, s.velocity, s.radius, awake, sleepers,
                                         wake_reach)
            if near.any():
                wake_islands(s, sleepers[near], reset=False)
            return
        ids = s.ids[sleepers]
        if self._tree is None or not np.array_equal(ids, self._tree_ids):
            # Sleeping particles do not move: the tree lasts while the set does.
            self._tree = cKDTree(s.position[sleepers])
            self._tree_ids = ids
        speed = np.sqrt(np.einsum('ij,ij->i', s.velocity[awake], s.velocity[awake]))
        reach = ((1.0 + CONTACT_MARGIN) * (s.radius[awake] + float(s.radius[sleepers].max()))
                 + speed * dt + sag) * (1.0 + 1e-9)
        hits = self._tree.query_ball_point(s.position[awake], reach)
        counts = np.fromiter(map(len, hits), dtype=np.int64, count=len(hits))
        if not counts.sum():
            return
        candidate_awake = np.repeat(np.arange(awake.size), counts)
        candidate_sleeper = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits if h])
        near = near_sleepers(s.position, s.velocity, s.radius, awake, sleepers, candidate_awake,
                             candidate_sleeper, wake_reach)
        if near.any():
            wake_islands(s, sleepers[candidate_sleeper[near]], reset=False)

    def describe(self) -> str:
        """Say what the stage does."""
        return ('islands of sleeping particles within reach of an awake one (radii + '
                f'{CONTACT_MARGIN:g} of them + |v| dt + |g| dt^2/2) wake; sleepers are static '
                'for the step; with nobody awake the stages up to sleep are skipped')


class SleepStage(Stage):
    """Last stage: restore masses, advance stillness timers, let still islands sleep."""

    name = 'sleep'

    def __init__(self, shared: _Shared, gravity: np.ndarray, sleep_time: float) -> None:
        """Keep g (sleep speed and travel), the sleep time and the shared state."""
        self.shared = shared
        self.gravity = np.asarray(gravity, dtype=float)
        self.sleep_time = float(sleep_time)
        self._dt: Optional[float] = None
        self._wake_reach = WakeReach(CONTACT_MARGIN, 0.0, 0.0)
        self._stillness = Stillness(0.0, self.sleep_time)

    def run(self, ctx: StepContext) -> None:
        """Decide which islands sleep after this step."""
        s = ctx.state
        if self.shared.real_inv_mass is not None:
            s.inv_mass = self.shared.real_inv_mass
            self.shared.real_inv_mass = None
        if not self.shared.anyone_awake:
            return
        n = len(s)
        dt = ctx.dt
        if dt != self._dt:
            # The sleep speed and the sag, computed once per dt.
            self._dt = dt
            sag = 0.5 * float(np.linalg.norm(self.gravity)) * dt * dt
            self._wake_reach = WakeReach(CONTACT_MARGIN, float(dt), float(sag))
            self._stillness = Stillness(float(sleep_speed(self.gravity, dt)), self.sleep_time)
        rep = np.full(n, -1, dtype=np.int64)
        sleeping = np.flatnonzero(s.asleep)
        if sleeping.size:
            # A representative always exists (a delete wakes its island); if
            # not, the particle stands for itself.
            rows = rows_named(s.ids, s.island[sleeping])
            rep[sleeping] = np.where(rows >= 0, rows, sleeping)
        pair_i = ctx.pair_i if ctx.pair_i is not None else _NO_PAIRS
        pair_j = ctx.pair_j if ctx.pair_j is not None else _NO_PAIRS
        angular = s.angular_velocity if s.angular_velocity is not None else _NO_SPIN
        particles = IslandParticles(s.position, s.velocity, angular, s.radius,
                                    s.inv_mass > 0.0)
        fell = settle_islands(particles, Islands(s.asleep, rep, s.still_time),
                              np.ascontiguousarray(pair_i, dtype=np.int64),
                              np.ascontiguousarray(pair_j, dtype=np.int64), self._wake_reach,
                              self._stillness)
        s.island = np.where(s.asleep, s.ids[np.maximum(rep, 0)], -1)
        rows = np.flatnonzero(fell)
        if rows.size:
            removed = energy.kinetic_linear(s, rows) + energy.kinetic_rotational(s, rows)
            ctx.stats.add_dissipated('sleep', removed)
            s.velocity[rows] = 0.0
            if s.angular_velocity is not None:
                s.angular_velocity[rows] = 0.0

    def describe(self) -> str:
        """Say what the stage does."""
        return (f'islands (contacts within {CONTACT_MARGIN:g} of the radii sum, walls and '
                'static particles do not link) whose every particle stayed below 2 |g| dt '
                f'(speed and spin x radius) for {self.sleep_time:g} s fall asleep (v = 0, '
                'booked as sleep)')


class SleepingPipeline(Pipeline):
    """A pipeline framed by ``wake`` and ``sleep``: skips its middle when nobody is awake.

    ``stages`` and ``names`` stay those of the step without sleeping (the
    effects' stages, compared across presets); ``explain`` lists the two
    sleep stages around them.
    """

    def __init__(self, stages: list[Stage], gravity: np.ndarray, sleep_time: float,
                 note: str = '') -> None:
        """Frame ``stages`` (the step without sleeping) with the two sleep stages."""
        super().__init__(stages, note=note)
        self.shared = _Shared()
        self.wake = WakeStage(self.shared, gravity)
        self.sleep = SleepStage(self.shared, gravity, sleep_time)
        self.frame(self.wake, self.sleep)

    def run(self, ctx: StepContext) -> None:
        """Run every stage, or only the two sleep stages when every particle sleeps."""
        self.run_stage(self.wake, ctx)
        if self.shared.anyone_awake:
            super().run(ctx)
        self.run_stage(self.sleep, ctx)

    def rows_moved(self, order: np.ndarray) -> None:
        """Rename the real inverse masses kept while sleepers are static, then tell every stage."""
        if self.shared.real_inv_mass is not None:
            self.shared.real_inv_mass = self.shared.real_inv_mass[order]
        self.wake.rows_moved(order)
        self.sleep.rows_moved(order)
        super().rows_moved(order)

    def explain(self) -> str:
        """Return the numbered stages, with ``wake`` before and ``sleep`` after them.

        The two framing stages are on lines of their own, not numbered: the
        numbered list stays the effects' stages, the same in every preset.
        """
        lines = [f'{k + 1}. {stage.name}: {stage.describe()}'
                 for k, stage in enumerate(self.stages)]
        lines.insert(0, f'before 1, {self.wake.name}: {self.wake.describe()}')
        lines.append(f'after {len(self.stages)}, {self.sleep.name}: {self.sleep.describe()}')
        if self.note:
            lines.append(f'note: {self.note}')
        return '\n'.join(lines)


def asleep_count(state: ParticleState) -> int:
    """Return how many particles sleep (0 when the state has never slept)."""
    return 0 if state.asleep is None else int(np.count_nonzero(state.asleep))


def sleepers_touching(state: ParticleState, rows: np.ndarray) -> np.ndarray:
    """Return the sleeping particles in contact with particles ``rows`` (within the margin)."""
    rows = np.asarray(rows, dtype=np.int64)
    if state.asleep is None or not rows.size or not state.asleep.any():
        return np.zeros(0, dtype=np.int64)
    sleepers = np.flatnonzero(state.asleep)
    reach = ((1.0 + CONTACT_MARGIN) * (state.radius[rows] + float(state.radius[sleepers].max()))
             * (1.0 + 1e-9))
    hits = cKDTree(state.position[sleepers]).query_ball_point(state.position[rows], reach)
    counts = np.fromiter(map(len, hits), dtype=np.int64, count=len(hits))
    if not counts.sum():
        return np.zeros(0, dtype=np.int64)
    a = np.repeat(rows, counts)
    b = sleepers[np.concatenate([np.asarray(h, dtype=np.int64) for h in hits if h])]
    gap = state.position[a] - state.position[b]
    near = np.einsum('ij,ij->i', gap, gap) <= \
        ((1.0 + CONTACT_MARGIN) * (state.radius[a] + state.radius[b])) ** 2
    return np.unique(b[near])
