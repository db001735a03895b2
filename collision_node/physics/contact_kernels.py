"""The contact law, compiled: one contact at a time, in loops numba compiles.

``contact_law`` states the law vectorised over a set of contacts that
share no dynamic particle; this module applies exactly the same law (the
same formulas, written in the same order of floating-point operations) to
one contact at a time, so a solve can visit contacts serially in any order
without a batch per colour. ``solve_contacts`` runs a whole contact solve
of ``stages.sequential_impulses`` (sweeps over pairs and wall planes,
restitution threshold with its 'struck' rule, Coulomb friction with spin,
shock passes) inside one compiled call, and ``solve_step`` wraps it with the
stage's set-up (wall contacts, orders, the warm start's contact cache), so a
step's solve is one call from Python; ``test/test_contact_kernels.py``
runs the vectorised law and these kernels on the same contacts and asserts
identical velocities and bookings.

The kernels are compiled on first use and cached (``cache=True``) in a
folder named by a digest of the physics sources (see ``_cache_directory``).
``prepare`` compiles (or loads) them up front and says how long that took.
"""

from __future__ import annotations

import math

import numpy as np

from . import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)

from .energy import SPHERE_INERTIA  # noqa: E402

# As friction.py: r^2 m / I of a solid sphere and 1 + that.
SPIN_FACTOR = 1.0 / SPHERE_INERTIA
STICK_FACTOR = 1.0 + SPIN_FACTOR
# Rows of the per-particle loss array the solve returns.
RESTITUTION, WALLS, FRICTION = 0, 1, 2
EFFECTS = ('restitution', 'walls', 'friction')
# The last row sums every booking per particle in the order it happens,
# starting from the step's losses so far: the same additions in the same
# order as ``StepContext.book`` makes them in the numpy reference, so the
# separation stage's budget is bit for bit the reference's.
BOOKED = len(EFFECTS)


@njit(cache=True, inline='always')
def _dot(ax, ay, az, bx, by, bz):
    """Return a . b, summed as numpy's einsum('ij,ij->i') does (x + z first, then y).

    The same order of additions keeps the kernel bit-identical to the
    vectorised law (measured on numpy 2.4: (x + z) + y on every row).
    """
    return (ax * bx + az * bz) + ay * by


@njit(cache=True)
def pair_impulse(v, inv_mass, a, b, nx, ny, nz, e, tolerance):
    """Apply the law's normal impulse to pair (a, b) if it closes faster than ``tolerance``.

    Returns (magnitude N s, approach speed m/s, energy removed J); magnitude
    0 when the pair did not close fast enough (then nothing changed).
    """
    approach = -_dot(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
    if not approach > tolerance:
        return 0.0, approach, 0.0
    magnitude, removed = _apply_pair(v, inv_mass, a, b, nx, ny, nz, e, approach)
    return magnitude, approach, removed


@njit(cache=True, inline='always')
def _apply_pair(v, inv_mass, a, b, nx, ny, nz, e, approach):
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


@njit(cache=True)
def _friction(v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_impulse, mu, planar):
    """Coulomb friction with spin at one contact (``b`` < 0: a static wall).

    The law of ``friction.py``: the impulse that stops the slip of the
    contact points, bounded by mu times the normal impulse. Returns
    (tangential impulse magnitude N s, energy removed J).
    """
    f_b = spin_factor(inv_mass, radius, b) if b >= 0 else 0.0
    return _friction_spun(v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_impulse, mu,
                          planar, spin_factor(inv_mass, radius, a), f_b)


@njit(cache=True)
def _friction_spun(v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_impulse, mu, planar,
                   f_a, f_b):
    """``_friction`` with the particles' spin factors given (``spin_factor``, the same values).

    A solve computes them once per particle instead of at every visit: the
    divisions are most of a contact visit's arithmetic.
    """
    magnitude, removed, _jx, _jy, _jz = _friction_vector(
        v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_impulse, mu, planar, f_a, f_b, True)
    return magnitude, removed


@njit(cache=True)
def _share(inv_mass, a, b):
    """Return particle a's share of a pair's loss, by inverse mass (``StepContext.book``)."""
    return inv_mass[a] / (inv_mass[a] + inv_mass[b])


@njit(cache=True, inline='always')
def _book_pair(loss, effect, a, b, removed, share):
    """Book a pair's loss to its particles, a taking ``share`` (``_share``)."""
    loss[effect, a] += removed * share
    loss[BOOKED, a] += removed * share
    loss[effect, b] += removed * (1.0 - share)
    loss[BOOKED, b] += removed * (1.0 - share)


@njit(cache=True, inline='always')
def _book(loss, effect, p, removed):
    """Book a loss to particle ``p``."""
    loss[effect, p] += removed
    loss[BOOKED, p] += removed


@njit(cache=True, inline='always')
def _push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach):
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
def _friction_acc(v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_total, mu, planar,
                  f_a, f_b, acc_t, row):
    """Coulomb friction with spin on an accumulated tangential impulse (``b`` < 0: a wall).

    ``acc_t[row]`` is the contact's tangential impulse on ``a`` so far in
    this solve (warm start included); the new total is the one that stops the
    slip of the contact points, clamped into the cone ``mu * normal_total``,
    and only the change is applied. With nothing accumulated yet this is
    ``_friction_spun`` with ``normal_total`` as the impulse, operation for
    operation (an isolated impact is unchanged). Returns (|change| N s, J
    removed): -(dJ . u_t + k |dJ|^2 / 2), the exact work of a tangential
    impulse on a sphere's contact point.
    """
    ox, oy, oz = acc_t[row, 0], acc_t[row, 1], acc_t[row, 2]
    if ox == 0.0 and oy == 0.0 and oz == 0.0:
        magnitude, removed, jx, jy, jz = _friction_vector(
            v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_total, mu, planar, f_a, f_b,
            True)
        acc_t[row, 0], acc_t[row, 1], acc_t[row, 2] = jx, jy, jz
        return magnitude, removed
    tx, ty, tz, w_sum = _slip(v, ang, inv_mass, radius, a, b, nx, ny, nz, planar)
    k = STICK_FACTOR * w_sum
    if not k > 0.0:
        return 0.0, 0.0
    # The total that stops the slip, then into the cone.
    qx, qy, qz = ox - tx / k, oy - ty / k, oz - tz / k
    # The accumulated impulse lies in this contact's tangent plane up to
    # rounding; keep it there (the normal may turn a little between steps).
    qn = _dot(qx, qy, qz, nx, ny, nz)
    qx, qy, qz = qx - qn * nx, qy - qn * ny, qz - qn * nz
    if planar:
        qz = 0.0
    size = math.sqrt(_dot(qx, qy, qz, qx, qy, qz))
    bound = mu * max(normal_total, 0.0)
    if size > bound:
        scale = bound / size
        qx, qy, qz = qx * scale, qy * scale, qz * scale
    jx, jy, jz = qx - ox, qy - oy, qz - oz
    acc_t[row, 0], acc_t[row, 1], acc_t[row, 2] = qx, qy, qz
    removed = -(_dot(jx, jy, jz, tx, ty, tz) + 0.5 * k * _dot(jx, jy, jz, jx, jy, jz))
    _apply_tangential(v, ang, inv_mass, a, b, nx, ny, nz, jx, jy, jz, f_a, f_b)
    return math.sqrt(_dot(jx, jy, jz, jx, jy, jz)), removed


