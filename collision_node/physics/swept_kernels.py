"""The swept stage of ``ccd``, compiled: times of impact and the rounds of impacts.

``stages/swept_contacts.py`` states the stage vectorised over pairs (one
numpy pass per round); this module runs the same step in one compiled
call: the time of impact of a pair (the quadratic root, on parabolas under
gravity; the quartic against a static sphere), of a wall plane (linear, or
a parabola's root under gravity), the rounds that take every impact that
is the earliest at both of its particles (ties by pair order), the
restitution threshold with its resting rule and 'struck' particles,
Coulomb friction at the impact, and the drift to the step end. Each
formula is written in the order of floating-point operations of the numpy
code (``_dot`` sums as numpy's einsum does), and the impulses come from the
per-contact law of ``contact_kernels``, so the two paths agree to the bit
on the cases ``test/test_swept_kernels.py`` runs.

Only the pairs whose particles changed are predicted again in a round
(through a per-particle list of pairs), and only pending impacts are
scanned to choose a round's batch, so a round costs what it resolves, not
the whole candidate list.
"""

from __future__ import annotations

import math

import numpy as np

from . import numba_cache  # noqa: F401 (chooses numba's cache directory first)
from numba import njit  # noqa: E402 (after the cache directory is chosen)

from .contact_kernels import _dot, _friction, line_of_action, pair_impulse  # noqa: E402

# As paths.BISECTIONS: steps that finish a quartic root the eigenvalues missed.
BISECTIONS = 60
# Rows of the per-particle loss array the step returns.
RESTITUTION, WALLS, FRICTION = 0, 1, 2
EFFECTS = ('restitution', 'walls', 'friction')
# Columns of the float record of each impact: time, point (3), normal (3),
# normal impulse, tangential impulse, approach speed.
RECORD_WIDTH = 10


@njit(cache=True, error_model='numpy')
def _horner(q, s):
    """Evaluate the quartic q (5 coefficients, highest first) at ``s`` (``paths._quartic``)."""
    out = q[0]
    for k in range(1, 5):
        out = out * s + q[k]
    return out


@njit(cache=True, error_model='numpy')
def parabola_sphere_time(ox, oy, oz, cx, cy, cz, ax, ay, az, horizon):
    """First s in [0, horizon] with |o + c s + a s^2 / 2| <= 1, inf for none.

    ``paths.parabola_sphere_time`` for one pair (units of the contact
    distance): the roots of the quartic from the eigenvalues of its
    companion matrix, polished by three Newton steps, bisection where the
    path ends inside but no root was accepted.
    """
    span = max(horizon, 0.0)
    vx, vy, vz = cx * span, cy * span, cz * span
    s2 = span * span
    kx, ky, kz = 0.5 * ax * s2, 0.5 * ay * s2, 0.5 * az * s2
    ok = _dot(ox, oy, oz, kx, ky, kz)
    q = np.empty(5)
    q[0] = _dot(kx, ky, kz, kx, ky, kz)
    q[1] = 2.0 * _dot(vx, vy, vz, kx, ky, kz)
    q[2] = _dot(vx, vy, vz, vx, vy, vz) + 2.0 * ok
    q[3] = 2.0 * _dot(ox, oy, oz, vx, vy, vz)
    q[4] = _dot(ox, oy, oz, ox, oy, oz) - 1.0
    inside = q[4] <= 0.0
    if inside:
        if q[3] < 0.0 or (q[3] == 0.0 and ok < 0.0):
            return 0.0
        return np.inf
    if not (span > 0.0 and q[0] > 0.0):
        return np.inf
    companion = np.zeros((4, 4), dtype=np.complex128)
    for k in range(4):
        companion[0, k] = -q[k + 1] / q[0]
    companion[1, 0] = companion[2, 1] = companion[3, 2] = 1.0
    roots = np.linalg.eigvals(companion)
    first = np.inf
    for r in range(4):
        re, im = roots[r].real, roots[r].imag
        sigma = re if abs(im) <= 1e-6 * (1.0 + abs(re)) else np.inf
        for _ in range(3):
            value = _horner(q, sigma)
            slope = ((4.0 * q[0] * sigma + 3.0 * q[1]) * sigma + 2.0 * q[2]) * sigma \
                + 1.0 * q[3]
            step = value / slope if slope != 0.0 else 0.0
            sigma = sigma - step if np.isfinite(sigma) else np.inf
        if sigma >= 0.0 and sigma <= 1.0 and sigma < first:
            first = sigma
    if not np.isfinite(first) and _horner(q, 1.0) <= 0.0:
        lo, hi = 0.0, 1.0
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            if _horner(q, mid) <= 0.0:
                hi = mid
            else:
                lo = mid
        first = hi
    return first * span


