"""Drag: F = -(k1 + k2 |v|) v, integrated in closed form over each step.

Replaces the drift stage (and the gravity stage) when drag is declared.
Over a step the rate lambda = (k1 + k2 |v|) / m is held at its value at
the start of the step; then m v' = m g - m lambda v has the exact solution
    v = v0 e^{-lambda dt} + g phi,
    x = x0 + v0 phi + g (dt - phi) / lambda,   phi = (1 - e^{-lambda dt}) / lambda.
With k2 = 0 this is exact: speed decays as exp(-k1 t / m) (and under
gravity reaches the terminal velocity m g / k1) at every step to rounding.
With k2 > 0 it is first-order accurate in dt for the quadratic part,
never reverses a velocity and is stable for any dt. The energy removed is
booked as 'drag', per particle from the drag force's own work: the kinetic
energy lost, 1/2 m (v0 - v) . (v0 + v), less gravity's work m g . dx on
the displacement (never a difference of world totals, so it keeps its
digits far from the origin).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...model.effects import Drag
from ...step.pipeline import Stage, StepContext
from ...model.tunables import SERIES_LIMIT


def drag_step(v0: np.ndarray, inv_mass: np.ndarray, drag: Drag, gravity: Optional[np.ndarray],
              dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (displacement, new velocity) of dynamic particles over one step."""
    rate = drag.linear * inv_mass
    if drag.quadratic:
        rate = rate + drag.quadratic * inv_mass * np.sqrt(np.einsum('ij,ij->i', v0, v0))
    a = rate * dt
    moving = rate > 0.0
    # phi = (1 - e^{-a}) / lambda, with expm1 for accuracy and dt at lambda = 0.
    phi = np.where(moving, -np.expm1(-a) / np.where(moving, rate, 1.0), dt)
    displacement = v0 * phi[:, None]
    velocity = v0 * np.exp(-a)[:, None]
    if gravity is not None:
        small = a < SERIES_LIMIT
        series = dt * dt * (0.5 + a * (-1.0 / 6.0 + a * (1.0 / 24.0 + a * (
            -1.0 / 120.0 + a / 720.0))))
        psi = np.where(small, series, (dt - phi) / np.where(small, 1.0, rate))
        displacement += psi[:, None] * gravity
        velocity += phi[:, None] * gravity
    return displacement, velocity


def advance_with_drag(ctx: StepContext, index: np.ndarray, drag: Drag,
                      gravity: Optional[np.ndarray], tau: float | np.ndarray) -> None:
    """Move particles ``index`` by ``tau`` s (one or per particle) of drag; book its work.

    The loss booked is the drag force's own work per particle: the kinetic
    energy change less gravity's work along the displacement.
    """
    s = ctx.state
    v0 = s.velocity[index]
    displacement, velocity = drag_step(v0, s.inv_mass[index], drag, gravity, tau)
    s.position[index] += displacement
    s.velocity[index] = velocity
    work = 0.5 * np.einsum('ij,ij->i', v0 - velocity, v0 + velocity)
    if gravity is not None:
        work += displacement @ gravity
    ctx.book('drag', work / s.inv_mass[index], index)


class DragStage(Stage):
    """Move particles under drag (and gravity, if declared) for one step."""

    name = 'drag'

    def __init__(self, drag: Drag, gravity: Optional[np.ndarray] = None) -> None:
        """Keep the drag coefficients and gravity (None: no gravity)."""
        self.drag = drag
        self.gravity = None if gravity is None else np.asarray(gravity, dtype=float)

    def run(self, ctx: StepContext) -> None:
        """Advance positions and velocities in place; book the energy removed."""
        s = ctx.state
        dyn = np.flatnonzero(s.dynamic)
        if not dyn.size:
            return
        advance_with_drag(ctx, dyn, self.drag, self.gravity, ctx.dt)

    def describe(self) -> str:
        """Say what the stage does."""
        text = (f'F = -({self.drag.linear:g} + {self.drag.quadratic:g} |v|) v N, closed form '
                'per step (exact for linear drag)')
        if self.gravity is not None:
            text += f', with g = {self.gravity.tolist()} m/s^2'
        return text
