"""A world: a scene's particles advanced step by step through its pipeline.

The state is passed into each step's stages; a world owns nothing else
than the state, the clock, the counters and the pipeline built from its
scene, so the node, the runner and the benchmarks drive it alike.
"""

from __future__ import annotations

from time import perf_counter
from typing import Optional

import numpy as np

from ..model import energy
from ..model.world_commands import check_inside_walls, check_no_overlap, rows_of
from ..model.effects import check_particles_for_effects
from ..model.impacts import ImpactLog
from ..model.particles import MAX_SPEED
from .plan import build_pipeline
from ..stages.detection.broadphase import check_pair_budget, StepTooLarge, swept_allowance
from ..stages.sleeping.sleep import asleep_count, sleepers_touching, wake_islands
from .pipeline import StepContext, StepStats
from .memory import keep_freed_memory
from .step_kernels import all_finite, all_finite_shared, float_rows
from . import threads as thread_count
from .timing import StepProfile, build_profile
from ..model.scene import Scene, parse_spawn
from ..model.state import ParticleState
from ..model.validation import SceneError, fail


_NO_SPIN = np.zeros((0, 3))


class NonFiniteStateError(FloatingPointError):
    """A step produced NaN or inf; the world refuses to go on silently."""


class World:
    """Particles of one scene, stepped with a fixed dt."""

    def __init__(self, scene: Scene, max_particles: Optional[int] = None,
                 threads: Optional[int] = None) -> None:
        """Build the pipeline and load the scene's initial state.

        ``threads``: how many threads the compiled kernels share a step's
        loops among (``step/threads.py``; None or 0: every core). The
        state after any number of steps is the same for every count.
        """
        self.scene = scene
        self.max_particles = max_particles
        self.threads = thread_count.resolve(threads)
        keep_freed_memory()
        # Impacts are recorded only while asked for (record_impacts).
        self.impact_log: Optional[ImpactLog] = None
        if max_particles is not None and len(scene.initial) > max_particles:
            raise SceneError(f'{scene.source}: {len(scene.initial)} particles exceed '
                             f'max_particles = {max_particles}')
        self.reset()

    def reset(self) -> None:
        """Return to the scene's initial state at time 0; drop spawned particles."""
        self.state = self._with_spin_state(self.scene.initial.copy())
        self.steps = 0
        self.stats = StepStats()
        self.pipeline = build_pipeline(self.scene.effects, self.scene.accuracy)
        # The profile's clock: wall seconds of the steps timed since reset,
        # their count, and (wall, stage totals) after the first of them.
        self.step_seconds = 0.0
        self.timed_steps = 0
        self._first_step: Optional[tuple[float, dict[str, float]]] = None
        self._check_pairs(self.state, self.scene.source)
        # Potential energy is measured from the grid point nearest the scene's
        # initial centre of mass (the origin for a scene near it; see
        # ``energy``), so it keeps its digits however far from the origin.
        self.reference = energy.reference_point(self.state)
        self.energy_start = self._mechanical(self.state)
        self.energy_spawned = 0.0
        # Energy changed by commands (delete, teleport, impulse), so the balance holds.
        self.energy_commanded = 0.0
        # Ids are stable: the scene's are 0..n-1, a spawn takes ids after the
        # largest ever given, a delete leaves a gap. Rows are in id order
        # unless the world is large enough to keep them in spatial order
        # (``stages/ordering``): ``rows`` finds an id's row either way.
        self.next_id = int(self.state.ids.max()) + 1 if len(self.state) else 0

    def _with_spin_state(self, state: ParticleState) -> ParticleState:
        """Give every particle spin and orientation iff the scene simulates spin."""
        if not self.scene.effects.spin:
            return state.with_arrays(angular_velocity=None, orientation=None)
        n = len(state)
        arrays = {}
        if state.angular_velocity is None:
            arrays['angular_velocity'] = np.zeros((n, 3))
        if state.orientation is None:
            arrays['orientation'] = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        return state.with_arrays(**arrays) if arrays else state

    def _check_pairs(self, state: ParticleState, source: str,
                     added: Optional[int] = None) -> None:
        """Refuse a state whose step's candidate pairs would not fit the memory budget.

        ``added``: the state's last ``added`` particles are a spawn's (the
        rest was checked before).
        """
        accuracy = self.scene.accuracy
        dt = self.scene.dt / accuracy.substeps
        extra = swept_allowance(state.velocity, state.dynamic, dt, self.scene.effects.gravity) \
            if accuracy.ccd else None
        try:
            check_pair_budget(state.position, state.radius, state.velocity, state.inv_mass, dt,
                              extra, added)
        except StepTooLarge as error:
            raise StepTooLarge(f'{source}: {error}') from None

    @property
    def dt(self) -> float:
        """Seconds per step."""
        return self.scene.dt

    @property
    def time(self) -> float:
        """Simulated time in seconds (steps times dt, so it never drifts)."""
        return self.steps * self.scene.dt

    def step(self, count: int = 1) -> None:
        """Advance ``count`` steps of dt, each split into the preset's substeps."""
        scene = self.scene
        substeps = scene.accuracy.substeps
        sub_dt = scene.dt / substeps
        run = self.pipeline.run
        thread_count.use(self.threads)
        for _ in range(count):
            begin = perf_counter()
            start = self.time
            if self.impact_log is not None:
                self.impact_log.name_rows(self.state.ids)
            for k in range(substeps):
                run(StepContext(self.state, sub_dt, scene.dimensions, scene.effects,
                                scene.accuracy, self.stats, time=start + k * sub_dt,
                                impacts=self.impact_log, threads=self.threads))
            self.steps += 1
            self._check_finite()
            self.step_seconds += perf_counter() - begin
            self.timed_steps += 1
            if self._first_step is None:
                self._first_step = (self.step_seconds, dict(self.pipeline.seconds))

    def profile(self) -> StepProfile:
        """Return the wall time per stage of the steps since reset (see ``timing``).

        The first step, which loads the compiled code, is reported apart;
        ms per step and shares are over the steps after it.
        """
        return build_profile(self.pipeline.seconds, self.step_seconds, self.timed_steps,
                             self._first_step)

    def record_impacts(self, enabled: bool) -> None:
        """Start (keeping nothing from before) or stop recording the impacts resolved."""
        self.impact_log = ImpactLog() if enabled else None

    def take_impacts(self) -> np.ndarray:
        """Return the impacts resolved since the last take (``impacts.IMPACT_DTYPE``)."""
        if self.impact_log is None:
            raise RuntimeError('impacts are not being recorded: call record_impacts(True)')
        return self.impact_log.take()

    def _check_finite(self) -> None:
        """Raise instead of letting NaN or inf spread through the state."""
        s = self.state
        spin = _NO_SPIN if s.angular_velocity is None else s.angular_velocity
        if float_rows(s.position) and float_rows(s.velocity) and float_rows(spin):
            # One compiled pass instead of three isfinite arrays and reductions.
            check = (all_finite_shared if thread_count.parallel(self.threads, len(s))
                     else all_finite)
            finite = check(s.position, s.velocity, spin)
        else:
            finite = bool(np.isfinite(s.position).all() and np.isfinite(s.velocity).all()
                          and np.isfinite(spin).all())
        if not finite:
            raise NonFiniteStateError(f'step {self.steps}: a position or velocity became '
                                      'non-finite')

    def spawn(self, particles: ParticleState, *, allow_overlap: bool = True,
              allow_outside: bool = True, source: str = 'spawn') -> np.ndarray:
        """Append validated particles atomically and return their new ids.

        With ``allow_outside=False`` a particle not inside the walls is
        refused, with ``allow_overlap=False`` one overlapping an existing
        particle or another new one (the node's requests ask for both
        checks; the API default keeps the checks off).
        """
        if self.max_particles is not None and \
                len(self.state) + len(particles) > self.max_particles:
            raise SceneError(f'{source}: {len(particles)} particles would make '
                             f'{len(self.state) + len(particles)}, over max_particles = '
                             f'{self.max_particles}')
        check_particles_for_effects(particles, self.scene.effects, f'{source}: ')
        where = f'{source}: particle {{}} of the request'
        if not allow_outside:
            check_inside_walls(particles.position, particles.radius, self.scene.effects.walls,
                               self.scene.dimensions, where)
        if not allow_overlap:
            check_no_overlap(self.state.position, self.state.radius, self.state.ids,
                             particles.position, particles.radius, where)
        first = self.next_id
        ids = np.arange(first, first + len(particles), dtype=np.int64)
        added = self._with_spin_state(particles.with_arrays(ids=ids))
        combined = self.state.concatenate(added)
        self._check_pairs(combined, source, len(added))
        if not self.state.dynamic.any():
            # No dynamic particle yet, so every potential so far is 0 whatever
            # the reference: take the newcomers' point, as a scene's start does.
            self.reference = energy.reference_point(added)
        self.state = combined
        self.next_id = first + len(particles)
        self.energy_spawned += self._mechanical(added)
        return ids

    def spawn_text(self, text: str, source: str = 'spawn') -> np.ndarray:
        """Validate a spawn request (YAML or JSON) and append it atomically."""
        return self.spawn(parse_spawn(text, self.scene.dimensions, len(self.state), source,
                                      self.max_particles), source=source)

    def rows(self, ids: np.ndarray, source: str = 'ids') -> np.ndarray:
        """Return the rows of particles ``ids``; raise naming an id that does not exist."""
        return rows_of(self.state.ids, np.asarray(ids, dtype=np.int64), source)

    def delete(self, ids: np.ndarray, source: str = 'delete') -> np.ndarray:
        """Remove particles ``ids`` atomically; the others keep their ids. Return the ids."""
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        rows = self.rows(ids, f'{source}: ids')
        keep = np.ones(len(self.state), dtype=bool)
        keep[rows] = False
        # What rested on a deleted particle must fall: its island, and the
        # islands of sleeping particles touching it, wake.
        touching = sleepers_touching(self.state, rows)
        self.state = self.state.with_arrays(**self._woken(np.concatenate([rows, touching])))
        removed = self.state.subset(rows)
        self.energy_commanded -= self._mechanical(removed)
        self.state = self.state.subset(keep)
        return ids

    def teleport(self, pid: int, position: Optional[np.ndarray] = None,
                 velocity: Optional[np.ndarray] = None, *, allow_overlap: bool = False,
                 source: str = 'teleport') -> None:
        """Set particle ``pid``'s position and/or velocity atomically.

        The new position must be inside the walls and (unless
        ``allow_overlap``) clear of every other particle; a static particle
        may be moved but not given a velocity.
        """
        row = int(self.rows(np.array([pid]), f'{source}: id')[0])
        s = self.state
        if velocity is not None and s.inv_mass[row] == 0.0 and np.any(velocity != 0.0):
            fail(f'{source}: velocity', f'particle {pid} is static (mass .inf) and cannot move')
        if position is not None:
            where = f'{source}: position'
            check_inside_walls(position[None, :], s.radius[row:row + 1],
                               self.scene.effects.walls, self.scene.dimensions, where)
            if not allow_overlap:
                others = np.arange(len(s)) != row
                check_no_overlap(s.position[others], s.radius[others], s.ids[others],
                                 position[None, :], s.radius[row:row + 1], where)
        self._replace_row(row, position, velocity)

    def apply_impulse(self, pid: int, impulse: np.ndarray, source: str = 'impulse') -> None:
        """Add ``impulse`` (N s) to particle ``pid``'s momentum: v += J / m."""
        row = int(self.rows(np.array([pid]), f'{source}: id')[0])
        inv_mass = self.state.inv_mass[row]
        if inv_mass == 0.0:
            fail(f'{source}: id', f'particle {pid} is static (mass .inf): an impulse cannot '
                                  'move it')
        velocity = self.state.velocity[row] + np.asarray(impulse, dtype=float) * inv_mass
        speed = float(np.linalg.norm(velocity))
        if not speed <= MAX_SPEED:
            fail(f'{source}: impulse', f'would give particle {pid} a speed of {speed:g} m/s, '
                                       f'over the supported {MAX_SPEED:g}')
        self._replace_row(row, None, velocity)

    def _replace_row(self, row: int, position: Optional[np.ndarray],
                     velocity: Optional[np.ndarray]) -> None:
        """Give one particle a new position/velocity in a new state, booking the energy."""
        before = self._mechanical(self.state.subset([row]))
        arrays = {}
        if position is not None:
            arrays['position'] = self.state.position.copy()
            arrays['position'][row] = position
        if velocity is not None:
            arrays['velocity'] = self.state.velocity.copy()
            arrays['velocity'][row] = velocity
        # A command wakes the particle's island (if it sleeps) and restarts
        # its stillness timer.
        arrays.update(self._woken(np.array([row])))
        # A new state object (not an in-place edit), so stages that cache the
        # last step's state (event mode) start afresh.
        self.state = self.state.with_arrays(**arrays)
        self.energy_commanded += self._mechanical(self.state.subset([row])) - before

    def _woken(self, rows: np.ndarray) -> dict:
        """Return new sleeping arrays in which the islands of ``rows`` are awake (timers 0)."""
        s = self.state
        if s.asleep is None:
            return {}
        arrays = {'asleep': s.asleep.copy(), 'still_time': s.still_time.copy(),
                  'island': s.island.copy()}
        wake_islands(s.with_arrays(**arrays), rows, reset=True)
        return arrays

    @property
    def asleep_count(self) -> int:
        """Particles sleeping now (see ``stages/sleeping/sleep.py``)."""
        return asleep_count(self.state)

    def explain(self) -> str:
        """Return the step pipeline, one numbered stage per line."""
        return self.pipeline.explain()

    def _mechanical(self, state: ParticleState) -> float:
        """Kinetic plus potential energy of ``state`` (potential from the reference), J."""
        return energy.mechanical(state, self.scene.effects.gravity, reference=self.reference)

    def kinetic_energy(self) -> float:
        """Total kinetic energy in joules."""
        return energy.kinetic_linear(self.state) + energy.kinetic_rotational(self.state)

    def energy(self) -> dict:
        """Return the energy balance, J, as a JSON-ready mapping.

        ``kinetic_linear``, ``kinetic_rotational``, ``potential`` (gravity,
        zero at the reference point: the origin, or for a scene far from it
        the 1024 m grid point nearest its initial centre of mass) and
        their ``total`` now; ``start`` (at reset)
        plus ``spawned`` (brought in by spawns) plus ``commanded`` (changed by
        delete, teleport and impulse commands); ``dissipated``, the energy
        each effect removed (a negative entry added energy, e.g.
        'separation' lifting particles under gravity); and
        ``balance_error`` = total + sum(dissipated) - start - spawned - commanded, which
        is zero up to rounding.
        """
        report = energy.breakdown(self.state, self.scene.effects.gravity, self.reference)
        dissipated = dict(self.stats.dissipated)
        report.update(start=self.energy_start, spawned=self.energy_spawned,
                      commanded=self.energy_commanded, dissipated=dissipated,
                      balance_error=report['total'] + sum(dissipated.values())
                      - self.energy_start - self.energy_spawned - self.energy_commanded)
        return report

    def momentum(self) -> np.ndarray:
        """Total linear momentum in kg m/s."""
        return self.state.momentum()
