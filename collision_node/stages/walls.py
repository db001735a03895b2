"""Walls: an axis-aligned box that reflects particles with its restitution."""

from __future__ import annotations

import numpy as np

from ..effects import Walls
from ..pipeline import Stage, StepContext


class WallStage(Stage):
    """Reflect the normal velocity of particles that reach a wall."""

    name = 'walls'

    def __init__(self, walls: Walls) -> None:
        """Keep the box."""
        self.walls = walls

    def run(self, ctx: StepContext) -> None:
        """Reflect and clamp in place; count wall impacts, book lost energy."""
        s = ctx.state
        dyn = s.dynamic
        e = self.walls.restitution
        lost = 0.0
        for axis in range(ctx.dimensions):
            low = self.walls.low[axis] + s.radius
            high = self.walls.high[axis] - s.radius
            p, v = s.position[:, axis], s.velocity[:, axis]
            hit = dyn & (((p < low) & (v < 0.0)) | ((p > high) & (v > 0.0)))
            if np.any(hit):
                ctx.stats.wall_collisions += int(hit.sum())
                if e < 1.0:
                    lost += 0.5 * (1.0 - e * e) * float(np.sum(v[hit] ** 2 / s.inv_mass[hit]))
                v[hit] *= -e
            # Position projection back inside: no velocity change, no energy added.
            p[dyn] = np.clip(p[dyn], low[dyn], np.maximum(low, high)[dyn])
        if lost:
            ctx.stats.add_dissipated('walls', lost)

    def describe(self) -> str:
        """Say what the stage does."""
        w = self.walls
        return (f'box {w.low.tolist()} .. {w.high.tolist()} m, v_n -> -{w.restitution:g} v_n, '
                'positions clamped inside')
