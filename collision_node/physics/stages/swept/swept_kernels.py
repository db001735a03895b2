"""The swept stage of ``ccd``, compiled: times of impact and the rounds of impacts in one call.

``sweep`` predicts the time of impact of every candidate pair (the smaller
root of |d + u s| = r_i + r_j in units of r_i + r_j; on parabolas under
gravity, where a falling and a static particle meet at the first root of a
quartic) and of every wall plane (linear, or a parabola's entering root).
Then it runs rounds: each takes the impacts that are the earliest at both
of their particles (``sequential``: ties by pair order, so one impact per
particle; ``batched``: every impact at a particle's earliest time, the
impulses shared out by degree as ``batched_impulses`` does), moves their
particles to the impact, applies the contact law of ``law/primitives``
(normal impulse, combine rule, restitution threshold with the resting rule
and 'struck' particles, Coulomb friction with spin) and predicts again only
the pairs of the particles that changed. With drag, particles move between
impacts on drag's closed form (its work booked as 'drag'), while impact
times are solved on the drag-free path. With requery, a particle an impact
sends out of the ball its broadphase query covered gets new candidate
pairs for the rest of its path. Finally every particle moves to the step end.

Each formula keeps the order of floating-point operations of the stage's
vectorised statement (``test/swept_reference.py``; ``dot3`` sums as numpy's
einsum, norms as ``np.linalg.norm``), and energy is booked per particle in
the order the reference books it, so the two agree to the bit except in
the quartic's eigenvalues (another LAPACK routine) and drag's exponentials
(libm's, not numpy's vector loops), which agree to a few units in the last
place.

A round costs what it resolves: only pending impacts are scanned, and only
the pairs of changed particles (a per-particle list) are predicted again.
The kernels take named records (``Particles``, ``OwnCoefficients``, ``Box``,
``Settings``, ``Candidates``, ``Escapes``, ``Tally`` and the workspace's
``PairState``, ``ParticleRounds``, ``Incidence``), built by the stage.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401 (chooses numba's cache directory first)
from numba import njit, prange  # noqa: E402 (after the cache directory is chosen)

from ...law.primitives import (apply_wall_normal, BOOKED, book_loss, book_pair_loss,
                               combined_coefficient, dot3, entering_time, FRICTION,
                               line_of_action, pair_friction, pair_impulse,
                               parabola_sphere_time, RESTITUTION, sphere_contact_time,
                               WALLS)  # noqa: E402
from ...model.tunables import (PARALLEL_BLOCK_ITEMS, PARALLEL_MIN_ITEMS, REACH_MARGIN,
                               SERIES_LIMIT)  # noqa: E402

# Row of the loss array (after the law's rows and BOOKED) that holds drag's work.
DRAG = BOOKED + 1
LOSS_ROWS = DRAG + 1
# Columns of the float record of each impact: time, point (3), normal (3),
# normal impulse, tangential impulse, approach speed.
RECORD_WIDTH = 10
# Largest number of wall columns (low and high in three dimensions).
WALL_COLUMNS = 6


class Particles(NamedTuple):
    """The particle arrays a step moves in place (the state's own arrays)."""

    position: np.ndarray    # (n, 3) m
    velocity: np.ndarray    # (n, 3) m/s
    spin: np.ndarray        # (n, 3) angular velocity, rad/s
    inv_mass: np.ndarray    # (n,) 1/kg, 0 for static particles
    radius: np.ndarray      # (n,) m
    dynamic: np.ndarray     # (n,) bool


class OwnCoefficients(NamedTuple):
    """Each particle's own restitution and friction (NaN: none), used when ``has_*``."""

    restitution: np.ndarray
    has_restitution: bool
    friction: np.ndarray
    has_friction: bool


class Box(NamedTuple):
    """The walls: planes per axis (-inf / inf: none on that side) and their restitution."""

    present: bool
    low: np.ndarray         # (3,) m
    high: np.ndarray        # (3,) m
    restitution: float


class Settings(NamedTuple):
    """What one step of the stage does."""

    dt: float               # s
    dimensions: int
    rounds: int             # most rounds of impacts
    batched: bool           # batched ordering (else sequential)
    requery: bool           # query again the particles an impact sends out of their ball
    restitution: float      # the scene's particle restitution
    has_friction: bool
    friction: float         # the scene's mu
    gravity: np.ndarray     # (3,) m/s^2, zeros without gravity
    has_gravity: bool
    min_speed: float        # restitution threshold, m/s (slower impacts are resting contact)
    strike_speed: float     # an impact this fast (with e > 0) marks its particles struck
    drag_linear: float      # kg/s
    drag_quadratic: float   # kg/m
    has_drag: bool
    record: bool            # return the impact records
    threads: int            # threads the first round's predictions and the last move share


class Candidates(NamedTuple):
    """The candidate pairs (one particle at least dynamic) and the contacts resting at start."""

    first: np.ndarray           # (m,) int64
    second: np.ndarray          # (m,) int64
    resting_pair: np.ndarray    # (m,) bool, in contact at the step start
    resting_wall: np.ndarray    # (n, 2 dimensions) bool, per wall column
    has_resting: bool


class Escapes(NamedTuple):
    """Requery: each particle's swept ball at the step start, and the escaped paths' balls."""

    centre: np.ndarray      # (n, 3) m, the mid-step point of the path
    half: np.ndarray        # (n,) m, the ball holding the path around it
    sag: float              # |g|, m/s^2
    escaped: np.ndarray     # (n,) bool
    middle: np.ndarray      # (n, 3) m, centre of the ball of an escaped path's rest
    reach: np.ndarray       # (n,) m, its radius plus the particle's


class Tally(NamedTuple):
    """What a step booked: energy per row (``LOSS_ROWS``) and particle, totals, counts."""

    loss: np.ndarray        # (LOSS_ROWS, n) J; BOOKED starts at the step's losses so far
    totals: np.ndarray      # (LOSS_ROWS,) J
    counts: np.ndarray      # pair impacts, wall impacts, rounds run, pairs resolved


class PairState(NamedTuple):
    """The candidate pairs and what the rounds keep per pair (room for requery's pairs)."""

    first: np.ndarray       # int64
    second: np.ndarray      # int64
    resting: np.ndarray     # bool
    time: np.ndarray        # time of impact on the step clock, s (inf: none)
    listed: np.ndarray      # bool, in ``pending``
    seen: np.ndarray        # int64, last round it was predicted in
    pending: np.ndarray     # int64, pairs due in the step
    chosen: np.ndarray      # int64, pairs a round resolves


class ParticleRounds(NamedTuple):
    """What the rounds keep per particle (arrays at least n long)."""

    local_time: np.ndarray      # s, each particle's clock inside the step
    touched: np.ndarray         # bool, some impact of this step changed it
    struck: np.ndarray          # bool, an impact of at least strike_speed struck it
    is_changed: np.ndarray      # bool, changed in this round
    changed: np.ndarray         # int64, the particles changed in this round
    wall_due: np.ndarray        # int64, particles with a wall impact due in the step
    wall_listed: np.ndarray     # bool, in ``wall_due``
    best_pair: np.ndarray       # int64, its earliest pending pair in the round
    best_round: np.ndarray      # int64, the round ``best_pair`` and ``best_time`` are of
    best_time: np.ndarray       # s
    hits: np.ndarray            # int64, particles at a wall in the round
    first_wall: np.ndarray      # s, its earliest wall time
    wall_time: np.ndarray       # (n, WALL_COLUMNS) s
    degree: np.ndarray          # batched: impacts at the particle in the round
    impulse: np.ndarray         # (n, 3) batched: summed impulse of the round, N s


class Incidence(NamedTuple):
    """The pairs of each particle: a counting sort of the candidates, and requery's additions."""

    start: np.ndarray       # (n + 1,) int64, particle p's pairs are pairs[start[p]:start[p + 1]]
    fill: np.ndarray        # (n,) int64
    pairs: np.ndarray       # (2 m,) int64
    extra_head: np.ndarray  # (n,) int64, first link of p's added pairs, -1 for none
    link_next: np.ndarray   # int64, next link of the same particle, -1 for none
    link_pair: np.ndarray   # int64, the pair of a link


class SweepResult(NamedTuple):
    """The impacts of a step when recorded: floats (``RECORD_WIDTH``) and (i, j), j = -1 a wall."""

    records: np.ndarray
    index: np.ndarray


@njit(cache=True, inline='always')
def _relative(x, v, a, b, k, lag_a, lag_b, fall_a, fall_b, has_gravity):
    """Return component k of (offset, relative velocity) of a and b moved to a common time.

    On their parabolas under gravity (``fall_a``, ``fall_b``: each one's g along k).
    """
    if has_gravity:
        at_a = x[a, k] + v[a, k] * lag_a + 0.5 * fall_a * lag_a * lag_a
        at_b = x[b, k] + v[b, k] * lag_b + 0.5 * fall_b * lag_b * lag_b
        return at_a - at_b, (v[a, k] + fall_a * lag_a) - (v[b, k] + fall_b * lag_b)
    return (x[a, k] + v[a, k] * lag_a) - (x[b, k] + v[b, k] * lag_b), v[a, k] - v[b, k]


@njit(cache=True, error_model='numpy', inline='always')
def pair_time(x, v, radius, local_time, dynamic, a, b, gravity, has_gravity, min_speed,
              horizon):
    """Time of impact of pair (a, b) on the step clock, inf for none.

    Both particles are brought to the later of their clocks (on their
    parabolas under gravity); an approaching pair that overlaps impacts at
    once; a falling and a static particle meet at ``parabola_sphere_time``;
    an impact closing slower than ``min_speed`` is none (resting contact).
    """
    start = max(local_time[a], local_time[b])
    reach = radius[a] + radius[b]
    lag_a, lag_b = start - local_time[a], start - local_time[b]
    falls_a = 1.0 if dynamic[a] else 0.0
    falls_b = 1.0 if dynamic[b] else 0.0
    # Scalars, not small arrays: an allocation per pair would cost more than the root.
    px, ux = _relative(x, v, a, b, 0, lag_a, lag_b, gravity[0] * falls_a, gravity[0] * falls_b,
                       has_gravity)
    py, uy = _relative(x, v, a, b, 1, lag_a, lag_b, gravity[1] * falls_a, gravity[1] * falls_b,
                       has_gravity)
    pz, uz = _relative(x, v, a, b, 2, lag_a, lag_b, gravity[2] * falls_a, gravity[2] * falls_b,
                       has_gravity)
    p = (px, py, pz)
    u = (ux, uy, uz)
    accel_x = accel_y = accel_z = 0.0
    if has_gravity:
        accel_x = (gravity[0] * falls_a - gravity[0] * falls_b) / reach
        accel_y = (gravity[1] * falls_a - gravity[1] * falls_b) / reach
        accel_z = (gravity[2] * falls_a - gravity[2] * falls_b) / reach
    curved = accel_x != 0.0 or accel_y != 0.0 or accel_z != 0.0
    acc = (accel_x, accel_y, accel_z)
    ox, oy, oz = p[0] / reach, p[1] / reach, p[2] / reach
    cx, cy, cz = u[0] / reach, u[1] / reach, u[2] / reach
    if curved:
        delay = parabola_sphere_time(ox, oy, oz, cx, cy, cz, acc[0], acc[1], acc[2],
                                     horizon - start)
    else:
        delay = sphere_contact_time(ox, oy, oz, cx, cy, cz, p[0], p[1], p[2], u[0], u[1], u[2])
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
        if -dot3(nx, ny, nz, wx, wy, wz) * reach < min_speed:
            delay = np.inf
    return start + delay


@njit(cache=True, error_model='numpy', inline='always')
def wall_times(x, v, radius, local_time, p, low, high, dimensions, gravity, has_gravity,
               min_speed, out):
    """Write particle p's times of impact with each wall to row p of ``out``.

    Columns (low x, high x, low y, ...); a particle past a plane and moving
    further out impacts at once; under gravity the gap is a quadratic
    (``entering_time``); an impact closing slower than ``min_speed`` is none.
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
    lag_i, lag_j = start - local_time[i], start - local_time[j]
    g0, g1, g2 = gravity[0], gravity[1], gravity[2]
    px, ux = _relative(x, v, i, j, 0, lag_i, lag_j, g0, g0, True)
    py, uy = _relative(x, v, i, j, 1, lag_i, lag_j, g1, g1, True)
    pz, uz = _relative(x, v, i, j, 2, lag_i, lag_j, g2, g2, True)
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


@njit(cache=True, error_model='numpy')
def _predict_pairs(count, particles, pairs, clock, settings, has_resting):
    """Predict the first ``count`` pairs (the first round); list the due ones; return how many.

    Each gets ``pair_time`` with the scene's gravity and threshold; a
    resting pair not yet touched, and under gravity a pair ``_out_of_reach``
    rejects, get inf without solving for a root (``pair_time`` would give
    them inf or a time past dt, which the rounds treat alike). Listed in
    pair order; the times on the threads when the step shares its loops. A
    loop of its own with the records unpacked once: through an inlined
    per-pair helper each pair cost a reference count per array, and a
    helper returning from several branches compiled slower than the
    branches written out (``_predict_changed`` repeats them).
    """
    n_pending = 0
    if settings.threads > 1 and count >= PARALLEL_MIN_ITEMS:
        # The times on the threads, then the due pairs listed in pair order,
        # as the loop below lists them.
        _pair_times_parallel(particles, pairs, clock, settings, count, has_resting)
        for k in range(count):
            n_pending = _list_if_due(k, pairs.time[k], settings.dt, pairs.time, pairs.listed,
                                     pairs.pending, n_pending)
        return n_pending
    x, v, radius, dynamic = particles.position, particles.velocity, particles.radius, \
        particles.dynamic
    local_time, touched = clock.local_time, clock.touched
    first_of, second_of, resting = pairs.first, pairs.second, pairs.resting
    gravity, min_speed, dt = settings.gravity, settings.min_speed, settings.dt
    has_gravity = settings.has_gravity
    for k in range(count):
        i, j = first_of[k], second_of[k]
        if has_resting and resting[k] and not (touched[i] or touched[j]):
            t = np.inf
        elif has_gravity:
            if _out_of_reach(x, v, radius, local_time, dynamic, i, j, gravity, dt):
                t = np.inf
            else:
                t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, True, min_speed,
                              dt)
        elif min_speed > 0.0:
            t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, min_speed, dt)
        else:
            t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, 0.0, dt)
        n_pending = _list_if_due(k, t, dt, pairs.time, pairs.listed, pairs.pending, n_pending)
    return n_pending


@njit(cache=True, error_model='numpy', inline='always')
def _predict_pair(k, particles, pairs, clock, settings, has_resting, n_pending):
    """Predict pair k again; list it if due in the step; return the pending count."""
    x, v, radius, dynamic = particles.position, particles.velocity, particles.radius, \
        particles.dynamic
    local_time = clock.local_time
    i, j = pairs.first[k], pairs.second[k]
    gravity, dt = settings.gravity, settings.dt
    # Constant flags in each call: the inlined straight-path case compiles
    # without the gravity and threshold code (three times faster).
    if settings.has_gravity:
        t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, True,
                      settings.min_speed, dt)
    elif settings.min_speed > 0.0:
        t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False,
                      settings.min_speed, dt)
    else:
        t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, 0.0, dt)
    if has_resting and pairs.resting[k] and not (clock.touched[i] or clock.touched[j]):
        t = np.inf
    return _list_if_due(k, t, dt, pairs.time, pairs.listed, pairs.pending, n_pending)


@njit(cache=True, error_model='numpy', inline='always')
def _wall_row(p, particles, clock, box, settings, dimensions, has_gravity, min_speed,
              has_resting, resting_wall):
    """Write particle p's wall times (an untouched resting contact: inf); return the earliest."""
    wall_time = clock.wall_time
    wall_times(particles.position, particles.velocity, particles.radius, clock.local_time, p,
               box.low, box.high, dimensions, settings.gravity, has_gravity, min_speed,
               wall_time)
    first = np.inf
    for column in range(2 * dimensions):
        if has_resting and resting_wall[p, column] and not clock.touched[p]:
            wall_time[p, column] = np.inf
        if wall_time[p, column] < first:
            first = wall_time[p, column]
    clock.first_wall[p] = first
    return first


@njit(cache=True, error_model='numpy', inline='always')
def _predict_walls(p, particles, clock, box, settings, dimensions, has_gravity, min_speed,
                   has_resting, resting_wall, n_wall_due):
    """Predict particle p's wall impacts again; list it if due; return the due count."""
    first = _wall_row(p, particles, clock, box, settings, dimensions, has_gravity, min_speed,
                      has_resting, resting_wall)
    if first <= settings.dt and not clock.wall_listed[p]:
        clock.wall_listed[p] = True
        clock.wall_due[n_wall_due] = p
        n_wall_due += 1
    return n_wall_due


@njit(cache=True, error_model='numpy')
def _predict_straight(particles, pairs, clock, count, settings):
    """Predict the first ``count`` pairs on straight paths without threshold; return the due count.

    The first round's ``_predict_pair`` loop for the common case, compiled
    on its own: inside ``sweep`` the same loop ran three times slower.
    """
    x, v, radius, dynamic = particles.position, particles.velocity, particles.radius, \
        particles.dynamic
    local_time = clock.local_time
    first_of, second_of = pairs.first, pairs.second
    pair_t, listed, pending = pairs.time, pairs.listed, pairs.pending
    gravity, dt = settings.gravity, settings.dt
    n_pending = 0
    if settings.threads > 1 and count >= PARALLEL_MIN_ITEMS:
        # The times on the threads, then the due pairs listed in pair order.
        _pair_times_parallel(particles, pairs, clock, settings, count, np.bool_(False))
        for k in range(count):
            if pair_t[k] <= dt:
                listed[k] = True
                pending[n_pending] = k
                n_pending += 1
        return n_pending
    for k in range(count):
        t = pair_time(x, v, radius, local_time, dynamic, first_of[k], second_of[k], gravity,
                      False, 0.0, dt)
        pair_t[k] = t
        if t <= dt:
            listed[k] = True
            pending[n_pending] = k
            n_pending += 1
    return n_pending


@njit(cache=True, parallel=True)
def _pair_times_parallel(particles, pairs, clock, settings, count, has_resting):
    """Write the first ``count`` pairs' times (``_pair_times_in``), blocks of pairs on the threads.

    Each pair's time depends on its own particles only, so the values are
    the serial loops' whatever thread computes them. The blocks call a
    function that is never inlined: numba's parallel loops lose the stores
    of inlined code and of NamedTuple fields.
    """
    for block in prange((count + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS):
        start = block * PARALLEL_BLOCK_ITEMS
        _pair_times_in(particles, pairs, clock, settings, has_resting, start,
                       min(start + PARALLEL_BLOCK_ITEMS, count))


@njit(cache=True, error_model='numpy')
def _pair_times_in(particles, pairs, clock, settings, has_resting, start, stop):
    """Write the times of pairs start .. stop - 1 as the first round predicts them.

    Straight paths without a threshold or resting contact: ``_predict_straight``'s
    formula; otherwise ``_predict_pairs``' rules (resting pairs not yet touched
    and pairs out of reach get inf).
    """
    x, v, radius, dynamic = particles.position, particles.velocity, particles.radius, \
        particles.dynamic
    local_time, touched = clock.local_time, clock.touched
    first_of, second_of, resting, pair_t = pairs.first, pairs.second, pairs.resting, pairs.time
    gravity, min_speed, dt = settings.gravity, settings.min_speed, settings.dt
    if not settings.has_gravity and not min_speed > 0.0 and not has_resting:
        for k in range(start, stop):
            pair_t[k] = pair_time(x, v, radius, local_time, dynamic, first_of[k], second_of[k],
                                  gravity, False, 0.0, dt)
        return
    for k in range(start, stop):
        i, j = first_of[k], second_of[k]
        if has_resting and resting[k] and not (touched[i] or touched[j]):
            pair_t[k] = np.inf
        elif settings.has_gravity:
            if _out_of_reach(x, v, radius, local_time, dynamic, i, j, gravity, dt):
                pair_t[k] = np.inf
            else:
                pair_t[k] = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, True,
                                      min_speed, dt)
        elif min_speed > 0.0:
            pair_t[k] = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False,
                                  min_speed, dt)
        else:
            pair_t[k] = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, 0.0,
                                  dt)


