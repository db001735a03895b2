"""Spawn, reset and parameters of the installed node, over real topics and services.

The node runs paused, so the state it publishes is exactly the state it
holds: spawned particles can be compared field by field.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Empty, String
from std_srvs.srv import Trigger

from msg_adapters import state_from_point_cloud
from node_harness import NodeUnderTest, output

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

PARTICLES = 16           # the default scene, scenes/elastic_break.yaml
CUE_SPEED = 5.0
MAX_PARTICLES = 40


@pytest.fixture(scope='module')
def node():
    """One paused node on the default scene, shared by the tests of this module."""
    running = NodeUnderTest(['-p', 'paused:=true', '-p', f'max_particles:={MAX_PARTICLES}',
                             '-p', 'publish_rate:=30.0'])
    running.clouds = running.probe.collect(PointCloud2, 'particles/state', 10)
    running.reset_client = running.probe.node.create_client(Trigger, 'reset')
    running.parameter_client = running.probe.node.create_client(
        SetParameters, 'collision_node/set_parameters')
    running.initial = world(running)
    yield running
    code, _, err = running.stop()
    assert code == 0, err


@pytest.fixture
def fresh(node):
    """Reset the world (service) before a test; give the node."""
    assert node.reset(node.reset_client).success
    return node


def world(node) -> dict:
    """Return the state the node publishes from now on.

    Clouds published before the last answer may still be queued (the probe
    spins only while a test waits): they are taken first (``drain``); the
    second cloud received after that is published after every request
    answered so far.
    """
    node.probe.drain()
    start = len(node.clouds)
    node.probe.wait_for(lambda: len(node.clouds) >= start + 2)
    return state_from_point_cloud(node.clouds[-1])


def spawn(node, text: str) -> dict:
    """Send a spawn request and return its answer."""
    event = node.request(String, 'spawn', String(data=text))
    assert event['request'] == 'spawn'
    return event


def set_parameters(node, **values) -> list:
    """Set parameters through the node's parameter service; return the results."""
    request = SetParameters.Request()
    for name, value in values.items():
        if isinstance(value, bool):
            pv = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
        elif isinstance(value, int):
            pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
        elif isinstance(value, float):
            pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        else:
            pv = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
        request.parameters.append(Parameter(name=name, value=pv))
    return node.probe.call(node.parameter_client, request).results


def assert_same_world(a: dict, b: dict) -> None:
    """Assert two published states are identical."""
    for key in ('ids', 'position', 'velocity', 'radius', 'mass'):
        np.testing.assert_array_equal(a[key], b[key])


def test_initial_world_is_the_default_break(node):
    assert node.initial['ids'].tolist() == list(range(PARTICLES))
    np.testing.assert_array_equal(node.initial['position'][0], [-0.635, 0.0, 0.0])
    np.testing.assert_array_equal(node.initial['velocity'][0], [CUE_SPEED, 0.0, 0.0])


def test_spawn_one_particle_with_the_requested_state(fresh):
    event = spawn(fresh, '{position: [0.5, 0.3], velocity: [1.0, -2.0], radius: 0.05, '
                         'mass: 2.0}')
    assert event['accepted'] and event['ids'] == [[PARTICLES, PARTICLES]]
    state = world(fresh)
    assert state['ids'].tolist() == list(range(PARTICLES + 1))
    np.testing.assert_array_equal(state['position'][-1], [0.5, 0.3, 0.0])
    np.testing.assert_array_equal(state['velocity'][-1], [1.0, -2.0, 0.0])
    assert state['radius'][-1] == 0.05 and state['mass'][-1] == 2.0
    np.testing.assert_array_equal(state['position'][:PARTICLES], fresh.initial['position'])


def test_spawn_json_list_appends_in_order(fresh):
    particles = [{'position': [0.0, 0.4], 'radius': 0.02, 'mass': 1.0},
                 {'position': [0.2, 0.4], 'velocity': [0.0, 1.5], 'radius': 0.03, 'mass': 3.0}]
    event = spawn(fresh, json.dumps(particles))
    assert event['accepted'] and event['ids'] == [[PARTICLES, PARTICLES + 1]]
    state = world(fresh)
    np.testing.assert_array_equal(state['position'][PARTICLES:], [[0.0, 0.4, 0.0],
                                                                  [0.2, 0.4, 0.0]])
    np.testing.assert_array_equal(state['radius'][PARTICLES:], [0.02, 0.03])
    np.testing.assert_array_equal(state['mass'][PARTICLES:], [1.0, 3.0])


def test_spawn_generate_entry_adds_count_particles(fresh):
    event = spawn(fresh, 'kind: gas\ncount: 5\nradius: 0.01\nmass: 0.1\nspeed: 2.0\n'
                         'seed: 3\nregion: {min: [-1.2, -0.5], max: [-0.7, 0.5]}')
    assert event['accepted'] and event['ids'] == [[PARTICLES, PARTICLES + 4]]
    state = world(fresh)
    assert len(state['ids']) == PARTICLES + 5
    new = slice(PARTICLES, None)
    np.testing.assert_allclose(np.linalg.norm(state['velocity'][new], axis=1), 2.0)
    assert np.all((state['position'][new, 0] > -1.2) & (state['position'][new, 0] < -0.7))
    assert np.all(state['radius'][new] == 0.01)


