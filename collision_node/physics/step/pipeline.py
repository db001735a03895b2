"""The step's framework: the stage base class, the step context and the pipeline.

Stages (one module each under ``physics/stages``) import this module;
``physics/step/plan.py`` chooses the stages for a scene and imports them, so
the framework, the stages and the plan form no import circle.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from time import perf_counter
from typing import Optional

import numpy as np

from ..model.accuracy import AccuracySettings
from ..model.effects import Effects
from ..model.impacts import ImpactLog
from ..model.state import ParticleState
from .step_kernels import add_losses, add_pair_losses


@dataclass
class StepStats:
    """Counters a world accumulates over its steps."""

    collisions: int = 0
    wall_collisions: int = 0
    max_penetration: float = 0.0
    dissipated: dict = field(default_factory=dict)
    # Steps the event-driven mode handed to its step-solver fallback.
    fallback_steps: int = 0

    def copy(self) -> 'StepStats':
        """Return an independent duplicate of the counters (to roll a step back)."""
        return replace(self, dissipated=dict(self.dissipated))

    def restore(self, saved: 'StepStats') -> None:
        """Take every counter back to ``saved`` in place."""
        for item in fields(self):
            value = getattr(saved, item.name)
            setattr(self, item.name, dict(value) if isinstance(value, dict) else value)

    def add_dissipated(self, effect: str, energy: float) -> None:
        """Book ``energy`` joules as removed by ``effect``."""
        self.dissipated[effect] = self.dissipated.get(effect, 0.0) + energy


@dataclass
class Contacts:
    """Overlapping particle pairs found by the narrowphase of one step."""

    i: np.ndarray
    j: np.ndarray
    normal: np.ndarray
    penetration: np.ndarray

    @classmethod
    def empty(cls) -> 'Contacts':
        """Return a set of no contacts."""
        none = np.zeros(0, dtype=np.int64)
        return cls(none, none, np.zeros((0, 3)), np.zeros(0))

    def __len__(self) -> int:
        """Return the number of contacts."""
        return int(self.i.shape[0])


@dataclass
class StepContext:
    """What the stages of one step share: the state, settings and results."""

    state: ParticleState
    dt: float
    dimensions: int
    effects: Effects
    accuracy: AccuracySettings
    stats: StepStats
    pair_i: Optional[np.ndarray] = None
    pair_j: Optional[np.ndarray] = None
    contacts: Optional[Contacts] = None
    # Simulated time at the start of this (sub)step, s.
    time: float = 0.0
    # Where the contact law records the impacts it resolves; None while
    # nobody reads them (recording then costs nothing).
    impacts: Optional[ImpactLog] = None
    # Threads the kernels may share this step's loops among (``threads.py``):
    # 1 runs every loop serially; any count gives the same result.
    threads: int = 1
    # The dynamic particles (ascending) near a wall plane as the positions
    # stand, set by the walls stage: each one not listed is farther from every
    # plane than any wall contact the solve takes (``walls.near_wall_distance``),
    # so the contact solve and the separation's clamp test only these. None:
    # not known (every particle is tested). A stage that moves particles after
    # the walls stage must keep it true or set it to None.
    near_walls: Optional[np.ndarray] = None
    # Under gravity, per particle (n, 3), m: how far the contact solve's
    # resting impulses held each particle up over this (sub)step
    # (``contact_kernels.support_shift``); the separation stage moves the
    # particles by it, as a lift it pays for. None: no solve set it.
    support_shift: Optional[np.ndarray] = None
    # Energy the contact law and the effects removed in this (sub)step, per
    # particle, J: the separation stage budgets a lift per cluster of
    # touching particles from it, never from losses elsewhere. Kept only
    # under gravity (the only case a lift changes energy).
    losses: Optional[np.ndarray] = field(init=False, default=None)

    def __post_init__(self) -> None:
        """Start the per-particle losses of this (sub)step under gravity."""
        if self.effects.gravity is not None:
            self.losses = np.zeros(len(self.state))

    def book(self, effect: str, removed: np.ndarray, i: np.ndarray,
             j: Optional[np.ndarray] = None) -> None:
        """Book energy ``removed`` (J, one value per contact) by ``effect``.

        ``i`` (and ``j`` for pairs) name the particles of each contact; a
        pair's loss is attributed to its two particles by inverse-mass share
        (a static partner takes none).
        """
        removed = np.asarray(removed, dtype=float)
        # removed.sum() without the method's argument handling (the same reduction).
        self.stats.add_dissipated(effect, float(np.add.reduce(removed, axis=None)))
        if self.losses is None or not removed.size:
            return
        inv_mass = self.state.inv_mass
        if _compiled_rows(removed, i) and (j is None or (
                _compiled_rows(removed, j) and inv_mass.dtype == np.float64
                and inv_mass.flags.c_contiguous)):
            # The compiled loops make np.add.at's additions in its order, without
            # its set-up and temporaries (a step books a few times per stage);
            # they take contiguous arrays (one compiled version, warmed up).
            removed = np.ascontiguousarray(removed)
            if j is None:
                add_losses(self.losses, np.ascontiguousarray(i), removed)
            else:
                add_pair_losses(self.losses, inv_mass, np.ascontiguousarray(i),
                                np.ascontiguousarray(j), removed)
            return
        if j is None:
            np.add.at(self.losses, i, removed)
            return
        w_i, w_j = self.state.inv_mass[i], self.state.inv_mass[j]
        share_i = w_i / (w_i + w_j)
        np.add.at(self.losses, i, removed * share_i)
        np.add.at(self.losses, j, removed * (1.0 - share_i))


def _compiled_rows(removed: np.ndarray, rows) -> bool:
    """Say whether ``book``'s compiled loops take these arrays (else numpy's add.at does)."""
    return (isinstance(rows, np.ndarray) and rows.dtype == np.int64 and rows.ndim == 1
            and removed.ndim == 1 and rows.shape[0] == removed.shape[0])


class Stage:
    """One part of a step; subclasses live one per module in ``stages/``."""

    name = 'stage'

    def run(self, ctx: StepContext) -> None:
        """Advance or correct ``ctx.state`` in place."""
        raise NotImplementedError

    def describe(self) -> str:
        """Return one line that says what the stage does."""
        return self.name

    def rows_moved(self, order: np.ndarray) -> None:
        """Hear that the rows were renumbered (new row k is old row ``order[k]``).

        A stage that keeps anything by row from step to step drops or
        renames it here; the default keeps nothing.
        """


class Pipeline:
    """An ordered list of stages run once per (sub)step."""

    def __init__(self, stages: list[Stage], note: str = '') -> None:
        """Keep the stages in the order they will run, and why they were chosen."""
        self.stages = stages
        self.note = note
        # Wall seconds each stage has run, by name in run order (the step's
        # profile, see ``timing``): two perf_counter calls per stage and step.
        self.seconds: dict[str, float] = dict.fromkeys(self.names, 0.0)
        # What keeps a large world's rows in spatial order (set by the plan:
        # ``stages/ordering.SpatialOrder``), None where nothing does.
        self.spatial_order = None

    @property
    def names(self) -> list[str]:
        """Stage names in run order."""
        return [stage.name for stage in self.stages]

    def run(self, ctx: StepContext) -> None:
        """Run every stage in order on one step context, timing each."""
        for stage in self.stages:
            self.run_stage(stage, ctx)

    def run_stage(self, stage: Stage, ctx: StepContext) -> None:
        """Run one stage on ``ctx`` and add its wall time to its total in ``seconds``."""
        start = perf_counter()
        stage.run(ctx)
        elapsed = perf_counter() - start
        self.seconds[stage.name] = self.seconds.get(stage.name, 0.0) + elapsed

    def rows_moved(self, order: np.ndarray) -> None:
        """Tell every stage that the rows were renumbered (``Stage.rows_moved``)."""
        for stage in self.stages:
            stage.rows_moved(order)

    def frame(self, before: Stage, after: Stage) -> None:
        """Time ``before`` and ``after``, stages a subclass runs around the list, in place."""
        self.seconds = {before.name: 0.0, **self.seconds, after.name: 0.0}

    def explain(self) -> str:
        """Return the pipeline as numbered lines, one per stage."""
        lines = [f'{k + 1}. {stage.name}: {stage.describe()}'
                 for k, stage in enumerate(self.stages)]
        if self.note:
            lines.append(f'note: {self.note}')
        return '\n'.join(lines)
