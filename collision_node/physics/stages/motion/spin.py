"""Spin: advance each particle's orientation by its angular velocity.

Between impulses a free sphere's angular velocity is constant (isotropic
inertia, no torque), so rotating the orientation quaternion by the angle
|w| dt about w / |w| is exact: q <- [sin(|w| dt / 2) w / |w|,
cos(|w| dt / 2)] * q, quaternions as [x, y, z, w] in the world frame.
The result is renormalised so rounding never accumulates. Present only
when friction is declared (nothing else changes spin). The update runs
compiled, in place (``step_kernels.rotate_orientations``).
"""

from __future__ import annotations

import numpy as np

from ...step.pipeline import Stage, StepContext
from ...step.step_kernels import rotate_orientations


class SpinStage(Stage):
    """Integrate orientation quaternions from angular velocities."""

    name = 'spin'

    def run(self, ctx: StepContext) -> None:
        """Rotate orientations in place."""
        s = ctx.state
        orientation = np.ascontiguousarray(s.orientation, dtype=np.float64)
        rotate_orientations(orientation,
                            np.ascontiguousarray(s.angular_velocity, dtype=np.float64), ctx.dt)
        if orientation is not s.orientation:
            s.orientation[...] = orientation

    def describe(self) -> str:
        """Say what the stage does."""
        return 'q <- exp(w dt / 2) q, exact for the constant spin between impulses'
