"""The public API for offline tests: exports, the typed scene builder, shared scenarios."""

from __future__ import annotations

import ast
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

import collision_node
from collision_node import (IMPACT_DTYPE, PRESETS, AccuracySettings, Effects, Gas, Particle,
                            SceneError, StepStats, World, build_scene, load_scene, parse_scene,
                            parse_scene_text, scenarios, scene_mapping, walls_box)
from collision_node import physics
from collision_node.bench.contact import resting
from collision_node.physics.model import accuracy, impacts
from collision_node.physics.step import pipeline

TEST_DIR = Path(__file__).resolve().parent


# -- exports -----------------------------------------------------------------------------

@pytest.mark.parametrize('name', collision_node.__all__)
def test_every_export_of_the_package_is_the_physics_one(name):
    assert getattr(collision_node, name) is getattr(physics, name)
    assert name in physics.__all__


def test_presets_are_the_settings_a_scene_gets_by_name():
    assert PRESETS is accuracy.PRESETS
    assert sorted(PRESETS) == ['accurate', 'balanced', 'exact', 'fast']
    for name, settings in PRESETS.items():
        assert isinstance(settings, AccuracySettings)
        assert parse_scene({'accuracy': name}, 't').accuracy == settings


def test_accuracy_settings_given_whole_build_the_same_scene_as_their_mapping():
    settings = replace(PRESETS['fast'], substeps=3, sleep_time=None)
    assert AccuracySettings is accuracy.AccuracySettings
    assert build_scene(accuracy=settings).accuracy == settings
    assert parse_scene({'accuracy': {'preset': 'fast', 'substeps': 3, 'sleep_time': None}},
                       't').accuracy == settings


def test_step_stats_count_what_a_world_resolved():
    world = World(load_scene('cradle'))
    assert StepStats is pipeline.StepStats and isinstance(world.stats, StepStats)
    world.step(400)
    assert world.stats.collisions == 4 and world.stats.wall_collisions == 0
    assert world.stats.copy() == world.stats


def test_impact_dtype_is_the_dtype_of_the_impacts_a_world_records():
    world = World(load_scene('cradle'))
    world.record_impacts(True)
    world.step(400)
    taken = world.take_impacts()
    assert IMPACT_DTYPE is impacts.IMPACT_DTYPE and taken.dtype == IMPACT_DTYPE
    assert len(taken) == 4
    pairs = zip(taken['i'].tolist(), taken['j'].tolist())
    assert sorted(tuple(sorted(pair)) for pair in pairs) == [(0, 1), (1, 2), (2, 3), (3, 4)]


# -- the builder --------------------------------------------------------------------------

YAML_SCENE = """
name: built
dimensions: 2
dt: 0.005
duration: 2.0
accuracy: {preset: fast, substeps: 2}
effects:
  gravity: [0, -9.81]
  walls: {min: [0, 0], max: [2, null], restitution: 0.5}
  restitution: 0.8
  friction: 0.3
particles:
  - {position: [0.5, 0.5], velocity: [1.0, 0.0], radius: 0.1, mass: 1.0}
  - {position: [0.8, 0.52], radius: 0.1, mass: 2.0, restitution: 0.2}
  - {position: [1.5, 0.1], radius: 0.1, mass: .inf}
generate:
  - {kind: gas, count: 20, radius: 0.02, mass: 0.1, speed: 1.0, seed: 4,
     region: {min: [0.1, 1.0], max: [1.9, 1.5]}}
"""


