"""The walls stage's law, compiled: every plane of a box in one pass over the particles.

``wall_pass`` reflects each particle found past a plane on the step's
path (the law of ``walls.py``), visiting each particle's planes in the
stage's order (a particle's result at one plane depends only on its own
state, so particle by particle is the same as plane by plane). It returns
one row per particle found past a plane, sorted plane by plane (put-back
rows, then impacts) and by particle within each, so the stage books the
energy and records the impacts plane by plane, in the order the vectorised
reference does (``test/test_wall_kernels.py`` asserts identical states
and bookings). In the same pass it lists the dynamic particles near a
plane as it leaves them (``WallRows.near``): the contact solve and the
separation stage then test those against the walls instead of every
particle.
"""

from __future__ import annotations

import math

import numpy as np

from typing import NamedTuple

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit, prange  # noqa: E402,I100 (after the cache directory is chosen)

from ...law.primitives import Bodies, combined_coefficient, pair_friction  # noqa: E402

# Columns of the float rows ``wall_pass`` returns.
WALLS_LOSS, FRICTION_LOSS, BACK, NORMAL_IMPULSE, TANGENTIAL, APPROACH, POINT = range(7)
FLOAT_COLUMNS = POINT + 3
# Columns of the integer rows: plane index, particle, 1 for an impact (0: put back).
PLANE, PARTICLE, IMPACT = range(3)


class WallPlanes(NamedTuple):
    """Axis-aligned wall planes, in the order the stages visit them."""

    axis: np.ndarray     # (planes,) int64: 0, 1 or 2
    value: np.ndarray    # (planes,) m: the plane's coordinate on its axis
    inward: np.ndarray   # (planes,) +1 or -1: the side particles stay on
    ulps: np.ndarray     # (planes,) m: WALL_ULPS float spacings at the coordinate


class WallCoefficients(NamedTuple):
    """Restitution and friction at the walls (per particle where a particle has its own)."""

    own_restitution: np.ndarray  # (n,) NaN: none; empty when no particle has one
    restitution: float           # the walls' e
    own_friction: np.ndarray     # (n,) likewise for mu
    friction: float              # the walls' mu


class WallMotion(NamedTuple):
    """The step the particles moved along, and how the pass treats it."""

    friction: bool           # Coulomb friction with spin at each impact
    has_gravity: bool
    gravity: np.ndarray      # (3,) m/s^2 (read only with has_gravity)
    dt: float                # s
    threshold: float         # m/s: the restitution threshold (0: none)
    planar: bool             # a 2-D scene
    near_slop: float         # ``near``: of its radius, plus the largest ulps and near_ahead
    near_ahead: float        # m


class WallRows(NamedTuple):
    """The rows of ``wall_pass``: one per particle past a plane, sorted plane by plane."""

    floats: np.ndarray       # (rows, FLOAT_COLUMNS)
    ints: np.ndarray         # (rows, 3): PLANE, PARTICLE, IMPACT
    group_start: np.ndarray  # (2 planes + 1,)
    near: np.ndarray         # (k,) int64: the dynamic particles near a plane, ascending


@njit(cache=True)
def _grow(floats, ints, count):
    """Return the row buffers doubled, holding their first ``count`` rows."""
    more_f = np.empty((2 * floats.shape[0], FLOAT_COLUMNS))
    more_i = np.empty((2 * ints.shape[0], 3), dtype=np.int64)
    more_f[:count] = floats[:count]
    more_i[:count] = ints[:count]
    return more_f, more_i


@njit(cache=True, nogil=True)
def wall_pass(bodies, position, planes, coefficients, motion, shared):
    """Reflect every particle found past a plane (``_wall_pass``); return ``WallRows``.

    ``bodies``, ``planes``, ``coefficients`` and ``motion`` are the records
    (``Bodies``, ``WallPlanes``, ``WallCoefficients``, ``WallMotion``) as
    plain tuples, ``tuple(record)``: numba types a plain tuple argument in
    its compiled dispatcher but a NamedTuple in Python, tens of
    microseconds a call. ``shared``: find the particles past a plane on the
    threads (the same rows).
    """
    return _wall_pass(Bodies(*bodies), position, WallPlanes(*planes),
                      WallCoefficients(*coefficients), WallMotion(*motion), shared)


@njit(cache=True, inline='always')
def _least_gap(position, radius, planes, p):
    """Return particle p's smallest gap to a plane, m (negative: past it)."""
    least = np.inf
    for k in range(planes.axis.size):
        least = min(least, planes.inward[k] * (position[p, planes.axis[k]] - planes.value[k])
                    - radius[p])
    return least


