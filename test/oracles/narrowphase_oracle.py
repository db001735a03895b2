"""The narrowphase's contact test, vectorised: the reference its compiled pass must equal."""

from __future__ import annotations

import numpy as np

from collision_node.physics.model.tunables import SPECULATIVE_MARGIN
from collision_node.physics.stages.detection.narrowphase import line_of_action, NarrowphaseStage
from collision_node.physics.step.pipeline import Contacts, StepContext


def find_contacts(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                  inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray, ahead: float = 0.0,
                  margin: float = 0.0, sweep: float = 0.0) -> Contacts:
    """Return the overlapping pairs among candidates (i, j) of dynamic particles.

    With ``ahead``, ``margin`` or ``sweep`` also the speculative pairs: within
    (r_i + r_j) (1 + margin / 2) + ahead + (|v_i| + |v_j|) sweep.
    """
    # Cheap prefilter on squared distances, a little generous so that it
    # keeps every pair the exact test below keeps (offsets that underflow
    # square to 0 and pass; none can overflow within the validated bounds).
    offset = position[i] - position[j]
    reach = radius[i] + radius[j]
    speculative = ahead > 0.0 or margin > 0.0 or sweep > 0.0
    limit = reach + (0.5 * margin * reach + ahead) if speculative else reach
    if sweep > 0.0:
        speed = np.sqrt(np.einsum('ij,ij->i', velocity, velocity))
        limit = limit + sweep * (speed[i] + speed[j])
    near = np.einsum('ij,ij->i', offset, offset) <= limit * limit * (1.0 + 1e-9)
    if not near.any():
        return Contacts.empty()
    i, j, limit = i[near], j[near], limit[near]
    movable = (inv_mass[i] + inv_mass[j]) > 0.0
    i, j, limit = i[movable], j[movable], limit[movable]
    normal, distance = line_of_action(position[i] - position[j], velocity[i] - velocity[j])
    reach = radius[i] + radius[j]
    overlapping = distance < limit
    return Contacts(i=i[overlapping], j=j[overlapping], normal=normal[overlapping],
                    penetration=(reach - distance)[overlapping])


class NarrowphaseOracle(NarrowphaseStage):
    """The narrowphase stage running the vectorised test."""

    def run(self, ctx: StepContext) -> None:
        """Store contacts on the context, as the stage does."""
        s = ctx.state
        ahead = margin = sweep = 0.0
        threshold = float(ctx.effects.threshold(ctx.dt))
        if self.speculative and threshold > 0.0:
            ahead, margin = threshold * ctx.dt, SPECULATIVE_MARGIN
            sweep = ctx.dt if self.impacts else 0.0
        ctx.contacts = find_contacts(s.position, s.velocity, s.radius, s.inv_mass, ctx.pair_i,
                                     ctx.pair_j, ahead, margin, sweep)
        if len(ctx.contacts):
            deepest = float(ctx.contacts.penetration.max())
            ctx.stats.max_penetration = max(ctx.stats.max_penetration, deepest)
