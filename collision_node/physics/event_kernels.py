"""The event loop of the ``exact`` preset, compiled: one call runs a whole step.

``stages/event_driven.py`` keeps the stage's rules (when to rebuild, roll
back and fall back, what to book); this module runs its events. The data
are plain arrays the stage owns between steps:

- **particles** at their own reference time (lazy advance): position and
  velocity of the world's state, ``ref_time``, the time of each particle's
  previous impact (TC model) and a change counter per particle;
- **cells** one contact diameter wide or more, as a hash grid: cell
  (cx, cy, cz) lives in slot (cx mod Mx, cy mod My, cz mod Mz) of a table
  at least 3 slots wide per axis, each slot a doubly linked list of its
  particles (O(1) moves at a cell crossing). A neighbour query visits the
  3^d slots around a particle and keeps only particles whose cell really is
  adjacent, so an open scene that outgrows the table stays correct;
- **events** in an array binary heap ordered by (time, sequence number):
  the push order breaks ties, as a Python heap of (time, seq, ...) tuples
  does. Each event carries the change counters of its particles when it was
  predicted; a popped event whose particle changed since is skipped (lazy
  invalidation). Stale entries are dropped when the heap grows (the order of
  the live ones is a total order, so compacting changes nothing).

Impact times are closed-form: the relative motion of two particles under
one uniform g is straight, so a pair meets at the smaller root of
|d + u s| = r_i + r_j (the quadratic of ``swept_contacts.pair_impact_times``,
same operations); a wall or cell face is reached at the entering root of a
quadratic in the gap (``paths.entering_time``, same operations). The
velocity update is the contact law's compiled per-contact form
(``contact_kernels.pair_impulse``, ``line_of_action``) with the combine rule
and the restitution threshold of ``contact_law``, so impacts are
bit-identical to the vectorised law's.
"""

from __future__ import annotations

import math

import numpy as np

from . import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from .contact_kernels import _dot, line_of_action, pair_impulse  # noqa: I100
from numba import njit  # noqa: E402,I100

PAIR, WALL, CELL = 0, 1, 2
# What a run returns: the step is done, or an event the TC model would have
# to alter under gravity (resting contact) or the event budget ended it.
DONE, NOT_EXACT = 0, 1
# Columns of ``meta`` (int64): heap size, next sequence number, largest slot
# occupancy seen (bounds the events one prediction pushes), impacts recorded,
# counters of the run (pair and wall impacts, events taken, whether the
# restitution and wall effects booked anything) and the heap size at which
# stale entries are dropped.
SIZE, SEQ, MAX_OCC, RECORDED, COLLISIONS, WALL_COLLISIONS, EVENTS, BOOKED_PAIRS, \
    BOOKED_WALLS, COMPACT_AT = range(10)
META_SIZE = 10
# Columns of the heap's integer rows.
H_SEQ, H_KIND, H_P, H_Q, H_SP, H_SQ = range(6)
# Columns of the float rows of recorded impacts: time, contact point,
# normal (from j to i), normal impulse, closing speed.
R_TIME, R_POINT, R_NORMAL, R_IMPULSE, R_APPROACH = 0, 1, 4, 7, 8
RECORD_COLUMNS = 9
# Columns of ``params`` (float64).
P_COLLAPSE, P_THRESHOLD, P_PAIR_E, P_WALL_E, P_CELL = range(5)
# Columns of ``flags`` (int64).
F_DIMS, F_GRAVITY, F_WALLS, F_OWN_E, F_RECORD, F_LOSSES = range(6)

_INF = np.inf


@njit(cache=True, inline='always')
def _entry_before(h_time, h_int, k, t, seq):
    """Say whether heap entry ``k`` comes before key (t, seq); reads its seq only on a tie."""
    tk = h_time[k]
    return tk < t or (tk == t and h_int[k, H_SEQ] < seq)


@njit(cache=True, inline='always')
def _entries_before(h_time, h_int, a, b):
    """Say whether heap entry ``a`` comes before entry ``b``."""
    ta, tb = h_time[a], h_time[b]
    return ta < tb or (ta == tb and h_int[a, H_SEQ] < h_int[b, H_SEQ])


