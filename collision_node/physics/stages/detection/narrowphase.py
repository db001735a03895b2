"""Narrowphase: which candidate pairs overlap, and their line of action.

As in the lecture: contact when |p1 - p2| < r1 + r2, line of action
N = (p1 - p2) / |p1 - p2|. The distance is computed after scaling each
offset by its largest component, so offsets of 1e-300 m (whose squares
underflow to zero) still give an exact unit normal.

``find_contacts`` is the vectorised statement; the stage runs the same
operations compiled (``contact_kernels.find_overlaps``, backend 'kernel',
the default), which keeps the same pairs with the same normals and
penetrations (``test/test_separation_kernels.py``).
"""

from __future__ import annotations

import numpy as np

from .narrowphase_kernels import find_overlaps
from ...step.pipeline import Contacts, Stage, StepContext
from ...model.tunables import BACKENDS


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


def find_contacts_compiled(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                           inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray) -> Contacts:
    """Return what ``find_contacts`` returns, from one compiled pass over the candidates."""
    m = i.shape[0]
    if m == 0:
        return Contacts.empty()
    out_i, out_j = np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64)
    normal, penetration = np.empty((m, 3)), np.empty(m)
    kept = find_overlaps(np.ascontiguousarray(position, dtype=float),
                         np.ascontiguousarray(velocity, dtype=float),
                         np.ascontiguousarray(radius, dtype=float),
                         np.ascontiguousarray(inv_mass, dtype=float),
                         np.ascontiguousarray(i, dtype=np.int64),
                         np.ascontiguousarray(j, dtype=np.int64), out_i, out_j, normal,
                         penetration)
    if kept == 0:
        return Contacts.empty()
    return Contacts(i=out_i[:kept], j=out_j[:kept], normal=normal[:kept],
                    penetration=penetration[:kept])


class NarrowphaseStage(Stage):
    """Keep the candidate pairs that overlap; record the deepest overlap."""

    name = 'narrowphase'

    def __init__(self, backend: str = 'kernel') -> None:
        """Choose the compiled pass ('kernel') or the vectorised reference ('numpy')."""
        if backend not in BACKENDS:
            raise ValueError(f'backend must be one of {BACKENDS}, got {backend!r}')
        self.backend = backend

    def run(self, ctx: StepContext) -> None:
        """Store contacts on the context."""
        s = ctx.state
        find = find_contacts_compiled if self.backend == 'kernel' else find_contacts
        ctx.contacts = find(s.position, s.velocity, s.radius, s.inv_mass, ctx.pair_i,
                            ctx.pair_j)
        if len(ctx.contacts):
            deepest = float(ctx.contacts.penetration.max())
            ctx.stats.max_penetration = max(ctx.stats.max_penetration, deepest)

    def describe(self) -> str:
        """Say what the stage does."""
        return 'contact when |p1-p2| < r1+r2, N = (p1-p2)/|p1-p2| (scale-robust)'
