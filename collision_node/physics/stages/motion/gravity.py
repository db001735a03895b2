"""Gravity: uniform acceleration g, integrated exactly over a step.

Runs right after the drift stage (x += v dt). Adding x += g dt^2 / 2 and
v += g dt makes the pair of stages the exact solution of x'' = g over the
step, x(t + dt) = x + v dt + g dt^2 / 2: free fall lands on the parabola
at every step to rounding, and kinetic plus potential energy is
conserved exactly (no energy is booked). Static particles do not fall.
"""

from __future__ import annotations

import numpy as np

from ...step.pipeline import Stage, StepContext
from ...step.step_kernels import apply_gravity


def _rows(a: np.ndarray) -> bool:
    """Say whether ``a`` is a C-contiguous float64 (n, 3) array (what the kernel takes)."""
    return a.dtype == np.float64 and a.ndim == 2 and a.shape[1] == 3 and a.flags.c_contiguous


class GravityStage(Stage):
    """Complete the drift to the exact constant-acceleration step."""

    name = 'gravity'

    def __init__(self, gravity: np.ndarray) -> None:
        """Keep g, m/s^2."""
        self.gravity = np.asarray(gravity, dtype=float)
        self._dt = None
        self._shift = self._kick = np.zeros(3)

    def run(self, ctx: StepContext) -> None:
        """Add g dt^2 / 2 to positions and g dt to velocities of dynamic particles."""
        s = ctx.state
        if ctx.dt != self._dt:
            # The same few products every step: computed once per dt.
            self._shift = 0.5 * ctx.dt * ctx.dt * self.gravity
            self._kick = ctx.dt * self.gravity
            self._dt = ctx.dt
        shift, kick = self._shift, self._kick
        if _rows(s.position) and _rows(s.velocity) and s.inv_mass.dtype == np.float64:
            # One compiled pass, the same additions (sleepers have inv_mass 0).
            apply_gravity(s.position, s.velocity, s.inv_mass, shift, kick)
            return
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
