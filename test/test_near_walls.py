"""The walls stage's list of particles near a plane changes no result.

The contact solve and the separation's clamp test only the particles the
walls stage lists near a wall plane (``StepContext.near_walls``). Stepped
with the list and with it withheld (every particle tested), worlds end in
bit-identical states: the shipped pile at each stepped preset, a 3-D pour
and a gas in a box, on 1 and 2 threads (the shared loops).
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World
from collision_node.bench.throughput import gas_scene
from collision_node.physics.model.scene import parse_scene
from collision_node.physics.stages.solve.walls import WallStage
from collision_node.scenarios import pour3d, shipped_pile


def _scene(case: str, preset: str):
    if case == 'pile':
        return shipped_pile(preset)
    if case == 'pour':
        return pour3d(600, accuracy=preset)
    return parse_scene(dict(gas_scene(6000, fraction=0.1), accuracy=preset), 'gas')


def _final_state(case: str, preset: str, steps: int, threads: int, withheld: bool,
                 monkeypatch) -> tuple:
    """Step a fresh world; with ``withheld`` the walls stage hands on no near list."""
    with monkeypatch.context() as patch:
        if withheld:
            run = WallStage.run

            def run_without_list(self, ctx):
                run(self, ctx)
                ctx.near_walls = None
            patch.setattr(WallStage, 'run', run_without_list)
        world = World(_scene(case, preset), threads=threads)
        world.step(steps)
    s = world.state
    return s.position.copy(), s.velocity.copy(), world.stats.dissipated


@pytest.mark.parametrize('case, preset, steps, threads', [
    ('pile', 'fast', 240, 1), ('pile', 'balanced', 120, 1), ('pile', 'accurate', 30, 1),
    ('pour', 'fast', 60, 1), ('pour', 'balanced', 40, 2), ('gas', 'fast', 40, 2)])
def test_a_step_with_the_near_list_equals_one_testing_every_particle(case, preset, steps,
                                                                     threads, monkeypatch):
    listed = _final_state(case, preset, steps, threads, False, monkeypatch)
    every = _final_state(case, preset, steps, threads, True, monkeypatch)
    np.testing.assert_array_equal(listed[0], every[0])
    np.testing.assert_array_equal(listed[1], every[1])
    assert listed[2] == every[2]


def test_the_contact_solve_and_the_clamp_see_the_list(monkeypatch):
    """In a box the list reaches the solve and the separation, which then drops it."""
    seen = []
    from collision_node.physics.stages.correction.separation import SeparationStage
    from collision_node.physics.stages.solve.sequential_impulses import \
        SequentialImpulseStage
    for stage in (SequentialImpulseStage, SeparationStage):
        run = stage.run

        def spy(self, ctx, run=run, name=stage.__name__):
            seen.append((name, None if ctx.near_walls is None else ctx.near_walls.size,
                         len(ctx.state)))
            run(self, ctx)
            if name == 'SeparationStage':
                seen.append(('after', ctx.near_walls))
        monkeypatch.setattr(stage, 'run', spy)
    World(_scene('gas', 'fast'), threads=1).step(2)
    solve = [row for row in seen if row[0] == 'SequentialImpulseStage']
    assert solve and all(0 < size < n for _, size, n in solve)
    assert [row[1] for row in seen if row[0] == 'after'] == [None, None]