@njit(cache=True, inline='always')
def _slip(v, ang, inv_mass, radius, a, b, nx, ny, nz, planar):
    """Return the slip velocity of the contact points (tangent to N) and w_a + w_b.

    ``b`` < 0 is a static wall. The one place the friction kernels take the
    contact points' relative velocity (spin included) from.
    """
    w_a = inv_mass[a]
    sx, sy, sz = radius[a] * ang[a, 0], radius[a] * ang[a, 1], radius[a] * ang[a, 2]
    ux, uy, uz = v[a, 0], v[a, 1], v[a, 2]
    w_sum = w_a
    if b >= 0:
        w_sum = w_a + inv_mass[b]
        sx += radius[b] * ang[b, 0]
        sy += radius[b] * ang[b, 1]
        sz += radius[b] * ang[b, 2]
        ux -= v[b, 0]
        uy -= v[b, 1]
        uz -= v[b, 2]
    ux -= sy * nz - sz * ny
    uy -= sz * nx - sx * nz
    uz -= sx * ny - sy * nx
    un = _dot(ux, uy, uz, nx, ny, nz)
    tx, ty, tz = ux - un * nx, uy - un * ny, uz - un * nz
    if planar:
        tz = 0.0
    return tx, ty, tz, w_sum


@njit(cache=True, inline='always')
def _apply_tangential(v, ang, inv_mass, a, b, nx, ny, nz, jx, jy, jz, f_a, f_b):
    """Apply tangential impulse J on ``a`` (-J on ``b`` if b >= 0), with its spin change."""
    cx, cy, cz = ny * jz - nz * jy, nz * jx - nx * jz, nx * jy - ny * jx
    w_a = inv_mass[a]
    v[a, 0] += w_a * jx
    v[a, 1] += w_a * jy
    v[a, 2] += w_a * jz
    ang[a, 0] += f_a * cx
    ang[a, 1] += f_a * cy
    ang[a, 2] += f_a * cz
    if b >= 0:
        w_b = inv_mass[b]
        v[b, 0] += -w_b * jx
        v[b, 1] += -w_b * jy
        v[b, 2] += -w_b * jz
        ang[b, 0] += f_b * cx
        ang[b, 1] += f_b * cy
        ang[b, 2] += f_b * cz


@njit(cache=True)
def _friction_vector(v, ang, inv_mass, radius, a, b, nx, ny, nz, normal_impulse, mu, planar,
                     f_a, f_b, apply):
    """``_friction_spun``'s law, also returning the impulse vector (same operations)."""
    tx, ty, tz, w_sum = _slip(v, ang, inv_mass, radius, a, b, nx, ny, nz, planar)
    slip = math.sqrt(_dot(tx, ty, tz, tx, ty, tz))
    k = STICK_FACTOR * w_sum
    stick = slip / k if (slip > 0.0 and k > 0.0) else 0.0
    magnitude = min(stick, mu * normal_impulse)
    if slip > 0.0:
        jx, jy, jz = -magnitude * (tx / slip), -magnitude * (ty / slip), -magnitude * (tz / slip)
    else:
        jx = jy = jz = -magnitude * 0.0
    removed = magnitude * slip - 0.5 * k * (magnitude * magnitude)
    if apply:
        _apply_tangential(v, ang, inv_mass, a, b, nx, ny, nz, jx, jy, jz, f_a, f_b)
    return math.sqrt(_dot(jx, jy, jz, jx, jy, jz)), removed, jx, jy, jz


@njit(cache=True)
def _solve_wall_plane(v, ang, inv_mass, radius, start, stop, w_index, w_axis, w_inward,
                      w_rest, w_mu, w_impact, struck, use_threshold, threshold, tolerance,
                      strike, friction, planar, w_hit, w_normal, w_tangential, loss, totals,
                      spin, accumulate, w_acc, w_acc_impact, w_acc_t, warm_dv, warmed):
    """Solve one wall plane's contacts (distinct particles); return whether any changed.

    ``spin``: each particle's ``spin_factor`` (used with friction only).
    With ``accumulate`` the resting impulse of each contact is accumulated
    (``w_acc``) and may be taken back down to 0 when the particle leaves the
    plane (see ``solve_contacts``); impact impulses go to ``w_acc_impact``,
    and a bounce never reflects the closing speed that warm pushes added
    (``warm_dv``, the velocity change of each ``warmed`` particle).
    """
    any_hit = False
    for c in range(start, stop):
        p, axis, inward = w_index[c], w_axis[c], w_inward[c]
        e = w_rest[c]
        if use_threshold:
            u = inward * v[p, axis]
            if not (-u >= threshold and (w_impact[c] or struck[p])):
                e = 0.0
        approach = -inward * v[p, axis]
        if approach > tolerance:
            bounce = approach
            if accumulate and e > 0.0 and warmed[p]:
                bounce = min(approach, max(approach + inward * warm_dv[p, axis], 0.0))
            if bounce < approach:
                change = approach + e * bounce
                v[p, axis] += inward * change
                magnitude = change / inv_mass[p]
                removed = 0.5 * magnitude * (approach - e * bounce)
            else:
                change = (1.0 + e) * approach
                v[p, axis] += inward * change
                magnitude = change / inv_mass[p]
                removed = 0.5 * magnitude * approach * (1.0 - e)
            if use_threshold and e > 0.0 and bounce >= strike * threshold:
                struck[p] = True
            w_hit[c] = True
            if accumulate:
                if w_impact[c] or e > 0.0:
                    w_acc_impact[c] += magnitude
                else:
                    w_acc[c] += magnitude
        elif accumulate and approach < -tolerance and w_acc[c] > 0.0:
            # Leaving the plane with resting impulse to give back: take back
            # what stops it leaving, at most the accumulated impulse (beyond
            # the tolerance, as an approach; the shock stage's wall visits
            # run at tolerance 0 and take back every leaving).
            magnitude = max(approach / inv_mass[p], -w_acc[c])
            change = magnitude * inv_mass[p]
            v[p, axis] += inward * change
            removed = -(magnitude * 0.5 * (-approach + (-approach + change)))
            w_acc[c] += magnitude
        else:
            continue
        any_hit = True
        _book(loss, WALLS, p, removed)
        totals[WALLS] += removed
        w_normal[c] += magnitude
        if friction:
            nx = inward if axis == 0 else 0.0
            ny = inward if axis == 1 else 0.0
            nz = inward if axis == 2 else 0.0
            if accumulate:
                tangential, lost = _friction_acc(v, ang, inv_mass, radius, p, -1, nx, ny, nz,
                                                 w_acc[c] + w_acc_impact[c], w_mu[c], planar,
                                                 spin[p], 0.0, w_acc_t, c)
            else:
                tangential, lost = _friction_spun(v, ang, inv_mass, radius, p, -1, nx, ny, nz,
                                                  magnitude, w_mu[c], planar, spin[p], 0.0)
            _book(loss, FRICTION, p, lost)
            totals[FRICTION] += lost
            w_tangential[c] += tangential
    return any_hit


