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
def _order(position, gravity, ordered, near_a, near_b, count, n):
    """Sort the near pairs in place by (a, b), then stably from the lowest (along g) up."""
    if count < 2:
        return
    key = np.empty(count, dtype=np.int64)
    for q in range(count):
        key[q] = near_a[q] * n + near_b[q]
    first = np.argsort(key, kind='mergesort')
    a_sorted, b_sorted = near_a[:count][first], near_b[:count][first]
    if ordered:
        height = np.empty(count)
        for q in range(count):
            a, b = a_sorted[q], b_sorted[q]
            ha = -(position[a, 0] * gravity[0] + position[a, 1] * gravity[1]
                   + position[a, 2] * gravity[2])
            hb = -(position[b, 0] * gravity[0] + position[b, 1] * gravity[1]
                   + position[b, 2] * gravity[2])
            height[q] = min(ha, hb)
        second = np.argsort(height, kind='mergesort')
        a_sorted, b_sorted = a_sorted[second], b_sorted[second]
    near_a[:count] = a_sorted
    near_b[:count] = b_sorted


@njit(cache=True)
def _is_near(position, radius, inv_mass, a, b):
    """Say whether pair (a, b) can move and lies within the near reach."""
    if not (inv_mass[a] + inv_mass[b]) > 0.0:
        return False
    ox = position[a, 0] - position[b, 0]
    oy = position[a, 1] - position[b, 1]
    oz = position[a, 2] - position[b, 2]
    reach = (radius[a] + radius[b]) * (1.0 + NEAR_FRACTION)
    return ox * ox + oy * oy + oz * oz < reach * reach


@njit(cache=True)
def _near_candidates(position, radius, inv_mass, ci, cj):
    """Return the candidate pairs (i < j) within the near reach."""
    near_a = np.empty(ci.size, dtype=np.int64)
    near_b = np.empty(ci.size, dtype=np.int64)
    count = 0
    for k in range(ci.size):
        a, b = min(ci[k], cj[k]), max(ci[k], cj[k])
        if _is_near(position, radius, inv_mass, a, b):
            near_a[count], near_b[count] = a, b
            count += 1
    return near_a[:count].copy(), near_b[:count].copy()


@njit(cache=True)
def _near_grid(position, radius, inv_mass, dimensions):
    """Return every pair (i < j) within the near reach, found on a hashed uniform grid."""
    n = position.shape[0]
    none = np.zeros(0, dtype=np.int64)
    if n < 2:
        return none, none
    cell = 2.0 * radius.max() * (1.0 + NEAR_FRACTION)
    if not cell > 0.0:
        return none, none
    origin = np.empty(3)
    for axis in range(3):
        origin[axis] = position[:, axis].min()
    coords = np.zeros((n, 3), dtype=np.int64)
    size = 1
    while size < 2 * n:
        size *= 2
    bucket = np.empty(n, dtype=np.int64)
    for p in range(n):
        for axis in range(dimensions):
            coords[p, axis] = int(math.floor((position[p, axis] - origin[axis]) / cell))
        bucket[p] = _hash(coords[p, 0], coords[p, 1], coords[p, 2], size)
    by_bucket = np.argsort(bucket, kind='mergesort')
    begin = np.zeros(size + 1, dtype=np.int64)
    for p in range(n):
        begin[bucket[p] + 1] += 1
    for h in range(size):
        begin[h + 1] += begin[h]
    span_z = 1 if dimensions == 3 else 0
    out_a = np.empty(4 * n, dtype=np.int64)
    out_b = np.empty(4 * n, dtype=np.int64)
    count = 0
    for a in range(n):
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-span_z, span_z + 1):
                    cx, cy, cz = coords[a, 0] + dx, coords[a, 1] + dy, coords[a, 2] + dz
                    h = _hash(cx, cy, cz, size)
                    for q in range(begin[h], begin[h + 1]):
                        b = by_bucket[q]
                        if b <= a or coords[b, 0] != cx or coords[b, 1] != cy \
                                or coords[b, 2] != cz:
                            continue
                        if not _is_near(position, radius, inv_mass, a, b):
                            continue
                        if count == out_a.size:
                            out_a = np.concatenate((out_a, np.empty(out_a.size, np.int64)))
                            out_b = np.concatenate((out_b, np.empty(out_b.size, np.int64)))
                        out_a[count], out_b[count] = a, b
                        count += 1
    return out_a[:count].copy(), out_b[:count].copy()


@njit(cache=True)
def _hash(cx, cy, cz, size):
    """Return the bucket of a grid cell (size: a power of two)."""
    return ((cx * 73856093) ^ (cy * 19349663) ^ (cz * 83492791)) & (size - 1)


