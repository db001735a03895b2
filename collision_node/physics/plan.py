"""The step's plan: which stages a scene's effects and accuracy settings call for.

A pipeline is built when a world is created (and again on reset), so an
effect the scene does not declare is simply not in the list and costs
nothing. This module imports the stages; they import only the framework
in ``step.py``.
"""

from __future__ import annotations

from .accuracy import AccuracySettings, EVENT_FALLBACK, PRESETS
from .effects import Effects
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
from .step import Pipeline, Stage


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
    if accuracy.mode == 'event':
        # Exact event-driven mode: one stage moves the world impact to impact.
        # Its fallback for steps it cannot do exactly is built here, by the plan,
        # so the stage needs no import of the plan.
        return Pipeline([EventDrivenStage(
            effects, accuracy,
            fallback=lambda: build_pipeline(effects, PRESETS[EVENT_FALLBACK]))])
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
