"""Resting contact for the ``exact`` preset, compiled: which particles rest, on what, how.

Under gravity a particle resting on a wall or on other particles would meet
its support again at once, with zero speed, again and again: no event list
can step through that. So at the start of each step the event stage
(``event_driven.py``) asks this module which contacts rest and gives each
particle the constant acceleration its supports leave it, for the whole step:

1. **Resting contacts** (``collect``): pairs and walls touching at the
   step's start (a gap at most ``RESTING_GAP`` of the two radii plus
   ``RESTING_ULPS`` spacings of the coordinates involved; overlaps count)
   whose normal speed, either way, is below the resting speed (the contact
   law's restitution threshold: the declared one, or 2 |g| dt).
2. **Their normal velocities are set to zero** (``project_velocities``) by
   normal impulses (the law's ``push_pair`` and its wall twin) in
   over-relaxed, then plain Gauss-Seidel sweeps, until no resting contact
   moves faster than the tolerance. Each increment's kinetic energy is
   booked to its contact (restitution for pairs, walls for walls).
3. **Support forces** (``support_forces``): the frictionless contact
   problem on accelerations (a = g + forces / m; at every resting contact
   relative normal acceleration >= 0, force >= 0, one of them 0) by
   projected Gauss-Seidel started from the previous step's forces. A
   particle whose acceleration is not g is *supported* (``Supports``).

Within the step a supported particle follows its own parabola; its resting
contacts are not predicted (they neither close nor open), and an impact
that would change a support's normal speed ends the step's exact attempt
(the stage falls back). With the supports fixed for the step this is exact
for a column or a packed pile at rest and first order in dt for a cluster
that slides.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from ...law.primitives import dot3, push_pair, line_of_action  # noqa: I100
from numba import njit  # noqa: E402,I100
from ...model.tunables import (RESTING_GAP, RESTING_ULPS, PARTNERS, OVER_RELAXATION,
                               MAX_SWEEPS)

_EPSILON = 2.220446049250313e-16
# Status: the supports are found; or a particle has more resting partners than PARTNERS.
FOUND, TOO_MANY = 0, 1
# How the sweeps went (one row): sweeps of each solve and what each left.
SWEEPS = np.dtype([
    ('velocity_sweeps', np.int64),
    ('force_sweeps', np.int64),
    ('speed_left', np.float64),          # m/s: the largest normal speed left
    ('acceleration_left', np.float64),   # m/s^2: the largest relative acceleration change left
])


class RestingContacts(NamedTuple):
    """Room for the resting contacts (every candidate pair and 2 dims walls per particle)."""

    first: np.ndarray           # (m,) int64: a particle
    second: np.ndarray          # (m,) int64: the other particle, or -2 - face for a wall
    normal: np.ndarray          # (m, 3): from second to first (a wall's: inward)


class Supports(NamedTuple):
    """Each particle's acceleration for the step and what it rests on (no rows: none)."""

    acceleration: np.ndarray    # (n, 3) m/s^2: g + its support forces / m (0: static)
    supported: np.ndarray       # (n,) int64: 1 when its acceleration is not g
    wall_mask: np.ndarray       # (n,) int64: a bit per wall it rests on (bit = 2 axis + side)
    partners: np.ndarray        # (n, PARTNERS) int64: particles, a wall as -2 - face; -1 ends


def new_supports(n: int) -> Supports:
    """Return supports for ``n`` particles: nobody supported, every acceleration 0."""
    return Supports(np.zeros((n, 3)), np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64),
                    np.full((n, PARTNERS), -1, dtype=np.int64))


@njit(cache=True, inline='always')
def _spacing(x):
    """Return about the floating-point spacing at coordinate ``x`` (eps |x|)."""
    return _EPSILON * abs(x)


