"""The contact solve, compiled: one contact at a time, in loops numba compiles.

``solve_step`` runs a whole step's contact solve of
``sequential_impulses`` in one call: its set-up (wall contacts, visit and
order, coefficients by the combine rule, the warm start's cache),
then ``solve_contacts`` (Gauss-Seidel sweeps over pairs and wall planes,
the restitution threshold with its 'struck' rule, speculative contacts
that may close by their gap, Coulomb friction with spin, accumulated
resting impulses), then this solve's cache. Every impulse between two
particles is equal and opposite; only walls and static particles take
momentum. ``jacobi_sweeps`` is the batched ordering's solve: every contact's
impulse from the velocities at the start of its sweep.

Every impulse comes from the law's primitives (``law/primitives.py``).
Kernels take named records (``typing.NamedTuple`` of arrays and scalars)
and return one (``SolveResult``, ``JacobiResult``); the stages build the
records once per step. ``test/test_contact_kernels.py`` runs the
vectorised reference (``test/solve_reference.py``) and these kernels on
the same contacts and asserts identical velocities and bookings.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit, prange  # noqa: E402,I100 (after the cache directory is chosen)

from ...law.primitives import (apply_pair_normal, apply_tangential, apply_wall_normal, Bodies,
                               book_pair_total, closing_allowance,
                               combined_coefficient, dot3, EFFECTS, FRICTION,
                               friction_accumulated, into_cone, loss_share, pair_friction_spun,
                               push_pair, push_wall, RESTITUTION, spin_factor, STICK_FACTOR,
                               tangential_slip, WALLS)
from ...model.tunables import (COLD_START_SHARE, COLD_START_SWEEPS, MIN_SUPPORT_ALIGNMENT,
                               PARALLEL_MIN_BATCH, PARALLEL_MIN_ITEMS, PARALLEL_SOLVE_BLOCK,
                               SUPPORT_SLOP, WALL_SLOP)
from ...step.step_kernels import incident, spread_levels, UNSUPPORTED
from .wall_kernels import WallPlanes

# Cache keys are lower id * (MAX_CACHED_ID + 1) + higher id in int64: a world
# with a larger id keeps no cache.
MAX_CACHED_ID = 2 ** 31 - 1


class SolverSettings(NamedTuple):
    """How one contact solve runs (fixed for the solve)."""

    use_threshold: bool      # a restitution threshold is set
    threshold: float         # m/s: slower contacts are resting (e = 0)
    tolerance: float         # m/s: closing speeds at or below it count as resolved
    strike_factor: float     # an impulse strikes its particles at this many thresholds
    iterations: int          # sweep budget
    friction: bool           # Coulomb friction with spin after each normal impulse
    planar: bool             # a 2-D scene: in-plane friction only
    accumulate: bool         # accumulated resting impulses, warm-started from the cache
    colour_order: bool       # visit in the given order (else pairs in order)
    dt: float                # s: the (sub)step the next drift takes (speculative contacts)
    ahead: float             # m: wall contacts are found this far beyond the touching slop
    margin: float            # of r: and this many radii (0 with ``ahead`` 0: touching only)
    early_impacts: bool      # an impact found before it touches bounces now (no swept stage)
    fall_x: float            # m/s: the velocity gravity adds in the (sub)step, g dt (0, 0, 0:
    fall_y: float            # no gravity); cold resting contacts start from the static load
    fall_z: float            # this weight puts on them (``_seed_loads``)
    threads: int             # threads a colour's pairs may be shared among (1: serial)


class StepContacts(NamedTuple):
    """The narrowphase's pairs as the solve takes them."""

    first: np.ndarray        # (m,) particle rows i
    second: np.ndarray       # (m,) particle rows j
    normal: np.ndarray       # (m, 3) line of action, from j to i
    visit_order: np.ndarray  # the sweeps' order with ``colour_order`` (else empty)
    gap: np.ndarray          # (m,) |p_i - p_j| - r_i - r_j, m (> 0: speculative; empty: none)
    colour_start: np.ndarray  # colour c is visit_order[colour_start[c]:colour_start[c + 1]],
    #                           overflow pairs after the last (empty: no colours)


class Coefficients(NamedTuple):
    """Restitution and friction, combined per contact by ``combined_coefficient``."""

    own_restitution: np.ndarray  # (n,) per particle, NaN: none; empty if no particle has one
    own_friction: np.ndarray     # the same for mu
    restitution: float           # the scene's e at a pair
    wall_restitution: float      # the walls' e
    friction: float              # the scene's mu (pairs and walls)


class WarmStartCache(NamedTuple):
    """Accumulated resting impulses of a solve, sorted by key (stable particle ids).

    Pair keys: lower id * (MAX_CACHED_ID + 1) + higher id, the tangential
    impulse on the lower id; wall keys: id * 8 + axis * 2 + (inward > 0).
    """

    key: np.ndarray
    normal: np.ndarray           # N s
    tangential: np.ndarray       # (., 3) N s
    wall_key: np.ndarray
    wall_normal: np.ndarray
    wall_tangential: np.ndarray


class PairContacts(NamedTuple):
    """The pairs of one solve with their coefficients and orders."""

    first: np.ndarray
    second: np.ndarray
    normal: np.ndarray
    restitution: np.ndarray  # (m,) e
    friction: np.ndarray     # (m,) mu (0 without friction)
    share: np.ndarray        # (m,) first's share of the pair's loss (``loss_share``)
    order: np.ndarray        # the sweeps' visit order
    allowance: np.ndarray    # (m,) m/s the pair may close by in the next step (gap / dt)
    ahead: np.ndarray        # (m,) the pair has a gap: found before it touches
    colour_start: np.ndarray  # colour batches of ``order`` (``StepContacts``; empty: none)


class WallContacts(NamedTuple):
    """Particles touching the wall planes, plane after plane."""

    start: np.ndarray        # (planes + 1,) each plane's first contact
    particle: np.ndarray
    axis: np.ndarray
    inward: np.ndarray       # +1 or -1 along the axis
    restitution: np.ndarray
    friction: np.ndarray
    allowance: np.ndarray    # m/s the particle may close by in the next step (gap / dt)
    ahead: np.ndarray        # a gap beyond the touching slop: found before it touches


class ContactImpulses(NamedTuple):
    """What a solve did at each contact (pairs, or wall contacts), filled in place."""

    hit: np.ndarray                 # received an impulse in the sweeps
    normal: np.ndarray              # summed normal impulse, N s
    tangential: np.ndarray          # summed tangential impulse magnitude, N s
    approach: np.ndarray            # closing speed before the solve (walls: at first visit)
    impact: np.ndarray              # closed faster than the threshold before the solve
    resting: np.ndarray             # accumulated resting impulse (warm start in, cache out)
    impact_total: np.ndarray        # accumulated impact impulse (never taken back)
    resting_tangential: np.ndarray  # (., 3) accumulated tangential impulse on the particle


class ParticleMarks(NamedTuple):
    """Per-particle values of one solve."""

    dynamic: np.ndarray      # inverse mass > 0
    struck: np.ndarray       # struck by an impulse with e > 0 in this solve
    spin: np.ndarray         # ``spin_factor`` (with friction)
    warm_change: np.ndarray  # (n, 3) velocity change of the warm pushes (accumulate)
    warmed: np.ndarray       # whether a warm push changed the particle


class Losses(NamedTuple):
    """Energy removed: per particle (all effects together) and per effect."""

    booked: np.ndarray       # (n,) per particle, J: the step's bookings so far plus this solve's
    totals: np.ndarray       # per effect, J


class SolveResult(NamedTuple):
    """What ``solve_step`` did."""

    sweeps: int
    totals: np.ndarray       # energy removed per effect, J
    pairs: ContactImpulses
    walls: WallContacts
    wall_impulses: ContactImpulses
    cache: WarmStartCache    # this solve's


