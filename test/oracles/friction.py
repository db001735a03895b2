"""Coulomb friction impulses between spheres (and against walls).

At a contact with unit normal N (from the other body into this one) the
contact points move relative to each other with
    u = v_i - v_j - (r_i w_i + r_j w_j) x N
(w: angular velocity). Its part u_t tangential to N is the slip. A
tangential impulse J (on i; -J on j) changes the slip by K J with
K = 7/2 (1/m_i + 1/m_j): 1/m from the linear part and r^2 / I = 5/2 (1/m)
from the spin of a solid sphere, I = 2/5 m r^2. Coulomb's law in impulse
form: the impulse that stops the slip, |u_t| / K, if it is within
mu * (normal impulse) (stick), otherwise mu * (normal impulse) against the
slip (slip). Each body's spin changes by the lecture's angular impulse
I (w+ - w-) = r x J. The kinetic energy removed is exactly
j_t |u_t| - K j_t^2 / 2 >= 0 for an impulse of magnitude j_t.
"""

from __future__ import annotations

import numpy as np

from collision_node.physics.model.energy import (  # noqa: F401
    SPHERE_INERTIA, SPIN_FACTOR, STICK_FACTOR)


def contact_slip(v_i: np.ndarray, v_j: np.ndarray, spin_i: np.ndarray, spin_j: np.ndarray,
                 normal: np.ndarray, planar: bool) -> np.ndarray:
    """Return the tangential relative velocity of the contact points.

    ``spin_i``/``spin_j`` are r * w of each side (zeros for a wall). In a
    2-D scene only in-plane slip counts, so the particles stay in x-y.
    """
    u = v_i - v_j - np.cross(spin_i + spin_j, normal)
    u_t = u - np.einsum('ij,ij->i', u, normal)[:, None] * normal
    if planar:
        u_t[:, 2] = 0.0
    return u_t


def friction_impulse(u_t: np.ndarray, w_sum: np.ndarray, normal_impulse: np.ndarray,
                     mu) -> tuple[np.ndarray, np.ndarray]:
    """Return (J on side i, kinetic energy removed per contact) for Coulomb friction."""
    slip = np.sqrt(np.einsum('ij,ij->i', u_t, u_t))
    k = STICK_FACTOR * w_sum
    sliding = slip > 0.0
    stick = np.divide(slip, k, out=np.zeros_like(slip), where=sliding & (k > 0.0))
    magnitude = np.minimum(stick, mu * normal_impulse)
    direction = np.divide(u_t, slip[:, None], out=np.zeros_like(u_t), where=sliding[:, None])
    impulse = -magnitude[:, None] * direction
    removed = magnitude * slip - 0.5 * k * magnitude ** 2
    return impulse, removed


def spin_change(inv_mass: np.ndarray, radius: np.ndarray, normal: np.ndarray,
                impulse: np.ndarray) -> np.ndarray:
    """Return dw = I^-1 (r x J) with r = -radius N, for the side the impulse acts on."""
    return -(SPIN_FACTOR * inv_mass / radius)[:, None] * np.cross(normal, impulse)


def apply_pair_friction(velocity: np.ndarray, angular: np.ndarray, inv_mass: np.ndarray,
                        radius: np.ndarray, i: np.ndarray, j: np.ndarray, normal: np.ndarray,
                        normal_impulse: np.ndarray, mu, planar: bool
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Apply friction to pairs that share no dynamic particle.

    Returns (tangential impulse magnitude, N s, and energy removed, J, per pair).
    """
    w_i, w_j = inv_mass[i], inv_mass[j]
    u_t = contact_slip(velocity[i], velocity[j], radius[i, None] * angular[i],
                       radius[j, None] * angular[j], normal, planar)
    impulse, removed = friction_impulse(u_t, w_i + w_j, normal_impulse, mu)
    np.add.at(velocity, i, w_i[:, None] * impulse)
    np.add.at(velocity, j, -w_j[:, None] * impulse)
    np.add.at(angular, i, spin_change(w_i, radius[i], normal, impulse))
    # Side j feels -J at r_j = +radius_j N: the same sign of spin change.
    np.add.at(angular, j, spin_change(w_j, radius[j], normal, impulse))
    return np.sqrt(np.einsum('ij,ij->i', impulse, impulse)), removed


def apply_wall_friction(velocity: np.ndarray, angular: np.ndarray, inv_mass: np.ndarray,
                        radius: np.ndarray, index: np.ndarray, normal: np.ndarray,
                        normal_impulse: np.ndarray, mu, planar: bool
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Apply friction against a static wall (distinct ``index``).

    Returns (tangential impulse magnitude, N s, and energy removed, J, per particle).
    """
    w, r = inv_mass[index], radius[index]
    still = np.zeros_like(normal)
    u_t = contact_slip(velocity[index], still, r[:, None] * angular[index], still, normal,
                       planar)
    impulse, removed = friction_impulse(u_t, w, normal_impulse, mu)
    velocity[index] += w[:, None] * impulse
    angular[index] += spin_change(w, r, normal, impulse)
    return np.sqrt(np.einsum('ij,ij->i', impulse, impulse)), removed
