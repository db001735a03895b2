"""Drift: move every particle along its velocity for one step."""

from __future__ import annotations

from ...step.pipeline import Stage, StepContext
from ...step.step_kernels import drift_shared, float_rows
from ...step.threads import parallel


class DriftStage(Stage):
    """x <- x + v dt (exact for force-free motion)."""

    name = 'drift'

    def run(self, ctx: StepContext) -> None:
        """Advance positions in place (a large world's rows on the threads, the same sums)."""
        position, velocity = ctx.state.position, ctx.state.velocity
        if (parallel(ctx.threads, position.shape[0]) and float_rows(position)
                and float_rows(velocity)):
            drift_shared(position, velocity, float(ctx.dt))
        else:
            position += velocity * ctx.dt

    def describe(self) -> str:
        """Say what the stage does."""
        return 'x += v dt for every particle'
