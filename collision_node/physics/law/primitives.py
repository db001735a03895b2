"""The contact law, compiled: the small functions every kernel calls for one contact.

Pair and wall impulses with inverse masses, the combine rule, Coulomb
friction with spin, the line of action, a speculative contact's allowance,
and the energy each impulse removes, booked per particle. Every solver and
preset calls these; none re-derives them. Friction helpers take the particle
arrays (velocity, spin, inverse mass, radius) and a contact's normal, impulse
and spin factors as 3- and 2-tuples (the same floating-point operations as
scalar arguments). A ``Bodies`` record is unpacked by the caller once, outside
its loop: a record handed to an inlined helper costs numba a reference count
per array at every contact.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)

from ..model.energy import SPIN_FACTOR, STICK_FACTOR  # noqa: E402
from ..model.tunables import BISECTIONS  # noqa: E402

# Rows of the per-particle loss array the solve returns.
RESTITUTION, WALLS, FRICTION = 0, 1, 2
EFFECTS = ('restitution', 'walls', 'friction')
# The last row sums every booking per particle in the order it happens,
# starting from the step's losses so far: the same additions in the same
# order as ``StepContext.book`` makes them, so the separation stage's
# budget is bit for bit what per-stage booking gives.
BOOKED = len(EFFECTS)


class Bodies(NamedTuple):
    """The particles as the contact law reads and changes them (one row per particle)."""

    velocity: np.ndarray          # (n, 3) m/s, changed in place
    angular_velocity: np.ndarray  # (n, 3) rad/s, changed in place by friction
    inv_mass: np.ndarray          # (n,) 1/kg, 0 for a static particle
    radius: np.ndarray            # (n,) m


@njit(cache=True, inline='always')
def dot3(ax, ay, az, bx, by, bz):
    """Return a . b, summed as numpy's einsum('ij,ij->i') does (x + z first, then y).

    The same order of additions keeps the kernel bit-identical to the
    vectorised law (measured on numpy 2.4: (x + z) + y on every row).
    """
    return (ax * bx + az * bz) + ay * by


@njit(cache=True, inline='always')
def closing_allowance(gap, dt):
    """Return the closing speed a contact ``gap`` m apart may keep for a step of ``dt``, m/s.

    A speculative contact (found before it touches, gap > 0) may close by
    its gap in the next drift and no more: v_n >= -gap / dt, so it touches
    at the step's end instead of overlapping. A touching or overlapping one
    (gap <= 0) may not close at all: v_n >= 0, the law's impulse with e.
    """
    return gap / dt if gap > 0.0 else 0.0


@njit(cache=True, nogil=True)
def pair_impulse(v, inv_mass, a, b, nx, ny, nz, e, tolerance):
    """Apply the law's normal impulse to pair (a, b) if it closes faster than ``tolerance``.

    Returns (magnitude N s, approach speed m/s, energy removed J); magnitude
    0 when the pair did not close fast enough (then nothing changed).
    """
    approach = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
    if not approach > tolerance:
        return 0.0, approach, 0.0
    magnitude, removed = apply_pair_normal(v, inv_mass, a, b, nx, ny, nz, e, approach)
    return magnitude, approach, removed


@njit(cache=True, inline='always')
def apply_pair_normal(v, inv_mass, a, b, nx, ny, nz, e, approach):
    """Apply the normal impulse to a pair closing at ``approach``; return (N s, J removed)."""
    w_a, w_b = inv_mass[a], inv_mass[b]
    magnitude = (1.0 + e) * approach / (w_a + w_b)
    ka, kb = magnitude * w_a, magnitude * w_b
    v[a, 0] += ka * nx
    v[a, 1] += ka * ny
    v[a, 2] += ka * nz
    v[b, 0] += -(kb * nx)
    v[b, 1] += -(kb * ny)
    v[b, 2] += -(kb * nz)
    return magnitude, 0.5 * magnitude * approach * (1.0 - e)


@njit(cache=True)
def spin_factor(inv_mass, radius, p):
    """Return -(r^2 m / I) w / r of particle ``p``: its spin change per unit r x J."""
    return -(SPIN_FACTOR * inv_mass[p] / radius[p])


@njit(cache=True, nogil=True)
def pair_friction(v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_impulse, mu, planar):
    """Coulomb friction with spin at one contact (``b`` < 0: a static wall).

    The impulse that stops the slip of the contact points, bounded by mu
    times the normal impulse. Returns (tangential impulse magnitude N s,
    energy removed J).
    """
    spin_b = spin_factor(inv_mass, radius, b) if b >= 0 else 0.0
    return pair_friction_spun(v, ang, inv_mass, radius, a, b, (nx, ny, nz), normal_impulse,
                              mu, planar, (spin_factor(inv_mass, radius, a), spin_b))


@njit(cache=True)
def pair_friction_spun(v, ang, inv_mass, radius, first, second, normal, normal_impulse, mu,
                       planar, spins):
    """``pair_friction`` with the particles' ``spin_factor`` values given as ``spins``.

    A solve computes them once per particle instead of at every visit: the
    divisions are most of a contact visit's arithmetic.
    """
    magnitude, removed, _impulse = friction_vector(v, ang, inv_mass, radius, first, second,
                                                   normal, normal_impulse, mu, planar, spins,
                                                   True)
    return magnitude, removed


@njit(cache=True)
def loss_share(inv_mass, a, b):
    """Return particle a's share of a pair's loss, by inverse mass (``StepContext.book``)."""
    return inv_mass[a] / (inv_mass[a] + inv_mass[b])


@njit(cache=True, inline='always')
def book_pair_loss(loss, effect, a, b, removed, share):
    """Book a pair's loss to its particles, a taking ``share`` (``loss_share``)."""
    loss[effect, a] += removed * share
    loss[BOOKED, a] += removed * share
    loss[effect, b] += removed * (1.0 - share)
    loss[BOOKED, b] += removed * (1.0 - share)


