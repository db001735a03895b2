"""Separation: remove the overlap left after the contact solve.

Method: a converging position projection (non-linear Gauss-Seidel, as
position-based solvers do). Each pass visits every wall contact (a
dynamic particle past a wall plane is placed back on it: the wall is a
contact of infinite mass) and then every near pair one at a time, each
measured again from the current positions when it is visited, and pushes
an overlapping pair apart along N by ``RELAXATION`` times its
penetration, shared by inverse mass. Passes repeat until a whole pass
finds no penetration above ``TOLERANCE`` times the smaller radius (plus a
few float spacings at the coordinates, so far from the origin it still
stops) or ``MAX_PASSES`` ran. Near pairs are the step's candidate pairs
(the broadphase's, or the contacts' when no broadphase ran) within a
quarter of their radii sum; when a particle has moved a quarter of its
radius during the projection the list is built again, so overlaps the
projection creates are picked up. Under gravity pairs are visited from
the lowest to the highest, so one pass carries a push from the floor up a
column. This replaced a Jacobi projection (pushes averaged per particle
over the pairs found once per step, walls as a clamp after each pass),
which in a jammed pile against a wall did not converge: more passes left
more overlap (``docs/performance.md``, "Converging projection").

Velocities are not pushed, so no kinetic energy is added and nothing is
fed back into them (under gravity they may only slow, see below).
Baumgarte-style correction, which feeds the overlap back into the
velocity, was rejected: it is how an elastic gas gains energy without
bound in a well-known engine. Without gravity a position correction
changes no energy at all.

A particle that its push would take into a wall it touches stays put and
its partner takes the whole push: else a ball pressed against a wall by a
much heavier one (which gets only its inverse-mass share of each push)
would be pushed into the wall and back pass after pass, converging only
at the mass ratio per pass.

Under gravity, moving a particle changes its potential energy. Pushes
between two dynamic particles are shared by inverse mass, so they leave
the total potential unchanged; a push off a static particle or a wall
lifts. The budget is local: per cluster of touching particles (the
connected components of this step's contact graph, with the pairs the
projection touched, through dynamic particles), up to the energy the
contact law and the effects removed from that cluster's own particles in
this step (``StepContext.losses``), a lift only restores what resting
particles lost falling into their supports during the drift. Beyond that
it would add energy, and that excess is taken back from the cluster's
lifted particles' speed along the way they were pushed, if they move that
way: a ball reflected elastically while overlapping a static ball, then
pushed out of it, is put where its path would have taken it with the
speed it would have there, so it keeps its apex (without this each
elastic bounce there added m g times the overlap; found by the fuzzer),
also when an inelastic impact elsewhere in the world dissipates in the
same step. What such speeds cannot pay (resting or falling particles) is
stated, not hidden: everything is booked as 'separation' (a net addition
as a negative loss), from each particle's displacement, -m g . dx, so the
energy balance closes, also far from the origin.

Two backends do exactly this. ``kernel`` (the default) runs the
projection (``projection_kernels.project_contacts``) and the per-cluster
budget (``contact_kernels.pay_for_lift``, clusters by union-find) in
compiled loops; ``numpy`` runs ``project_reference``, the same projection
stated in plain Python (a Gauss-Seidel sweep is sequential: it has no
vectorised form) with the same floating-point operations in the same
order, and the vectorised budget. ``test/test_separation_kernels.py``
asserts identical positions, velocities and bookings.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from ..contact_kernels import pay_for_lift
from ..effects import Walls
from ..energy import lift
from ..projection_kernels import EPSILON, NEAR_FRACTION, SPACINGS, project_contacts
from ..step import Stage, StepContext

# Each visit pushes a pair apart by this fraction of its penetration (1: fully;
# below 1 converges more slowly, above 1 overshoots into gaps that cost lift).
RELAXATION = 1.0
# A pass that leaves no penetration above this fraction of the smaller radius
# (plus a few float spacings at the coordinates) ends the projection.
TOLERANCE = 1e-3
# At most this many passes per step (the shipped pile needs a handful once settled).
MAX_PASSES = 64
SHOCK_AFTER = 100000
# 'kernel' (compiled: projection_kernels.project_contacts and contact_kernels.pay_for_lift)
# and 'numpy' (project_reference and the vectorised budget); test/test_separation_kernels.py
# asserts they move and book the same.
BACKENDS = ('kernel', 'numpy')


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


def _line_of_action(ox: float, oy: float, oz: float, rx: float, ry: float,
                    rz: float) -> tuple[float, float, float, float]:
    """Return (N, |offset|) of one offset, as ``narrowphase.line_of_action`` (same operations)."""
    scale = max(abs(ox), abs(oy), abs(oz))
    if scale != 0.0:
        sx, sy, sz = ox / scale, oy / scale, oz / scale
        norm = math.sqrt((sx * sx + sz * sz) + sy * sy)
        return sx / norm, sy / norm, sz / norm, scale * norm
    rv_scale = max(abs(rx), abs(ry), abs(rz))
    if rv_scale > 0.0:
        ux, uy, uz = rx / rv_scale, ry / rv_scale, rz / rv_scale
        norm = math.sqrt((ux * ux + uz * uz) + uy * uy)
        return -(ux / norm), -(uy / norm), -(uz / norm), 0.0
    return 1.0, 0.0, 0.0, 0.0


def _held(x: list, r: float, moved: tuple, way: tuple, low: np.ndarray, high: np.ndarray,
          dimensions: int) -> bool:
    """Say whether a particle at ``x`` moved by ``moved`` reaches a wall ``way`` points into."""
    for axis in range(dimensions):
        p, d = x[axis] + moved[axis], way[axis]
        if (p <= low[axis] + r and d < 0.0) or (p >= high[axis] - r and d > 0.0):
            return True
    return False


def _near_pairs(x: np.ndarray, radius: np.ndarray, inv_mass: np.ndarray, ci: np.ndarray,
                cj: np.ndarray, gravity: np.ndarray, ordered: bool) -> np.ndarray:
    """Return the candidates within the near reach, lowest first under gravity."""
    o = x[ci] - x[cj]
    reach = (radius[ci] + radius[cj]) * (1.0 + NEAR_FRACTION)
    keep = ((inv_mass[ci] + inv_mass[cj]) > 0.0) & \
        (o[:, 0] * o[:, 0] + o[:, 1] * o[:, 1] + o[:, 2] * o[:, 2] < reach * reach)
    near = np.flatnonzero(keep)
    if ordered and near.size > 1:
        up = -(x[:, 0] * gravity[0] + x[:, 1] * gravity[1] + x[:, 2] * gravity[2])
        height = np.minimum(up[ci[near]], up[cj[near]])
        near = near[np.argsort(height, kind='mergesort')]
    return near


def project_reference(position: np.ndarray, velocity: np.ndarray, inv_mass: np.ndarray,
                      radius: np.ndarray, ci: np.ndarray, cj: np.ndarray,
                      gravity: Optional[np.ndarray], walls: Optional[Walls], dimensions: int,
                      touched: np.ndarray, relax: float = RELAXATION,
                      tolerance: float = TOLERANCE,
                      max_passes: int = MAX_PASSES) -> tuple[int, float]:
    """Project overlaps away in place; return (passes run, worst excess over tolerance, m).

    The statement of ``projection_kernels.project_contacts`` (see the module
    docstring) in plain Python, one visit at a time; ``touched`` (one flag
    per candidate pair ``ci``/``cj``) is set for the pairs found overlapping.
    """
    n = position.shape[0]
    x = position.tolist()                     # Python floats: the same IEEE operations
    v = velocity.tolist()
    w = inv_mass.tolist()
    r = radius.tolist()
    dynamic = (inv_mass > 0.0).tolist()
    planes = walls.planes(dimensions) if walls is not None else []
    low = walls.low if walls is not None else np.full(3, -np.inf)
    high = walls.high if walls is not None else np.full(3, np.inf)
    hold = walls is not None
    ordered = gravity is not None
    g = np.zeros(3) if gravity is None else np.asarray(gravity, dtype=float)
    spacing = (SPACINGS * EPSILON * np.max(np.abs(position), axis=1)).tolist()
    ci_list, cj_list = ci.tolist(), cj.tolist()
    near = _near_pairs(position, radius, inv_mass, ci, cj, g, ordered).tolist()
    built = position.copy()
    worst = -math.inf
    passes = 0
    while passes < max_passes:
        passes += 1
        worst = -math.inf
        for axis, plane, inward in planes:
            for p in range(n):
                if dynamic[p] and inward * (x[p][axis] - plane) < r[p]:
                    depth = r[p] - inward * (x[p][axis] - plane)
                    worst = max(worst, depth - (tolerance * r[p] + spacing[p]))
                    x[p][axis] = plane + inward * r[p]
        for k in near:
            a, b = ci_list[k], cj_list[k]
            xa, xb, va, vb = x[a], x[b], v[a], v[b]
            nx, ny, nz, distance = _line_of_action(xa[0] - xb[0], xa[1] - xb[1], xa[2] - xb[2],
                                                   va[0] - vb[0], va[1] - vb[1], va[2] - vb[2])
            pen = r[a] + r[b] - distance
            if not pen > 0.0:
                continue
            touched[k] = True
            worst = max(worst, pen - (tolerance * min(r[a], r[b]) + max(spacing[a], spacing[b])))
            w_a, w_b = w[a], w[b]
            push = relax * pen
            if hold:
                s = push / (w_a + w_b)
                sx, sy, sz = s * nx, s * ny, s * nz
                held_a = _held(xa, r[a], (w_a * sx, w_a * sy, w_a * sz), (nx, ny, nz), low,
                               high, dimensions)
                held_b = _held(xb, r[b], (-(w_b * sx), -(w_b * sy), -(w_b * sz)),
                               (-nx, -ny, -nz), low, high, dimensions)
                w_a, w_b = (0.0 if (held_a and not held_b and w_b > 0.0) else w_a,
                            0.0 if (held_b and not held_a and w_a > 0.0) else w_b)
            w_sum = w_a + w_b
            f_a = push * w_a / w_sum
            f_b = push * w_b / w_sum
            xa[0] += f_a * nx
            xa[1] += f_a * ny
            xa[2] += f_a * nz
            xb[0] -= f_b * nx
            xb[1] -= f_b * ny
            xb[2] -= f_b * nz
        if not worst > 0.0:
            break
        now = np.array(x)
        step = now - built
        reach = NEAR_FRACTION * radius
        if np.any(step[:, 0] * step[:, 0] + step[:, 1] * step[:, 1] + step[:, 2] * step[:, 2]
                  >= reach * reach):
            near = _near_pairs(now, radius, inv_mass, ci, cj, g, ordered).tolist()
            built = now
    position[...] = x
    return passes, worst


class SeparationStage(Stage):
    """Project overlapping pairs apart (velocities only pay for a lift under gravity)."""

    name = 'separation'

    def __init__(self, walls: Optional[Walls] = None, backend: str = 'kernel') -> None:
        """Keep the wall planes to project particles back inside (None: no walls)."""
        if backend not in BACKENDS:
            raise ValueError(f'backend must be one of {BACKENDS}, got {backend!r}')
        self.walls = walls
        self.backend = backend
        # Passes of the last projection and its worst penetration over the tolerance
        # (m, <= 0: converged), for tests and benchmarks.
        self.passes = 0
        self.excess = -math.inf

    def run(self, ctx: StepContext) -> None:
        """Move positions in place."""
        c = ctx.contacts
        has_pairs = c is not None and len(c) > 0
        if not has_pairs and self.walls is None:
            return
        s = ctx.state
        if ctx.pair_i is not None:
            ci, cj = ctx.pair_i, ctx.pair_j
        elif has_pairs:
            ci, cj = c.i, c.j
        else:
            ci = cj = np.zeros(0, dtype=np.int64)
        ci = np.ascontiguousarray(ci, dtype=np.int64)
        cj = np.ascontiguousarray(cj, dtype=np.int64)
        gravity = ctx.effects.gravity
        gravity = None if gravity is None else np.asarray(gravity, float)
        start = s.position.copy() if gravity is not None else None
        i, j = self._project(ctx, ci, cj, gravity)
        if gravity is None:
            return
        added = lift(s.inv_mass, s.position - start, gravity)   # delta U per particle
        budget = ctx.losses if ctx.losses is not None else np.zeros(len(s))
        # Clusters: the step's contacts and every pair the projection pushed apart.
        if has_pairs:
            i, j = np.concatenate([c.i, i]), np.concatenate([c.j, j])
        if self.backend == 'kernel':
            velocity = np.ascontiguousarray(s.velocity, dtype=float)
            paid = pay_for_lift(np.ascontiguousarray(s.position, dtype=float), start, velocity,
                                np.ascontiguousarray(s.inv_mass, dtype=float),
                                np.ascontiguousarray(s.dynamic, dtype=np.bool_),
                                np.ascontiguousarray(i, dtype=np.int64),
                                np.ascontiguousarray(j, dtype=np.int64),
                                np.ascontiguousarray(added, dtype=float),
                                np.ascontiguousarray(budget, dtype=float))
            if velocity is not s.velocity:
                s.velocity[...] = velocity
        else:
            paid = self._pay_for_lift(s, start, added, clusters(len(s), s.dynamic, i, j),
                                      budget)
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
        return removed

    def _project(self, ctx: StepContext, ci: np.ndarray, cj: np.ndarray,
                 gravity: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Run the projection with the stage's backend; return the pairs it pushed apart."""
        s, dims, walls = ctx.state, ctx.dimensions, self.walls
        if self.backend == 'numpy':
            self.passes, self.excess, i, j = project_reference(
                s.position, s.velocity, s.inv_mass, s.radius, ci, cj, gravity, walls, dims)
            return i, j
        planes = walls.planes(dims) if walls is not None else []
        low = np.full(3, -np.inf) if walls is None else np.asarray(walls.low, dtype=float)
        high = np.full(3, np.inf) if walls is None else np.asarray(walls.high, dtype=float)
        position = np.ascontiguousarray(s.position, dtype=float)
        self.passes, self.excess, i, j = project_contacts(
            position, np.ascontiguousarray(s.velocity, dtype=float),
            np.ascontiguousarray(s.inv_mass, dtype=float),
            np.ascontiguousarray(s.radius, dtype=float),
            np.ascontiguousarray(s.dynamic, dtype=np.bool_), ci, cj,
            np.zeros(3) if gravity is None else gravity, gravity is not None,
            np.array([p[0] for p in planes], dtype=np.int64),
            np.array([p[1] for p in planes], dtype=float),
            np.array([p[2] for p in planes], dtype=float), low, high, dims,
            walls is not None, RELAXATION, TOLERANCE, MAX_PASSES, SHOCK_AFTER)
        if position is not s.position:
            s.position[...] = position
        return i, j

    def describe(self) -> str:
        """Say what the stage does."""
        text = ('position projection (Gauss-Seidel over the near pairs measured again at each '
                f'visit, until no overlap above {TOLERANCE:g} r or {MAX_PASSES} passes; '
                'velocities untouched; under gravity a lift beyond the cluster\'s losses is '
                'paid from the lifted particles\' speed and what they cannot pay is booked)')
        if self.walls is not None:
            text += ', walls as contacts'
        return text