@njit(cache=True, error_model='numpy', inline='always')
def entering_time(gap, rate, curvature):
    """First s >= 0 at which gap + rate s + curvature s^2 / 2 falls to 0 (``paths``)."""
    disc = rate * rate - 2.0 * curvature * gap
    root = math.sqrt(disc if not disc < 0.0 else 0.0)
    closing = rate < 0.0
    if curvature != 0.0:
        if disc >= 0.0:
            s = 2.0 * gap / (root - rate) if closing else (-rate - root) / curvature
        else:
            s = np.inf
    else:
        s = gap / -rate if closing else np.inf
    if not s > 0.0:
        s = np.inf
    if gap <= 0.0 and (closing or (rate == 0.0 and curvature < 0.0)):
        s = 0.0
    return s


@njit(cache=True, inline='always')
def _relative(x, v, a, b, k, ta, tb, ga, gb, has_gravity):
    """Return component k of (offset, relative velocity) of a and b moved to a common time.

    On their parabolas under gravity (``ga``, ``gb``: each one's fall), as ``_on_path``.
    """
    if has_gravity:
        pa = x[a, k] + v[a, k] * ta + 0.5 * ga * ta * ta
        pb = x[b, k] + v[b, k] * tb + 0.5 * gb * tb * tb
        return pa - pb, (v[a, k] + ga * ta) - (v[b, k] + gb * tb)
    return (x[a, k] + v[a, k] * ta) - (x[b, k] + v[b, k] * tb), v[a, k] - v[b, k]


@njit(cache=True, error_model='numpy', inline='always')
def pair_time(x, v, radius, local_time, dynamic, a, b, gravity, has_gravity, min_speed,
              horizon):
    """Time of impact of pair (a, b) on the step clock (``pair_impact_times``), inf for none."""
    start = max(local_time[a], local_time[b])
    reach = radius[a] + radius[b]
    ta, tb = start - local_time[a], start - local_time[b]
    fa = 1.0 if dynamic[a] else 0.0
    fb = 1.0 if dynamic[b] else 0.0
    # Scalars, not small arrays: an allocation per pair would cost more than the root.
    px, vx_ = _relative(x, v, a, b, 0, ta, tb, gravity[0] * fa, gravity[0] * fb, has_gravity)
    py, vy_ = _relative(x, v, a, b, 1, ta, tb, gravity[1] * fa, gravity[1] * fb, has_gravity)
    pz, vz_ = _relative(x, v, a, b, 2, ta, tb, gravity[2] * fa, gravity[2] * fb, has_gravity)
    p = (px, py, pz)
    u = (vx_, vy_, vz_)
    acc0 = acc1 = acc2 = 0.0
    if has_gravity:
        acc0 = (gravity[0] * fa - gravity[0] * fb) / reach
        acc1 = (gravity[1] * fa - gravity[1] * fb) / reach
        acc2 = (gravity[2] * fa - gravity[2] * fb) / reach
    curved = acc0 != 0.0 or acc1 != 0.0 or acc2 != 0.0
    acc = (acc0, acc1, acc2)
    ox, oy, oz = p[0] / reach, p[1] / reach, p[2] / reach
    cx, cy, cz = u[0] / reach, u[1] / reach, u[2] / reach
    half_b = _dot(ox, oy, oz, cx, cy, cz)
    c = _dot(ox, oy, oz, ox, oy, oz) - 1.0
    u2 = _dot(cx, cy, cz, cx, cy, cz)
    disc = half_b * half_b - u2 * c
    approaching = half_b < 0.0
    overlapping = c <= 0.0
    if overlapping and half_b == 0.0:
        # A subnormal offset underflows the dot product: the scale-robust normal decides.
        nx, ny, nz, _ = line_of_action(p[0], p[1], p[2], u[0], u[1], u[2])
        approaching = _dot(nx, ny, nz, u[0], u[1], u[2]) < 0.0
    delay = np.inf
    if approaching and (overlapping or disc >= 0.0):
        if overlapping:
            delay = 0.0
        else:
            delay = c / (-half_b + math.sqrt(disc if not disc < 0.0 else 0.0))
    if curved:
        delay = parabola_sphere_time(ox, oy, oz, cx, cy, cz, acc[0], acc[1], acc[2],
                                     horizon - start)
    if min_speed > 0.0 and np.isfinite(delay):
        s = delay
        if has_gravity:
            wx, wy, wz = cx + acc[0] * s, cy + acc[1] * s, cz + acc[2] * s
            rx = ox + cx * s + 0.5 * acc[0] * s * s
            ry = oy + cy * s + 0.5 * acc[1] * s * s
            rz = oz + cz * s + 0.5 * acc[2] * s * s
        else:
            wx, wy, wz = cx, cy, cz
            rx, ry, rz = ox + cx * s, oy + cy * s, oz + cz * s
        nx, ny, nz, _ = line_of_action(rx, ry, rz, wx, wy, wz)
        if -_dot(nx, ny, nz, wx, wy, wz) * reach < min_speed:
            delay = np.inf
    return start + delay


