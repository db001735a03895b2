"""Resting contact for the ``exact`` preset, compiled: which particles rest, on what, how.

Under gravity a particle resting on a wall or on other particles would
meet its support again at once, with zero speed, again and again: no
event list can step through that. So at the start of each step the event
stage (``stages/event_driven.py``) asks this module which contacts rest
and gives each particle the constant acceleration its supports leave it,
for the whole step:

1. **Resting contacts**: pairs and walls touching at the step's start (a
   gap at most ``RESTING_GAP`` of the two radii plus ``RESTING_ULPS``
   spacings of the coordinates involved; overlaps count) whose normal
   speed, either way, is below the resting speed (the contact law's
   restitution threshold: the declared one, or 2 |g| dt under gravity).
2. **Their normal velocities are set to zero**, by normal impulses
   (``contact_kernels._push_pair``, the law's pair increment, and its wall
   twin) in over-relaxed sweeps, then plain Gauss-Seidel ones, until no
   resting contact moves faster than ``VELOCITY_TOLERANCE`` of the resting
   speed. Each increment takes kinetic energy out (an increment of w times
   the one that stops the contact removes w (1 - w/2) of that contact's
   normal energy: some for 0 < w < 2) and books it to its contact
   (restitution for pairs, walls for walls).
3. **Support forces**: the frictionless contact problem on accelerations
   (each particle's acceleration a = g + the forces on it / m; at every
   resting contact the relative normal acceleration >= 0, the force >= 0,
   one of them 0), solved by projected Gauss-Seidel (over-relaxed, then
   plain) started from the previous step's forces; the accelerations are
   then summed afresh from the forces. A particle whose acceleration is
   not g is *supported*.

Within the step a supported particle follows its own parabola
x0 + v0 t + a t^2 / 2; its resting contacts (with a supported particle
on either side) are not predicted (their normal relative velocity and
acceleration are zero: they neither close nor open), and an impact that
would change a support's normal speed ends the step's exact attempt (the
stage then falls back, counted). With the supports fixed for the step this is
exact for a column or a packed pile at rest and first order in dt for a
cluster that slides (its contact normals turn within the step).
"""

from __future__ import annotations

import math

import numpy as np

from . import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from .contact_kernels import _dot, _push_pair, line_of_action  # noqa: I100
from numba import njit  # noqa: E402,I100

# A contact rests when its gap is at most this fraction of r_i + r_j ...
RESTING_GAP = 1e-9
# ... plus this many floating-point spacings of the largest coordinate involved.
RESTING_ULPS = 64.0
_EPSILON = 2.220446049250313e-16
# Resting partners a particle can hold (12 touch an equal sphere in 3-D;
# overlapping or mixed sizes can touch more). More ends the exact attempt.
PARTNERS = 16
# Both solves sweep over-relaxed to their tolerance, then plainly (Gauss-
# Seidel) to it again: a chain or a pile of n rows needs about n^2 plain
# sweeps but about n over-relaxed ones (the 500-disc pile: 2,000 to 5,000
# plain sweeps a step, measured), and the plain ones leave a lone contact
# solved exactly (a ball on a floor: speed and acceleration exactly 0).
OVER_RELAXATION = 1.6
# Sweeps end when no resting normal speed exceeds this fraction of the
# resting speed, and when no force changes any relative acceleration by
# more than this fraction of |g|; at most MAX_SWEEPS of each.
# (1e-11 |g| leaves a packed pile sinking into itself by ½ 1e-10 dt^2,
# 1e-15 m a step at 240 Hz; 1e-13 |g| cost the 500-disc pile 3 to 6 times
# the sweeps.)
VELOCITY_TOLERANCE = 1e-12
ACCELERATION_TOLERANCE = 1e-11
MAX_SWEEPS = 20000
# Status: the supports are found; or a particle has more resting partners than PARTNERS.
FOUND, TOO_MANY = 0, 1
# Columns of ``info`` (float64): velocity sweeps, force sweeps, largest
# normal speed left (m/s), largest relative acceleration change left (m/s^2).
I_V_SWEEPS, I_A_SWEEPS, I_V_LEFT, I_A_LEFT = range(4)
INFO_SIZE = 4