@njit(cache=True, nogil=True)
def collect(position, velocity, inv_mass, radius, pair_first, pair_second, low_walls,
            high_walls, dimensions, rest_speed, contacts):
    """Write the resting contacts into ``contacts``; return their count.

    Pairs come from the candidate pairs (N from second to first); a wall
    contact has second = -2 - face (face = 2 axis + side, side 1 the high
    wall) and N its inward normal.
    """
    first, second, normal = contacts.first, contacts.second, contacts.normal
    m = 0
    for k in range(pair_first.shape[0]):
        i, j = pair_first[k], pair_second[k]
        if inv_mass[i] == 0.0 and inv_mass[j] == 0.0:
            continue
        dx = position[i, 0] - position[j, 0]
        dy = position[i, 1] - position[j, 1]
        dz = position[i, 2] - position[j, 2]
        rx = velocity[i, 0] - velocity[j, 0]
        ry = velocity[i, 1] - velocity[j, 1]
        rz = velocity[i, 2] - velocity[j, 2]
        nx, ny, nz, dist = line_of_action(dx, dy, dz, rx, ry, rz)
        reach = radius[i] + radius[j]
        coordinate = 0.0
        for c in range(3):
            coordinate = max(coordinate, abs(position[i, c]), abs(position[j, c]))
        tolerance = RESTING_GAP * reach + RESTING_ULPS * _spacing(coordinate)
        if dist - reach > tolerance:
            continue
        if abs(dot3(rx, ry, rz, nx, ny, nz)) > rest_speed:
            continue
        first[m], second[m] = i, j
        normal[m, 0], normal[m, 1], normal[m, 2] = nx, ny, nz
        m += 1
    n = position.shape[0]
    for p in range(n):
        if inv_mass[p] == 0.0:
            continue
        for axis in range(dimensions):
            for side in range(2):
                plane = high_walls[axis] if side else low_walls[axis]
                if not math.isfinite(plane):
                    continue
                inward = -1.0 if side else 1.0
                gap = inward * (position[p, axis] - plane) - radius[p]
                tolerance = RESTING_GAP * radius[p] + RESTING_ULPS * _spacing(
                    max(abs(position[p, axis]), abs(plane)))
                if gap > tolerance or abs(velocity[p, axis]) > rest_speed:
                    continue
                first[m], second[m] = p, -2 - (2 * axis + side)
                normal[m, 0] = normal[m, 1] = normal[m, 2] = 0.0
                normal[m, axis] = inward
                m += 1
    return m


@njit(cache=True, inline='always')
def _wall_axis(code):
    """Return the axis of a wall contact's code (second = -2 - face)."""
    return (-2 - code) // 2


@njit(cache=True, inline='always')
def _normal_part(rate, inv_mass, i, j, nx, ny, nz):
    """Return contact (i, j)'s relative normal rate (velocity or acceleration) and its 1/m sum.

    Positive opens the contact; a wall (j < 0) is static, its N an axis.
    """
    if j >= 0:
        return (dot3(rate[i, 0] - rate[j, 0], rate[i, 1] - rate[j, 1], rate[i, 2] - rate[j, 2],
                     nx, ny, nz), inv_mass[i] + inv_mass[j])
    return (nx + ny + nz) * rate[i, _wall_axis(j)], inv_mass[i]


@njit(cache=True)
def _push_wall(v, inv_mass, p, axis, inward, magnitude):
    """Apply a normal impulse increment ``magnitude`` (either sign) from a wall to ``p``.

    Returns the energy it removed, J (``push_pair`` with a static partner).
    """
    before = inward * v[p, axis]
    v[p, axis] += inward * (magnitude * inv_mass[p])
    after = before + inv_mass[p] * magnitude
    return -(magnitude * 0.5 * (before + after))


@njit(cache=True, nogil=True)
def project_velocities(velocity, inv_mass, contacts, m, tolerance, removed, info):
    """Set the first ``m`` contacts' normal speeds to zero (either way); book what it removes.

    ``removed[k]`` (J) sums contact k's increments. Over-relaxed, then plain
    Gauss-Seidel sweeps until no normal speed exceeds ``tolerance`` (m/s)
    (or ``MAX_SWEEPS`` of each).
    """
    for k in range(m):
        removed[k] = 0.0
    sweeps = 0
    for relaxation in (OVER_RELAXATION, 1.0):
        sweeps += _velocity_sweeps(velocity, inv_mass, contacts, m, tolerance, removed,
                                   relaxation, info)
    info[0].velocity_sweeps = sweeps