class JacobiResult(NamedTuple):
    """What ``jacobi_sweeps`` did; the energy per sweep, as the particles that took it."""

    sweeps: int
    hit: np.ndarray          # per pair
    normal: np.ndarray       # summed normal impulse per pair, N s
    approach: np.ndarray     # closing speed per pair before the solve
    sweep_start: np.ndarray  # (sweeps + 1,): sweep s booked rows sweep_start[s]..[s + 1] - 1
    particle: np.ndarray     # ascending within a sweep
    removed: np.ndarray      # J


@njit(cache=True, inline='always')
def _wall_normal(axis, inward):
    """Return the unit normal of an axis-aligned wall as a 3-tuple."""
    return (inward if axis == 0 else 0.0, inward if axis == 1 else 0.0,
            inward if axis == 2 else 0.0)


@njit(cache=True)
def _solve_wall_plane(bodies, marks, walls, impulses, settings, tolerance, start, stop,
                      losses):
    """Solve one wall plane's contacts (distinct particles); return whether any changed.

    With ``accumulate`` the resting impulse of each contact is accumulated
    and may be taken back down to 0 when the particle leaves the plane (see
    ``solve_contacts``); impact impulses go to ``impact_total``, and a
    bounce never reflects the closing speed that warm pushes added. A
    contact found before it touches (``ahead``) may close by its
    ``allowance``; one that is an impact is left to the walls stage, which
    takes it at its time in the next step.
    """
    v, ang, inv_mass, radius = bodies
    threshold, accumulate = settings.threshold, settings.accumulate
    any_hit = False
    for c in range(start, stop):
        p, axis, inward = walls.particle[c], walls.axis[c], walls.inward[c]
        if walls.ahead[c] and impulses.impact[c]:
            continue
        e = walls.restitution[c]
        if settings.use_threshold:
            u = inward * v[p, axis]
            if not (-u >= threshold and (impulses.impact[c] or marks.struck[p])):
                e = 0.0
        approach = -inward * v[p, axis]
        slack = approach - walls.allowance[c]
        if slack > tolerance:
            bounce = approach
            if accumulate and e > 0.0 and marks.warmed[p]:
                bounce = min(approach, max(approach + inward * marks.warm_change[p, axis], 0.0))
            if e == 0.0 and walls.allowance[c] > 0.0:
                # Speculative: close by the gap in the next step, no more.
                magnitude = slack / inv_mass[p]
                removed = push_wall(v, inv_mass, p, axis, inward, magnitude, approach)
            elif bounce < approach:
                change = approach + e * bounce
                v[p, axis] += inward * change
                magnitude = change / inv_mass[p]
                removed = 0.5 * magnitude * (approach - e * bounce)
            else:
                magnitude, removed = apply_wall_normal(v, inv_mass, p, axis, inward, e, approach)
            if settings.use_threshold and e > 0.0 and bounce >= settings.strike_factor * threshold:
                marks.struck[p] = True
            impulses.hit[c] = True
            if accumulate:
                if impulses.impact[c] or e > 0.0:
                    impulses.impact_total[c] += magnitude
                else:
                    impulses.resting[c] += magnitude
        elif accumulate and slack < -tolerance and impulses.resting[c] > 0.0:
            # Leaving the plane (beyond its allowance) with resting impulse to
            # give back: take back what stops it leaving, at most the
            # accumulated impulse (beyond the tolerance, as an approach).
            magnitude = max(slack / inv_mass[p], -impulses.resting[c])
            removed = push_wall(v, inv_mass, p, axis, inward, magnitude, approach)
            impulses.resting[c] += magnitude
        else:
            continue
        any_hit = True
        losses.booked[p] += removed
        losses.totals[WALLS] += removed
        impulses.normal[c] += magnitude
        if settings.friction:
            normal = _wall_normal(axis, inward)
            spins = (marks.spin[p], 0.0)
            if accumulate:
                tangential, lost = friction_accumulated(
                    v, ang, inv_mass, radius, (p, -1), normal,
                    impulses.resting[c] + impulses.impact_total[c], walls.friction[c],
                    settings.planar, spins, impulses.resting_tangential, c)
            else:
                tangential, lost = pair_friction_spun(v, ang, inv_mass, radius, p, -1, normal,
                                                      magnitude, walls.friction[c],
                                                      settings.planar, spins)
            losses.booked[p] += lost
            losses.totals[FRICTION] += lost
            impulses.tangential[c] += tangential
    return any_hit


@njit(cache=True)
def _solve_walls(bodies, marks, walls, impulses, settings, tolerance, first_visit, losses):
    """Solve every wall plane once, plane after plane; return whether any changed.

    On the ``first_visit`` each plane's contacts keep the approach speed
    they are recorded with, just before that plane is solved (an earlier
    plane's friction may have changed it at a corner).
    """
    v, start = bodies.velocity, walls.start
    any_hit = False
    for plane in range(start.size - 1):
        if first_visit:
            for c in range(start[plane], start[plane + 1]):
                impulses.approach[c] = -walls.inward[c] * v[walls.particle[c], walls.axis[c]]
        if _solve_wall_plane(bodies, marks, walls, impulses, settings, tolerance, start[plane],
                             start[plane + 1], losses):
            any_hit = True
    return any_hit


@njit(cache=True)
def _take_back_pairs(bodies, pairs, impulses, losses):
    """One pass in visit order taking back the resting impulse of every opening pair.

    The sweeps take back only beyond the tolerance; this leaves no pair
    opening (beyond its allowance) under a resting impulse it holds
    (momentum conserved, the work booked as 'restitution').
    """
    v, inv_mass, normal, resting = bodies.velocity, bodies.inv_mass, pairs.normal, \
        impulses.resting
    for k in pairs.order:
        if not resting[k] > 0.0:
            continue
        a, b = pairs.first[k], pairs.second[k]
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        approach = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
        slack = approach - pairs.allowance[k]
        if not slack < 0.0:
            continue
        magnitude = max(slack / (inv_mass[a] + inv_mass[b]), -resting[k])
        removed = push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
        resting[k] += magnitude
        book_pair_total(losses.booked, a, b, removed, pairs.share[k])
        losses.totals[RESTITUTION] += removed
        impulses.normal[k] += magnitude


@njit(cache=True)
def _warm_tangential(bodies, first, second, normal, bound, planar, spins, accumulated, row):
    """Apply a contact's cached tangential impulse, clamped into ``bound``; return J removed.

    The cached impulse is projected on today's tangent plane (the normal
    may have turned) and clamped into the cone of today's warm normal
    impulse; what is applied is booked by its exact work on the slip.
    """
    qx, qy, qz = into_cone((accumulated[row, 0], accumulated[row, 1], accumulated[row, 2]),
                           normal, planar, bound)
    accumulated[row, 0], accumulated[row, 1], accumulated[row, 2] = qx, qy, qz
    if qx == 0.0 and qy == 0.0 and qz == 0.0:
        return 0.0
    v, ang, inv_mass, radius = bodies
    tx, ty, tz, w_sum = tangential_slip(v, ang, inv_mass, radius, first, second, normal,
                                        planar)
    k = STICK_FACTOR * w_sum
    removed = -(dot3(qx, qy, qz, tx, ty, tz) + 0.5 * k * dot3(qx, qy, qz, qx, qy, qz))
    apply_tangential(v, ang, inv_mass, first, second, normal, (qx, qy, qz), spins)
    return removed