@njit(cache=True, error_model='numpy')
def _predict_all_walls(particles, clock, box, settings, has_resting, resting_wall):
    """Predict every dynamic particle's wall impacts (the first round); return the due count.

    Compiled on its own, with constant flags in each inlined case, for the
    reason given at ``_predict_straight``.
    """
    dimensions, dt = settings.dimensions, settings.dt
    n_wall_due = 0
    n = particles.position.shape[0]
    if settings.threads > 1 and n >= PARALLEL_MIN_ITEMS:
        # The rows on the threads, then the due particles listed in index
        # order, as the loop below lists them.
        _wall_rows_parallel(particles, clock, box, settings, has_resting, resting_wall)
        straight = dimensions == 3 and not settings.has_gravity and \
            not (settings.min_speed > 0.0 or has_resting)
        for p in range(n):
            if particles.dynamic[p] and clock.first_wall[p] <= dt:
                if straight:
                    # The row of a due particle, as the loop below writes it.
                    n_wall_due = _predict_walls(p, particles, clock, box, settings, 3, False,
                                                0.0, False, resting_wall, n_wall_due)
                elif not clock.wall_listed[p]:
                    clock.wall_listed[p] = True
                    clock.wall_due[n_wall_due] = p
                    n_wall_due += 1
        return n_wall_due
    for p in range(n):
        if not particles.dynamic[p]:
            continue
        if settings.has_gravity:
            n_wall_due = _predict_walls(p, particles, clock, box, settings, dimensions, True,
                                        settings.min_speed, has_resting, resting_wall,
                                        n_wall_due)
        elif settings.min_speed > 0.0 or has_resting:
            n_wall_due = _predict_walls(p, particles, clock, box, settings, dimensions, False,
                                        settings.min_speed, has_resting, resting_wall,
                                        n_wall_due)
        elif dimensions == 3:
            # The earliest wall time alone, in locals: the row is written only
            # for a due particle (the others' rows are never read), and with a
            # constant dimension the compiler drops the branches on each
            # velocity's sign (random in a gas, mispredicted half the time).
            first = _first_wall_straight(particles.position, particles.velocity,
                                         particles.radius, clock.local_time, p, box.low,
                                         box.high, 3)
            clock.first_wall[p] = first
            if first <= dt:
                n_wall_due = _predict_walls(p, particles, clock, box, settings, 3, False, 0.0,
                                            False, resting_wall, n_wall_due)
        else:
            n_wall_due = _predict_walls(p, particles, clock, box, settings, dimensions, False,
                                        0.0, False, resting_wall, n_wall_due)
    return n_wall_due


