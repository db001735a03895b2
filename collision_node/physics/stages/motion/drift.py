"""Drift: move every particle along its velocity for one step."""

from __future__ import annotations

from ...step.pipeline import Stage, StepContext


class DriftStage(Stage):
    """x <- x + v dt (exact for force-free motion)."""

    name = 'drift'

    def run(self, ctx: StepContext) -> None:
        """Advance positions in place."""
        ctx.state.position += ctx.state.velocity * ctx.dt

    def describe(self) -> str:
        """Say what the stage does."""
        return 'x += v dt for every particle'