@njit(cache=True, error_model='numpy', inline='always')
def wall_times(x, v, radius, local_time, p, low, high, dimensions, gravity, has_gravity,
               min_speed, out):
    """Write particle p's times of impact with each wall to row p of ``out``.

    As ``swept_contacts.wall_impact_times`` for one particle.
    """
    r = radius[p]
    for axis in range(dimensions):
        pos, vel = x[p, axis], v[p, axis]
        gap_low = pos - (low[axis] + r)
        gap_high = (high[axis] - r) - pos
        if has_gravity:
            g = gravity[axis]
            for column, gap, rate, curvature in ((2 * axis, gap_low, vel, g),
                                                 (2 * axis + 1, gap_high, -vel, -g)):
                s = entering_time(gap, rate, curvature)
                if min_speed > 0.0:
                    speed = -(rate + curvature * (s if np.isfinite(s) else 0.0))
                    if not speed >= min_speed:
                        s = np.inf
                out[p, column] = local_time[p] + s
        else:
            lo = (gap_low if not gap_low < 0.0 else 0.0) / -vel if vel < 0.0 else np.inf
            hi = (gap_high if not gap_high < 0.0 else 0.0) / vel if vel > 0.0 else np.inf
            if min_speed > 0.0:
                if not -vel >= min_speed:
                    lo = np.inf
                if not vel >= min_speed:
                    hi = np.inf
            out[p, 2 * axis] = local_time[p] + lo
            out[p, 2 * axis + 1] = local_time[p] + hi


@njit(cache=True, error_model='numpy', inline='always')
def _advance(x, v, local_time, p, when, gravity, has_gravity):
    """Move particle p on its drag-free path to ``when`` (``SweptContactStage._advance``)."""
    tau = when - local_time[p]
    local_time[p] = when
    for k in range(3):
        if has_gravity:
            x[p, k] = x[p, k] + v[p, k] * tau + 0.5 * gravity[k] * tau * tau
            v[p, k] = v[p, k] + gravity[k] * tau
        else:
            x[p, k] = x[p, k] + v[p, k] * tau


@njit(cache=True)
def _coefficient(own, has_own, p, q, default):
    """Return the coefficient of p and q (q < 0: a wall) by ``contact_law.combine``."""
    if not has_own:
        return default
    own_p = own[p]
    missing_p = np.isnan(own_p)
    missing_q = True
    own_q = default
    if q >= 0:
        own_q = own[q]
        missing_q = np.isnan(own_q)
    if missing_p and missing_q:
        return default
    first = default if missing_p else own_p
    second = default if missing_q else own_q
    return math.sqrt(first * second)


@njit(cache=True)
def _grow(records, index, count):
    """Return the record arrays with room for ``count`` + 1 rows."""
    if count < index.shape[0]:
        return records, index
    bigger = np.empty((2 * records.shape[0] + 16, RECORD_WIDTH))
    bigger[:count] = records[:count]
    bigger_index = np.empty((2 * index.shape[0] + 16, 2), dtype=np.int64)
    bigger_index[:count] = index[:count]
    return bigger, bigger_index


# Relative margin of ``_out_of_reach``: far above the rounding of its
# distance test (a few ulps) and of the root ``pair_time`` computes (at worst
# about 3e-8 relative, for a grazing pair, where its discriminant cancels).
REACH_MARGIN = 1.0e-6


@njit(cache=True, error_model='numpy', inline='always')
def _out_of_reach(x, v, radius, local_time, dynamic, i, j, gravity, horizon):
    """Return True if falling pair (i, j) surely has no impact by ``horizon``.

    A test without divisions, taken before ``pair_time`` under gravity:
    when both particles fall alike their relative path is straight, and
    they cannot touch within the time s left when |p| > r_i + r_j + |u| s
    (p, u: offset and relative velocity at their common time, formed as
    ``pair_time`` forms them). It is asked with margins (REACH_MARGIN
    relative, and s longer by REACH_MARGIN * horizon), so ``pair_time``
    would give a rejected pair no root or one that rounds past
    ``horizon``: the rounds list only times <= horizon, so rejection
    (inf) changes nothing. A falling and a static particle (a curved
    relative path), NaN and subnormal scales are never rejected.
    """
    if dynamic[i] != dynamic[j]:
        return False
    start = max(local_time[i], local_time[j])
    ta, tb = start - local_time[i], start - local_time[j]
    g0, g1, g2 = gravity[0], gravity[1], gravity[2]
    px, ux = _relative(x, v, i, j, 0, ta, tb, g0, g0, True)
    py, uy = _relative(x, v, i, j, 1, ta, tb, g1, g1, True)
    pz, uz = _relative(x, v, i, j, 2, ta, tb, g2, g2, True)
    span = (horizon - start) + REACH_MARGIN * horizon
    limit = (radius[i] + radius[j] + math.sqrt(ux * ux + uy * uy + uz * uz) * span) \
        * (1.0 + REACH_MARGIN)
    return limit > 1.0e-150 and px * px + py * py + pz * pz > limit * limit


