"""Contact solve, batched: every contact's impulse from the same velocities (Jacobi).

The ``batched`` ordering: each sweep computes the impulse of every
approaching contact from the velocities at the start of the sweep and
applies them all at once, vectorised and independent of the contact
order. A particle in k approaching contacts of the sweep receives each of
their impulses scaled by 1/k (each contact takes the smaller share of its
two particles). Then a sweep never adds kinetic energy: with the full
elastic changes dV_p of each contact (each one alone conserving energy),
the change is -sum_p s_p |dV_p|^2 + |sum_p s_p dV_p|^2 (mass-weighted)
and, per particle, Cauchy-Schwarz with sum of its shares <= 1 bounds the
second term by the first. Pure Jacobi (no shares) does add energy: an
elastic 200-particle gas gained 2.4 % in one step when we measured it.

Outcome: identical to the sequential solve when no particle is in two
approaching contacts in the same sweep (a dilute gas; Newton's cradle,
whose wave moves one pair per sweep, ends at (0, 0, 0, 0, v0)); a particle
struck from two sides at once loses energy: three touching balls
[1, 0, -1] end at [0, 0, 0] instead of [-1, 0, 1].
"""

from __future__ import annotations

import numpy as np

from ...law.contact_law import apply_pair_impulses, pair_coefficient, record_pairs
from ...law.impulse import closing_speed
from ...step.pipeline import Stage, StepContext


def shared_scale(i: np.ndarray, j: np.ndarray, active: np.ndarray, dynamic: np.ndarray,
                 n: int) -> np.ndarray:
    """Return each contact's share 1 / max(k_i, k_j) of its impulse.

    k counts the ``active`` contacts at each dynamic particle; a static
    particle never changes velocity, so it never forces a share.
    """
    weight = active.astype(float)
    degree = np.bincount(i, weights=weight * dynamic[i], minlength=n) + \
        np.bincount(j, weights=weight * dynamic[j], minlength=n)
    return 1.0 / np.maximum(np.maximum(degree[i], degree[j]), 1.0)


class BatchedImpulseStage(Stage):
    """Resolve approaching contacts all at once per sweep, shared by degree."""

    name = 'contact_impulses_batched'

    def __init__(self, restitution: float, iterations: int) -> None:
        """Keep the particle-particle restitution and the sweep budget."""
        self.restitution = restitution
        self.iterations = iterations

    def run(self, ctx: StepContext) -> None:
        """Apply the law's impulses in place, count the contacts hit, book and record them."""
        contacts = ctx.contacts
        if contacts is None or len(contacts) == 0:
            return
        state = ctx.state
        i, j, normal = contacts.i, contacts.j, contacts.normal
        restitution = pair_coefficient(state.restitution, i, j, self.restitution)
        record = ctx.impacts is not None
        if record:
            approach0 = -closing_speed(state.velocity, i, j, normal)
            summed = np.zeros(len(contacts))
        hit = np.zeros(len(contacts), dtype=bool)
        for _ in range(self.iterations):
            approaching = closing_speed(state.velocity, i, j, normal) < 0.0
            if not approaching.any():
                break
            scale = shared_scale(i, j, approaching, state.dynamic, len(state))
            result = apply_pair_impulses(state.velocity, state.inv_mass, i, j, normal,
                                         restitution, scale=scale)
            ctx.book('restitution', result.removed_at, result.particles)
            if record:
                summed += result.magnitude
            hit |= approaching
        ctx.stats.collisions += int(hit.sum())
        if record:
            record_pairs(ctx.impacts, ctx.time, state.position, state.radius, i[hit], j[hit],
                         normal[hit], summed[hit], 0.0, np.maximum(approach0[hit], 0.0))

    def describe(self) -> str:
        """Say what the stage does."""
        return (f'impulse j = -(1+e) vn / (w1+w2) along N, e = {self.restitution:g}, '
                f'all contacts at once per sweep (Jacobi, shared 1/k by a particle in k), '
                f'up to {self.iterations} sweeps')
