"""The step's plan: which stages a scene's effects and accuracy settings call for.

A pipeline is built when a world is created (and again on reset), so an
effect the scene does not declare is simply not in the list and costs
nothing. This module imports the stages; they import only the framework
in ``pipeline.py``, so there is no import circle.
"""

from __future__ import annotations

from ..model.accuracy import AccuracySettings, EVENT_FALLBACK, PRESETS
from ..model.effects import Effects
from ..stages.solve.batched_impulses import BatchedImpulseStage
from ..stages.detection.broadphase import BroadphaseStage
from ..stages.motion.drag import DragStage
from ..stages.motion.drift import DriftStage
from ..stages.events.event_driven import EventDrivenStage
from ..stages.motion.gravity import GravityStage
from ..stages.detection.narrowphase import NarrowphaseStage
from ..stages.correction.separation import SeparationStage
from ..stages.ordering.spatial_order import SpatialOrder
from ..stages.solve.sequential_impulses import SequentialImpulseStage
from ..stages.sleeping.sleep import SleepingPipeline
from ..stages.motion.spin import SpinStage
from ..stages.swept.swept_contacts import SweptContactStage
from ..stages.solve.walls import WallStage
from .pipeline import Pipeline, Stage


def needs_contact_solve(effects: Effects) -> bool:
    """Say whether swept contacts need the step-end contact solve after them.

    Without gravity, drag, friction or a restitution threshold every
    contact is an impact the ccd stage resolves at its time of impact.
    With any of them, contacts closing slower than the restitution
    threshold are resting contact, which the ccd stage leaves to the
    sequential solve (threshold, speculative contacts, friction) at the step end.
    """
    return not (effects.gravity is None and effects.drag is None and effects.friction is None
                and effects.restitution_threshold is None)


def build_pipeline(effects: Effects, accuracy: AccuracySettings,
                   spatial_order: bool = True) -> Pipeline:
    """Assemble the stages a scene's effects and accuracy settings call for.

    Sleeping (``accuracy.sleep_time``) frames a step-mode pipeline with the
    ``wake`` and ``sleep`` stages only under gravity, the one effect that
    makes particles rest; without it the setting costs nothing.
    ``spatial_order``: a large world's rows are put in cell order at each
    full search of the step's first pair list (``stages/ordering``); the
    event mode's fallback, which steps the event stage's rows, goes without.
    """
    pipeline = _build(effects, accuracy)
    if accuracy.mode == 'step' and accuracy.sleep_time is not None \
            and effects.gravity is not None:
        pipeline = SleepingPipeline(pipeline.stages, effects.gravity, accuracy.sleep_time,
                                    note=pipeline.note)
    if spatial_order:
        _order_rows(pipeline)
    return pipeline


def _order_rows(pipeline: Pipeline) -> None:
    """Give the step's first pair list the spatial order, told to the whole pipeline."""
    for stage in pipeline.stages:
        search = stage.pair_search if isinstance(stage, SweptContactStage) else stage
        if isinstance(search, BroadphaseStage):
            search.order = pipeline.spatial_order = SpatialOrder(pipeline)
            return


def _build(effects: Effects, accuracy: AccuracySettings) -> Pipeline:
    """Assemble the stages of one step without sleeping."""
    if accuracy.mode == 'event':
        # Exact event-driven mode: one stage moves the world impact to impact.
        # Its fallback for steps it cannot do exactly is built here, by the plan,
        # so the stage needs no import of the plan.
        return Pipeline([EventDrivenStage(
            effects, accuracy,
            fallback=lambda: build_pipeline(effects, PRESETS[EVENT_FALLBACK],
                                            spatial_order=False))])
    if accuracy.ccd:
        return _swept_pipeline(effects, accuracy)
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
    # The batched solver knows walls and restitution only.
    if accuracy.ordering == 'batched' and not needs_contact_solve(effects):
        solver: Stage = BatchedImpulseStage(effects.particle_restitution, accuracy.iterations)
    else:
        if accuracy.ordering == 'batched':
            notes.append('batched ordering covers walls and restitution only: contacts '
                         'are solved sequentially')
        solver = SequentialImpulseStage(effects.particle_restitution, accuracy.iterations,
                                        friction=effects.friction, walls=effects.walls,
                                        gravity=effects.gravity)
    # Speculative contacts (under a restitution threshold) for the sequential solve;
    # without a swept stage impacts are found before they overlap too.
    speculative = isinstance(solver, SequentialImpulseStage)
    if speculative:
        solver.early_impacts = True
    stages += [BroadphaseStage(speculative, impacts=speculative),
               NarrowphaseStage(speculative, impacts=speculative), solver,
               SeparationStage(walls=effects.walls, passes=accuracy.separation_passes)]
    return Pipeline(stages, note='; '.join(notes))


def _swept_pipeline(effects: Effects, accuracy: AccuracySettings) -> Pipeline:
    """Continuous detection: impacts at their time of impact, with every effect.

    Paths inside the step are straight, parabolas under gravity, drag's
    closed form with drag (see ``swept_contacts``). With gravity, drag,
    friction or a threshold, contacts slower than the restitution threshold
    are resting contact: the walls stage, the sequential solve (threshold,
    speculative contacts, friction) and separation take them at the step end.
    """
    notes = []
    ordering = accuracy.ordering
    if ordering == 'batched' and effects.friction is not None:
        # Friction at an impact needs the particle's velocity after that
        # impact alone, so impacts sharing a particle are taken in turn.
        ordering = 'sequential'
        notes.append('batched ordering with friction: impacts are taken sequentially')
    resting = needs_contact_solve(effects)
    stages: list[Stage] = []
    if effects.spin:
        stages.append(SpinStage())
    stages.append(SweptContactStage(effects.particle_restitution, effects.walls, ordering,
                                    accuracy.iterations, accuracy.requery,
                                    gravity=effects.gravity, drag=effects.drag,
                                    friction=effects.friction, resting=resting))
    if not resting:
        stages += [NarrowphaseStage(),
                   SeparationStage(walls=effects.walls, passes=accuracy.separation_passes)]
        return Pipeline(stages, note='; '.join(notes))
    if effects.walls is not None:
        # Wall contacts slower than the threshold, found past a plane at the
        # step end, rest on it (the walls stage's law at its time in the step).
        stages.append(WallStage(effects.walls, friction=effects.friction))
    # A fresh candidate search at the step end (as in discrete detection):
    # it also finds the overlaps of particles an impact sent beyond the
    # swept stage's list, and gives the solve the discrete pipeline's order.
    stages += [BroadphaseStage(speculative=True), NarrowphaseStage(speculative=True),
               SequentialImpulseStage(effects.particle_restitution, accuracy.iterations,
                                      friction=effects.friction, walls=effects.walls,
                                      gravity=effects.gravity),
               SeparationStage(walls=effects.walls, passes=accuracy.separation_passes)]
    return Pipeline(stages, note='; '.join(notes))
