"""Converging position projection, compiled: non-linear Gauss-Seidel over pairs and walls.

``project_contacts`` removes the overlap left after the contact solve by
moving positions only (velocities are never touched, so nothing is fed
back into them). One pass visits every wall contact (each dynamic particle
against each wall plane: the wall is a contact of infinite mass) and then
every near pair, one at a time, each measured again from the current
positions when it is visited (Gauss-Seidel), and pushes an overlapping
pair apart along its line of action by ``relax`` times its penetration,
shared by inverse mass. Passes repeat until a whole pass finds no
penetration above the tolerance (a fraction of the smaller radius plus a
few float spacings at the coordinates involved) or ``max_passes`` ran.

Near pairs: the step's candidate pairs whose gap is below ``NEAR_FRACTION``
of their radii sum. A candidate further apart can only come to overlap if
one of its particles moved more than ``NEAR_FRACTION`` of its own radius
since the list was built; when any particle has, the list is built again
from the candidates at the current positions, so overlaps the projection
creates are picked up (Verlet-list reasoning inside the projection).

Order: under gravity the pairs are visited from the lowest (along g) to
the highest, so one pass carries a push from the floor up a whole column;
without gravity in candidate order. Walls hold: a particle its push would
take into a wall it touches stays put and its partner takes the whole
push (else a light ball pressed on the floor by a heavy one converges at
the mass ratio per pass).

``separation.project_reference`` states the same algorithm in plain
Python with the same floating-point operations in the same order;
``test/test_separation_kernels.py`` asserts identical results.
"""

from __future__ import annotations

import math

import numpy as np

# Imported first: it sets numba's cache directory before numba is imported.
from .contact_kernels import _held, line_of_action

from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)

# Candidates closer than this fraction of their radii sum are visited each pass.
NEAR_FRACTION = 0.25
# Float spacings at the coordinate added to the tolerance (coordinates far
# from the origin cannot be placed closer than their spacing).
SPACINGS = 4.0
EPSILON = 2.220446049250313e-16


@njit(cache=True)
def _near_pairs(position, radius, inv_mass, ci, cj, gravity, ordered, near, height):
    """Write the near candidates (indices into ci/cj) to ``near``, lowest first; return count."""
    count = 0
    for k in range(ci.size):
        a, b = ci[k], cj[k]
        if not (inv_mass[a] + inv_mass[b]) > 0.0:
            continue
        ox = position[a, 0] - position[b, 0]
        oy = position[a, 1] - position[b, 1]
        oz = position[a, 2] - position[b, 2]
        reach = (radius[a] + radius[b]) * (1.0 + NEAR_FRACTION)
        if not ox * ox + oy * oy + oz * oz < reach * reach:
            continue
        near[count] = k
        ha = -(position[a, 0] * gravity[0] + position[a, 1] * gravity[1]
               + position[a, 2] * gravity[2])
        hb = -(position[b, 0] * gravity[0] + position[b, 1] * gravity[1]
               + position[b, 2] * gravity[2])
        height[count] = min(ha, hb)
        count += 1
    if ordered and count > 1:
        order = np.argsort(height[:count], kind='mergesort')
        chosen = near[:count].copy()
        for q in range(count):
            near[q] = chosen[order[q]]
    return count


@njit(cache=True)
def _wall_pass(position, radius, dynamic, p_axis, p_value, p_inward, tolerance, spacing):
    """Place particles found past a wall plane back on it; return the worst excess over tol."""
    worst = -math.inf
    for q in range(p_axis.size):
        axis, plane, inward = p_axis[q], p_value[q], p_inward[q]
        for p in range(position.shape[0]):
            if dynamic[p] and inward * (position[p, axis] - plane) < radius[p]:
                depth = radius[p] - inward * (position[p, axis] - plane)
                worst = max(worst, depth - (tolerance * radius[p] + spacing[p]))
                position[p, axis] = plane + inward * radius[p]
    return worst