@njit(cache=True)
def _warm_start(bodies, marks, pairs, walls, pair_impulses, wall_impulses, settings, losses):
    """Apply the cached resting impulses of the contacts that persist (not new impacts).

    ``resting`` holds the previous step's accumulated resting normal
    impulse per contact (0 for a new contact), ``resting_tangential`` its
    tangential one; an impact's entries are cleared (an impact starts from
    nothing, as without warm starting). Each impulse is booked by its own
    work (``push_pair``): a warm impulse on a contact that has opened adds
    energy that is booked as a negative loss, and the sweeps take it back
    (the accumulated impulse is clamped at 0).
    """
    v, inv_mass, normal = bodies.velocity, bodies.inv_mass, pairs.normal
    booked, totals, spin = losses.booked, losses.totals, marks.spin
    resting, resting_t = pair_impulses.resting, pair_impulses.resting_tangential
    for k in range(pairs.first.size):
        if pair_impulses.impact[k] or not resting[k] > 0.0:
            resting[k] = 0.0
            resting_t[k, 0] = resting_t[k, 1] = resting_t[k, 2] = 0.0
            continue
        a, b = pairs.first[k], pairs.second[k]
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        approach = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
        removed = push_pair(v, inv_mass, a, b, nx, ny, nz, resting[k], approach)
        book_pair_total(booked, a, b, removed, pairs.share[k])
        totals[RESTITUTION] += removed
        pair_impulses.normal[k] += resting[k]
        if settings.friction:
            lost = _warm_tangential(bodies, a, b, (nx, ny, nz), pairs.friction[k] * resting[k],
                                    settings.planar, (spin[a], spin[b]), resting_t, k)
            book_pair_total(booked, a, b, lost, pairs.share[k])
            totals[FRICTION] += lost
        else:
            resting_t[k, 0] = resting_t[k, 1] = resting_t[k, 2] = 0.0
    resting, resting_t = wall_impulses.resting, wall_impulses.resting_tangential
    for c in range(walls.particle.size):
        if wall_impulses.impact[c] or not resting[c] > 0.0:
            resting[c] = 0.0
            resting_t[c, 0] = resting_t[c, 1] = resting_t[c, 2] = 0.0
            continue
        p, axis, inward = walls.particle[c], walls.axis[c], walls.inward[c]
        approach = -inward * v[p, axis]
        removed = push_wall(v, inv_mass, p, axis, inward, resting[c], approach)
        booked[p] += removed
        totals[WALLS] += removed
        wall_impulses.normal[c] += resting[c]
        if settings.friction:
            lost = _warm_tangential(bodies, p, -1, _wall_normal(axis, inward),
                                    walls.friction[c] * resting[c], settings.planar,
                                    (spin[p], 0.0), resting_t, c)
            booked[p] += lost
            totals[FRICTION] += lost
        else:
            resting_t[c, 0] = resting_t[c, 1] = resting_t[c, 2] = 0.0


@njit(cache=True)
def _start_solve(bodies, marks, pairs, walls, pair_impulses, wall_impulses, settings, losses):
    """Set a solve's fixed values up: approach speeds, impacts, spin factors, warm start.

    Returns whether one sweep resolves every contact (no dynamic particle in
    two pairs and no wall: vn' = -e vn >= 0, so a checking sweep is skipped).
    """
    v, inv_mass, normal = bodies.velocity, bodies.inv_mass, pairs.normal
    n, m = v.shape[0], pairs.first.size
    for k in range(m):
        a, b = pairs.first[k], pairs.second[k]
        pair_impulses.approach[k] = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1],
                                          v[a, 2] - v[b, 2], normal[k, 0], normal[k, 1],
                                          normal[k, 2])
    if settings.use_threshold:
        for k in range(m):
            pair_impulses.impact[k] = pair_impulses.approach[k] >= settings.threshold
        for c in range(walls.particle.size):
            wall_impulses.impact[c] = (-walls.inward[c] * v[walls.particle[c], walls.axis[c]]
                                       >= settings.threshold)
    # Contacts per particle: only the pairs' particles are counted and read.
    count = np.empty(n, dtype=np.int64)
    for k in range(m):
        count[pairs.first[k]] = count[pairs.second[k]] = 0
    single = walls.particle.size == 0
    for k in range(m):
        for p in (pairs.first[k], pairs.second[k]):
            if marks.dynamic[p]:
                count[p] += 1
                if count[p] > 1:
                    single = False
    # The spin factors are fixed for the solve: computed once, not at each
    # of up to ``iterations`` visits (the same values).
    if settings.friction:
        for p in range(n):
            marks.spin[p] = spin_factor(inv_mass, bodies.radius, p)
    if settings.accumulate:
        warm = marks.warm_change
        for p in range(n):
            warm[p, 0], warm[p, 1], warm[p, 2] = v[p, 0], v[p, 1], v[p, 2]
        _warm_start(bodies, marks, pairs, walls, pair_impulses, wall_impulses, settings,
                    losses)
        # What the warm pushes changed, per particle.
        for p in range(n):
            for d in range(3):
                warm[p, d] = v[p, d] - warm[p, d]
                if warm[p, d] != 0.0:
                    marks.warmed[p] = True
    return single


@njit(cache=True)
def _sweep_pairs(bodies, marks, pairs, impulses, settings, losses):
    """Visit every pair once in visit order (one Gauss-Seidel sweep); return whether any did.

    With colours on several threads, colour by colour (``_sweep_colours``).
    """
    if settings.threads > 1 and pairs.colour_start.size > 1:
        return _sweep_colours(bodies, marks, pairs, impulses, settings, losses)
    return _visit_range(bodies, marks, pairs, impulses, settings, losses, np.int64(0),
                        pairs.order.size, _no_visits())


@njit(cache=True)
def _visit_range(bodies, marks, pairs, impulses, settings, losses, start, stop, visits):
    """Visit pairs order[start] .. order[stop - 1] one after another; return whether any did.

    Each visit writes its pair's impulses and its two particles only
    (velocities, spins, marks, per-particle losses). The energy removed goes
    to ``losses.totals`` in visit order, or, with ``visits`` (applied,
    removed, lost to friction: arrays over the visit order) not empty, is
    kept there per pair for the caller to add in visit order (a colour's
    blocks on several threads).
    """
    v, ang, inv_mass, radius = bodies
    normal, rest = pairs.normal, pairs.restitution
    struck, warm, warmed = marks.struck, marks.warm_change, marks.warmed
    threshold, tolerance, accumulate = settings.threshold, settings.tolerance, \
        settings.accumulate
    resting = impulses.resting
    allowance, ahead = pairs.allowance, pairs.ahead
    booked, totals = losses.booked, losses.totals
    keep = visits[0].size > 0
    applied = False
    for q in range(start, stop):
        k = pairs.order[q]
        a, b = pairs.first[k], pairs.second[k]
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        # The closing speed is read once: it decides both whether the pair
        # gets an impulse and, against the threshold, its e.
        approach = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2], nx, ny, nz)
        slack = approach - allowance[k]
        if slack > tolerance:
            if ahead[k] and impulses.impact[k] and not settings.early_impacts:
                # An impact found before it touches: taken when it does, at its
                # time of impact by the swept stage.
                continue
            e = rest[k]
            if settings.use_threshold:
                if not (approach >= threshold and (impulses.impact[k] or struck[a]
                                                   or struck[b])):
                    e = 0.0
            bounce = approach
            if accumulate and e > 0.0 and (warmed[a] or warmed[b]):
                # A bounce reflects the closing speed the impacts made, never
                # what the warm pushes added to it: with e = 1 that excess
                # would leave at full speed and add energy.
                bounce = min(approach, max(approach + dot3(
                    warm[a, 0] - warm[b, 0], warm[a, 1] - warm[b, 1],
                    warm[a, 2] - warm[b, 2], nx, ny, nz), 0.0))
            if e == 0.0 and allowance[k] > 0.0:
                # Speculative: close by the gap in the next step, no more.
                magnitude = slack / (inv_mass[a] + inv_mass[b])
                removed = push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
            elif bounce < approach:
                magnitude = (approach + e * bounce) / (inv_mass[a] + inv_mass[b])
                removed = push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
            else:
                magnitude, removed = apply_pair_normal(v, inv_mass, a, b, nx, ny, nz, e,
                                                       approach)
            if settings.use_threshold and e > 0.0 and bounce >= settings.strike_factor * threshold:
                # A static particle never moves, so it passes no shock on.
                struck[a] = marks.dynamic[a]
                struck[b] = marks.dynamic[b]
            impulses.hit[k] = True
            if accumulate:
                # Closing faster than the threshold: an impact's impulse, never
                # taken back or cached; slower: resting.
                if impulses.impact[k] or e > 0.0:
                    impulses.impact_total[k] += magnitude
                else:
                    resting[k] += magnitude
        elif accumulate and slack < -tolerance and resting[k] > 0.0:
            # Opening (beyond its allowance) with resting impulse to give back
            # (e.g. from the warm start): take back what stops it opening, at
            # most all of it. Beyond the tolerance only, as an approach: a
            # converged contact costs a dot product per sweep;
            # ``_take_back_pairs`` takes back what is left below it after the
            # sweeps.
            magnitude = max(slack / (inv_mass[a] + inv_mass[b]), -resting[k])
            removed = push_pair(v, inv_mass, a, b, nx, ny, nz, magnitude, approach)
            resting[k] += magnitude
        else:
            continue
        book_pair_total(booked, a, b, removed, pairs.share[k])
        impulses.normal[k] += magnitude
        lost = 0.0
        if settings.friction:
            spins = (marks.spin[a], marks.spin[b])
            if accumulate:
                tangential, lost = friction_accumulated(
                    v, ang, inv_mass, radius, (a, b), (nx, ny, nz),
                    resting[k] + impulses.impact_total[k], pairs.friction[k], settings.planar,
                    spins, impulses.resting_tangential, k)
            else:
                tangential, lost = pair_friction_spun(v, ang, inv_mass, radius, a, b,
                                                      (nx, ny, nz), magnitude, pairs.friction[k],
                                                      settings.planar, spins)
            book_pair_total(booked, a, b, lost, pairs.share[k])
            impulses.tangential[k] += tangential
        if keep:
            visits[0][q], visits[1][q], visits[2][q] = True, removed, lost
        else:
            totals[RESTITUTION] += removed
            if settings.friction:
                totals[FRICTION] += lost
        applied = True
    return applied