@njit(cache=True, error_model='numpy')
def _walls_out_of_reach(x, v, radius, local_time, p, low, high, dimensions, gravity, horizon):
    """Return True if falling particle p surely reaches no wall plane by ``horizon``.

    ``_out_of_reach`` for the walls: along each axis the path moves at most
    |v| s + |g| s^2 / 2 in the time s left, asked with the same margins, so
    ``wall_times`` would give every column no root or one that rounds past
    ``horizon``. A particle already touching or past a plane (gap <= the
    margin) is never rejected.
    """
    span = (horizon - local_time[p]) + REACH_MARGIN * horizon
    r = radius[p]
    for axis in range(dimensions):
        pos = x[p, axis]
        move = (abs(v[p, axis]) * span + 0.5 * abs(gravity[axis]) * span * span) \
            * (1.0 + REACH_MARGIN) + REACH_MARGIN * r
        if not (pos - (low[axis] + r) > move and (high[axis] - r) - pos > move):
            return False
    return True


@njit(cache=True, error_model='numpy')
def _predict_falling(first, last, keys, use_keys, seen, round_, x, v, radius, local_time,
                     dynamic, a, b, gravity, min_speed, dt, has_resting, resting_pair, touched,
                     pair_t, listed, pending, n_pending):
    """Predict pairs again under gravity; list the due ones; return the pending count.

    The pairs are ``keys[first:last]`` not yet ``seen`` in this round (a
    particle's incident pairs), or with ``use_keys`` False every pair in
    ``range(first, last)``. As ``_predict_pair``, except that a resting
    pair not yet touched and a pair ``_out_of_reach`` rejects get inf
    without solving for a root (``pair_time`` would give them inf or a time
    past ``dt``, which the rounds treat alike). Written out as a loop of
    its own: through an inlined per-pair function the test saved nothing
    (80 ns a pair, against 20 here, on the 10k-sphere pour).
    """
    for q in range(first, last):
        k = q
        if use_keys:
            k = keys[q]
            if seen[k] == round_:
                continue
            seen[k] = round_
        i, j = a[k], b[k]
        if has_resting and resting_pair[k] and not (touched[i] or touched[j]):
            t = np.inf
        elif _out_of_reach(x, v, radius, local_time, dynamic, i, j, gravity, dt):
            t = np.inf
        else:
            t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, True, min_speed, dt)
        n_pending = _list_if_due(k, t, dt, pair_t, listed, pending, n_pending)
    return n_pending


@njit(cache=True, error_model='numpy', inline='always')
def _predict_pair(k, x, v, radius, local_time, dynamic, a, b, gravity, has_gravity, min_speed,
                  dt, has_resting, resting_pair, touched, pair_t, listed, pending, n_pending):
    """Predict pair k again; list it if due in the step; return the pending count."""
    i, j = a[k], b[k]
    # Constant flags in each call: the inlined straight-path case compiles
    # without the gravity and threshold code (three times faster).
    if has_gravity:
        t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, True, min_speed, dt)
    elif min_speed > 0.0:
        t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, min_speed, dt)
    else:
        t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, 0.0, dt)
    if has_resting and resting_pair[k] and not (touched[i] or touched[j]):
        t = np.inf
    return _list_if_due(k, t, dt, pair_t, listed, pending, n_pending)


@njit(cache=True, inline='always')
def _list_if_due(k, t, dt, pair_t, listed, pending, n_pending):
    """Keep pair k's time ``t``; list it once if it is due in the step; return the count."""
    pair_t[k] = t
    if t <= dt and not listed[k]:
        listed[k] = True
        pending[n_pending] = k
        n_pending += 1
    return n_pending


@njit(cache=True, error_model='numpy', inline='always')
def _predict_walls(p, x, v, radius, local_time, low, high, dimensions, gravity, has_gravity,
                   min_speed, dt, has_resting, resting_wall, touched, wall_t, first_wall,
                   wall_listed, wall_due, n_wall_due):
    """Predict particle p's wall impacts again; list it if due; return the due count."""
    wall_times(x, v, radius, local_time, p, low, high, dimensions, gravity, has_gravity,
               min_speed, wall_t)
    first = np.inf
    for col in range(2 * dimensions):
        if has_resting and resting_wall[p, col] and not touched[p]:
            wall_t[p, col] = np.inf
        if wall_t[p, col] < first:
            first = wall_t[p, col]
    first_wall[p] = first
    if first <= dt and not wall_listed[p]:
        wall_listed[p] = True
        wall_due[n_wall_due] = p
        n_wall_due += 1
    return n_wall_due


@njit(cache=True, error_model='numpy')
def _predict_straight(x, v, radius, local_time, dynamic, a, b, gravity, dt, pair_t, listed,
                      pending):
    """Predict every pair on straight paths without threshold; return the pending count.

    The first round's ``_predict_pair`` loop for the common case, compiled
    on its own: inside ``sweep`` the same loop ran three times slower.
    """
    n_pending = 0
    for k in range(a.size):
        t = pair_time(x, v, radius, local_time, dynamic, a[k], b[k], gravity, False, 0.0, dt)
        pair_t[k] = t
        if t <= dt:
            listed[k] = True
            pending[n_pending] = k
            n_pending += 1
    return n_pending