@njit(cache=True, nogil=True, parallel=True)
def _flag_near_shared(position, radius, planes, slop, ahead, flagged):
    """Set flagged[p] as ``_wall_pass`` does (a gap of at most slop r + ahead), on the threads."""
    axis, value, inward = planes.axis, planes.value, planes.inward
    for p in prange(position.shape[0]):
        close = False
        for k in range(axis.size):
            close |= inward[k] * (position[p, axis[k]] - value[k]) - radius[p] \
                <= slop * radius[p] + ahead
        flagged[p] = close


@njit(cache=True)
def _wall_pass(bodies, position, planes, coefficients, motion, shared):
    """Reflect every particle found past a plane, in place; return the rows of what happened.

    ``gravity`` counts only with ``has_gravity`` (else g_n = 0.0). Returns
    ``WallRows`` sorted by plane, then put back before impacts, then
    particle: plane k's put-back rows at group_start[2 k] ..
    group_start[2 k + 1] - 1, its impacts from there to
    group_start[2 k + 2] - 1. ``near`` lists every dynamic particle whose
    smallest gap to a plane is at most near_slop r + the largest ulps +
    near_ahead as the pass leaves it (a particle the pass moves is tested
    where it ends): each one within near_slop r + ulps[q] + near_ahead of
    some plane q, and a few more.
    """
    inv_mass, radius = bodies.inv_mass, bodies.radius
    axis, value, inward = planes.axis, planes.value, planes.inward
    n = position.shape[0]
    plane_count = axis.size
    ulps = 0.0
    for k in range(plane_count):
        ulps = max(ulps, planes.ulps[k])
    slop, ahead = motion.near_slop, ulps + motion.near_ahead
    floats = np.empty((64, FLOAT_COLUMNS))
    ints = np.empty((64, 3), dtype=np.int64)
    count = np.int64(0)
    # The particles near or past a plane as the step ends (branch-free passes;
    # the bound is >= 0, so every particle past a plane is flagged). Moving a
    # particle along one plane's axis changes no other particle's gaps.
    flagged = np.zeros(n, dtype=np.bool_)
    if shared:
        _flag_near_shared(position, radius, planes, slop, ahead, flagged)
    else:
        for k in range(plane_count):
            ax, plane, sign = axis[k], value[k], inward[k]
            for p in range(n):
                flagged[p] |= sign * (position[p, ax] - plane) - radius[p] \
                    <= slop * radius[p] + ahead
    listed = np.empty(n, dtype=np.int64)
    near_count = 0
    for p in range(n):
        if not flagged[p] or not inv_mass[p] > 0.0:   # static (``ParticleState.dynamic``)
            continue
        gap = _least_gap(position, radius, planes, p)
        if gap < 0.0:
            count, floats, ints = _reflect(bodies, position, planes, coefficients, motion, p,
                                           count, floats, ints)
            # Moved along its planes' axes: tested where it ends.
            gap = _least_gap(position, radius, planes, p)
        if gap <= slop * radius[p] + ahead:
            listed[near_count] = p
            near_count += 1
    return _sorted_rows(floats, ints, count, plane_count, listed[:near_count].copy())