@njit(cache=True, inline='always')
def _spacing(x):
    """Return about the floating-point spacing at coordinate ``x`` (eps |x|)."""
    return _EPSILON * abs(x)


@njit(cache=True, nogil=True)
def collect(position, velocity, inv_mass, radius, cand_i, cand_j, low, high, dims,
            rest_speed, c_i, c_j, c_normal):
    """Write the resting contacts into (c_i, c_j, c_normal); return their count.

    Pairs come from the candidates (i, j) (N from j to i); a wall contact
    has c_j = -2 - face (face = 2 axis + side, side 1 the high wall) and N
    its inward normal. ``c_*`` hold room for every candidate and 2 dims walls
    per particle.
    """
    m = 0
    for k in range(cand_i.shape[0]):
        i, j = cand_i[k], cand_j[k]
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
        if abs(_dot(rx, ry, rz, nx, ny, nz)) > rest_speed:
            continue
        c_i[m], c_j[m] = i, j
        c_normal[m, 0], c_normal[m, 1], c_normal[m, 2] = nx, ny, nz
        m += 1
    n = position.shape[0]
    for p in range(n):
        if inv_mass[p] == 0.0:
            continue
        for axis in range(dims):
            for side in range(2):
                plane = high[axis] if side else low[axis]
                if not math.isfinite(plane):
                    continue
                inward = -1.0 if side else 1.0
                gap = inward * (position[p, axis] - plane) - radius[p]
                tolerance = RESTING_GAP * radius[p] + RESTING_ULPS * _spacing(
                    max(abs(position[p, axis]), abs(plane)))
                if gap > tolerance or abs(velocity[p, axis]) > rest_speed:
                    continue
                c_i[m], c_j[m] = p, -2 - (2 * axis + side)
                c_normal[m, 0] = c_normal[m, 1] = c_normal[m, 2] = 0.0
                c_normal[m, axis] = inward
                m += 1
    return m


@njit(cache=True, inline='always')
def _wall_axis(code):
    """Return the axis of a wall contact's code (c_j = -2 - face)."""
    return (-2 - code) // 2


@njit(cache=True, inline='always')
def _normal_part(rate, inv_mass, i, j, nx, ny, nz):
    """Return contact (i, j)'s relative normal rate (velocity or acceleration) and its 1/m sum.

    Positive opens the contact; a wall (j < 0) is static, its N an axis.
    """
    if j >= 0:
        return (_dot(rate[i, 0] - rate[j, 0], rate[i, 1] - rate[j, 1], rate[i, 2] - rate[j, 2],
                     nx, ny, nz), inv_mass[i] + inv_mass[j])
    return (nx + ny + nz) * rate[i, _wall_axis(j)], inv_mass[i]


@njit(cache=True)
def _push_wall(v, inv_mass, p, axis, inward, magnitude):
    """Apply a normal impulse increment ``magnitude`` (either sign) from a wall to ``p``.

    Returns the energy it removed, J (``_push_pair`` with a static partner).
    """
    before = inward * v[p, axis]
    v[p, axis] += inward * (magnitude * inv_mass[p])
    after = before + inv_mass[p] * magnitude
    return -(magnitude * 0.5 * (before + after))


@njit(cache=True, nogil=True)
def project_velocities(velocity, inv_mass, m, c_i, c_j, c_normal, tolerance, removed, info):
    """Set every resting contact's normal speed to zero (either way); book what it removes.

    ``removed[k]`` (J) sums contact k's increments. Over-relaxed, then plain
    Gauss-Seidel sweeps until no normal speed exceeds ``tolerance`` (m/s)
    (or ``MAX_SWEEPS`` of each).
    """
    for k in range(m):
        removed[k] = 0.0
    sweeps = 0
    for relaxation in (OVER_RELAXATION, 1.0):
        sweeps += _velocity_sweeps(velocity, inv_mass, m, c_i, c_j, c_normal, tolerance,
                                   removed, relaxation, info)
    info[I_V_SWEEPS] = sweeps


