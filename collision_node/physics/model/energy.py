"""Mechanical energy of a particle state: kinetic (linear, rotational), potential.

Potential energy under uniform gravity g is U = -sum m g . (x - x_ref)
over the dynamic particles, measured from a reference point x_ref: the
point of a grid of ``REFERENCE_GRID`` (1024 m) nearest the scene's
initial centre of mass (``reference_point``). For a scene within 512 m of
the origin that is the origin itself (U = -sum m g . x, as always); a
scene 1e9 m away gets a point within 512 m of it, exactly
representable, so x - x_ref is exact and its potential energies keep
their digits instead of being 1e10 J totals whose changes are rounding.
Static particles never move and are left out. Changes of potential
energy that stages book are the per-particle work -m g . dx of each
displacement (``lift``), never differences of totals. Rotational energy
uses the solid sphere I = 2/5 m r^2 (``SPHERE_INERTIA``, the one place the
inertia is defined) and exists only when the scene simulates spin
(friction declared). Every kinetic energy in the package is computed here.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .state import ParticleState
from ..step.step_kernels import finish_lift

SPHERE_INERTIA = 0.4       # I = 0.4 m r^2 (solid sphere)
# r^2 m / I of a solid sphere (2.5), so dw = -(2.5 / (m r)) N x J, and the
# slip a unit tangential impulse stops per 1/m: 1 + r^2 m / I (3.5).
SPIN_FACTOR = 1.0 / SPHERE_INERTIA
STICK_FACTOR = 1.0 + SPIN_FACTOR
# Spacing of the points potential energy may be measured from, m: a power of
# two, so every point is exact and x - point is exact near it.
REFERENCE_GRID = 1024.0


def kinetic_linear(state: ParticleState, index: Optional[np.ndarray] = None) -> float:
    """Sum of 1/2 m |v|^2 over the dynamic particles (of ``index`` if given), J."""
    w = state.inv_mass if index is None else state.inv_mass[index]
    v = state.velocity if index is None else state.velocity[index]
    dyn = w > 0.0
    mass = 1.0 / w[dyn]
    return 0.5 * float(np.sum(mass * np.einsum('ij,ij->i', v[dyn], v[dyn])))


def kinetic_rotational(state: ParticleState, index: Optional[np.ndarray] = None) -> float:
    """Sum of 1/2 I |w|^2 (I = 2/5 m r^2) over the dynamic particles, J."""
    if state.angular_velocity is None:
        return 0.0
    w = state.inv_mass if index is None else state.inv_mass[index]
    omega = state.angular_velocity if index is None else state.angular_velocity[index]
    r = state.radius if index is None else state.radius[index]
    dyn = w > 0.0
    inertia = SPHERE_INERTIA * (1.0 / w[dyn]) * r[dyn] ** 2
    return 0.5 * float(np.sum(inertia * np.einsum('ij,ij->i', omega[dyn], omega[dyn])))


def potential(state: ParticleState, gravity: Optional[np.ndarray],
              index: Optional[np.ndarray] = None,
              reference: Optional[np.ndarray] = None) -> float:
    """Potential energy -sum m g . (x - reference) of the dynamic particles, J.

    ``reference`` defaults to the origin.
    """
    if gravity is None:
        return 0.0
    w = state.inv_mass if index is None else state.inv_mass[index]
    x = state.position if index is None else state.position[index]
    dyn = w > 0.0
    x = x[dyn] if reference is None else x[dyn] - reference
    return -float(np.sum((x @ gravity) / w[dyn]))


def lift(inv_mass: np.ndarray, displacement: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """Return the potential energy each displacement adds, -m g . dx, J (0 if static)."""
    work = displacement @ gravity
    if work.dtype == np.float64 and work.ndim == 1 and inv_mass.dtype == np.float64 \
            and inv_mass.shape == work.shape:
        # One compiled pass over the masks' np.where (the same quotient).
        finish_lift(work, inv_mass)
        return work
    dyn = inv_mass > 0.0
    return np.where(dyn, -work / np.where(dyn, inv_mass, 1.0), 0.0)


def reference_point(state: ParticleState) -> np.ndarray:
    """Return the point potential energy is measured from (see the module doc).

    The point of the ``REFERENCE_GRID`` grid nearest the dynamic particles'
    centre of mass; the origin when there is none (then every potential is
    0 whatever the point).
    """
    dyn = state.dynamic
    if not dyn.any():
        return np.zeros(3)
    mass = 1.0 / state.inv_mass[dyn]
    x = state.position[dyn]
    # Mass-weighted mean about the first particle, so the sum keeps its digits.
    origin = x[0]
    centre = origin + (mass @ (x - origin)) / float(mass.sum())
    return np.round(centre / REFERENCE_GRID) * REFERENCE_GRID


def mechanical(state: ParticleState, gravity: Optional[np.ndarray],
               index: Optional[np.ndarray] = None,
               reference: Optional[np.ndarray] = None) -> float:
    """Kinetic (linear + rotational) plus potential energy, J."""
    return (kinetic_linear(state, index) + kinetic_rotational(state, index)
            + potential(state, gravity, index, reference))


def breakdown(state: ParticleState, gravity: Optional[np.ndarray],
              reference: Optional[np.ndarray] = None) -> dict:
    """Return the energy terms of a state as a JSON-ready mapping, J."""
    linear = kinetic_linear(state)
    rotational = kinetic_rotational(state)
    pot = potential(state, gravity, reference=reference)
    return {'kinetic_linear': linear, 'kinetic_rotational': rotational, 'potential': pot,
            'total': linear + rotational + pot}
