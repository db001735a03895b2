"""Separation: remove the overlap left after the contact solve.

Method: pure position projection. Each overlapping pair is pushed apart
along N by its penetration, shared by inverse mass; a particle in several
contacts moves by the average of its pushes (Jacobi averaging, which
cannot overshoot). Velocities are not pushed, so no kinetic energy is
added (under gravity they may only slow, see below). Baumgarte-style
correction, which feeds the overlap back into the velocity, was rejected:
it is how an elastic gas gains energy without bound in a well-known
engine.

A particle that its push would take into a wall stays put and its
partner takes the whole push: the wall clamp would otherwise put it
back and leave the overlap, and a ball pressed against a wall by a much
heavier one (which gets only its inverse-mass share of the push) would be
overrun by it step after step.

With walls, particles pushed past a wall plane are then placed back on
it (again positions only).

Under gravity, moving a particle changes its potential energy. Pushes
between two dynamic particles are shared by inverse mass, so they leave
the total potential unchanged; a push off a static particle or a wall
lifts. The budget is local: per cluster of touching particles (the
connected components of this step's contact graph through dynamic
particles), up to the energy the contact law and the effects removed
from that cluster's own particles in this step (``StepContext.losses``),
a lift only restores what resting particles lost falling into their
supports during the drift. Beyond that it would add energy, and that
excess is taken back from the cluster's lifted particles' speed along the
way they were pushed, if they move that way: a ball reflected
elastically while overlapping a static ball, then pushed out of it, is
put where its path would have taken it with the speed it would have
there, so it keeps its apex (without this each elastic bounce there added
m g times the overlap; found by the fuzzer), also when an inelastic
impact elsewhere in the world dissipates in the same step (the budget
used to be the whole world's). What such speeds cannot pay (resting or
falling particles) is not lifted: each such particle goes back along its
push by the unpaid fraction of it, so the projection never adds energy
and the unpaid overlap stays. It used to stay added, and that let energy
rise in two ways: a lift restoring overlap an earlier step's four passes
left (a ball landing on one resting on a floor: each pass gives the
lower ball half the push into the floor, the floor takes it back, 1/16
of the overlap is left, and the next steps lifted it out with nothing to
pay: +5.2e-5 J under ``balanced``), and a ball sliding over a static one
(the drift leaves the curved surface by v_t^2 dt^2 / 2R, so per substep
the lift m g_n dt^2 (g_n - v_t^2/R) / 2 exceeds the loss of the stopped
approach speed dt (g_n - v_t^2/R) by m dt^2 (g_n - v_t^2/R) v_t^2/R / 2).
Everything is booked as 'separation' (a net addition as a negative loss),
from each particle's final displacement, -m g . dx, so the energy balance
closes, also far from the origin.

Two backends do exactly this. ``kernel`` (the default) runs the passes,
wall clamps and the per-cluster budget (clusters by union-find) in
compiled loops (``contact_kernels.project_overlaps`` and ``pay_for_lift``),
with the same floating-point operations in the same order as ``numpy``,
the vectorised statement kept below as the reference;
``test/test_separation_kernels.py`` asserts identical positions, velocities
and bookings.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .separation_kernels import pay_for_lift, project_overlaps
from ...model.effects import Walls
from ...model.energy import lift
from ...step.pipeline import Contacts, Stage, StepContext
from ..detection.narrowphase import line_of_action
from ...model.tunables import BACKENDS, GRAVITY_PASSES


def held_by_walls(position: np.ndarray, radius: np.ndarray, push: np.ndarray, walls: Walls,
                  dimensions: int) -> np.ndarray:
    """Return the mask of pushed particles that reach a wall the push points into.

    ``position`` is where the push would take them, ``push`` its direction.
    """
    p, d, r = position[:, :dimensions], push[:, :dimensions], radius[:, None]
    into_low = (p <= walls.low[:dimensions] + r) & (d < 0.0)
    into_high = (p >= walls.high[:dimensions] - r) & (d > 0.0)
    return np.any(into_low | into_high, axis=1)


def clusters(n: int, dynamic: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Return a cluster label per particle: the components of the contact graph.

    Only contacts between two dynamic particles connect; a static particle
    (or a wall) does not join the particles resting on it into one cluster.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    both = dynamic[i] & dynamic[j]
    graph = coo_matrix((np.ones(int(both.sum())), (i[both], j[both])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def separate(position: np.ndarray, inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray,
             normal: np.ndarray, penetration: np.ndarray, radius: Optional[np.ndarray] = None,
             walls: Optional[Walls] = None, dimensions: int = 3) -> None:
    """Push overlapping pairs apart in place along their normals.

    With ``walls`` (and ``radius``), a particle held by a wall does not
    move and its partner, if it can move, takes the whole push.
    """
    w_i, w_j = inv_mass[i], inv_mass[j]
    if walls is not None:
        share = (penetration / (w_i + w_j))[:, None] * normal
        held_i = held_by_walls(position[i] + w_i[:, None] * share, radius[i], normal, walls,
                               dimensions)
        held_j = held_by_walls(position[j] - w_j[:, None] * share, radius[j], -normal, walls,
                               dimensions)
        w_i, w_j = (np.where(held_i & ~held_j & (w_j > 0.0), 0.0, w_i),
                    np.where(held_j & ~held_i & (w_i > 0.0), 0.0, w_j))
    w_sum = w_i + w_j
    push_i = (penetration * w_i / w_sum)[:, None] * normal
    push_j = -(penetration * w_j / w_sum)[:, None] * normal
    n = position.shape[0]
    moves = np.bincount(i, weights=(w_i > 0), minlength=n) + \
        np.bincount(j, weights=(w_j > 0), minlength=n)
    total = np.zeros_like(position)
    np.add.at(total, i, push_i)
    np.add.at(total, j, push_j)
    moved = moves > 0
    position[moved] += total[moved] / moves[moved, None]


class SeparationStage(Stage):
    """Project overlapping pairs apart (velocities only pay for a lift under gravity)."""

    name = 'separation'

    def __init__(self, walls: Optional[Walls] = None, backend: str = 'kernel') -> None:
        """Keep the wall planes to project particles back inside (None: no walls)."""
        if backend not in BACKENDS:
            raise ValueError(f'backend must be one of {BACKENDS}, got {backend!r}')
        self.walls = walls
        self.backend = backend

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
        self._project(ctx, has_pairs)
        s = ctx.state
        added = lift(s.inv_mass, s.position - start, gravity)   # delta U per particle
        budget = ctx.losses if ctx.losses is not None else np.zeros(len(s))
        if self.backend == 'kernel':
            i, j = (c.i, c.j) if has_pairs else (np.zeros(0, np.int64), np.zeros(0, np.int64))
            velocity = np.ascontiguousarray(s.velocity, dtype=float)
            position = np.ascontiguousarray(s.position, dtype=float)
            paid = pay_for_lift(position, start, velocity,
                                np.ascontiguousarray(s.inv_mass, dtype=float),
                                np.ascontiguousarray(s.dynamic, dtype=np.bool_),
                                np.ascontiguousarray(i, dtype=np.int64),
                                np.ascontiguousarray(j, dtype=np.int64),
                                np.ascontiguousarray(added, dtype=float),
                                np.ascontiguousarray(budget, dtype=float))
            if velocity is not s.velocity:
                s.velocity[...] = velocity
            if position is not s.position:
                s.position[...] = position
        else:
            cluster = clusters(len(s), s.dynamic, c.i, c.j) if has_pairs else \
                np.arange(len(s))
            paid = self._pay_for_lift(s, start, added, cluster, budget)
        # The lift actually made: particles the budget and their speed could not
        # pay for went back part of their way.
        added = lift(s.inv_mass, s.position - start, gravity)
        ctx.book('separation', paid - added, np.arange(len(s)))

    @staticmethod
    def _pay_for_lift(state, start: np.ndarray, added: np.ndarray, cluster: np.ndarray,
                      budget: np.ndarray) -> np.ndarray:
        """Take back what the projection's net lift adds to each cluster's energy.

        ``added`` is the potential energy the projection gave each particle,
        ``cluster`` its cluster label and ``budget`` the energy removed from
        it in this step, J. Per cluster, the lift gives back, first, that
        energy: a resting particle fell into its support during the drift,
        the solve stopped it, the lift restores its height. Only a lift
        beyond that adds energy, and a lifted particle pays it from its
        velocity along the way it was moved, if it is moving that way (one
        reflected while overlapping a static particle or a wall: it is put
        where its path would have taken it, with the speed it would have
        there). Returns the kinetic energy removed per particle, J (see the
        module docstring).
        """
        count = int(cluster.max()) + 1 if cluster.size else 0
        excess = np.bincount(cluster, weights=added, minlength=count) - \
            np.maximum(np.bincount(cluster, weights=budget, minlength=count), 0.0)
        removed = np.zeros(added.size)
        up = (added > 0.0) & (excess[cluster] > 0.0)
        if not up.any():
            return removed
        index = np.flatnonzero(up)
        raised = np.bincount(cluster[index], weights=added[index], minlength=count)
        owed = excess[cluster[index]] * added[index] / raised[cluster[index]]
        mass = 1.0 / state.inv_mass[index]
        moved = state.position[index] - start[index]
        way = moved / np.linalg.norm(moved, axis=1)[:, None]
        # One still moving against its push (a falling particle in a stack the
        # next solve stops anyway) does not pay: taking its fall speed made a
        # compressed column creep back up, adding energy.
        along = np.maximum(np.einsum('ij,ij->i', state.velocity[index], way), 0.0)
        taken = np.minimum(owed, 0.5 * mass * along * along)
        slower = np.sqrt(np.maximum(along * along - 2.0 * taken / mass, 0.0))
        state.velocity[index] += (slower - along)[:, None] * way
        removed[index] = taken
        # What the speed cannot pay is not lifted: the particle goes back along
        # its push by that fraction of it, so the lift adds no energy (a lift
        # that "stayed added" restored overlap an earlier step left, or fed a
        # ball sliding over a static one; see the module docstring).
        unpaid = owed - taken
        back = unpaid > 0.0
        state.position[index[back]] -= (unpaid[back] / added[index[back]])[:, None] * \
            moved[back]
        return removed

    def _project(self, ctx: StepContext, has_pairs: bool) -> None:
        """Separate overlapping pairs, then clamp particles inside the walls.

        Under gravity a resting pile sinks a little into itself every step
        and one averaged pass only removes part of it, so the pass is
        repeated (``GRAVITY_PASSES``) on the step's contact pairs with their
        overlap measured again.
        """
        s, c = ctx.state, ctx.contacts
        passes = 1 if ctx.effects.gravity is None else GRAVITY_PASSES
        # One pass: a particle its push would take into a wall is held there (see the
        # module docstring). The repeated passes under gravity already hand the rest of
        # the push to the partner after each clamp (and holding there made a settling
        # pile jitter above its rest bound, test_effects).
        held_by = self.walls if passes == 1 else None
        if self.backend == 'kernel':
            self._project_kernel(ctx, has_pairs, passes, held_by is not None)
            return
        for k in range(passes):
            if has_pairs:
                if k == 0:
                    normal, penetration = c.normal, c.penetration
                    i, j = c.i, c.j
                else:
                    normal, distance = line_of_action(s.position[c.i] - s.position[c.j],
                                                      s.velocity[c.i] - s.velocity[c.j])
                    penetration = s.radius[c.i] + s.radius[c.j] - distance
                    overlapping = penetration > 0.0
                    if not overlapping.any() and self.walls is None:
                        return
                    i, j = c.i[overlapping], c.j[overlapping]
                    normal, penetration = normal[overlapping], penetration[overlapping]
                separate(s.position, s.inv_mass, i, j, normal, penetration, s.radius,
                         held_by, ctx.dimensions)
            self._clamp_inside_walls(ctx)

    def _project_kernel(self, ctx: StepContext, has_pairs: bool, passes: int,
                        hold: bool) -> None:
        """Run ``_project`` in one compiled call (``contact_kernels.project_overlaps``)."""
        s, c = ctx.state, ctx.contacts
        if not has_pairs:
            c = Contacts.empty()
        dims = ctx.dimensions
        walls = self.walls
        planes = walls.planes(dims) if walls is not None else []
        low = np.full(3, -np.inf) if walls is None else np.asarray(walls.low, dtype=float)
        high = np.full(3, np.inf) if walls is None else np.asarray(walls.high, dtype=float)
        position = np.ascontiguousarray(s.position, dtype=float)
        project_overlaps(position, np.ascontiguousarray(s.velocity, dtype=float),
                         np.ascontiguousarray(s.inv_mass, dtype=float),
                         np.ascontiguousarray(s.radius, dtype=float),
                         np.ascontiguousarray(s.dynamic, dtype=np.bool_),
                         np.ascontiguousarray(c.i, dtype=np.int64),
                         np.ascontiguousarray(c.j, dtype=np.int64),
                         np.ascontiguousarray(c.normal, dtype=float),
                         np.ascontiguousarray(c.penetration, dtype=float), passes, hold,
                         walls is not None, low, high, dims,
                         np.array([p[0] for p in planes], dtype=np.int64),
                         np.array([p[1] for p in planes], dtype=float),
                         np.array([p[2] for p in planes], dtype=float))
        if position is not s.position:
            s.position[...] = position

    def _clamp_inside_walls(self, ctx: StepContext) -> None:
        """Place particles found past a wall plane back on it."""
        if self.walls is None:
            return
        s = ctx.state
        dyn = s.dynamic
        for axis, plane, inward in self.walls.planes(ctx.dimensions):
            p = s.position[:, axis]
            inside = dyn & (inward * (p - plane) < s.radius)
            p[inside] = plane + inward * s.radius[inside]

    def describe(self) -> str:
        """Say what the stage does."""
        text = ('position projection along N shared by inverse mass (velocities untouched; '
                f'under gravity {GRAVITY_PASSES} passes, and a lift beyond the step\'s losses '
                'is paid from the lifted particles\' speed, or not made)')
        if self.walls is not None:
            text += ', then back onto wall planes'
        return text
