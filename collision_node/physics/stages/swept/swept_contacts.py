"""Swept contacts (``ccd``): impacts found at their time of impact inside the step.

Replaces drift + broadphase + narrowphase + impulses when ``ccd`` is on.
Each particle keeps a local clock inside the step. The broadphase reaches
every particle a path can touch in the step (radius plus |v| dt, plus
|g| dt^2 / 2 under gravity); the compiled step (``swept_kernels.sweep``)
then runs rounds of impacts in time order: ``sequential`` takes the
impacts that are the earliest at both of their particles (ties by pair
order), so touching chains are walked one pair per round (the cradle's
wave); ``batched`` takes every impact at both particles' earliest time
and shares the impulses out (Jacobi). Finally every particle moves to the
end of the step.

Paths are straight, parabolas under gravity (a static particle does not
move), and drag's closed form with drag: impact times are solved on the
drag-free path from the particle's current state (drag only slows a path,
so the broadphase's allowance still bounds it), and the impulse is applied
where the drag paths reached. With ``requery`` (preset ``accurate``) a
particle an impact sends out of the ball its query covered is queried
again for the rest of its path; without it such contacts are found at the
next step, as overlaps.

Only impacts closing at least as fast as the restitution threshold
(``Effects.threshold(dt)``) are taken here; slower contacts are resting
contact (a pile, a ball come to rest on the floor), left to the step-end
stages the plan adds (walls, narrowphase, the sequential solve with
speculative contacts and friction, separation): taken here they would be Zeno's loop of
ever smaller bounces. ``test/swept_reference.py`` states the same step in
numpy rounds; the tests compare the two.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...law.primitives import BOOKED, EFFECTS as KERNEL_EFFECTS
from ...model.accuracy import ORDERINGS
from ...model.effects import Drag, Walls
from ...model.tunables import STRIKE_FACTOR, TOUCH_SLOP
from ...step.pipeline import Stage, StepContext
from ..detection.broadphase import BroadphaseStage
from .swept_kernels import (Box, Candidates, DRAG, Escapes, in_contact, LOSS_ROWS,
                            OwnCoefficients, Particles, Settings, sweep, Tally, workspace)


class SweptContactStage(Stage):
    """Move particles through the step, stopping at each impact in time order."""

    name = 'swept_contacts'

    def __init__(self, restitution: float, walls: Optional[Walls], ordering: str,
                 rounds: int, requery: bool = False, gravity: Optional[np.ndarray] = None,
                 drag: Optional[Drag] = None, friction: Optional[float] = None,
                 resting: bool = False) -> None:
        """Keep the restitution, the box, the ordering, the round budget, requery.

        ``gravity``, ``drag`` and ``friction`` are the scene's effects (None:
        not declared); the restitution threshold comes from the step's
        effects (``Effects.threshold(dt)``), since its default depends on dt.
        ``resting``: a contact solve follows that takes slower contacts.
        Friction needs each impact's own velocities, so it takes sequential
        ordering (the plan chooses it).
        """
        if ordering not in ORDERINGS:
            raise ValueError(f'swept contacts: unknown ordering {ordering!r} '
                             f'(known: {", ".join(ORDERINGS)})')
        if ordering == 'batched' and friction is not None:
            raise ValueError('swept contacts: batched ordering takes no friction '
                             '(impacts with friction are taken sequentially)')
        self.resting = resting
        self.requery = requery
        # Verlet list over k-d tree searches, widened by each particle's path.
        self._pairs = BroadphaseStage()
        self.restitution = restitution
        self.walls = walls
        self.ordering = ordering
        self.rounds = rounds
        self.gravity = None if gravity is None else np.asarray(gravity, dtype=float)
        self.drag = drag
        self.friction = friction
        self._workspace = None

    def _travel(self, ctx: StepContext) -> np.ndarray:
        """Return how far each particle can travel in the step (the broadphase's allowance)."""
        s, dt = ctx.state, ctx.dt
        v = s.velocity
        travel = np.sqrt(np.einsum('ij,ij->i', v, v)) * dt
        if self.gravity is not None:
            sag = float(np.linalg.norm(self.gravity))
            travel = travel + np.where(s.dynamic, 0.5 * sag * dt * dt, 0.0)
        return travel

    def _escapes(self, ctx: StepContext) -> Escapes:
        """Return each particle's swept ball for requery (empty arrays without requery).

        The mid-step ball (centre x + v dt / 2, radius |v| dt / 2) holds a
        straight path; under gravity a parabola's chord midpoint and
        |g| dt^2 / 4 more; drag only shortens a path.
        """
        s, dt = ctx.state, ctx.dt
        sag = 0.0 if self.gravity is None else float(np.linalg.norm(self.gravity))
        if not self.requery:
            none = np.zeros(0)
            return Escapes(np.zeros((0, 3)), none, sag, np.zeros(0, dtype=bool),
                           np.zeros((0, 3)), none)
        x, v, dynamic, n = s.position, s.velocity, s.dynamic, len(s)
        speed = np.sqrt(np.einsum('ij,ij->i', v, v))
        centre, half = x + v * (0.5 * dt), speed * (0.5 * dt)
        if self.gravity is not None:
            centre = centre + np.where(dynamic[:, None], self.gravity * (0.25 * dt * dt), 0.0)
            half = half + np.where(dynamic, 0.25 * sag * dt * dt, 0.0)
        return Escapes(np.ascontiguousarray(centre), np.ascontiguousarray(half), sag,
                       np.zeros(n, dtype=bool), np.zeros((n, 3)), np.zeros(n))

    def run(self, ctx: StepContext) -> None:
        """Advance positions to the end of the step in one compiled call; book and record."""
        s, dt = ctx.state, ctx.dt
        n = len(s)
        self._pairs.threads = ctx.threads
        # (A full search may put the rows in cell order: read them after it.)
        pair_i, pair_j = self._pairs.find(s.position, s.radius, s.velocity, s.inv_mass, dt,
                                          extra=self._travel(ctx), ctx=ctx)
        ctx.pair_i, ctx.pair_j = pair_i, pair_j
        dynamic = s.dynamic
        if dynamic.all():
            # Every pair can move (a gas): the pairs as they are, no mask to build.
            a = np.ascontiguousarray(pair_i, dtype=np.int64)
            b = np.ascontiguousarray(pair_j, dtype=np.int64)
        else:
            movable = dynamic[pair_i] | dynamic[pair_j]
            a = np.ascontiguousarray(pair_i[movable], dtype=np.int64)
            b = np.ascontiguousarray(pair_j[movable], dtype=np.int64)
        min_speed = float(ctx.effects.threshold(dt))
        d = ctx.dimensions
        resting_pair = np.zeros(0, dtype=bool)
        resting_wall = np.zeros((0, 2 * d), dtype=bool)
        has_resting = self.gravity is not None
        if has_resting:
            resting_pair, walls_touch = self._in_contact(ctx, a, b)
            resting_wall = walls_touch if walls_touch is not None else \
                np.zeros((n, 2 * d), dtype=bool)
        walls, drag = self.walls, self.drag
        spin = s.angular_velocity if s.angular_velocity is not None else np.zeros((n, 3))
        particles = Particles(s.position, s.velocity, spin, s.inv_mass, s.radius, dynamic)
        own = OwnCoefficients(
            s.restitution if s.restitution is not None else np.zeros(0),
            s.restitution is not None,
            s.friction if s.friction is not None else np.zeros(0), s.friction is not None)
        box = Box(walls is not None,
                  np.full(3, -np.inf) if walls is None else np.asarray(walls.low, dtype=float),
                  np.full(3, np.inf) if walls is None else np.asarray(walls.high, dtype=float),
                  float(1.0 if walls is None else walls.restitution))
        settings = Settings(
            float(dt), d, int(self.rounds), self.ordering == 'batched', bool(self.requery),
            float(self.restitution), self.friction is not None, float(self.friction or 0.0),
            np.zeros(3) if self.gravity is None else self.gravity, self.gravity is not None,
            min_speed, STRIKE_FACTOR * min_speed,
            float(drag.linear) if drag is not None else 0.0,
            float(drag.quadratic) if drag is not None else 0.0, drag is not None,
            ctx.impacts is not None, ctx.threads)
        tally = Tally(np.zeros((LOSS_ROWS, n)), np.zeros(LOSS_ROWS), np.zeros(4, dtype=np.int64))
        if ctx.losses is not None:
            # Booked on top of the step's losses so far, in the order the impacts happen.
            tally.loss[BOOKED] = ctx.losses
        self._workspace = workspace(n, a.size, self._workspace)
        result = sweep(particles, own, box, settings,
                       Candidates(a, b, resting_pair, resting_wall, has_resting),
                       self._escapes(ctx), tally, *self._workspace)
        self._book(ctx, tally, bool(dynamic.any()))
        if ctx.impacts is not None and len(result.index):
            records, index = result
            ctx.impacts.record(ctx.time + records[:, 0], index[:, 0], index[:, 1],
                               records[:, 1:4], records[:, 4:7], records[:, 7], records[:, 8],
                               records[:, 9])

    def _book(self, ctx: StepContext, tally: Tally, any_dynamic: bool) -> None:
        """Book the step's energy and counts as the stage's effects book them."""
        counts = tally.counts
        # Drag whenever a particle moved; restitution when a pair was resolved;
        # walls and friction when one hit.
        if self.drag is not None and any_dynamic:
            ctx.stats.add_dissipated('drag', float(tally.totals[DRAG]))
        booked = (counts[3] > 0, counts[1] > 0,
                  self.friction is not None and counts[0] + counts[1] > 0)
        for row, effect in enumerate(KERNEL_EFFECTS):
            if booked[row]:
                ctx.stats.add_dissipated(effect, float(tally.totals[row]))
        if ctx.losses is not None:
            ctx.losses[:] = tally.loss[BOOKED]
        ctx.stats.collisions += int(counts[0])
        ctx.stats.wall_collisions += int(counts[1])

    def _in_contact(self, ctx: StepContext, a: np.ndarray, b: np.ndarray
                    ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Return (pairs, particle-wall columns) touching at the step start.

        Under gravity these are resting contact (a pile, a stack, a ball on
        the floor): the step-end solve takes them with its threshold and
        shock passes, since taken here a resting column kept the closing
        speeds its last solve left as a wave that never settled. Once an
        impact here changes one of their particles, they are taken here in
        time order (held, the changed particle would run through its
        supports). As in the solver, such a contact keeps its e only if an
        impact of at least STRIKE_FACTOR thresholds struck one of its
        particles (the sequential impact model's shock through a resting
        column); otherwise it is resting contact, e = 0.
        """
        s = ctx.state
        d = ctx.dimensions
        pairs = np.empty(a.size, dtype=bool)
        walls = np.empty((len(s), 2 * d), dtype=bool)
        has_walls = self.walls is not None
        low = np.asarray(self.walls.low, dtype=float) if has_walls else np.zeros(3)
        high = np.asarray(self.walls.high, dtype=float) if has_walls else np.zeros(3)
        in_contact(s.position, s.radius, np.ascontiguousarray(a, dtype=np.int64),
                   np.ascontiguousarray(b, dtype=np.int64), TOUCH_SLOP, has_walls, low, high,
                   d, pairs, walls)
        return pairs, walls if has_walls else None

    def rows_moved(self, order: np.ndarray) -> None:
        """Drop the pair list, which names rows."""
        self._pairs.rows_moved(order)

    @property
    def pair_search(self) -> BroadphaseStage:
        """Return the stage's own pair list (a Verlet list widened by each path)."""
        return self._pairs

    @property
    def searches(self) -> int:
        """Return the full pair searches of this stage's pair list so far (for benchmarks)."""
        return self._pairs.searches

    def describe(self) -> str:
        """Say what the stage does."""
        reach = 'r + |v| dt' if self.gravity is None else 'r + |v| dt + |g| dt^2/2'
        paths = 'straight paths'
        if self.gravity is not None:
            paths = 'parabolas under g (straight between falling particles)'
        text = (f'swept broadphase (Verlet list, reach {reach}), {paths}, impacts at their '
                f'time of impact, {self.ordering} in time order, e = {self.restitution:g}, '
                f'up to {self.rounds} rounds{", requery escaped paths" if self.requery else ""}')
        if self.friction is not None:
            text += f', Coulomb friction mu = {self.friction:g} at each impact'
        if self.resting:
            text += ', impacts slower than the restitution threshold left to the contact solve'
        if self.drag is not None:
            text += (f'; drag k1 = {self.drag.linear:g}, k2 = {self.drag.quadratic:g} moves '
                     'particles between impacts in closed form, impact times are solved on '
                     'the drag-free path (drag only shortens it: the allowance bounds it)')
        return text + ', then to the step end'