@njit(cache=True)
def _wall_pass(position, radius, dynamic, p_axis, p_value, p_inward, slop, tolerance,
               spacing):
    """Put particles deeper than the slop into a wall back at the slop; return the worst excess."""
    worst = -math.inf
    for q in range(p_axis.size):
        axis, plane, inward = p_axis[q], p_value[q], p_inward[q]
        for p in range(position.shape[0]):
            kept = slop * radius[p]
            if dynamic[p] and inward * (position[p, axis] - plane) < radius[p] - kept:
                depth = radius[p] - inward * (position[p, axis] - plane)
                worst = max(worst, depth - ((slop + tolerance) * radius[p] + spacing[p]))
                position[p, axis] = plane + inward * (radius[p] - kept)
    return worst


@njit(cache=True)
def _pair_visit(position, velocity, inv_mass, radius, a, b, hold, low, high, dimensions,
                relax, kept):
    """Measure pair (a, b) now and push it apart if it overlaps; return its penetration."""
    nx, ny, nz, distance = line_of_action(
        position[a, 0] - position[b, 0], position[a, 1] - position[b, 1],
        position[a, 2] - position[b, 2], velocity[a, 0] - velocity[b, 0],
        velocity[a, 1] - velocity[b, 1], velocity[a, 2] - velocity[b, 2])
    pen = radius[a] + radius[b] - distance
    if not pen > kept:
        return pen
    w_a, w_b = inv_mass[a], inv_mass[b]
    push = relax * (pen - kept)
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
                     slop, tolerance, max_passes):
    """Project overlaps away in place; return (passes, worst excess over tolerance (m), i, j).

    ``ci``/``cj``: the step's candidate pairs. The excess is the largest
    penetration minus its tolerance in the last pass (<= 0: converged;
    -inf: nothing overlapped); (i, j) are the pairs found overlapping in
    some visit (repeats possible).
    """
    n = position.shape[0]
    spacing = np.empty(n)
    for p in range(n):
        big = max(abs(position[p, 0]), abs(position[p, 1]), abs(position[p, 2]))
        spacing[p] = SPACINGS * EPSILON * big
    near_a, near_b = _near_candidates(position, radius, inv_mass, ci, cj)
    _order(position, gravity, ordered, near_a, near_b, near_a.size, n)
    built = position.copy()
    touched_a = np.empty(max(near_a.size, 16), dtype=np.int64)
    touched_b = np.empty(max(near_a.size, 16), dtype=np.int64)
    touched = 0
    worst = -math.inf
    passes = 0
    while passes < max_passes:
        passes += 1
        worst = _wall_pass(position, radius, dynamic, p_axis, p_value, p_inward, slop,
                           tolerance, spacing)
        for q in range(near_a.size):
            a, b = near_a[q], near_b[q]
            kept = slop * min(radius[a], radius[b])
            pen = _pair_visit(position, velocity, inv_mass, radius, a, b, hold, low, high,
                              dimensions, relax, kept)
            if pen > kept:
                if touched == touched_a.size:
                    touched_a = np.concatenate((touched_a, np.empty(touched, np.int64)))
                    touched_b = np.concatenate((touched_b, np.empty(touched, np.int64)))
                touched_a[touched], touched_b[touched] = a, b
                touched += 1
                worst = max(worst, pen - ((slop + tolerance) * min(radius[a], radius[b])
                                          + max(spacing[a], spacing[b])))
        if not worst > 0.0:
            break
        # A particle that moved a near fraction of its radius since the list was
        # built may reach a pair that is not on it (nor among the step's
        # candidates): search the grid again.
        for p in range(n):
            dx = position[p, 0] - built[p, 0]
            dy = position[p, 1] - built[p, 1]
            dz = position[p, 2] - built[p, 2]
            reach = NEAR_FRACTION * radius[p]
            if dx * dx + dy * dy + dz * dz >= reach * reach:
                near_a, near_b = _near_grid(position, radius, inv_mass, dimensions)
                _order(position, gravity, ordered, near_a, near_b, near_a.size, n)
                built[...] = position
                break
    return passes, worst, touched_a[:touched].copy(), touched_b[:touched].copy()


def warm_up() -> None:
    """Compile (or load) the projection kernels on a tiny problem."""
    position = np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]])
    velocity = np.zeros((2, 3))
    ones = np.ones(2)
    pi, pj = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    project_contacts(position, velocity, ones, ones, np.ones(2, dtype=np.bool_), pi, pj,
                     np.array([0.0, -9.81, 0.0]), True, np.zeros(1, dtype=np.int64),
                     np.full(1, -10.0), np.ones(1), np.full(3, -10.0), np.full(3, 10.0), 3,
                     True, 1.0, 4e-3, 1e-3, 8)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [project_contacts]
