"""The separation kernels: overlaps projected apart, and lift paid for from speed.

``project_overlaps`` runs the separation stage's Jacobi passes and wall
clamps in place; ``pay_for_lift`` applies the per-cluster energy budget
(clusters by union-find). The tests compare both with a vectorised
reference (``test/oracles/separation_oracle.py``), bit for bit: sums per
particle and per cluster run in numpy's order (``add.at``, ``bincount``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit, prange  # noqa: E402,I100 (after the cache directory is chosen)

from ...law.primitives import dot3, line_of_action  # noqa: E402
from ...step.step_kernels import (ParticleArrays, spread_levels, union_root,  # noqa: E402
                                  UNSUPPORTED)
from ..detection.narrowphase_kernels import ContactArrays  # noqa: E402
from ...model.tunables import (STACK_ALIGNMENT, SUPPORT_SLOP, SUPPORT_SWEEPS,  # noqa: E402
                               SUPPORT_TOLERANCE)


class WallBounds(NamedTuple):
    """The walls the projection holds at and clamps to (``present`` False: none)."""

    present: bool
    low: np.ndarray             # (3,) lower wall per axis, m (-inf: none)
    high: np.ndarray            # (3,) upper wall per axis, m (inf: none)
    dimensions: int             # axes that have walls (2 or 3)
    plane_axis: np.ndarray      # (planes,) int64, each plane's axis
    plane_value: np.ndarray     # (planes,) its coordinate, m
    plane_inward: np.ndarray    # (planes,) +1 for a lower wall, -1 for an upper one


class ProjectionWork(NamedTuple):
    """Per-particle buffers of the projection, kept by the stage from step to step.

    Every call reads and writes only the rows of the particles of its
    pairs and leaves ``moves`` at zero and ``seen`` False, so a step costs
    its contacts, not its particle count (no fresh memory to fault in).
    """

    total: np.ndarray           # (n, 3) sum of each particle's pushes, m (rows of pairs)
    moves: np.ndarray           # (n,) how many pushes move each particle; 0 between calls
    seen: np.ndarray            # (n,) bool, a particle listed for the clamps; False between calls


def projection_work(n: int) -> ProjectionWork:
    """Return clean buffers for ``n`` particles."""
    return ProjectionWork(np.empty((n, 3)), np.zeros(n), np.zeros(n, dtype=np.bool_))


@njit(cache=True, inline='always')
def _into_wall(position, p, r, shift, way, low, high, dimensions):
    """Say whether particle ``p`` moved by ``shift`` reaches a wall ``way`` points into.

    The walls are their arrays (``WallBounds.low``, ``high``, ``dimensions``):
    the in-turn passes call it per pair, where a record handed on would cost a
    reference count per array.
    """
    moved = (position[p, 0] + shift[0], position[p, 1] + shift[1], position[p, 2] + shift[2])
    for axis in range(dimensions):
        x, d = moved[axis], way[axis]
        if (x <= low[axis] + r and d < 0.0) or (x >= high[axis] - r and d > 0.0):
            return True
    return False


@njit(cache=True)
def _held(particles, p, shift, way, walls):
    """Say whether particle ``p`` moved by ``shift`` reaches a wall ``way`` points into."""
    return _into_wall(particles.position, p, particles.radius[p], shift, way, walls.low,
                      walls.high, walls.dimensions)


@njit(cache=True)
def _separate_pass(particles, contacts, listed, hold, walls, work):
    """One Jacobi projection pass over the contacts ``listed`` (ascending).

    Every push is computed from the positions before the pass, summed per
    particle (all first sides in pair order, then all second sides, as
    numpy's ``add.at``) and averaged over the pushes that move the particle.
    With ``hold``, a particle its push would take into a wall stays put and
    its partner, if it can move, takes the whole push.
    """
    position, inv_mass = particles.position, particles.inv_mass
    pair_first, pair_second = contacts.first, contacts.second
    normal, penetration = contacts.normal, contacts.penetration
    total, moves = work.total, work.moves
    push = np.empty((listed.size, 2))
    # Only the particles of listed pairs are summed and moved: their rows are
    # cleared here (the rest of ``total`` and ``moves`` is never read).
    for k in listed:
        for p in (pair_first[k], pair_second[k]):
            total[p, 0] = total[p, 1] = total[p, 2] = 0.0
            moves[p] = 0.0
    for t in range(listed.size):
        k = listed[t]
        a, b = pair_first[k], pair_second[k]
        w_a, w_b = inv_mass[a], inv_mass[b]
        nx, ny, nz, depth = normal[k, 0], normal[k, 1], normal[k, 2], penetration[k]
        if hold:
            share = depth / (w_a + w_b)
            sx, sy, sz = share * nx, share * ny, share * nz
            held_a = _held(particles, a, (w_a * sx, w_a * sy, w_a * sz), (nx, ny, nz), walls)
            held_b = _held(particles, b, (-(w_b * sx), -(w_b * sy), -(w_b * sz)),
                           (-nx, -ny, -nz), walls)
            w_a, w_b = (0.0 if (held_a and not held_b and w_b > 0.0) else w_a,
                        0.0 if (held_b and not held_a and w_a > 0.0) else w_b)
        w_sum = w_a + w_b
        push[t, 0] = depth * w_a / w_sum
        push[t, 1] = depth * w_b / w_sum
        if w_a > 0.0:
            moves[a] += 1.0
        if w_b > 0.0:
            moves[b] += 1.0
    for t in range(listed.size):
        k = listed[t]
        f, a = push[t, 0], pair_first[k]
        total[a, 0] += f * normal[k, 0]
        total[a, 1] += f * normal[k, 1]
        total[a, 2] += f * normal[k, 2]
    for t in range(listed.size):
        k = listed[t]
        f, b = push[t, 1], pair_second[k]
        total[b, 0] += -(f * normal[k, 0])
        total[b, 1] += -(f * normal[k, 1])
        total[b, 2] += -(f * normal[k, 2])
    for k in listed:
        for p in (pair_first[k], pair_second[k]):
            if moves[p] > 0.0:
                position[p, 0] += total[p, 0] / moves[p]
                position[p, 1] += total[p, 1] / moves[p]
                position[p, 2] += total[p, 2] / moves[p]
                moves[p] = 0.0       # moved once: ``moves`` is clean again


@njit(cache=True)
def support_levels(particles, dynamic, contacts, walls, floors):
    """Return each particle's distance in contacts from a support (UNSUPPORTED: none).

    A static particle, and a dynamic one within ``SUPPORT_SLOP`` of its
    radius of a wall plane that holds it up against gravity (``floors``,
    one flag per plane: its inward normal points against gravity), is level
    0 (``spread_levels`` does the rest).
    """
    position, radius = particles.position, particles.radius
    n = position.shape[0]
    level = np.full(n, UNSUPPORTED, dtype=np.int64)
    for p in range(n):
        supported = not dynamic[p]
        if walls.present:
            for q in range(walls.plane_axis.size):
                if not floors[q]:
                    continue
                axis, inward = walls.plane_axis[q], walls.plane_inward[q]
                gap = inward * (position[p, axis] - walls.plane_value[q]) - radius[p]
                if gap <= SUPPORT_SLOP * radius[p]:
                    supported = True
        if supported:
            level[p] = 0
    spread_levels(level, contacts.first, contacts.second)
    return level


@njit(cache=True)
def support_order(contacts, level):
    """Return the pairs nearest a support first (by the lower level of the two; stable).

    A counting sort by that level (pairs of unsupported particles last), in
    pair order within a level: the order a stable sort of the keys gives.
    """
    first, second = contacts.first, contacts.second
    m = first.size
    key = np.empty(m, dtype=np.int64)
    top = 0
    for k in range(m):
        key[k] = min(level[first[k]], level[second[k]])
        if key[k] != UNSUPPORTED:
            top = max(top, key[k])
    start = np.zeros(top + 3, dtype=np.int64)
    for k in range(m):
        if key[k] == UNSUPPORTED:
            key[k] = top + 1
        start[key[k] + 1] += 1
    for c in range(top + 2):
        start[c + 1] += start[c]
    order = np.empty(m, dtype=np.int64)
    for k in range(m):
        order[start[key[k]]] = k
        start[key[k]] += 1
    return order


@njit(cache=True, inline='always')
def _mover(position, radius, inv_mass, a, b, normal, depth, level, walls, up):
    """Return which of pair (a, b) moves alone out of its overlap, or -1 if they share it.

    Of two dynamic particles at different support levels, one above the
    other (the line of action ``normal``, from b to a, within STACK_ALIGNMENT
    of ``up``), the one farther from a support moves alone, unless its push
    by ``depth`` would take it into a wall (the clamp would put it back and
    leave the overlap). ``walls`` is (present, low, high, dimensions).
    """
    nx, ny, nz = normal
    present, low, high, dimensions = walls
    if abs(dot3(nx, ny, nz, up[0], up[1], up[2])) < STACK_ALIGNMENT:
        return -1
    if level[a] < level[b] and inv_mass[b] > 0.0 and not (present and _into_wall(
            position, b, radius[b], (-depth * nx, -depth * ny, -depth * nz), (-nx, -ny, -nz),
            low, high, dimensions)):
        return b
    if level[b] < level[a] and inv_mass[a] > 0.0 and not (present and _into_wall(
            position, a, radius[a], (depth * nx, depth * ny, depth * nz), (nx, ny, nz), low,
            high, dimensions)):
        return a
    return -1


@njit(cache=True, inline='always')
def _onto_sphere(position, p, sphere, other):
    """Put particle ``p`` on one reach sphere if it then clears the other; return whether.

    ``sphere`` is (centre row, p's offset from it, that offset's length, reach):
    p goes along its offset to the reach; ``other`` is (centre row, reach).
    """
    centre, offset, distance, reach = sphere
    s = reach / distance
    x = (position[centre, 0] + s * offset[0], position[centre, 1] + s * offset[1],
         position[centre, 2] + s * offset[2])
    e = (x[0] - position[other[0], 0], x[1] - position[other[0], 1],
         x[2] - position[other[0], 2])
    if dot3(e[0], e[1], e[2], e[0], e[1], e[2]) >= other[1] * other[1]:
        position[p, 0], position[p, 1], position[p, 2] = x
        return True
    return False


@njit(cache=True, inline='always')
def _outside_two(position, radius, p, q1, q2):
    """Move particle ``p`` to the nearest point where it overlaps neither ``q1`` nor ``q2``.

    The point nearest ``p`` outside one reach sphere (r_p + r_q about q)
    if it is outside the other too, else the nearest point of the circle
    where the two spheres meet: the exact answer of the projected sweeps in
    one go (in a groove they need about ten to reach SUPPORT_TOLERANCE).
    Returns False, moving nothing, where the closed
    form does not apply (coincident centres, spheres that do not meet, a
    particle on their axis): the caller sweeps.
    """
    reach1, reach2 = radius[p] + radius[q1], radius[p] + radius[q2]
    o1 = (position[p, 0] - position[q1, 0], position[p, 1] - position[q1, 1],
          position[p, 2] - position[q1, 2])
    o2 = (position[p, 0] - position[q2, 0], position[p, 1] - position[q2, 1],
          position[p, 2] - position[q2, 2])
    d1 = math.sqrt(dot3(o1[0], o1[1], o1[2], o1[0], o1[1], o1[2]))
    d2 = math.sqrt(dot3(o2[0], o2[1], o2[2], o2[0], o2[1], o2[2]))
    if d1 == 0.0 or d2 == 0.0:
        return False
    if d1 >= reach1 and d2 >= reach2:
        return True
    if d1 < reach1 and _onto_sphere(position, p, (q1, o1, d1, reach1), (q2, reach2)):
        return True
    if d2 < reach2 and _onto_sphere(position, p, (q2, o2, d2, reach2), (q1, reach1)):
        return True
    ux, uy, uz = (position[q2, 0] - position[q1, 0], position[q2, 1] - position[q1, 1],
                  position[q2, 2] - position[q1, 2])
    apart = math.sqrt(dot3(ux, uy, uz, ux, uy, uz))
    if apart == 0.0:
        return False
    ux, uy, uz = ux / apart, uy / apart, uz / apart
    a = (apart * apart + reach1 * reach1 - reach2 * reach2) / (2.0 * apart)
    h2 = reach1 * reach1 - a * a
    if not h2 > 0.0:
        return False
    cx, cy, cz = position[q1, 0] + a * ux, position[q1, 1] + a * uy, position[q1, 2] + a * uz
    wx, wy, wz = position[p, 0] - cx, position[p, 1] - cy, position[p, 2] - cz
    along = dot3(wx, wy, wz, ux, uy, uz)
    wx, wy, wz = wx - along * ux, wy - along * uy, wz - along * uz
    w = math.sqrt(dot3(wx, wy, wz, wx, wy, wz))
    if w == 0.0:
        return False
    s = math.sqrt(h2) / w
    position[p, 0], position[p, 1], position[p, 2] = cx + s * wx, cy + s * wy, cz + s * wz
    return True


@njit(cache=True, inline='always')
def _lift_off_supports(position, velocity, radius, pairs, p, group, lifted):
    """Project one lone mover out of all its supports at once.

    ``pairs`` is (first, second, order) and ``group`` (head, following):
    the positions in ``order`` of the pairs in which the mover ``p`` stands
    on a support one level lower (which holds), linked in visit order from
    ``head``, -1 ending the chain. The constraints are the mover's own:
    projected Gauss-Seidel on the pushes (``lifted``, one per pair of the
    group, >= 0) finds the smallest move that leaves none of them
    overlapping. A disc sunk into a groove rises straight up; pushing it out
    of one support after the other (never back) would walk it sideways every
    step. Two supports, the usual groove, have that move in closed form
    (``_outside_two``); the sweeps run for one, three or more.
    """
    pair_first, pair_second, order = pairs
    head, following = group
    t, size = head, 0
    while t >= 0:
        lifted[size] = 0.0
        size += 1
        t = following[t]
    if size == 2:
        one, two = order[head], order[following[head]]
        if _outside_two(position, radius, p,
                        pair_second[one] if pair_first[one] == p else pair_first[one],
                        pair_second[two] if pair_first[two] == p else pair_first[two]):
            return
    for _ in range(SUPPORT_SWEEPS):
        converged = True
        t, row = head, 0
        while t >= 0:
            k = order[t]
            at = row
            t = following[t]
            row += 1
            a, b = pair_first[k], pair_second[k]
            q = b if a == p else a
            nx, ny, nz, distance = line_of_action(
                position[p, 0] - position[q, 0], position[p, 1] - position[q, 1],
                position[p, 2] - position[q, 2], velocity[p, 0] - velocity[q, 0],
                velocity[p, 1] - velocity[q, 1], velocity[p, 2] - velocity[q, 2])
            push = max(lifted[at] + radius[p] + radius[q] - distance, 0.0)
            change = push - lifted[at]
            if change == 0.0:
                continue
            lifted[at] = push
            position[p, 0] += change * nx
            position[p, 1] += change * ny
            position[p, 2] += change * nz
            if abs(change) > SUPPORT_TOLERANCE * radius[p]:
                converged = False
        if converged:
            break


@njit(cache=True, inline='always')
def _pair_overlap(position, velocity, radius, a, b):
    """Return (N, depth) of pair (a, b) as the particles stand: the line of action from b to a."""
    nx, ny, nz, distance = line_of_action(
        position[a, 0] - position[b, 0], position[a, 1] - position[b, 1],
        position[a, 2] - position[b, 2], velocity[a, 0] - velocity[b, 0],
        velocity[a, 1] - velocity[b, 1], velocity[a, 2] - velocity[b, 2])
    return (nx, ny, nz), radius[a] + radius[b] - distance


@njit(cache=True)
def _separate_in_turn(particles, contacts, order, level, walls, up):
    """One Gauss-Seidel projection pass over the pairs, a support level at a time.

    The pairs come nearest a support first (``order``, by the lower level of
    the two) and are visited in turn from the positions as they are. Where
    a particle stands on others one level lower (the line of action within
    STACK_ALIGNMENT of ``up``), it is lifted out of all those supports
    together at its first such pair (``_lift_off_supports``: a lift paid for
    by ``pay_for_lift``); the other overlapping pairs (side contacts, one
    level, a cluster no wall or static particle supports, a lift that would
    go into a wall) are pushed apart by inverse mass, m_a dx_a = -m_b dx_b,
    which keeps the centre of mass, so no pass lifts an unsupported cluster.
    Returns whether any pair overlapped. The records are unpacked once
    here: the helpers, called per pair, take plain arrays (a record handed
    on costs a reference count per array at every call), and each mover's
    pairs of a level are linked in visit order as they are measured.
    """
    position, velocity, radius, inv_mass = particles
    pair_first, pair_second = contacts.first, contacts.second
    bounds = (walls.present, walls.low, walls.high, walls.dimensions)
    pairs = (pair_first, pair_second, order)
    m, n = order.size, position.shape[0]
    mover = np.empty(m, dtype=np.int64)
    # Each mover's pairs of the current level, linked in visit order: the
    # first (head), the next after each (following), the last so far (tail).
    following = np.empty(m, dtype=np.int64)
    head = np.empty(n, dtype=np.int64)
    tail = np.empty(n, dtype=np.int64)
    linked_in = np.full(n, -1, dtype=np.int64)
    lifted = np.empty(m)
    lifted_in = np.full(n, -1, dtype=np.int64)
    any_overlap = False
    start = 0
    while start < m:
        key = min(level[pair_first[order[start]]], level[pair_second[order[start]]])
        end = start + 1
        while end < m and min(level[pair_first[order[end]]],
                              level[pair_second[order[end]]]) == key:
            end += 1
        for t in range(start, end):
            k = order[t]
            a, b = pair_first[k], pair_second[k]
            normal, depth = _pair_overlap(position, velocity, radius, a, b)
            mover[t] = -1
            if depth > 0.0:
                p = _mover(position, radius, inv_mass, a, b, normal, depth, level, bounds, up)
                mover[t] = p
                if p >= 0:
                    following[t] = -1
                    if linked_in[p] != start:
                        linked_in[p] = start
                        head[p] = t
                    else:
                        following[tail[p]] = t
                    tail[p] = t
        for t in range(start, end):
            p = mover[t]
            if p >= 0:
                any_overlap = True
                if lifted_in[p] == start:
                    continue
                lifted_in[p] = start
                _lift_off_supports(position, velocity, radius, pairs, p,
                                   (head[p], following), lifted)
                continue
            k = order[t]
            a, b = pair_first[k], pair_second[k]
            normal, depth = _pair_overlap(position, velocity, radius, a, b)
            if not depth > 0.0:
                continue
            any_overlap = True
            w_a, w_b = inv_mass[a], inv_mass[b]
            # Overlapping only since this level's earlier pushes: one above the
            # other, the one nearer a support still holds.
            alone = _mover(position, radius, inv_mass, a, b, normal, depth, level, bounds, up)
            if alone == a:
                w_b = 0.0
            elif alone == b:
                w_a = 0.0
            w_sum = w_a + w_b
            if not w_sum > 0.0:
                continue
            nx, ny, nz = normal
            push_a, push_b = depth * w_a / w_sum, depth * w_b / w_sum
            position[a, 0] += push_a * nx
            position[a, 1] += push_a * ny
            position[a, 2] += push_a * nz
            position[b, 0] += -(push_b * nx)
            position[b, 1] += -(push_b * ny)
            position[b, 2] += -(push_b * nz)
        start = end
    return any_overlap


@njit(cache=True, inline='always')
def _clamp_particle(position, radius, dynamic, walls, p):
    """Place dynamic particle ``p``, if past a wall plane, back on it, plane after plane."""
    if not dynamic[p]:
        return
    for q in range(walls.plane_axis.size):
        axis, plane = walls.plane_axis[q], walls.plane_value[q]
        inward = walls.plane_inward[q]
        if inward * (position[p, axis] - plane) < radius[p]:
            position[p, axis] = plane + inward * radius[p]


@njit(cache=True, nogil=True, parallel=True)
def _clamp_inside_shared(position, radius, dynamic, walls):
    """``_clamp_inside`` with the rows on the threads (a particle's planes in the same order)."""
    for p in prange(position.shape[0]):
        _clamp_particle(position, radius, dynamic, walls, p)


@njit(cache=True)
def _clamp_inside(particles, dynamic, walls, shared, among):
    """Place dynamic particles found past a wall plane back on it, plane after plane.

    Each particle's clamps are its own, so the particles may go in any
    order: ``shared``, on the threads. ``among`` (known, particles): with
    known, only those particles (each once) can be past a plane, and only
    they are tested.
    """
    position, radius = particles.position, particles.radius
    if among[0]:
        for p in among[1]:
            _clamp_particle(position, radius, dynamic, walls, p)
        return
    if shared:
        _clamp_inside_shared(position, radius, dynamic, walls)
        return
    for p in range(position.shape[0]):
        _clamp_particle(position, radius, dynamic, walls, p)


@njit(cache=True)
def _clamp_candidates(near, contacts, listed, seen):
    """Return (known, particles): ``near``'s particles and the ``listed`` contacts', each once.

    Only these can be past a wall plane after the projection when ``near``
    (known, particles) lists every particle near a plane before it
    (``StepContext.near_walls``) and the projection moves the particles of
    the ``listed`` contacts only. Each particle's clamp is its own, so
    their order does not matter. ``seen`` (n,) is False on entry and exit.
    """
    if not near[0]:
        return near
    rows = np.empty(near[1].size + 2 * listed.size, dtype=np.int64)
    kept = _add_unseen(near[1], seen, rows, 0)
    for k in listed:
        kept = _add_unseen((contacts.first[k], contacts.second[k]), seen, rows, kept)
    for t in range(kept):
        seen[rows[t]] = False
    return True, rows[:kept].copy()


@njit(cache=True, inline='always')
def _add_unseen(group, seen, rows, kept):
    """Append the particles of ``group`` not seen yet to ``rows`` from ``kept``; return the end."""
    for p in group:
        if not seen[p]:
            seen[p] = True
            rows[kept] = p
            kept += 1
    return kept


@njit(cache=True)
def _overlapping(penetration):
    """Return the contacts that overlap (penetration > 0), ascending."""
    listed = np.empty(penetration.size, dtype=np.int64)
    count = 0
    for k in range(penetration.size):
        if penetration[k] > 0.0:
            listed[count] = k
            count += 1
    return listed[:count]


@njit(cache=True, nogil=True)
def project_overlaps(particles, dynamic, contacts, walls, floors, up, passes, hold, in_turn,
                     shared, near, work):
    """Run the separation stage's projection on ``particles.position`` in place.

    ``passes`` Jacobi passes: the first on the narrowphase's normals and
    penetrations (the pairs that overlap: speculative ones have a negative
    penetration), each later one on the pairs still overlapping, measured
    again; with walls present the particles are clamped back inside after
    each pass. ``hold``: a particle its push would take into a wall stays
    put. ``floors``: per wall plane, whether it holds particles up against
    gravity, and ``up`` the unit vector against it (any unit vector without
    gravity). ``in_turn`` (under gravity): Gauss-Seidel passes instead
    (``_separate_in_turn``), the pairs nearest a support first, stopping
    early once no pair overlaps. ``shared``: the wall clamps run on the
    threads (the same positions). ``near`` (known, particles): with known,
    every particle near a wall plane (``StepContext.near_walls``): the clamps
    test those and the contacts' particles only (the same positions).
    ``work`` (``ProjectionWork``, n rows) is left clean. One pass reads
    the overlapping contacts only.
    """
    position, velocity, radius = particles.position, particles.velocity, particles.radius
    pair_first, pair_second = contacts.first, contacts.second
    m = pair_first.size
    if passes == 1 and not in_turn:
        # One pass moves only the particles of the contacts that overlap now.
        listed = _overlapping(contacts.penetration)
        among = _clamp_candidates(near, contacts, listed, work.seen)
        if listed.size:
            _separate_pass(particles, contacts, listed, hold, walls, work)
        if walls.present:
            _clamp_inside(particles, dynamic, walls, shared, among)
        return
    among = _clamp_candidates(near, contacts, np.arange(m), work.seen)
    if in_turn:
        level = support_levels(particles, dynamic, contacts, walls, floors)
        order = support_order(contacts, level)
        for _ in range(passes):
            overlapped = (_separate_in_turn(particles, contacts, order, level, walls, up)
                          if m else False)
            if walls.present:
                _clamp_inside(particles, dynamic, walls, shared, among)
            if not overlapped:
                break
        return
    current = ContactArrays(pair_first, pair_second, contacts.normal.copy(),
                            contacts.penetration.copy())
    normal, penetration = current.normal, current.penetration
    for step in range(passes):
        if m:
            if step > 0:
                overlapping = False
                for k in range(m):
                    a, b = pair_first[k], pair_second[k]
                    nx, ny, nz, distance = line_of_action(
                        position[a, 0] - position[b, 0], position[a, 1] - position[b, 1],
                        position[a, 2] - position[b, 2], velocity[a, 0] - velocity[b, 0],
                        velocity[a, 1] - velocity[b, 1], velocity[a, 2] - velocity[b, 2])
                    normal[k, 0], normal[k, 1], normal[k, 2] = nx, ny, nz
                    penetration[k] = radius[a] + radius[b] - distance
                    overlapping = overlapping or penetration[k] > 0.0
                if not overlapping and not walls.present:
                    return
            _separate_pass(particles, current, _overlapping(penetration), hold, walls, work)
        if walls.present:
            _clamp_inside(particles, dynamic, walls, shared, among)


@njit(cache=True, nogil=True)
def pay_for_lift(particles, dynamic, pair_first, pair_second, start, added, budget):
    """Take back what the projection's net lift adds per cluster; return J removed per particle.

    ``added`` is the potential energy the projection gave each particle and
    ``budget`` the energy removed from it in this step, J; ``start`` the
    positions before the projection. Clusters are the connected components
    of the pairs between two dynamic particles; sums per cluster run in
    particle order, as numpy's ``bincount``. A lift beyond the cluster's
    budget is paid from the lifted particle's speed along its push; what the
    speed cannot pay is not lifted (``particles.position`` goes back along
    the push by that fraction of it). Velocities change in place.
    """
    position, velocity, inv_mass = particles.position, particles.velocity, particles.inv_mass
    n = position.shape[0]
    parent = np.arange(n)
    for k in range(pair_first.size):
        a, b = pair_first[k], pair_second[k]
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
    particles = ParticleArrays(np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]]),
                               np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]), np.ones(2),
                               np.ones(2))
    dynamic = np.ones(2, dtype=bool)
    pair_first, pair_second = np.array([1], dtype=np.int64), np.array([0], dtype=np.int64)
    contacts = ContactArrays(pair_first, pair_second, np.array([[1.0, 0.0, 0.0]]),
                             np.array([0.1]))
    walls = WallBounds(True, np.full(3, -10.0), np.full(3, 10.0), 3,
                       np.zeros(1, dtype=np.int64), np.full(1, -10.0), np.ones(1))
    start = particles.position.copy()
    for in_turn, passes in ((False, 1), (False, 2), (True, 2)):
        for near in ((False, np.zeros(0, dtype=np.int64)), (True, np.arange(1))):
            project_overlaps(particles, dynamic, contacts, walls, np.ones(1, dtype=np.bool_),
                             (0.0, 1.0, 0.0), passes, True, in_turn, False, near,
                             projection_work(2))
    pay_for_lift(particles, dynamic, pair_first, pair_second, start, np.ones(2), np.zeros(2))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [project_overlaps, pay_for_lift]
