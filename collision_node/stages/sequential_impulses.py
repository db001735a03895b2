"""Contact solve: impulses along the line of action, one colour at a time.

Sweeps the colour batches of the contact graph in order (Gauss-Seidel)
until no contact approaches or the iteration budget is spent. Each
impulse only changes the velocity component along N, exactly as the
lecture's velocity update.
"""

from __future__ import annotations

import numpy as np

from ..coloring import color_pairs
from ..impulse import apply_normal_impulses
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

    def __init__(self, restitution: float, iterations: int) -> None:
        """Keep the particle-particle restitution and the sweep budget."""
        self.restitution = restitution
        self.iterations = iterations

    def run(self, ctx: StepContext) -> None:
        """Apply impulses in place and count the contacts that received one."""
        contacts = ctx.contacts
        if contacts is None or len(contacts) == 0:
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
            # One batch shares no dynamic particle, so after one sweep every
            # contact is resolved (vn' = -e vn >= 0) and a checking sweep
            # would find nothing: skip it.
            if not applied or (len(batches) == 1 and not leftover.size):
                break
        ctx.stats.collisions += int(hit.sum())
        if track_energy:
            ctx.stats.add_dissipated('restitution',
                                     energy_before - self._energy(state, touched))

    @staticmethod
    def _energy(state, index: np.ndarray) -> float:
        """Linear kinetic energy of the particles in ``index``."""
        dyn = index[state.inv_mass[index] > 0.0]
        v = state.velocity[dyn]
        return 0.5 * float(np.sum(np.einsum('ij,ij->i', v, v) / state.inv_mass[dyn]))

    def describe(self) -> str:
        """Say what the stage does."""
        return (f'impulse j = -(1+e) vn / (w1+w2) along N, e = {self.restitution:g}, '
                f'colour by colour, up to {self.iterations} sweeps')