@njit(cache=True, parallel=True)
def _wall_rows_parallel(particles, clock, box, settings, has_resting, resting_wall):
    """Write every dynamic particle's wall times (``_wall_rows_in``), blocks on the threads."""
    n = particles.position.shape[0]
    for block in prange((n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS):
        start = block * PARALLEL_BLOCK_ITEMS
        _wall_rows_in(particles, clock, box, settings, has_resting, resting_wall, start,
                      min(start + PARALLEL_BLOCK_ITEMS, n))


@njit(cache=True, error_model='numpy')
def _wall_rows_in(particles, clock, box, settings, has_resting, resting_wall, start, stop):
    """Write the wall times of particles start .. stop - 1 as ``_predict_all_walls`` does.

    The earliest time of each (3-D straight paths: that alone, the row is
    written when it is due), without listing them.
    """
    dimensions = settings.dimensions
    for p in range(start, stop):
        if not particles.dynamic[p]:
            continue
        if settings.has_gravity:
            _wall_row(p, particles, clock, box, settings, dimensions, True, settings.min_speed,
                      has_resting, resting_wall)
        elif settings.min_speed > 0.0 or has_resting:
            _wall_row(p, particles, clock, box, settings, dimensions, False,
                      settings.min_speed, has_resting, resting_wall)
        elif dimensions == 3:
            clock.first_wall[p] = _first_wall_straight(particles.position, particles.velocity,
                                                       particles.radius, clock.local_time, p,
                                                       box.low, box.high, 3)
        else:
            _wall_row(p, particles, clock, box, settings, dimensions, False, 0.0, False,
                      resting_wall)


@njit(cache=True, error_model='numpy', inline='always')
def _move(x, v, local_time, p, when, gravity, has_gravity):
    """Move particle p on its drag-free path to ``when``.

    Arrays, not records: a record handed to an inlined helper costs a
    reference count per array at every call.
    """
    tau = when - local_time[p]
    local_time[p] = when
    for k in range(3):
        if has_gravity:
            x[p, k] = x[p, k] + v[p, k] * tau + 0.5 * gravity[k] * tau * tau
            v[p, k] = v[p, k] + gravity[k] * tau
        else:
            x[p, k] = x[p, k] + v[p, k] * tau


@njit(cache=True, error_model='numpy')
def _advance(particles, local_time, p, when, settings, tally):
    """Move particle p on its free path to ``when``: ``_move``, or drag's closed form."""
    if settings.has_drag:
        tau = when - local_time[p]
        local_time[p] = when
        _advance_with_drag(particles, p, tau, settings, tally)
    else:
        _move(particles.position, particles.velocity, local_time, p, when, settings.gravity,
              settings.has_gravity)


@njit(cache=True, error_model='numpy')
def _advance_with_drag(particles, p, tau, settings, tally):
    """Move particle p by ``tau`` on drag's closed form (``motion/drag.py``); book its work.

    The rate lambda = (k1 + k2 |v|) / m is held at its start value:
    v = v0 e^(-lambda tau) + g phi, x = x0 + v0 phi + g psi, with
    phi = (1 - e^(-lambda tau)) / lambda and psi = (tau - phi) / lambda
    (its Taylor series below SERIES_LIMIT). Booked: the drag force's own
    work, the kinetic energy lost less gravity's work on the displacement.
    """
    x, v, gravity = particles.position, particles.velocity, settings.gravity
    inverse_mass = particles.inv_mass[p]
    ux, uy, uz = v[p, 0], v[p, 1], v[p, 2]
    rate = settings.drag_linear * inverse_mass
    if settings.drag_quadratic != 0.0:
        rate = rate + settings.drag_quadratic * inverse_mass * math.sqrt(dot3(ux, uy, uz,
                                                                              ux, uy, uz))
    exponent = rate * tau
    phi = -math.expm1(-exponent) / rate if rate > 0.0 else tau
    decay = math.exp(-exponent)
    dx, dy, dz = ux * phi, uy * phi, uz * phi
    wx, wy, wz = ux * decay, uy * decay, uz * decay
    if settings.has_gravity:
        if exponent < SERIES_LIMIT:
            psi = tau * tau * (0.5 + exponent * (-1.0 / 6.0 + exponent * (1.0 / 24.0 + exponent * (
                -1.0 / 120.0 + exponent / 720.0))))
        else:
            psi = (tau - phi) / rate
        dx, dy, dz = dx + psi * gravity[0], dy + psi * gravity[1], dz + psi * gravity[2]
        wx, wy, wz = wx + phi * gravity[0], wy + phi * gravity[1], wz + phi * gravity[2]
    x[p, 0] += dx
    x[p, 1] += dy
    x[p, 2] += dz
    v[p, 0], v[p, 1], v[p, 2] = wx, wy, wz
    work = 0.5 * dot3(ux - wx, uy - wy, uz - wz, ux + wx, uy + wy, uz + wz)
    if settings.has_gravity:
        work += (dx * gravity[0] + dy * gravity[1]) + dz * gravity[2]
    removed = work / inverse_mass
    book_loss(tally.loss, DRAG, p, removed)
    tally.totals[DRAG] += removed


@njit(cache=True, error_model='numpy')
def _advance_all(particles, local_time, when, settings, tally):
    """Move every dynamic particle on its free path to ``when`` (``_advance`` for each).

    One loop with the records unpacked once: ``_advance`` per particle would
    be a call, or inlined, take the records' reference counts per particle.
    """
    x, v, dynamic, gravity = particles.position, particles.velocity, particles.dynamic, \
        settings.gravity
    if not settings.has_drag and settings.threads > 1 and x.shape[0] >= PARALLEL_MIN_ITEMS:
        # Drag-free paths on the threads (drag books its work into one total,
        # summed in particle order, so it moves them here).
        _advance_parallel(particles, local_time, when, settings)
        return
    for p in range(x.shape[0]):
        if not dynamic[p]:
            continue
        if settings.has_drag:
            tau = when - local_time[p]
            local_time[p] = when
            _advance_with_drag(particles, p, tau, settings, tally)
        else:
            _move(x, v, local_time, p, when, gravity, settings.has_gravity)


@njit(cache=True, parallel=True)
def _advance_parallel(particles, local_time, when, settings):
    """Move every dynamic particle on its drag-free path to ``when``, blocks on the threads."""
    n = particles.position.shape[0]
    for block in prange((n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS):
        start = block * PARALLEL_BLOCK_ITEMS
        _advance_in(particles, local_time, when, settings, start,
                    min(start + PARALLEL_BLOCK_ITEMS, n))


@njit(cache=True, error_model='numpy')
def _advance_in(particles, local_time, when, settings, start, stop):
    """Move the dynamic particles start .. stop - 1 on their drag-free paths to ``when``."""
    x, v, dynamic, gravity = particles.position, particles.velocity, particles.dynamic, \
        settings.gravity
    for p in range(start, stop):
        if dynamic[p]:
            _move(x, v, local_time, p, when, gravity, settings.has_gravity)


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


@njit(cache=True, inline='always')
def _record_pair(records, index, count, t, particles, i, j, normal, impulses):
    """Append pair (i, j)'s impact (written i < j, the normal from j to i); return the arrays."""
    x, radius = particles.position, particles.radius
    records, index = _grow(records, index, count)
    first, second, sign = (i, j, 1.0) if i <= j else (j, i, -1.0)
    row = records[count]
    row[0] = t
    for axis in range(3):
        direction = sign * normal[axis] if sign < 0.0 else normal[axis]
        row[4 + axis] = direction
        row[1 + axis] = 0.5 * ((x[first, axis] - radius[first] * direction)
                               + (x[second, axis] + radius[second] * direction))
    row[7], row[8], row[9] = impulses
    index[count, 0], index[count, 1] = first, second
    return records, index


@njit(cache=True, inline='always')
def _mark_changed(is_changed, changed, p, n_changed):
    """List particle p as changed in this round (once); return the count."""
    if not is_changed[p]:
        is_changed[p] = True
        changed[n_changed] = p
        n_changed += 1
    return n_changed


@njit(cache=True, error_model='numpy')
def _resolve_sequential(particles, own, settings, has_resting, pairs, clock, tally, n_chosen,
                        n_changed, records, index, count):
    """Resolve the round's chosen pairs one after another (they share no dynamic particle).

    Returns (changed count, records, index, record count).
    """
    x, v, spin = particles.position, particles.velocity, particles.spin
    inv_mass, radius, dynamic = particles.inv_mass, particles.radius, particles.dynamic
    loss, totals, counts = tally.loss, tally.totals, tally.counts
    struck, touched = clock.struck, clock.touched
    local_time, is_changed, changed = clock.local_time, clock.is_changed, clock.changed
    gravity, has_gravity = settings.gravity, settings.has_gravity
    min_speed, planar = settings.min_speed, settings.dimensions == 2
    for k in np.sort(pairs.chosen[:n_chosen]):
        i, j = pairs.first[k], pairs.second[k]
        t = pairs.time[k]
        for p in (i, j):
            if not dynamic[p]:
                continue
            if settings.has_drag:
                _advance(particles, local_time, p, t, settings, tally)
            else:
                _move(x, v, local_time, p, t, gravity, has_gravity)
        nx, ny, nz, _ = line_of_action(x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2],
                                       v[i, 0] - v[j, 0], v[i, 1] - v[j, 1], v[i, 2] - v[j, 2])
        e = combined_coefficient(own.restitution, own.has_restitution, i, j,
                                 settings.restitution)
        if min_speed > 0.0:
            closing = dot3(v[j, 0] - v[i, 0], v[j, 1] - v[i, 1], v[j, 2] - v[i, 2], nx, ny, nz)
            if closing < min_speed:
                e = 0.0
        if has_resting and pairs.resting[k] and not (struck[i] or struck[j]):
            e = 0.0
        n_changed = _mark_changed(is_changed, changed, i, n_changed)
        n_changed = _mark_changed(is_changed, changed, j, n_changed)
        magnitude, approach, removed = pair_impulse(v, inv_mass, i, j, nx, ny, nz, e, 0.0)
        if not approach > 0.0:
            continue
        share = inv_mass[i] / (inv_mass[i] + inv_mass[j])
        book_pair_loss(loss, RESTITUTION, i, j, removed, share)
        totals[RESTITUTION] += removed
        tangential = 0.0
        if settings.has_friction:
            pair_mu = combined_coefficient(own.friction, own.has_friction, i, j,
                                           settings.friction)
            tangential, lost = pair_friction(v, spin, inv_mass, radius, i, j, nx, ny, nz,
                                             magnitude, pair_mu, planar)
            book_pair_loss(loss, FRICTION, i, j, lost, share)
            totals[FRICTION] += lost
        counts[0] += 1
        if e > 0.0 and approach >= settings.strike_speed:
            struck[i] = struck[j] = True
        touched[i] = touched[j] = True
        if settings.record:
            records, index = _record_pair(records, index, count, t, particles, i, j,
                                          (nx, ny, nz), (magnitude, tangential, approach))
            count += 1
    return n_changed, records, index, count


@njit(cache=True, error_model='numpy')
def _resolve_batched(particles, own, settings, has_resting, pairs, clock, tally, n_chosen,
                     n_changed, records, index, count):
    """Resolve the round's chosen pairs at once from the same velocities (Jacobi).

    A particle in k impacts of the round takes each impulse scaled by
    1 / max(k_i, k_j) of its pair (the batched solve's share, so a round
    never adds energy); the summed impulse per particle is applied and its
    exact work, -(v . P + w |P|^2 / 2), booked. Returns what
    ``_resolve_sequential`` does.
    """
    x, v = particles.position, particles.velocity
    inv_mass, dynamic = particles.inv_mass, particles.dynamic
    loss, totals, counts = tally.loss, tally.totals, tally.counts
    struck, touched, degree, impulse = clock.struck, clock.touched, clock.degree, clock.impulse
    min_speed = settings.min_speed
    order = np.sort(pairs.chosen[:n_chosen])
    for k in order:
        for p in (pairs.first[k], pairs.second[k]):
            if dynamic[p]:
                _advance(particles, clock.local_time, p, pairs.time[k], settings, tally)
    normals = np.empty((n_chosen, 3))
    restitution = np.empty(n_chosen)
    approach = np.empty(n_chosen)
    for q in range(n_chosen):
        i, j = pairs.first[order[q]], pairs.second[order[q]]
        nx, ny, nz, _ = line_of_action(x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2],
                                       v[i, 0] - v[j, 0], v[i, 1] - v[j, 1], v[i, 2] - v[j, 2])
        e = combined_coefficient(own.restitution, own.has_restitution, i, j,
                                 settings.restitution)
        if min_speed > 0.0:
            closing = dot3(v[j, 0] - v[i, 0], v[j, 1] - v[i, 1], v[j, 2] - v[i, 2], nx, ny, nz)
            if closing < min_speed:
                e = 0.0
        if has_resting and pairs.resting[order[q]] and not (struck[i] or struck[j]):
            e = 0.0
        normals[q, 0], normals[q, 1], normals[q, 2] = nx, ny, nz
        restitution[q] = e
        approach[q] = -dot3(v[i, 0] - v[j, 0], v[i, 1] - v[j, 1], v[i, 2] - v[j, 2], nx, ny, nz)
        degree[i] = degree[j] = 0.0
        impulse[i, :] = 0.0
        impulse[j, :] = 0.0
    for q in range(n_chosen):
        i, j = pairs.first[order[q]], pairs.second[order[q]]
        degree[i] += 1.0 if dynamic[i] else 0.0
        degree[j] += 1.0 if dynamic[j] else 0.0
    magnitude = np.zeros(n_chosen)
    members = np.empty(2 * n_chosen, dtype=np.int64)
    n_members = 0
    for q in range(n_chosen):
        i, j = pairs.first[order[q]], pairs.second[order[q]]
        if approach[q] > 0.0:
            magnitude[q] = (1.0 + restitution[q]) * approach[q] / (inv_mass[i] + inv_mass[j]) \
                * (1.0 / max(max(degree[i], degree[j]), 1.0))
            members[n_members], members[n_members + 1] = i, j
            n_members += 2
    # The summed impulse of each particle: first sides in pair order, then second sides.
    for side in range(2):
        for q in range(n_chosen):
            if approach[q] > 0.0:
                p = pairs.first[order[q]] if side == 0 else pairs.second[order[q]]
                for axis in range(3):
                    push = magnitude[q] * normals[q, axis]
                    impulse[p, axis] += push if side == 0 else -push
    members = np.sort(members[:n_members])
    for slot in range(n_members):
        p = members[slot]
        if slot > 0 and members[slot - 1] == p:
            continue
        weight = inv_mass[p]
        ix, iy, iz = impulse[p, 0], impulse[p, 1], impulse[p, 2]
        removed = -0.0
        if weight > 0.0:
            removed = -(dot3(v[p, 0], v[p, 1], v[p, 2], ix, iy, iz)
                        + 0.5 * weight * dot3(ix, iy, iz, ix, iy, iz))
        v[p, 0] += weight * ix
        v[p, 1] += weight * iy
        v[p, 2] += weight * iz
        book_loss(loss, RESTITUTION, p, removed)
        totals[RESTITUTION] += removed
    for q in range(n_chosen):
        i, j = pairs.first[order[q]], pairs.second[order[q]]
        n_changed = _mark_changed(clock.is_changed, clock.changed, i, n_changed)
        n_changed = _mark_changed(clock.is_changed, clock.changed, j, n_changed)
        if not approach[q] > 0.0:
            continue
        counts[0] += 1
        if restitution[q] > 0.0 and approach[q] >= settings.strike_speed:
            struck[i] = struck[j] = True
        touched[i] = touched[j] = True
        if settings.record:
            records, index = _record_pair(records, index, count, pairs.time[order[q]],
                                          particles, i, j,
                                          (normals[q, 0], normals[q, 1], normals[q, 2]),
                                          (magnitude[q], 0.0, approach[q]))
            count += 1
    return n_changed, records, index, count