@njit(cache=True, inline='always')
def _no_visits():
    """Return empty per-pair outcomes: ``_visit_range`` adds the energy to the totals itself."""
    return np.zeros(0, dtype=np.bool_), np.zeros(0), np.zeros(0)


@njit(cache=True)
def _sweep_colours(bodies, marks, pairs, impulses, settings, losses):
    """One sweep colour by colour: a colour of PARALLEL_MIN_BATCH pairs or more on the threads.

    The pairs of a colour share no dynamic particle, so visiting them at
    once changes nothing; their energy is added to the totals afterwards,
    in visit order. The result is the serial sweep's over the same order,
    bit for bit, whatever the thread count. Overflow pairs follow, one at a time.
    """
    start, m = pairs.colour_start, pairs.order.size
    visits = (np.zeros(m, dtype=np.bool_), np.zeros(m), np.zeros(m))
    did, removed, lost = visits
    applied = False
    for c in range(start.size - 1):
        lo, hi = start[c], start[c + 1]
        if hi - lo < PARALLEL_MIN_BATCH:
            applied |= _visit_range(bodies, marks, pairs, impulses, settings, losses, lo, hi,
                                    _no_visits())
            continue
        did[lo:hi] = False
        _visit_colour_parallel(bodies, marks, pairs, impulses, settings, losses, lo, hi,
                               visits)
        for q in range(lo, hi):
            if did[q]:
                applied = True
                losses.totals[RESTITUTION] += removed[q]
                if settings.friction:
                    losses.totals[FRICTION] += lost[q]
    overflow = _visit_range(bodies, marks, pairs, impulses, settings, losses,
                            start[start.size - 1], m, _no_visits())
    return applied or overflow