@njit(cache=True)
def heap_push(h_time, h_int, meta, when, kind, p, q, sp, sq):
    """Push one event (capacity is the caller's: ``_reserve``)."""
    k = meta[SIZE]
    seq = meta[SEQ]
    meta[SEQ] = seq + 1
    while k > 0:
        parent = (k - 1) >> 1
        tp = h_time[parent]
        if not (when < tp or (when == tp and seq < h_int[parent, H_SEQ])):
            break
        h_time[k] = h_time[parent]
        for c in range(6):
            h_int[k, c] = h_int[parent, c]
        k = parent
    h_time[k] = when
    h_int[k, H_SEQ], h_int[k, H_KIND], h_int[k, H_P] = seq, kind, p
    h_int[k, H_Q], h_int[k, H_SP], h_int[k, H_SQ] = q, sp, sq
    meta[SIZE] += 1


@njit(cache=True)
def _sift_down(h_time, h_int, size, k, t, row):
    """Place entry (t, row) at hole ``k`` of a heap of ``size``, moving it down."""
    seq = row[H_SEQ]
    while True:
        c = 2 * k + 1
        if c >= size:
            break
        if c + 1 < size and _entries_before(h_time, h_int, c + 1, c):
            c += 1
        if not _entry_before(h_time, h_int, c, t, seq):
            break
        h_time[k] = h_time[c]
        for j in range(6):
            h_int[k, j] = h_int[c, j]
        k = c
    h_time[k] = t
    for j in range(6):
        h_int[k, j] = row[j]


@njit(cache=True)
def heap_pop(h_time, h_int, meta, out, scratch):
    """Pop the earliest event into ``out`` (6 ints); return its time (``scratch``: 6 ints)."""
    when = h_time[0]
    for j in range(6):
        out[j] = h_int[0, j]
    size = meta[SIZE] - 1
    meta[SIZE] = size
    if size > 0:
        for j in range(6):
            scratch[j] = h_int[size, j]
        _sift_down(h_time, h_int, size, 0, h_time[size], scratch)
    return when


@njit(cache=True)
def _stale(h_int, k, count):
    """Say whether heap entry ``k`` was predicted before one of its particles changed."""
    p, q = h_int[k, H_P], h_int[k, H_Q]
    return count[p] != h_int[k, H_SP] or (h_int[k, H_KIND] == PAIR
                                          and count[q] != h_int[k, H_SQ])


