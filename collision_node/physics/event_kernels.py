"""The event loop of the ``exact`` preset, compiled: one call runs a whole step.

``stages/event_driven.py`` keeps the stage's rules (when to rebuild, roll
back and fall back, what to book); this module runs its events. The data
are plain arrays the stage owns between steps:

- **particles**: the stage's own copy of position and velocity, each
  particle at its own reference time (lazy advance), the time of its
  previous impact (TC model) and a change counter (``count``), raised
  whenever its path changes;
- **cells** one contact diameter wide or more, as a hash grid: cell
  (cx, cy, cz) lives in slot (cx mod Mx, cy mod My, cz mod Mz) of a table
  at least 3 slots wide per axis, each slot a doubly linked list of its
  particles (O(1) moves at a cell crossing). A neighbour query visits the
  slots around a particle and keeps only particles whose cell really is
  adjacent, so an open scene that outgrows the table stays correct;
- **events per particle** (Rapaport's and Lubachevsky's scheme): a
  particle's own next wall event and next cell crossing, and a short list
  of *candidates*, the pair impacts it predicted (time, partner, the
  partner's change counter then). Its next event is the earliest of them;
- **a heap of particles** (an indexed binary heap of N entries, keyed by
  each particle's next event, ties by index), updated in place when a
  particle's next event changes.

What each event costs:

- an **impact** changes two paths: both particles are predicted afresh
  against the particles of the 3^d cells around them (their candidate
  lists rebuilt, their counters raised, which makes every candidate that
  others hold with them stale);
- a **cell crossing** changes no path: the particle keeps its candidates
  and is predicted only against the newly entered layer of cells (3^(d-1)
  of them: the cells next to its new cell that were not next to its old
  one). Any pair that can meet is predicted by one of the two before it
  does: a pair in adjacent cells was predicted when the later of the two
  entered adjacency or changed path, and stays in that particle's list
  until one of them changes path (then that one predicts again);
- a **wall** event is an impact with the wall (or a visit without one):
  the particle is predicted afresh;
- a candidate whose partner changed since is dropped when it comes up
  (lazy invalidation) and the particle's next event is the next earliest.

A list holds ``CANDIDATES`` pair impacts; one more drops the latest and
schedules a *refresh* at its time (a fresh prediction of that particle,
path unchanged), so nothing is lost. Pair candidates later than either
particle's next wall event are not kept (that wall event re-predicts it).

Impact times are closed-form: the relative motion of two particles under
one uniform g is straight, so a pair meets at the smaller root of
|d + u s| = r_i + r_j (the quadratic of ``swept_contacts.pair_impact_times``,
same operations); a wall or cell face is reached at the entering root of a
quadratic in the gap (``paths.entering_time``, same operations). The
velocity update is the contact law's compiled per-contact form
(``contact_kernels.pair_impulse``, ``line_of_action``) with the combine rule
and the restitution threshold of ``contact_law``. Which particle predicts a
pair, and when, decides the last bits of an impact time (the pair's times
are evaluated from the prediction's moment); a different schedule gives
the same impacts to round-off, not to the bit.
"""

from __future__ import annotations

import math

import numpy as np

from . import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from .contact_kernels import _dot, line_of_action, pair_impulse  # noqa: I100
from numba import njit  # noqa: E402,I100

PAIR, WALL, CELL, REFRESH = 0, 1, 2, 3
# What a run returns: the step is done, or an event the TC model would have
# to alter under gravity (resting contact) or the event budget ended it.
# Or the impact records are full: the caller gives larger ones and calls again
# (the loop resumes where it stopped; the kernel allocates nothing).
DONE, NOT_EXACT, GROW = 0, 1, 2
# Columns of ``meta`` (int64): largest slot occupancy seen, impacts
# recorded, counters of the run (pair and wall impacts, events taken: impacts,
# wall visits and cell crossings; chores: stale candidates dropped and
# refreshes; whether the restitution and wall effects booked anything),
# crossings, fresh predictions, refreshes.
MAX_OCC, RECORDED, COLLISIONS, WALL_COLLISIONS, EVENTS, CHORES, BOOKED_PAIRS, \
    BOOKED_WALLS, CROSSINGS, PREDICTIONS, REFRESHES = range(11)
META_SIZE = 11
# Columns of ``clock`` (float64, one row per particle): reference time, time
# of the previous impact, next wall event, next cell crossing, refresh time,
# next event (the heap's key).
C_REF, C_LAST, C_WALL, C_CELL, C_REFRESH, C_KEY = range(6)
CLOCK_COLUMNS = 6
# Columns of ``book`` (int64, one row per particle): change counter, wall of
# the next wall event (2 axis + side), face of the next crossing, candidates
# held, which event is next (a candidate's slot, or one of the codes below).
B_COUNT, B_WALL, B_FACE, B_HELD, B_NEXT = range(5)
BOOK_COLUMNS = 5
NEXT_WALL, NEXT_CELL, NEXT_REFRESH, NEXT_NONE = -1, -2, -3, -4
# Pair candidates a particle holds (one more schedules a refresh).
CANDIDATES = 8
# Columns of the float rows of recorded impacts: time, contact point,
# normal (from j to i), normal impulse, closing speed.
R_TIME, R_POINT, R_NORMAL, R_IMPULSE, R_APPROACH = 0, 1, 4, 7, 8
RECORD_COLUMNS = 9
# Columns of ``params`` (float64).
P_COLLAPSE, P_THRESHOLD, P_PAIR_E, P_WALL_E, P_CELL, P_END = range(6)
PARAMS_SIZE = 6
# Columns of ``flags`` (int64); F_VARIED: particles have accelerations of
# their own (``accel``: resting contact, see ``resting_kernels``).
F_DIMS, F_GRAVITY, F_WALLS, F_OWN_E, F_RECORD, F_LOSSES, F_VARIED = range(7)
FLAGS_SIZE = 7
# Columns of ``rest`` (int64, one row per particle, read when F_VARIED):
# supported (1 or 0), the bit mask of the walls it rests on (bit = face),
# then its resting partners (stage indices; a wall as -2 - face; -1 ends).
S_SUPPORTED, S_WALLS, S_PARTNERS = 0, 1, 2