@njit(cache=True, error_model='numpy', inline='always')
def _first_wall_straight(x, v, radius, local_time, p, low, high, dimensions):
    """Return particle p's earliest wall time on a straight path: ``wall_times``' minimum.

    The same formulas as ``wall_times`` without gravity or threshold, so
    the value is the minimum of the row that function writes.
    """
    r = radius[p]
    first = np.inf
    for axis in range(dimensions):
        pos, vel = x[p, axis], v[p, axis]
        gap_low = pos - (low[axis] + r)
        gap_high = (high[axis] - r) - pos
        lo = (gap_low if not gap_low < 0.0 else 0.0) / -vel if vel < 0.0 else np.inf
        hi = (gap_high if not gap_high < 0.0 else 0.0) / vel if vel > 0.0 else np.inf
        t_lo, t_hi = local_time[p] + lo, local_time[p] + hi
        if t_lo < first:
            first = t_lo
        if t_hi < first:
            first = t_hi
    return first


@njit(cache=True, error_model='numpy')
def _predict_all_walls(x, v, radius, local_time, dynamic, low, high, dimensions, gravity,
                       has_gravity, min_speed, dt, has_resting, resting_wall, touched, wall_t,
                       first_wall, wall_listed, wall_due):
    """Predict every dynamic particle's wall impacts (the first round); return the due count.

    Compiled on its own, with constant flags in each inlined case, for the
    reason given at ``_predict_straight``.
    """
    n_wall_due = 0
    for p in range(x.shape[0]):
        if not dynamic[p]:
            continue
        if has_gravity:
            n_wall_due = _predict_walls(p, x, v, radius, local_time, low, high, dimensions,
                                        gravity, True, min_speed, dt, has_resting,
                                        resting_wall, touched, wall_t, first_wall,
                                        wall_listed, wall_due, n_wall_due)
        elif min_speed > 0.0 or has_resting:
            n_wall_due = _predict_walls(p, x, v, radius, local_time, low, high, dimensions,
                                        gravity, False, min_speed, dt, has_resting,
                                        resting_wall, touched, wall_t, first_wall,
                                        wall_listed, wall_due, n_wall_due)
        elif dimensions == 3:
            # The earliest wall time alone, in locals: the row is written only
            # for a due particle (the others' rows are never read), and with a
            # constant dimension the compiler drops the branches on each
            # velocity's sign (random in a gas, mispredicted half the time).
            first = _first_wall_straight(x, v, radius, local_time, p, low, high, 3)
            first_wall[p] = first
            if first <= dt:
                n_wall_due = _predict_walls(p, x, v, radius, local_time, low, high, 3,
                                            gravity, False, 0.0, dt, False, resting_wall,
                                            touched, wall_t, first_wall, wall_listed, wall_due,
                                            n_wall_due)
        else:
            n_wall_due = _predict_walls(p, x, v, radius, local_time, low, high, dimensions,
                                        gravity, False, 0.0, dt, False, resting_wall, touched,
                                        wall_t, first_wall, wall_listed, wall_due, n_wall_due)
    return n_wall_due


def workspace_sizes(n: int, m: int, dimensions: int) -> tuple[int, int, int]:
    """Return the (int, float, bool) scratch sizes ``sweep`` needs for n particles, m pairs."""
    return 4 * m + 9 * n + 1, 2 * n * dimensions + 3 * n + m, 4 * n + m


