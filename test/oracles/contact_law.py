"""The contact law vectorised over contacts with numpy: the oracle of the compiled law.

The package applies the law through ``collision_node/physics/law/primitives.py``
(compiled, one contact at a time); the tests hold it against this statement of
the same law for pairs and particle-wall contacts:

- **Combine rule** (restitution and friction alike): each side of a
  contact brings a coefficient, the contact uses their geometric mean
  sqrt(c_i c_j); a particle without its own value (NaN, or no per-particle
  array at all) brings the contact's default: the scene's value at a
  particle pair, the walls' restitution (and the scene's friction) at a
  wall. A wall brings the default, so a particle of e_p at a wall of e_w
  gets sqrt(e_p e_w).
- **Restitution threshold**: a contact closing slower than the threshold
  is perfectly inelastic (e = 0); ``thresholded``.
- **Normal impulse** (the lecture's, with inverse masses,
  ``impulse.py``): j = (1 + e) v_close / (w_i + w_j) along the line of
  action; a wall is the other side with w = 0.
- **Coulomb friction with spin** (``friction.py``): bounded by mu j.
- **Wall reflection** on the step's path (``reflect_on_plane``).
- **Energy** each impulse removes, from the impulse itself: an impact
  removes (1 - e^2)/2 m_red v_close^2 = j v_close (1 - e) / 2; friction its
  own work (``friction.friction_impulse``); impulses that share a particle
  (batched sweeps, dense-cluster leftovers, shock passes) their exact work
  per particle, v . P + w |P|^2 / 2 (``apply_impulses``). Never a
  difference of world totals, so a loss is exact also far from the origin.
- **Impacts**: ``record_pairs`` / ``record_walls`` (``model/impacts.py``) append what the law
  resolved to the step's impact log, and do nothing without one.

Everything here is vectorised over contacts. The compiled kernels write the same
formulas in the same order of floating-point operations, and
``test/test_contact_kernels.py`` asserts both give identical velocities and
bookings on the same contacts.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from oracles.friction import apply_pair_friction, apply_wall_friction  # noqa: F401 (the law's)
from collision_node.physics.model.impacts import (  # noqa: F401
    contact_points, record_pairs, record_walls)
from oracles.impulse import closing_speed


def combine(own_i: Optional[np.ndarray], own_j: Optional[np.ndarray], default):
    """Geometric-mean combine rule for per-particle coefficients.

    ``own_i``/``own_j`` are the per-contact values of each side (NaN where a
    particle has none) or None when no particle has one (a wall is None);
    ``default`` is the contact's value. Returns ``default`` itself when
    neither side has one.
    """
    if own_i is None and own_j is None:
        return default
    missing_i = True if own_i is None else np.isnan(own_i)
    missing_j = True if own_j is None else np.isnan(own_j)
    a = default if own_i is None else np.where(missing_i, default, own_i)
    b = default if own_j is None else np.where(missing_j, default, own_j)
    # Exactly the default (not sqrt(d * d)) where neither side has a value.
    return np.where(missing_i & missing_j, default, np.sqrt(a * b))


def pair_coefficient(own: Optional[np.ndarray], i: np.ndarray, j: np.ndarray, default):
    """Return the coefficient of pairs (i, j): scalar ``default`` or one per pair."""
    if own is None:
        return default
    return combine(own[i], own[j], default)


def wall_coefficient(own: Optional[np.ndarray], index: np.ndarray, default):
    """Return the coefficient of particles ``index`` at a wall of value ``default``."""
    if own is None:
        return default
    return combine(own[index], None, default)


def thresholded(restitution, approach: np.ndarray, threshold: float):
    """Return e, set to 0 where the approach speed (> 0: closing) is below the threshold."""
    if not threshold > 0.0:
        return restitution
    return np.where(approach < threshold, 0.0, restitution)


def impact_loss(magnitude, approach, restitution):
    """Energy an impulse of ``magnitude`` removes from a contact closing at ``approach``.

    j v (1 - e) / 2 with j = (1 + e) v m_red: (1 - e^2)/2 m_red v^2 >= 0.
    """
    return 0.5 * magnitude * approach * (1.0 - restitution)


class PairImpulses:
    """What one application of the law to a set of pairs did (one row per pair)."""

    def __init__(self, hit: np.ndarray, magnitude: np.ndarray, approach: np.ndarray,
                 removed: Optional[np.ndarray], removed_at: Optional[np.ndarray] = None,
                 particles: Optional[np.ndarray] = None) -> None:
        """Keep the mask hit, magnitudes (N s), approach speeds and energy removed."""
        self.hit, self.magnitude, self.approach = hit, magnitude, approach
        # Per pair (unshared pairs), or per particle of ``particles`` (shared).
        self.removed, self.removed_at, self.particles = removed, removed_at, particles

    @property
    def total_removed(self) -> float:
        """Energy removed by the whole application, J."""
        values = self.removed if self.removed is not None else self.removed_at
        return float(values.sum()) if values is not None and values.size else 0.0


def apply_pair_impulses(velocity: np.ndarray, inv_mass: np.ndarray, i: np.ndarray,
                        j: np.ndarray, normal: np.ndarray, restitution,
                        tolerance: float = 0.0, scale=None) -> PairImpulses:
    """Apply the normal impulse to pairs closing faster than ``tolerance``, in place.

    Pairs must share no dynamic particle unless ``scale`` (per pair, <= 1)
    shares the impulses out; then the energy is the exact work of the
    summed impulses per particle (``apply_impulses``), else per pair.
    """
    approach = -closing_speed(velocity, i, j, normal)
    hit = approach > tolerance
    if not hit.any():
        zero = np.zeros_like(approach)
        return PairImpulses(hit, zero, approach, zero if scale is None else None,
                            None if scale is None else np.zeros(0),
                            None if scale is None else np.zeros(0, dtype=np.int64))
    w_i, w_j = inv_mass[i], inv_mass[j]
    magnitude = np.where(hit, (1.0 + restitution) * approach / (w_i + w_j), 0.0)
    if scale is not None:
        magnitude = magnitude * scale
        impulse = magnitude[:, None] * normal
        particles, removed_at = apply_impulses(velocity, inv_mass,
                                               np.concatenate([i[hit], j[hit]]),
                                               np.concatenate([impulse[hit], -impulse[hit]]))
        return PairImpulses(hit, magnitude, approach, None, removed_at, particles)
    np.add.at(velocity, i, (magnitude * w_i)[:, None] * normal)
    np.add.at(velocity, j, -(magnitude * w_j)[:, None] * normal)
    removed = np.where(hit, impact_loss(magnitude, approach, restitution), 0.0)
    return PairImpulses(hit, magnitude, approach, removed)


def apply_impulses(velocity: np.ndarray, inv_mass: np.ndarray, index: np.ndarray,
                   impulse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply impulse vectors to particles ``index`` (may repeat) in place.

    Returns (the distinct particles, the kinetic energy each lost, J): the
    exact work of its summed impulse P, -(v . P + w |P|^2 / 2), computed
    from the impulses rather than as a difference of energies.
    """
    particles, where = np.unique(index, return_inverse=True)
    total = np.zeros((particles.size, 3))
    np.add.at(total, where.ravel(), impulse)
    w = inv_mass[particles]
    dyn = w > 0.0
    v = velocity[particles]
    removed = -np.where(dyn, np.einsum('ij,ij->i', v, total)
                        + 0.5 * w * np.einsum('ij,ij->i', total, total), 0.0)
    velocity[particles] += w[:, None] * total
    return particles, removed