_INF = np.inf


# -- the heap of particles ----------------------------------------------------

@njit(cache=True, inline='always')
def _sift_down(heap_key, heap_int, size, k, p, t):
    """Place particle ``p`` of key ``t`` at heap slot ``k`` or below."""
    while True:
        c = 2 * k + 1
        if c >= size:
            break
        tc = heap_key[c]
        if c + 1 < size:
            ts = heap_key[c + 1]
            if ts < tc or (ts == tc and heap_int[0, c + 1] < heap_int[0, c]):
                c, tc = c + 1, ts
        if not (tc < t or (tc == t and heap_int[0, c] < p)):
            break
        r = heap_int[0, c]
        heap_key[k] = tc
        heap_int[0, k] = r
        heap_int[1, r] = k
        k = c
    heap_key[k] = t
    heap_int[0, k] = p
    heap_int[1, p] = k


@njit(cache=True, inline='always')
def heap_update(clock, heap_key, heap_int, p):
    """Move particle ``p`` to its place after its key (``clock[p, C_KEY]``) changed.

    The heap keeps the keys in its own order (``heap_key``, slot by slot) so
    that a sift reads neighbouring memory; ``heap_int`` rows: the particle
    at each slot, each particle's slot. Ties go to the lower index.
    """
    t = clock[p, C_KEY]
    k = heap_int[1, p]
    while k > 0:
        parent = (k - 1) >> 1
        tp = heap_key[parent]
        r = heap_int[0, parent]
        if not (t < tp or (t == tp and p < r)):
            break
        heap_key[k] = tp
        heap_int[0, k] = r
        heap_int[1, r] = k
        k = parent
    _sift_down(heap_key, heap_int, heap_key.size, k, p, t)


