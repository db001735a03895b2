"""Separation: remove the overlap left after the contact solve.

Method: pure position projection. Each overlapping pair is pushed apart
along N by its penetration, shared by inverse mass; a particle in several
contacts moves by the average of its pushes (Jacobi averaging, which
cannot overshoot). Velocities are not touched, so no kinetic energy is
added. Baumgarte-style correction, which feeds the overlap back into the
velocity, was rejected: it is how an elastic gas gains energy without
bound in a well-known engine.

Under gravity, moving a particle changes its potential energy; that
change is booked (with its sign: a push upwards adds energy, booked as a
negative loss) as 'separation', so the energy balance still closes.
"""

from __future__ import annotations

import numpy as np

from ..energy import potential
from ..pipeline import Stage, StepContext


def separate(position: np.ndarray, inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray,
             normal: np.ndarray, penetration: np.ndarray) -> None:
    """Push overlapping pairs apart in place along their normals."""
    w_i, w_j = inv_mass[i], inv_mass[j]
    w_sum = w_i + w_j
    push_i = (penetration * w_i / w_sum)[:, None] * normal
    push_j = -(penetration * w_j / w_sum)[:, None] * normal
    n = position.shape[0]
    moves = np.bincount(i, weights=(w_i > 0), minlength=n) + \
        np.bincount(j, weights=(w_j > 0), minlength=n)
    total = np.zeros_like(position)
    np.add.at(total, i, push_i)
    np.add.at(total, j, push_j)
    moved = moves > 0
    position[moved] += total[moved] / moves[moved, None]


class SeparationStage(Stage):
    """Project overlapping pairs apart without touching velocities."""

    name = 'separation'

    def run(self, ctx: StepContext) -> None:
        """Move positions in place."""
        c = ctx.contacts
        if c is None or len(c) == 0:
            return
        gravity = ctx.effects.gravity
        if gravity is None:
            separate(ctx.state.position, ctx.state.inv_mass, c.i, c.j, c.normal,
                     c.penetration)
            return
        touched = np.unique(np.concatenate([c.i, c.j]))
        before = potential(ctx.state, gravity, touched)
        separate(ctx.state.position, ctx.state.inv_mass, c.i, c.j, c.normal, c.penetration)
        ctx.stats.add_dissipated('separation', before - potential(ctx.state, gravity, touched))

    def describe(self) -> str:
        """Say what the stage does."""
        return 'position projection along N shared by inverse mass (velocities untouched)'
