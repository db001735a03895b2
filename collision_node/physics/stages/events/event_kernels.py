"""The event loop of the ``exact`` preset, compiled: one call runs a whole step.

``event_driven.py`` keeps the stage's rules (when to rebuild, roll back and
fall back, what to book); this module runs its events on records the stage
owns between steps (``Particles``, ``Supports``, ``CellGrid``, each particle's
``SCHEDULE`` row, ``Candidates``, ``Heap``, the ``TALLY``) and one step's
``Settings``, ``ImpactBuffer`` and ``WorldArrays``:

- each particle moves on its closed-form path from its own reference time
  (lazy advance) and holds a change counter, raised when its path changes;
- cells at least one contact diameter wide form a hash grid: cell
  (cx, cy, cz) lives in slot (cx mod Mx, cy mod My, cz mod Mz) of a table at
  least 3 slots wide per axis, each slot a doubly linked list of its
  particles; a neighbour query keeps only particles whose cell really is
  adjacent, so an open scene that outgrows the table stays correct;
- each particle holds its next wall event, its next cell crossing and up to
  ``CANDIDATES`` predicted pair impacts (time, partner, the partner's change
  counter then: Rapaport's and Lubachevsky's scheme). A full list drops its
  latest and schedules a refresh at its time, so nothing is lost; a
  candidate whose partner changed since is dropped when it comes up (lazy
  invalidation);
- an indexed binary heap of the particles orders them by their next event.

An impact predicts its particles afresh against the 3^d cells around them;
a cell crossing changes no path and predicts the particle only against the
newly entered layer of 3^(d-1) cells (a pair in adjacent cells was
predicted when the later of the two entered adjacency or changed path).
Pair candidates later than either particle's next wall event are not kept
(that wall event predicts again).

Impact times are closed-form: under one uniform g a pair's relative motion
is straight (the smaller root of |d + u s| = r_i + r_j), a wall or a cell
face is reached at the entering root of a quadratic in the gap (the
operations of ``primitives.entering_time``), and a pair whose own accelerations
differ meets at the first root of a quartic (``curved_delay``). The velocity
update is the compiled contact law (``law.primitives``). Which particle
predicts a pair, and when, decides the last bits of an impact time: another
schedule gives the same impacts to round-off, not to the bit.

Of the helpers, only the neighbour scan (``_scan``, ``pair_delay``) and the
heap's sift run inlined into their callers, where the step's time goes: the
rest are compiled once and called, since numba types an inlined helper again
at every call site, which lengthens the first-start compile.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from ...law.primitives import (apply_wall_normal, combined_coefficient, dot3,  # noqa: I100
                               entering_time, line_of_action, pair_impulse,
                               sphere_contact_time)
from numba import njit  # noqa: E402,I100
from .resting_kernels import new_supports  # noqa: E402,I100
from ...model.tunables import CANDIDATES  # noqa: E402,I100

# What a run returns: the step is done; or an event the TC model would have
# to alter under gravity (resting contact), or the event budget, ended it;
# or the impact buffer is full: the caller gives a larger one and calls
# again (the loop resumes where it stopped; the kernel allocates nothing).
DONE, NOT_EXACT, GROW = 0, 1, 2
# A particle's next event (``SCHEDULE['next_event']``) when it is not a
# candidate (a candidate is its slot in the list, >= 0).
NEXT_WALL, NEXT_CELL, NEXT_REFRESH, NEXT_NONE = -1, -2, -3, -4

_INF = np.inf


class Settings(NamedTuple):
    """What one step's event loop reads and never changes (SI units; the step's five first)."""

    end: float                  # s: the step's end
    budget: int                 # events the step may take (chores: 4 budget)
    own_restitution: bool       # particles have their own e (``Particles.restitution``)
    record: bool                # write impacts to the ``ImpactBuffer``
    book_losses: bool           # add each particle's losses to ``WorldArrays.losses``
    dimensions: int
    cell_size: float            # m
    collapse_time: float        # s: an impact this soon after another is elastic (TC model)
    threshold: float            # m/s: e = 0 below this closing speed (0: none)
    pair_restitution: float     # the scene's particle restitution
    wall_restitution: float     # the walls' restitution
    gravity: np.ndarray         # (3,) m/s^2
    half_gravity: np.ndarray    # (3,) g / 2
    low_walls: np.ndarray       # (3,) m, -inf where open
    high_walls: np.ndarray      # (3,) m, inf where open
    under_gravity: bool
    has_walls: bool
    own_acceleration: bool      # particles have their own acceleration (``Supports``)


class Particles(NamedTuple):
    """The stage's own copy of the particles, in cell order (neighbours near in memory)."""

    position: np.ndarray        # (n, 3) m, each particle at its own reference time
    velocity: np.ndarray        # (n, 3) m/s
    inv_mass: np.ndarray        # (n,) 1/kg, 0 for a static particle
    radius: np.ndarray          # (n,) m
    restitution: np.ndarray     # (n,) its own e, NaN for none (read with own_restitution)


class CellGrid(NamedTuple):
    """The hash grid of cells: each slot a doubly linked list of its particles."""

    cell: np.ndarray            # (n, 3) int64: each particle's cell coordinates
    slot: np.ndarray            # (n, 3) int64: its slot's coordinates (cell mod table)
    table: np.ndarray           # (3,) int64: slots per axis
    head: np.ndarray            # (slots,) int64: first particle of each slot, -1 none
    next_in_slot: np.ndarray    # (n,) int64: the next particle of its slot, -1 none
    previous_in_slot: np.ndarray  # (n,) int64
    occupancy: np.ndarray       # (slots,) int64: particles in each slot