@njit(cache=True, error_model='numpy')
def _resolve_walls(particles, own, box, settings, candidates, clock, tally, n_hits, n_changed,
                   records, index, count):
    """Move the round's wall hits to their first wall time and apply the law, plane by plane.

    Returns (changed count, records, index, record count).
    """
    x, v, spin = particles.position, particles.velocity, particles.spin
    inv_mass, radius = particles.inv_mass, particles.radius
    loss, totals, counts = tally.loss, tally.totals, tally.counts
    struck, touched = clock.struck, clock.touched
    min_speed, planar = settings.min_speed, settings.dimensions == 2
    has_resting, resting_wall = candidates.has_resting, candidates.resting_wall
    for q in range(n_hits):
        p = clock.hits[q]
        _advance(particles, clock.local_time, p, clock.first_wall[p], settings, tally)
        n_changed = _mark_changed(clock.is_changed, clock.changed, p, n_changed)
    hit_order = np.sort(clock.hits[:n_hits])
    for axis in range(settings.dimensions):
        for column, plane, inward in ((2 * axis, box.low[axis], 1.0),
                                      (2 * axis + 1, box.high[axis], -1.0)):
            for p in hit_order:
                if not (clock.wall_time[p, column] == clock.first_wall[p]
                        and inward * v[p, axis] < 0.0):
                    continue
                e = combined_coefficient(own.restitution, own.has_restitution, p, -1,
                                         box.restitution)
                if min_speed > 0.0 and -inward * v[p, axis] < min_speed:
                    e = 0.0
                if has_resting and resting_wall[p, column] and not struck[p]:
                    e = 0.0
                approach = -inward * v[p, axis]
                magnitude, removed = apply_wall_normal(v, inv_mass, p, axis, inward, e,
                                                       approach if approach > 0.0 else 0.0)
                book_loss(loss, WALLS, p, removed)
                totals[WALLS] += removed
                if e > 0.0 and approach >= settings.strike_speed:
                    struck[p] = True
                touched[p] = True
                tangential = 0.0
                nx = inward if axis == 0 else 0.0
                ny = inward if axis == 1 else 0.0
                nz = inward if axis == 2 else 0.0
                if settings.has_friction:
                    wall_mu = combined_coefficient(own.friction, own.has_friction, p, -1,
                                                   settings.friction)
                    tangential, lost = pair_friction(v, spin, inv_mass, radius, p, -1, nx, ny,
                                                     nz, magnitude, wall_mu, planar)
                    book_loss(loss, FRICTION, p, lost)
                    totals[FRICTION] += lost
                counts[1] += 1
                if settings.record:
                    records, index = _grow(records, index, count)
                    row = records[count]
                    row[0] = clock.local_time[p]
                    row[1], row[2], row[3] = x[p, 0], x[p, 1], x[p, 2]
                    row[1 + axis] = plane
                    row[4], row[5], row[6] = nx, ny, nz
                    row[7], row[8], row[9] = magnitude, tangential, approach
                    index[count, 0], index[count, 1] = p, -1
                    count += 1
    return n_changed, records, index, count