BAD_SPAWNS = {
    'malformed YAML': ('{position: [0, 0', 'not valid YAML'),
    'not a mapping': ('42', 'spawn'),
    'unknown field': ('{position: [0, 0], radius: 0.1, mass: 1, colour: red}', 'colour'),
    'missing field': ('{position: [0, 0], mass: 1}', 'radius'),
    'wrong shape': ('{position: [0, 0, 0, 0], radius: 0.1, mass: 1}', 'position'),
    'z off the plane': ('{position: [0, 0, 1], radius: 0.1, mass: 1}', 'position'),
    'NaN': ('{position: [.nan, 0], radius: 0.1, mass: 1}', 'position'),
    'inf': ('{position: [0, 0], velocity: [.inf, 0], radius: 0.1, mass: 1}', 'velocity'),
    'zero radius': ('{position: [0, 0], radius: 0, mass: 1}', 'radius'),
    'negative radius': ('{position: [0, 0], radius: -1, mass: 1}', 'radius'),
    'moving static particle': ('{position: [0, 0], velocity: [1, 0], radius: 0.1, '
                               'mass: .inf}', 'velocity'),
    'zero mass': ('{position: [0, 0], radius: 0.1, mass: 0}', 'mass'),
    'negative mass': ('{position: [0, 0], radius: 0.1, mass: -2}', 'mass'),
    'bad entry in a batch': ('[{position: [0, 0.5], radius: 0.01, mass: 1}, '
                             '{position: [0, 0], radius: -0.1, mass: 1}]',
                             'particles[1].radius'),
    'over max_particles': ('{kind: gas, count: 30, radius: 0.01, mass: 1, '
                           'region: {min: [-1, -0.5], max: [0, 0.5]}}', 'max_particles'),
}


@pytest.mark.parametrize('text, reason', BAD_SPAWNS.values(), ids=BAD_SPAWNS.keys())
def test_bad_spawn_is_rejected_whole_and_the_world_is_unchanged(fresh, text, reason):
    event = spawn(fresh, text)
    assert event['accepted'] is False
    assert reason in event['reason']
    assert '\n' not in event['reason']
    assert event['particles'] == PARTICLES
    assert_same_world(world(fresh), fresh.initial)


def test_a_rejection_logs_exactly_one_warning(fresh):
    event = spawn(fresh, '{position: [0, 0], radius: 0.1, mass: 1, marker_7f3a: 1}')
    assert not event['accepted']
    world(fresh)           # the node has moved on to later ticks
    _, err = output(fresh.process)
    lines = [line for line in err.splitlines() if 'marker_7f3a' in line]
    assert len(lines) == 1 and '[WARN]' in lines[0]


def test_reset_topic_removes_spawned_particles(fresh):
    assert spawn(fresh, '{position: [0.1, 0.1], radius: 0.02, mass: 1}')['accepted']
    assert len(world(fresh)['ids']) == PARTICLES + 1
    event = fresh.request(Empty, 'reset', Empty())
    assert event['request'] == 'reset' and event['accepted']
    assert event['ids'] == [[0, PARTICLES - 1]]
    assert_same_world(world(fresh), fresh.initial)


def test_parameter_changes_take_effect_and_reset_restores_time_zero(fresh):
    results = set_parameters(fresh, paused=False)
    assert results[0].successful
    try:
        moving = fresh.next_status(lambda s: s['time'] > 0.1)
        assert not moving['paused'] and moving['particles'] == PARTICLES
        seen = len(fresh.statuses)
        response = fresh.reset(fresh.reset_client)
        assert response.success and 'time 0' in response.message
        # The node announces the reset in a status before it replies.
        after = fresh.probe.wait_for(lambda: [json.loads(m.data) for m in
                                              fresh.statuses[seen:]])
        assert after[0]['steps'] == 0 and after[0]['time'] == 0.0
        assert after[0]['particles'] == PARTICLES
    finally:
        assert set_parameters(fresh, paused=True)[0].successful
    poses = fresh.probe.collect(PoseArray, 'particles/poses', 10)
    assert set_parameters(fresh, frame_id='map')[0].successful
    try:
        assert fresh.probe.next_message(poses, where=lambda m: m.header.frame_id == 'map')
    finally:
        assert set_parameters(fresh, frame_id='world')[0].successful


@pytest.mark.parametrize('name, value, why', [
    ('real_time_factor', -1.0, 'range'),
    ('real_time_factor', math.nan, 'range'),
    ('publish_rate', 0.0, 'range'),
    ('real_time_factor', 'fast', 'type'),
    ('publish_rate', 5000, 'range'),
    ('frame_id', 'a\tb', 'frame name'),
    ('frame_id', 'map\n', 'frame name'),
    ('frame_id', 'x' * 1_000_000, 'longer than 256'),
    ('frame_id', '', 'frame_id'),
    ('scene', 'oblique_pair', 'read-only'),
    ('max_particles', 10, 'read-only'),
    ('threads', 1, 'read-only'),
])
def test_invalid_parameter_is_refused_with_a_reason(node, name, value, why):
    result = set_parameters(node, **{name: value})[0]
    assert not result.successful
    assert why in result.reason.lower().replace('read only', 'read-only')
    defaults = {'real_time_factor': 1.0, 'publish_rate': 30.0, 'frame_id': 'world'}
    if name in defaults:
        assert node.status()[name] == defaults[name]
