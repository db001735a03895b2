"""The node's commands over real topics and services: nothing lost, every answer matched.

One paused node on the default scene (16 balls on a 2.54 m x 1.27 m table)
serves the module; each test resets it first. The world is read back from
``particles/state``, so "unchanged" means the published state is identical.
"""

from __future__ import annotations

import json
import subprocess
import time

import numpy as np
import pytest
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.qos import HistoryPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from collision_node.physics.model.guard import MAX_TEXT_BYTES
from collision_node.ros.qos import SERVICE_QOS, STATUS_QOS
from msg_adapters import state_from_point_cloud
from msg_adapters.strings import string_bytes
from node_harness import executable, NodeUnderTest, ros_env, unique_domain_id

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

PARTICLES = 16
DT = 1.0 / 240.0
BURST = 2000                 # the target is 10,000: see docs/performance.md
KEEP_ALL = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture(scope='module')
def node():
    """One paused node shared by the tests of this module."""
    running = NodeUnderTest(['-p', 'paused:=true', '-p', 'max_particles:=5000'])
    running.answers = running.probe.collect(String, 'events', KEEP_ALL)
    running.clouds = running.probe.collect(PointCloud2, 'particles/state', 10)
    running.reset_client = running.probe.node.create_client(Trigger, 'reset')
    running.pause_client = running.probe.node.create_client(SetBool, 'pause')
    running.parameter_client = running.probe.node.create_client(
        SetParameters, 'collision_node/set_parameters')
    yield running
    code, _, err = running.stop()
    assert code == 0, err


@pytest.fixture
def fresh(node):
    """Reset the world (service) before a test; give the node."""
    assert node.reset(node.reset_client).success
    node.initial = world(node)
    return node


def world(node) -> dict:
    """Return the state the node publishes after every request answered so far.

    Clouds published before the last answer may still be queued: they are
    taken first (``drain``), then two more are waited for.
    """
    node.probe.drain()
    start = len(node.clouds)
    node.probe.wait_for(lambda: len(node.clouds) >= start + 2)
    return state_from_point_cloud(node.clouds[-1])


def send(node, topic: str, request) -> dict:
    """Publish one request (a mapping is sent as JSON) and return its answer."""
    text = request if isinstance(request, str) else json.dumps(request)
    pub = node.publisher(String, topic)
    start = len(node.answers)
    pub.publish(String(data=text))
    node.probe.wait_for(lambda: len(node.answers) > start)
    answer = json.loads(node.answers[start].data)
    assert answer['request'] == topic
    return answer


def assert_same_world(a: dict, b: dict) -> None:
    """Assert two published states are identical."""
    for key in ('ids', 'position', 'velocity', 'radius', 'mass'):
        np.testing.assert_array_equal(a[key], b[key])


def set_parameter(node, name: str, value) -> object:
    """Set one parameter through the parameter service; return its result."""
    if isinstance(value, bool):
        pv = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    elif isinstance(value, int):
        pv = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)
    else:
        pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
    request = SetParameters.Request(parameters=[Parameter(name=name, value=pv)])
    return node.probe.call(node.parameter_client, request).results[0]