@njit(cache=True, inline='always')
def _distance(dx, dy, dz):
    """Return |d| summed as ``np.linalg.norm`` over the last axis sums it."""
    return math.sqrt((dx * dx + dy * dy) + dz * dz)


@njit(cache=True, inline='always')
def _rest_ball(particles, p, rest, settings, sag):
    """Return (centre, radius) of a ball holding the rest of p's path (``rest`` s of it).

    Centre: the chord's midpoint x + v t / 2 + g t^2 / 4; every point of
    the parabola (or of a drag path, which only falls short of it) lies
    within |v| t / 2 + |g| t^2 / 4 of it.
    """
    x, v, gravity = particles.position, particles.velocity, settings.gravity
    mx = x[p, 0] + v[p, 0] * (0.5 * rest)
    my = x[p, 1] + v[p, 1] * (0.5 * rest)
    mz = x[p, 2] + v[p, 2] * (0.5 * rest)
    own = _distance(v[p, 0], v[p, 1], v[p, 2]) * (0.5 * rest)
    if settings.has_gravity:
        mx = mx + gravity[0] * (0.25 * rest * rest)
        my = my + gravity[1] * (0.25 * rest * rest)
        mz = mz + gravity[2] * (0.25 * rest * rest)
        own = own + sag * 0.25 * rest * rest
    return mx, my, mz, own


