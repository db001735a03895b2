"""The narrowphase's contact test, vectorised: the reference its compiled pass must equal."""

from __future__ import annotations

import numpy as np

from collision_node.physics.stages.detection.narrowphase import line_of_action, NarrowphaseStage
from collision_node.physics.step.pipeline import Contacts, StepContext


def find_contacts(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                  inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray) -> Contacts:
    """Return the overlapping pairs among candidates (i, j) of dynamic particles."""
    # Cheap prefilter on squared distances, a little generous so that it
    # keeps every pair the exact test below keeps (offsets that underflow
    # square to 0 and pass; none can overflow within the validated bounds).
    offset = position[i] - position[j]
    reach = radius[i] + radius[j]
    near = np.einsum('ij,ij->i', offset, offset) <= reach * reach * (1.0 + 1e-9)
    if not near.any():
        return Contacts.empty()
    i, j = i[near], j[near]
    movable = (inv_mass[i] + inv_mass[j]) > 0.0
    i, j = i[movable], j[movable]
    normal, distance = line_of_action(position[i] - position[j], velocity[i] - velocity[j])
    reach = radius[i] + radius[j]
    overlapping = distance < reach
    return Contacts(i=i[overlapping], j=j[overlapping], normal=normal[overlapping],
                    penetration=(reach - distance)[overlapping])


class NarrowphaseOracle(NarrowphaseStage):
    """The narrowphase stage running the vectorised test."""

    def run(self, ctx: StepContext) -> None:
        """Store contacts on the context, as the stage does."""
        s = ctx.state
        ctx.contacts = find_contacts(s.position, s.velocity, s.radius, s.inv_mass, ctx.pair_i,
                                     ctx.pair_j)
        if len(ctx.contacts):
            deepest = float(ctx.contacts.penetration.max())
            ctx.stats.max_penetration = max(ctx.stats.max_penetration, deepest)