@njit(cache=True)
def heapify(clock, heap_key, heap_int):
    """Order every particle by its key (the heap of all particles)."""
    n = heap_key.size
    for p in range(n):
        heap_key[p] = clock[p, C_KEY]
        heap_int[0, p] = p
        heap_int[1, p] = p
    for k in range((n - 2) // 2, -1, -1):
        _sift_down(heap_key, heap_int, n, k, heap_int[0, k], heap_key[k])


@njit(cache=True, inline='always')
def _set_key(p, clock, book, cand_time):
    """Make particle p's key the earliest of its events and note which one it is.

    On a tie the wall comes first, then the cell crossing, the refresh and
    the candidates in list order.
    """
    best, which = clock[p, C_WALL], NEXT_WALL
    if clock[p, C_CELL] < best:
        best, which = clock[p, C_CELL], NEXT_CELL
    if clock[p, C_REFRESH] < best:
        best, which = clock[p, C_REFRESH], NEXT_REFRESH
    for k in range(book[p, B_HELD]):
        if cand_time[p, k] < best:
            best, which = cand_time[p, k], k
    if best == _INF:
        which = NEXT_NONE
    clock[p, C_KEY] = best
    book[p, B_NEXT] = which


@njit(cache=True, inline='always')
def _drop(p, k, book, cand_time, cand_int):
    """Remove candidate ``k`` of particle ``p`` (the last one takes its slot)."""
    last = book[p, B_HELD] - 1
    cand_time[p, k] = cand_time[p, last]
    cand_int[p, k, 0] = cand_int[p, last, 0]
    cand_int[p, k, 1] = cand_int[p, last, 1]
    book[p, B_HELD] = last


@njit(cache=True, inline='always')
def _hold(p, q, at, stamp, clock, book, cand_time, cand_int):
    """Add pair candidate (q at ``at``) to p's list; a full list drops its latest.

    The dropped time becomes a refresh of p (if earlier than the one
    scheduled), where p is predicted afresh: nothing is lost.
    """
    held = book[p, B_HELD]
    if held < CANDIDATES:
        cand_time[p, held] = at
        cand_int[p, held, 0] = q
        cand_int[p, held, 1] = stamp
        book[p, B_HELD] = held + 1
        return
    latest, slot = at, -1
    for k in range(held):
        if cand_time[p, k] > latest:
            latest, slot = cand_time[p, k], k
    if slot >= 0:
        cand_time[p, slot] = at
        cand_int[p, slot, 0] = q
        cand_int[p, slot, 1] = stamp
    if latest < clock[p, C_REFRESH]:
        clock[p, C_REFRESH] = latest


# -- paths --------------------------------------------------------------------

@njit(cache=True, inline='always')
def _advance(pos, vel, clock, gravity, half_g, accel, varied, p, when):
    """Bring particle ``p`` to time ``when`` on its parabola (``EventDrivenStage._advance``).

    The operations of the vectorised form: x + (v tau + ((g / 2) tau) tau), v + g tau,
    with p's own acceleration for g when particles have their own (``varied``).
    """
    tau = when - clock[p, C_REF]
    if varied:
        for c in range(3):
            pos[p, c] += vel[p, c] * tau + (0.5 * accel[p, c]) * tau * tau
        for c in range(3):
            vel[p, c] += accel[p, c] * tau
    else:
        for c in range(3):
            pos[p, c] += vel[p, c] * tau + half_g[c] * tau * tau
        for c in range(3):
            vel[p, c] += gravity[c] * tau
    clock[p, C_REF] = when


@njit(cache=True, error_model='numpy', inline='always')
def entering(gap, rate, curvature):
    """``paths.entering_time`` for one gap (the same operations and special cases)."""
    closing = rate < 0.0
    if curvature != 0.0:
        disc = rate * rate - 2.0 * curvature * gap
        root = math.sqrt(disc if not disc < 0.0 else 0.0)
        if disc >= 0.0:
            s = 2.0 * gap / (root - rate) if closing else (-rate - root) / curvature
        else:
            s = _INF
    else:
        s = gap / (-rate) if closing else _INF
    if not s > 0.0:
        s = _INF
    if gap <= 0.0 and (closing or (rate == 0.0 and curvature < 0.0)):
        s = 0.0
    return s


@njit(cache=True, error_model='numpy', inline='always')
def pair_time(pos, vel, radius, a, b):
    """Delay until pair (a, b), both at one time, touches: ``pair_impact_times`` for one pair.

    inf for none; 0 for an overlapping pair that approaches.
    """
    return pair_delay(pos[a, 0] - pos[b, 0], pos[a, 1] - pos[b, 1], pos[a, 2] - pos[b, 2],
                      vel[a, 0] - vel[b, 0], vel[a, 1] - vel[b, 1], vel[a, 2] - vel[b, 2],
                      radius[a] + radius[b])


@njit(cache=True, error_model='numpy', inline='always')
def pair_delay(dx, dy, dz, rx, ry, rz, reach):
    """``pair_time`` from the offset d, relative velocity r and contact distance (scalars).

    Scalars only: an array handed to a function, even an inlined one, costs
    two atomic reference-count updates, which the innermost loop cannot pay.
    """
    # Most neighbours recede, or approach and miss: say so before dividing,
    # in raw units (the sign of each test is the scaled one's but at round-off
    # in a grazing pair; a product that underflows to 0 or overflows to NaN
    # takes the long way).
    raw_b = _dot(dx, dy, dz, rx, ry, rz)
    raw_c = _dot(dx, dy, dz, dx, dy, dz) - reach * reach
    if raw_c > 0.0 and (raw_b > 0.0 or raw_b * raw_b - _dot(rx, ry, rz, rx, ry, rz) * raw_c < 0.0):
        return _INF
    ox, oy, oz = dx / reach, dy / reach, dz / reach
    ux, uy, uz = rx / reach, ry / reach, rz / reach
    half_b = _dot(ox, oy, oz, ux, uy, uz)
    c = _dot(ox, oy, oz, ox, oy, oz) - 1.0
    u2 = _dot(ux, uy, uz, ux, uy, uz)
    disc = half_b * half_b - u2 * c
    approaching = half_b < 0.0
    overlapping = c <= 0.0
    if overlapping and half_b == 0.0:
        # The dot product underflowed: decide with the scale-robust line of action.
        nx, ny, nz, _ = line_of_action(dx, dy, dz, rx, ry, rz)
        approaching = _dot(nx, ny, nz, rx, ry, rz) < 0.0
    if not (approaching and (overlapping or disc >= 0.0)):
        return _INF
    if overlapping:
        return 0.0
    return c / (-half_b + math.sqrt(disc if not disc < 0.0 else 0.0))


@njit(cache=True, error_model='numpy', inline='always')
def _curved_gap(ox, oy, oz, wx, wy, wz, hx, hy, hz, s):
    """Return F(s) = |o + w s + h s^2|^2 - 1 (a pair's scaled squared distance less 1)."""
    x = ox + (wx + hx * s) * s
    y = oy + (wy + hy * s) * s
    z = oz + (wz + hz * s) * s
    return _dot(x, y, z, x, y, z) - 1.0


@njit(cache=True, error_model='numpy', inline='always')
def _curved_slope(ox, oy, oz, wx, wy, wz, hx, hy, hz, s):
    """Return F'(s) / 2 = D(s) . D'(s), D(s) = o + w s + h s^2 (a cubic in s)."""
    x = ox + (wx + hx * s) * s
    y = oy + (wy + hy * s) * s
    z = oz + (wz + hz * s) * s
    return _dot(x, y, z, wx + 2.0 * hx * s, wy + 2.0 * hy * s, wz + 2.0 * hz * s)


@njit(cache=True, error_model='numpy', inline='always')
def _slope_root(ox, oy, oz, wx, wy, wz, hx, hy, hz, lo, hi):
    """Return the root of F' in [lo, hi], where F' is monotonic; inf if it keeps its sign."""
    g_lo = _curved_slope(ox, oy, oz, wx, wy, wz, hx, hy, hz, lo)
    g_hi = _curved_slope(ox, oy, oz, wx, wy, wz, hx, hy, hz, hi)
    if (g_lo < 0.0) == (g_hi < 0.0):
        return _INF
    falling = g_lo < 0.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if not (lo < mid < hi):
            break
        if (_curved_slope(ox, oy, oz, wx, wy, wz, hx, hy, hz, mid) < 0.0) == falling:
            lo = mid
        else:
            hi = mid
    return hi


@njit(cache=True, nogil=True, error_model='numpy')
def curved_delay(dx, dy, dz, ux, uy, uz, ax, ay, az, reach, horizon):
    """Delay until a pair whose accelerations differ touches, within ``horizon``; inf for none.

    Offset d, relative velocity u and relative acceleration a: the offset
    is d + u s + a s^2 / 2, so the squared distance less reach^2 is a
    quartic F(s). The roots of F''s derivative (a quadratic, closed form)
    split [0, horizon] where F' is monotonic, bisection finds F''s roots
    there, and they split it where F is: the first piece on which F falls
    to 0 holds the impact, found by bisection to round-off (the last time
    at which the pair is apart). 0 for a pair touching or overlapping as it
    starts to approach: at once, or later while still overlapping.
    """
    ox, oy, oz = dx / reach, dy / reach, dz / reach
    wx, wy, wz = ux / reach, uy / reach, uz / reach
    hx, hy, hz = 0.5 * ax / reach, 0.5 * ay / reach, 0.5 * az / reach
    # Far apart for the whole horizon: |D(s)| >= |o| - |w| s - |h| s^2 > 1.
    speed = math.sqrt(_dot(wx, wy, wz, wx, wy, wz))
    curve = math.sqrt(_dot(hx, hy, hz, hx, hy, hz))
    if math.sqrt(_dot(ox, oy, oz, ox, oy, oz)) - (speed + curve * horizon) * horizon > 1.0:
        return _INF
    # F'/2 = D . D' has derivative |D'|^2 + 2 h . D = A s^2 + B s + C.
    a_ = 6.0 * _dot(hx, hy, hz, hx, hy, hz)
    b_ = 6.0 * _dot(wx, wy, wz, hx, hy, hz)
    c_ = _dot(wx, wy, wz, wx, wy, wz) + 2.0 * _dot(hx, hy, hz, ox, oy, oz)
    # Break points of F': 0, the quadratic's roots inside, the horizon (no
    # arrays: the event loop runs without the runtime that would allocate them).
    cut1 = cut2 = horizon
    disc = b_ * b_ - 4.0 * a_ * c_
    if a_ > 0.0 and disc > 0.0:
        root = math.sqrt(disc)
        q = -0.5 * (b_ + (root if b_ >= 0.0 else -root))
        r1 = q / a_
        r2 = c_ / q if q != 0.0 else r1
        if r1 > r2:
            r1, r2 = r2, r1
        if 0.0 < r1 < horizon:
            cut1 = r1
        if 0.0 < r2 < horizon:
            if cut1 == horizon:
                cut1 = r2
            else:
                cut2 = r2
    # F's extrema (F' = 0), one at most between neighbouring break points.
    ext0 = ext1 = ext2 = horizon
    for k in range(3):
        lo = 0.0 if k == 0 else (cut1 if k == 1 else cut2)
        hi = cut1 if k == 0 else (cut2 if k == 1 else horizon)
        if not hi > lo:
            continue
        extremum = _slope_root(ox, oy, oz, wx, wy, wz, hx, hy, hz, lo, hi)
        if 0.0 < extremum < horizon:
            if ext0 == horizon:
                ext0 = extremum
            elif ext1 == horizon:
                ext1 = extremum
            else:
                ext2 = extremum
    # Walk the pieces on which F is monotonic, in order.
    start = 0.0
    for k in range(4):
        stop = ext0 if k == 0 else (ext1 if k == 1 else (ext2 if k == 2 else horizon))
        if not stop > start:
            continue
        mid = 0.5 * (start + stop)
        if _curved_slope(ox, oy, oz, wx, wy, wz, hx, hy, hz, mid) < 0.0:
            if _curved_gap(ox, oy, oz, wx, wy, wz, hx, hy, hz, start) <= 0.0:
                return start
            if _curved_gap(ox, oy, oz, wx, wy, wz, hx, hy, hz, stop) <= 0.0:
                lo, hi = start, stop
                for _ in range(200):
                    mid = 0.5 * (lo + hi)
                    if not (lo < mid < hi):
                        break
                    if _curved_gap(ox, oy, oz, wx, wy, wz, hx, hy, hz, mid) > 0.0:
                        lo = mid
                    else:
                        hi = mid
                return lo
        start = stop
    return _INF


@njit(cache=True, error_model='numpy', inline='always')
def _varied_delay(p, q, when, horizon, pos, vel, radius, accel, rest, clock):
    """Return when pair (p, q) meets, each with its own acceleration (``F_VARIED``).

    Brings q to ``when`` first; p is there already. A resting partner of p
    is never predicted (inf).
    """
    tau = when - clock[q, C_REF]
    if tau != 0.0:
        for c in range(3):
            pos[q, c] += vel[q, c] * tau + (0.5 * accel[q, c]) * tau * tau
        for c in range(3):
            vel[q, c] += accel[q, c] * tau
        clock[q, C_REF] = when
    if rest[p, S_SUPPORTED] or rest[q, S_SUPPORTED]:
        for s in range(S_PARTNERS, rest.shape[1]):
            partner = rest[p, s]
            if partner == q:
                return _INF
            if partner == -1:
                break
    ax, ay, az = accel[p, 0] - accel[q, 0], accel[p, 1] - accel[q, 1], accel[p, 2] - accel[q, 2]
    dx, dy, dz = pos[p, 0] - pos[q, 0], pos[p, 1] - pos[q, 1], pos[p, 2] - pos[q, 2]
    rx, ry, rz = vel[p, 0] - vel[q, 0], vel[p, 1] - vel[q, 1], vel[p, 2] - vel[q, 2]
    reach = radius[p] + radius[q]
    if ax == 0.0 and ay == 0.0 and az == 0.0:
        return when + pair_delay(dx, dy, dz, rx, ry, rz, reach)
    return when + curved_delay(dx, dy, dz, rx, ry, rz, ax, ay, az, reach, horizon)


# -- the cell grid ------------------------------------------------------------

@njit(cache=True, inline='always')
def _slot(p, cell, table):
    """Return the slot of particle p's cell (its slot coordinates are columns 3 to 5)."""
    return (cell[p, 3] * table[1] + cell[p, 4]) * table[2] + cell[p, 5]


@njit(cache=True, inline='always')
def _insert(p, cell, table, head, nxt, prv, occupancy, meta):
    """Put particle ``p`` at the head of its cell's slot list."""
    s = _slot(p, cell, table)
    first = head[s]
    nxt[p], prv[p] = first, -1
    if first >= 0:
        prv[first] = p
    head[s] = p
    occupancy[s] += 1
    if occupancy[s] > meta[MAX_OCC]:
        meta[MAX_OCC] = occupancy[s]


@njit(cache=True, inline='always')
def _remove(p, cell, table, head, nxt, prv, occupancy):
    """Take particle ``p`` out of its cell's slot list."""
    s = _slot(p, cell, table)
    if prv[p] >= 0:
        nxt[prv[p]] = nxt[p]
    else:
        head[s] = nxt[p]
    if nxt[p] >= 0:
        prv[nxt[p]] = prv[p]
    occupancy[s] -= 1


# -- prediction ---------------------------------------------------------------

@njit(cache=True, error_model='numpy', inline='always')
def _own_events(p, pos, vel, radius, gravity, accel, rest, low, high, params, flags, cell,
                clock, book, walls_too):
    """Delays until p (at its reference time) leaves its cell and reaches a wall.

    Sets p's next crossing (and, with ``walls_too``, its next wall event) as
    times; on a tie the lower face or wall of the lower axis is taken. With
    accelerations of their own (``F_VARIED``) p moves with its own, and the
    walls it rests on are not predicted (it neither closes nor opens on them).
    """
    varied = flags[F_VARIED] != 0
    resting_on = rest[p, S_WALLS] if varied else 0
    when = clock[p, C_REF]
    size = params[P_CELL]
    r = radius[p]
    best_wall, wall_col = _INF, -1
    best_cell, cell_col = _INF, 0
    for axis in range(flags[F_DIMS]):
        x, v = pos[p, axis], vel[p, axis]
        g = accel[p, axis] if varied else gravity[axis]
        low_face = cell[p, axis] * size
        t_low = entering(x - low_face, v, g)
        t_high = entering((low_face + size) - x, -v, -g)
        if t_low < best_cell:
            best_cell, cell_col = t_low, 2 * axis
        if t_high < best_cell:
            best_cell, cell_col = t_high, 2 * axis + 1
        if walls_too and flags[F_WALLS]:
            w_low = _INF if resting_on >> (2 * axis) & 1 else entering(x - (low[axis] + r), v, g)
            w_high = (_INF if resting_on >> (2 * axis + 1) & 1
                      else entering((high[axis] - r) - x, -v, -g))
            if w_low < best_wall:
                best_wall, wall_col = w_low, 2 * axis
            if w_high < best_wall:
                best_wall, wall_col = w_high, 2 * axis + 1
    clock[p, C_CELL] = when + best_cell
    book[p, B_FACE] = cell_col
    if walls_too:
        clock[p, C_WALL] = when + best_wall
        book[p, B_WALL] = wall_col


@njit(cache=True, error_model='numpy', inline='always')
def _scan(p, when, along, offset, skip_before, pos, vel, inv_mass, radius, gravity, half_g,
          accel, rest, params, flags, cell, table, head, nxt, clock, book, cand_time, cand_int):
    """Predict p against the particles of the cells around it; keep the impacts as candidates.

    ``along`` < 0: the 3^d cells around p's cell; otherwise the layer of
    3^(d-1) cells ``offset`` (+1 or -1) cells away along that axis. Dynamic
    particles below ``skip_before`` are left out (they predicted p already).
    A candidate later than either particle's next wall event is not kept.
    With accelerations of their own (``F_VARIED``): a pair whose two
    accelerations differ moves on a parabola relative to each other, so its
    time is ``curved_delay``'s (within the step, to ``params[P_END]``), and
    p's resting partners are not predicted.
    """
    varied = flags[F_VARIED] != 0
    horizon = params[P_END] - when
    dims = flags[F_DIMS]
    mx, my, mz = table[0], table[1], table[2]
    px, py, pz = cell[p, 0], cell[p, 1], cell[p, 2]
    sx0, sy0, sz0 = cell[p, 3], cell[p, 4], cell[p, 5]
    wall_p = clock[p, C_WALL]
    # p's state and g as scalars for the inner loop.
    px_, py_, pz_ = pos[p, 0], pos[p, 1], pos[p, 2]
    vx_, vy_, vz_ = vel[p, 0], vel[p, 1], vel[p, 2]
    r_p = radius[p]
    gx, gy, gz = gravity[0], gravity[1], gravity[2]
    hx, hy, hz = half_g[0], half_g[1], half_g[2]
    lo_x = hi_x = lo_y = hi_y = lo_z = hi_z = 0
    if dims > 0:
        lo_x, hi_x = -1, 1
    if dims > 1:
        lo_y, hi_y = -1, 1
    if dims > 2:
        lo_z, hi_z = -1, 1
    if along == 0:
        lo_x = hi_x = offset
    elif along == 1:
        lo_y = hi_y = offset
    elif along == 2:
        lo_z = hi_z = offset
    for dx in range(lo_x, hi_x + 1):
        sx = sx0 + dx
        sx = mx - 1 if sx < 0 else (0 if sx >= mx else sx)
        for dy in range(lo_y, hi_y + 1):
            sy = sy0 + dy
            sy = my - 1 if sy < 0 else (0 if sy >= my else sy)
            row = (sx * my + sy) * mz
            for dz in range(lo_z, hi_z + 1):
                sz = sz0 + dz
                sz = mz - 1 if sz < 0 else (0 if sz >= mz else sz)
                cx, cy, cz = px + dx, py + dy, pz + dz
                q = head[row + sz]
                while q >= 0:
                    if q != p and cell[q, 0] == cx and cell[q, 1] == cy and cell[q, 2] == cz \
                            and not (q < skip_before and inv_mass[q] > 0.0):
                        if varied:
                            at = _varied_delay(p, q, when, horizon, pos, vel, radius, accel,
                                               rest, clock)
                        else:
                            tau = when - clock[q, C_REF]
                            if tau != 0.0:
                                # _advance(q), written out: no arrays handed on.
                                pos[q, 0] += vel[q, 0] * tau + hx * tau * tau
                                pos[q, 1] += vel[q, 1] * tau + hy * tau * tau
                                pos[q, 2] += vel[q, 2] * tau + hz * tau * tau
                                vel[q, 0] += gx * tau
                                vel[q, 1] += gy * tau
                                vel[q, 2] += gz * tau
                                clock[q, C_REF] = when
                            at = when + pair_delay(
                                px_ - pos[q, 0], py_ - pos[q, 1], pz_ - pos[q, 2],
                                vx_ - vel[q, 0], vy_ - vel[q, 1], vz_ - vel[q, 2],
                                r_p + radius[q])
                        if at < wall_p and at < clock[q, C_WALL]:
                            _hold(p, q, at, book[q, B_COUNT], clock, book, cand_time, cand_int)
                    q = nxt[q]


@njit(cache=True, error_model='numpy')
def _predict(p, bump, skip_before, pos, vel, inv_mass, radius, gravity, half_g, accel, rest,
             low, high, params, flags, cell, table, head, nxt, clock, book, cand_time,
             cand_int, meta):
    """Predict particle p (at its reference time) afresh: walls, cell, 3^d cells around.

    ``bump``: p's path changed, so the candidates others hold with p go stale.
    Sets p's key; the caller moves it in the heap. (``build_events``'s; the
    event loop has the same steps inline.)
    """
    if bump:
        book[p, B_COUNT] += 1
    meta[PREDICTIONS] += 1
    book[p, B_HELD] = 0
    clock[p, C_REFRESH] = _INF
    _own_events(p, pos, vel, radius, gravity, accel, rest, low, high, params, flags, cell,
                clock, book, True)
    _scan(p, clock[p, C_REF], -1, 0, skip_before, pos, vel, inv_mass, radius, gravity, half_g,
          accel, rest, params, flags, cell, table, head, nxt, clock, book, cand_time, cand_int)
    _set_key(p, clock, book, cand_time)


@njit(cache=True, inline='always')
def _enter_cell(p, cell, table, head, nxt, prv, occupancy, book, cand_time, cand_int, meta):
    """Move p into the next cell; return the axis and side (+1, -1) of its new layer.

    Candidates whose partner changed path are dropped now (room for new ones).
    """
    face = book[p, B_FACE]
    axis, side = face // 2, face % 2
    _remove(p, cell, table, head, nxt, prv, occupancy)
    # The cell and its slot along the axis (wrapping round the table).
    wrap = table[axis]
    if side:
        cell[p, axis] += 1
        cell[p, 3 + axis] = 0 if cell[p, 3 + axis] == wrap - 1 else cell[p, 3 + axis] + 1
    else:
        cell[p, axis] -= 1
        cell[p, 3 + axis] = wrap - 1 if cell[p, 3 + axis] == 0 else cell[p, 3 + axis] - 1
    _insert(p, cell, table, head, nxt, prv, occupancy, meta)
    for k in range(book[p, B_HELD] - 1, -1, -1):
        q = cand_int[p, k, 0]
        if book[q, B_COUNT] != cand_int[p, k, 1]:
            _drop(p, k, book, cand_time, cand_int)
    return axis, 1 if side else -1


# -- events -------------------------------------------------------------------

@njit(cache=True, error_model='numpy', inline='always')
def _own_coefficient(own, p, default):
    """Return particle p's coefficient for the combine rule, and whether it has one."""
    value = own[p]
    if math.isnan(value):
        return default, False
    return value, True


@njit(cache=True, error_model='numpy', inline='always')
def pair_restitution(own, has_own, a, b, default):
    """``contact_law.pair_coefficient`` for one pair (geometric mean, default if neither)."""
    if not has_own:
        return default
    x, have_a = _own_coefficient(own, a, default)
    y, have_b = _own_coefficient(own, b, default)
    if not have_a and not have_b:
        return default
    return math.sqrt(x * y)


@njit(cache=True, error_model='numpy', inline='always')
def wall_restitution(own, has_own, p, default):
    """``contact_law.wall_coefficient`` for one particle at a wall of ``default``."""
    if not has_own:
        return default
    x, have = _own_coefficient(own, p, default)
    if not have:
        return default
    return math.sqrt(x * default)


@njit(cache=True, inline='always')
def _record(rec_f, rec_ij, meta, when, i, j, px, py, pz, nx, ny, nz, impulse, approach):
    """Append one impact row (room is reserved before each event)."""
    k = meta[RECORDED]
    rec_f[k, R_TIME] = when
    rec_f[k, R_POINT], rec_f[k, R_POINT + 1], rec_f[k, R_POINT + 2] = px, py, pz
    rec_f[k, R_NORMAL], rec_f[k, R_NORMAL + 1], rec_f[k, R_NORMAL + 2] = nx, ny, nz
    rec_f[k, R_IMPULSE], rec_f[k, R_APPROACH] = impulse, approach
    rec_ij[k, 0], rec_ij[k, 1] = i, j
    meta[RECORDED] = k + 1


@njit(cache=True, inline='always')
def _keeps_supports(rest, p, nx, ny, nz):
    """Say whether an impulse along N on particle p leaves its supports as they are.

    True for a particle that is not supported, and for one that rests on
    walls only, each at right angles to N (a ball rolling on a floor struck
    sideways); an impulse on a particle resting on others would change
    their normal speeds too.
    """
    if not rest[p, S_SUPPORTED]:
        return True
    walls = rest[p, S_WALLS]
    for s in range(S_PARTNERS, rest.shape[1]):
        partner = rest[p, s]
        if partner == -1:
            break
        if partner >= 0:
            return False
    if walls & 3 and nx != 0.0:
        return False
    if walls & 12 and ny != 0.0:
        return False
    if walls & 48 and nz != 0.0:
        return False
    return True


# Without the runtime's reference counting (``_nrt=False``): the kernel
# allocates nothing, and the counts numba keeps for every array handed to an
# inlined helper cost atomic updates in the innermost loops (13 % of the
# loop's time, measured with perf).
@njit(cache=True, nogil=True, error_model='numpy', _nrt=False)
def run_events(end, budget, pos, vel, inv_mass, radius, own_e, gravity, half_g, accel, rest,
               low, high, params, flags, cell, table, head, nxt, prv, occupancy, clock, book,
               cand_time, cand_int, heap_key, heap_int, meta, totals, losses, rec_f, rec_ij,
               perm, out_pos, out_vel):
    """Process every event up to ``end``, then publish every particle at ``end``.

    The stage's particles are the world's in another order (neighbours
    near in memory): stage particle k is the world's ``perm[k]``, which is
    the index that impacts, losses and the published state use.

    The rules of ``EventDrivenStage`` (see its module doc): returns the
    status. On ``NOT_EXACT`` (an event the TC model would have to alter
    under gravity, or more than ``budget`` events) the stage's arrays are
    left mid-step and ``out_pos``, ``out_vel`` (the world's state)
    untouched, for the caller to rebuild. On ``GROW`` the impact records
    are full: call again with larger ones (their rows so far copied).
    ``totals`` (restitution, walls) accumulate the energy booked, ``losses``
    the per-particle share, impacts go to the record arrays when
    ``flags[F_RECORD]``; ``half_g`` is g / 2. With ``F_VARIED`` each
    particle moves with its own acceleration (``accel``), and an impact that
    would change the normal speed at a support of a supported particle
    (``rest``; see ``_keeps_supports``) also ends the attempt (``NOT_EXACT``).
    """
    under_gravity = flags[F_GRAVITY] != 0
    varied = flags[F_VARIED] != 0
    collapse = params[P_COLLAPSE]
    threshold = params[P_THRESHOLD]
    has_own = flags[F_OWN_E] != 0
    record = flags[F_RECORD] != 0
    book_losses = flags[F_LOSSES] != 0
    while book.shape[0] > 0:
        p = heap_int[0, 0]
        when = heap_key[0]
        if not when <= end:
            break
        which = book[p, B_NEXT]
        if which >= 0:
            q = cand_int[p, which, 0]
            if book[q, B_COUNT] != cand_int[p, which, 1]:
                # Its partner changed path since: drop it, take p's next one.
                meta[CHORES] += 1
                if meta[CHORES] > 4 * budget:
                    return NOT_EXACT
                _drop(p, which, book, cand_time, cand_int)
                _set_key(p, clock, book, cand_time)
                heap_update(clock, heap_key, heap_int, p)
                continue
        # Who is predicted after this event, whether their paths changed, and
        # whether it is a crossing (then only the new layer of cells).
        if record and meta[RECORDED] >= rec_f.shape[0]:
            return GROW
        first, second, bump, crossing = p, -1, True, False
        if which == NEXT_REFRESH:
            meta[CHORES] += 1
            meta[REFRESHES] += 1
            if meta[CHORES] > 4 * budget:
                return NOT_EXACT
            _advance(pos, vel, clock, gravity, half_g, accel, varied, p, when)
            bump = False
        else:
            if meta[EVENTS] >= budget:
                return NOT_EXACT
            meta[EVENTS] += 1
        if which == NEXT_REFRESH:
            pass
        elif which >= 0:
            q = cand_int[p, which, 0]
            _advance(pos, vel, clock, gravity, half_g, accel, varied, p, when)
            _advance(pos, vel, clock, gravity, half_g, accel, varied, q, when)
            rx, ry, rz = vel[p, 0] - vel[q, 0], vel[p, 1] - vel[q, 1], vel[p, 2] - vel[q, 2]
            nx, ny, nz, _ = line_of_action(pos[p, 0] - pos[q, 0], pos[p, 1] - pos[q, 1],
                                           pos[p, 2] - pos[q, 2], rx, ry, rz)
            if varied and -_dot(rx, ry, rz, nx, ny, nz) > 0.0 and not (
                    _keeps_supports(rest, p, nx, ny, nz) and _keeps_supports(rest, q, nx, ny, nz)):
                return NOT_EXACT
            e = pair_restitution(own_e, has_own, p, q, params[P_PAIR_E])
            if threshold > 0.0 and -_dot(rx, ry, rz, nx, ny, nz) < threshold:
                e = 0.0
            if (when - clock[p, C_LAST] < collapse or when - clock[q, C_LAST] < collapse) \
                    and e < 1.0:
                if under_gravity:
                    return NOT_EXACT
                e = 1.0     # TC model: an impact this soon after another is elastic
            magnitude, approach, removed = pair_impulse(vel, inv_mass, p, q, nx, ny, nz, e,
                                                        0.0)
            if approach > 0.0:
                meta[COLLISIONS] += 1
                meta[BOOKED_PAIRS] = 1
                totals[0] += removed
                if book_losses:
                    share = inv_mass[p] / (inv_mass[p] + inv_mass[q])
                    losses[perm[p]] += removed * share
                    losses[perm[q]] += removed * (1.0 - share)
                if record:
                    # Written with i < j (the world's indices) and the normal
                    # from j to i (``record_pairs``).
                    i, j, sign = (p, q, 1.0) if perm[p] <= perm[q] else (q, p, -1.0)
                    mx, my, mz = sign * nx, sign * ny, sign * nz
                    _record(rec_f, rec_ij, meta, when, perm[i], perm[j],
                            0.5 * ((pos[i, 0] - radius[i] * mx) + (pos[j, 0] + radius[j] * mx)),
                            0.5 * ((pos[i, 1] - radius[i] * my) + (pos[j, 1] + radius[j] * my)),
                            0.5 * ((pos[i, 2] - radius[i] * mz) + (pos[j, 2] + radius[j] * mz)),
                            mx, my, mz, magnitude, approach)
            clock[p, C_LAST] = when
            clock[q, C_LAST] = when
            if inv_mass[q] > 0.0:      # a static particle's events stay valid
                second = q
        elif which == NEXT_WALL:
            _advance(pos, vel, clock, gravity, half_g, accel, varied, p, when)
            face = book[p, B_WALL]
            axis, side = face // 2, face % 2
            toward = 1.0 if side else -1.0      # direction of the wall along the axis
            speed_in = toward * vel[p, axis]
            pushed_in = toward * (accel[p, axis] if varied else gravity[axis])
            if speed_in > 0.0 or (speed_in == 0.0 and pushed_in > 0.0):
                if varied and not _keeps_supports(rest, p, 1.0 if axis == 0 else 0.0,
                                                  1.0 if axis == 1 else 0.0,
                                                  1.0 if axis == 2 else 0.0):
                    return NOT_EXACT
                e = wall_restitution(own_e, has_own, p, params[P_WALL_E])
                if threshold > 0.0 and speed_in < threshold:
                    e = 0.0
                if when - clock[p, C_LAST] < collapse:
                    resting = pushed_in > 0.0 and speed_in < 0.5 * pushed_in * collapse
                    if under_gravity and (e < 1.0 or resting):
                        return NOT_EXACT
                    e = 1.0
                plane = high[axis] if side else low[axis]
                inward = -toward
                # ``contact_law.apply_wall_impulses`` with no tolerance.
                approach = -inward * vel[p, axis]
                change = (1.0 + e) * approach
                vel[p, axis] += inward * change
                magnitude = change / inv_mass[p]
                removed = 0.5 * magnitude * approach * (1.0 - e)
                meta[BOOKED_WALLS] = 1
                totals[1] += removed
                if book_losses:
                    losses[perm[p]] += removed
                pos[p, axis] = plane - toward * radius[p]   # exact contact, no drift
                meta[WALL_COLLISIONS] += 1
                if record:
                    _record(rec_f, rec_ij, meta, when, perm[p], -1,
                            plane if axis == 0 else pos[p, 0],
                            plane if axis == 1 else pos[p, 1],
                            plane if axis == 2 else pos[p, 2],
                            inward if axis == 0 else 0.0, inward if axis == 1 else 0.0,
                            inward if axis == 2 else 0.0, magnitude, approach)
                clock[p, C_LAST] = when
        elif which == NEXT_CELL:
            meta[CROSSINGS] += 1
            _advance(pos, vel, clock, gravity, half_g, accel, varied, p, when)
            crossing = True
        # One site for all predictions: the helpers are inlined here, and
        # arrays passed to a function that is called cost reference counting.
        for k in range(2):
            r = first if k == 0 else second
            if r < 0:
                continue
            along, offset = -1, 0
            if crossing:
                along, offset = _enter_cell(r, cell, table, head, nxt, prv, occupancy, book,
                                            cand_time, cand_int, meta)
            else:
                if bump:
                    book[r, B_COUNT] += 1
                meta[PREDICTIONS] += 1
                book[r, B_HELD] = 0
                clock[r, C_REFRESH] = _INF
            _own_events(r, pos, vel, radius, gravity, accel, rest, low, high, params, flags, cell,
                        clock, book, not crossing)
            _scan(r, when, along, offset, 0, pos, vel, inv_mass, radius, gravity, half_g, accel,
                  rest, params, flags, cell, table, head, nxt, clock, book, cand_time, cand_int)
            _set_key(r, clock, book, cand_time)
            heap_update(clock, heap_key, heap_int, r)
    for p in range(pos.shape[0]):
        _advance(pos, vel, clock, gravity, half_g, accel, varied, p, end)
        k = perm[p]
        for c in range(3):
            out_pos[k, c] = pos[p, c]
            out_vel[k, c] = vel[p, c]
    return DONE


@njit(cache=True, nogil=True, error_model='numpy')
def build_events(when, pos, vel, inv_mass, radius, gravity, accel, rest, low, high, params,
                 flags, cell, table, head, nxt, prv, occupancy, clock, book, cand_time,
                 cand_int, heap_key, heap_int, meta):
    """Fill the grid, predict every dynamic particle (each pair once) and order the heap.

    ``clock`` comes with every reference time at ``when``, no impact yet, no
    events (inf); ``book`` with zero counters.
    """
    half_g = 0.5 * gravity
    n = pos.shape[0]
    for p in range(n):
        _insert(p, cell, table, head, nxt, prv, occupancy, meta)
    for p in range(n):
        if inv_mass[p] > 0.0:
            _predict(p, False, p, pos, vel, inv_mass, radius, gravity, half_g, accel, rest,
                     low, high, params, flags, cell, table, head, nxt, clock, book, cand_time,
                     cand_int, meta)
        else:
            book[p, B_NEXT] = NEXT_NONE
    heapify(clock, heap_key, heap_int)


@njit(cache=True, nogil=True)
def matches(state_pos, state_vel, state_inv_mass, state_radius, pos, vel, inv_mass, radius,
            perm):
    """Say whether the world's particles are still the ones the last step published."""
    for p in range(pos.shape[0]):
        k = perm[p]
        if state_inv_mass[k] != inv_mass[p] or state_radius[k] != radius[p]:
            return False
        for c in range(3):
            if state_pos[k, c] != pos[p, c] or state_vel[k, c] != vel[p, c]:
                return False
    return True


def new_arrays(n: int) -> tuple:
    """Return (clock, book, cand_time, cand_int, heap_key, heap_int) for ``n`` particles.

    Nothing predicted yet, no impact yet.
    """
    clock = np.full((n, CLOCK_COLUMNS), np.inf)
    clock[:, C_LAST] = -np.inf
    book = np.zeros((n, BOOK_COLUMNS), dtype=np.int64)
    return (clock, book, np.empty((n, CANDIDATES)),
            np.empty((n, CANDIDATES, 2), dtype=np.int64), np.empty(n),
            np.empty((2, n), dtype=np.int64))


def warm_up() -> None:
    """Run the kernels once on two particles meeting head on between walls."""
    pos = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    vel = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    inv_mass, radius = np.ones(2), np.full(2, 0.25)
    gravity, low, high = np.zeros(3), np.full(3, -1.0), np.full(3, 1.0)
    params = np.array([1e-5, 0.0, 1.0, 1.0, 0.5, 1.0])
    flags = np.array([3, 0, 1, 1, 1, 1, 0], dtype=np.int64)
    accel, rest = new_supports(2, 1)
    table = np.full(3, 7, dtype=np.int64)
    cell = np.zeros((2, 6), dtype=np.int64)
    cell[:, :3] = np.floor(pos / 0.5)
    cell[:, 3:] = cell[:, :3] % table
    head, occupancy = np.full(343, -1, dtype=np.int64), np.zeros(343, dtype=np.int64)
    nxt, prv = np.full(2, -1, dtype=np.int64), np.full(2, -1, dtype=np.int64)
    clock, book, cand_time, cand_int, heap_key, heap_int = new_arrays(2)
    clock[:, C_REF] = 0.0
    meta = np.zeros(META_SIZE, dtype=np.int64)
    build_events(0.0, pos, vel, inv_mass, radius, gravity, accel, rest, low, high, params,
                 flags, cell, table, head, nxt, prv, occupancy, clock, book, cand_time, cand_int,
                 heap_key, heap_int, meta)
    out_pos, out_vel = pos.copy(), vel.copy()
    perm = np.arange(2)
    run_events(1.0, 1000, pos, vel, inv_mass, radius, np.full(2, np.nan), gravity, gravity,
               accel, rest, low, high, params, flags, cell, table, head, nxt, prv, occupancy,
               clock, book, cand_time, cand_int, heap_key, heap_int, meta, np.zeros(2),
               np.zeros(2),
               np.empty((4, RECORD_COLUMNS)), np.empty((4, 2), dtype=np.int64), perm, out_pos,
               out_vel)
    matches(out_pos, out_vel, inv_mass, radius, pos, vel, inv_mass, radius, perm)
    curved_delay(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.5, 1.0)


def new_supports(n: int, partners: int) -> tuple:
    """Return (accel, rest) for ``n`` particles with room for ``partners`` resting partners.

    No particle supported, no partner: read only under ``F_VARIED``.
    """
    rest = np.zeros((n, S_PARTNERS + partners), dtype=np.int64)
    rest[:, S_PARTNERS:] = -1
    return np.zeros((n, 3)), rest


def kernels() -> list:
    """Return the compiled kernels of this module (the ones a warm-up compiles)."""
    return [build_events, run_events, matches, curved_delay]
