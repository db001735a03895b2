"""Gravity: uniform acceleration g, integrated exactly over a step.

Runs right after the drift stage (x += v dt). Adding x += g dt^2 / 2 and
v += g dt makes the pair of stages the exact solution of x'' = g over the
step, x(t + dt) = x + v dt + g dt^2 / 2: free fall lands on the parabola
at every step to rounding, and kinetic plus potential energy is
conserved exactly (no energy is booked). Static particles do not fall.
"""

from __future__ import annotations

import numpy as np

from ..step import Stage, StepContext


class GravityStage(Stage):
    """Complete the drift to the exact constant-acceleration step."""

    name = 'gravity'

    def __init__(self, gravity: np.ndarray) -> None:
        """Keep g, m/s^2."""
        self.gravity = np.asarray(gravity, dtype=float)

    def run(self, ctx: StepContext) -> None:
        """Add g dt^2 / 2 to positions and g dt to velocities of dynamic particles."""
        s = ctx.state
        shift = 0.5 * ctx.dt * ctx.dt * self.gravity
        kick = ctx.dt * self.gravity
        if s.inv_mass.all():
            s.position += shift
            s.velocity += kick
            return
        dyn = s.dynamic
        s.position[dyn] += shift
        s.velocity[dyn] += kick

    def describe(self) -> str:
        """Say what the stage does."""
        return (f'g = {self.gravity.tolist()} m/s^2: x += g dt^2/2, v += g dt '
                '(with the drift: the exact parabola)')
