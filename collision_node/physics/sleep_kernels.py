"""Sleeping islands, compiled: stillness timers and the islands of the contact graph.

``settle_islands`` is the end of a step with sleeping (``stages/sleep.py``)
in one compiled call: it advances each awake particle's stillness timer,
finds the islands (connected components, union-find) of the near pairs
between particles that can move, joins every sleeping particle to its
island's representative, and decides per island: an island that holds an
awake particle falls asleep as a whole once every member has been still
for the sleep time, otherwise its sleeping members wake.
"""

from __future__ import annotations

import math

import numpy as np

from . import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from .contact_kernels import _root  # noqa: I100

from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)


@njit(cache=True)
def _travel(velocity, p, dt, sag):
    """Return how far particle ``p`` can move in the next step, m (|v| dt + |g| dt^2 / 2)."""
    vx, vy, vz = velocity[p, 0], velocity[p, 1], velocity[p, 2]
    return math.sqrt(vx * vx + vy * vy + vz * vz) * dt + sag


@njit(cache=True, nogil=True)
def settle_islands(position, velocity, angular, radius, dynamic, asleep, rep, pi, pj, margin,
                   sag, still_time, dt, speed, sleep_time):
    """Update timers and islands in place; return the mask of particles that fell asleep.

    ``dynamic``: particles of finite (real) mass; ``asleep`` and ``rep``
    (each sleeping particle's island representative, a row; -1 awake) are
    updated. Pairs (pi, pj) link when their gap is at most ``margin``
    times the radii sum plus both particles' travel in the next step
    (``sag`` = |g| dt^2 / 2 is part of it), the reach at which an awake
    particle would wake a sleeping one; two sleeping particles link through
    their representatives. ``angular`` has a row per particle or none.
    Sleeping particles' velocities are left to the caller (who books the
    kinetic energy before zeroing it).
    """
    n = position.shape[0]
    limit = speed * speed
    spun = angular.shape[0] == n
    for p in range(n):
        if not dynamic[p] or asleep[p]:
            continue
        vx, vy, vz = velocity[p, 0], velocity[p, 1], velocity[p, 2]
        still = vx * vx + vy * vy + vz * vz < limit
        if spun and still:
            wx, wy, wz = angular[p, 0], angular[p, 1], angular[p, 2]
            still = (wx * wx + wy * wy + wz * wz) * radius[p] * radius[p] < limit
        still_time[p] = still_time[p] + dt if still else 0.0
    parent = np.arange(n)
    for k in range(pi.size):
        a, b = pi[k], pj[k]
        if not (dynamic[a] and dynamic[b]) or (asleep[a] and asleep[b]):
            continue
        reach = margin * (radius[a] + radius[b])
        if not asleep[a]:
            reach += _travel(velocity, a, dt, sag)
        if not asleep[b]:
            reach += _travel(velocity, b, dt, sag)
        reach += radius[a] + radius[b]
        dx = position[a, 0] - position[b, 0]
        dy = position[a, 1] - position[b, 1]
        dz = position[a, 2] - position[b, 2]
        if dx * dx + dy * dy + dz * dz <= reach * reach:
            ra, rb = _root(parent, a), _root(parent, b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    for p in range(n):
        if asleep[p] and rep[p] >= 0:
            ra, rb = _root(parent, p), _root(parent, rep[p])
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    least = np.full(n, np.inf)
    awake = np.zeros(n, dtype=np.bool_)
    root = np.empty(n, dtype=np.int64)
    for p in range(n):
        if not dynamic[p]:
            continue
        c = _root(parent, p)
        root[p] = c
        least[c] = min(least[c], still_time[p])
        if not asleep[p]:
            awake[c] = True
    fell = np.zeros(n, dtype=np.bool_)
    for p in range(n):
        if not dynamic[p]:
            continue
        c = root[p]
        if not awake[c]:
            continue        # an island asleep as a whole stays as it is
        if least[c] >= sleep_time:
            if not asleep[p]:
                fell[p] = True
                asleep[p] = True
            rep[p] = c
        elif asleep[p]:
            # Touched by an awake particle that is not yet still: wake,
            # keeping the timer (the island sleeps again once the newcomer
            # has been still for the sleep time too).
            asleep[p] = False
            rep[p] = -1
    return fell


@njit(cache=True, nogil=True)
def near_sleepers(position, radius, velocity, awake, sleepers, margin, dt, sag, ci, cj):
    """Return the mask of candidate pairs (awake ci, sleeping cj) within waking reach.

    The reach is the radii sum times (1 + ``margin``) plus the awake
    particle's travel in the step (``settle_islands`` links the same
    pairs).
    """
    hit = np.zeros(ci.size, dtype=np.bool_)
    for k in range(ci.size):
        a, b = awake[ci[k]], sleepers[cj[k]]
        reach = (1.0 + margin) * (radius[a] + radius[b]) + _travel(velocity, a, dt, sag)
        dx = position[a, 0] - position[b, 0]
        dy = position[a, 1] - position[b, 1]
        dz = position[a, 2] - position[b, 2]
        hit[k] = dx * dx + dy * dy + dz * dz <= reach * reach
    return hit


@njit(cache=True, nogil=True)
def sleepers_within_reach(position, radius, velocity, awake, sleepers, margin, dt, sag):
    """Return the mask of ``sleepers`` within waking reach of any of ``awake``.

    Every pair is tested with ``near_sleepers``' test (no tree), which for
    a few hundred particles costs less than building the tree's query.
    """
    hit = np.zeros(sleepers.size, dtype=np.bool_)
    for q in range(awake.size):
        a = awake[q]
        travel = _travel(velocity, a, dt, sag)
        for k in range(sleepers.size):
            if hit[k]:
                continue
            b = sleepers[k]
            reach = (1.0 + margin) * (radius[a] + radius[b]) + travel
            dx = position[a, 0] - position[b, 0]
            dy = position[a, 1] - position[b, 1]
            dz = position[a, 2] - position[b, 2]
            hit[k] = dx * dx + dy * dy + dz * dz <= reach * reach
    return hit


def warm_up() -> None:
    """Call each kernel once on a tiny problem (compiles or loads from the cache)."""
    position = np.array([[0.0, 0.0, 0.0], [1.9, 0.0, 0.0]])
    velocity = np.zeros((2, 3))
    radius = np.ones(2)
    pair = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    settle_islands(position, velocity, np.zeros((2, 3)), radius, np.ones(2, dtype=bool),
                   np.zeros(2, dtype=bool), np.full(2, -1, dtype=np.int64), pair[0], pair[1],
                   0.02, 0.0, np.zeros(2), 0.01, 0.1, 0.5)
    near_sleepers(position, radius, velocity, pair[0], pair[1], 0.02, 0.01, 0.0, pair[0],
                  pair[0])
    sleepers_within_reach(position, radius, velocity, pair[0], pair[1], 0.02, 0.01, 0.0)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [settle_islands, near_sleepers, sleepers_within_reach]
