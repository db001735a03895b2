"""Separation: remove the overlap left after the contact solve.

Method: pure position projection. Each overlapping pair is pushed apart
along N by its penetration, shared by inverse mass; a particle in several
contacts moves by the average of its pushes (Jacobi averaging, which
cannot overshoot). Velocities are not pushed, so no kinetic energy is
added. Baumgarte-style correction, which feeds the overlap back into the
velocity, is not used: it is how an elastic gas gains energy without bound.

Without gravity there is one pass, and a particle that its push would take
into a wall stays put while its partner takes the whole push (the wall
clamp would otherwise put it back and leave the overlap). Under gravity
there are up to ``separation_passes`` (an accuracy setting) Gauss-Seidel
passes instead, each from the positions as the previous pushes left them,
the pairs nearest a support (a floor a particle rests on, or a static
particle) first. Of a pair
standing within ``STACK_ALIGNMENT`` of vertical, the particle nearer a
support holds and the other takes the whole push (unless that takes it into
a wall), so a push travels up a stack in one pass. Otherwise two dynamic
particles move by m_a dx_a = -m_b dx_b, so the centre of mass of a cluster
that no wall or static particle supports never moves (no lift, no velocity
paid: its momentum is untouched). Only pairs that overlap are pushed (speculative
contacts, found before they touch, have a gap instead). After each pass,
particles past a wall plane are placed back on it.

Under gravity the projection starts from where the resting contacts held
the particles: the drift moved every particle along its free parabola,
|g| dt^2 / 2 below the straight path, but a resting contact's impulse is a
force that acted all through the step, so each particle first moves by
the part of that sag its resting impulses with other particles carried
(``StepContext.support_shift``, ``contact_kernels.support_shift``; the
walls stage puts a particle its sag took past a wall plane back on it).
A settled pile then ends each step where it began, and the passes only
take out what the solve did not prevent (a pair the sweeps did not
converge on, a spawn with ``allow_overlap``).

Under gravity, moving a particle changes its potential energy: a push that
lifts is paid for. The budget is local: per cluster of
touching particles (the components of this step's contact graph through
dynamic particles), a lift may restore up to the energy the contact law
and the effects removed from that cluster in this step
(``StepContext.losses``): a resting particle fell into its support during
the drift and the solve stopped it. A lift beyond that is paid from the
lifted particles' speed along their push, if they move that way (a ball
reflected while overlapping a static one is put where its path would have
taken it, with the speed it would have there). What the speed cannot pay
is not lifted: the particle goes back along its push by the unpaid
fraction, so the projection never adds energy. Everything is booked as
'separation' (a net addition as a negative loss), from each particle's
final displacement, -m g . dx.

Both parts run compiled (``separation_kernels``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .separation_kernels import (pay_for_lift, project_overlaps, projection_work,
                                 ProjectionWork, WallBounds)
from ...model.accuracy import AccuracySettings
from ...model.effects import Walls
from ...model.energy import lift
from ...step.pipeline import Stage, StepContext
from ...step.threads import parallel
from ...step.step_kernels import particle_arrays
from ..detection.narrowphase_kernels import ContactArrays

_NO_PAIRS = np.zeros(0, dtype=np.int64)


class SeparationStage(Stage):
    """Project overlapping pairs apart (velocities only pay for a lift under gravity)."""

    name = 'separation'

    def __init__(self, walls: Optional[Walls] = None,
                 passes: int = AccuracySettings.separation_passes) -> None:
        """Keep the wall planes (None: no walls) and the passes under gravity.

        ``passes`` is the accuracy setting ``separation_passes``.
        """
        self.walls = walls
        self.passes = passes
        self._bounds: Optional[WallBounds] = None
        self._bounds_of: tuple = (None, 0)         # the walls and dimensions they were built for
        self._work: Optional[ProjectionWork] = None  # the kernel's buffers, kept clean

    def run(self, ctx: StepContext) -> None:
        """Move positions in place."""
        c = ctx.contacts
        has_pairs = c is not None and len(c) > 0
        if not has_pairs and self.walls is None:
            return
        gravity = ctx.effects.gravity
        if gravity is None:
            self._project(ctx, has_pairs)
            return
        gravity = np.asarray(gravity, float)
        start = ctx.state.position.copy()
        self._hold_up(ctx)
        self._project(ctx, has_pairs)
        s = ctx.state
        added = lift(s.inv_mass, s.position - start, gravity)   # delta U per particle
        budget = ctx.losses if ctx.losses is not None else np.zeros(len(s))
        paid = self._pay_for_lift(ctx, has_pairs, start, added, budget)
        # The lift actually made: particles the budget and their speed could not
        # pay for went back part of their way.
        added = lift(s.inv_mass, s.position - start, gravity)
        ctx.book('separation', paid - added, np.arange(len(s)))

    @staticmethod
    def _hold_up(ctx: StepContext) -> None:
        """Move each particle by how far its resting contacts held it up (``support_shift``).

        A shift is at most |g| dt^2 / 2, less than the reach of a wall
        contact beyond its plane, so the particles near a wall stay those
        listed in ``ctx.near_walls``.
        """
        shift = ctx.support_shift
        if shift is not None and shift.shape == ctx.state.position.shape:
            ctx.state.position += shift

    def _pay_for_lift(self, ctx: StepContext, has_pairs: bool, start: np.ndarray,
                      added: np.ndarray, budget: np.ndarray) -> np.ndarray:
        """Take back what the projection's net lift adds to each cluster; return J per particle.

        ``added`` is the potential energy the projection gave each particle
        and ``budget`` the energy removed from it in this step, J (see the
        module docstring); velocities and positions change in place.
        """
        s, c = ctx.state, ctx.contacts
        first, second = (c.i, c.j) if has_pairs else (_NO_PAIRS, _NO_PAIRS)
        particles = particle_arrays(s)
        paid = pay_for_lift(particles, np.ascontiguousarray(s.dynamic, dtype=np.bool_),
                            np.ascontiguousarray(first, dtype=np.int64),
                            np.ascontiguousarray(second, dtype=np.int64),
                            start, np.ascontiguousarray(added, dtype=float),
                            np.ascontiguousarray(budget, dtype=float))
        if particles.velocity is not s.velocity:
            s.velocity[...] = particles.velocity
        if particles.position is not s.position:
            s.position[...] = particles.position
        return paid

    def _project(self, ctx: StepContext, has_pairs: bool) -> None:
        """Separate overlapping pairs, then clamp particles inside the walls.

        Under gravity a resting pile sinks a little into itself every step
        (where the walls stage put its lowest particles back on the floor),
        so up to ``passes`` Gauss-Seidel passes run on the step's
        contact pairs, their overlap measured again at each pair.
        """
        passes = 1 if ctx.effects.gravity is None else self.passes
        # One pass: a particle its push would take into a wall is held there (see the
        # module docstring). The repeated passes under gravity already hand the rest of
        # the push to the partner after each clamp (and holding there made a settling
        # pile jitter above its rest bound, test_effects).
        hold = passes == 1 and self.walls is not None
        self._project_passes(ctx, has_pairs, passes, hold)

    def _project_passes(self, ctx: StepContext, has_pairs: bool, passes: int,
                        hold: bool) -> None:
        """Run ``passes`` projection passes and wall clamps in one compiled call.

        More than one pass (under gravity): Gauss-Seidel passes (see the
        module docstring).
        """
        s, c = ctx.state, ctx.contacts
        if has_pairs:
            contacts = ContactArrays(np.ascontiguousarray(c.i, dtype=np.int64),
                                     np.ascontiguousarray(c.j, dtype=np.int64),
                                     np.ascontiguousarray(c.normal, dtype=float),
                                     np.ascontiguousarray(c.penetration, dtype=float))
        else:
            contacts = ContactArrays(_NO_PAIRS, _NO_PAIRS, np.zeros((0, 3)), np.zeros(0))
        particles = particle_arrays(s)
        bounds = self._wall_bounds(ctx.dimensions)
        gravity = ctx.effects.gravity
        g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
        norm = float(np.linalg.norm(g))
        up = (0.0, 0.0, 1.0) if norm == 0.0 else tuple(float(x) for x in -g / norm)
        near = ctx.near_walls
        try:
            project_overlaps(particles, np.ascontiguousarray(s.dynamic, dtype=np.bool_),
                             contacts, bounds, self._floors(bounds, gravity), up, passes, hold,
                             passes > 1, parallel(ctx.threads, len(s)),
                             (near is not None, _NO_PAIRS if near is None else near),
                             self._buffers(len(s)))
        except BaseException:
            self._work = None               # interrupted: the buffers may not be clean
            raise
        # The particles moved: the list of those near a wall no longer holds.
        ctx.near_walls = None
        if particles.position is not s.position:
            s.position[...] = particles.position

    def _buffers(self, n: int) -> ProjectionWork:
        """Return the projection's per-particle buffers for ``n`` particles (kept between steps).

        The kernel leaves them clean, so keeping them makes a step cost its
        contacts rather than its particle count; rows moved by the spatial
        order need nothing, as clean rows are all alike.
        """
        if self._work is None or self._work.moves.size != n:
            self._work = projection_work(n)
        return self._work

    @staticmethod
    def _floors(bounds: WallBounds, gravity: Optional[np.ndarray]) -> np.ndarray:
        """Return per wall plane whether it holds particles up (inward against gravity)."""
        if gravity is None:
            return np.zeros(bounds.plane_axis.size, dtype=np.bool_)
        g = np.asarray(gravity, dtype=float)
        return np.ascontiguousarray(bounds.plane_inward * g[bounds.plane_axis] < 0.0)

    def _wall_bounds(self, dimensions: int) -> WallBounds:
        """Return the walls as the kernels take them (built once per dimension count)."""
        walls = self.walls
        if self._bounds is None or self._bounds_of[0] is not walls \
                or self._bounds_of[1] != dimensions:
            self._bounds_of = (walls, dimensions)
            planes = walls.planes(dimensions) if walls is not None else []
            self._bounds = WallBounds(
                walls is not None,
                np.full(3, -np.inf) if walls is None else np.asarray(walls.low, dtype=float),
                np.full(3, np.inf) if walls is None else np.asarray(walls.high, dtype=float),
                int(dimensions), np.array([p[0] for p in planes], dtype=np.int64),
                np.array([p[1] for p in planes], dtype=float),
                np.array([p[2] for p in planes], dtype=float))
        return self._bounds

    def describe(self) -> str:
        """Say what the stage does."""
        text = ('position projection along N shared by inverse mass (velocities untouched; '
                'under gravity from where the resting contacts held the particles up, then '
                f'up to {self.passes} Gauss-Seidel passes from the supports up, '
                'the particle nearer a floor or static particle holding, '
                'and a lift beyond the step\'s losses '
                'is paid from the lifted particles\' speed, or not made)')
        if self.walls is not None:
            text += ', then back onto wall planes'
        return text