@njit(cache=True, parallel=True)
def _visit_colour_parallel(bodies, marks, pairs, impulses, settings, losses, lo, hi, visits):
    """Visit the pairs order[lo] .. order[hi - 1] of one colour, blocks of them on the threads.

    The blocks call a function that is never inlined: numba's parallel loops
    lose the stores of inlined code and of NamedTuple fields.
    """
    for block in prange((hi - lo + PARALLEL_SOLVE_BLOCK - 1) // PARALLEL_SOLVE_BLOCK):
        start = lo + block * PARALLEL_SOLVE_BLOCK
        _visit_range(bodies, marks, pairs, impulses, settings, losses, start,
                     min(start + PARALLEL_SOLVE_BLOCK, hi), visits)


@njit(cache=True)
def solve_contacts(bodies, marks, pairs, walls, pair_impulses, wall_impulses, settings,
                   losses, budget):
    """Run one contact solve in place; return the sweeps run. See ``SequentialImpulseStage``.

    Sweeps visit the pairs in visit order, then each wall plane, until no
    contact's impulse changes by more than ``tolerance`` times its mass
    (its velocity change) or ``budget`` sweeps are done. Outputs are
    filled in place (``ContactImpulses``, ``Losses``). A contact found
    before it touches (``ahead``, a gap g > 0) is held to closing at most
    g / dt (its ``allowance``: it touches at the end of the next drift, no
    earlier overlap), as resting contact; one closing faster than the
    threshold before the solve is an impact: with ``early_impacts`` (no
    swept stage) it gets the law's impulse now, before it overlaps;
    otherwise it is left to the swept stage, at its time of impact. Every
    impulse between two particles is equal and opposite, so only walls and
    static particles take momentum.

    With ``accumulate`` (a restitution threshold is set), impulses at
    contacts below the threshold (resting, e = 0, target separating speed
    0) are accumulated per contact (normal >= 0, tangential inside the
    Coulomb cone of the accumulated normal impulse), clamped: a contact that
    opens gets its resting impulse taken back, down to 0. On entry
    ``resting`` holds the previous step's values for contacts that persist
    (warm start, applied first to contacts that are not new impacts); on
    return, this solve's. Each contact's class is fixed at the start: one
    closing faster than the threshold before any warm push is an impact for
    the whole solve (its impulses, and any with e > 0 by the 'struck' rule,
    are the law's, never taken back and not cached); every other contact is
    resting, whatever a warm push makes it do. Resting impulse left pushing
    an opening contact after the sweeps is taken back. A warm impulse is not
    counted in ``hit`` (no collision).
    """
    single = _start_solve(bodies, marks, pairs, walls, pair_impulses, wall_impulses, settings,
                          losses)
    has_walls = walls.start.size > 1
    first_wall_visit = np.bool_(True)
    sweeps = 0
    for _ in range(budget):
        sweeps += 1
        applied = _sweep_pairs(bodies, marks, pairs, pair_impulses, settings, losses)
        if has_walls:
            if _solve_walls(bodies, marks, walls, wall_impulses, settings, settings.tolerance,
                            first_wall_visit, losses):
                applied = True
            first_wall_visit = False
        if not applied or single:
            break
    if settings.accumulate:
        _take_back_pairs(bodies, pairs, pair_impulses, losses)
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
def find_wall_contacts(position, radius, dynamic, planes, slop, ahead=0.0):
    """Return (start per plane, particle, axis, inward) of the particles touching each plane.

    A dynamic particle touches a plane (``WallPlanes``) when its gap is at
    most ``slop`` times its radius plus the plane's ``ulps`` (WALL_ULPS
    spacings at its coordinate) plus ``ahead``, m; plane after plane, in
    particle order.
    ``start`` has one entry per plane and one more (a plane nothing touches
    is an empty run).
    """
    return find_wall_contacts_among(position, radius, dynamic, planes, slop, ahead,
                                    np.arange(position.shape[0]))


@njit(cache=True)
def find_wall_contacts_among(position, radius, dynamic, planes, slop, ahead, candidates):
    """Return ``find_wall_contacts``' result, testing only ``candidates`` (ascending).

    The same lists when every particle that is not a candidate is farther
    from every plane (``StepContext.near_walls``).
    """
    count = planes.axis.size
    start = np.zeros(count + 1, dtype=np.int64)
    index = np.empty(candidates.size * count, dtype=np.int64)
    k = 0
    for q in range(count):
        axis, plane, inward = planes.axis[q], planes.value[q], planes.inward[q]
        for p in candidates:
            gap = inward * (position[p, axis] - plane) - radius[p]
            if dynamic[p] and gap <= slop * radius[p] + planes.ulps[q] + ahead:
                index[k] = p
                k += 1
        start[q + 1] = k
    return _with_planes(planes, start, index[:k].copy())


@njit(cache=True)
def _with_planes(planes, start, index):
    """Return (start, index, axis, inward): each plane's run of ``index``, its axis and side."""
    k = index.size
    axes = np.empty(k, dtype=np.int64)
    inwards = np.empty(k)
    for q in range(planes.axis.size):
        for c in range(start[q], start[q + 1]):
            axes[c], inwards[c] = planes.axis[q], planes.inward[q]
    return start, index, axes, inwards


@njit(cache=True, nogil=True, parallel=True)
def _touch_masks(position, radius, dynamic, planes, slop, ahead, touch):
    """Set bit q of touch[p] where particle p touches plane q (``find_wall_contacts``' test)."""
    for p in prange(position.shape[0]):
        bits = 0
        for q in range(planes.axis.size):
            gap = planes.inward[q] * (position[p, planes.axis[q]] - planes.value[q]) - radius[p]
            if dynamic[p] and gap <= slop * radius[p] + planes.ulps[q] + ahead:
                bits |= 1 << q
        touch[p] = bits


@njit(cache=True)
def find_wall_contacts_shared(position, radius, dynamic, planes, slop, ahead):
    """Return ``find_wall_contacts``' result, the particles' tests on the threads.

    Each particle's planes are tested on the threads into a bit mask; the
    touching particles are then listed plane by plane in particle order,
    as the serial loop lists them.
    """
    n, count = position.shape[0], planes.axis.size
    touch = np.empty(n, dtype=np.int64)
    _touch_masks(position, radius, dynamic, planes, slop, ahead, touch)
    near = 0
    for p in range(n):
        if touch[p] != 0:
            near += 1
    touching = np.empty(near, dtype=np.int64)
    near = 0
    for p in range(n):
        if touch[p] != 0:
            touching[near] = p
            near += 1
    start = np.zeros(count + 1, dtype=np.int64)
    index = np.empty(near * count, dtype=np.int64)
    k = 0
    for q in range(count):
        for s in range(near):
            if touch[touching[s]] & (1 << q):
                index[k] = touching[s]
                k += 1
        start[q + 1] = k
    return _with_planes(planes, start, index[:k].copy())


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


@njit(cache=True)
def _contact_impulses(size):
    """Return a solve's zeroed per-contact arrays for ``size`` contacts."""
    return ContactImpulses(np.zeros(size, dtype=np.bool_), np.zeros(size), np.zeros(size),
                           np.zeros(size), np.zeros(size, dtype=np.bool_), np.zeros(size),
                           np.zeros(size), np.zeros((size, 3)))


@njit(cache=True)
def _pair_contacts(bodies, contacts, coefficients, settings):
    """Return the solve's pairs: coefficients by the combine rule, loss shares, orders."""
    first, second = contacts.first, contacts.second
    m = first.size
    inv_mass = bodies.inv_mass
    own_e, own_mu = coefficients.own_restitution, coefficients.own_friction
    has_e, has_mu = own_e.size > 0, own_mu.size > 0
    rest, mu, share = np.empty(m), np.zeros(m), np.empty(m)
    for c in range(m):
        a, b = first[c], second[c]
        rest[c] = combined_coefficient(own_e, has_e, a, b, coefficients.restitution)
        if settings.friction:
            mu[c] = combined_coefficient(own_mu, has_mu, a, b, coefficients.friction)
        share[c] = loss_share(inv_mass, a, b)
    order = contacts.visit_order if settings.colour_order else np.arange(m)
    allowance, ahead = np.zeros(m), np.zeros(m, dtype=np.bool_)
    if contacts.gap.size == m:
        for c in range(m):
            ahead[c] = contacts.gap[c] > 0.0
            allowance[c] = closing_allowance(contacts.gap[c], settings.dt)
    colour_start = contacts.colour_start if settings.colour_order else \
        np.zeros(0, dtype=np.int64)
    return PairContacts(first, second, contacts.normal, rest, mu, share, order, allowance,
                        ahead, colour_start)


@njit(cache=True)
def _wall_contacts(radius, dynamic, position, planes, coefficients, settings, near):
    """Return the particles touching each wall plane with their coefficients.

    With ``ahead`` > 0 also those within ``ahead`` plus ``margin`` radii of
    a plane (speculative: their gap beyond the touching slop is their
    allowance times dt). ``near`` (known, particles): with known, only those
    particles are tested (the same list: no other can touch).
    """
    slop = WALL_SLOP + settings.margin
    if near[0]:
        start, particle, axis, inward = find_wall_contacts_among(
            position, radius, dynamic, planes, slop, settings.ahead, near[1])
    elif settings.threads > 1 and radius.size >= PARALLEL_MIN_ITEMS:
        start, particle, axis, inward = find_wall_contacts_shared(
            position, radius, dynamic, planes, slop, settings.ahead)
    else:
        start, particle, axis, inward = find_wall_contacts(
            position, radius, dynamic, planes, slop, settings.ahead)
    k = particle.size
    own_e, own_mu = coefficients.own_restitution, coefficients.own_friction
    has_e, has_mu = own_e.size > 0, own_mu.size > 0
    rest, mu = np.empty(k), np.zeros(k)
    allowance, ahead = np.zeros(k), np.zeros(k, dtype=np.bool_)
    for q in range(start.size - 1):
        value, ulps = planes.value[q], planes.ulps[q]
        for c in range(start[q], start[q + 1]):
            p = particle[c]
            gap = inward[c] * (position[p, axis[c]] - value) - radius[p]
            if gap > WALL_SLOP * radius[p] + ulps:
                ahead[c] = True
                allowance[c] = closing_allowance(gap, settings.dt)
    for c in range(k):
        p = particle[c]
        rest[c] = combined_coefficient(own_e, has_e, p, -1, coefficients.wall_restitution)
        if settings.friction:
            mu[c] = combined_coefficient(own_mu, has_mu, p, -1, coefficients.friction)
    return WallContacts(start, particle, axis, inward, rest, mu, allowance, ahead)


@njit(cache=True, inline='always')
def _wall_key(ids, walls, c):
    """Return wall contact ``c``'s cache key: id * 8 + axis * 2 + (inward > 0)."""
    return (ids[walls.particle[c]] * 8 + walls.axis[c] * 2
            + (1 if walls.inward[c] > 0.0 else 0))


@njit(cache=True)
def _warm_from(cache, ids, pairs, walls, pair_impulses, wall_impulses):
    """Fill the resting impulses of the contacts found in ``cache`` (sorted keys)."""
    first, second = pairs.first, pairs.second
    m = first.size
    stride = MAX_CACHED_ID + 1
    if cache.key.size:
        keys = np.empty(m, dtype=np.int64)
        for c in range(m):
            a, b = ids[first[c]], ids[second[c]]
            keys[c] = min(a, b) * stride + max(a, b)
        # The broadphase's pairs come sorted by row, and rows by id unless ids
        # were reordered: then one merge walk finds every key (the first row
        # holding it, as the binary search would).
        merge = _ascending(keys)
        row = 0
        for c in range(m):
            a, b = ids[first[c]], ids[second[c]]
            if merge:
                while row < cache.key.size and cache.key[row] < keys[c]:
                    row += 1
                found = row if row < cache.key.size and cache.key[row] == keys[c] else -1
            else:
                found = _find_key(cache.key, keys[c])
            if found >= 0:
                sign = -1.0 if a > b else 1.0
                pair_impulses.resting[c] = cache.normal[found]
                for d in range(3):
                    pair_impulses.resting_tangential[c, d] = cache.tangential[found, d] * sign
    for c in range(walls.particle.size if cache.wall_key.size else 0):
        row = _find_key(cache.wall_key, _wall_key(ids, walls, c))
        if row >= 0:
            wall_impulses.resting[c] = cache.wall_normal[row]
            for d in range(3):
                wall_impulses.resting_tangential[c, d] = cache.wall_tangential[row, d]


@njit(cache=True)
def _mostly_cold(bodies, pairs, walls, pair_impulses, wall_impulses, settings):
    """Say whether most of a solve's touching resting contacts start cold (nothing cached).

    Touching: within SUPPORT_SLOP of the smaller radius at the end of the
    next drift (``allowance`` dt); resting: closing slower than the
    threshold. More than COLD_START_SHARE of them without a warm start
    (a stack or pile built in place, an island just woken) makes the solve's
    budget COLD_START_SWEEPS.
    """
    v, radius, dt, threshold = bodies.velocity, bodies.radius, settings.dt, settings.threshold
    first, second, normal = pairs.first, pairs.second, pairs.normal
    touching = cold = 0
    for k in range(first.size):
        a, b = first[k], second[k]
        if pairs.allowance[k] * dt > SUPPORT_SLOP * min(radius[a], radius[b]):
            continue
        approach = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2],
                         normal[k, 0], normal[k, 1], normal[k, 2])
        if approach >= threshold:
            continue
        touching += 1
        if not pair_impulses.resting[k] > 0.0:
            cold += 1
    for c in range(walls.particle.size):
        p = walls.particle[c]
        if walls.allowance[c] * dt > SUPPORT_SLOP * radius[p] \
                or -walls.inward[c] * v[p, walls.axis[c]] >= threshold:
            continue
        touching += 1
        if not wall_impulses.resting[c] > 0.0:
            cold += 1
    return touching > 0 and cold > COLD_START_SHARE * touching


