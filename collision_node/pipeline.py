"""A step as a pipeline of stages, assembled once from the scene.

Each stage is one module under ``collision_node/stages``; the pipeline is
built when a world is created (and again on reset), so an effect the scene
does not declare is simply not in the list and costs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Optional

import numpy as np

from .accuracy import AccuracySettings
from .effects import Effects
from .state import ParticleState


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
    # Energy the effects had removed before this (sub)step, J: a stage can tell
    # what this step has dissipated so far (separation uses it).
    dissipated_before: float = field(init=False)

    def __post_init__(self) -> None:
        """Note the dissipation booked so far."""
        self.dissipated_before = sum(self.stats.dissipated.values())

    def dissipated_now(self) -> float:
        """Return the energy the effects removed so far in this (sub)step, J."""
        return sum(self.stats.dissipated.values()) - self.dissipated_before


class Stage:
    """One part of a step; subclasses live one per module in ``stages/``."""

    name = 'stage'

    def run(self, ctx: StepContext) -> None:
        """Advance or correct ``ctx.state`` in place."""
        raise NotImplementedError

    def describe(self) -> str:
        """Return one line that says what the stage does."""
        return self.name


class Pipeline:
    """An ordered list of stages run once per (sub)step."""

    def __init__(self, stages: list[Stage], note: str = '') -> None:
        """Keep the stages in the order they will run, and why they were chosen."""
        self.stages = stages
        self.note = note

    @property
    def names(self) -> list[str]:
        """Stage names in run order."""
        return [stage.name for stage in self.stages]

    def run(self, ctx: StepContext) -> None:
        """Run every stage in order on one step context."""
        for stage in self.stages:
            stage.run(ctx)

    def explain(self) -> str:
        """Return the pipeline as numbered lines, one per stage."""
        lines = [f'{k + 1}. {stage.name}: {stage.describe()}'
                 for k, stage in enumerate(self.stages)]
        if self.note:
            lines.append(f'note: {self.note}')
        return '\n'.join(lines)


def swept_contacts_cover(effects: Effects) -> bool:
    """Say whether the ccd stage simulates every declared effect.

    It moves particles on straight lines and knows walls and restitution;
    under gravity, drag or friction (curved paths, tangential impulses,
    resting-contact threshold) a step falls back to discrete contacts,
    whose stages implement those effects, and ``explain`` shows it.
    """
    return (effects.gravity is None and effects.drag is None and effects.friction is None
            and effects.restitution_threshold is None)


def build_pipeline(effects: Effects, accuracy: AccuracySettings) -> Pipeline:
    """Assemble the stages a scene's effects and accuracy settings call for."""
    from .stages.batched_impulses import BatchedImpulseStage
    from .stages.broadphase import BroadphaseStage
    from .stages.drag import DragStage
    from .stages.drift import DriftStage
    from .stages.event_driven import EventDrivenStage
    from .stages.gravity import GravityStage
    from .stages.narrowphase import NarrowphaseStage
    from .stages.separation import SeparationStage
    from .stages.sequential_impulses import SequentialImpulseStage
    from .stages.spin import SpinStage
    from .stages.swept_contacts import SweptContactStage
    from .stages.walls import WallStage

    if accuracy.mode == 'event':
        # Exact event-driven mode: one stage moves the world impact to impact.
        return Pipeline([EventDrivenStage(effects, accuracy)])
    if accuracy.ccd and swept_contacts_cover(effects):
        # Continuous detection: straight paths inside the step, impacts at
        # their time of impact (walls included), then the leftover overlap.
        stages: list[Stage] = [
            SweptContactStage(effects.particle_restitution, effects.walls, accuracy.ordering,
                              accuracy.iterations, accuracy.requery),
            NarrowphaseStage(), SeparationStage(walls=effects.walls)]
        return Pipeline(stages)
    # Discrete detection at the step end (the lecture's test), with every effect.
    # Motion: free drift, plus gravity's exact completion, or the closed-form
    # drag step (which includes gravity when declared).
    if effects.drag is not None:
        stages = [DragStage(effects.drag, effects.gravity)]
    else:
        stages = [DriftStage()]
        if effects.gravity is not None:
            stages.append(GravityStage(effects.gravity))
    if effects.spin:
        stages.append(SpinStage())
    if effects.walls is not None:
        # Impacts at their time in the step; resting wall contact is then
        # solved together with the pairs, and separation projects back inside.
        stages.append(WallStage(effects.walls, friction=effects.friction))
    notes = []
    if accuracy.ccd:
        notes.append('ccd asked for, but gravity, drag, friction or a restitution threshold '
                     'is declared: contacts are detected at the step end')
    # The batched solver knows the same effects as the swept stage.
    if accuracy.ordering == 'batched' and swept_contacts_cover(effects):
        solver: Stage = BatchedImpulseStage(effects.particle_restitution, accuracy.iterations)
    else:
        if accuracy.ordering == 'batched':
            notes.append('batched ordering needs the same effects as ccd: contacts are '
                         'solved sequentially')
        solver = SequentialImpulseStage(effects.particle_restitution, accuracy.iterations,
                                        friction=effects.friction, walls=effects.walls,
                                        gravity=effects.gravity)
    stages += [BroadphaseStage(), NarrowphaseStage(), solver,
               SeparationStage(walls=effects.walls)]
    return Pipeline(stages, note='; '.join(notes))
