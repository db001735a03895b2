"""The separation kernels: overlaps projected apart, and lift paid for from speed."""

from __future__ import annotations

import math

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)

from ...law.primitives import dot3, line_of_action  # noqa: E402
from ...step.step_kernels import union_root  # noqa: E402


@njit(cache=True)
def _held(position, radius, p, dx, dy, dz, nx, ny, nz, low, high, dimensions):
    """Say whether particle ``p`` moved by (dx, dy, dz) reaches a wall N points into.

    As ``separation.held_by_walls`` for one particle (N: its push direction).
    """
    r = radius[p]
    moved = (position[p, 0] + dx, position[p, 1] + dy, position[p, 2] + dz)
    way = (nx, ny, nz)
    for axis in range(dimensions):
        x, d = moved[axis], way[axis]
        if (x <= low[axis] + r and d < 0.0) or (x >= high[axis] - r and d > 0.0):
            return True
    return False


@njit(cache=True)
def _separate_pass(position, inv_mass, radius, pi, pj, normal, penetration, active, hold,
                   low, high, dimensions, push, total, moves):
    """One Jacobi projection pass over the ``active`` pairs (``separation.separate``).

    Every push is computed from the positions before the pass, summed per
    particle (all i sides in pair order, then all j sides, as numpy's
    ``add.at``) and averaged over the pushes that move the particle.
    """
    n, m = position.shape[0], pi.size
    for p in range(n):
        total[p, 0] = total[p, 1] = total[p, 2] = 0.0
        moves[p] = 0.0
    for k in range(m):
        if not active[k]:
            continue
        a, b = pi[k], pj[k]
        w_a, w_b = inv_mass[a], inv_mass[b]
        nx, ny, nz, pen = normal[k, 0], normal[k, 1], normal[k, 2], penetration[k]
        if hold:
            s = pen / (w_a + w_b)
            sx, sy, sz = s * nx, s * ny, s * nz
            held_a = _held(position, radius, a, w_a * sx, w_a * sy, w_a * sz, nx, ny, nz,
                           low, high, dimensions)
            held_b = _held(position, radius, b, -(w_b * sx), -(w_b * sy), -(w_b * sz), -nx,
                           -ny, -nz, low, high, dimensions)
            w_a, w_b = (0.0 if (held_a and not held_b and w_b > 0.0) else w_a,
                        0.0 if (held_b and not held_a and w_a > 0.0) else w_b)
        w_sum = w_a + w_b
        push[k, 0] = pen * w_a / w_sum
        push[k, 1] = pen * w_b / w_sum
        if w_a > 0.0:
            moves[a] += 1.0
        if w_b > 0.0:
            moves[b] += 1.0
    for k in range(m):
        if active[k]:
            f, a = push[k, 0], pi[k]
            total[a, 0] += f * normal[k, 0]
            total[a, 1] += f * normal[k, 1]
            total[a, 2] += f * normal[k, 2]
    for k in range(m):
        if active[k]:
            f, b = push[k, 1], pj[k]
            total[b, 0] += -(f * normal[k, 0])
            total[b, 1] += -(f * normal[k, 1])
            total[b, 2] += -(f * normal[k, 2])
    for p in range(n):
        if moves[p] > 0.0:
            position[p, 0] += total[p, 0] / moves[p]
            position[p, 1] += total[p, 1] / moves[p]
            position[p, 2] += total[p, 2] / moves[p]


@njit(cache=True)
def _clamp_inside(position, radius, dynamic, p_axis, p_value, p_inward):
    """Place dynamic particles found past a wall plane back on it, plane after plane."""
    for q in range(p_axis.size):
        axis, plane, inward = p_axis[q], p_value[q], p_inward[q]
        for p in range(position.shape[0]):
            if dynamic[p] and inward * (position[p, axis] - plane) < radius[p]:
                position[p, axis] = plane + inward * radius[p]


