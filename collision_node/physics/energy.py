"""Mechanical energy of a particle state: kinetic (linear, rotational), potential.

Potential energy under uniform gravity g is U = -sum m g . x over the
dynamic particles (zero at the origin); static particles never move and
are left out. Rotational energy uses the solid sphere I = 2/5 m r^2 and
exists only when the scene simulates spin (friction declared).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .state import ParticleState

SPHERE_INERTIA = 0.4       # I = 0.4 m r^2 (solid sphere)


def kinetic_linear(state: ParticleState, index: Optional[np.ndarray] = None) -> float:
    """Sum of 1/2 m |v|^2 over the dynamic particles (of ``index`` if given), J."""
    w = state.inv_mass if index is None else state.inv_mass[index]
    v = state.velocity if index is None else state.velocity[index]
    dyn = w > 0.0
    return 0.5 * float(np.sum(np.einsum('ij,ij->i', v[dyn], v[dyn]) / w[dyn]))


def kinetic_rotational(state: ParticleState, index: Optional[np.ndarray] = None) -> float:
    """Sum of 1/2 I |w|^2 (I = 2/5 m r^2) over the dynamic particles, J."""
    if state.angular_velocity is None:
        return 0.0
    w = state.inv_mass if index is None else state.inv_mass[index]
    omega = state.angular_velocity if index is None else state.angular_velocity[index]
    r = state.radius if index is None else state.radius[index]
    dyn = w > 0.0
    inertia = SPHERE_INERTIA * r[dyn] ** 2 / w[dyn]
    return 0.5 * float(np.sum(inertia * np.einsum('ij,ij->i', omega[dyn], omega[dyn])))


def potential(state: ParticleState, gravity: Optional[np.ndarray],
              index: Optional[np.ndarray] = None) -> float:
    """Gravitational potential energy -sum m g . x of the dynamic particles, J."""
    if gravity is None:
        return 0.0
    w = state.inv_mass if index is None else state.inv_mass[index]
    x = state.position if index is None else state.position[index]
    dyn = w > 0.0
    return -float(np.sum((x[dyn] @ gravity) / w[dyn]))


def mechanical(state: ParticleState, gravity: Optional[np.ndarray],
               index: Optional[np.ndarray] = None) -> float:
    """Kinetic (linear + rotational) plus potential energy, J."""
    return (kinetic_linear(state, index) + kinetic_rotational(state, index)
            + potential(state, gravity, index))


def breakdown(state: ParticleState, gravity: Optional[np.ndarray]) -> dict:
    """Return the energy terms of a state as a JSON-ready mapping, J."""
    linear = kinetic_linear(state)
    rotational = kinetic_rotational(state)
    pot = potential(state, gravity)
    return {'kinetic_linear': linear, 'kinetic_rotational': rotational, 'potential': pot,
            'total': linear + rotational + pot}