@njit(cache=True, inline='always')
def book_pair_total(booked, a, b, removed, share):
    """Book a pair's loss to its particles' totals only (``book_pair_loss``'s BOOKED row)."""
    booked[a] += removed * share
    booked[b] += removed * (1.0 - share)


@njit(cache=True, inline='always')
def book_loss(loss, effect, p, removed):
    """Book a loss to particle ``p``."""
    loss[effect, p] += removed
    loss[BOOKED, p] += removed


@njit(cache=True, inline='always')
def push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach):
    """Apply a normal impulse increment ``magnitude`` (either sign) to pair (a, b).

    Returns the energy it removed, J: an impulse dP along N changes the
    kinetic energy by dP times the mean of the normal separating speed before
    and after it (exact for one impulse), booked negated.
    """
    w_a, w_b = inv_mass[a], inv_mass[b]
    ka, kb = magnitude * w_a, magnitude * w_b
    v[a, 0] += ka * nx
    v[a, 1] += ka * ny
    v[a, 2] += ka * nz
    v[b, 0] += -(kb * nx)
    v[b, 1] += -(kb * ny)
    v[b, 2] += -(kb * nz)
    before = -approach
    after = before + (w_a + w_b) * magnitude
    return -(magnitude * 0.5 * (before + after))


@njit(cache=True, inline='always')
def push_wall(v, inv_mass, p, axis, inward, magnitude, approach):
    """``push_pair`` against a static axis-aligned wall (N = ``inward`` on ``axis``)."""
    change = magnitude * inv_mass[p]
    v[p, axis] += inward * change
    before = -approach
    after = before + change
    return -(magnitude * 0.5 * (before + after))


@njit(cache=True, inline='always')
def push_particle(v, inv_mass, p, impulse):
    """Apply impulse vector ``impulse`` to particle ``p``; return J removed.

    The exact work of the impulse P, -(v . P + w |P|^2 / 2), from the
    velocity before it.
    """
    px, py, pz = impulse
    w = inv_mass[p]
    removed = -(dot3(v[p, 0], v[p, 1], v[p, 2], px, py, pz)
                + 0.5 * w * dot3(px, py, pz, px, py, pz))
    v[p, 0] += w * px
    v[p, 1] += w * py
    v[p, 2] += w * pz
    return removed