@njit(cache=True)
def _reflect(bodies, position, planes, coefficients, motion, p, count, floats, ints):
    """Reflect particle p at each plane it is past (``_wall_pass``); return the rows so far."""
    velocity, angular, inv_mass, radius = bodies
    axis, value, inward = planes.axis, planes.value, planes.inward
    own_rest, own_mu = coefficients.own_restitution, coefficients.own_friction
    wall_rest, wall_mu = coefficients.restitution, coefficients.friction
    gravity, dt, threshold = motion.gravity, motion.dt, motion.threshold
    has_rest, has_mu = own_rest.size > 0, own_mu.size > 0
    for k in range(axis.size):
        ax, plane, sign = axis[k], value[k], inward[k]
        gap = sign * (position[p, ax] - plane) - radius[p]
        if not gap < 0.0:
            continue
        if count == floats.shape[0]:
            floats, ints = _grow(floats, ints, count)
        u1 = sign * velocity[p, ax]
        g_n = sign * gravity[ax] if motion.has_gravity else 0.0
        ints[count, PLANE], ints[count, PARTICLE] = k, p
        if not u1 < 0.0:
            # Put back on the plane without an impact: the lift's energy.
            ints[count, IMPACT] = 0
            floats[count, WALLS_LOSS] = -g_n * gap / inv_mass[p]
            position[p, ax] = plane + sign * radius[p]
            count += 1
            continue
        ints[count, IMPACT] = 1
        e = combined_coefficient(own_rest, has_rest, p, -1, wall_rest)
        # reflect_on_plane, one particle (q1 = gap).
        disc = u1 * u1 - 2.0 * g_n * gap
        real = disc >= 0.0
        denominator = u1 - math.sqrt(disc if real else 0.0)
        back = 2.0 * gap / denominator if (real and denominator < 0.0) else np.inf
        on_path = back <= dt
        if not on_path:
            back = 0.0
        approach = -(u1 - g_n * back)
        if threshold > 0.0 and approach < threshold:
            e = 0.0
        out = e * approach
        gap_out = out * back + 0.5 * g_n * back * back if on_path else 0.0
        speed = out + g_n * back
        resting = gap_out < 0.0
        settle = (0.5 * out * out if resting else 0.0) + (0.0 if on_path else -g_n * gap)
        if resting:
            gap_out, speed = 0.0, 0.0
        impact_loss = 0.5 * (1.0 + e) * (1.0 - e) * approach * approach
        mass = 1.0 / inv_mass[p]
        normal_impulse = mass * (speed - u1)
        velocity[p, ax] = sign * speed
        position[p, ax] = plane + sign * (gap_out + radius[p])
        floats[count, WALLS_LOSS] = mass * (impact_loss + settle)
        tangential, lost = 0.0, 0.0
        if motion.friction:
            mu = combined_coefficient(own_mu, has_mu, p, -1, wall_mu)
            nx = sign if ax == 0 else 0.0
            ny = sign if ax == 1 else 0.0
            nz = sign if ax == 2 else 0.0
            tangential, lost = pair_friction(velocity, angular, inv_mass, radius, p, -1, nx,
                                             ny, nz, normal_impulse, mu, motion.planar)
        floats[count, FRICTION_LOSS] = lost
        floats[count, BACK] = back
        floats[count, NORMAL_IMPULSE] = normal_impulse
        floats[count, TANGENTIAL] = tangential
        floats[count, APPROACH] = approach
        for d in range(3):
            floats[count, POINT + d] = position[p, d]
        floats[count, POINT + ax] = plane
        count += 1
    return count, floats, ints


@njit(cache=True)
def _sorted_rows(floats, ints, count, plane_count, near):
    """Return ``WallRows`` of the first ``count`` rows, sorted as ``_wall_pass`` says."""
    # Plane by plane, and within a plane the put-back rows before the impacts
    # (a stable counting sort on 2 plane + impact: particles stay ascending).
    groups = 2 * plane_count
    group_start = np.zeros(groups + 1, dtype=np.int64)
    for r in range(count):
        group_start[2 * ints[r, PLANE] + ints[r, IMPACT] + 1] += 1
    for k in range(groups):
        group_start[k + 1] += group_start[k]
    fill = group_start[:groups].copy()
    sorted_f = np.empty((count, FLOAT_COLUMNS))
    sorted_i = np.empty((count, 3), dtype=np.int64)
    for r in range(count):
        g = 2 * ints[r, PLANE] + ints[r, IMPACT]
        at = fill[g]
        fill[g] += 1
        sorted_f[at] = floats[r]
        sorted_i[at] = ints[r]
    return WallRows(sorted_f, sorted_i, group_start, near)


def warm_up() -> None:
    """Call the kernel once on a tiny problem (compiles or loads from the cache)."""
    position = np.array([[-0.1, 0.5, 0.0], [0.5, 0.5, 0.0]])
    velocity = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    none = np.zeros(0)
    planes = WallPlanes(np.array([0, 0], dtype=np.int64), np.array([0.0, 1.0]),
                        np.array([1.0, -1.0]), np.zeros(2))
    bodies = Bodies(velocity, np.zeros((2, 3)), np.ones(2), np.full(2, 0.1))
    coefficients = WallCoefficients(none, 1.0, none, 0.5)
    motion = WallMotion(True, False, np.zeros(3), 0.01, 0.0, False, 0.02, 0.0)
    wall_pass(tuple(bodies), position, tuple(planes), tuple(coefficients), tuple(motion), False)


def kernels() -> list:
    """Return the compiled kernels of this module (for the cache check)."""
    return [wall_pass]