@njit(cache=True)
def _seed_loads(bodies, dynamic, pairs, walls, pair_impulses, wall_impulses, settings):
    """Start cold resting contacts from the static load they carry under gravity.

    A contact the cache does not hold starts from 0, and Gauss-Seidel sweeps
    pass a column's weight down one contact per sweep: a stack that starts
    touching sinks for many steps. Here each particle's weight for the step
    (m g dt, N s) plus the load resting on it goes down to its supports,
    the touching contacts with a particle one level nearer a floor or a
    static particle (``spread_levels``; touching: a gap of at most
    SUPPORT_SLOP of r) and below it, shared equally; a
    floor takes a level-0 particle's load. The contacts of a cold particle
    (none of its contacts warm-started from the cache) that are not impacts
    start from their share along their normal; a particle with a warm
    contact keeps the cache's impulses (a contact the cache dropped had
    converged to 0), but its load still goes down. The sweeps correct the
    estimate and take back what opens, so it changes how fast the solve
    converges, not the constraints it converges to.
    """
    v, inv_mass = bodies.velocity, bodies.inv_mass
    fall = math.sqrt(settings.fall_x ** 2 + settings.fall_y ** 2 + settings.fall_z ** 2)
    if not fall > 0.0:
        return
    up = (-settings.fall_x / fall, -settings.fall_y / fall, -settings.fall_z / fall)
    n, m = v.shape[0], pairs.first.size
    # A particle with any warm contact is settled in: the sweeps start from the cache's
    # impulses there, and a contact of it the cache dropped had converged to 0.
    cold = np.ones(n, dtype=np.bool_)
    for k in range(m):
        if pair_impulses.resting[k] > 0.0:
            cold[pairs.first[k]] = cold[pairs.second[k]] = False
    for c in range(walls.particle.size):
        if wall_impulses.resting[c] > 0.0:
            cold[walls.particle[c]] = False
    # Only a cold dynamic particle's touching contacts are seeded: a settled world, where
    # every such contact is warm, skips the levels and the sort.
    seeds = False
    level = np.full(n, UNSUPPORTED, dtype=np.int64)
    for p in range(n):
        if not dynamic[p]:
            level[p] = 0
    radius, dt = bodies.radius, settings.dt
    for c in range(walls.particle.size):
        p = walls.particle[c]
        if walls.allowance[c] * dt <= SUPPORT_SLOP * radius[p] \
                and walls.inward[c] * up[walls.axis[c]] >= MIN_SUPPORT_ALIGNMENT:
            level[p] = 0
            seeds = seeds or (cold[p] and dynamic[p])
    touching = np.empty(m, dtype=np.int64)
    count = 0
    for k in range(m):
        a, b = pairs.first[k], pairs.second[k]
        if pairs.allowance[k] * dt <= SUPPORT_SLOP * min(radius[a], radius[b]):
            touching[count] = k
            count += 1
            seeds = seeds or (cold[a] and dynamic[a]) or (cold[b] and dynamic[b])
    if not seeds:
        return
    touching = touching[:count]
    first, second = pairs.first[touching], pairs.second[touching]
    spread_levels(level, first, second)
    start, incident_contact = incident(n, first, second)
    load = np.zeros(n)
    key = np.empty(n, dtype=np.int64)
    for p in range(n):
        if dynamic[p]:
            load[p] = fall / inv_mass[p]
        key[p] = -1 if level[p] == UNSUPPORTED else level[p]
    order = np.argsort(key, kind='mergesort')
    normal, resting = pairs.normal, pair_impulses.resting
    for s in range(n - 1, -1, -1):
        p = order[s]
        if key[p] < 1 or not dynamic[p]:
            continue
        supports = 0
        for t in range(start[p], start[p + 1]):
            k = touching[incident_contact[t]]
            q = pairs.second[k] if pairs.first[k] == p else pairs.first[k]
            side = 1.0 if pairs.first[k] == p else -1.0
            along = side * dot3(normal[k, 0], normal[k, 1], normal[k, 2], up[0], up[1], up[2])
            if level[q] == level[p] - 1 and along >= MIN_SUPPORT_ALIGNMENT:
                supports += 1
        if supports == 0:
            continue
        share = load[p] / supports
        for t in range(start[p], start[p + 1]):
            k = touching[incident_contact[t]]
            a, b = pairs.first[k], pairs.second[k]
            q = b if a == p else a
            side = 1.0 if a == p else -1.0
            nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
            along = side * dot3(nx, ny, nz, up[0], up[1], up[2])
            if not (level[q] == level[p] - 1 and along >= MIN_SUPPORT_ALIGNMENT):
                continue
            load[q] += share
            approach = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2],
                             nx, ny, nz)
            if cold[p] and approach < settings.threshold:
                resting[k] = share / along
    for c in range(walls.particle.size):
        p, axis, inward = walls.particle[c], walls.axis[c], walls.inward[c]
        along = inward * up[axis]
        if walls.allowance[c] * dt > SUPPORT_SLOP * radius[p] or along < MIN_SUPPORT_ALIGNMENT \
                or level[p] != 0 or not dynamic[p]:
            continue
        approach = -inward * v[p, axis]
        if cold[p] and approach < settings.threshold:
            wall_impulses.resting[c] = load[p] / along


