"""Small per-step loops, compiled: what a step does around its big kernels.

With a few hundred particles a step costs a few hundred microseconds, so a
chain of small numpy calls (each allocating its result) around a stage
costs as much as the stage's work. These loops replace such chains in the
step's framework and the motion stages, with the same floating-point
operations in the same order as the numpy statements they replace:

- ``apply_gravity``: x += g dt^2 / 2, v += g dt for the dynamic particles
  (``stages.motion.gravity``);
- ``rotate_orientations``: the spin stage's quaternion update in place;
- ``all_finite``: the world's check that no position or velocity became
  NaN or inf (``all_finite_shared``: the same check on the threads);
- ``drift_shared``: the drift stage's x += v dt on the threads, for large
  worlds;
- ``add_losses`` and ``add_pair_losses``: ``StepContext.book``'s per-particle
  attribution, the same sequential additions as ``np.add.at``;
- ``finish_lift``: ``energy.lift``'s quotient -m g . dx without its masks;
- ``union_root``: the union-find of the separation and sleeping kernels.

``ParticleArrays`` is the record of the state's arrays that the contact
stages' kernels take (``particle_arrays`` builds it once per call).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from . import numba_cache  # noqa: F401,I100 (chooses numba's cache directory first)
from numba import njit, prange  # noqa: E402,I100 (after the cache directory is chosen)


class ParticleArrays(NamedTuple):
    """The particle arrays a contact kernel reads, contiguous float64, one row per particle."""

    position: np.ndarray        # (n, 3), m
    velocity: np.ndarray        # (n, 3), m/s
    radius: np.ndarray          # (n,), m
    inv_mass: np.ndarray        # (n,), 1/kg (0: static)


def float_rows(a: np.ndarray) -> bool:
    """Say whether ``a`` is a C-contiguous float64 array of 3-vectors (what the kernels take)."""
    return a.dtype == np.float64 and a.ndim == 2 and a.shape[1] == 3 and a.flags.c_contiguous


def particle_arrays(state) -> ParticleArrays:
    """Return ``state``'s arrays as a ``ParticleArrays`` (copies only where not contiguous)."""
    return ParticleArrays(np.ascontiguousarray(state.position, dtype=np.float64),
                          np.ascontiguousarray(state.velocity, dtype=np.float64),
                          np.ascontiguousarray(state.radius, dtype=np.float64),
                          np.ascontiguousarray(state.inv_mass, dtype=np.float64))


@njit(cache=True, nogil=True)
def apply_gravity(position, velocity, inv_mass, shift, kick):
    """Add ``shift`` to positions and ``kick`` to velocities of particles with inv_mass > 0."""
    for p in range(position.shape[0]):
        if inv_mass[p] > 0.0:
            for d in range(3):
                position[p, d] += shift[d]
                velocity[p, d] += kick[d]


@njit(cache=True, nogil=True)
def rotate_orientations(orientation, angular_velocity, dt):
    """Rotate quaternions [x, y, z, w] in place by angular_velocity * dt."""
    for p in range(orientation.shape[0]):
        wx, wy, wz = angular_velocity[p, 0], angular_velocity[p, 1], angular_velocity[p, 2]
        rate = math.sqrt(wx * wx + wy * wy + wz * wz)
        half = 0.5 * rate * dt
        # sin(|w| dt / 2) / |w|, with its limit dt / 2 at rest.
        factor = math.sin(half) / rate if rate > 0.0 else 0.5 * dt
        ax, ay, az = factor * wx, factor * wy, factor * wz
        dw = math.cos(half)
        qx, qy, qz, qw = (orientation[p, 0], orientation[p, 1], orientation[p, 2],
                          orientation[p, 3])
        # dw qv + qw dv + dv x qv, and dw qw - dv . qv (np.cross's order of terms).
        ox = dw * qx + qw * ax + (ay * qz - az * qy)
        oy = dw * qy + qw * ay + (az * qx - ax * qz)
        oz = dw * qz + qw * az + (ax * qy - ay * qx)
        ow = dw * qw - (ax * qx + ay * qy + az * qz)
        norm = math.sqrt(ox * ox + oy * oy + oz * oz + ow * ow)
        orientation[p, 0] = ox / norm
        orientation[p, 1] = oy / norm
        orientation[p, 2] = oz / norm
        orientation[p, 3] = ow / norm


@njit(cache=True)
def _finite(a):
    """Return whether every entry of the 2-D array ``a`` is finite."""
    for p in range(a.shape[0]):
        for d in range(a.shape[1]):
            if not math.isfinite(a[p, d]):
                return False
    return True


@njit(cache=True, nogil=True)
def all_finite(position, velocity, angular):
    """Return whether every entry of the three arrays is finite (``angular`` may be empty)."""
    return _finite(position) and _finite(velocity) and _finite(angular)