@njit(cache=True)
def _solve_walls(v, ang, inv_mass, radius, w_start, w_index, w_axis, w_inward, w_rest, w_mu,
                 w_impact, struck, use_threshold, threshold, tolerance, strike, friction,
                 planar, w_hit, w_normal, w_tangential, loss, totals, w_approach, first,
                 spin, accumulate, w_acc, w_acc_impact, w_acc_t, warm_dv, warmed):
    """Solve every wall plane once, plane after plane; return whether any changed.

    On the ``first`` visit each plane's contacts keep the approach speed they
    are recorded with, just before that plane is solved (an earlier plane's
    friction may have changed it at a corner).
    """
    any_hit = False
    for plane in range(w_start.size - 1):
        if first:
            for c in range(w_start[plane], w_start[plane + 1]):
                w_approach[c] = -w_inward[c] * v[w_index[c], w_axis[c]]
        if _solve_wall_plane(v, ang, inv_mass, radius, w_start[plane], w_start[plane + 1],
                             w_index, w_axis, w_inward, w_rest, w_mu, w_impact, struck,
                             use_threshold, threshold, tolerance, strike, friction, planar,
                             w_hit, w_normal, w_tangential, loss, totals, spin, accumulate,
                             w_acc, w_acc_impact, w_acc_t, warm_dv, warmed):
            any_hit = True
    return any_hit


@njit(cache=True)
def _shock_rows(pi, pj, normal, i_lower, shock_order):
    """Return each pair's (lower, upper, N lower -> upper) in ``shock_order``.

    Gathered once per solve for the up to 2 * SHOCK_PASSES passes that walk
    them: rows in the order they are visited, and no branch on which side
    is the lower one (the same values, N negated exactly).
    """
    size = shock_order.size
    low, up, out = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64), \
        np.empty((size, 3))
    for s in range(size):
        k = shock_order[s]
        if i_lower[k]:
            low[s], up[s] = pi[k], pj[k]
            out[s, 0], out[s, 1], out[s, 2] = -normal[k, 0], -normal[k, 1], -normal[k, 2]
        else:
            low[s], up[s] = pj[k], pi[k]
            out[s, 0], out[s, 1], out[s, 2] = normal[k, 0], normal[k, 1], normal[k, 2]
    return low, up, out


@njit(cache=True)
def _shock_pass(v, inv_mass, dynamic, s_low, s_up, s_out, shock_order, threshold, pushed,
                loss, totals):
    """One shock-propagation pass in ``shock_order`` (ground up); return whether it pushed.

    The law of ``SequentialImpulseStage._shock_pass``: the upper particle's
    approach along the line of action is stopped against the lower one
    (never lifted), the work of the impulse booked as 'restitution'. The
    pairs come as ``_shock_rows`` gathers them.
    """
    any_push = False
    for s in range(shock_order.size):
        k, low, up = shock_order[s], s_low[s], s_up[s]
        nx, ny, nz = s_out[s, 0], s_out[s, 1], s_out[s, 2]
        u_upper = _dot(v[up, 0], v[up, 1], v[up, 2], nx, ny, nz)
        u_lower = _dot(v[low, 0], v[low, 1], v[low, 2], nx, ny, nz)
        target = min(u_lower, 0.0)
        if not (u_upper < target - 0.0 and u_lower - u_upper < threshold and dynamic[up]):
            continue
        w = inv_mass[up]
        magnitude = (target - u_upper) / w
        px, py, pz = magnitude * nx, magnitude * ny, magnitude * nz
        removed = -(_dot(v[up, 0], v[up, 1], v[up, 2], px, py, pz)
                    + 0.5 * w * _dot(px, py, pz, px, py, pz))
        v[up, 0] += w * px
        v[up, 1] += w * py
        v[up, 2] += w * pz
        _book(loss, RESTITUTION, up, removed)
        totals[RESTITUTION] += removed
        pushed[k] += magnitude
        any_push = True
    return any_push