# Each particle's clocks and bookkeeping, one row (its fields near in memory).
SCHEDULE = np.dtype([
    ('reference_time', np.float64),     # s: the time its position and velocity are at
    ('last_impact', np.float64),        # s: its previous impact (TC model), -inf for none
    ('wall_time', np.float64),          # s: its next wall event
    ('crossing_time', np.float64),      # s: its next cell crossing
    ('refresh_time', np.float64),       # s: a fresh prediction (a full list dropped one)
    ('next_time', np.float64),          # s: its next event, the heap's key
    ('changes', np.int64),              # raised whenever its path changes
    ('wall_face', np.int64),            # wall of the next wall event (2 axis + side)
    ('crossing_face', np.int64),        # face of the next crossing (2 axis + side)
    ('held', np.int64),                 # pair candidates held
    ('next_event', np.int64),           # a candidate's slot, or one of NEXT_*
])


class Candidates(NamedTuple):
    """Each particle's predicted pair impacts (``CANDIDATES`` slots, ``held`` in use)."""

    time: np.ndarray            # (n, CANDIDATES) s
    partner: np.ndarray         # (n, CANDIDATES) int64
    stamp: np.ndarray           # (n, CANDIDATES) int64: the partner's ``changes`` then


class Heap(NamedTuple):
    """An indexed binary heap of all particles by next event (ties: the lower index)."""

    key: np.ndarray             # (n,) s: each slot's key, in slot order (sifts read it)
    particle: np.ndarray        # (n,) int64: the particle at each slot
    slot: np.ndarray            # (n,) int64: each particle's slot


# What a run counts (one row; a step starts it at 0 and at the step's dissipated
# totals so far, and a run resumed after GROW goes on from it).
TALLY = np.dtype([
    ('events', np.int64),               # impacts, wall visits and cell crossings taken
    ('collisions', np.int64),           # pair impacts
    ('wall_collisions', np.int64),      # wall impacts
    ('crossings', np.int64),            # cell crossings
    ('chores', np.int64),               # stale candidates dropped and refreshes
    ('refreshes', np.int64),            # fresh predictions of a full list
    ('predictions', np.int64),          # particles predicted afresh
    ('recorded', np.int64),             # rows written to the impact buffer
    ('booked_pairs', np.int64),         # 1 when a pair impact booked restitution
    ('booked_walls', np.int64),         # 1 when a wall impact booked walls
    ('restitution_dissipated', np.float64),  # J: the step's total so far, impact by impact
    ('walls_dissipated', np.float64),   # J
])


class ImpactBuffer(NamedTuple):
    """Room for the impacts a run records (world indices; a wall as -1)."""

    time: np.ndarray            # (k,) s
    point: np.ndarray           # (k, 3) m: the contact point
    normal: np.ndarray          # (k, 3): from the second to the first
    impulse: np.ndarray         # (k,) N s: the normal impulse
    approach: np.ndarray        # (k,) m/s: the closing speed
    first: np.ndarray           # (k,) int64
    second: np.ndarray          # (k,) int64 (-1: a wall)


class WorldArrays(NamedTuple):
    """The world's arrays a run publishes to: stage particle k is world particle order[k]."""

    order: np.ndarray           # (n,) int64
    position: np.ndarray        # (n, 3) m
    velocity: np.ndarray        # (n, 3) m/s
    losses: np.ndarray          # (n,) J booked per particle (no rows: not booked)


class Outcome(NamedTuple):
    """What a run returns: its status and the step's counts so far (the tally's)."""

    status: int                 # DONE, NOT_EXACT or GROW
    events: int
    collisions: int
    wall_collisions: int
    crossings: int
    refreshes: int
    recorded: int
    booked_pairs: int
    booked_walls: int
    restitution_dissipated: float   # J: the step's total, from the one it started with
    walls_dissipated: float         # J


# -- the heap of particles ----------------------------------------------------

@njit(cache=True, inline='always')
def _sift_down(heap, size, slot, p, key):
    """Place particle ``p`` of key ``key`` at heap slot ``slot`` or below."""
    keys, particle_at, slot_of = heap.key, heap.particle, heap.slot
    while True:
        child = 2 * slot + 1
        if child >= size:
            break
        child_key = keys[child]
        if child + 1 < size:
            sibling_key = keys[child + 1]
            if sibling_key < child_key or (sibling_key == child_key
                                           and particle_at[child + 1] < particle_at[child]):
                child, child_key = child + 1, sibling_key
        if not (child_key < key or (child_key == key and particle_at[child] < p)):
            break
        moved = particle_at[child]
        keys[slot] = child_key
        particle_at[slot] = moved
        slot_of[moved] = slot
        slot = child
    keys[slot] = key
    particle_at[slot] = p
    slot_of[p] = slot


@njit(cache=True, inline='always')
def heap_update(heap, schedule, p):
    """Move particle ``p`` to its place after its key (``next_time``) changed."""
    key = schedule[p].next_time
    keys, particle_at, slot_of = heap.key, heap.particle, heap.slot
    slot = slot_of[p]
    while slot > 0:
        parent = (slot - 1) >> 1
        parent_key = keys[parent]
        above = particle_at[parent]
        if not (key < parent_key or (key == parent_key and p < above)):
            break
        keys[slot] = parent_key
        particle_at[slot] = above
        slot_of[above] = slot
        slot = parent
    _sift_down(heap, keys.size, slot, p, key)