@njit(cache=True, inline='always')
def into_cone(impulse, normal, planar, bound):
    """Return ``impulse`` projected on the tangent plane of ``normal``, clamped to ``bound``.

    In a 2-D scene only its in-plane part is kept.
    """
    qx, qy, qz = impulse
    nx, ny, nz = normal
    qn = dot3(qx, qy, qz, nx, ny, nz)
    qx, qy, qz = qx - qn * nx, qy - qn * ny, qz - qn * nz
    if planar:
        qz = 0.0
    size = math.sqrt(dot3(qx, qy, qz, qx, qy, qz))
    if size > bound:
        scale = bound / size
        qx, qy, qz = qx * scale, qy * scale, qz * scale
    return qx, qy, qz


@njit(cache=True, inline='always')
def friction_accumulated(v, ang, inv_mass, radius, pair, normal, normal_total, mu, planar,
                         spins, accumulated, row):
    """Coulomb friction with spin on an accumulated tangential impulse (``second`` < 0: a wall).

    ``accumulated[row]`` is the contact's tangential impulse on ``first``
    so far in this solve (warm start included); the new total is the one
    that stops the slip of the contact points, clamped into the cone
    ``mu * normal_total``, and only the change is applied. With nothing
    accumulated yet this is ``pair_friction_spun`` with ``normal_total`` as
    the impulse, operation for operation (an isolated impact is unchanged).
    Returns (|change| N s, J removed): -(dJ . u_t + k |dJ|^2 / 2), the
    exact work of a tangential impulse on a sphere's contact point.
    """
    first, second = pair
    ox, oy, oz = accumulated[row, 0], accumulated[row, 1], accumulated[row, 2]
    if ox == 0.0 and oy == 0.0 and oz == 0.0:
        magnitude, removed, (jx, jy, jz) = friction_vector(
            v, ang, inv_mass, radius, first, second, normal, normal_total, mu, planar, spins,
            True)
        accumulated[row, 0], accumulated[row, 1], accumulated[row, 2] = jx, jy, jz
        return magnitude, removed
    tx, ty, tz, w_sum = tangential_slip(v, ang, inv_mass, radius, first, second, normal,
                                        planar)
    k = STICK_FACTOR * w_sum
    if not k > 0.0:
        return 0.0, 0.0
    # The total that stops the slip, then into the cone. The accumulated
    # impulse lies in this contact's tangent plane up to rounding; keep it
    # there (the normal may turn a little between steps).
    qx, qy, qz = into_cone((ox - tx / k, oy - ty / k, oz - tz / k), normal, planar,
                           mu * max(normal_total, 0.0))
    jx, jy, jz = qx - ox, qy - oy, qz - oz
    accumulated[row, 0], accumulated[row, 1], accumulated[row, 2] = qx, qy, qz
    removed = -(dot3(jx, jy, jz, tx, ty, tz) + 0.5 * k * dot3(jx, jy, jz, jx, jy, jz))
    apply_tangential(v, ang, inv_mass, first, second, normal, (jx, jy, jz), spins)
    return math.sqrt(dot3(jx, jy, jz, jx, jy, jz)), removed


@njit(cache=True, inline='always')
def tangential_slip(v, ang, inv_mass, radius, first, second, normal, planar):
    """Return the slip velocity of the contact points (tangent to N) and w_first + w_second.

    ``second`` < 0 is a static wall. The one place the friction kernels
    take the contact points' relative velocity (spin included) from.
    """
    nx, ny, nz = normal
    a, b = first, second
    w_sum = inv_mass[a]
    sx, sy, sz = radius[a] * ang[a, 0], radius[a] * ang[a, 1], radius[a] * ang[a, 2]
    ux, uy, uz = v[a, 0], v[a, 1], v[a, 2]
    if b >= 0:
        w_sum = w_sum + inv_mass[b]
        sx += radius[b] * ang[b, 0]
        sy += radius[b] * ang[b, 1]
        sz += radius[b] * ang[b, 2]
        ux -= v[b, 0]
        uy -= v[b, 1]
        uz -= v[b, 2]
    ux -= sy * nz - sz * ny
    uy -= sz * nx - sx * nz
    uz -= sx * ny - sy * nx
    un = dot3(ux, uy, uz, nx, ny, nz)
    tx, ty, tz = ux - un * nx, uy - un * ny, uz - un * nz
    if planar:
        tz = 0.0
    return tx, ty, tz, w_sum