@njit(cache=True)
def _kept(ids, pairs, walls, pair_impulses, wall_impulses, keyed):
    """Return this solve's cache: the contacts holding resting impulse, sorted by key."""
    first, second = pairs.first, pairs.second
    m, k = first.size, walls.particle.size
    stride = MAX_CACHED_ID + 1
    resting = pair_impulses.resting
    kept = 0
    for c in range(m):
        if keyed and resting[c] > 0.0:
            kept += 1
    keys = np.empty(kept, dtype=np.int64)
    rows = np.empty(kept, dtype=np.int64)
    kept = 0
    for c in range(m):
        if keyed and resting[c] > 0.0:
            a, b = ids[first[c]], ids[second[c]]
            keys[kept], rows[kept] = min(a, b) * stride + max(a, b), c
            kept += 1
    sorted_rows = np.arange(kept) if _ascending(keys) else _stable_order(keys)
    new_key = np.empty(kept, dtype=np.int64)
    new_normal, new_tangential = np.empty(kept), np.empty((kept, 3))
    for s in range(kept):
        c = rows[sorted_rows[s]]
        new_key[s] = keys[sorted_rows[s]]
        new_normal[s] = resting[c]
        sign = -1.0 if ids[first[c]] > ids[second[c]] else 1.0
        for d in range(3):
            new_tangential[s, d] = pair_impulses.resting_tangential[c, d] * sign
    resting = wall_impulses.resting
    kept = 0
    for c in range(k):
        if keyed and resting[c] > 0.0:
            kept += 1
    keys = np.empty(kept, dtype=np.int64)
    rows = np.empty(kept, dtype=np.int64)
    kept = 0
    for c in range(k):
        if keyed and resting[c] > 0.0:
            keys[kept] = _wall_key(ids, walls, c)
            rows[kept] = c
            kept += 1
    sorted_rows = _stable_order(keys)
    new_wall_key = np.empty(kept, dtype=np.int64)
    new_wall_normal, new_wall_tangential = np.empty(kept), np.empty((kept, 3))
    for s in range(kept):
        c = rows[sorted_rows[s]]
        new_wall_key[s] = keys[sorted_rows[s]]
        new_wall_normal[s] = resting[c]
        for d in range(3):
            new_wall_tangential[s, d] = wall_impulses.resting_tangential[c, d]
    return WarmStartCache(new_key, new_normal, new_tangential, new_wall_key, new_wall_normal,
                          new_wall_tangential)


@njit(cache=True, nogil=True)
def solve_step(bodies, position, ids, contacts, planes, coefficients, settings, cache,
               booked, near):
    """Run a whole step's contact solve in one call (``_solve_step``); return ``SolveResult``.

    ``bodies``, ``contacts``, ``planes``, ``coefficients``, ``settings`` and
    ``cache`` are the records (``Bodies``, ``StepContacts``, ``WallPlanes``,
    ``Coefficients``, ``SolverSettings``, ``WarmStartCache``) as plain
    tuples, ``tuple(record)``: numba types a plain tuple argument in its
    compiled dispatcher but a NamedTuple in Python, tens of microseconds a
    call. ``near`` is (known, particles): with known, the only particles
    that may touch a wall plane (``StepContext.near_walls``), ascending.
    """
    return _solve_step(Bodies(*bodies), position, ids, StepContacts(*contacts),
                       WallPlanes(*planes), Coefficients(*coefficients),
                       SolverSettings(*settings), WarmStartCache(*cache), booked, near)


@njit(cache=True)
def _solve_step(bodies, position, ids, contacts, planes, coefficients, settings, cache,
                booked, near):
    """Run a whole step's contact solve: set-up, ``solve_contacts``, this solve's cache.

    The set-up: the wall contacts (``find_wall_contacts`` at WALL_SLOP of
    the ``planes``), e and mu per contact by the combine rule, the visit
    order (``visit_order`` with ``colour_order``, else the pairs in order),
    the speculative allowances (gap / dt), and the warm start looked up in
    ``cache``. ``booked`` (the
    step's losses per particle so far, or empty) is updated in place.
    Returns a ``SolveResult`` with this solve's cache.
    """
    n, m = bodies.velocity.shape[0], contacts.first.size
    dynamic = np.empty(n, dtype=np.bool_)
    for p in range(n):
        dynamic[p] = bodies.inv_mass[p] > 0.0
    pairs = _pair_contacts(bodies, contacts, coefficients, settings)
    walls = _wall_contacts(bodies.radius, dynamic, position, planes, coefficients, settings,
                           near)
    k = walls.particle.size
    pair_impulses, wall_impulses = _contact_impulses(m), _contact_impulses(k)
    # Ids past MAX_CACHED_ID would overflow the keys: such a world keeps no cache.
    keyed = settings.accumulate
    for p in range(n if keyed else 0):
        if ids[p] > MAX_CACHED_ID:
            keyed = False
    if keyed:
        _warm_from(cache, ids, pairs, walls, pair_impulses, wall_impulses)
    budget = settings.iterations
    if settings.accumulate and budget < COLD_START_SWEEPS and _mostly_cold(
            bodies, pairs, walls, pair_impulses, wall_impulses, settings):
        budget = COLD_START_SWEEPS
    if settings.accumulate:
        _seed_loads(bodies, dynamic, pairs, walls, pair_impulses, wall_impulses, settings)
    warm = n if settings.accumulate else 0
    # Spin factors only with friction (nothing reads them without).
    marks = ParticleMarks(dynamic, np.zeros(n, dtype=np.bool_),
                          np.zeros(n if settings.friction else 0),
                          np.zeros((warm, 3)), np.zeros(warm, dtype=np.bool_))
    # Per-particle bookings go straight into ``booked`` when the step books per
    # particle; without, into scratch nothing reads (no zeroing).
    losses = Losses(booked if booked.size == n else np.empty(n), np.zeros(len(EFFECTS)))
    sweeps = solve_contacts(bodies, marks, pairs, walls, pair_impulses, wall_impulses,
                            settings, losses, budget)
    return SolveResult(sweeps, losses.totals, pair_impulses, walls, wall_impulses,
                       _kept(ids, pairs, walls, pair_impulses, wall_impulses, keyed))


@njit(cache=True, nogil=True)
def jacobi_sweeps(bodies, contacts, coefficients, iterations):
    """Solve the pairs batched (``_jacobi_sweeps``); the records as plain tuples.

    ``bodies``, ``contacts`` and ``coefficients`` are ``tuple(record)`` of a
    ``Bodies``, ``StepContacts`` and ``Coefficients`` (as for ``solve_step``).
    """
    return _jacobi_sweeps(Bodies(*bodies), StepContacts(*contacts),
                          Coefficients(*coefficients), iterations)


@njit(cache=True)
def _jacobi_sweeps(bodies, contacts, coefficients, iterations):
    """Solve the pairs batched: each sweep's impulses from the velocities at its start.

    A particle in k approaching contacts of a sweep receives each of their
    impulses scaled by 1/k (each contact takes the smaller share of its two
    particles; a static particle forces none). The impulses of a sweep are
    summed per particle in pair order (first sides, then second sides) and
    applied at once; each particle's loss is the exact work of its sum,
    -(v . P + w |P|^2 / 2). Returns a ``JacobiResult``.
    """
    v, inv_mass, normal = bodies.velocity, bodies.inv_mass, contacts.normal
    first, second = contacts.first, contacts.second
    n, m = v.shape[0], first.size
    own = coefficients.own_restitution
    has_own = own.size > 0
    rest = np.empty(m)
    approach = np.empty(m)
    for k in range(m):
        a, b = first[k], second[k]
        rest[k] = combined_coefficient(own, has_own, a, b, coefficients.restitution)
        approach[k] = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2],
                            normal[k, 0], normal[k, 1], normal[k, 2])
    hit = np.zeros(m, dtype=np.bool_)
    summed = np.zeros(m)
    closing, magnitude = np.empty(m), np.zeros(m)
    degree = np.zeros(n, dtype=np.int64)
    total = np.zeros((n, 3))
    touched = np.zeros(n, dtype=np.bool_)
    sweep_start = np.zeros(iterations + 1, dtype=np.int64)
    particle = np.empty(0, dtype=np.int64)
    removed = np.empty(0)
    count = 0
    sweeps = 0
    for _ in range(iterations):
        any_closing = False
        for k in range(m):
            a, b = first[k], second[k]
            closing[k] = -dot3(v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2],
                               normal[k, 0], normal[k, 1], normal[k, 2])
            if closing[k] > 0.0:
                any_closing = True
                if inv_mass[a] > 0.0:
                    degree[a] += 1
                if inv_mass[b] > 0.0:
                    degree[b] += 1
        if not any_closing:
            break
        sweeps += 1
        for k in range(m):
            if not closing[k] > 0.0:
                continue
            a, b = first[k], second[k]
            share = 1.0 / max(max(float(degree[a]), float(degree[b])), 1.0)
            magnitude[k] = (1.0 + rest[k]) * closing[k] / (inv_mass[a] + inv_mass[b]) * share
            summed[k] += magnitude[k]
            hit[k] = True
            for d in range(3):
                total[a, d] += magnitude[k] * normal[k, d]
            touched[a] = True
        for k in range(m):
            if closing[k] > 0.0:
                b = second[k]
                for d in range(3):
                    total[b, d] += -(magnitude[k] * normal[k, d])
                touched[b] = True
        grow = 0
        for p in range(n):
            if touched[p]:
                grow += 1
        if count + grow > particle.size:
            size = max(2 * particle.size, count + grow)
            more_particle, more_removed = np.empty(size, dtype=np.int64), np.empty(size)
            more_particle[:count] = particle[:count]
            more_removed[:count] = removed[:count]
            particle, removed = more_particle, more_removed
        for p in range(n):
            if not touched[p]:
                continue
            w = inv_mass[p]
            px, py, pz = total[p, 0], total[p, 1], total[p, 2]
            work = 0.0
            if w > 0.0:
                work = (dot3(v[p, 0], v[p, 1], v[p, 2], px, py, pz)
                        + 0.5 * w * dot3(px, py, pz, px, py, pz))
            particle[count], removed[count] = p, -work
            count += 1
            v[p, 0] += w * px
            v[p, 1] += w * py
            v[p, 2] += w * pz
            total[p, 0] = total[p, 1] = total[p, 2] = 0.0
            touched[p] = False
            degree[p] = 0
        sweep_start[sweeps] = count
    return JacobiResult(sweeps, hit, summed, approach, sweep_start[:sweeps + 1].copy(),
                        particle[:count].copy(), removed[:count].copy())