def built() -> collision_node.Scene:
    """Return YAML_SCENE built in code (numpy values where a file holds lists)."""
    return build_scene(
        [Particle(position=np.array([0.5, 0.5]), velocity=[1.0, 0.0], radius=0.1, mass=1.0),
         Particle(position=(0.8, 0.52), radius=np.float64(0.1), mass=2, restitution=0.2),
         Particle(position=[1.5, 0.1], radius=0.1, mass=math.inf)],
        dimensions=2, dt=0.005, duration=2.0, name='built',
        accuracy={'preset': 'fast', 'substeps': 2},
        effects=Effects(gravity=np.array([0.0, -9.81, 0.0]),
                        walls=walls_box([0, 0], [2, None], restitution=0.5),
                        restitution=0.8, friction=0.3),
        generate=[Gas(count=20, radius=0.02, mass=0.1, speed=1.0, seed=4,
                      low=[0.1, 1.0], high=[1.9, 1.5])])


def assert_same_state(a, b) -> None:
    """Assert two particle states hold identical arrays."""
    for name in ('ids', 'position', 'velocity', 'radius', 'inv_mass', 'restitution',
                 'friction', 'angular_velocity', 'orientation'):
        left, right = getattr(a, name), getattr(b, name)
        assert (left is None) == (right is None), name
        if left is not None:
            np.testing.assert_array_equal(left, right, err_msg=name)


def test_a_built_scene_is_the_yaml_scene_with_the_same_content():
    from_code, from_file = built(), parse_scene_text(YAML_SCENE, 'built.yaml')
    for key in ('name', 'dimensions', 'dt', 'duration', 'accuracy'):
        assert getattr(from_code, key) == getattr(from_file, key), key
    for key in ('restitution', 'restitution_threshold', 'friction', 'drag'):
        assert getattr(from_code.effects, key) == getattr(from_file.effects, key), key
    np.testing.assert_array_equal(from_code.effects.gravity, from_file.effects.gravity)
    for key in ('low', 'high', 'restitution'):
        np.testing.assert_array_equal(getattr(from_code.effects.walls, key),
                                      getattr(from_file.effects.walls, key))
    assert_same_state(from_code.initial, from_file.initial)
    assert len(from_code.initial) == 23
    worlds = [World(from_code), World(from_file)]
    for world in worlds:
        world.step(60)
    assert_same_state(worlds[0].state, worlds[1].state)
    assert worlds[0].stats == worlds[1].stats and worlds[0].stats.collisions > 0


def test_the_builder_mapping_is_what_the_file_holds():
    mapping = scene_mapping([Particle(position=[0, 1, 2], radius=0.5, mass=1.0)],
                            effects=Effects(walls=walls_box(high=[None, 3.0, None])))
    assert mapping == {'effects': {'walls': {'min': [None, None, None],
                                             'max': [None, 3.0, None], 'restitution': 1.0}},
                       'particles': [{'position': [0, 1, 2], 'radius': 0.5, 'mass': 1.0}]}
    assert yaml.safe_load(yaml.safe_dump(mapping)) == mapping


def test_effects_of_a_loaded_scene_build_the_same_effects():
    pile = load_scene('pile')
    scene = build_scene(dimensions=2, effects=pile.effects)
    np.testing.assert_array_equal(scene.effects.gravity, pile.effects.gravity)
    np.testing.assert_array_equal(scene.effects.walls.low, pile.effects.walls.low)
    np.testing.assert_array_equal(scene.effects.walls.high, pile.effects.walls.high)
    assert (scene.effects.restitution, scene.effects.friction) == \
        (pile.effects.restitution, pile.effects.friction)


