"""Spin: advance each particle's orientation by its angular velocity.

Between impulses a free sphere's angular velocity is constant (isotropic
inertia, no torque), so rotating the orientation quaternion by the angle
|w| dt about w / |w| is exact: q <- [sin(|w| dt / 2) w / |w|,
cos(|w| dt / 2)] * q, quaternions as [x, y, z, w] in the world frame.
The result is renormalised so rounding never accumulates. Present only
when friction is declared (nothing else changes spin). ``rotate`` is the
numpy statement; the stage runs it compiled
(``step_kernels.rotate_orientations``, the same operations in place).
"""

from __future__ import annotations

import numpy as np

from ...step.pipeline import Stage, StepContext
from ...step.step_kernels import rotate_orientations


def rotate(orientation: np.ndarray, angular_velocity: np.ndarray, dt: float) -> np.ndarray:
    """Return orientations [x, y, z, w] rotated by angular_velocity * dt."""
    rate = np.sqrt(np.einsum('ij,ij->i', angular_velocity, angular_velocity))
    half = 0.5 * rate * dt
    # sin(|w| dt / 2) / |w|, with its limit dt / 2 at rest.
    factor = np.where(rate > 0.0, np.sin(half) / np.where(rate > 0.0, rate, 1.0), 0.5 * dt)
    dv = factor[:, None] * angular_velocity
    dw = np.cos(half)
    qv, qw = orientation[:, :3], orientation[:, 3]
    out = np.empty_like(orientation)
    out[:, :3] = dw[:, None] * qv + qw[:, None] * dv + np.cross(dv, qv)
    out[:, 3] = dw * qw - np.einsum('ij,ij->i', dv, qv)
    out /= np.sqrt(np.einsum('ij,ij->i', out, out))[:, None]
    return out


class SpinStage(Stage):
    """Integrate orientation quaternions from angular velocities."""

    name = 'spin'

    def run(self, ctx: StepContext) -> None:
        """Rotate orientations in place."""
        s = ctx.state
        q, w = s.orientation, s.angular_velocity
        if (q.dtype == np.float64 and w.dtype == np.float64 and q.flags.c_contiguous
                and w.flags.c_contiguous and q.ndim == 2 and q.shape[1] == 4
                and w.shape == (q.shape[0], 3)):
            # The same update compiled, in place: no dozen temporaries per step.
            rotate_orientations(q, w, ctx.dt)
            return
        q[:] = rotate(q, w, ctx.dt)

    def describe(self) -> str:
        """Say what the stage does."""
        return 'q <- exp(w dt / 2) q, exact for the constant spin between impulses'