@njit(cache=True)
def _take_back_pairs(v, inv_mass, pi, pj, normal, order, acc, share, summed_normal, loss,
                     totals):
    """One pass in ``order`` taking back the resting impulse of every opening pair.

    The sweeps take back only beyond the tolerance; this leaves no pair
    opening under a resting impulse it holds (momentum conserved, the work
    booked as 'restitution').
    """
    for k in order:
        if not acc[k] > 0.0:
            continue
        a, b = pi[k], pj[k]
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        approach = -_dot(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
        if not approach < 0.0:
            continue
        magnitude = max(approach / (inv_mass[a] + inv_mass[b]), -acc[k])
        removed = _push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
        acc[k] += magnitude
        _book_pair(loss, RESTITUTION, a, b, removed, share[k])
        totals[RESTITUTION] += removed
        summed_normal[k] += magnitude


@njit(cache=True)
def _take_back_pass(v, inv_mass, dynamic, s_low, s_up, s_out, shock_order, acc, pushed,
                    loss, totals):
    """Take back resting impulse the sweeps left pushing contacts open; return whether any.

    The counterpart of ``_shock_pass`` for accumulated impulses: warm pushes
    the sweeps' budget did not finish correcting leave resting contacts
    opening (a column flies apart by a fraction of g dt). Ground up, the
    upper particle of a contact that holds resting impulse and opens is
    slowed along the line of action to the lower one's speed (never below
    0: it is not pulled down), taking back at most that impulse. Only the
    upper particle's kinetic energy changes and it only falls; the work is
    booked as 'restitution'.
    """
    any_taken = False
    for s in range(shock_order.size):
        k = shock_order[s]
        if not acc[k] > 0.0:
            continue
        low, up = s_low[s], s_up[s]
        nx, ny, nz = s_out[s, 0], s_out[s, 1], s_out[s, 2]
        if not dynamic[up]:
            continue
        u_upper = _dot(v[up, 0], v[up, 1], v[up, 2], nx, ny, nz)
        u_lower = _dot(v[low, 0], v[low, 1], v[low, 2], nx, ny, nz)
        target = max(u_lower, 0.0)
        if not u_upper > target:
            continue
        w = inv_mass[up]
        magnitude = max((target - u_upper) / w, -acc[k])
        px, py, pz = magnitude * nx, magnitude * ny, magnitude * nz
        removed = -(_dot(v[up, 0], v[up, 1], v[up, 2], px, py, pz)
                    + 0.5 * w * _dot(px, py, pz, px, py, pz))
        v[up, 0] += w * px
        v[up, 1] += w * py
        v[up, 2] += w * pz
        acc[k] += magnitude
        _book(loss, RESTITUTION, up, removed)
        totals[RESTITUTION] += removed
        pushed[k] += magnitude
        any_taken = True
    return any_taken


@njit(cache=True)
def _warm_tangential(v, ang, inv_mass, radius, a, b, nx, ny, nz, bound, planar, f_a, f_b,
                     acc_t, row):
    """Apply a contact's cached tangential impulse, clamped into ``bound``; return J removed.

    The cached impulse is projected on today's tangent plane (the normal
    may have turned) and clamped into the cone of today's warm normal
    impulse; what is applied is booked by its exact work on the slip.
    """
    qx, qy, qz = acc_t[row, 0], acc_t[row, 1], acc_t[row, 2]
    qn = _dot(qx, qy, qz, nx, ny, nz)
    qx, qy, qz = qx - qn * nx, qy - qn * ny, qz - qn * nz
    if planar:
        qz = 0.0
    size = math.sqrt(_dot(qx, qy, qz, qx, qy, qz))
    if size > bound:
        scale = bound / size
        qx, qy, qz = qx * scale, qy * scale, qz * scale
    acc_t[row, 0], acc_t[row, 1], acc_t[row, 2] = qx, qy, qz
    if qx == 0.0 and qy == 0.0 and qz == 0.0:
        return 0.0
    tx, ty, tz, w_sum = _slip(v, ang, inv_mass, radius, a, b, nx, ny, nz, planar)
    k = STICK_FACTOR * w_sum
    removed = -(_dot(qx, qy, qz, tx, ty, tz) + 0.5 * k * _dot(qx, qy, qz, qx, qy, qz))
    _apply_tangential(v, ang, inv_mass, a, b, nx, ny, nz, qx, qy, qz, f_a, f_b)
    return removed


@njit(cache=True)
def _warm_start(v, ang, inv_mass, radius, pi, pj, normal, mu, impact, acc, acc_t, share,
                w_index, w_axis, w_inward, w_mu, w_impact, w_acc, w_acc_t, friction, planar,
                spin, summed_normal, w_normal, loss, totals):
    """Apply the cached resting impulses of the contacts that persist (not new impacts).

    ``acc`` / ``w_acc`` hold the previous step's accumulated resting normal
    impulse per contact (0 for a new contact), ``acc_t`` / ``w_acc_t`` its
    tangential one; an impact's entries are cleared (an impact starts from
    nothing, as without warm starting). Each impulse is booked by its own
    work (``_push_pair``): a warm impulse on a contact that has opened adds
    energy that is booked as a negative loss, and the sweeps take it back
    (the accumulated impulse is clamped at 0).
    """
    for k in range(pi.size):
        if impact[k] or not acc[k] > 0.0:
            acc[k] = 0.0
            acc_t[k, 0] = acc_t[k, 1] = acc_t[k, 2] = 0.0
            continue
        a, b = pi[k], pj[k]
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        approach = -_dot(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
        removed = _push_pair(v, inv_mass, a, b, nx, ny, nz, acc[k], approach)
        _book_pair(loss, RESTITUTION, a, b, removed, share[k])
        totals[RESTITUTION] += removed
        summed_normal[k] += acc[k]
        if friction:
            lost = _warm_tangential(v, ang, inv_mass, radius, a, b, nx, ny, nz, mu[k] * acc[k],
                                    planar, spin[a], spin[b], acc_t, k)
            _book_pair(loss, FRICTION, a, b, lost, share[k])
            totals[FRICTION] += lost
        else:
            acc_t[k, 0] = acc_t[k, 1] = acc_t[k, 2] = 0.0
    for c in range(w_index.size):
        if w_impact[c] or not w_acc[c] > 0.0:
            w_acc[c] = 0.0
            w_acc_t[c, 0] = w_acc_t[c, 1] = w_acc_t[c, 2] = 0.0
            continue
        p, axis, inward = w_index[c], w_axis[c], w_inward[c]
        approach = -inward * v[p, axis]
        change = w_acc[c] * inv_mass[p]
        v[p, axis] += inward * change
        removed = -(w_acc[c] * 0.5 * (-approach + (-approach + change)))
        _book(loss, WALLS, p, removed)
        totals[WALLS] += removed
        w_normal[c] += w_acc[c]
        if friction:
            nx = inward if axis == 0 else 0.0
            ny = inward if axis == 1 else 0.0
            nz = inward if axis == 2 else 0.0
            lost = _warm_tangential(v, ang, inv_mass, radius, p, -1, nx, ny, nz,
                                    w_mu[c] * w_acc[c], planar, spin[p], 0.0, w_acc_t, c)
            _book(loss, FRICTION, p, lost)
            totals[FRICTION] += lost
        else:
            w_acc_t[c, 0] = w_acc_t[c, 1] = w_acc_t[c, 2] = 0.0


@njit(cache=True, nogil=True)
def solve_contacts(v, ang, inv_mass, radius, dynamic, pi, pj, normal, rest, mu, order,
                   w_start, w_index, w_axis, w_inward, w_rest, w_mu,
                   use_threshold, threshold, tolerance, strike, iterations, friction, planar,
                   shock_order, i_lower, shock_passes,
                   hit, summed_normal, summed_tangential, w_hit, w_normal, w_tangential,
                   w_approach, loss, totals, accumulate, acc, acc_t, w_acc, w_acc_t):
    """Run one contact solve in place; return the sweeps run. See ``SequentialImpulseStage``.

    Sweeps visit the pairs in ``order``, then each wall plane, until no
    contact's impulse changes by more than ``tolerance`` times its mass
    (its velocity change) or ``iterations`` sweeps are done; then, if
    ``shock_order`` is not empty, walls and up to ``shock_passes`` shock
    passes. Outputs are filled in place: per pair ``hit`` and summed
    impulses, per wall contact the same and its approach speed at its first
    visit, per particle and effect the energy removed (``loss``, rows as
    ``EFFECTS``) and per effect the total (``totals``).

    With ``accumulate`` (a restitution threshold is set), impulses at
    contacts below the threshold (resting, e = 0, target separating speed
    0) are accumulated per contact in ``acc`` (normal, >= 0) and ``acc_t``
    (tangential on i, inside the Coulomb cone of the contact's accumulated
    normal impulse), clamped: a contact that opens gets its resting
    impulse taken back, down to 0. On entry ``acc`` / ``acc_t`` (and the
    wall arrays) hold the previous step's values for contacts that persist
    (warm start, applied first to contacts that are not new impacts); on
    return, this solve's. Each contact's class is fixed at the start: one
    closing faster than the threshold before any warm push is an impact for
    the whole solve (its impulses, and any with e > 0 by the 'struck' rule,
    are the law's, never taken back and not cached); every other contact is
    resting, whatever a warm push makes it do. A bounce never reflects the
    closing speed warm pushes added (``warm_dv``). Resting impulse left
    pushing an opening contact after the sweeps is taken back
    (``_take_back_pairs``, and ``_take_back_pass`` beside the shock passes).
    A warm impulse is not counted in ``hit`` (no collision).
    """
    n = v.shape[0]
    m = pi.size
    struck = np.zeros(n, dtype=np.bool_)
    impact = np.zeros(m, dtype=np.bool_)
    w_impact = np.zeros(w_index.size, dtype=np.bool_)
    acc_impact = np.zeros(m)
    w_acc_impact = np.zeros(w_index.size)
    if use_threshold:
        for k in range(m):
            a, b = pi[k], pj[k]
            impact[k] = -_dot(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2],
                              normal[k, 0], normal[k, 1], normal[k, 2]) >= threshold
        for c in range(w_index.size):
            w_impact[c] = -w_inward[c] * v[w_index[c], w_axis[c]] >= threshold
    # No dynamic particle in two pairs and no wall: one sweep resolves every
    # pair (vn' = -e vn >= 0), so a checking sweep is skipped, as for one batch.
    count = np.zeros(n, dtype=np.int64)
    single = w_index.size == 0
    for k in range(m):
        for p in (pi[k], pj[k]):
            if dynamic[p]:
                count[p] += 1
                if count[p] > 1:
                    single = False
    walls = w_start.size > 1
    first_wall_visit = True
    # The loss shares and spin factors are fixed for the solve: computed once,
    # not at each of up to ``iterations`` visits (the same values).
    share = np.empty(m)
    for k in range(m):
        share[k] = _share(inv_mass, pi[k], pj[k])
    spin = np.zeros(n)
    if friction:
        for p in range(n):
            spin[p] = spin_factor(inv_mass, radius, p)
    warm_dv = np.zeros((n if accumulate else 0, 3))
    warmed = np.zeros(n if accumulate else 0, dtype=np.bool_)
    if accumulate:
        for p in range(n):
            warm_dv[p, 0], warm_dv[p, 1], warm_dv[p, 2] = v[p, 0], v[p, 1], v[p, 2]
        _warm_start(v, ang, inv_mass, radius, pi, pj, normal, mu, impact, acc, acc_t, share,
                    w_index, w_axis, w_inward, w_mu, w_impact, w_acc, w_acc_t, friction,
                    planar, spin, summed_normal, w_normal, loss, totals)
        # What the warm pushes changed, per particle.
        for p in range(n):
            for d in range(3):
                warm_dv[p, d] = v[p, d] - warm_dv[p, d]
                if warm_dv[p, d] != 0.0:
                    warmed[p] = True
    sweeps = 0
    for _ in range(iterations):
        sweeps += 1
        applied = False
        for k in order:
            a, b = pi[k], pj[k]
            nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
            # The closing speed is read once: it decides both whether the pair
            # gets an impulse and, against the threshold, its e.
            approach = -_dot(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2],
                             nx, ny, nz)
            if approach > tolerance:
                e = rest[k]
                if use_threshold:
                    if not (approach >= threshold and (impact[k] or struck[a] or struck[b])):
                        e = 0.0
                bounce = approach
                if accumulate and e > 0.0 and (warmed[a] or warmed[b]):
                    # A bounce reflects the closing speed the impacts made,
                    # never what the warm pushes added to it: with e = 1 that
                    # excess would leave at full speed and add energy.
                    bounce = min(approach, max(approach + _dot(
                        warm_dv[a, 0] - warm_dv[b, 0], warm_dv[a, 1] - warm_dv[b, 1],
                        warm_dv[a, 2] - warm_dv[b, 2], nx, ny, nz), 0.0))
                if bounce < approach:
                    magnitude = (approach + e * bounce) / (inv_mass[a] + inv_mass[b])
                    removed = _push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
                else:
                    magnitude, removed = _apply_pair(v, inv_mass, a, b, nx, ny, nz, e,
                                                     approach)
                if use_threshold and e > 0.0 and bounce >= strike * threshold:
                    # A static particle never moves, so it passes no shock on.
                    struck[a] = dynamic[a]
                    struck[b] = dynamic[b]
                hit[k] = True
                if accumulate:
                    # Closing faster than the threshold: an impact's impulse,
                    # never taken back or cached; slower: resting.
                    if impact[k] or e > 0.0:
                        acc_impact[k] += magnitude
                    else:
                        acc[k] += magnitude
            elif accumulate and approach < -tolerance and acc[k] > 0.0:
                # Opening with resting impulse to give back (e.g. from the warm
                # start): take back what stops it opening, at most all of it.
                # Beyond the tolerance only, as an approach: a converged
                # contact costs a dot product per sweep; ``_take_back_pairs``
                # takes back what is left below it after the sweeps.
                magnitude = max(approach / (inv_mass[a] + inv_mass[b]), -acc[k])
                removed = _push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
                acc[k] += magnitude
            else:
                continue
            applied = True
            _book_pair(loss, RESTITUTION, a, b, removed, share[k])
            totals[RESTITUTION] += removed
            summed_normal[k] += magnitude
            if friction:
                if accumulate:
                    tangential, lost = _friction_acc(v, ang, inv_mass, radius, a, b, nx, ny, nz,
                                                     acc[k] + acc_impact[k], mu[k], planar,
                                                     spin[a], spin[b], acc_t, k)
                else:
                    tangential, lost = _friction_spun(v, ang, inv_mass, radius, a, b, nx, ny,
                                                      nz, magnitude, mu[k], planar, spin[a],
                                                      spin[b])
                _book_pair(loss, FRICTION, a, b, lost, share[k])
                totals[FRICTION] += lost
                summed_tangential[k] += tangential
        if walls:
            if _solve_walls(v, ang, inv_mass, radius, w_start, w_index, w_axis, w_inward,
                            w_rest, w_mu, w_impact, struck, use_threshold, threshold,
                            tolerance, strike, friction, planar, w_hit, w_normal,
                            w_tangential, loss, totals, w_approach, first_wall_visit, spin,
                            accumulate, w_acc, w_acc_impact, w_acc_t, warm_dv, warmed):
                applied = True
            first_wall_visit = False
        if not applied or single:
            break
    if accumulate:
        _take_back_pairs(v, inv_mass, pi, pj, normal, order, acc, share, summed_normal, loss,
                         totals)
    if shock_order.size:
        _solve_walls(v, ang, inv_mass, radius, w_start, w_index, w_axis, w_inward, w_rest,
                     w_mu, w_impact, struck, use_threshold, threshold, 0.0, strike, friction,
                     planar, w_hit, w_normal, w_tangential, loss, totals, w_approach, False,
                     spin, accumulate, w_acc, w_acc_impact, w_acc_t, warm_dv, warmed)
        s_low, s_up, s_out = _shock_rows(pi, pj, normal, i_lower, shock_order)
        for _ in range(shock_passes):
            taken = False
            if accumulate:
                taken = _take_back_pass(v, inv_mass, dynamic, s_low, s_up, s_out,
                                        shock_order, acc, summed_normal, loss, totals)
            pushed = _shock_pass(v, inv_mass, dynamic, s_low, s_up, s_out, shock_order,
                                 threshold, summed_normal, loss, totals)
            _solve_walls(v, ang, inv_mass, radius, w_start, w_index, w_axis, w_inward,
                         w_rest, w_mu, w_impact, struck, use_threshold, threshold, 0.0,
                         strike, friction, planar, w_hit, w_normal, w_tangential, loss,
                         totals, w_approach, False, spin, accumulate, w_acc, w_acc_impact,
                         w_acc_t, warm_dv, warmed)
            if not pushed and not taken:
                break
    return sweeps