@njit(cache=True)
def _velocity_sweeps(velocity, inv_mass, m, c_i, c_j, c_normal, tolerance, removed, relaxation,
                     info):
    """Run ``project_velocities``' sweeps at one relaxation; return how many."""
    sweeps, left = 0, 0.0
    while sweeps < MAX_SWEEPS:
        sweeps += 1
        left = 0.0
        for k in range(m):
            i, j = c_i[k], c_j[k]
            nx, ny, nz = c_normal[k, 0], c_normal[k, 1], c_normal[k, 2]
            speed, w = _normal_part(velocity, inv_mass, i, j, nx, ny, nz)
            if speed == 0.0:
                continue
            left = max(left, abs(speed))
            magnitude = -relaxation * speed / w
            if j >= 0:
                removed[k] += _push_pair(velocity, inv_mass, i, j, nx, ny, nz, magnitude,
                                         -speed)
            else:
                removed[k] += _push_wall(velocity, inv_mass, i, _wall_axis(j), nx + ny + nz,
                                         magnitude)
        if left <= tolerance:
            break
    info[I_V_LEFT] = left
    return sweeps


@njit(cache=True, nogil=True)
def support_forces(accel, inv_mass, gravity, m, c_i, c_j, c_normal, force, tolerance, info):
    """Solve the resting contacts' forces (N) and each particle's acceleration (m/s^2).

    ``force[k]`` comes in as the warm start (clamped at 0) and leaves as the
    solution; ``accel`` leaves as g + the contact forces / m (0 for a static
    particle). Projected over-relaxed, then plain Gauss-Seidel sweeps until
    no force changes a relative acceleration by more than ``tolerance``
    (m/s^2) (or ``MAX_SWEEPS`` of each);
    then the accelerations are summed afresh from the forces, so that the
    round-off of thousands of increments does not stay in them.
    """
    n = accel.shape[0]
    for p in range(n):
        for c in range(3):
            accel[p, c] = gravity[c] if inv_mass[p] > 0.0 else 0.0
    for k in range(m):
        force[k] = max(force[k], 0.0)
        if force[k] > 0.0:
            _apply_force(accel, inv_mass, c_i[k], c_j[k], c_normal, k, force[k])
    sweeps = 0
    for relaxation in (OVER_RELAXATION, 1.0):
        sweeps += _force_sweeps(accel, inv_mass, m, c_i, c_j, c_normal, force, tolerance,
                                relaxation, info)
    info[I_A_SWEEPS] = sweeps
    for p in range(n):
        for c in range(3):
            accel[p, c] = gravity[c] if inv_mass[p] > 0.0 else 0.0
    for k in range(m):
        if force[k] > 0.0:
            _apply_force(accel, inv_mass, c_i[k], c_j[k], c_normal, k, force[k])


@njit(cache=True)
def _force_sweeps(accel, inv_mass, m, c_i, c_j, c_normal, force, tolerance, relaxation, info):
    """Run ``support_forces``' sweeps at one relaxation; return how many."""
    sweeps, left = 0, 0.0
    while sweeps < MAX_SWEEPS:
        sweeps += 1
        left = 0.0
        for k in range(m):
            i, j = c_i[k], c_j[k]
            nx, ny, nz = c_normal[k, 0], c_normal[k, 1], c_normal[k, 2]
            opening, w = _normal_part(accel, inv_mass, i, j, nx, ny, nz)
            new = max(force[k] - relaxation * opening / w, 0.0)
            change = new - force[k]
            if change == 0.0:
                continue
            left = max(left, abs(change) * w)
            force[k] = new
            _apply_force(accel, inv_mass, i, j, c_normal, k, change)
        if left <= tolerance:
            break
    info[I_A_LEFT] = left
    return sweeps


