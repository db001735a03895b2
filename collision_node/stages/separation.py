"""Separation: remove the overlap left after the contact solve.

Method: pure position projection. Each overlapping pair is pushed apart
along N by its penetration, shared by inverse mass; a particle in several
contacts moves by the average of its pushes (Jacobi averaging, which
cannot overshoot). Velocities are not touched, so no kinetic energy is
added. Baumgarte-style correction, which feeds the overlap back into the
velocity, was rejected: it is how an elastic gas gains energy without
bound in a well-known engine.

A particle that its push would take into a wall stays put and its
partner takes the whole push: the wall stage would otherwise put it
back and leave the overlap, and a ball pressed against a wall by a much
heavier one (which gets only its inverse-mass share of the push) would be
overrun by it step after step.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..effects import Walls
from ..pipeline import Stage, StepContext


def held_by_walls(position: np.ndarray, radius: np.ndarray, push: np.ndarray, walls: Walls,
                  dimensions: int) -> np.ndarray:
    """Return the mask of pushed particles that reach a wall the push points into.

    ``position`` is where the push would take them, ``push`` its direction.
    """
    p, d, r = position[:, :dimensions], push[:, :dimensions], radius[:, None]
    into_low = (p <= walls.low[:dimensions] + r) & (d < 0.0)
    into_high = (p >= walls.high[:dimensions] - r) & (d > 0.0)
    return np.any(into_low | into_high, axis=1)


def separate(position: np.ndarray, inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray,
             normal: np.ndarray, penetration: np.ndarray, radius: Optional[np.ndarray] = None,
             walls: Optional[Walls] = None, dimensions: int = 3) -> None:
    """Push overlapping pairs apart in place along their normals.

    With ``walls`` (and ``radius``), a particle held by a wall does not
    move and its partner, if it can move, takes the whole push.
    """
    w_i, w_j = inv_mass[i], inv_mass[j]
    if walls is not None:
        share = (penetration / (w_i + w_j))[:, None] * normal
        held_i = held_by_walls(position[i] + w_i[:, None] * share, radius[i], normal, walls,
                               dimensions)
        held_j = held_by_walls(position[j] - w_j[:, None] * share, radius[j], -normal, walls,
                               dimensions)
        w_i, w_j = (np.where(held_i & ~held_j & (w_j > 0.0), 0.0, w_i),
                    np.where(held_j & ~held_i & (w_i > 0.0), 0.0, w_j))
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
        separate(ctx.state.position, ctx.state.inv_mass, c.i, c.j, c.normal, c.penetration,
                 ctx.state.radius, ctx.effects.walls, ctx.dimensions)

    def describe(self) -> str:
        """Say what the stage does."""
        return 'position projection along N shared by inverse mass (velocities untouched)'