@njit(cache=True, nogil=True, parallel=True)
def all_finite_shared(position, velocity, angular):
    """Return ``all_finite``'s answer, rows checked on the threads (a count: any order)."""
    bad = 0
    for p in prange(position.shape[0]):
        for d in range(3):
            if not (math.isfinite(position[p, d]) and math.isfinite(velocity[p, d])):
                bad += 1
    for p in prange(angular.shape[0]):
        for d in range(3):
            if not math.isfinite(angular[p, d]):
                bad += 1
    return bad == 0


@njit(cache=True, nogil=True, parallel=True)
def drift_shared(position, velocity, dt):
    """Add velocity * dt to position in place, rows on the threads (numpy's two roundings)."""
    for p in prange(position.shape[0]):
        for d in range(position.shape[1]):
            position[p, d] += velocity[p, d] * dt


@njit(cache=True, nogil=True)
def add_losses(losses, i, removed):
    """``np.add.at(losses, i, removed)``: the same additions in the same order."""
    for k in range(i.size):
        losses[i[k]] += removed[k]


@njit(cache=True, nogil=True)
def add_pair_losses(losses, inv_mass, i, j, removed):
    """Attribute each pair's ``removed`` to i and j by inverse-mass share, as ``book`` does.

    The i shares are added first, in contact order, then the j shares: the
    additions of ``np.add.at`` on ``removed * share_i`` and then on
    ``removed * (1 - share_i)``.
    """
    m = i.size
    for k in range(m):
        w_i = inv_mass[i[k]]
        losses[i[k]] += removed[k] * (w_i / (w_i + inv_mass[j[k]]))
    for k in range(m):
        w_i = inv_mass[i[k]]
        losses[j[k]] += removed[k] * (1.0 - w_i / (w_i + inv_mass[j[k]]))


@njit(cache=True, nogil=True)
def finish_lift(work, inv_mass):
    """Turn ``work`` = dx . g into -m g . dx in place (0 where inv_mass is 0), ``energy.lift``."""
    for p in range(work.size):
        work[p] = -work[p] / inv_mass[p] if inv_mass[p] > 0.0 else 0.0


@njit(cache=True)
def union_root(parent, p):
    """Return the root of ``p`` in a union-find forest, halving the path on the way."""
    while parent[p] != p:
        parent[p] = parent[parent[p]]
        p = parent[p]
    return p


# The support level of a particle that no contact chain links to a support.
UNSUPPORTED = np.iinfo(np.int64).max


@njit(cache=True)
def incident(n, first, second):
    """Return (start, contact): the pairs of particle p are contact[start[p]:start[p + 1]]."""
    m = first.size
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(m):
        start[first[k] + 1] += 1
        start[second[k] + 1] += 1
    for p in range(n):
        start[p + 1] += start[p]
    fill = start[:n].copy()
    contact = np.empty(2 * m, dtype=np.int64)
    for k in range(m):
        contact[fill[first[k]]] = k
        fill[first[k]] += 1
        contact[fill[second[k]]] = k
        fill[second[k]] += 1
    return start, contact


@njit(cache=True)
def spread_levels(level, first, second):
    """Fill ``level`` in place: each particle's distance in contacts from a level-0 one.

    ``level`` holds 0 at the supports and UNSUPPORTED elsewhere; breadth
    first over the pairs (``first``, ``second``), a particle in contact
    with a level-k one becomes at most level k + 1. Shortest distances, so
    the result does not depend on the pairs' order.
    """
    n = level.size
    queue = np.empty(n, dtype=np.int64)
    tail = 0
    for p in range(n):
        if level[p] == 0:
            queue[tail] = p
            tail += 1
    start, contact = incident(n, first, second)
    head = 0
    while head < tail:
        p = queue[head]
        head += 1
        for s in range(start[p], start[p + 1]):
            k = contact[s]
            q = second[k] if first[k] == p else first[k]
            if level[q] == UNSUPPORTED:
                level[q] = level[p] + 1
                queue[tail] = q
                tail += 1


def warm_up() -> None:
    """Call each kernel once on a tiny problem (compiles or loads from the cache)."""
    position, velocity = np.zeros((2, 3)), np.ones((2, 3))
    inv_mass = np.array([1.0, 0.0])
    apply_gravity(position, velocity, inv_mass, np.zeros(3), np.zeros(3))
    rotate_orientations(np.array([[0.0, 0.0, 0.0, 1.0]] * 2), velocity, 0.01)
    all_finite(position, velocity, np.zeros((0, 3)))
    all_finite(position, velocity, velocity)
    all_finite_shared(position, velocity, np.zeros((0, 3)))
    all_finite_shared(position, velocity, velocity)
    drift_shared(position.copy(), velocity, 0.01)
    pair = np.array([0], dtype=np.int64), np.array([1], dtype=np.int64)
    add_losses(np.zeros(2), pair[0], np.ones(1))
    add_pair_losses(np.zeros(2), inv_mass, pair[0], pair[1], np.ones(1))
    finish_lift(np.ones(2), inv_mass)


def kernels() -> list:
    """Return the compiled kernels of this module (for ``kernels.prepare``)."""
    return [apply_gravity, rotate_orientations, all_finite, all_finite_shared, drift_shared,
            add_losses, add_pair_losses, finish_lift]