@njit(cache=True, inline='always')
def _apply_force(accel, inv_mass, i, j, c_normal, k, change):
    """Add a force ``change`` (N) along contact k's normal to its particles' accelerations."""
    if j >= 0:
        ka, kb = change * inv_mass[i], change * inv_mass[j]
        for c in range(3):
            accel[i, c] += ka * c_normal[k, c]
            accel[j, c] -= kb * c_normal[k, c]
    else:
        axis = _wall_axis(j)
        accel[i, axis] += change * inv_mass[i] * c_normal[k, axis]


@njit(cache=True, nogil=True)
def warm_forces(m, c_i, c_j, old_partner, old_force, force):
    """Start each contact's force from the last step's on the same contact (0 if new)."""
    for k in range(m):
        force[k] = 0.0
        i, j = c_i[k], c_j[k]
        if i >= old_partner.shape[0]:
            continue
        for s in range(old_partner.shape[1]):
            if old_partner[i, s] == j:
                force[k] = old_force[i, s]
                break


@njit(cache=True, nogil=True)
def supports(accel, inv_mass, gravity, m, c_i, c_j, force, supported, partner, partner_force,
             wall_mask):
    """Mark supported particles and their resting contacts; return FOUND or TOO_MANY.

    A dynamic particle is supported when its acceleration is not g. Each
    contact with a supported particle on either side is listed at both
    (``partner``, -1 padded; a wall as -2 - face, also in the bit mask
    ``wall_mask``), with its force (the next step's warm start).
    """
    n = accel.shape[0]
    for p in range(n):
        supported[p] = 0
        wall_mask[p] = 0
        if inv_mass[p] > 0.0:
            for c in range(3):
                if accel[p, c] != gravity[c]:
                    supported[p] = 1
        for s in range(partner.shape[1]):
            partner[p, s] = -1
    status = FOUND
    for k in range(m):
        i, j = c_i[k], c_j[k]
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


def warm_up() -> None:
    """Run the kernels once on a ball resting on a floor under another ball."""
    position = np.array([[0.0, 0.5, 0.0], [0.0, 1.5, 0.0]])
    velocity = np.array([[0.0, -0.01, 0.0], [0.0, 0.0, 0.0]])
    inv_mass, radius = np.ones(2), np.full(2, 0.5)
    low, high = np.array([-np.inf, 0.0, -np.inf]), np.full(3, np.inf)
    gravity = np.array([0.0, -9.81, 0.0])
    cand_i, cand_j = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    size = 1 + 2 * 2 * 3
    c_i, c_j = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64)
    c_normal, removed, force = np.empty((size, 3)), np.empty(size), np.empty(size)
    info = np.zeros(INFO_SIZE)
    m = collect(position, velocity, inv_mass, radius, cand_i, cand_j, low, high, 3, 0.1, c_i,
                c_j, c_normal)
    project_velocities(velocity, inv_mass, m, c_i, c_j, c_normal, 1e-12, removed, info)
    partner = np.full((2, PARTNERS), -1, dtype=np.int64)
    partner_force = np.zeros((2, PARTNERS))
    warm_forces(m, c_i, c_j, partner, partner_force, force)
    accel = np.empty((2, 3))
    support_forces(accel, inv_mass, gravity, m, c_i, c_j, c_normal, force, 1e-12, info)
    supports(accel, inv_mass, gravity, m, c_i, c_j, force, np.zeros(2, dtype=np.int64),
             partner, partner_force, np.zeros(2, dtype=np.int64))


def kernels() -> list:
    """Return the compiled kernels of this module (the ones a warm-up compiles)."""
    return [collect, project_velocities, support_forces, warm_forces, supports]