@njit(cache=True, nogil=True)
def support_shift(inv_mass, contacts, pair_impulses, walls, wall_impulses, fall, dt):
    """Return how far the step's resting contacts held each particle up (``_support_shift``).

    The records (``StepContacts``, ``ContactImpulses``, ``WallContacts``)
    come as plain tuples, as ``solve_step`` takes them.
    """
    return _support_shift(inv_mass, StepContacts(*contacts), ContactImpulses(*pair_impulses),
                          WallContacts(*walls), ContactImpulses(*wall_impulses), fall, dt)


@njit(cache=True)
def _support_shift(inv_mass, contacts, pair_impulses, walls, wall_impulses, fall, dt):
    """Return, per particle, how far the step's resting contacts held it up, m (n, 3).

    The drift took every particle along its free parabola, g dt^2 / 2 below
    the straight path; a resting contact's impulse stands for a force that
    acted all through the step. Per particle, u is the velocity change of
    its accumulated resting impulses (normal and tangential with other
    particles, tangential with walls: the walls stage already put a
    particle that sank past a plane back on it) and k = -g dt (``fall`` is
    g dt) the kick it undoes: the part
    of the kick they carried is c = u min(1, max(0, k.u / |u|^2)), never
    more than k, and a force c m / dt held through the step moves the
    particle by c dt / 2. A particle at rest on its supports gets exactly
    its sag back; one sliding on a slope gets its sag along the normal;
    one nothing holds gets nothing. Only a chain of resting contacts to a
    wall or a static particle holds anything up: in a cluster touching
    neither (falling freely) the contacts only push its particles apart,
    and none moves. ``contacts``: the pairs as the solve took them
    (``StepContacts``), normals from ``second`` to ``first``.
    """
    n = inv_mass.shape[0]
    held = np.zeros((n, 3))
    first, second, normal = contacts.first, contacts.second, contacts.normal
    resting, tangential = pair_impulses.resting, pair_impulses.resting_tangential
    # Level 0 at a wall or a static particle, spread over the resting pairs.
    level = np.full(n, UNSUPPORTED, dtype=np.int64)
    count = 0
    for k in range(first.size):
        if resting[k] > 0.0:
            count += 1
    chain_first = np.empty(count, dtype=np.int64)
    chain_second = np.empty(count, dtype=np.int64)
    count = 0
    for k in range(first.size):
        if not resting[k] > 0.0:
            continue
        a, b = first[k], second[k]
        chain_first[count], chain_second[count] = a, b
        count += 1
        if not inv_mass[a] > 0.0:
            level[a] = 0
        if not inv_mass[b] > 0.0:
            level[b] = 0
        jx = resting[k] * normal[k, 0] + tangential[k, 0]
        jy = resting[k] * normal[k, 1] + tangential[k, 1]
        jz = resting[k] * normal[k, 2] + tangential[k, 2]
        held[a, 0] += inv_mass[a] * jx
        held[a, 1] += inv_mass[a] * jy
        held[a, 2] += inv_mass[a] * jz
        held[b, 0] -= inv_mass[b] * jx
        held[b, 1] -= inv_mass[b] * jy
        held[b, 2] -= inv_mass[b] * jz
    resting, tangential = wall_impulses.resting, wall_impulses.resting_tangential
    for c in range(walls.particle.size):
        if not resting[c] > 0.0:
            continue
        # The walls stage already put a particle its sag took past a plane back
        # on it: only the wall's friction holds anything up here.
        p = walls.particle[c]
        level[p] = 0
        w = inv_mass[p]
        held[p, 0] += w * tangential[c, 0]
        held[p, 1] += w * tangential[c, 1]
        held[p, 2] += w * tangential[c, 2]
    spread_levels(level, chain_first, chain_second)
    kx, ky, kz = -fall[0], -fall[1], -fall[2]
    for p in range(n):
        ux, uy, uz = held[p, 0], held[p, 1], held[p, 2]
        size = dot3(ux, uy, uz, ux, uy, uz)
        if level[p] == UNSUPPORTED or not size > 0.0:
            held[p, 0] = held[p, 1] = held[p, 2] = 0.0
            continue
        carried = min(1.0, max(0.0, dot3(kx, ky, kz, ux, uy, uz) / size)) * 0.5 * dt
        held[p, 0], held[p, 1], held[p, 2] = carried * ux, carried * uy, carried * uz
    return held


def warm_up() -> None:
    """Call this module's kernels once on a tiny problem (compiles or loads the cache)."""
    from ...law.coloring import greedy_colors
    velocity = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    bodies = Bodies(velocity, np.zeros((2, 3)), np.ones(2), np.ones(2))
    first, second = np.array([1], dtype=np.int64), np.array([0], dtype=np.int64)
    normal = np.array([[-1.0, 0.0, 0.0]])
    none, no_rows = np.zeros(0), np.zeros(0, dtype=np.int64)
    greedy_colors(first, second, np.ones(2, dtype=bool), 32)
    # The whole step's solve: a floor under the pair, both warm-started from a cache.
    position = np.array([[0.0, 1.0, 0.0], [1.9, 1.0, 0.0]])
    ids = np.array([0, 1], dtype=np.int64)
    contacts = StepContacts(first, second, normal, no_rows, np.array([0.01]), no_rows)
    floor = WallPlanes(np.zeros(1, dtype=np.int64), np.zeros(1), np.ones(1), np.zeros(1))
    coefficients = Coefficients(none, none, 1.0, 1.0, 1.0)
    settings = SolverSettings(True, 0.1, 1e-4, 10.0, 4, True, True, True, False, 0.01, 1e-3,
                              0.02, True, 0.0, -0.1, 0.0, 2)
    cache = WarmStartCache(np.array([1], dtype=np.int64), np.ones(1), np.ones((1, 3)),
                           np.array([3], dtype=np.int64), np.ones(1), np.ones((1, 3)))
    for near in ((False, np.zeros(0, dtype=np.int64)), (True, np.arange(2))):
        result = solve_step(tuple(bodies), position, ids, tuple(contacts), tuple(floor),
                            tuple(coefficients), tuple(settings), tuple(cache), np.zeros(2),
                            near)
        support_shift(bodies.inv_mass, tuple(contacts), tuple(result.pairs),
                      tuple(result.walls), tuple(result.wall_impulses), (0.0, -0.1, 0.0), 0.01)
    jacobi_sweeps(tuple(bodies), tuple(contacts), tuple(coefficients), 4)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    from ...law.coloring import greedy_colors
    return [solve_step, support_shift, jacobi_sweeps, greedy_colors]
