"""Contact solve: impulses along the line of action, one colour at a time.

Sweeps the colour batches of the contact graph in order (Gauss-Seidel)
until no contact approaches or the iteration budget is spent. Each
impulse only changes the velocity component along N, exactly as the
lecture's velocity update.

With e < 1, per-particle restitution, a restitution threshold or friction
the solve books the energy it removes, per effect ('restitution',
'friction'), from the exact per-pair formulas. Friction (see
``collision_node.friction``) is applied to a pair right after its normal
impulse in the same colour batch, bounded by mu times that normal
impulse, so pairs sharing a particle stay sequential. The dense-cluster
fallback (pairs past ``MAX_BATCHES`` colours) is frictionless.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..coloring import color_pairs
from ..effects import combine
from ..energy import kinetic_linear
from ..friction import apply_pair_friction
from ..impulse import apply_normal_impulses, apply_normal_impulses_dissipative
from ..pipeline import Stage, StepContext

# Past this many colours (only in very dense clusters, e.g. a thousand
# particles spawned on one point) the remaining pairs share their impulses
# out, each scaled by 1 / (contacts of its busiest particle): stable and
# never energy-adding, at the price of the order-dependent exactness that
# such a cluster does not have anyway.
MAX_BATCHES = 256


class SequentialImpulseStage(Stage):
    """Resolve approaching contacts with restitution, colour by colour."""

    name = 'contact_impulses'

    def __init__(self, restitution: float, iterations: int,
                 friction: Optional[float] = None) -> None:
        """Keep the particle-particle restitution, the sweep budget and friction mu.

        The restitution threshold comes from the step's effects
        (``Effects.threshold(dt)``), since its default depends on dt.
        """
        self.restitution = restitution
        self.iterations = iterations
        self.friction = friction

    def run(self, ctx: StepContext) -> None:
        """Apply impulses in place and count the contacts that received one."""
        contacts = ctx.contacts
        if contacts is None or len(contacts) == 0:
            return
        threshold = ctx.effects.threshold(ctx.dt)
        if threshold > 0.0 or self.friction is not None or ctx.state.restitution is not None:
            self._run_dissipative(ctx, threshold)
            return
        state = ctx.state
        i, j, normal = contacts.i, contacts.j, contacts.normal
        batches, leftover = color_pairs(i, j, state.dynamic, MAX_BATCHES)
        leftover_scale = None
        if leftover.size:
            busiest = np.maximum(np.bincount(i[leftover], minlength=len(state)),
                                 np.bincount(j[leftover], minlength=len(state)))
            leftover_scale = 1.0 / np.maximum(busiest[i[leftover]], busiest[j[leftover]])
        track_energy = self.restitution < 1.0
        if track_energy:
            touched = np.unique(np.concatenate([i, j]))
            energy_before = self._energy(state, touched)
        hit = np.zeros(len(contacts), dtype=bool)
        for _ in range(self.iterations):
            applied = False
            for batch in batches:
                mask = apply_normal_impulses(state.velocity, state.inv_mass, i[batch],
                                             j[batch], normal[batch], self.restitution)
                if mask.any():
                    hit[batch[mask]] = True
                    applied = True
            if leftover.size:
                mask = apply_normal_impulses(state.velocity, state.inv_mass, i[leftover],
                                             j[leftover], normal[leftover], self.restitution,
                                             scale=leftover_scale)
                if mask.any():
                    hit[leftover[mask]] = True
                    applied = True
            if not applied:
                break
        ctx.stats.collisions += int(hit.sum())
        if track_energy:
            ctx.stats.add_dissipated('restitution',
                                     energy_before - self._energy(state, touched))

    def _run_dissipative(self, ctx: StepContext, threshold: float) -> None:
        """Solve with per-pair restitution, the threshold and friction; book losses."""
        state, contacts = ctx.state, ctx.contacts
        i, j, normal = contacts.i, contacts.j, contacts.normal
        own = state.restitution
        restitution = combine(None if own is None else own[i],
                              None if own is None else own[j], self.restitution)
        per_pair = np.ndim(restitution) > 0
        mu = None
        if self.friction is not None:
            own_mu = state.friction
            mu = combine(None if own_mu is None else own_mu[i],
                         None if own_mu is None else own_mu[j], self.friction)
        mu_per_pair = np.ndim(mu) > 0
        planar = ctx.dimensions == 2
        batches, leftover = color_pairs(i, j, state.dynamic, MAX_BATCHES)
        hit = np.zeros(len(contacts), dtype=bool)
        lost_normal = lost_friction = 0.0
        for _ in range(self.iterations):
            applied = False
            for batch in batches:
                bi, bj, bn = i[batch], j[batch], normal[batch]
                e = restitution[batch] if per_pair else restitution
                mask, magnitude, removed = apply_normal_impulses_dissipative(
                    state.velocity, state.inv_mass, bi, bj, bn, e, threshold)
                if not mask.any():
                    continue
                hit[batch[mask]] = True
                applied = True
                lost_normal += removed
                if mu is not None:
                    lost_friction += apply_pair_friction(
                        state.velocity, state.angular_velocity, state.inv_mass, state.radius,
                        bi[mask], bj[mask], bn[mask], magnitude[mask],
                        mu[batch][mask] if mu_per_pair else mu, planar)
            if leftover.size:
                touched = np.unique(np.concatenate([i[leftover], j[leftover]]))
                before = kinetic_linear(state, touched)
                e = restitution[leftover] if per_pair else restitution
                mask = apply_normal_impulses(state.velocity, state.inv_mass, i[leftover],
                                             j[leftover], normal[leftover], e,
                                             scale=self._leftover_scale(state, i, j, leftover))
                if mask.any():
                    hit[leftover[mask]] = True
                    applied = True
                    lost_normal += before - kinetic_linear(state, touched)
            if not applied:
                break
        ctx.stats.collisions += int(hit.sum())
        ctx.stats.add_dissipated('restitution', lost_normal)
        if mu is not None:
            ctx.stats.add_dissipated('friction', lost_friction)

    @staticmethod
    def _leftover_scale(state, i: np.ndarray, j: np.ndarray, leftover: np.ndarray
                        ) -> np.ndarray:
        """Share out the impulses of pairs past the colour budget (see MAX_BATCHES)."""
        busiest = np.maximum(np.bincount(i[leftover], minlength=len(state)),
                             np.bincount(j[leftover], minlength=len(state)))
        return 1.0 / np.maximum(busiest[i[leftover]], busiest[j[leftover]])

    @staticmethod
    def _energy(state, index: np.ndarray) -> float:
        """Linear kinetic energy of the particles in ``index``."""
        dyn = index[state.inv_mass[index] > 0.0]
        v = state.velocity[dyn]
        return 0.5 * float(np.sum(np.einsum('ij,ij->i', v, v) / state.inv_mass[dyn]))

    def describe(self) -> str:
        """Say what the stage does."""
        text = (f'impulse j = -(1+e) vn / (w1+w2) along N, e = {self.restitution:g}, '
                f'colour by colour, up to {self.iterations} sweeps')
        if self.friction is not None:
            text += (f'; Coulomb friction mu = {self.friction:g} with spin '
                     '(|J_t| <= mu j, I = 2/5 m r^2)')
        return text