@njit(cache=True, inline='always')
def apply_tangential(v, ang, inv_mass, first, second, normal, impulse, spins):
    """Apply tangential ``impulse`` J on ``first`` (-J on ``second`` if >= 0), with its spin.

    ``spins``: the two particles' ``spin_factor`` values.
    """
    nx, ny, nz = normal
    jx, jy, jz = impulse
    spin_a, spin_b = spins
    a, b = first, second
    cx, cy, cz = ny * jz - nz * jy, nz * jx - nx * jz, nx * jy - ny * jx
    w_a = inv_mass[a]
    v[a, 0] += w_a * jx
    v[a, 1] += w_a * jy
    v[a, 2] += w_a * jz
    ang[a, 0] += spin_a * cx
    ang[a, 1] += spin_a * cy
    ang[a, 2] += spin_a * cz
    if b >= 0:
        w_b = inv_mass[b]
        v[b, 0] += -w_b * jx
        v[b, 1] += -w_b * jy
        v[b, 2] += -w_b * jz
        ang[b, 0] += spin_b * cx
        ang[b, 1] += spin_b * cy
        ang[b, 2] += spin_b * cz


@njit(cache=True)
def friction_vector(v, ang, inv_mass, radius, first, second, normal, normal_impulse, mu, planar,
                    spins, apply):
    """``pair_friction_spun``'s law, also returning the impulse vector (same operations).

    Returns (magnitude N s, J removed, (jx, jy, jz) on ``first``); the
    impulse is applied only with ``apply``.
    """
    tx, ty, tz, w_sum = tangential_slip(v, ang, inv_mass, radius, first, second, normal,
                                        planar)
    slip = math.sqrt(dot3(tx, ty, tz, tx, ty, tz))
    k = STICK_FACTOR * w_sum
    stick = slip / k if (slip > 0.0 and k > 0.0) else 0.0
    magnitude = min(stick, mu * normal_impulse)
    if slip > 0.0:
        jx, jy, jz = -magnitude * (tx / slip), -magnitude * (ty / slip), -magnitude * (tz / slip)
    else:
        jx = jy = jz = -magnitude * 0.0
    removed = magnitude * slip - 0.5 * k * (magnitude * magnitude)
    if apply:
        apply_tangential(v, ang, inv_mass, first, second, normal, (jx, jy, jz), spins)
    return math.sqrt(dot3(jx, jy, jz, jx, jy, jz)), removed, (jx, jy, jz)


@njit(cache=True, nogil=True)
def line_of_action(ox, oy, oz, rx, ry, rz):
    """Return (N, |offset|) of one offset, as ``narrowphase.line_of_action`` (same operations).

    The offset is scaled by its largest component first; coincident centres
    take -(relative velocity) as N, or +x when they do not move apart.
    """
    scale = max(abs(ox), abs(oy), abs(oz))
    if scale != 0.0:
        sx, sy, sz = ox / scale, oy / scale, oz / scale
        norm = math.sqrt(dot3(sx, sy, sz, sx, sy, sz))
        return sx / norm, sy / norm, sz / norm, scale * norm
    rv_scale = max(abs(rx), abs(ry), abs(rz))
    if rv_scale > 0.0:
        ux, uy, uz = rx / rv_scale, ry / rv_scale, rz / rv_scale
        norm = math.sqrt(dot3(ux, uy, uz, ux, uy, uz))
        return -(ux / norm), -(uy / norm), -(uz / norm), 0.0
    return 1.0, 0.0, 0.0, 0.0


@njit(cache=True, error_model='numpy', inline='always')
def combined_coefficient(own, has_own, p, q, default):
    """Return the coefficient of p and q (q < 0: a wall) by the geometric-mean combine rule.

    ``own`` holds each particle's own value (NaN where it has none); a side
    without one takes ``default``; neither side with one gives ``default``
    itself (the vectorised rule is ``contact_law.combine``).
    """
    if not has_own:
        return default
    own_p = own[p]
    missing_p = math.isnan(own_p)
    missing_q = True
    own_q = default
    if q >= 0:
        own_q = own[q]
        missing_q = math.isnan(own_q)
    if missing_p and missing_q:
        return default
    first = default if missing_p else own_p
    second = default if missing_q else own_q
    return math.sqrt(first * second)


