"""The step's profile: every stage of the pipeline timed, the first step apart."""

from __future__ import annotations

import json
import re
import time

import pytest

from collision_node import StepProfile, World, load_scene, parse_scene, scenarios
from collision_node.physics.step.timing import OUTSIDE
from collision_node.simulate import main as simulate_main


def explained_names(world: World) -> list[str]:
    """Return the stage names ``world.explain()`` lists, in its order (framing stages too)."""
    names = []
    for line in world.explain().splitlines():
        match = re.match(r'^(?:\d+\.|before 1,|after \d+,) ([a-z_]+):', line)
        if match:
            names.append(match.group(1))
    return names


def timed(world: World, steps: int) -> float:
    """Step ``world`` one step at a time; return the wall seconds around the calls."""
    start = time.perf_counter()
    for _ in range(steps):
        world.step()
    return time.perf_counter() - start


@pytest.mark.parametrize('preset', ['fast', 'balanced', 'accurate', 'exact'])
def test_profile_lists_exactly_the_pipeline_stages(preset):
    """Under gravity `fast` and `balanced` frame the stages with wake and sleep."""
    world = World(parse_scene(dict(scenarios.resting_column(5), accuracy=preset), 'column'))
    world.step(3)
    profile = world.profile()
    assert isinstance(profile, StepProfile)
    assert profile.names == explained_names(world)
    inner = [name for name in profile.names if name not in ('wake', 'sleep')]
    assert inner == world.pipeline.names
    assert ('wake' in profile.names) == (preset in ('fast', 'balanced'))
    assert [stage.name for stage in profile.stages] == profile.names + [OUTSIDE]


def test_times_are_non_negative_and_sum_to_at_most_the_wall_time_of_the_steps():
    world = World(parse_scene(scenarios.gas(40, 0.04, 1.0, seed=3, dt=0.01,
                                            accuracy='balanced'), 'gas'))
    wall = timed(world, 12)
    profile = world.profile()
    assert profile.steps == 12
    assert all(stage.first_ms >= 0.0 and stage.ms_per_step >= 0.0 and stage.share >= 0.0
               for stage in profile.stages)
    stage_total = sum(stage.first_ms + stage.ms_per_step * (profile.steps - 1)
                      for stage in profile.stages if stage.name != OUTSIDE)
    step_total = profile.first_step_ms + profile.ms_per_step * (profile.steps - 1)
    assert stage_total <= step_total * (1 + 1e-12)
    assert step_total <= wall * 1e3
    assert sum(stage.share for stage in profile.stages) == pytest.approx(1.0, rel=1e-9)


def test_the_first_step_is_reported_apart_from_the_steady_state():
    world = World(parse_scene(dict(scenarios.resting_column(5), accuracy='fast'), 'column'))
    before = world.profile()
    assert before.steps == 0 and before.first_step_ms == 0.0
    assert all(stage.first_ms == 0.0 for stage in before.stages)
    world.step()
    first = world.profile()
    assert first.steps == 1 and first.first_step_ms > 0.0 and first.ms_per_step == 0.0
    assert all(stage.ms_per_step == 0.0 and stage.share == 0.0 for stage in first.stages)
    assert sum(stage.first_ms for stage in first.stages) == pytest.approx(first.first_step_ms)
    world.step(4)
    later = world.profile()
    assert later.steps == 5 and later.first_step_ms == first.first_step_ms
    assert [stage.first_ms for stage in later.stages] == [stage.first_ms for stage in first.stages]
    assert later.ms_per_step > 0.0
    world.reset()
    assert world.profile().steps == 0


def test_simulate_profile_prints_every_stage_and_writes_it_to_the_json(tmp_path, capsys):
    out = tmp_path / 'run.json'
    assert simulate_main(['cradle', '--steps', '4', '--profile', '--quiet',
                          '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    rows = [line.split('|')[1].strip() for line in printed.splitlines()
            if line.startswith('| ') and not line.startswith('| stage')]
    world = World(load_scene('cradle'))
    assert rows == explained_names(world) + [OUTSIDE, 'step']
    assert 'steps timed: 4' in printed
    record = json.loads(out.read_text())['profile']
    assert record['steps'] == 4
    assert [stage['name'] for stage in record['stages']] == explained_names(world) + [OUTSIDE]