@njit(cache=True)
def heapify(heap, schedule):
    """Order every particle by its key (the heap of all particles)."""
    n = heap.key.size
    for p in range(n):
        heap.key[p] = schedule[p].next_time
        heap.particle[p] = p
        heap.slot[p] = p
    for slot in range((n - 2) // 2, -1, -1):
        _sift_down(heap, n, slot, heap.particle[slot], heap.key[slot])


# -- the candidate lists -------------------------------------------------------

@njit(cache=True)
def _set_next(p, schedule, candidates):
    """Make particle p's key the earliest of its events and note which one it is.

    On a tie the wall comes first, then the cell crossing, the refresh and
    the candidates in list order.
    """
    own = schedule[p]
    best, which = own.wall_time, NEXT_WALL
    if own.crossing_time < best:
        best, which = own.crossing_time, NEXT_CELL
    if own.refresh_time < best:
        best, which = own.refresh_time, NEXT_REFRESH
    times = candidates.time
    for k in range(own.held):
        if times[p, k] < best:
            best, which = times[p, k], k
    if best == _INF:
        which = NEXT_NONE
    own.next_time = best
    own.next_event = which


@njit(cache=True)
def _drop(p, k, schedule, candidates):
    """Remove candidate ``k`` of particle ``p`` (the last one takes its slot)."""
    last = schedule[p].held - 1
    candidates.time[p, k] = candidates.time[p, last]
    candidates.partner[p, k] = candidates.partner[p, last]
    candidates.stamp[p, k] = candidates.stamp[p, last]
    schedule[p].held = last


@njit(cache=True)
def _hold(p, q, at, stamp, schedule, candidates):
    """Add pair candidate (q at ``at``) to p's list; a full list drops its latest.

    The dropped time becomes a refresh of p (if earlier than the one
    scheduled), where p is predicted afresh: nothing is lost.
    """
    own = schedule[p]
    held = own.held
    if held < CANDIDATES:
        candidates.time[p, held] = at
        candidates.partner[p, held] = q
        candidates.stamp[p, held] = stamp
        own.held = held + 1
        return
    latest, slot = at, -1
    for k in range(held):
        if candidates.time[p, k] > latest:
            latest, slot = candidates.time[p, k], k
    if slot >= 0:
        candidates.time[p, slot] = at
        candidates.partner[p, slot] = q
        candidates.stamp[p, slot] = stamp
    if latest < own.refresh_time:
        own.refresh_time = latest


# -- paths --------------------------------------------------------------------

@njit(cache=True)
def _advance(settings, particles, supports, schedule, p, when):
    """Bring particle ``p`` to time ``when`` on its parabola.

    The operations of the vectorised form: x + (v tau + ((g / 2) tau) tau), v + g tau,
    with p's own acceleration for g when particles have their own.
    """
    own = schedule[p]
    tau = when - own.reference_time
    position, velocity = particles.position, particles.velocity
    if settings.own_acceleration:
        acceleration = supports.acceleration
        for c in range(3):
            position[p, c] += velocity[p, c] * tau + (0.5 * acceleration[p, c]) * tau * tau
        for c in range(3):
            velocity[p, c] += acceleration[p, c] * tau
    else:
        gravity, half_gravity = settings.gravity, settings.half_gravity
        for c in range(3):
            position[p, c] += velocity[p, c] * tau + half_gravity[c] * tau * tau
        for c in range(3):
            velocity[p, c] += gravity[c] * tau
    own.reference_time = when


@njit(cache=True, error_model='numpy', inline='always')
def pair_delay(dx, dy, dz, rx, ry, rz, reach):
    """Delay until a pair touches, from its offset d, relative velocity r and reach (scalars).

    The smaller root of |d + r s| = reach (the quadratic of
    ``swept_contacts.pair_impact_times``, same operations): inf for none, 0
    for an overlapping pair that approaches.
    """
    # Most neighbours recede, or approach and miss: say so before dividing,
    # in raw units (the sign of each test is the scaled one's but at round-off
    # in a grazing pair; a product that underflows to 0 or overflows to NaN
    # takes the long way).
    raw_b = dot3(dx, dy, dz, rx, ry, rz)
    raw_c = dot3(dx, dy, dz, dx, dy, dz) - reach * reach
    if raw_c > 0.0 and (raw_b > 0.0 or raw_b * raw_b - dot3(rx, ry, rz, rx, ry, rz) * raw_c < 0.0):
        return _INF
    ox, oy, oz = dx / reach, dy / reach, dz / reach
    ux, uy, uz = rx / reach, ry / reach, rz / reach
    return sphere_contact_time(ox, oy, oz, ux, uy, uz, dx, dy, dz, rx, ry, rz)


@njit(cache=True, error_model='numpy')
def _curved_gap(ox, oy, oz, wx, wy, wz, hx, hy, hz, s):
    """Return F(s) = |o + w s + h s^2|^2 - 1 (a pair's scaled squared distance less 1)."""
    x = ox + (wx + hx * s) * s
    y = oy + (wy + hy * s) * s
    z = oz + (wz + hz * s) * s
    return dot3(x, y, z, x, y, z) - 1.0


@njit(cache=True, error_model='numpy')
def _curved_slope(ox, oy, oz, wx, wy, wz, hx, hy, hz, s):
    """Return F'(s) / 2 = D(s) . D'(s), D(s) = o + w s + h s^2 (a cubic in s)."""
    x = ox + (wx + hx * s) * s
    y = oy + (wy + hy * s) * s
    z = oz + (wz + hz * s) * s
    return dot3(x, y, z, wx + 2.0 * hx * s, wy + 2.0 * hy * s, wz + 2.0 * hz * s)


@njit(cache=True, error_model='numpy')
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
    speed = math.sqrt(dot3(wx, wy, wz, wx, wy, wz))
    curve = math.sqrt(dot3(hx, hy, hz, hx, hy, hz))
    if math.sqrt(dot3(ox, oy, oz, ox, oy, oz)) - (speed + curve * horizon) * horizon > 1.0:
        return _INF
    # F'/2 = D . D' has derivative |D'|^2 + 2 h . D = A s^2 + B s + C.
    a_ = 6.0 * dot3(hx, hy, hz, hx, hy, hz)
    b_ = 6.0 * dot3(wx, wy, wz, hx, hy, hz)
    c_ = dot3(wx, wy, wz, wx, wy, wz) + 2.0 * dot3(hx, hy, hz, ox, oy, oz)
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


@njit(cache=True, error_model='numpy')
def _varied_delay(p, q, when, horizon, particles, supports, schedule):
    """Return when pair (p, q) meets, each with its own acceleration (``own_acceleration``).

    Brings q to ``when`` first; p is there already. A resting partner of p
    is never predicted (inf).
    """
    position, velocity = particles.position, particles.velocity
    acceleration = supports.acceleration
    tau = when - schedule[q].reference_time
    if tau != 0.0:
        for c in range(3):
            position[q, c] += velocity[q, c] * tau + (0.5 * acceleration[q, c]) * tau * tau
        for c in range(3):
            velocity[q, c] += acceleration[q, c] * tau
        schedule[q].reference_time = when
    if supports.supported[p] or supports.supported[q]:
        for s in range(supports.partners.shape[1]):
            partner = supports.partners[p, s]
            if partner == q:
                return _INF
            if partner == -1:
                break
    ax = acceleration[p, 0] - acceleration[q, 0]
    ay = acceleration[p, 1] - acceleration[q, 1]
    az = acceleration[p, 2] - acceleration[q, 2]
    dx, dy, dz = (position[p, 0] - position[q, 0], position[p, 1] - position[q, 1],
                  position[p, 2] - position[q, 2])
    rx, ry, rz = (velocity[p, 0] - velocity[q, 0], velocity[p, 1] - velocity[q, 1],
                  velocity[p, 2] - velocity[q, 2])
    reach = particles.radius[p] + particles.radius[q]
    if ax == 0.0 and ay == 0.0 and az == 0.0:
        return when + pair_delay(dx, dy, dz, rx, ry, rz, reach)
    return when + curved_delay(dx, dy, dz, rx, ry, rz, ax, ay, az, reach, horizon)


# -- the cell grid ------------------------------------------------------------

@njit(cache=True)
def _slot(p, grid):
    """Return the slot of particle p's cell."""
    table, slot = grid.table, grid.slot
    return (slot[p, 0] * table[1] + slot[p, 1]) * table[2] + slot[p, 2]


@njit(cache=True)
def _insert(p, grid):
    """Put particle ``p`` at the head of its cell's slot list."""
    s = _slot(p, grid)
    first = grid.head[s]
    grid.next_in_slot[p], grid.previous_in_slot[p] = first, -1
    if first >= 0:
        grid.previous_in_slot[first] = p
    grid.head[s] = p
    grid.occupancy[s] += 1


@njit(cache=True)
def _remove(p, grid):
    """Take particle ``p`` out of its cell's slot list."""
    s = _slot(p, grid)
    following, preceding = grid.next_in_slot, grid.previous_in_slot
    if preceding[p] >= 0:
        following[preceding[p]] = following[p]
    else:
        grid.head[s] = following[p]
    if following[p] >= 0:
        preceding[following[p]] = preceding[p]
    grid.occupancy[s] -= 1


# -- prediction ---------------------------------------------------------------

@njit(cache=True, error_model='numpy')
def _own_events(p, settings, particles, supports, grid, schedule, walls_too):
    """Delays until p (at its reference time) leaves its cell and reaches a wall.

    Sets p's next crossing (and, with ``walls_too``, its next wall event) as
    times; on a tie the lower face or wall of the lower axis is taken. With
    accelerations of their own p moves with its own, and the walls it rests
    on are not predicted (it neither closes nor opens on them).
    """
    varied = settings.own_acceleration
    resting_on = supports.wall_mask[p] if varied else 0
    own = schedule[p]
    when = own.reference_time
    size = settings.cell_size
    low, high = settings.low_walls, settings.high_walls
    r = particles.radius[p]
    best_wall, wall_face = _INF, -1
    best_cell, cell_face = _INF, 0
    for axis in range(settings.dimensions):
        x, v = particles.position[p, axis], particles.velocity[p, axis]
        g = supports.acceleration[p, axis] if varied else settings.gravity[axis]
        low_face = grid.cell[p, axis] * size
        t_low = entering_time(x - low_face, v, g)
        t_high = entering_time((low_face + size) - x, -v, -g)
        if t_low < best_cell:
            best_cell, cell_face = t_low, 2 * axis
        if t_high < best_cell:
            best_cell, cell_face = t_high, 2 * axis + 1
        if walls_too and settings.has_walls:
            w_low = (_INF if resting_on >> (2 * axis) & 1
                     else entering_time(x - (low[axis] + r), v, g))
            w_high = (_INF if resting_on >> (2 * axis + 1) & 1
                      else entering_time((high[axis] - r) - x, -v, -g))
            if w_low < best_wall:
                best_wall, wall_face = w_low, 2 * axis
            if w_high < best_wall:
                best_wall, wall_face = w_high, 2 * axis + 1
    own.crossing_time = when + best_cell
    own.crossing_face = cell_face
    if walls_too:
        own.wall_time = when + best_wall
        own.wall_face = wall_face


@njit(cache=True, error_model='numpy', inline='always')
def _scan(p, when, along, offset, skip_before, settings, particles, supports, grid, schedule,
          candidates):
    """Predict p against the particles of the cells around it; keep the impacts as candidates.

    ``along`` < 0: the 3^d cells around p's cell; otherwise the layer of
    3^(d-1) cells ``offset`` (+1 or -1) cells away along that axis. Dynamic
    particles below ``skip_before`` are left out (they predicted p already).
    A candidate later than either particle's next wall event is not kept.
    With accelerations of their own: a pair whose two accelerations differ
    moves on a parabola relative to each other, so its time is
    ``curved_delay``'s (within the step), and p's resting partners are not
    predicted.
    """
    varied = settings.own_acceleration
    horizon = settings.end - when
    dims = settings.dimensions
    table, cell, head, following = grid.table, grid.cell, grid.head, grid.next_in_slot
    position, velocity = particles.position, particles.velocity
    inv_mass, radius = particles.inv_mass, particles.radius
    slots_x, slots_y, slots_z = table[0], table[1], table[2]
    cell_x, cell_y, cell_z = cell[p, 0], cell[p, 1], cell[p, 2]
    slot_x, slot_y, slot_z = grid.slot[p, 0], grid.slot[p, 1], grid.slot[p, 2]
    wall_p = schedule[p].wall_time
    # p's state and g as scalars for the inner loop.
    x_p, y_p, z_p = position[p, 0], position[p, 1], position[p, 2]
    vx_p, vy_p, vz_p = velocity[p, 0], velocity[p, 1], velocity[p, 2]
    radius_p = radius[p]
    gravity, half_gravity = settings.gravity, settings.half_gravity
    gx, gy, gz = gravity[0], gravity[1], gravity[2]
    hx, hy, hz = half_gravity[0], half_gravity[1], half_gravity[2]
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
        sx = slot_x + dx
        sx = slots_x - 1 if sx < 0 else (0 if sx >= slots_x else sx)
        for dy in range(lo_y, hi_y + 1):
            sy = slot_y + dy
            sy = slots_y - 1 if sy < 0 else (0 if sy >= slots_y else sy)
            row = (sx * slots_y + sy) * slots_z
            for dz in range(lo_z, hi_z + 1):
                sz = slot_z + dz
                sz = slots_z - 1 if sz < 0 else (0 if sz >= slots_z else sz)
                cx, cy, cz = cell_x + dx, cell_y + dy, cell_z + dz
                q = head[row + sz]
                while q >= 0:
                    if q != p and cell[q, 0] == cx and cell[q, 1] == cy and cell[q, 2] == cz \
                            and not (q < skip_before and inv_mass[q] > 0.0):
                        if varied:
                            at = _varied_delay(p, q, when, horizon, particles, supports, schedule)
                        else:
                            tau = when - schedule[q].reference_time
                            if tau != 0.0:
                                # _advance(q), written out with g as scalars.
                                position[q, 0] += velocity[q, 0] * tau + hx * tau * tau
                                position[q, 1] += velocity[q, 1] * tau + hy * tau * tau
                                position[q, 2] += velocity[q, 2] * tau + hz * tau * tau
                                velocity[q, 0] += gx * tau
                                velocity[q, 1] += gy * tau
                                velocity[q, 2] += gz * tau
                                schedule[q].reference_time = when
                            at = when + pair_delay(
                                x_p - position[q, 0], y_p - position[q, 1], z_p - position[q, 2],
                                vx_p - velocity[q, 0], vy_p - velocity[q, 1],
                                vz_p - velocity[q, 2], radius_p + radius[q])
                        if at < wall_p and at < schedule[q].wall_time:
                            _hold(p, q, at, schedule[q].changes, schedule, candidates)
                    q = following[q]


@njit(cache=True, error_model='numpy')
def _predict(p, bump, skip_before, settings, particles, supports, grid, schedule, candidates,
             tally):
    """Predict particle p (at its reference time) afresh: walls, cell, 3^d cells around.

    ``bump``: p's path changed, so the candidates others hold with p go stale.
    Sets p's key; the caller moves it in the heap. (``build_events``'s; the
    event loop has the same steps inline.)
    """
    own = schedule[p]
    if bump:
        own.changes += 1
    tally[0].predictions += 1
    own.held = 0
    own.refresh_time = _INF
    _own_events(p, settings, particles, supports, grid, schedule, True)
    _scan(p, own.reference_time, -1, 0, skip_before, settings, particles, supports, grid,
          schedule, candidates)
    _set_next(p, schedule, candidates)


@njit(cache=True)
def _enter_cell(p, grid, schedule, candidates):
    """Move p into the next cell; return the axis and side (+1, -1) of its new layer.

    Candidates whose partner changed path are dropped now (room for new ones).
    """
    face = schedule[p].crossing_face
    axis, side = face // 2, face % 2
    _remove(p, grid)
    # The cell and its slot along the axis (wrapping round the table).
    cell, slot = grid.cell, grid.slot
    wrap = grid.table[axis]
    if side:
        cell[p, axis] += 1
        slot[p, axis] = 0 if slot[p, axis] == wrap - 1 else slot[p, axis] + 1
    else:
        cell[p, axis] -= 1
        slot[p, axis] = wrap - 1 if slot[p, axis] == 0 else slot[p, axis] - 1
    _insert(p, grid)
    for k in range(schedule[p].held - 1, -1, -1):
        q = candidates.partner[p, k]
        if schedule[q].changes != candidates.stamp[p, k]:
            _drop(p, k, schedule, candidates)
    return axis, 1 if side else -1


# -- events -------------------------------------------------------------------

@njit(cache=True)
def _outcome(status, counts):
    """Return the ``Outcome`` of a run that ends with ``status`` (``counts``: the tally's row)."""
    return Outcome(status, counts.events, counts.collisions, counts.wall_collisions,
                   counts.crossings, counts.refreshes, counts.recorded, counts.booked_pairs,
                   counts.booked_walls, counts.restitution_dissipated, counts.walls_dissipated)


@njit(cache=True)
def _record(impacts, tally, when, first, second, point, normal, impulse, approach):
    """Append one impact (room is checked before each event); point, normal: 3-tuples."""
    counts = tally[0]
    k = counts.recorded
    impacts.time[k] = when
    impacts.point[k, 0], impacts.point[k, 1], impacts.point[k, 2] = point
    impacts.normal[k, 0], impacts.normal[k, 1], impacts.normal[k, 2] = normal
    impacts.impulse[k], impacts.approach[k] = impulse, approach
    impacts.first[k], impacts.second[k] = first, second
    counts.recorded = k + 1


@njit(cache=True)
def _keeps_supports(supports, p, normal):
    """Say whether an impulse along ``normal`` (a 3-tuple) on p leaves its supports as they are.

    True for a particle that is not supported, and for one that rests on
    walls only, each at right angles to N (a ball rolling on a floor struck
    sideways); an impulse on a particle resting on others would change
    their normal speeds too.
    """
    if not supports.supported[p]:
        return True
    for s in range(supports.partners.shape[1]):
        partner = supports.partners[p, s]
        if partner == -1:
            break
        if partner >= 0:
            return False
    walls = supports.wall_mask[p]
    nx, ny, nz = normal
    if walls & 3 and nx != 0.0:
        return False
    if walls & 12 and ny != 0.0:
        return False
    if walls & 48 and nz != 0.0:
        return False
    return True


# Without the runtime's reference counting (``_nrt=False``): the kernel
# allocates nothing, and the counts numba keeps for every array handed to an
# inlined helper would cost atomic updates in the innermost loops.
@njit(cache=True, nogil=True, error_model='numpy', _nrt=False)
def run_events(settings, particles, supports, grid, schedule, candidates, heap, tally, impacts,
               world):
    """Process every event up to ``settings.end``, then publish every particle there.

    Returns the ``Outcome``. On ``NOT_EXACT`` (an event the TC model would have
    to alter under gravity, an impact that would change the normal speed at
    a support of a supported particle (``_keeps_supports``), or more events
    than the budget) the records are left mid-step and the world's arrays
    untouched, for the caller to rebuild. On ``GROW`` the impact buffer is
    full: call again with a larger one (its rows so far copied). The tally's
    dissipated totals accumulate the energy booked, impact after impact;
    ``world.losses`` each particle's share (world indices, as the impacts).
    """
    under_gravity = settings.under_gravity
    varied = settings.own_acceleration
    collapse = settings.collapse_time
    threshold = settings.threshold
    has_own = settings.own_restitution
    record = settings.record
    book_losses = settings.book_losses
    end, budget = settings.end, settings.budget
    position, velocity = particles.position, particles.velocity
    inv_mass, radius = particles.inv_mass, particles.radius
    order, losses = world.order, world.losses
    counts = tally[0]
    while schedule.shape[0] > 0:
        p = heap.particle[0]
        when = heap.key[0]
        if not when <= end:
            break
        which = schedule[p].next_event
        if which >= 0:
            q = candidates.partner[p, which]
            if schedule[q].changes != candidates.stamp[p, which]:
                # Its partner changed path since: drop it, take p's next one.
                counts.chores += 1
                if counts.chores > 4 * budget:
                    return _outcome(NOT_EXACT, counts)
                _drop(p, which, schedule, candidates)
                _set_next(p, schedule, candidates)
                heap_update(heap, schedule, p)
                continue
        # Who is predicted after this event, whether their paths changed, and
        # whether it is a crossing (then only the new layer of cells).
        if record and counts.recorded >= impacts.time.shape[0]:
            return _outcome(GROW, counts)
        first, second, bump, crossing = p, -1, True, False
        if which == NEXT_REFRESH:
            counts.chores += 1
            counts.refreshes += 1
            if counts.chores > 4 * budget:
                return _outcome(NOT_EXACT, counts)
            _advance(settings, particles, supports, schedule, p, when)
            bump = False
        else:
            if counts.events >= budget:
                return _outcome(NOT_EXACT, counts)
            counts.events += 1
        if which == NEXT_REFRESH:
            pass
        elif which >= 0:
            q = candidates.partner[p, which]
            _advance(settings, particles, supports, schedule, p, when)
            _advance(settings, particles, supports, schedule, q, when)
            rx = velocity[p, 0] - velocity[q, 0]
            ry = velocity[p, 1] - velocity[q, 1]
            rz = velocity[p, 2] - velocity[q, 2]
            nx, ny, nz, _ = line_of_action(position[p, 0] - position[q, 0],
                                           position[p, 1] - position[q, 1],
                                           position[p, 2] - position[q, 2], rx, ry, rz)
            if varied and -dot3(rx, ry, rz, nx, ny, nz) > 0.0 and not (
                    _keeps_supports(supports, p, (nx, ny, nz))
                    and _keeps_supports(supports, q, (nx, ny, nz))):
                return _outcome(NOT_EXACT, counts)
            e = combined_coefficient(particles.restitution, has_own, p, q,
                                     settings.pair_restitution)
            if threshold > 0.0 and -dot3(rx, ry, rz, nx, ny, nz) < threshold:
                e = 0.0
            if (when - schedule[p].last_impact < collapse
                    or when - schedule[q].last_impact < collapse) and e < 1.0:
                if under_gravity:
                    return _outcome(NOT_EXACT, counts)
                e = 1.0     # TC model: an impact this soon after another is elastic
            magnitude, approach, removed = pair_impulse(velocity, inv_mass, p, q, nx, ny, nz, e,
                                                        0.0)
            if approach > 0.0:
                counts.collisions += 1
                counts.booked_pairs = 1
                counts.restitution_dissipated += removed
                if book_losses:
                    share = inv_mass[p] / (inv_mass[p] + inv_mass[q])
                    losses[order[p]] += removed * share
                    losses[order[q]] += removed * (1.0 - share)
                if record:
                    # Written with i < j (the world's indices) and the normal
                    # from j to i (``record_pairs``).
                    i, j, sign = (p, q, 1.0) if order[p] <= order[q] else (q, p, -1.0)
                    mx, my, mz = sign * nx, sign * ny, sign * nz
                    r_i, r_j = radius[i], radius[j]
                    point = (0.5 * ((position[i, 0] - r_i * mx) + (position[j, 0] + r_j * mx)),
                             0.5 * ((position[i, 1] - r_i * my) + (position[j, 1] + r_j * my)),
                             0.5 * ((position[i, 2] - r_i * mz) + (position[j, 2] + r_j * mz)))
                    _record(impacts, tally, when, order[i], order[j], point, (mx, my, mz),
                            magnitude, approach)
            schedule[p].last_impact = when
            schedule[q].last_impact = when
            if inv_mass[q] > 0.0:      # a static particle's events stay valid
                second = q
        elif which == NEXT_WALL:
            _advance(settings, particles, supports, schedule, p, when)
            face = schedule[p].wall_face
            axis, side = face // 2, face % 2
            toward = 1.0 if side else -1.0      # direction of the wall along the axis
            speed_in = toward * velocity[p, axis]
            pushed_in = toward * (supports.acceleration[p, axis] if varied
                                  else settings.gravity[axis])
            if speed_in > 0.0 or (speed_in == 0.0 and pushed_in > 0.0):
                if varied and not _keeps_supports(supports, p, (1.0 if axis == 0 else 0.0,
                                                                1.0 if axis == 1 else 0.0,
                                                                1.0 if axis == 2 else 0.0)):
                    return _outcome(NOT_EXACT, counts)
                e = combined_coefficient(particles.restitution, has_own, p, -1,
                                         settings.wall_restitution)
                if threshold > 0.0 and speed_in < threshold:
                    e = 0.0
                if when - schedule[p].last_impact < collapse:
                    resting = pushed_in > 0.0 and speed_in < 0.5 * pushed_in * collapse
                    if under_gravity and (e < 1.0 or resting):
                        return _outcome(NOT_EXACT, counts)
                    e = 1.0
                plane = settings.high_walls[axis] if side else settings.low_walls[axis]
                inward = -toward
                approach = -inward * velocity[p, axis]
                magnitude, removed = apply_wall_normal(velocity, inv_mass, p, axis, inward, e,
                                                       approach)
                counts.booked_walls = 1
                counts.walls_dissipated += removed
                if book_losses:
                    losses[order[p]] += removed
                position[p, axis] = plane - toward * radius[p]   # exact contact, no drift
                counts.wall_collisions += 1
                if record:
                    _record(impacts, tally, when, order[p], -1,
                            (plane if axis == 0 else position[p, 0],
                             plane if axis == 1 else position[p, 1],
                             plane if axis == 2 else position[p, 2]),
                            (inward if axis == 0 else 0.0, inward if axis == 1 else 0.0,
                             inward if axis == 2 else 0.0), magnitude, approach)
                schedule[p].last_impact = when
        elif which == NEXT_CELL:
            counts.crossings += 1
            _advance(settings, particles, supports, schedule, p, when)
            crossing = True
        # One site for all predictions: the helpers are inlined here once.
        for k in range(2):
            r = first if k == 0 else second
            if r < 0:
                continue
            along, offset = -1, 0
            if crossing:
                along, offset = _enter_cell(r, grid, schedule, candidates)
            else:
                if bump:
                    schedule[r].changes += 1
                counts.predictions += 1
                schedule[r].held = 0
                schedule[r].refresh_time = _INF
            _own_events(r, settings, particles, supports, grid, schedule, not crossing)
            _scan(r, when, along, offset, 0, settings, particles, supports, grid, schedule,
                  candidates)
            _set_next(r, schedule, candidates)
            heap_update(heap, schedule, r)
    for p in range(position.shape[0]):
        _advance(settings, particles, supports, schedule, p, end)
        k = order[p]
        for c in range(3):
            world.position[k, c] = position[p, c]
            world.velocity[k, c] = velocity[p, c]
    return _outcome(DONE, counts)


@njit(cache=True, nogil=True, error_model='numpy')
def build_events(settings, particles, supports, grid, schedule, candidates, heap, tally):
    """Fill the grid, predict every dynamic particle (each pair once) and order the heap.

    ``schedule`` comes from ``new_schedule`` (every particle at one reference
    time, no impact yet, nothing predicted).
    """
    n = particles.position.shape[0]
    for p in range(n):
        _insert(p, grid)
    for p in range(n):
        if particles.inv_mass[p] > 0.0:
            _predict(p, False, p, settings, particles, supports, grid, schedule, candidates,
                     tally)
        else:
            schedule[p].next_event = NEXT_NONE
    heapify(heap, schedule)


@njit(cache=True, nogil=True)
def matches(position, velocity, inv_mass, radius, own_position, own_velocity, own_inv_mass,
            own_radius, order):
    """Say whether the world's particle arrays still hold what the last step published.

    ``own_*`` are the stage's copies (``Particles``'s, plain arrays: this runs
    every step, and a NamedTuple argument costs its dispatch a microsecond a
    field).
    """
    for p in range(own_position.shape[0]):
        k = order[p]
        if inv_mass[k] != own_inv_mass[p] or radius[k] != own_radius[p]:
            return False
        for c in range(3):
            if position[k, c] != own_position[p, c] or velocity[k, c] != own_velocity[p, c]:
                return False
    return True


def entry_point(kernel, args: tuple):
    """Return ``kernel``'s compiled entry point for the types of ``args`` (loaded or compiled).

    Calling it skips numba's dispatch, which types every field of a
    NamedTuple argument in Python at each call (about a microsecond a field,
    a third of a step of a 1,000-particle gas). The caller must call it only
    with arguments of these types.
    """
    return kernel.compile(tuple(kernel.typeof_pyval(value) for value in args))


def start_tally(tally: np.ndarray, restitution: float, walls: float) -> None:
    """Start a step's tally: every count 0, the dissipated totals at the step's so far (J)."""
    tally[0] = _ZERO_COUNTS + (restitution, walls)


_ZERO_COUNTS = (0,) * (len(TALLY.names) - 2)


def new_schedule(n: int, time: float) -> np.ndarray:
    """Return ``n`` particles' schedule rows at ``time`` s: no impact yet, nothing predicted."""
    schedule = np.zeros(n, dtype=SCHEDULE)
    schedule['reference_time'] = time
    schedule['last_impact'] = -np.inf
    for name in ('wall_time', 'crossing_time', 'refresh_time', 'next_time'):
        schedule[name] = np.inf
    return schedule


def new_candidates(n: int) -> Candidates:
    """Return empty candidate lists for ``n`` particles."""
    return Candidates(np.empty((n, CANDIDATES)), np.empty((n, CANDIDATES), dtype=np.int64),
                      np.empty((n, CANDIDATES), dtype=np.int64))


def new_heap(n: int) -> Heap:
    """Return room for a heap of ``n`` particles (``heapify`` orders it)."""
    return Heap(np.empty(n), np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64))


