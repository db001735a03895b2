"""Sleeping islands, compiled: stillness timers and the islands of the contact graph.

``settle_islands`` is the end of a step with sleeping (``stages/sleeping/sleep.py``)
in one compiled call: it advances each awake particle's stillness timer,
finds the islands (connected components, union-find) of the near pairs
between particles that can move, joins every sleeping particle to its
island's representative, and decides per island: an island that holds an
awake particle falls asleep as a whole once every member has been still
for the sleep time, otherwise its sleeping members wake.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ...step import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from ...step.step_kernels import union_root  # noqa: I100

from numba import njit  # noqa: E402,I100 (after the cache directory is chosen)


class IslandParticles(NamedTuple):
    """The particle arrays the islands are found from (one row per particle)."""

    position: np.ndarray            # (n, 3), m
    velocity: np.ndarray            # (n, 3), m/s
    angular_velocity: np.ndarray    # (n, 3) rad/s, or (0, 3) without spin
    radius: np.ndarray              # (n,), m
    dynamic: np.ndarray             # (n,) bool: finite (real) mass


class Islands(NamedTuple):
    """The sleeping state, updated in place by ``settle_islands``."""

    asleep: np.ndarray              # (n,) bool
    representative: np.ndarray      # (n,) int64: each sleeper's island representative, -1 awake
    still_time: np.ndarray          # (n,) seconds each particle has stayed still


class WakeReach(NamedTuple):
    """How near two particles link (or wake): margin x radii sum + their travel in a step."""

    margin: float                   # share of the radii sum (CONTACT_MARGIN)
    dt: float                       # the step, s
    sag: float                      # |g| dt^2 / 2, m


class Stillness(NamedTuple):
    """When a particle is still and when a still island sleeps."""

    speed: float                    # speeds (and spin x radius) below this are still, m/s
    sleep_time: float               # an island sleeps once all stayed still this long, s


@njit(cache=True)
def _travel(velocity, p, dt, sag):
    """Return how far particle ``p`` can move in the next step, m (|v| dt + |g| dt^2 / 2)."""
    vx, vy, vz = velocity[p, 0], velocity[p, 1], velocity[p, 2]
    return math.sqrt(vx * vx + vy * vy + vz * vz) * dt + sag


@njit(cache=True, nogil=True)
def settle_islands(particles, islands, pair_first, pair_second, wake_reach, stillness):
    """Update timers and islands in place; return the mask of particles that fell asleep.

    Pairs link when their gap is at most ``wake_reach``: the margin times the
    radii sum plus both particles' travel in the next step, the reach at
    which an awake particle would wake a sleeping one; two sleeping
    particles link through their representatives. Sleeping particles'
    velocities are left to the caller (who books the kinetic energy before
    zeroing it).
    """
    position, velocity, radius = particles.position, particles.velocity, particles.radius
    angular, dynamic = particles.angular_velocity, particles.dynamic
    asleep, rep, still_time = islands.asleep, islands.representative, islands.still_time
    margin, dt, sag = wake_reach.margin, wake_reach.dt, wake_reach.sag
    n = position.shape[0]
    limit = stillness.speed * stillness.speed
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
    for k in range(pair_first.size):
        a, b = pair_first[k], pair_second[k]
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
            ra, rb = union_root(parent, a), union_root(parent, b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    for p in range(n):
        if asleep[p] and rep[p] >= 0:
            ra, rb = union_root(parent, p), union_root(parent, rep[p])
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    least = np.full(n, np.inf)
    awake = np.zeros(n, dtype=np.bool_)
    root = np.empty(n, dtype=np.int64)
    for p in range(n):
        if not dynamic[p]:
            continue
        c = union_root(parent, p)
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
        if least[c] >= stillness.sleep_time:
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
def near_sleepers(position, velocity, radius, awake, sleepers, candidate_awake,
                  candidate_sleeper, wake_reach):
    """Return the mask of candidate pairs (awake, sleeping) within waking reach.

    Candidate k pairs awake[candidate_awake[k]] with
    sleepers[candidate_sleeper[k]]; the reach is the radii sum times
    (1 + margin) plus the awake particle's travel in the step
    (``settle_islands`` links the same pairs).
    """
    margin, dt, sag = wake_reach.margin, wake_reach.dt, wake_reach.sag
    hit = np.zeros(candidate_awake.size, dtype=np.bool_)
    for k in range(candidate_awake.size):
        a, b = awake[candidate_awake[k]], sleepers[candidate_sleeper[k]]
        reach = (1.0 + margin) * (radius[a] + radius[b]) + _travel(velocity, a, dt, sag)
        dx = position[a, 0] - position[b, 0]
        dy = position[a, 1] - position[b, 1]
        dz = position[a, 2] - position[b, 2]
        hit[k] = dx * dx + dy * dy + dz * dz <= reach * reach
    return hit


@njit(cache=True, nogil=True)
def sleepers_within_reach(position, velocity, radius, awake, sleepers, wake_reach):
    """Return the mask of ``sleepers`` within waking reach of any of ``awake``.

    Every pair is tested with ``near_sleepers``' test (no tree), which for
    a few hundred particles costs less than building the tree's query.
    """
    margin, dt, sag = wake_reach.margin, wake_reach.dt, wake_reach.sag
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
    first, second = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    wake_reach = WakeReach(0.02, 0.01, 0.0)
    particles = IslandParticles(position, velocity, np.zeros((2, 3)), radius,
                                np.ones(2, dtype=bool))
    islands = Islands(np.zeros(2, dtype=bool), np.full(2, -1, dtype=np.int64), np.zeros(2))
    settle_islands(particles, islands, first, second, wake_reach, Stillness(0.1, 0.5))
    near_sleepers(position, velocity, radius, first, second, first, first, wake_reach)
    sleepers_within_reach(position, velocity, radius, first, second, wake_reach)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [settle_islands, near_sleepers, sleepers_within_reach]