@njit(cache=True)
def _compact(h_time, h_int, meta, count):
    """Drop stale entries and rebuild the heap (the live entries keep their order)."""
    kept = 0
    for k in range(meta[SIZE]):
        if _stale(h_int, k, count):
            continue
        h_time[kept] = h_time[k]
        for j in range(6):
            h_int[kept, j] = h_int[k, j]
        kept += 1
    meta[SIZE] = kept
    row = np.empty(6, dtype=np.int64)
    for k in range((kept - 2) // 2, -1, -1):
        for j in range(6):
            row[j] = h_int[k, j]
        _sift_down(h_time, h_int, kept, k, h_time[k], row)


@njit(cache=True)
def _reserve(h_time, h_int, meta, count, room):
    """Return heap arrays with room for ``room`` more entries (compacted or grown)."""
    if meta[SIZE] + room <= h_time.size and meta[SIZE] < meta[COMPACT_AT]:
        return h_time, h_int
    _compact(h_time, h_int, meta, count)
    # Compact again only once the live entries have doubled: no thrashing.
    meta[COMPACT_AT] = max(meta[COMPACT_AT], 2 * meta[SIZE])
    if meta[SIZE] + room <= h_time.size:
        return h_time, h_int
    capacity = max(2 * h_time.size, meta[SIZE] + room)
    grown_time = np.empty(capacity)
    grown_int = np.empty((capacity, 6), dtype=np.int64)
    grown_time[:meta[SIZE]] = h_time[:meta[SIZE]]
    grown_int[:meta[SIZE]] = h_int[:meta[SIZE]]
    return grown_time, grown_int


# -- paths --------------------------------------------------------------------

@njit(cache=True, inline='always')
def _advance(pos, vel, ref_time, gravity, half_g, p, when):
    """Bring particle ``p`` to time ``when`` on its parabola (``EventDrivenStage._advance``).

    The operations of the vectorised form: x + (v tau + ((g / 2) tau) tau), v + g tau.
    """
    tau = when - ref_time[p]
    for c in range(3):
        pos[p, c] += vel[p, c] * tau + half_g[c] * tau * tau
    for c in range(3):
        vel[p, c] += gravity[c] * tau
    ref_time[p] = when


@njit(cache=True, error_model='numpy')
def entering(gap, rate, curvature):
    """``paths.entering_time`` for one gap (the same operations and special cases)."""
    disc = rate * rate - 2.0 * curvature * gap
    root = math.sqrt(disc if not disc < 0.0 else 0.0)
    closing = rate < 0.0
    if curvature != 0.0:
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


@njit(cache=True, error_model='numpy')
def pair_time(pos, vel, radius, a, b):
    """Delay until pair (a, b), both at one time, touches: ``pair_impact_times`` for one pair.

    inf for none; 0 for an overlapping pair that approaches.
    """
    reach = radius[a] + radius[b]
    dx, dy, dz = pos[a, 0] - pos[b, 0], pos[a, 1] - pos[b, 1], pos[a, 2] - pos[b, 2]
    rx, ry, rz = vel[a, 0] - vel[b, 0], vel[a, 1] - vel[b, 1], vel[a, 2] - vel[b, 2]
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


# -- the cell grid ------------------------------------------------------------

@njit(cache=True, inline='always')
def _slot(cx, cy, cz, table):
    """Return the slot of cell (cx, cy, cz) in a table of table[0] x table[1] x table[2]."""
    return ((cx % table[0]) * table[1] + (cy % table[1])) * table[2] + (cz % table[2])


@njit(cache=True)
def _insert(p, cell, table, head, nxt, prv, occupancy, meta):
    """Put particle ``p`` at the head of its cell's slot list."""
    s = _slot(cell[p, 0], cell[p, 1], cell[p, 2], table)
    first = head[s]
    nxt[p], prv[p] = first, -1
    if first >= 0:
        prv[first] = p
    head[s] = p
    occupancy[s] += 1
    if occupancy[s] > meta[MAX_OCC]:
        meta[MAX_OCC] = occupancy[s]


@njit(cache=True)
def _remove(p, cell, table, head, nxt, prv, occupancy):
    """Take particle ``p`` out of its cell's slot list."""
    s = _slot(cell[p, 0], cell[p, 1], cell[p, 2], table)
    if prv[p] >= 0:
        nxt[prv[p]] = nxt[p]
    else:
        head[s] = nxt[p]
    if nxt[p] >= 0:
        prv[nxt[p]] = prv[p]
    occupancy[s] -= 1


# -- prediction ---------------------------------------------------------------

@njit(cache=True, error_model='numpy')
def _predict(p, when, pos, vel, radius, ref_time, count, own_next, gravity, half_g, low, high,
             params, flags, cell, table, head, nxt, h_time, h_int, meta):
    """Invalidate particle p's events and push its new ones (p is at ``when``).

    As ``EventDrivenStage._predict``: its wall event, its cell crossing, then
    a pair event per neighbour in the 3^d cells around it that it will meet
    (each neighbour brought to ``when`` first).
    """
    count[p] += 1
    stamp = count[p]
    dims = flags[F_DIMS]
    size = params[P_CELL]
    r = radius[p]
    best_wall, wall_col = _INF, -1
    best_cell, cell_col = _INF, 0
    for axis in range(dims):
        x, v, g = pos[p, axis], vel[p, axis], gravity[axis]
        low_face = cell[p, axis] * size
        t_low = entering(x - low_face, v, g)
        t_high = entering((low_face + size) - x, -v, -g)
        if t_low < best_cell:
            best_cell, cell_col = t_low, 2 * axis
        if t_high < best_cell:
            best_cell, cell_col = t_high, 2 * axis + 1
        if flags[F_WALLS]:
            w_low = entering(x - (low[axis] + r), v, g)
            w_high = entering((high[axis] - r) - x, -v, -g)
            if w_low < best_wall:
                best_wall, wall_col = w_low, 2 * axis
            if w_high < best_wall:
                best_wall, wall_col = w_high, 2 * axis + 1
    # p's own next event (a wall, or the face of its cell) re-predicts p, so
    # any event of p keyed after it will be found stale when popped: only the
    # earlier of the two is pushed (the wall on a tie: it was pushed first),
    # and only pair events before it, and before the partner's own event.
    # Not pushing them changes nothing but the heap's size.
    # (Compared as the times pushed: when + delay may round two delays together.)
    wall_at, cell_at = when + best_wall, when + best_cell
    own = _INF
    if wall_col >= 0 and wall_at <= cell_at:
        own = wall_at
        heap_push(h_time, h_int, meta, own, WALL, p, wall_col, stamp, 0)
    elif best_cell < _INF:
        own = cell_at
        heap_push(h_time, h_int, meta, own, CELL, p, cell_col, stamp, 0)
    own_next[p] = own
    # The 3^d cells around p in itertools.product order (first axis slowest),
    # their slots found by wrapping p's slot coordinates (one modulo per axis).
    span_x = 3 if dims > 0 else 1
    span_y = 3 if dims > 1 else 1
    span_z = 3 if dims > 2 else 1
    mx, my, mz = table[0], table[1], table[2]
    px, py, pz = cell[p, 0], cell[p, 1], cell[p, 2]
    sx0, sy0, sz0 = px % mx, py % my, pz % mz
    for a in range(span_x):
        dx = a - 1 if span_x == 3 else 0
        sx = sx0 + dx
        sx = mx - 1 if sx < 0 else (0 if sx >= mx else sx)
        for b in range(span_y):
            dy = b - 1 if span_y == 3 else 0
            sy = sy0 + dy
            sy = my - 1 if sy < 0 else (0 if sy >= my else sy)
            row = (sx * my + sy) * mz
            for c in range(span_z):
                dz = c - 1 if span_z == 3 else 0
                sz = sz0 + dz
                sz = mz - 1 if sz < 0 else (0 if sz >= mz else sz)
                cx, cy, cz = px + dx, py + dy, pz + dz
                q = head[row + sz]
                while q >= 0:
                    if q != p and cell[q, 0] == cx and cell[q, 1] == cy and cell[q, 2] == cz:
                        _advance(pos, vel, ref_time, gravity, half_g, q, when)
                        at = when + pair_time(pos, vel, radius, p, q)
                        if at < own and at < own_next[q]:
                            heap_push(h_time, h_int, meta, at, PAIR, p, q, stamp, count[q])
                    q = nxt[q]


# -- events -------------------------------------------------------------------

@njit(cache=True, error_model='numpy')
def _own_coefficient(own, p, default):
    """Return particle p's coefficient for the combine rule, and whether it has one."""
    value = own[p]
    if math.isnan(value):
        return default, False
    return value, True


@njit(cache=True, error_model='numpy')
def pair_restitution(own, has_own, a, b, default):
    """``contact_law.pair_coefficient`` for one pair (geometric mean, default if neither)."""
    if not has_own:
        return default
    x, have_a = _own_coefficient(own, a, default)
    y, have_b = _own_coefficient(own, b, default)
    if not have_a and not have_b:
        return default
    return math.sqrt(x * y)


@njit(cache=True, error_model='numpy')
def wall_restitution(own, has_own, p, default):
    """``contact_law.wall_coefficient`` for one particle at a wall of ``default``."""
    if not has_own:
        return default
    x, have = _own_coefficient(own, p, default)
    if not have:
        return default
    return math.sqrt(x * default)


@njit(cache=True)
def _record(rec_f, rec_ij, meta, when, i, j, px, py, pz, nx, ny, nz, impulse, approach):
    """Append one impact row (room is reserved before each event)."""
    k = meta[RECORDED]
    rec_f[k, R_TIME] = when
    rec_f[k, R_POINT], rec_f[k, R_POINT + 1], rec_f[k, R_POINT + 2] = px, py, pz
    rec_f[k, R_NORMAL], rec_f[k, R_NORMAL + 1], rec_f[k, R_NORMAL + 2] = nx, ny, nz
    rec_f[k, R_IMPULSE], rec_f[k, R_APPROACH] = impulse, approach
    rec_ij[k, 0], rec_ij[k, 1] = i, j
    meta[RECORDED] = k + 1


@njit(cache=True, error_model='numpy')
def run_events(end, budget, pos, vel, inv_mass, radius, own_e, gravity, low, high, params,
               flags, cell, table, head, nxt, prv, occupancy, ref_time, last_impact,
               count, own_next, h_time, h_int, meta, totals, losses, rec_f, rec_ij):
    """Process every event up to ``end``, then bring every particle to ``end``.

    The rules of ``EventDrivenStage`` (see its module doc): returns
    (status, heap arrays, record arrays), the arrays possibly grown. On
    ``NOT_EXACT`` (an event the TC model would have to alter under gravity,
    or more than ``budget`` events) the state is left mid-step for the
    caller to roll back. ``totals`` (restitution, walls) accumulate the
    energy booked, ``losses`` the per-particle share, impacts go to the
    record arrays when ``flags[F_RECORD]``.
    """
    half_g = 0.5 * gravity
    dims = flags[F_DIMS]
    under_gravity = flags[F_GRAVITY] != 0
    collapse = params[P_COLLAPSE]
    threshold = params[P_THRESHOLD]
    has_own = flags[F_OWN_E] != 0
    record = flags[F_RECORD] != 0
    book_losses = flags[F_LOSSES] != 0
    neighbours = 1
    for _ in range(dims):
        neighbours *= 3
    popped = np.empty(6, dtype=np.int64)
    scratch = np.empty(6, dtype=np.int64)
    taken = 0
    while meta[SIZE] > 0 and h_time[0] <= end:
        when = heap_pop(h_time, h_int, meta, popped, scratch)
        kind, p, q = popped[H_KIND], popped[H_P], popped[H_Q]
        if count[p] != popped[H_SP] or (kind == PAIR and count[q] != popped[H_SQ]):
            continue
        taken += 1
        if taken > budget:
            return NOT_EXACT, h_time, h_int, rec_f, rec_ij
        meta[EVENTS] += 1
        # Room for two predictions' events and one impact record.
        h_time, h_int = _reserve(h_time, h_int, meta, count,
                                 2 * (2 + neighbours * meta[MAX_OCC]))
        if record and meta[RECORDED] >= rec_f.shape[0]:
            grown_f = np.empty((2 * rec_f.shape[0], RECORD_COLUMNS))
            grown_ij = np.empty((2 * rec_f.shape[0], 2), dtype=np.int64)
            grown_f[:rec_f.shape[0]] = rec_f
            grown_ij[:rec_f.shape[0]] = rec_ij
            rec_f, rec_ij = grown_f, grown_ij
        if kind == PAIR:
            _advance(pos, vel, ref_time, gravity, half_g, p, when)
            _advance(pos, vel, ref_time, gravity, half_g, q, when)
            rx, ry, rz = vel[p, 0] - vel[q, 0], vel[p, 1] - vel[q, 1], vel[p, 2] - vel[q, 2]
            nx, ny, nz, _ = line_of_action(pos[p, 0] - pos[q, 0], pos[p, 1] - pos[q, 1],
                                           pos[p, 2] - pos[q, 2], rx, ry, rz)
            e = pair_restitution(own_e, has_own, p, q, params[P_PAIR_E])
            if threshold > 0.0 and -_dot(rx, ry, rz, nx, ny, nz) < threshold:
                e = 0.0
            if (when - last_impact[p] < collapse or when - last_impact[q] < collapse) \
                    and e < 1.0:
                if under_gravity:
                    return NOT_EXACT, h_time, h_int, rec_f, rec_ij
                e = 1.0     # TC model: an impact this soon after another is elastic
            magnitude, approach, removed = pair_impulse(vel, inv_mass, p, q, nx, ny, nz, e,
                                                        0.0)
            if approach > 0.0:
                meta[COLLISIONS] += 1
                meta[BOOKED_PAIRS] = 1
                totals[0] += removed
                if book_losses:
                    share = inv_mass[p] / (inv_mass[p] + inv_mass[q])
                    losses[p] += removed * share
                    losses[q] += removed * (1.0 - share)
                if record:
                    # Written with i < j and the normal from j to i (``record_pairs``).
                    i, j, sign = (p, q, 1.0) if p <= q else (q, p, -1.0)
                    mx, my, mz = sign * nx, sign * ny, sign * nz
                    _record(rec_f, rec_ij, meta, when, i, j,
                            0.5 * ((pos[i, 0] - radius[i] * mx) + (pos[j, 0] + radius[j] * mx)),
                            0.5 * ((pos[i, 1] - radius[i] * my) + (pos[j, 1] + radius[j] * my)),
                            0.5 * ((pos[i, 2] - radius[i] * mz) + (pos[j, 2] + radius[j] * mz)),
                            mx, my, mz, magnitude, approach)
            last_impact[p] = when
            last_impact[q] = when
            for k in (p, q):
                if inv_mass[k] > 0.0:      # a static particle's events stay valid
                    _predict(k, when, pos, vel, radius, ref_time, count, own_next, gravity, half_g,
                             low, high, params, flags, cell, table, head, nxt,
                             h_time, h_int, meta)
        elif kind == WALL:
            _advance(pos, vel, ref_time, gravity, half_g, p, when)
            axis, side = q // 2, q % 2
            toward = 1.0 if side else -1.0      # direction of the wall along the axis
            speed_in = toward * vel[p, axis]
            pushed_in = toward * gravity[axis]
            if speed_in > 0.0 or (speed_in == 0.0 and pushed_in > 0.0):
                e = wall_restitution(own_e, has_own, p, params[P_WALL_E])
                if threshold > 0.0 and speed_in < threshold:
                    e = 0.0
                if when - last_impact[p] < collapse:
                    resting = pushed_in > 0.0 and speed_in < 0.5 * pushed_in * collapse
                    if under_gravity and (e < 1.0 or resting):
                        return NOT_EXACT, h_time, h_int, rec_f, rec_ij
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
                    losses[p] += removed
                pos[p, axis] = plane - toward * radius[p]   # exact contact, no drift
                meta[WALL_COLLISIONS] += 1
                if record:
                    point = [pos[p, 0], pos[p, 1], pos[p, 2]]
                    normal = [0.0, 0.0, 0.0]
                    point[axis] = plane
                    normal[axis] = inward
                    _record(rec_f, rec_ij, meta, when, p, -1, point[0], point[1], point[2],
                            normal[0], normal[1], normal[2], magnitude, approach)
                last_impact[p] = when
            _predict(p, when, pos, vel, radius, ref_time, count, own_next, gravity, half_g, low,
                     high, params, flags, cell, table, head, nxt, h_time, h_int, meta)
        else:
            _advance(pos, vel, ref_time, gravity, half_g, p, when)
            axis, side = q // 2, q % 2
            _remove(p, cell, table, head, nxt, prv, occupancy)
            cell[p, axis] += 1 if side else -1
            _insert(p, cell, table, head, nxt, prv, occupancy, meta)
            _predict(p, when, pos, vel, radius, ref_time, count, own_next, gravity, half_g, low,
                     high, params, flags, cell, table, head, nxt, h_time, h_int, meta)
    for p in range(pos.shape[0]):
        _advance(pos, vel, ref_time, gravity, half_g, p, end)
    return DONE, h_time, h_int, rec_f, rec_ij


@njit(cache=True, error_model='numpy')
def build_events(when, pos, vel, inv_mass, radius, gravity, low, high, params, flags, cell,
                 table, head, nxt, prv, occupancy, ref_time, count, own_next, h_time, h_int,
                 meta):
    """Fill the grid and predict every dynamic particle's events, in index order.

    Returns the heap arrays (possibly grown).
    """
    half_g = 0.5 * gravity
    n = pos.shape[0]
    for p in range(n):
        _insert(p, cell, table, head, nxt, prv, occupancy, meta)
    neighbours = 1
    for _ in range(flags[F_DIMS]):
        neighbours *= 3
    for p in range(n):
        if not inv_mass[p] > 0.0:
            continue
        h_time, h_int = _reserve(h_time, h_int, meta, count, 2 + neighbours * meta[MAX_OCC])
        _predict(p, when, pos, vel, radius, ref_time, count, own_next, gravity, half_g, low, high,
                 params, flags, cell, table, head, nxt, h_time, h_int, meta)
    return h_time, h_int


def warm_up() -> None:
    """Run both kernels once on two particles meeting head on between walls."""
    pos = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    vel = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    inv_mass, radius = np.ones(2), np.full(2, 0.25)
    gravity, low, high = np.zeros(3), np.full(3, -1.0), np.full(3, 1.0)
    params = np.array([1e-5, 0.0, 1.0, 1.0, 0.5])
    flags = np.array([3, 0, 1, 1, 1, 1], dtype=np.int64)
    cell = np.floor(pos / 0.5).astype(np.int64)
    table = np.full(3, 7, dtype=np.int64)
    head, occupancy = np.full(343, -1, dtype=np.int64), np.zeros(343, dtype=np.int64)
    nxt, prv = np.full(2, -1, dtype=np.int64), np.full(2, -1, dtype=np.int64)
    ref_time, count, own_next = np.zeros(2), np.zeros(2, dtype=np.int64), np.full(2, np.inf)
    meta = np.zeros(META_SIZE, dtype=np.int64)
    meta[COMPACT_AT] = 1024
    h_time, h_int = build_events(0.0, pos, vel, inv_mass, radius, gravity, low, high, params,
                                 flags, cell, table, head, nxt, prv, occupancy, ref_time,
                                 count, own_next, np.empty(64), np.empty((64, 6), np.int64),
                                 meta)
    run_events(1.0, 1000, pos, vel, inv_mass, radius, np.full(2, np.nan), gravity, low, high,
               params, flags, cell, table, head, nxt, prv, occupancy, ref_time,
               np.full(2, -np.inf), count, own_next, h_time, h_int, meta, np.zeros(2),
               np.zeros(2), np.empty((4, RECORD_COLUMNS)), np.empty((4, 2), dtype=np.int64))


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [build_events, run_events]