def workspace(n: int, m: int, dimensions: int, old=None) -> tuple:
    """Return scratch buffers for ``sweep``: ``old`` if large enough, else new ones."""
    sizes = workspace_sizes(n, m, dimensions)
    if old is not None and all(buf.size >= size for buf, size in zip(old, sizes)):
        return old
    # Some room to grow, so a step with a few more pairs does not reallocate.
    return (np.empty(sizes[0] + sizes[0] // 4, dtype=np.int64),
            np.empty(sizes[1] + sizes[1] // 4), np.empty(sizes[2] + sizes[2] // 4, dtype=bool))


@njit(cache=True)
def _keep_due(items, count, times, dt, listed):
    """Keep in ``items[:count]`` (in order) those whose time is within the step; return how many.

    An entry dropped is marked as no longer listed, so it can be listed again.
    """
    kept = 0
    for q in range(count):
        k = items[q]
        if times[k] <= dt:
            items[kept] = k
            kept += 1
        else:
            listed[k] = False
    return kept


@njit(cache=True, nogil=True, error_model='numpy')
def sweep(x, v, ang, inv_mass, radius, dynamic, a, b, own_e, has_own_e, own_mu, has_own_mu,
          restitution, wall_restitution, friction, mu, has_walls, low, high, dimensions,
          gravity, has_gravity, resting_pair, resting_wall, has_resting, min_speed,
          strike_speed, dt, rounds, planar, record, loss, totals, counts, workspace):
    """Run one step of the swept stage in place; see ``SweptContactStage`` for the rules.

    ``workspace``: (int64, float64, bool) buffers of at least
    ``workspace_sizes(n, m, dimensions)`` elements.

    ``a``, ``b``: the candidate pairs (at least one particle dynamic).
    Fills ``loss`` (rows as ``EFFECTS``, per particle), ``totals`` (per
    effect) and ``counts`` (pair impacts, wall impacts, rounds run, pairs
    resolved), and
    returns the impact records when ``record`` (floats: time, point,
    normal, normal and tangential impulse, approach; ints: i, j with
    j = -1 at a wall), in the order the numpy stage records them.
    """
    n = x.shape[0]
    m = a.size
    columns = 2 * dimensions
    # Scratch from the caller's buffers (``workspace_sizes``), kept between
    # steps: fresh arrays of this size cost page faults every step.
    ints, floats, flags = workspace
    start, ints = ints[:n + 1], ints[n + 1:]
    fill, ints = ints[:n], ints[n:]
    incident, ints = ints[:2 * m], ints[2 * m:]
    seen, ints = ints[:m], ints[m:]
    pending, ints = ints[:m], ints[m:]
    changed, ints = ints[:n], ints[n:]
    wall_due, ints = ints[:n], ints[n:]
    best_k, ints = ints[:n], ints[n:]
    best_round, ints = ints[:n], ints[n:]
    chosen, hits = ints[:n], ints[n:2 * n]
    local_time, floats = floats[:n], floats[n:]
    pair_t, floats = floats[:m], floats[m:]
    wall_t = floats[:n * columns].reshape((n, columns))
    first_wall, best_t = floats[n * columns:n * columns + n], floats[n * columns + n:
                                                                     n * columns + 2 * n]
    struck, touched, is_changed = flags[:n], flags[n:2 * n], flags[2 * n:3 * n]
    listed, wall_listed = flags[3 * n:3 * n + m], flags[3 * n + m:4 * n + m]
    start[:] = 0
    flags[:4 * n + m] = False
    local_time[:] = 0.0
    # pair_t, wall_t and best_t need no clearing: the first round writes
    # every pair's time and the wall rows of every due particle, and a
    # particle's best_t is read only in the round that set it (best_round).
    first_wall[:] = np.inf
    seen[:] = -1
    best_k[:] = m
    best_round[:] = -1
    # Pairs of each particle (counting sort): who to predict again when it changes.
    for k in range(m):
        start[a[k] + 1] += 1
        start[b[k] + 1] += 1
    for p in range(n):
        start[p + 1] += start[p]
    fill[:] = start[:n]
    for k in range(m):
        incident[fill[a[k]]] = k
        fill[a[k]] += 1
        incident[fill[b[k]]] = k
        fill[b[k]] += 1
    # Particles changed in the last round (the first round predicts every
    # pair and particle instead); pending pairs (time <= dt) and particles
    # with a pending wall impact.
    n_changed = 0
    n_pending = 0
    n_wall_due = 0
    records = np.empty((16, RECORD_WIDTH))
    index = np.empty((16, 2), dtype=np.int64)
    count = 0
    rounds_run = 0
    for round_ in range(rounds):
        rounds_run += 1
        # Predict again the pairs and walls of the particles that changed
        # (in the first round every pair, in pair order, then every particle).
        if round_ == 0 and not has_gravity and not min_speed > 0.0 and not has_resting:
            n_pending = _predict_straight(x, v, radius, local_time, dynamic, a, b, gravity, dt,
                                          pair_t, listed, pending)
        elif round_ == 0 and has_gravity:
            n_pending = _predict_falling(0, m, incident, False, seen, round_, x, v, radius,
                                         local_time, dynamic, a, b, gravity, min_speed, dt,
                                         has_resting, resting_pair, touched, pair_t, listed,
                                         pending, 0)
        elif round_ == 0:
            for k in range(m):
                n_pending = _predict_pair(k, x, v, radius, local_time, dynamic, a, b, gravity,
                                          has_gravity, min_speed, dt, has_resting,
                                          resting_pair, touched, pair_t, listed, pending,
                                          n_pending)
        if round_ == 0 and has_walls:
            n_wall_due = _predict_all_walls(x, v, radius, local_time, dynamic, low, high,
                                            dimensions, gravity, has_gravity, min_speed, dt,
                                            has_resting, resting_wall, touched, wall_t,
                                            first_wall, wall_listed, wall_due)
        for c in range(n_changed):
            p = changed[c]
            if round_ > 0 and has_gravity:
                n_pending = _predict_falling(start[p], start[p + 1], incident, True, seen,
                                             round_, x, v, radius, local_time, dynamic, a, b,
                                             gravity, min_speed, dt, has_resting, resting_pair,
                                             touched, pair_t, listed, pending, n_pending)
            elif round_ > 0:
                for e_ in range(start[p], start[p + 1]):
                    k = incident[e_]
                    if seen[k] == round_:
                        continue
                    seen[k] = round_
                    n_pending = _predict_pair(k, x, v, radius, local_time, dynamic, a, b,
                                              gravity, has_gravity, min_speed, dt,
                                              has_resting, resting_pair, touched, pair_t,
                                              listed, pending, n_pending)
            if has_walls and dynamic[p]:
                if has_gravity and _walls_out_of_reach(x, v, radius, local_time, p, low, high,
                                                       dimensions, gravity, dt):
                    # Its row of wall_t is read only while it is due.
                    first_wall[p] = np.inf
                else:
                    n_wall_due = _predict_walls(p, x, v, radius, local_time, low, high,
                                                dimensions, gravity, has_gravity, min_speed, dt,
                                                has_resting, resting_wall, touched, wall_t,
                                                first_wall, wall_listed, wall_due, n_wall_due)
        for c in range(n_changed):
            is_changed[changed[c]] = False
        n_changed = 0
        # Drop what is no longer due.
        n_pending = _keep_due(pending, n_pending, pair_t, dt, listed)
        n_wall_due = _keep_due(wall_due, n_wall_due, first_wall, dt, wall_listed)
        if n_pending == 0 and n_wall_due == 0:
            rounds_run -= 1
            break
        # Each particle's first pending pair by (time, pair order).
        for q in range(n_pending):
            k = pending[q]
            t = pair_t[k]
            for p in (a[k], b[k]):
                if best_round[p] != round_ or t < best_t[p] or \
                        (t == best_t[p] and k < best_k[p]):
                    best_round[p] = round_
                    best_t[p] = t
                    best_k[p] = k
        n_chosen = 0
        for q in range(n_pending):
            k = pending[q]
            i, j = a[k], b[k]
            t = pair_t[k]
            # A static particle never changes, so it never has to wait its turn.
            if (best_k[i] == k or not dynamic[i]) and (best_k[j] == k or not dynamic[j]) \
                    and t < first_wall[i] and t < first_wall[j]:
                chosen[n_chosen] = k
                n_chosen += 1
        n_hits = 0
        for q in range(n_wall_due):
            p = wall_due[q]
            earliest = best_t[p] if best_round[p] == round_ else np.inf
            if first_wall[p] <= earliest:
                hits[n_hits] = p
                n_hits += 1
        counts[3] += n_chosen
        order = np.sort(chosen[:n_chosen])
        for k in order:
            i, j = a[k], b[k]
            t = pair_t[k]
            if dynamic[i]:
                _advance(x, v, local_time, i, t, gravity, has_gravity)
            if dynamic[j]:
                _advance(x, v, local_time, j, t, gravity, has_gravity)
            nx, ny, nz, _ = line_of_action(x[i, 0] - x[j, 0], x[i, 1] - x[j, 1],
                                           x[i, 2] - x[j, 2], v[i, 0] - v[j, 0],
                                           v[i, 1] - v[j, 1], v[i, 2] - v[j, 2])
            e = _coefficient(own_e, has_own_e, i, j, restitution)
            if min_speed > 0.0:
                closing = _dot(v[j, 0] - v[i, 0], v[j, 1] - v[i, 1], v[j, 2] - v[i, 2],
                               nx, ny, nz)
                if closing < min_speed:
                    e = 0.0
            if has_resting and resting_pair[k] and not (struck[i] or struck[j]):
                e = 0.0
            for p in (i, j):
                if not is_changed[p]:
                    is_changed[p] = True
                    changed[n_changed] = p
                    n_changed += 1
            magnitude, approach, removed = pair_impulse(v, inv_mass, i, j, nx, ny, nz, e, 0.0)
            if not approach > 0.0:
                continue
            share = inv_mass[i] / (inv_mass[i] + inv_mass[j])
            loss[RESTITUTION, i] += removed * share
            loss[RESTITUTION, j] += removed * (1.0 - share)
            totals[RESTITUTION] += removed
            tangential = 0.0
            if friction:
                pair_mu = _coefficient(own_mu, has_own_mu, i, j, mu)
                tangential, lost = _friction(v, ang, inv_mass, radius, i, j, nx, ny, nz,
                                             magnitude, pair_mu, planar)
                loss[FRICTION, i] += lost * share
                loss[FRICTION, j] += lost * (1.0 - share)
                totals[FRICTION] += lost
            counts[0] += 1
            if e > 0.0 and approach >= strike_speed:
                struck[i] = struck[j] = True
            touched[i] = touched[j] = True
            if record:
                records, index = _grow(records, index, count)
                first, second, sign = (i, j, 1.0) if i <= j else (j, i, -1.0)
                row = records[count]
                row[0] = t
                for d, n_d in enumerate((nx, ny, nz)):
                    normal = sign * n_d if sign < 0.0 else n_d
                    row[4 + d] = normal
                    row[1 + d] = 0.5 * ((x[first, d] - radius[first] * normal)
                                        + (x[second, d] + radius[second] * normal))
                row[7], row[8], row[9] = magnitude, tangential, approach
                index[count, 0], index[count, 1] = first, second
                count += 1
        # Walls: every particle to its first wall time, then plane after plane.
        for q in range(n_hits):
            p = hits[q]
            _advance(x, v, local_time, p, first_wall[p], gravity, has_gravity)
            if not is_changed[p]:
                is_changed[p] = True
                changed[n_changed] = p
                n_changed += 1
        if n_hits:
            hit_order = np.sort(hits[:n_hits])
            for axis in range(dimensions):
                for column, plane, inward in ((2 * axis, low[axis], 1.0),
                                              (2 * axis + 1, high[axis], -1.0)):
                    for p in hit_order:
                        if not (wall_t[p, column] == first_wall[p]
                                and inward * v[p, axis] < 0.0):
                            continue
                        e = _coefficient(own_e, has_own_e, p, -1, wall_restitution)
                        if min_speed > 0.0 and -inward * v[p, axis] < min_speed:
                            e = 0.0
                        if has_resting and resting_wall[p, column] and not struck[p]:
                            e = 0.0
                        approach = -inward * v[p, axis]
                        change = (1.0 + e) * approach if approach > 0.0 else 0.0
                        v[p, axis] += inward * change
                        magnitude = change / inv_mass[p]
                        removed = 0.5 * magnitude * approach * (1.0 - e) \
                            if approach > 0.0 else 0.0
                        loss[WALLS, p] += removed
                        totals[WALLS] += removed
                        if e > 0.0 and approach >= strike_speed:
                            struck[p] = True
                        touched[p] = True
                        tangential = 0.0
                        nx = inward if axis == 0 else 0.0
                        ny = inward if axis == 1 else 0.0
                        nz = inward if axis == 2 else 0.0
                        if friction:
                            wall_mu = _coefficient(own_mu, has_own_mu, p, -1, mu)
                            tangential, lost = _friction(v, ang, inv_mass, radius, p, -1,
                                                         nx, ny, nz, magnitude, wall_mu,
                                                         planar)
                            loss[FRICTION, p] += lost
                            totals[FRICTION] += lost
                        counts[1] += 1
                        if record:
                            records, index = _grow(records, index, count)
                            row = records[count]
                            row[0] = local_time[p]
                            row[1], row[2], row[3] = x[p, 0], x[p, 1], x[p, 2]
                            row[1 + axis] = plane
                            row[4], row[5], row[6] = nx, ny, nz
                            row[7], row[8], row[9] = magnitude, tangential, approach
                            index[count, 0], index[count, 1] = p, -1
                            count += 1
    for p in range(n):
        if dynamic[p]:
            _advance(x, v, local_time, p, dt, gravity, has_gravity)
    counts[2] += rounds_run
    return records[:count], index[:count]


@njit(cache=True, nogil=True)
def in_contact(x, radius, a, b, slop, has_walls, low, high, dimensions, pairs, walls):
    """Mark the pairs and particle-wall columns touching at the step start.

    ``SweptContactStage._in_contact`` in one pass: pair k touches when
    |x_a - x_b| - (r_a + r_b) <= slop (r_a + r_b) (the norm summed as
    numpy's), particle p touches wall column c (low x, high x, ...) when
    its gap to the plane is at most slop r_p; NaN touches nothing.
    """
    for k in range(a.size):
        i, j = a[k], b[k]
        reach = radius[i] + radius[j]
        d0, d1, d2 = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
        gap = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - reach
        pairs[k] = gap <= slop * reach
    if has_walls:
        for p in range(x.shape[0]):
            r = radius[p]
            for axis in range(dimensions):
                walls[p, 2 * axis] = x[p, axis] - (low[axis] + r) <= slop * r
                walls[p, 2 * axis + 1] = (high[axis] - r) - x[p, axis] <= slop * r


def warm_up() -> None:
    """Run the swept step once on a tiny problem of each kind (compiles or loads)."""
    x = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    v = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    ang = np.zeros((3, 3))
    inv_mass, radius = np.array([1.0, 1.0, 0.0]), np.ones(3)
    dynamic = inv_mass > 0.0
    a, b = np.array([0, 0], dtype=np.int64), np.array([1, 2], dtype=np.int64)
    low, high = np.full(3, -10.0), np.full(3, 10.0)
    for gravity in (np.zeros(3), np.array([0.0, -9.81, 0.0])):
        sweep(x.copy(), v.copy(), ang, inv_mass, radius, dynamic, a, b, np.full(3, np.nan),
              True, np.full(3, np.nan), True, 1.0, 1.0, True, 0.5, True, low, high, 3,
              gravity, bool(gravity.any()), np.zeros(2, dtype=bool),
              np.zeros((3, 6), dtype=bool), True, 0.1, 1.0, 1.0, 32, False, True,
              np.zeros((3, 3)), np.zeros(3), np.zeros(4, dtype=np.int64),
              workspace(3, 2, 3))
    in_contact(x, radius, a, b, 1e-6, True, low, high, 3, np.empty(2, dtype=bool),
               np.empty((3, 6), dtype=bool))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [sweep, in_contact]