@njit(cache=True)
def _find_key(table, key):
    """Return the first row of sorted ``table`` holding ``key``, or -1 (binary search)."""
    lo, hi = 0, table.size
    while lo < hi:
        mid = (lo + hi) >> 1
        if table[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    if lo < table.size and table[lo] == key:
        return lo
    return -1


@njit(cache=True)
def find_wall_contacts(position, radius, dynamic, p_axis, p_plane, p_inward, p_ulps, slop):
    """Return (start per plane, particle, axis, inward) of the particles touching each plane.

    As ``SequentialImpulseStage._wall_contacts``: a dynamic particle whose gap
    to the plane is at most ``slop`` times its radius plus the plane's
    ``p_ulps`` (WALL_ULPS spacings at its coordinate), plane after plane, in
    particle order. ``start`` has one entry per plane and one more (a plane
    nothing touches is an empty run).
    """
    n, planes = position.shape[0], p_axis.size
    start = np.zeros(planes + 1, dtype=np.int64)
    index = np.empty(n * planes, dtype=np.int64)
    k = 0
    for q in range(planes):
        axis, plane, inward = p_axis[q], p_plane[q], p_inward[q]
        for p in range(n):
            gap = inward * (position[p, axis] - plane) - radius[p]
            if dynamic[p] and gap <= slop * radius[p] + p_ulps[q]:
                index[k] = p
                k += 1
        start[q + 1] = k
    axes = np.empty(k, dtype=np.int64)
    inwards = np.empty(k)
    for q in range(planes):
        for c in range(start[q], start[q + 1]):
            axes[c], inwards[c] = p_axis[q], p_inward[q]
    return start, index[:k].copy(), axes, inwards


@njit(cache=True)
def _ascending(keys):
    """Say whether ``keys`` never decrease (then their stable order is the identity)."""
    for c in range(1, keys.size):
        if keys[c] < keys[c - 1]:
            return False
    return True


@njit(cache=True)
def _stable_order(keys):
    """Return the stable ascending order of ``keys`` (numpy's argsort kind='stable')."""
    return np.argsort(keys, kind='mergesort')


@njit(cache=True, nogil=True)
def solve_step(v, ang, position, inv_mass, radius, ids, pi, pj, normal, rest_in, mu_in,
               colours, order_in, p_axis, p_plane, p_inward, p_ulps, slop, w_rest_in,
               w_mu_in, use_threshold, threshold, tolerance, strike, iterations, friction,
               planar, shock, height, shock_in, shock_passes, booked, accumulate, max_id,
               c_key, c_normal, c_tangential, cw_key, cw_normal, cw_tangential):
    """Run a whole step's contact solve in one call: set-up, ``solve_contacts``, cache.

    The set-up ``SequentialImpulseStage`` did in numpy, with the same values:
    the wall contacts (``find_wall_contacts``), coefficients broadcast from a
    single value (``rest_in``, ``mu_in`` per pair; ``w_rest_in``, ``w_mu_in``
    per particle), the visit order (``order_in`` with ``colours``, else the
    pairs in order), with ``shock`` the shock passes' order (``shock_in``
    with ``colours``, else the pairs by the ``height`` of their lower
    particle, stable), the
    warm start looked up in the contact cache (sorted keys: ``c_key`` of
    pairs, lower id * (max_id + 1) + higher id, tangential impulses on the
    lower id; ``cw_key`` of wall contacts, id * 8 + axis * 2 + (inward > 0)),
    and the cache of this solve, sorted the same way. ``booked`` (the step's
    losses per particle so far, or empty) is updated in place.

    Returns (sweeps, totals per effect, hit, summed normal and tangential
    impulse per pair, the wall contacts' start per plane, particle, axis,
    inward, hit, normal and tangential impulse and first approach speed,
    then the new cache: pair keys, normal, tangential, wall keys, normal,
    tangential).
    """
    n, m = v.shape[0], pi.size
    dynamic = np.empty(n, dtype=np.bool_)
    for p in range(n):
        dynamic[p] = inv_mass[p] > 0.0
    w_start, w_index, w_axis, w_inward = find_wall_contacts(
        position, radius, dynamic, p_axis, p_plane, p_inward, p_ulps, slop)
    k = w_index.size
    rest = np.empty(m)
    mu = np.empty(m)
    for c in range(m):
        rest[c] = rest_in[c if rest_in.size > 1 else 0]
        mu[c] = mu_in[c if mu_in.size > 1 else 0] if friction else 0.0
    w_rest = np.empty(k)
    w_mu = np.zeros(k)
    for c in range(k):
        p = w_index[c]
        w_rest[c] = w_rest_in[p if w_rest_in.size > 1 else 0]
        if friction:
            w_mu[c] = w_mu_in[p if w_mu_in.size > 1 else 0]
    order = order_in if colours else np.arange(m)
    shock_order = np.zeros(0, dtype=np.int64)
    i_lower = np.zeros(m, dtype=np.bool_)
    if shock and m:
        lower_height = np.empty(m)
        for c in range(m):
            i_lower[c] = height[pi[c]] <= height[pj[c]]
            lower_height[c] = height[pi[c]] if i_lower[c] else height[pj[c]]
        shock_order = shock_in if colours else _stable_order(lower_height)
    acc, acc_t = np.zeros(m), np.zeros((m, 3))
    w_acc, w_acc_t = np.zeros(k), np.zeros((k, 3))
    # Ids past max_id would overflow the keys: such a world keeps no cache.
    keyed = accumulate
    for p in range(n):
        if ids[p] > max_id:
            keyed = False
    stride = max_id + 1
    if keyed and c_key.size:
        keys = np.empty(m, dtype=np.int64)
        for c in range(m):
            a, b = ids[pi[c]], ids[pj[c]]
            keys[c] = min(a, b) * stride + max(a, b)
        # The broadphase's pairs come sorted by row, and rows by id unless ids
        # were reordered: then one merge walk finds every key (the first row
        # holding it, as the binary search would).
        merge = _ascending(keys)
        row = 0
        for c in range(m):
            a, b = ids[pi[c]], ids[pj[c]]
            if merge:
                while row < c_key.size and c_key[row] < keys[c]:
                    row += 1
                found = row if row < c_key.size and c_key[row] == keys[c] else -1
            else:
                found = _find_key(c_key, keys[c])
            if found >= 0:
                sign = -1.0 if a > b else 1.0
                acc[c] = c_normal[found]
                for d in range(3):
                    acc_t[c, d] = c_tangential[found, d] * sign
    if keyed:
        for c in range(k if cw_key.size else 0):
            row = _find_key(cw_key, ids[w_index[c]] * 8 + w_axis[c] * 2
                            + (1 if w_inward[c] > 0.0 else 0))
            if row >= 0:
                w_acc[c] = cw_normal[row]
                for d in range(3):
                    w_acc_t[c, d] = cw_tangential[row, d]
    hit = np.zeros(m, dtype=np.bool_)
    summed_normal, summed_tangential = np.zeros(m), np.zeros(m)
    w_hit = np.zeros(k, dtype=np.bool_)
    w_normal, w_tangential, w_approach = np.zeros(k), np.zeros(k), np.zeros(k)
    loss = np.zeros((len(EFFECTS) + 1, n))
    for p in range(booked.size):
        loss[BOOKED, p] = booked[p]
    totals = np.zeros(len(EFFECTS))
    sweeps = solve_contacts(
        v, ang, inv_mass, radius, dynamic, pi, pj, normal, rest, mu, order, w_start, w_index,
        w_axis, w_inward, w_rest, w_mu, use_threshold, threshold, tolerance, strike,
        iterations, friction, planar, shock_order, i_lower, shock_passes, hit, summed_normal,
        summed_tangential, w_hit, w_normal, w_tangential, w_approach, loss, totals,
        accumulate, acc, acc_t, w_acc, w_acc_t)
    for p in range(booked.size):
        booked[p] = loss[BOOKED, p]
    # This solve's cache: contacts holding resting impulse, sorted by key.
    kept = 0
    for c in range(m):
        if keyed and acc[c] > 0.0:
            kept += 1
    keys = np.empty(kept, dtype=np.int64)
    rows = np.empty(kept, dtype=np.int64)
    kept = 0
    for c in range(m):
        if keyed and acc[c] > 0.0:
            a, b = ids[pi[c]], ids[pj[c]]
            keys[kept], rows[kept] = min(a, b) * stride + max(a, b), c
            kept += 1
    sorted_rows = np.arange(kept) if _ascending(keys) else _stable_order(keys)
    new_key = np.empty(kept, dtype=np.int64)
    new_normal, new_tangential = np.empty(kept), np.empty((kept, 3))
    for s in range(kept):
        c = rows[sorted_rows[s]]
        new_key[s] = keys[sorted_rows[s]]
        new_normal[s] = acc[c]
        sign = -1.0 if ids[pi[c]] > ids[pj[c]] else 1.0
        for d in range(3):
            new_tangential[s, d] = acc_t[c, d] * sign
    kept = 0
    for c in range(k):
        if keyed and w_acc[c] > 0.0:
            kept += 1
    keys = np.empty(kept, dtype=np.int64)
    rows = np.empty(kept, dtype=np.int64)
    kept = 0
    for c in range(k):
        if keyed and w_acc[c] > 0.0:
            keys[kept] = ids[w_index[c]] * 8 + w_axis[c] * 2 + (1 if w_inward[c] > 0.0 else 0)
            rows[kept] = c
            kept += 1
    sorted_rows = _stable_order(keys)
    new_w_key = np.empty(kept, dtype=np.int64)
    new_w_normal, new_w_tangential = np.empty(kept), np.empty((kept, 3))
    for s in range(kept):
        c = rows[sorted_rows[s]]
        new_w_key[s] = keys[sorted_rows[s]]
        new_w_normal[s] = w_acc[c]
        for d in range(3):
            new_w_tangential[s, d] = w_acc_t[c, d]
    return (sweeps, totals, hit, summed_normal, summed_tangential, w_start, w_index, w_axis,
            w_inward, w_hit, w_normal, w_tangential, w_approach, new_key, new_normal,
            new_tangential, new_w_key, new_w_normal, new_w_tangential)


@njit(cache=True)
def line_of_action(ox, oy, oz, rx, ry, rz):
    """Return (N, |offset|) of one offset, as ``narrowphase.line_of_action`` (same operations).

    The offset is scaled by its largest component first; coincident centres
    take -(relative velocity) as N, or +x when they do not move apart.
    """
    scale = max(abs(ox), abs(oy), abs(oz))
    if scale != 0.0:
        sx, sy, sz = ox / scale, oy / scale, oz / scale
        norm = math.sqrt(_dot(sx, sy, sz, sx, sy, sz))
        return sx / norm, sy / norm, sz / norm, scale * norm
    rv_scale = max(abs(rx), abs(ry), abs(rz))
    if rv_scale > 0.0:
        ux, uy, uz = rx / rv_scale, ry / rv_scale, rz / rv_scale
        norm = math.sqrt(_dot(ux, uy, uz, ux, uy, uz))
        return -(ux / norm), -(uy / norm), -(uz / norm), 0.0
    return 1.0, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def find_overlaps(position, velocity, radius, inv_mass, ci, cj, out_i, out_j, normal,
                  penetration):
    """Keep the candidate pairs that overlap (``narrowphase.find_contacts``); return how many.

    Writes the kept pairs, their normals and penetrations to the front of the
    output arrays (sized for every candidate), in candidate order.
    """
    kept = 0
    for k in range(ci.size):
        a, b = ci[k], cj[k]
        ox = position[a, 0] - position[b, 0]
        oy = position[a, 1] - position[b, 1]
        oz = position[a, 2] - position[b, 2]
        reach = radius[a] + radius[b]
        # The numpy path's generous prefilter, kept so both keep the same pairs.
        if not _dot(ox, oy, oz, ox, oy, oz) <= reach * reach * (1.0 + 1e-9):
            continue
        if not (inv_mass[a] + inv_mass[b]) > 0.0:
            continue
        nx, ny, nz, distance = line_of_action(
            ox, oy, oz, velocity[a, 0] - velocity[b, 0], velocity[a, 1] - velocity[b, 1],
            velocity[a, 2] - velocity[b, 2])
        if not distance < reach:
            continue
        out_i[kept], out_j[kept] = a, b
        normal[kept, 0], normal[kept, 1], normal[kept, 2] = nx, ny, nz
        penetration[kept] = reach - distance
        kept += 1
    return kept


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


@njit(cache=True, nogil=True)
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
def _root(parent, p):
    """Return the root of ``p`` in a union-find forest, halving the path on the way."""
    while parent[p] != p:
        parent[p] = parent[parent[p]]
        p = parent[p]
    return p


@njit(cache=True, nogil=True)
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
            ra, rb = _root(parent, a), _root(parent, b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    cluster = np.empty(n, dtype=np.int64)
    lifted = np.zeros(n)
    spent = np.zeros(n)
    for p in range(n):
        c = _root(parent, p)
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
        along = max(_dot(velocity[p, 0], velocity[p, 1], velocity[p, 2], wx, wy, wz), 0.0)
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
    from .coloring import greedy_colors
    v = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    ang = np.zeros((2, 3))
    inv_mass, radius = np.ones(2), np.ones(2)
    dynamic = np.ones(2, dtype=bool)
    pi, pj = np.array([1], dtype=np.int64), np.array([0], dtype=np.int64)
    normal = np.array([[-1.0, 0.0, 0.0]])
    one = np.ones(1)
    walls = np.array([0, 1], dtype=np.int64)
    solve_contacts(v, ang, inv_mass, radius, dynamic, pi, pj, normal, one, one,
                   np.zeros(1, dtype=np.int64), walls, np.zeros(1, dtype=np.int64),
                   np.zeros(1, dtype=np.int64), one, one, one, True, 0.1, 1e-4, 10.0, 4,
                   True, True, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=bool), 2,
                   np.zeros(1, dtype=bool), np.zeros(1), np.zeros(1), np.zeros(1, dtype=bool),
                   np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((4, 2)), np.zeros(3),
                   True, np.ones(1), np.ones((1, 3)), np.ones(1), np.ones((1, 3)))
    greedy_colors(pi, pj, dynamic, 32)
    # The whole step's solve: a floor under the pair, both warm-started from a cache.
    position = np.array([[0.0, 1.0, 0.0], [1.9, 1.0, 0.0]])
    ids = np.array([0, 1], dtype=np.int64)
    key = np.array([1], dtype=np.int64)
    floor = np.zeros(1, dtype=np.int64)
    solve_step(v, ang, position, inv_mass, radius, ids, pi, pj, normal, one, one, False,
               np.zeros(0, dtype=np.int64), floor, np.zeros(1), one, np.zeros(1), 1e-9, one,
               one, True, 0.1, 1e-4, 10.0, 4, True, True, True, np.array([1.0, 1.0]),
               np.zeros(0, dtype=np.int64), 2, np.zeros(2), True, 2 ** 31 - 1, key, one,
               np.ones((1, 3)), np.array([3], dtype=np.int64), one, np.ones((1, 3)))
    # Narrowphase and separation (a pair 1.9 m apart with radii 1 m overlaps).
    position = np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]])
    out_i, out_j = np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64)
    found_normal, found_penetration = np.zeros((1, 3)), np.zeros(1)
    find_overlaps(position, v, radius, inv_mass, pi, pj, out_i, out_j, found_normal,
                  found_penetration)
    low, high = np.full(3, -10.0), np.full(3, 10.0)
    start = position.copy()
    project_overlaps(position, v, inv_mass, radius, dynamic, pi, pj, found_normal,
                     found_penetration, 2, True, True, low, high, 3, np.zeros(1, dtype=np.int64),
                     np.full(1, -10.0), np.ones(1))
    pay_for_lift(position, start, v, inv_mass, dynamic, pi, pj, np.ones(2), np.zeros(2))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    from .coloring import greedy_colors
    return [solve_contacts, solve_step, greedy_colors, find_overlaps, project_overlaps,
            pay_for_lift]