@njit(cache=True)
def _grow_pairs(pairs, count):
    """Return the pair state with twice the room, its first ``count`` pairs kept."""
    size = 2 * pairs.first.size + 16
    first = np.empty(size, dtype=np.int64)
    second = np.empty(size, dtype=np.int64)
    resting = np.empty(size, dtype=np.bool_)
    time = np.empty(size)
    listed = np.empty(size, dtype=np.bool_)
    seen = np.empty(size, dtype=np.int64)
    pending = np.empty(size, dtype=np.int64)
    first[:count], second[:count] = pairs.first[:count], pairs.second[:count]
    resting[:count], time[:count] = pairs.resting[:count], pairs.time[:count]
    listed[:count], seen[:count] = pairs.listed[:count], pairs.seen[:count]
    pending[:count] = pairs.pending[:count]
    return PairState(first, second, resting, time, listed, seen, pending,
                     np.empty(size, dtype=np.int64))


@njit(cache=True)
def _grow_links(incidence, count):
    """Return the incidence with twice the room for added pairs' links."""
    size = 2 * incidence.link_next.size + 16
    link_next = np.empty(size, dtype=np.int64)
    link_pair = np.empty(size, dtype=np.int64)
    link_next[:count] = incidence.link_next[:count]
    link_pair[:count] = incidence.link_pair[:count]
    return Incidence(incidence.start, incidence.fill, incidence.pairs, incidence.extra_head,
                     link_next, link_pair)


@njit(cache=True)
def _is_known(pairs, incidence, lo, hi):
    """Say whether the pair list holds (lo, hi) in that order."""
    for slot in range(incidence.start[lo], incidence.start[lo + 1]):
        k = incidence.pairs[slot]
        if pairs.first[k] == lo and pairs.second[k] == hi:
            return True
    link = incidence.extra_head[lo]
    while link >= 0:
        k = incidence.link_pair[link]
        if pairs.first[k] == lo and pairs.second[k] == hi:
            return True
        link = incidence.link_next[link]
    return False


@njit(cache=True)
def _add_key(keys, n_keys, p, q, n):
    """Append pair key min * n + max of (p, q), p != q; return (keys, count)."""
    if p == q:
        return keys, n_keys
    if n_keys == keys.size:
        bigger = np.empty(2 * keys.size + 16, dtype=np.int64)
        bigger[:n_keys] = keys[:n_keys]
        keys = bigger
    keys[n_keys] = min(p, q) * n + max(p, q)
    return keys, n_keys + 1


@njit(cache=True, error_model='numpy')
def _requery(particles, clock, escapes, settings, pairs, incidence, n_pairs, n_links, n_changed):
    """Add candidate pairs for the changed particles an impact sent out of their swept ball.

    The broadphase covered each path inside the ball (``Escapes.centre``,
    ``half``). A changed particle whose rest of path leaves it escapes: it
    is paired with every particle whose ball meets the ball of its rest of
    path, and with every escaped particle whose rest-of-path ball meets it.
    New pairs, (lo, hi) in key order, are appended; returns (pairs,
    incidence, pair count, link count), grown when full.
    """
    x, v, radius = particles.position, particles.velocity, particles.radius
    n = x.shape[0]
    centre, half, escaped = escapes.centre, escapes.half, escapes.escaped
    middle, reach = escapes.middle, escapes.reach
    fresh = np.empty(n_changed, dtype=np.int64)
    n_fresh = 0
    for c in range(n_changed):
        p = clock.changed[c]
        if escaped[p]:
            continue
        limit = half[p] * (1.0 + 1e-12)
        rest = settings.dt - clock.local_time[p]
        if settings.has_gravity:
            mx, my, mz, own = _rest_ball(particles, p, rest, settings, escapes.sag)
            inside = _distance(mx - centre[p, 0], my - centre[p, 1], mz - centre[p, 2]) + own \
                <= limit
        else:
            # The rest of the path is a segment: inside the ball iff both ends are.
            ex = x[p, 0] + v[p, 0] * rest
            ey = x[p, 1] + v[p, 1] * rest
            ez = x[p, 2] + v[p, 2] * rest
            inside = _distance(x[p, 0] - centre[p, 0], x[p, 1] - centre[p, 1],
                               x[p, 2] - centre[p, 2]) <= limit and \
                _distance(ex - centre[p, 0], ey - centre[p, 1], ez - centre[p, 2]) <= limit
        if not inside:
            fresh[n_fresh] = p
            n_fresh += 1
    if n_fresh == 0:
        return pairs, incidence, n_pairs, n_links
    for q in range(n_fresh):
        p = fresh[q]
        mx, my, mz, own = _rest_ball(particles, p, settings.dt - clock.local_time[p], settings,
                                     escapes.sag)
        middle[p, 0], middle[p, 1], middle[p, 2] = mx, my, mz
        reach[p] = own + radius[p]
        escaped[p] = True
    keys = np.empty(64, dtype=np.int64)
    n_keys = np.int64(0)
    for q in range(n_fresh):
        p = fresh[q]
        mx, my, mz, own = middle[p, 0], middle[p, 1], middle[p, 2], reach[p]
        for other in range(n):
            if _distance(mx - centre[other, 0], my - centre[other, 1], mz - centre[other, 2]) \
                    <= own + (radius[other] + half[other]):
                keys, n_keys = _add_key(keys, n_keys, p, other, n)
            if escaped[other] and _distance(mx - middle[other, 0], my - middle[other, 1],
                                            mz - middle[other, 2]) <= own + reach[other]:
                keys, n_keys = _add_key(keys, n_keys, p, other, n)
    keys = np.sort(keys[:n_keys])
    for slot in range(n_keys):
        key = keys[slot]
        if slot > 0 and keys[slot - 1] == key:
            continue
        lo, hi = key // n, key % n
        if _is_known(pairs, incidence, lo, hi):
            continue
        if n_pairs == pairs.first.size:
            pairs = _grow_pairs(pairs, n_pairs)
        k = n_pairs
        pairs.first[k], pairs.second[k], pairs.resting[k] = lo, hi, False
        pairs.time[k], pairs.listed[k], pairs.seen[k] = np.inf, False, -1
        n_pairs += 1
        for p in (lo, hi):
            if n_links == incidence.link_next.size:
                incidence = _grow_links(incidence, n_links)
            incidence.link_pair[n_links] = k
            incidence.link_next[n_links] = incidence.extra_head[p]
            incidence.extra_head[p] = n_links
            n_links += 1
    return pairs, incidence, n_pairs, n_links


@njit(cache=True, error_model='numpy')
def _predict_added_pairs(p, round_, particles, pairs, clock, incidence, settings, has_resting,
                         n_pending):
    """Predict again the pairs requery added to particle p; return the pending count."""
    link = incidence.extra_head[p]
    while link >= 0:
        k = incidence.link_pair[link]
        link = incidence.link_next[link]
        if pairs.seen[k] == round_:
            continue
        pairs.seen[k] = round_
        n_pending = _predict_pair(k, particles, pairs, clock, settings, has_resting, n_pending)
    return n_pending