@pytest.mark.parametrize('arguments, message', [
    ({'particles': [Particle(position=[0, 0, 0], radius=-1.0, mass=1.0)]},
     'build_scene: particles[0].radius: must be >= 1e-30, got -1'),
    ({'particles': [Particle(position=[0, 0], radius=1.0, mass=1.0)]},
     'build_scene: particles[0].position: expected [x, y, z], got 2 values'),
    ({'particles': ['ball']}, 'build_scene: particles[0]: expected a mapping, got str'),
    ({'effects': Effects(restitution=2.0)},
     'build_scene: effects.restitution: must be <= 1, got 2'),
    ({'effects': Effects(walls=walls_box([0, 0, 0], [1, -1, 1]))},
     'build_scene: effects.walls: max must exceed min on every axis (axis y)'),
    ({'effects': Effects(walls=walls_box())}, 'build_scene: effects.walls: no plane given'),
    ({'accuracy': 'fastest'}, "build_scene: accuracy: unknown preset 'fastest'"),
    ({'accuracy': replace(PRESETS['fast'], substeps=0)},
     'build_scene: accuracy.substeps: must be >= 1, got 0'),
    ({'generate': [Gas(count=0, radius=0.1, mass=1.0, low=[0, 0, 0], high=[1, 1, 1])]},
     'build_scene: generate[0].count: must be >= 1, got 0'),
    ({'dt': 0.0}, 'build_scene: dt: must be > 0, got 0'),
])
def test_builder_errors_are_the_validators_one_line_naming_the_field(arguments, message):
    with pytest.raises(SceneError) as error:
        build_scene(**arguments)
    assert str(error.value).startswith(message)


def test_walls_box_refuses_a_component_that_is_not_a_number():
    with pytest.raises(SceneError, match=r"^walls_box: low\[1\]: expected a number, got 'a'"):
        walls_box([0.0, 'a'])


# -- shared scenarios -----------------------------------------------------------------------

def test_cradle_balls_touch_exactly_and_the_striker_leads():
    balls = scenarios.cradle(5, 0.0625, 0.5, 1.0, -0.25)
    assert balls == load_scene_particles('cradle')
    x = [entry['position'][0] for entry in balls[1:]]
    assert np.all(np.diff(x) == 0.125)


def load_scene_particles(name: str) -> list:
    """Return a shipped scene's particle entries as its file writes them (floats)."""
    text = (TEST_DIR.parent / 'scenes' / f'{name}.yaml').read_text()
    return [scenarios.ball(entry['position'], entry['radius'], entry['mass'],
                           entry.get('velocity')) for entry in yaml.safe_load(text)['particles']]


def test_resting_pile_fits_between_its_walls_without_overlap():
    scene = parse_scene(scenarios.resting_pile(0.0, 4, 5), 'pile')
    s, walls = scene.initial, scene.effects.walls
    assert len(s) == 20
    assert np.all(s.position[:, 0] - s.radius >= walls.low[0])
    assert np.all(s.position[:, 0] + s.radius <= walls.high[0])
    gaps = np.linalg.norm(s.position[:, None] - s.position[None], axis=2)
    assert gaps[np.triu_indices(len(s), 1)].min() >= 2 * 0.05 * (1 - 1e-12)


def test_the_benchmarks_and_the_tests_share_the_scenarios():
    assert resting.scene('pile', 'fast') == dict(scenarios.resting_pile(), accuracy='fast')
    assert resting.scene('column', 'exact') == dict(scenarios.resting_column(), accuracy='exact')
    assert len(resting.scene('drop', 'fast')['particles']) == 501


# -- markers ------------------------------------------------------------------------------

def ros_user(path: Path) -> bool:
    """Say whether a test module starts ROS processes or tests a ROS front end."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        names = ([alias.name for alias in node.names] if isinstance(node, ast.Import) else
                 [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
        if any(name == 'node_harness' or name.startswith('collision_node.ros')
               or name.startswith('ament_index_python') for name in names):
            return True
    return False


def ros_marked(path: Path) -> bool:
    """Say whether a test module sets ``pytestmark = pytest.mark.ros`` at its top level."""
    return any(isinstance(node, ast.Assign) and ast.unparse(node) == 'pytestmark = pytest.mark.ros'
               for node in ast.parse(path.read_text()).body)


def test_every_test_of_a_ros_front_end_carries_the_ros_marker():
    marked = {path.name for path in TEST_DIR.glob('test_*.py') if ros_marked(path)}
    users = {path.name for path in TEST_DIR.glob('test_*.py') if ros_user(path)}
    assert users <= marked and 'test_node_topics.py' in users
    assert 'test_public_api.py' not in marked and 'test_outcome_digest.py' not in marked