@njit(cache=True)
def _velocity_sweeps(velocity, inv_mass, contacts, m, tolerance, removed, relaxation, info):
    """Run ``project_velocities``' sweeps at one relaxation; return how many."""
    first, second, normal = contacts.first, contacts.second, contacts.normal
    sweeps, left = 0, 0.0
    while sweeps < MAX_SWEEPS:
        sweeps += 1
        left = 0.0
        for k in range(m):
            i, j = first[k], second[k]
            nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
            speed, w = _normal_part(velocity, inv_mass, i, j, nx, ny, nz)
            if speed == 0.0:
                continue
            left = max(left, abs(speed))
            magnitude = -relaxation * speed / w
            if j >= 0:
                removed[k] += push_pair(velocity, inv_mass, i, j, nx, ny, nz, magnitude,
                                        -speed)
            else:
                removed[k] += _push_wall(velocity, inv_mass, i, _wall_axis(j), nx + ny + nz,
                                         magnitude)
        if left <= tolerance:
            break
    info[0].speed_left = left
    return sweeps


@njit(cache=True, nogil=True)
def support_forces(acceleration, inv_mass, gravity, contacts, m, force, tolerance, info):
    """Solve the first ``m`` contacts' forces (N) and each particle's acceleration (m/s^2).

    ``force[k]`` comes in as the warm start (clamped at 0) and leaves as the
    solution; ``acceleration`` leaves as g + the contact forces / m (0 for a
    static particle). Projected over-relaxed, then plain Gauss-Seidel sweeps
    until no force changes a relative acceleration by more than
    ``tolerance`` (m/s^2) (or ``MAX_SWEEPS`` of each); then the
    accelerations are summed afresh from the forces, so that the round-off
    of thousands of increments does not stay in them.
    """
    first, second = contacts.first, contacts.second
    n = acceleration.shape[0]
    for p in range(n):
        for c in range(3):
            acceleration[p, c] = gravity[c] if inv_mass[p] > 0.0 else 0.0
    for k in range(m):
        force[k] = max(force[k], 0.0)
        if force[k] > 0.0:
            _apply_force(acceleration, inv_mass, first[k], second[k], contacts.normal, k,
                         force[k])
    sweeps = 0
    for relaxation in (OVER_RELAXATION, 1.0):
        sweeps += _force_sweeps(acceleration, inv_mass, contacts, m, force, tolerance,
                                relaxation, info)
    info[0].force_sweeps = sweeps
    for p in range(n):
        for c in range(3):
            acceleration[p, c] = gravity[c] if inv_mass[p] > 0.0 else 0.0
    for k in range(m):
        if force[k] > 0.0:
            _apply_force(acceleration, inv_mass, first[k], second[k], contacts.normal, k,
                         force[k])


@njit(cache=True)
def _force_sweeps(acceleration, inv_mass, contacts, m, force, tolerance, relaxation, info):
    """Run ``support_forces``' sweeps at one relaxation; return how many."""
    first, second, normal = contacts.first, contacts.second, contacts.normal
    sweeps, left = 0, 0.0
    while sweeps < MAX_SWEEPS:
        sweeps += 1
        left = 0.0
        for k in range(m):
            i, j = first[k], second[k]
            nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
            opening, w = _normal_part(acceleration, inv_mass, i, j, nx, ny, nz)
            new = max(force[k] - relaxation * opening / w, 0.0)
            change = new - force[k]
            if change == 0.0:
                continue
            left = max(left, abs(change) * w)
            force[k] = new
            _apply_force(acceleration, inv_mass, i, j, normal, k, change)
        if left <= tolerance:
            break
    info[0].acceleration_left = left
    return sweeps


@njit(cache=True, inline='always')
def _apply_force(acceleration, inv_mass, i, j, normal, k, change):
    """Add a force ``change`` (N) along contact k's normal to its particles' accelerations."""
    if j >= 0:
        ka, kb = change * inv_mass[i], change * inv_mass[j]
        for c in range(3):
            acceleration[i, c] += ka * normal[k, c]
            acceleration[j, c] -= kb * normal[k, c]
    else:
        axis = _wall_axis(j)
        acceleration[i, axis] += change * inv_mass[i] * normal[k, axis]