@njit(cache=True, error_model='numpy')
def _predict_changed(round_, particles, pairs, clock, incidence, box, settings, has_resting,
                     resting_wall, n_changed, n_pending, n_wall_due):
    """Predict again the pairs and walls of the round's changed particles; return both counts.

    Particle by particle in ``clock.changed`` order: its pairs not yet seen
    in this round (``_predict_pairs``' rules), requery's added pairs, then
    its wall row (``_predict_walls``). One call per round with the records
    unpacked once: a call per particle took a reference count on every
    array of five records, more than its predictions cost.
    """
    x, v, radius, dynamic = particles.position, particles.velocity, particles.radius, \
        particles.dynamic
    local_time, touched, changed = clock.local_time, clock.touched, clock.changed
    first_wall, wall_time = clock.first_wall, clock.wall_time
    wall_listed, wall_due = clock.wall_listed, clock.wall_due
    first_of, second_of, resting, seen = pairs.first, pairs.second, pairs.resting, pairs.seen
    pair_t, listed, pending = pairs.time, pairs.listed, pairs.pending
    start, keys = incidence.start, incidence.pairs
    gravity, min_speed, dt = settings.gravity, settings.min_speed, settings.dt
    has_gravity, dimensions = settings.has_gravity, settings.dimensions
    box_present, low, high = box.present, box.low, box.high
    for c in range(n_changed):
        p = changed[c]
        for slot in range(start[p], start[p + 1]):
            k = keys[slot]
            if seen[k] == round_:
                continue
            seen[k] = round_
            i, j = first_of[k], second_of[k]
            if has_resting and resting[k] and not (touched[i] or touched[j]):
                t = np.inf
            elif has_gravity:
                if _out_of_reach(x, v, radius, local_time, dynamic, i, j, gravity, dt):
                    t = np.inf
                else:
                    t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, True,
                                  min_speed, dt)
            elif min_speed > 0.0:
                t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False,
                              min_speed, dt)
            else:
                t = pair_time(x, v, radius, local_time, dynamic, i, j, gravity, False, 0.0, dt)
            n_pending = _list_if_due(k, t, dt, pair_t, listed, pending, n_pending)
        if incidence.extra_head[p] >= 0:
            n_pending = _predict_added_pairs(p, round_, particles, pairs, clock, incidence,
                                             settings, has_resting, n_pending)
        if not (box_present and dynamic[p]):
            continue
        if has_gravity and _walls_out_of_reach(x, v, radius, local_time, p, low, high,
                                               dimensions, gravity, dt):
            # Its row of wall_time is read only while it is due.
            first_wall[p] = np.inf
            continue
        wall_times(x, v, radius, local_time, p, low, high, dimensions, gravity, has_gravity,
                   min_speed, wall_time)
        first = np.inf
        for column in range(2 * dimensions):
            if has_resting and resting_wall[p, column] and not touched[p]:
                wall_time[p, column] = np.inf
            if wall_time[p, column] < first:
                first = wall_time[p, column]
        first_wall[p] = first
        if first <= dt and not wall_listed[p]:
            wall_listed[p] = True
            wall_due[n_wall_due] = p
            n_wall_due += 1
    return n_pending, n_wall_due


@njit(cache=True)
def _pairs_from_candidates_in(pairs, candidates, begin, end):
    """Copy candidates begin .. end - 1 into ``pairs``, not listed and not yet predicted.

    ``pairs.time`` needs no clearing: the first round writes every pair's time.
    """
    has_resting = candidates.has_resting
    for k in range(begin, end):
        pairs.first[k] = candidates.first[k]
        pairs.second[k] = candidates.second[k]
        pairs.resting[k] = candidates.resting_pair[k] if has_resting else False
        pairs.listed[k] = False
        pairs.seen[k] = -1


@njit(cache=True)
def _clear_particles_in(clock, extra_head, m, begin, end):
    """Clear the round marks of particles begin .. end - 1 (m: the 'no pair' index).

    ``wall_time`` and ``best_time`` need no clearing: the first round writes
    the wall rows of every due particle, and a particle's best_time is read
    only in the round that set it.
    """
    for p in range(begin, end):
        clock.touched[p] = False
        clock.struck[p] = False
        clock.is_changed[p] = False
        clock.wall_listed[p] = False
        clock.local_time[p] = 0.0
        clock.first_wall[p] = np.inf
        clock.best_pair[p] = m
        clock.best_round[p] = -1
        extra_head[p] = -1


@njit(cache=True)
def _incidence_serial(first, second, m, n, start, fill, incident):
    """List each particle's pairs (ascending) in ``incident[start[p]:start[p + 1]]``.

    ``_set_up_shared``'s counting sort with the m pairs in one slice,
    ``fill`` its counts and next slots.
    """
    counts = fill[:n]
    counts[:] = 0
    _count_pairs_in(first, second, counts, np.int64(0), m)
    _first_slots_in(counts.reshape((1, n)), start, np.int64(0), np.int64(0), n)
    start[n] = 2 * m
    _place_pairs_in(first, second, counts, incident, np.int64(0), m)