def new_impact_buffer(rows: int) -> ImpactBuffer:
    """Return room for ``rows`` impacts."""
    return ImpactBuffer(np.empty(rows), np.empty((rows, 3)), np.empty((rows, 3)),
                        np.empty(rows), np.empty(rows), np.empty(rows, dtype=np.int64),
                        np.empty(rows, dtype=np.int64))


def grown(impacts: ImpactBuffer) -> ImpactBuffer:
    """Return an impact buffer twice as long, its rows so far copied."""
    return ImpactBuffer(*(np.concatenate([field, np.empty_like(field)]) for field in impacts))


def new_grid(cell: np.ndarray, table: np.ndarray) -> CellGrid:
    """Return the empty grid of particles in cells ``cell`` ((n, 3) int64), ``table`` slots."""
    n, slots = cell.shape[0], int(np.prod(table))
    return CellGrid(cell, cell % table, table, np.full(slots, -1, dtype=np.int64),
                    np.full(n, -1, dtype=np.int64), np.full(n, -1, dtype=np.int64),
                    np.zeros(slots, dtype=np.int64))


def warm_up() -> None:
    """Run the kernels once on two particles meeting head on between walls."""
    position = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]])
    velocity = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    particles = Particles(position, velocity, np.ones(2), np.full(2, 0.25), np.full(2, np.nan))
    settings = Settings(end=1.0, budget=1000, dimensions=3, cell_size=0.5, collapse_time=1e-5,
                        threshold=0.0, pair_restitution=1.0, wall_restitution=1.0,
                        gravity=np.zeros(3), half_gravity=np.zeros(3),
                        low_walls=np.full(3, -1.0), high_walls=np.full(3, 1.0),
                        under_gravity=False, has_walls=True, own_restitution=True,
                        own_acceleration=False, record=True, book_losses=True)
    supports = new_supports(2)
    grid = new_grid(np.floor(position / 0.5).astype(np.int64), np.full(3, 7, dtype=np.int64))
    schedule, candidates, heap = new_schedule(2, 0.0), new_candidates(2), new_heap(2)
    tally = np.zeros(1, dtype=TALLY)
    build_events(settings, particles, supports, grid, schedule, candidates, heap, tally)
    world = WorldArrays(np.arange(2), position.copy(), velocity.copy(), np.zeros(2))
    run_events(settings, particles, supports, grid, schedule, candidates, heap, tally,
               new_impact_buffer(4), world)
    matches(world.position, world.velocity, particles.inv_mass, particles.radius,
            particles.position, particles.velocity, particles.inv_mass, particles.radius,
            world.order)
    curved_delay(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.5, 1.0)


def kernels() -> list:
    """Return the compiled kernels of this module (the ones a warm-up compiles)."""
    return [build_events, run_events, matches, curved_delay]
