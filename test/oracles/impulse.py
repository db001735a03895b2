"""The impulse along the line of action, written with inverse masses.

For a pair with unit normal N (from 2 to 1), closing speed
vn = (v1 - v2) . N < 0 and coefficient of restitution e, the impulse
magnitude is j = -(1 + e) vn / (w1 + w2), with w = 1/m, and
v1 += j w1 N, v2 -= j w2 N. With e = 1 this is the lecture's
v1+ = ((m1 - m2) v1- + 2 m2 v2-) / (m1 + m2) (and its mirror for v2),
rearranged so that an infinite mass is w = 0 instead of inf/inf, and a
mass ratio of 1e12 loses no precision (no difference of large masses).
"""

from __future__ import annotations

import numpy as np


def closing_speed(velocity: np.ndarray, i: np.ndarray, j: np.ndarray,
                  normal: np.ndarray) -> np.ndarray:
    """Return (v_i - v_j) . N per pair; negative means approaching."""
    return np.einsum('ij,ij->i', velocity[i] - velocity[j], normal)


def apply_normal_impulses(velocity: np.ndarray, inv_mass: np.ndarray, i: np.ndarray,
                          j: np.ndarray, normal: np.ndarray, restitution,
                          scale=1.0) -> np.ndarray:
    """Apply impulses to approaching pairs in place; return the mask of those hit.

    Pairs must not share a dynamic particle (one colour of the contact
    graph) unless ``scale`` shares the impulse out, as the batched fallback
    does; updates go through ``np.add.at`` so shared static particles and
    scaled batches stay correct.
    """
    vn = closing_speed(velocity, i, j, normal)
    approaching = vn < 0.0
    if not np.any(approaching):
        return approaching
    w_i, w_j = inv_mass[i], inv_mass[j]
    magnitude = np.where(approaching, -(1.0 + restitution) * vn / (w_i + w_j), 0.0) * scale
    np.add.at(velocity, i, (magnitude * w_i)[:, None] * normal)
    np.add.at(velocity, j, -(magnitude * w_j)[:, None] * normal)
    return approaching


def apply_normal_impulses_booked(velocity: np.ndarray, inv_mass: np.ndarray, i: np.ndarray,
                                 j: np.ndarray, normal: np.ndarray, restitution,
                                 tolerance: float = 0.0
                                 ) -> tuple[np.ndarray, np.ndarray, float]:
    """Like :func:`apply_normal_impulses`, also returning magnitudes and energy removed.

    Pairs closing slower than ``tolerance`` count as not approaching, so
    repeated sweeps stop on rounding-level residues. Pairs in one call
    share no dynamic particle, so the kinetic energy removed is exact per
    pair, j |vn| (1 - e) / 2 >= 0: no application ever adds energy.
    Returns (mask of pairs hit, impulse magnitudes, energy removed in J).
    """
    vn = closing_speed(velocity, i, j, normal)
    approaching = vn < -tolerance
    if not np.any(approaching):
        return approaching, np.zeros_like(vn), 0.0
    w_i, w_j = inv_mass[i], inv_mass[j]
    magnitude = np.where(approaching, -(1.0 + restitution) * vn / (w_i + w_j), 0.0)
    np.add.at(velocity, i, (magnitude * w_i)[:, None] * normal)
    np.add.at(velocity, j, -(magnitude * w_j)[:, None] * normal)
    removed = 0.5 * float(np.sum(magnitude * -vn * (1.0 - restitution)))
    return approaching, magnitude, removed
