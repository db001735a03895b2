"""Narrowphase: which candidate pairs overlap, and their line of action.

As in the lecture: contact when |p1 - p2| < r1 + r2, line of action
N = (p1 - p2) / |p1 - p2|. The distance is computed after scaling each
offset by its largest component, so offsets of 1e-300 m (whose squares
underflow to zero) still give an exact unit normal.
"""

from __future__ import annotations

import numpy as np

from ..step import Contacts, Stage, StepContext


def line_of_action(offset: np.ndarray, relative_velocity: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Return unit normals N = offset / |offset| and distances |offset|.

    Coincident centres have no line of action; the fallback is
    deterministic: against the relative velocity (so the impulse reverses
    the approach, as a head-on impact would), or +x if they do not move
    relative to each other.
    """
    scale = np.max(np.abs(offset), axis=1)
    coincident = scale == 0.0
    safe_scale = np.where(coincident, 1.0, scale)
    scaled = offset / safe_scale[:, None]
    scaled_norm = np.sqrt(np.einsum('ij,ij->i', scaled, scaled))
    distance = scale * scaled_norm
    normal = scaled / np.where(coincident, 1.0, scaled_norm)[:, None]
    if np.any(coincident):
        rv = relative_velocity[coincident]
        rv_scale = np.max(np.abs(rv), axis=1)
        moving = rv_scale > 0.0
        fallback = np.zeros_like(rv)
        fallback[:, 0] = 1.0
        rv_unit = rv[moving] / rv_scale[moving, None]
        rv_unit /= np.sqrt(np.einsum('ij,ij->i', rv_unit, rv_unit))[:, None]
        fallback[moving] = -rv_unit
        normal[coincident] = fallback
    return normal, distance


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


class NarrowphaseStage(Stage):
    """Keep the candidate pairs that overlap; record the deepest overlap."""

    name = 'narrowphase'

    def run(self, ctx: StepContext) -> None:
        """Store contacts on the context."""
        s = ctx.state
        ctx.contacts = find_contacts(s.position, s.velocity, s.radius, s.inv_mass,
                                     ctx.pair_i, ctx.pair_j)
        if len(ctx.contacts):
            deepest = float(ctx.contacts.penetration.max())
            ctx.stats.max_penetration = max(ctx.stats.max_penetration, deepest)

    def describe(self) -> str:
        """Say what the stage does."""
        return 'contact when |p1-p2| < r1+r2, N = (p1-p2)/|p1-p2| (scale-robust)'