@njit(cache=True, nogil=True)
def warm_forces(contacts, m, old_partner, old_force, force):
    """Start each contact's force from the last step's on the same contact (0 if new)."""
    for k in range(m):
        force[k] = 0.0
        i, j = contacts.first[k], contacts.second[k]
        if i >= old_partner.shape[0]:
            continue
        for s in range(old_partner.shape[1]):
            if old_partner[i, s] == j:
                force[k] = old_force[i, s]
                break


@njit(cache=True, nogil=True)
def supports(inv_mass, gravity, contacts, m, force, found, partner_force):
    """Mark supported particles and their resting contacts in ``found``; return FOUND or TOO_MANY.

    ``found.acceleration`` holds the solved accelerations; a dynamic particle
    is supported when its acceleration is not g. Each contact with a
    supported particle on either side is listed at both (``partners``, -1
    padded; a wall as -2 - face, also in the bit mask ``wall_mask``), with
    its force in ``partner_force`` (the next step's warm start).
    """
    acceleration, supported, wall_mask = found.acceleration, found.supported, found.wall_mask
    partner = found.partners
    n = acceleration.shape[0]
    for p in range(n):
        supported[p] = 0
        wall_mask[p] = 0
        if inv_mass[p] > 0.0:
            for c in range(3):
                if acceleration[p, c] != gravity[c]:
                    supported[p] = 1
        for s in range(partner.shape[1]):
            partner[p, s] = -1
    status = FOUND
    for k in range(m):
        i, j = contacts.first[k], contacts.second[k]
        if j >= 0:
            if not (supported[i] or supported[j]):
                continue
            if not (_add_partner(partner, partner_force, i, j, force[k])
                    and _add_partner(partner, partner_force, j, i, force[k])):
                status = TOO_MANY
        elif supported[i]:
            wall_mask[i] |= 1 << (-2 - j)
            if not _add_partner(partner, partner_force, i, j, force[k]):
                status = TOO_MANY
    return status


@njit(cache=True, inline='always')
def _add_partner(partner, partner_force, p, q, value):
    """List q (with its contact's force) among p's resting partners; False if p's list is full."""
    for s in range(partner.shape[1]):
        if partner[p, s] < 0:
            partner[p, s] = q
            partner_force[p, s] = value
            return True
    return False


def new_contacts(size: int) -> RestingContacts:
    """Return room for ``size`` resting contacts."""
    return RestingContacts(np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64),
                           np.empty((size, 3)))


def warm_up() -> None:
    """Run the kernels once on a ball resting on a floor under another ball."""
    position = np.array([[0.0, 0.5, 0.0], [0.0, 1.5, 0.0]])
    velocity = np.array([[0.0, -0.01, 0.0], [0.0, 0.0, 0.0]])
    inv_mass, radius = np.ones(2), np.full(2, 0.5)
    low, high = np.array([-np.inf, 0.0, -np.inf]), np.full(3, np.inf)
    gravity = np.array([0.0, -9.81, 0.0])
    pair_first, pair_second = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    size = 1 + 2 * 2 * 3
    contacts = new_contacts(size)
    removed, force = np.empty(size), np.empty(size)
    info = np.zeros(1, dtype=SWEEPS)
    m = collect(position, velocity, inv_mass, radius, pair_first, pair_second, low, high, 3, 0.1,
                contacts)
    project_velocities(velocity, inv_mass, contacts, m, 1e-12, removed, info)
    found = new_supports(2)
    partner_force = np.zeros((2, PARTNERS))
    warm_forces(contacts, m, found.partners, partner_force, force)
    support_forces(found.acceleration, inv_mass, gravity, contacts, m, force, 1e-12, info)
    supports(inv_mass, gravity, contacts, m, force, found, partner_force)


def kernels() -> list:
    """Return the compiled kernels of this module (the ones a warm-up compiles)."""
    return [collect, project_velocities, support_forces, warm_forces, supports]