@njit(cache=True)
def project_overlaps(position, velocity, inv_mass, radius, dynamic, pi, pj, normal0,
                     penetration0, passes, hold, walls, low, high, dimensions, p_axis, p_value,
                     p_inward):
    """Run the separation stage's projection in place (``SeparationStage._project``).

    ``passes`` Jacobi passes: the first on the narrowphase's normals and
    penetrations, each later one on the pairs still overlapping, measured
    again; with ``walls`` the particles are clamped back inside after each
    pass. ``hold``: a particle its push would take into a wall stays put.
    """
    n, m = position.shape[0], pi.size
    normal = normal0.copy()
    penetration = penetration0.copy()
    active = np.ones(m, dtype=np.bool_)
    push = np.zeros((m, 2))
    total = np.zeros((n, 3))
    moves = np.zeros(n)
    for step in range(passes):
        if m:
            if step > 0:
                overlapping = False
                for k in range(m):
                    a, b = pi[k], pj[k]
                    nx, ny, nz, distance = line_of_action(
                        position[a, 0] - position[b, 0], position[a, 1] - position[b, 1],
                        position[a, 2] - position[b, 2], velocity[a, 0] - velocity[b, 0],
                        velocity[a, 1] - velocity[b, 1], velocity[a, 2] - velocity[b, 2])
                    normal[k, 0], normal[k, 1], normal[k, 2] = nx, ny, nz
                    penetration[k] = radius[a] + radius[b] - distance
                    active[k] = penetration[k] > 0.0
                    overlapping = overlapping or active[k]
                if not overlapping and not walls:
                    return
            _separate_pass(position, inv_mass, radius, pi, pj, normal, penetration, active,
                           hold, low, high, dimensions, push, total, moves)
        if walls:
            _clamp_inside(position, radius, dynamic, p_axis, p_value, p_inward)


@njit(cache=True)
def pay_for_lift(position, start, velocity, inv_mass, dynamic, pi, pj, added, budget):
    """Take back what the projection's net lift adds per cluster; return J removed per particle.

    The law of ``SeparationStage._pay_for_lift`` (``position`` is moved back
    in place where the speed cannot pay); clusters are the connected
    components of the pairs between two dynamic particles (union-find, the
    partition ``separation.clusters`` finds), sums per cluster run in
    particle order as numpy's ``bincount``.
    """
    n = position.shape[0]
    parent = np.arange(n)
    for k in range(pi.size):
        a, b = pi[k], pj[k]
        if dynamic[a] and dynamic[b]:
            ra, rb = union_root(parent, a), union_root(parent, b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    cluster = np.empty(n, dtype=np.int64)
    lifted = np.zeros(n)
    spent = np.zeros(n)
    for p in range(n):
        c = union_root(parent, p)
        cluster[p] = c
        lifted[c] += added[p]
        spent[c] += budget[p]
    raised = np.zeros(n)
    up = np.zeros(n, dtype=np.bool_)
    for p in range(n):
        c = cluster[p]
        if added[p] > 0.0 and lifted[c] - max(spent[c], 0.0) > 0.0:
            up[p] = True
            raised[c] += added[p]
    removed = np.zeros(n)
    for p in range(n):
        if not up[p]:
            continue
        c = cluster[p]
        owed = (lifted[c] - max(spent[c], 0.0)) * added[p] / raised[c]
        mass = 1.0 / inv_mass[p]
        mx = position[p, 0] - start[p, 0]
        my = position[p, 1] - start[p, 1]
        mz = position[p, 2] - start[p, 2]
        norm = math.sqrt(mx * mx + my * my + mz * mz)
        wx, wy, wz = mx / norm, my / norm, mz / norm
        along = max(dot3(velocity[p, 0], velocity[p, 1], velocity[p, 2], wx, wy, wz), 0.0)
        taken = min(owed, 0.5 * mass * along * along)
        slower = math.sqrt(max(along * along - 2.0 * taken / mass, 0.0))
        change = slower - along
        velocity[p, 0] += change * wx
        velocity[p, 1] += change * wy
        velocity[p, 2] += change * wz
        removed[p] = taken
        # What the speed cannot pay is not lifted: the particle goes back along
        # its push by that fraction of it (positions only, see the stage).
        unpaid = owed - taken
        if unpaid > 0.0:
            back = unpaid / added[p]
            position[p, 0] -= back * mx
            position[p, 1] -= back * my
            position[p, 2] -= back * mz
    return removed


def warm_up() -> None:
    """Call this module's kernels once on a tiny problem (compiles or loads the cache)."""
    # A pair 1.9 m apart with radii 1 m overlaps by 0.1 m along -x (from 0 to 1).
    position = np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]])
    v = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    inv_mass, radius = np.ones(2), np.ones(2)
    dynamic = np.ones(2, dtype=bool)
    pi, pj = np.array([1], dtype=np.int64), np.array([0], dtype=np.int64)
    normal, penetration = np.array([[1.0, 0.0, 0.0]]), np.array([0.1])
    low, high = np.full(3, -10.0), np.full(3, 10.0)
    start = position.copy()
    project_overlaps(position, v, inv_mass, radius, dynamic, pi, pj, normal, penetration, 2,
                     True, True, low, high, 3, np.zeros(1, dtype=np.int64), np.full(1, -10.0),
                     np.ones(1))
    pay_for_lift(position, start, v, inv_mass, dynamic, pi, pj, np.ones(2), np.zeros(2))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [project_overlaps, pay_for_lift]