def grid(k: int) -> tuple[float, float]:
    """Return the k-th place of a 1 cm grid 50 places wide in the table's lower left."""
    return -1.24 + 0.01 * (k % 50), -0.6 + 0.01 * (k // 50)


def test_a_burst_of_single_spawns_all_land_each_with_one_answer(fresh):
    pub = fresh.probe.node.create_publisher(String, 'spawn', KEEP_ALL)
    fresh.probe.wait_for(lambda: pub.get_subscription_count() > 0)
    start = len(fresh.answers)
    for k in range(BURST):        # a grid 1 cm apart, 50 wide, left of and below the cue ball
        x, y = grid(k)
        pub.publish(String(data=json.dumps({'position': [x, y], 'radius': 0.004,
                                            'mass': 0.01, 'request_id': f'b{k}'})))
    fresh.probe.wait_for(lambda: len(fresh.answers) >= start + BURST, timeout=300)
    answers = [json.loads(m.data) for m in fresh.answers[start:]]
    assert len(answers) == BURST
    assert sorted(a['request_id'] for a in answers) == sorted(f'b{k}' for k in range(BURST))
    assert all(a['accepted'] for a in answers), [a for a in answers if not a['accepted']][:1]
    seqs = [a['seq'] for a in answers]
    assert seqs == list(range(seqs[0], seqs[0] + BURST))
    # One publisher's messages arrive in order: request k got id 16 + k.
    assert [a['ids'] for a in answers] == [[[PARTICLES + k] * 2] for k in range(BURST)]
    state = world(fresh)
    assert len(state['ids']) == PARTICLES + BURST
    np.testing.assert_array_equal(state['position'][PARTICLES + 1234], [*grid(1234), 0.0])


def test_request_id_is_echoed_and_seq_counts_up(fresh):
    one = send(fresh, 'spawn', {'position': [0.0, 0.4], 'radius': 0.02, 'mass': 1,
                                'request_id': 'first'})
    two = send(fresh, 'spawn', {'particles': [{'position': [0.1, 0.4], 'radius': 0.02,
                                               'mass': 1}], 'request_id': 42})
    bad = send(fresh, 'spawn', {'position': [0.2, 0.4], 'radius': -1, 'mass': 1,
                                'request_id': 3.5})
    unparsable = send(fresh, 'spawn', '{position: [0')
    assert (one['request_id'], two['request_id'], bad['request_id']) == ('first', 42, 3.5)
    assert unparsable['request_id'] is None and 'not valid YAML' in unparsable['reason']
    assert [one['seq'] + k for k in range(4)] == [a['seq'] for a in (one, two, bad,
                                                                     unparsable)]
    odd = send(fresh, 'delete', {'ids': [0], 'request_id': [1, 2]})
    assert not odd['accepted'] and 'request_id: expected a string or a finite number' in \
        odd['reason']


def test_id_lists_are_inclusive_ranges(fresh):
    gas = send(fresh, 'spawn', {'kind': 'gas', 'count': 300, 'radius': 0.005, 'mass': 0.01,
                                'region': {'min': [-1.25, -0.6], 'max': [-0.8, 0.6]}})
    assert gas['accepted'] and gas['ids'] == [[PARTICLES, PARTICLES + 299]]
    gone = send(fresh, 'delete', {'ids': [3, 4, 5, [20, 29], 40]})
    assert gone['ids'] == [[3, 5], [20, 29], [40, 40]]
    assert gone['particles'] == PARTICLES + 300 - 14


def test_delete_keeps_ids_stable_and_refusals_change_nothing(fresh):
    answer = send(fresh, 'delete', {'ids': [0, [5, 6]], 'request_id': 'd'})
    assert answer['accepted'] and answer['ids'] == [[0, 0], [5, 6]]
    state = world(fresh)
    assert state['ids'].tolist() == [1, 2, 3, 4] + list(range(7, PARTICLES))
    np.testing.assert_array_equal(state['position'], fresh.initial['position'][
        [1, 2, 3, 4] + list(range(7, PARTICLES))])
    spawned = send(fresh, 'spawn', {'position': [0.0, 0.4], 'radius': 0.02, 'mass': 1})
    assert spawned['ids'] == [[PARTICLES, PARTICLES]]             # deleted ids are not reused
    before = world(fresh)
    for request, says in [({'ids': [1, 99]}, 'delete: ids: no particle with id 99'),
                          ({'ids': [0]}, 'no particle with id 0'),
                          ('{ids: [1, x]}', 'expected an integer id'),
                          ({'id': 1}, 'unknown key')]:
        refused = send(fresh, 'delete', request)
        assert not refused['accepted'] and says in refused['reason']
    assert_same_world(world(fresh), before)


def test_teleport_sets_position_and_velocity_and_refuses_bad_places(fresh):
    answer = send(fresh, 'teleport', {'id': 3, 'position': [-0.2, 0.3], 'velocity': [0.5, 0],
                                      'request_id': 't'})
    assert answer['accepted'] and answer['ids'] == [[3, 3]]
    assert answer['position'] == [-0.2, 0.3, 0.0] and answer['velocity'] == [0.5, 0.0, 0.0]
    state = world(fresh)
    np.testing.assert_array_equal(state['position'][3], [-0.2, 0.3, 0.0])
    np.testing.assert_array_equal(state['velocity'][3], [0.5, 0.0, 0.0])
    before = state
    for request, says in [({'id': 3, 'position': [50, 50]}, 'not inside the walls'),
                          ({'id': 3, 'position': [-0.635, 0.01]}, 'overlaps particle 0'),
                          ({'id': 77, 'velocity': [1, 0]}, 'no particle with id 77'),
                          ({'id': 3}, 'give position and/or velocity'),
                          ({'id': 3, 'velocity': ['fast', 0]}, 'expected a number')]:
        refused = send(fresh, 'teleport', request)
        assert not refused['accepted'] and says in refused['reason'], refused
    assert_same_world(world(fresh), before)
    overlap = send(fresh, 'teleport', {'id': 3, 'position': [-0.635, 0.01],
                                       'allow_overlap': True})
    assert overlap['accepted']


def test_impulse_adds_j_over_m_and_refusals_change_nothing(fresh):
    answer = send(fresh, 'impulse', {'id': 2, 'impulse': [0.017, -0.034]})   # m = 0.17 kg
    assert answer['accepted']
    np.testing.assert_allclose(answer['velocity'], [0.1, -0.2, 0.0], rtol=1e-15)
    np.testing.assert_allclose(world(fresh)['velocity'][2], [0.1, -0.2, 0.0], rtol=1e-15)
    before = world(fresh)
    for request, says in [({'id': 2, 'impulse': [1e12, 0]}, 'speed'),
                          ({'id': 2}, 'impulse: impulse: missing'),
                          ({'id': 2, 'impulse': [0, 0, 1]}, 'z must be 0')]:
        refused = send(fresh, 'impulse', request)
        assert not refused['accepted'] and says in refused['reason']
    assert_same_world(world(fresh), before)


def test_spawn_outside_the_walls_or_overlapping_is_refused_unless_allowed(fresh):
    outside = send(fresh, 'spawn', {'position': [50, 50], 'radius': 0.03, 'mass': 0.17})
    assert not outside['accepted']
    assert 'position [50, 50] with radius 0.03 is not inside the walls [-1.27, -0.635] .. ' \
           '[1.27, 0.635]' in outside['reason']
    on_top = send(fresh, 'spawn', {'position': [-0.635, 0.0], 'radius': 0.03, 'mass': 0.17})
    assert not on_top['accepted'] and 'overlaps particle 0' in on_top['reason']
    assert_same_world(world(fresh), fresh.initial)
    allowed = send(fresh, 'spawn', {'position': [-0.635, 0.0], 'radius': 0.03, 'mass': 0.17,
                                    'allow_overlap': True})
    assert allowed['accepted'] and allowed['ids'] == [[PARTICLES, PARTICLES]]


def test_step_while_paused_then_pause_service_resumes(fresh):
    answer = send(fresh, 'step', {'steps': 24, 'request_id': 's'})
    assert answer['accepted'] and answer['steps'] == 24
    assert answer['time'] == pytest.approx(24 * DT, rel=1e-12)
    state = world(fresh)
    np.testing.assert_allclose(state['position'][0], [-0.635 + 5.0 * 24 * DT, 0, 0],
                               rtol=1e-12)
    assert not send(fresh, 'step', '0')['accepted']
    assert not send(fresh, 'step', {'steps': 'many'})['accepted']
    reply = fresh.probe.call(fresh.pause_client, SetBool.Request(data=False))
    try:
        assert reply.success
        assert fresh.next_status(lambda s: not s['paused'])['paused'] is False
        refused = send(fresh, 'step', '5')
        assert not refused['accepted'] and 'pause it first' in refused['reason']
    finally:
        assert fresh.probe.call(fresh.pause_client, SetBool.Request(data=True)).success
    assert fresh.next_status(lambda s: s['paused'])['paused'] is True


def test_500_concurrent_pause_calls_from_one_client_are_all_answered(fresh):
    """The node's services keep every request until taken (the default depth was 10)."""
    # The client's own queue must be deep too, or it drops answers itself (qos.py).
    client = fresh.probe.node.create_client(SetBool, 'pause', qos_profile=SERVICE_QOS)
    assert client.wait_for_service(timeout_sec=15)
    start = len(fresh.answers)
    futures = [client.call_async(SetBool.Request(data=True)) for _ in range(500)]
    try:
        fresh.probe.wait_for(lambda: all(f.done() for f in futures), timeout=120)
    finally:
        answered = sum(f.done() for f in futures)
        for future in futures:
            if not future.done():
                client.remove_pending_request(future)
    assert answered == 500
    assert all(f.result().success and f.result().message.startswith('paused at time 0 s')
               for f in futures)
    # Each call is answered on events too.
    fresh.probe.wait_for(lambda: len(fresh.answers) >= start + 500)
    answers = [json.loads(m.data) for m in fresh.answers[start:]]
    assert [a['request'] for a in answers] == ['pause'] * 500
    assert all(a['accepted'] and a['paused'] for a in answers)


def test_integer_values_for_double_parameters_are_accepted(node):
    try:
        assert set_parameter(node, 'real_time_factor', 2).successful
        assert node.next_status(lambda s: s['real_time_factor'] == 2.0)
        refused = set_parameter(node, 'real_time_factor', 0)
        assert not refused.successful and 'range' in refused.reason
    finally:
        assert set_parameter(node, 'real_time_factor', 1.0).successful


def test_integer_parameters_on_the_command_line_and_a_new_publish_rate_at_once():
    running = NodeUnderTest(['-p', 'real_time_factor:=2', '-p', 'publish_rate:=0.1'])
    try:
        status = running.status()
        assert status['real_time_factor'] == 2.0 and status['publish_rate'] == 0.1
        clocks = running.probe.collect(Clock, '/clock', 10)
        client = running.probe.node.create_client(SetParameters,
                                                  'collision_node/set_parameters')
        running.parameter_client = client
        assert set_parameter(running, 'publish_rate', 30).successful
        changed = time.monotonic()
        # At 30 Hz ten ticks take a third of a second; the old 10 s period
        # would hold the first of them back until its deadline.
        running.probe.wait_for(lambda: len(clocks) >= 10, timeout=5.0)
        assert time.monotonic() - changed < 2.0
    finally:
        code, _, err = running.stop()
    assert code == 0, err


def test_clock_never_runs_ahead_of_wall_time_at_a_high_publish_rate():
    running = NodeUnderTest(['-p', 'publish_rate:=1000.0'])
    try:
        samples = []
        # A kHz reader subscribes best effort (what sensor-data readers do). Its
        # stream may still pause when this process is starved: Fast DDS's shared
        # memory transport gives up on a reader that does not drain its port in
        # time. So /clock is checked over what arrives, and the long span over
        # the reliable status, which carries the same simulated time.
        running.probe.node.create_subscription(
            Clock, '/clock',
            lambda m: samples.append((time.monotonic(), m.clock.sec + 1e-9 * m.clock.nanosec)),
            qos_profile_sensor_data)
        statuses = []
        running.probe.node.create_subscription(
            String, 'status', lambda m: statuses.append((time.monotonic(), json.loads(m.data))),
            STATUS_QOS)
        # The first status may be the latched one from before this subscription.
        running.probe.wait_for(lambda: len(statuses) >= 2
                               and statuses[-1][0] - statuses[1][0] > 3.0, timeout=30.0)
        (first_wall, first), (last_wall, last) = statuses[1], statuses[-1]
        # Receipt times carry at most one spin period (0.05 s) of latency each.
        assert 0.0 < last['time'] - first['time'] <= 1.02 * (last_wall - first_wall) + 0.05
        running.probe.wait_for(lambda: len(samples) >= 20, timeout=15.0)
        (wall0, sim0), (wall1, sim1) = samples[0], samples[-1]
        assert all(b[1] >= a[1] for a, b in zip(samples, samples[1:]))
        assert 0.0 < (sim1 - sim0) <= 1.02 * (wall1 - wall0) + 0.05
        assert running.status()['dropped_backlog_s'] >= 0.0
    finally:
        code, _, err = running.stop()
    assert code == 0, err


def run_node(*args: str) -> subprocess.CompletedProcess:
    """Run the installed node with ``args`` until it exits."""
    return subprocess.run([executable('collision_node'), *args], capture_output=True,
                          text=True, timeout=60, env=ros_env(unique_domain_id()))


def test_help_prints_parameters_and_topics_and_exits_0():
    result = run_node('--help')
    assert result.returncode == 0, result.stderr
    for name in ('real_time_factor (double, default 1.0)', 'frame_id', 'max_particles',
                 'teleport', 'impulse', 'pause', '/clock'):
        assert name in result.stdout


def test_unknown_arguments_exit_2_with_one_line():
    result = run_node('--speed', '3', '--ros-args', '-p', 'paused:=true')
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and 'unrecognized arguments: --speed 3' in lines[0]


def send_bytes(node, data: bytes) -> dict:
    """Publish serialised bytes on ``spawn`` as they are and return the answer."""
    pub = node.publisher(String, 'spawn')
    start = len(node.answers)
    pub.publish(data)
    node.probe.wait_for(lambda: len(node.answers) > start)
    return json.loads(node.answers[start].data)


def test_requests_are_read_from_their_bytes_as_rclpy_reads_them(fresh):
    # Over the limit by its length field alone: refused before any text is made.
    big = string_bytes('{"position": [0, 0.4], "radius": 0.02, "mass": 1, "c": "'
                       + 'x' * MAX_TEXT_BYTES + '"}')
    over = send_bytes(fresh, big)
    assert not over['accepted'] and over['request_id'] is None
    assert over['reason'] == (f'spawn: text of {len(big) - 9} bytes (or more) is over the '
                              f'limit of {MAX_TEXT_BYTES} bytes (1 MiB)')
    # A length that runs past the message: not a String, one line saying so.
    broken = send_bytes(fresh, b'\x00\x01\x00\x00' + (100).to_bytes(4, 'little') + b'{}\x00')
    # (The middleware pads the 11 bytes to a multiple of 4.)
    assert not broken['accepted'] and broken['reason'] == (
        'spawn: not a std_msgs/String: string length 100 runs past the end of a 12-byte '
        'message')
    # (An earlier test resumed the world, so only the particle set is compared.)
    assert world(fresh)['ids'].tolist() == fresh.initial['ids'].tolist()
    # Invalid UTF-8 becomes U+FFFD and the text ends at a NUL, as with rclpy.
    text = b'{"position": [0, 0.4], "radius": 0.02, "mass": 1, "request_id": "a\xffb"}'
    odd = b'\x00\x01\x00\x00' + (len(text) + 6).to_bytes(4, 'little') + text + b'\x00junk\x00'
    accepted = send_bytes(fresh, odd)
    assert accepted['accepted'] and accepted['request_id'] == 'a\ufffdb'
    assert accepted['request_id'] == json.loads(deserialize_message(odd, String).data)[
        'request_id']
    assert len(world(fresh)['ids']) == PARTICLES + 1