@njit(cache=True)
def _pair_visit(position, velocity, inv_mass, radius, a, b, hold, low, high, dimensions,
                relax, shock, gravity):
    """Measure pair (a, b) now and push it apart if it overlaps; return its penetration."""
    nx, ny, nz, distance = line_of_action(
        position[a, 0] - position[b, 0], position[a, 1] - position[b, 1],
        position[a, 2] - position[b, 2], velocity[a, 0] - velocity[b, 0],
        velocity[a, 1] - velocity[b, 1], velocity[a, 2] - velocity[b, 2])
    pen = radius[a] + radius[b] - distance
    if not pen > 0.0:
        return pen
    w_a, w_b = inv_mass[a], inv_mass[b]
    push = relax * pen
    if shock and w_a > 0.0 and w_b > 0.0:
        # Shock propagation: the lower particle (along g) supports the upper one.
        rise = -(nx * gravity[0] + ny * gravity[1] + nz * gravity[2])
        if rise > 0.0:
            w_b = 0.0
        elif rise < 0.0:
            w_a = 0.0
    if hold:
        s = push / (w_a + w_b)
        sx, sy, sz = s * nx, s * ny, s * nz
        held_a = _held(position, radius, a, w_a * sx, w_a * sy, w_a * sz, nx, ny, nz,
                       low, high, dimensions)
        held_b = _held(position, radius, b, -(w_b * sx), -(w_b * sy), -(w_b * sz), -nx,
                       -ny, -nz, low, high, dimensions)
        w_a, w_b = (0.0 if (held_a and not held_b and w_b > 0.0) else w_a,
                    0.0 if (held_b and not held_a and w_a > 0.0) else w_b)
    w_sum = w_a + w_b
    f_a = push * w_a / w_sum
    f_b = push * w_b / w_sum
    position[a, 0] += f_a * nx
    position[a, 1] += f_a * ny
    position[a, 2] += f_a * nz
    position[b, 0] -= f_b * nx
    position[b, 1] -= f_b * ny
    position[b, 2] -= f_b * nz
    return pen


@njit(cache=True)
def project_contacts(position, velocity, inv_mass, radius, dynamic, ci, cj, gravity, ordered,
                     p_axis, p_value, p_inward, low, high, dimensions, hold, relax,
                     tolerance, max_passes, touched, shock_after):
    """Project overlaps away in place; return (passes run, worst excess over tolerance, m).

    ``ci``/``cj``: the step's candidate pairs; ``touched`` (one flag per
    candidate) is set for every candidate found overlapping in a visit.
    The excess is the largest penetration minus its tolerance in the last
    pass (<= 0: converged; -inf: nothing touched or overlapped).
    """
    n, m = position.shape[0], ci.size
    spacing = np.empty(n)
    for p in range(n):
        big = max(abs(position[p, 0]), abs(position[p, 1]), abs(position[p, 2]))
        spacing[p] = SPACINGS * EPSILON * big
    near = np.empty(m, dtype=np.int64)
    height = np.empty(m)
    built = position.copy()
    count = _near_pairs(position, radius, inv_mass, ci, cj, gravity, ordered, near, height)
    worst = -math.inf
    passes = 0
    while passes < max_passes:
        passes += 1
        worst = _wall_pass(position, radius, dynamic, p_axis, p_value, p_inward, tolerance,
                           spacing)
        for q in range(count):
            k = near[q]
            a, b = ci[k], cj[k]
            pen = _pair_visit(position, velocity, inv_mass, radius, a, b, hold, low, high,
                              dimensions, relax, ordered and passes > shock_after, gravity)
            if pen > 0.0:
                touched[k] = True
                worst = max(worst, pen - (tolerance * min(radius[a], radius[b])
                                          + max(spacing[a], spacing[b])))
        if not worst > 0.0:
            break
        # A particle that moved a near fraction of its radius since the list was
        # built may reach a candidate that is not on it: build the list again.
        for p in range(n):
            dx = position[p, 0] - built[p, 0]
            dy = position[p, 1] - built[p, 1]
            dz = position[p, 2] - built[p, 2]
            reach = NEAR_FRACTION * radius[p]
            if dx * dx + dy * dy + dz * dz >= reach * reach:
                count = _near_pairs(position, radius, inv_mass, ci, cj, gravity, ordered,
                                    near, height)
                built[...] = position
                break
    return passes, worst


def warm_up() -> None:
    """Compile (or load) the projection kernels on a tiny problem."""
    position = np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]])
    velocity = np.zeros((2, 3))
    ones = np.ones(2)
    pi, pj = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    project_contacts(position, velocity, ones, ones, np.ones(2, dtype=np.bool_), pi, pj,
                     np.array([0.0, -9.81, 0.0]), True, np.zeros(1, dtype=np.int64),
                     np.full(1, -10.0), np.ones(1), np.full(3, -10.0), np.full(3, 10.0), 3,
                     True, 1.0, 1e-3, 8, np.zeros(1, dtype=np.bool_), 2)


def kernels() -> list:
    """Return the dispatchers ``contact_kernels.prepare`` checks for a cache."""
    return [project_contacts]