def apply_wall_impulses(velocity: np.ndarray, inv_mass: np.ndarray, index: np.ndarray,
                        axis: int, inward: float, restitution, tolerance: float = 0.0
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Apply the normal impulse of a static plane to particles ``index`` (distinct).

    The wall is the pair's other side with w = 0. Returns (mask hit,
    magnitudes N s, approach speeds, energy removed per particle J).
    """
    approach = -inward * velocity[index, axis]
    hit = approach > tolerance
    change = np.where(hit, (1.0 + restitution) * approach, 0.0)
    velocity[index, axis] += inward * change
    magnitude = change / inv_mass[index]
    removed = np.where(hit, impact_loss(magnitude, approach, restitution), 0.0)
    return hit, magnitude, approach, removed


def reflect_on_plane(q1: np.ndarray, u1: np.ndarray, g_n: float, dt: float,
                     restitution, threshold: float) -> dict:
    """Reflect particles found past a plane at the end of a step, on the step's path.

    ``q1`` (< 0) is how far each particle is past the plane and ``u1``
    (< 0) its velocity along the inward normal at the end of the step;
    ``g_n`` is gravity along that normal. The time of impact solves
    q1 - u1 t + g_n t^2 / 2 = 0 backwards from the step end; where that is
    not on the step (pushed in, started inside) the impact is at the step
    end. Returns a mapping of arrays: ``gap`` and ``velocity`` along the
    normal at the step end, ``impact`` (approach speed at impact, > 0),
    ``restitution`` used, ``back`` (time from impact to step end), and the
    energy booked per particle: ``impact_loss`` (the law's) and
    ``settle_loss`` (a reflected particle back inside the plane before the
    step ends rests on it; an impact off the path is lifted onto the plane,
    a negative loss). All energies are relative to the plane, so they are
    exact far from the origin.
    """
    # Smallest t >= 0 with q1 - u1 t + g_n t^2 / 2 = 0, in the form without
    # cancellation (u1 - sqrt(D) adds two negative numbers).
    disc = u1 * u1 - 2.0 * g_n * q1
    real = disc >= 0.0
    denominator = u1 - np.sqrt(np.where(real, disc, 0.0))
    back = np.where(real & (denominator < 0.0),
                    2.0 * q1 / np.where(denominator < 0.0, denominator, -1.0), np.inf)
    on_path = back <= dt
    back = np.where(on_path, back, 0.0)
    approach = -(u1 - g_n * back)
    e = thresholded(restitution, approach, threshold)
    out = e * approach
    gap = np.where(on_path, out * back + 0.5 * g_n * back * back, 0.0)
    velocity = out + g_n * back
    resting = gap < 0.0
    # Per unit mass: what resting on the plane removes (the rebound's energy
    # relative to the plane, conserved along the path), and the lift onto
    # the plane of an impact off the path, -g_n q1 (energy added: a negative
    # loss; the potential energy along the normal is -m g_n q).
    settle = np.where(resting, 0.5 * out * out, 0.0) + np.where(on_path, 0.0, -g_n * q1)
    return {'gap': np.where(resting, 0.0, gap), 'velocity': np.where(resting, 0.0, velocity),
            'impact': approach, 'restitution': e, 'back': back,
            'impact_loss_per_mass': 0.5 * (1.0 + e) * (1.0 - e) * approach * approach,
            'settle_loss_per_mass': settle}
