"""The step's profile: wall time per stage, the first step apart from the rest.

The pipeline adds each stage's ``time.perf_counter`` interval to a total
per stage name; the world times each whole step around it. The first step
of a world pays for loading (or compiling) the stages' compiled code, so
it is reported on its own and the steady state is the mean of the steps
after it. Time spent outside every stage (building the step's context,
the finite check) is reported too, so the shares add up to the step.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple, Optional

# The name the profile gives to the part of a step spent outside every stage.
OUTSIDE = '(outside the stages)'


class StageTime(NamedTuple):
    """One stage's cost: in the first step, and per step after it."""

    name: str
    # Wall time in the world's first step, ms.
    first_ms: float
    # Mean wall time per step over the steps after the first, ms.
    ms_per_step: float
    # ms_per_step over the steady step's wall time (0 with no steady step).
    share: float


class StepProfile(NamedTuple):
    """Where a world's steps spent their wall time, stage by stage."""

    # One entry per timed stage in run order, then OUTSIDE.
    stages: tuple[StageTime, ...]
    # Steps timed (the first included).
    steps: int
    # Wall time of the first step, ms.
    first_step_ms: float
    # Mean wall time of a step after the first, ms (0 with no steady step).
    ms_per_step: float

    @property
    def names(self) -> list[str]:
        """Names of the timed stages in run order (without OUTSIDE)."""
        return [stage.name for stage in self.stages if stage.name != OUTSIDE]

    def table(self) -> str:
        """Return the profile as a Markdown table, one row per stage and one for the step."""
        lines = [f'steps timed: {self.steps} (the first step, which loads the compiled code, '
                 'apart; ms per step and share over the steps after it)', '',
                 '| stage | first step ms | ms per step | share |', '|---|---:|---:|---:|']
        for stage in self.stages:
            lines.append(f'| {stage.name} | {stage.first_ms:.4g} | {stage.ms_per_step:.4g} '
                         f'| {100.0 * stage.share:.1f} % |')
        lines.append(f'| step | {self.first_step_ms:.4g} | {self.ms_per_step:.4g} '
                     f'| {100.0 if self.steps > 1 else 0.0:.1f} % |')
        return '\n'.join(lines)


def build_profile(stage_seconds: Mapping[str, float], step_seconds: float, steps: int,
                  first: Optional[tuple[float, Mapping[str, float]]]) -> StepProfile:
    """Return the profile of ``steps`` steps from the accumulated totals, s.

    ``stage_seconds`` holds each stage's total over every step,
    ``step_seconds`` the steps' total; ``first`` is (the first step's wall
    time, the stage totals after it), or None before any step.
    """
    if first is None:
        first_wall, first_stages = 0.0, {}
    else:
        first_wall, first_stages = first
    steady = steps - 1
    steady_wall = (step_seconds - first_wall) / steady if steady > 0 else 0.0
    rows = []
    first_inside = steady_inside = 0.0
    for name, total in stage_seconds.items():
        before = first_stages.get(name, 0.0)
        per_step = (total - before) / steady if steady > 0 else 0.0
        first_inside += before
        steady_inside += per_step
        rows.append(_row(name, before, per_step, steady_wall))
    rows.append(_row(OUTSIDE, max(first_wall - first_inside, 0.0),
                     max(steady_wall - steady_inside, 0.0), steady_wall))
    return StepProfile(stages=tuple(rows), steps=steps, first_step_ms=first_wall * 1e3,
                       ms_per_step=steady_wall * 1e3)


def _row(name: str, first: float, per_step: float, steady_wall: float) -> StageTime:
    """Return one stage's row from seconds."""
    share = per_step / steady_wall if steady_wall > 0.0 else 0.0
    return StageTime(name=name, first_ms=first * 1e3, ms_per_step=per_step * 1e3, share=share)