@njit(cache=True, inline='always')
def apply_wall_normal(v, inv_mass, p, axis, inward, e, approach):
    """Apply the law's wall impulse to ``p`` closing at ``approach`` on an axis-aligned wall.

    The wall has infinite mass: the normal speed changes by (1 + e) approach
    along ``inward`` (+1 or -1 on ``axis``). Returns (N s, J removed).
    """
    change = (1.0 + e) * approach
    v[p, axis] += inward * change
    magnitude = change / inv_mass[p]
    return magnitude, 0.5 * magnitude * approach * (1.0 - e)


@njit(cache=True, error_model='numpy', inline='always')
def sphere_contact_time(ox, oy, oz, cx, cy, cz, dx, dy, dz, rx, ry, rz):
    """Smaller root s >= 0 of |o + c s| = 1: inf for none, 0 for an overlapping pair that closes.

    ``o``, ``c``: the offset and relative velocity in units of the contact
    distance (a straight relative path); ``d``, ``r``: the same unscaled, for
    the scale-robust line of action that decides a grazing pair whose dot
    product underflowed.
    """
    half_b = dot3(ox, oy, oz, cx, cy, cz)
    c = dot3(ox, oy, oz, ox, oy, oz) - 1.0
    u2 = dot3(cx, cy, cz, cx, cy, cz)
    disc = half_b * half_b - u2 * c
    approaching = half_b < 0.0
    overlapping = c <= 0.0
    if overlapping and half_b == 0.0:
        nx, ny, nz, _ = line_of_action(dx, dy, dz, rx, ry, rz)
        approaching = dot3(nx, ny, nz, rx, ry, rz) < 0.0
    if not (approaching and (overlapping or disc >= 0.0)):
        return np.inf
    if overlapping:
        return 0.0
    return c / (-half_b + math.sqrt(disc if not disc < 0.0 else 0.0))


@njit(cache=True, error_model='numpy')
def _horner(q, s):
    """Evaluate the quartic q (5 coefficients, highest first) at ``s``."""
    out = q[0]
    for k in range(1, 5):
        out = out * s + q[k]
    return out


@njit(cache=True, error_model='numpy')
def parabola_sphere_time(ox, oy, oz, cx, cy, cz, ax, ay, az, horizon):
    """First s in [0, horizon] with |o + c s + a s^2 / 2| <= 1, inf for none.

    Units of the contact distance r_i + r_j (the unit sphere), ``a`` the
    relative acceleration of a falling and a static particle: the roots of
    the quartic from the eigenvalues of its companion matrix (in units of
    the horizon), polished by three Newton steps, bisection where the path
    ends inside but no root was accepted.
    """
    span = max(horizon, 0.0)
    vx, vy, vz = cx * span, cy * span, cz * span
    s2 = span * span
    kx, ky, kz = 0.5 * ax * s2, 0.5 * ay * s2, 0.5 * az * s2
    ok = dot3(ox, oy, oz, kx, ky, kz)
    q = np.empty(5)
    q[0] = dot3(kx, ky, kz, kx, ky, kz)
    q[1] = 2.0 * dot3(vx, vy, vz, kx, ky, kz)
    q[2] = dot3(vx, vy, vz, vx, vy, vz) + 2.0 * ok
    q[3] = 2.0 * dot3(ox, oy, oz, vx, vy, vz)
    q[4] = dot3(ox, oy, oz, ox, oy, oz) - 1.0
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
    """First s >= 0 at which gap + rate s + curvature s^2 / 2 falls to 0.

    A gap at or below zero that is closing (or not opening while pushed in)
    counts as now; inf where it never happens.
    """
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


def warm_up() -> None:
    """Call the law's entry points once on a tiny problem (compiles or loads the cache)."""
    v = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    inv_mass, radius = np.ones(2), np.ones(2)
    pair_impulse(v, inv_mass, 1, 0, -1.0, 0.0, 0.0, 1.0, 0.0)
    pair_friction(v, np.zeros((2, 3)), inv_mass, radius, 1, 0, -1.0, 0.0, 0.0, 1.0, 0.5, True)
    line_of_action(1.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def kernels() -> list:
    """Return the law's compiled entry points (for ``kernels.prepare``)."""
    return [pair_impulse, pair_friction, line_of_action]