@njit(cache=True, parallel=True)
def _set_up_shared(pairs, clock, incidence, candidates, n, m, threads):
    """Do ``sweep``'s set-up on the threads: the serial path's arrays, bit for bit.

    Pairs and particles in blocks; the incidence as a counting sort over
    ``threads`` slices of the pairs, each counting and then placing its own
    pairs after the earlier slices' (so each particle's pairs stay in
    ascending order whatever the thread count).
    """
    pair_blocks = (m + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    for block in prange(pair_blocks):
        begin = block * PARALLEL_BLOCK_ITEMS
        _pairs_from_candidates_in(pairs, candidates, begin, min(begin + PARALLEL_BLOCK_ITEMS, m))
    particle_blocks = (n + PARALLEL_BLOCK_ITEMS - 1) // PARALLEL_BLOCK_ITEMS
    for block in prange(particle_blocks):
        begin = block * PARALLEL_BLOCK_ITEMS
        _clear_particles_in(clock, incidence.extra_head, m, begin,
                            min(begin + PARALLEL_BLOCK_ITEMS, n))
    first, second = pairs.first, pairs.second
    slice_size = (m + threads - 1) // threads
    slots = np.zeros((threads, n), dtype=np.int64)
    for part in prange(threads):
        _count_pairs_in(first, second, slots[part], part * slice_size,
                        min((part + 1) * slice_size, m))
    totals = np.zeros(particle_blocks + 1, dtype=np.int64)
    for block in prange(particle_blocks):
        begin = block * PARALLEL_BLOCK_ITEMS
        totals[block + 1] = _slot_total_in(slots, begin, min(begin + PARALLEL_BLOCK_ITEMS, n))
    for block in range(particle_blocks):
        totals[block + 1] += totals[block]
    start = incidence.start
    for block in prange(particle_blocks):
        begin = block * PARALLEL_BLOCK_ITEMS
        _first_slots_in(slots, start, totals[block], begin, min(begin + PARALLEL_BLOCK_ITEMS, n))
    start[n] = 2 * m
    incident = incidence.pairs
    for part in prange(threads):
        _place_pairs_in(first, second, slots[part], incident, part * slice_size,
                        min((part + 1) * slice_size, m))


@njit(cache=True)
def _count_pairs_in(first, second, counts, begin, end):
    """Add to ``counts`` each particle's pairs among begin .. end - 1."""
    for k in range(begin, end):
        counts[first[k]] += 1
        counts[second[k]] += 1


@njit(cache=True)
def _slot_total_in(slots, begin, end):
    """Return how many pairs the slices count at particles begin .. end - 1."""
    total = 0
    for part in range(slots.shape[0]):
        for p in range(begin, end):
            total += slots[part, p]
    return total


@njit(cache=True)
def _first_slots_in(slots, start, at, begin, end):
    """Turn the slices' counts of particles begin .. end - 1 into their first slots.

    ``at``: the first slot of particle ``begin``. Writes ``start[p]``.
    """
    for p in range(begin, end):
        start[p] = at
        for part in range(slots.shape[0]):
            count = slots[part, p]
            slots[part, p] = at
            at += count


@njit(cache=True)
def _place_pairs_in(first, second, slots, incident, begin, end):
    """Place pairs begin .. end - 1 at their particles' next slots (``slots``, advanced)."""
    for k in range(begin, end):
        incident[slots[first[k]]] = k
        slots[first[k]] += 1
        incident[slots[second[k]]] = k
        slots[second[k]] += 1


@njit(cache=True, nogil=True, error_model='numpy')
def sweep(particles, own, box, settings, candidates, escapes, tally, pairs, clock, incidence):
    """Run one step of the swept stage in place; see ``SweptContactStage`` for the rules.

    ``pairs``, ``clock`` and ``incidence``: the workspace (``workspace``),
    at least as large as the candidates and particles. Fills ``tally``
    (energy per particle and row, totals, counts) and returns the impact
    records when ``settings.record``, in the order the reference records them.
    """
    dynamic = particles.dynamic
    n = particles.position.shape[0]
    m = candidates.first.size
    dt = settings.dt
    has_gravity, min_speed = settings.has_gravity, settings.min_speed
    has_resting, resting_wall = candidates.has_resting, candidates.resting_wall
    local_time = clock.local_time
    best_pair, best_round, best_time = clock.best_pair, clock.best_round, clock.best_time
    # The candidates copied, every per-pair and per-particle mark cleared,
    # and the pairs of each particle listed: who to predict again when it changes.
    if settings.threads > 1 and max(n, m) >= PARALLEL_MIN_ITEMS:
        _set_up_shared(pairs, clock, incidence, candidates, n, m, settings.threads)
    else:
        _pairs_from_candidates_in(pairs, candidates, np.int64(0), m)
        _clear_particles_in(clock, incidence.extra_head, m, np.int64(0), n)
        _incidence_serial(pairs.first, pairs.second, m, n, incidence.start, incidence.fill,
                          incidence.pairs)
    # Counts start as np.int64(0), not the literal 0: a literal argument
    # makes numba compile each helper it is passed to a second time.
    n_pairs, n_links = m, np.int64(0)
    # Particles changed in the last round (the first round predicts every
    # pair and particle instead); pending pairs (time <= dt) and particles
    # with a pending wall impact.
    n_changed = n_pending = n_wall_due = np.int64(0)
    records = np.empty((16, RECORD_WIDTH))
    index = np.empty((16, 2), dtype=np.int64)
    count = np.int64(0)
    rounds_run = 0
    for round_ in range(settings.rounds):
        rounds_run += 1
        # Predict again the pairs and walls of the particles that changed
        # (in the first round every pair, in pair order, then every particle).
        if round_ == 0 and not has_gravity and not min_speed > 0.0 and not has_resting:
            n_pending = _predict_straight(particles, pairs, clock, m, settings)
        elif round_ == 0:
            n_pending = _predict_pairs(m, particles, pairs, clock, settings, has_resting)
        if round_ == 0 and box.present:
            n_wall_due = _predict_all_walls(particles, clock, box, settings, has_resting,
                                            resting_wall)
        if n_changed:
            n_pending, n_wall_due = _predict_changed(round_, particles, pairs, clock, incidence,
                                                     box, settings, has_resting, resting_wall,
                                                     n_changed, n_pending, n_wall_due)
        for c in range(n_changed):
            clock.is_changed[clock.changed[c]] = False
        n_changed = np.int64(0)
        # Drop what is no longer due.
        n_pending = _keep_due(pairs.pending, n_pending, pairs.time, dt, pairs.listed)
        n_wall_due = _keep_due(clock.wall_due, n_wall_due, clock.first_wall, dt,
                               clock.wall_listed)
        if n_pending == 0 and n_wall_due == 0:
            rounds_run -= 1
            break
        # Each particle's first pending pair by (time, pair order).
        for q in range(n_pending):
            k = pairs.pending[q]
            t = pairs.time[k]
            for p in (pairs.first[k], pairs.second[k]):
                if best_round[p] != round_ or t < best_time[p] or \
                        (t == best_time[p] and k < best_pair[p]):
                    best_round[p] = round_
                    best_time[p] = t
                    best_pair[p] = k
        # Sequential: the pairs first at both particles; batched: every pair at
        # both particles' earliest time. A static particle never has to wait
        # its turn (it never changes); a wall impact as early goes first.
        n_chosen = np.int64(0)
        for q in range(n_pending):
            k = pairs.pending[q]
            i, j = pairs.first[k], pairs.second[k]
            t = pairs.time[k]
            if settings.batched:
                first_at_i, first_at_j = t == best_time[i], t == best_time[j]
            else:
                first_at_i, first_at_j = best_pair[i] == k, best_pair[j] == k
            if (first_at_i or not dynamic[i]) and (first_at_j or not dynamic[j]) \
                    and t < clock.first_wall[i] and t < clock.first_wall[j]:
                pairs.chosen[n_chosen] = k
                n_chosen += 1
        n_hits = np.int64(0)
        for q in range(n_wall_due):
            p = clock.wall_due[q]
            earliest = best_time[p] if best_round[p] == round_ else np.inf
            if clock.first_wall[p] <= earliest:
                clock.hits[n_hits] = p
                n_hits += 1
        tally.counts[3] += n_chosen
        if settings.batched:
            n_changed, records, index, count = _resolve_batched(
                particles, own, settings, has_resting, pairs, clock, tally, n_chosen, n_changed,
                records, index, count)
        else:
            n_changed, records, index, count = _resolve_sequential(
                particles, own, settings, has_resting, pairs, clock, tally, n_chosen, n_changed,
                records, index, count)
        if n_hits:
            n_changed, records, index, count = _resolve_walls(
                particles, own, box, settings, candidates, clock, tally, n_hits, n_changed,
                records, index, count)
        if settings.requery and round_ + 1 < settings.rounds:
            pairs, incidence, n_pairs, n_links = _requery(particles, clock, escapes, settings,
                                                          pairs, incidence, n_pairs, n_links,
                                                          n_changed)
    _advance_all(particles, local_time, dt, settings, tally)
    tally.counts[2] += rounds_run
    return SweepResult(records[:count], index[:count])


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


def workspace(n: int, m: int, old: tuple | None = None
              ) -> tuple[PairState, ParticleRounds, Incidence]:
    """Return ``sweep``'s workspace for n particles and m pairs: ``old`` if large enough.

    New arrays get a quarter more room, so a step with a few more pairs
    does not allocate again.
    """
    if old is not None and old[0].first.size >= m and old[1].local_time.size >= n \
            and old[2].pairs.size >= 2 * m:
        return old
    m, n = m + m // 4 + 16, n + n // 4 + 1
    ints = lambda size: np.empty(size, dtype=np.int64)  # noqa: E731
    flags = lambda size: np.zeros(size, dtype=bool)  # noqa: E731
    pairs = PairState(ints(m), ints(m), flags(m), np.empty(m), flags(m), ints(m), ints(m),
                      ints(m))
    clock = ParticleRounds(np.empty(n), flags(n), flags(n), flags(n), ints(n), ints(n), flags(n),
                           ints(n), ints(n), np.empty(n), ints(n), np.empty(n),
                           np.empty((n, WALL_COLUMNS)), np.empty(n), np.empty((n, 3)))
    incidence = Incidence(ints(n + 1), ints(n), ints(2 * m), ints(n), ints(64), ints(64))
    return pairs, clock, incidence


def warm_up() -> None:
    """Run the swept step once on a tiny problem of each kind (compiles or loads)."""
    x = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    v = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    inv_mass, radius = np.array([1.0, 1.0, 0.0]), np.ones(3)
    first, second = np.array([0, 0], dtype=np.int64), np.array([1, 2], dtype=np.int64)
    low, high = np.full(3, -10.0), np.full(3, 10.0)
    own = OwnCoefficients(np.full(3, np.nan), True, np.full(3, np.nan), True)
    box = Box(True, low, high, 1.0)
    falling = np.array([0.0, -9.81, 0.0])
    for gravity, batched, drag in ((np.zeros(3), False, 0.0), (falling, False, 0.1),
                                   (np.zeros(3), True, 0.0)):
        particles = Particles(x.copy(), v.copy(), np.zeros((3, 3)), inv_mass, radius,
                              inv_mass > 0.0)
        settings = Settings(1.0, 3, 32, batched, True, 1.0, not batched, 0.5, gravity,
                            bool(gravity.any()), 0.1, 1.0, drag, 0.0, drag > 0.0, True, 2)
        candidates = Candidates(first, second, np.zeros(2, dtype=bool),
                                np.zeros((3, 6), dtype=bool), True)
        escapes = Escapes(x + v * 0.5, np.full(3, 0.5), 9.81, np.zeros(3, dtype=bool),
                          np.zeros((3, 3)), np.zeros(3))
        tally = Tally(np.zeros((LOSS_ROWS, 3)), np.zeros(LOSS_ROWS), np.zeros(4, dtype=np.int64))
        sweep(particles, own, box, settings, candidates, escapes, tally, *workspace(3, 2))
    in_contact(x, radius, first, second, 1e-6, True, low, high, 3, np.empty(2, dtype=bool),
               np.empty((3, 6), dtype=bool))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [sweep, in_contact]
