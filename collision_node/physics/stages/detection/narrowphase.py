"""Narrowphase: which candidate pairs overlap, and their line of action.

As in the lecture: contact when |p1 - p2| < r1 + r2, line of action
N = (p1 - p2) / |p1 - p2|. The distance is computed after scaling each
offset by its largest component, so offsets of 1e-300 m (whose squares
underflow to zero) still give an exact unit normal.

``find_contacts`` runs the test compiled (``narrowphase_kernels``);
``line_of_action`` is the same statement vectorised, for the stages that
need normals of many offsets at once (the swept contacts). The tests keep
a vectorised reference of the whole test (``test/oracles``).
"""

from __future__ import annotations

import numpy as np

from .narrowphase_kernels import find_overlaps, find_overlaps_parallel
from ...model.tunables import SPECULATIVE_MARGIN
from ...step.pipeline import Contacts, Stage, StepContext
from ...step.step_kernels import ParticleArrays
from ...step.threads import parallel


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
                  inv_mass: np.ndarray, first: np.ndarray, second: np.ndarray,
                  ahead: float = 0.0, margin: float = 0.0, sweep: float = 0.0,
                  threads: int = 1) -> Contacts:
    """Return the overlapping pairs among candidates (first, second), one compiled pass.

    With ``ahead`` (m) or ``margin`` (of the mean radius) also the pairs
    within that gap (speculative contacts, negative penetration), with
    ``sweep`` (s) also those within (|v_i| + |v_j|) sweep. ``threads``:
    how many threads may share the test (the same result for any count).
    """
    if first.shape[0] == 0:
        return Contacts.empty()
    particles = ParticleArrays(np.ascontiguousarray(position, dtype=float),
                               np.ascontiguousarray(velocity, dtype=float),
                               np.ascontiguousarray(radius, dtype=float),
                               np.ascontiguousarray(inv_mass, dtype=float))
    kernel = find_overlaps_parallel if parallel(threads, first.shape[0]) else find_overlaps
    found = kernel(particles, np.ascontiguousarray(first, dtype=np.int64),
                   np.ascontiguousarray(second, dtype=np.int64), float(ahead), float(margin),
                   float(sweep))
    if found.first.size == 0:
        return Contacts.empty()
    return Contacts(i=found.first, j=found.second, normal=found.normal,
                    penetration=found.penetration)


class NarrowphaseStage(Stage):
    """Keep the candidate pairs that overlap; record the deepest overlap.

    ``speculative``: under a restitution threshold, also the pairs whose gap
    is below threshold x dt plus SPECULATIVE_MARGIN of their mean radius
    (found before they touch; the contact solve lets them close by their
    gap, ``law.primitives.closing_allowance``). ``impacts``: also pairs
    within (|v_i| + |v_j|) dt, which may meet within the step (a pipeline
    without swept contacts finds its impacts before they overlap, also
    those the solve's impulses turn towards each other).
    """

    name = 'narrowphase'

    def __init__(self, speculative: bool = False, impacts: bool = False) -> None:
        """Say whether speculative contacts (and impacts before they touch) are kept too."""
        self.speculative = speculative
        self.impacts = impacts

    def run(self, ctx: StepContext) -> None:
        """Store contacts on the context."""
        s = ctx.state
        ahead = margin = sweep = 0.0
        if self.speculative:
            threshold = float(ctx.effects.threshold(ctx.dt))
            if threshold > 0.0:
                ahead, margin = threshold * ctx.dt, SPECULATIVE_MARGIN
                sweep = ctx.dt if self.impacts else 0.0
        ctx.contacts = find_contacts(s.position, s.velocity, s.radius, s.inv_mass, ctx.pair_i,
                                     ctx.pair_j, ahead, margin, sweep, ctx.threads)
        if len(ctx.contacts):
            deepest = float(ctx.contacts.penetration.max())
            ctx.stats.max_penetration = max(ctx.stats.max_penetration, deepest)

    def describe(self) -> str:
        """Say what the stage does."""
        text = 'contact when |p1-p2| < r1+r2, N = (p1-p2)/|p1-p2| (scale-robust)'
        if self.speculative:
            text += ('; under a restitution threshold also pairs within threshold x dt + '
                     f'{SPECULATIVE_MARGIN:g} r of touching (speculative)')
        return text
