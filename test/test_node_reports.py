"""The node's reports over real topics: /diagnostics and particles/collisions.

The collision tests run a head-on pair whose single impact the lecture's
formulas predict (time, closing speed, impulse j = (1 + e) m1 m2 / (m1 + m2)
|v_rel|) and compare the topic with the core's own impact list for the same
scene, field by field. They need the contact law to record impacts
(``ctx.impacts``); the recording switch itself is tested in-process here.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.clock import Clock, ClockType
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from collision_node.physics.model.impacts import IMPACT_DTYPE
from collision_node.physics.model.scene import load_scene
from collision_node.physics.step.world import World
from collision_node.ros.qos import COLLISIONS_QOS
from collision_node.ros.reports import Reports
from msg_adapters import impacts_from_point_cloud, seconds_from_stamp
from node_harness import executable, NodeUnderTest, ros_env, unique_domain_id

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

# Two balls closing at 1 m/s with 4.0005 m between their surfaces: one impact at
# t = 4.0005 s (inside a step of 1 ms), late enough for a subscriber to be listening.
M1, M2, V1, V2, RADIUS = 1.0, 3.0, 0.5, -0.5, 0.1
GAP = 4.0005
IMPACT_TIME = GAP / (V1 - V2)
IMPULSE = 2.0 * M1 * M2 / (M1 + M2) * (V1 - V2)      # e = 1: 1.5 N s
HEAD_ON = {
    'name': 'head_on', 'dimensions': 3, 'dt': 0.001,
    'particles': [
        {'position': [-(RADIUS + GAP / 2), 0, 0], 'velocity': [V1, 0, 0], 'radius': RADIUS,
         'mass': M1},
        {'position': [RADIUS + GAP / 2, 0, 0], 'velocity': [V2, 0, 0], 'radius': RADIUS,
         'mass': M2}]}
STEPS = 4200                                          # t = 4.2 s, well past the impact


@pytest.fixture(scope='module')
def head_on_scene(tmp_path_factory):
    """Write the head-on scene to a file; return its path."""
    path = tmp_path_factory.mktemp('scenes') / 'head_on.yaml'
    path.write_text(yaml.safe_dump(HEAD_ON))
    return path


def diagnostic_values(msg: DiagnosticArray) -> tuple[DiagnosticStatus, dict]:
    """Return the node's one status and its values as a dict."""
    assert len(msg.status) == 1
    return msg.status[0], {kv.key: kv.value for kv in msg.status[0].values}


def test_diagnostics_report_a_healthy_world(head_on_scene):
    # Paused and stepped by request: the world advances exactly 120 steps whatever
    # the machine's load, so the report's level and values are deterministic.
    node = NodeUnderTest(['-p', f'scene:={head_on_scene}', '-p', 'paused:=true'])
    try:
        arrays = node.probe.collect(DiagnosticArray, '/diagnostics', 10)
        answer = node.request(String, 'step', String(data=json.dumps({'steps': 120})))
        assert answer['accepted'], answer
        msg = node.probe.next_message(
            arrays, where=lambda m: diagnostic_values(m)[1]['steps'] == '120')
        status, values = diagnostic_values(msg)
        assert (status.level, status.name, status.message, status.hardware_id) == (
            DiagnosticStatus.OK, 'collision_node: simulation', 'paused', 'head_on')
        assert values['particles'] == '2' and values['keeping_up'] == 'true'
        assert values['paused'] == 'true'
        assert float(values['time']) == pytest.approx(120 * HEAD_ON['dt'], rel=1e-12)
        assert float(values['dropped_backlog_s']) == 0.0 and values['fallback_steps'] == '0'
        assert float(values['energy_balance_relative_error']) < 1e-12
        # Stamped with the node's clock (wall time), not the simulated time.
        assert abs(seconds_from_stamp(msg.header.stamp) - node.probe.node.get_clock().now()
                   .nanoseconds * 1e-9) < 30.0
    finally:
        code, _, err = node.stop()
    assert code == 0, err


def test_diagnostics_warn_when_the_node_cannot_keep_up():
    # The default 16-ball break at 1000x real time needs 240,000 steps per second.
    node = NodeUnderTest(['-p', 'real_time_factor:=1000.0'])
    try:
        arrays = node.probe.collect(DiagnosticArray, '/diagnostics', 10)
        msg = node.probe.next_message(
            arrays, timeout=30.0,
            where=lambda m: m.status[0].level == DiagnosticStatus.WARN)
        status, values = diagnostic_values(msg)
        assert status.message.startswith('not keeping up with real-time factor 1000 (measured ')
        assert values['keeping_up'] == 'false' and values['real_time_factor'] == '1000.0'
        assert float(values['measured_real_time_factor']) < 1000.0
    finally:
        code, _, err = node.stop()
    assert code == 0, err


def test_impacts_are_recorded_only_while_somebody_subscribes(head_on_scene):
    context = Context()
    rclpy.init(context=context, domain_id=unique_domain_id())
    try:
        node = rclpy.create_node('reports_probe', context=context,
                                 start_parameter_services=False)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        world = World(load_scene(head_on_scene))
        reports = Reports(node, lambda: {}, Clock(clock_type=ClockType.STEADY_TIME))

        def spin_until(condition):
            for _ in range(200):
                if condition():
                    return
                executor.spin_once(timeout_sec=0.05)
            raise AssertionError('timed out')
        reports.publish_collisions(world, 0.0, 'world')
        assert world.impact_log is None                  # nobody listens: nothing recorded
        received = []
        subscription = node.create_subscription(PointCloud2, 'particles/collisions',
                                                received.append, COLLISIONS_QOS)
        spin_until(lambda: reports.pub_collisions.get_subscription_count() == 1)
        reports.publish_collisions(world, 0.0, 'world')
        assert world.impact_log is not None              # the first subscriber switched it on
        world.step(10)
        reports.publish_collisions(world, world.time, 'world')
        spin_until(lambda: received)
        assert received[0].width == 0 and seconds_from_stamp(received[0].header.stamp) == 0.01
        node.destroy_subscription(subscription)
        spin_until(lambda: reports.pub_collisions.get_subscription_count() == 0)
        reports.publish_collisions(world, world.time, 'world')
        assert world.impact_log is None                  # the last one left: off again
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def core_impacts(scene_path) -> np.ndarray:
    """Return the impacts the core resolves in STEPS steps of the scene."""
    world = World(load_scene(scene_path))
    world.record_impacts(True)
    world.step(STEPS)
    return world.take_impacts()


def test_core_head_on_impact_matches_the_lecture(head_on_scene):
    # Needs the contact law recording impacts (ctx.impacts).
    impacts = core_impacts(head_on_scene)
    assert impacts.size == 1
    impact = impacts[0]
    assert impact['time'] == pytest.approx(IMPACT_TIME, abs=1e-9)
    assert sorted([impact['i'], impact['j']]) == [0, 1]
    # The normal points from j to i: along -x if i is the left ball (id 0).
    assert impact['normal'] == pytest.approx([-1.0 if impact['i'] == 0 else 1.0, 0, 0])
    assert impact['point'] == pytest.approx([0.0, 0.0, 0.0], abs=1e-9)
    assert impact['normal_impulse'] == pytest.approx(IMPULSE, rel=1e-12)
    assert impact['tangential_impulse'] == 0.0
    assert impact['closing_speed'] == pytest.approx(V1 - V2, rel=1e-12)


def test_collisions_topic_carries_the_cores_impacts(head_on_scene):
    # Needs the contact law recording impacts (ctx.impacts).
    expected = core_impacts(head_on_scene)
    node = NodeUnderTest(['-p', f'scene:={head_on_scene}'])
    try:
        clouds = node.probe.collect(PointCloud2, 'particles/collisions', 100)
        first = node.probe.next_message(clouds)
        assert seconds_from_stamp(first.header.stamp) < IMPACT_TIME, \
            'the subscription came too late to see the impact'
        node.probe.wait_for(lambda: seconds_from_stamp(clouds[-1].header.stamp)
                            > STEPS * HEAD_ON['dt'], timeout=30.0)
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    stamps = [seconds_from_stamp(m.header.stamp) for m in clouds]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))    # one message per tick
    batches = [(stamp, impacts_from_point_cloud(m)) for stamp, m in zip(stamps, clouds)]
    got = {name: np.concatenate([b[name] for _, b in batches]) for name in IMPACT_DTYPE.names}
    for name in IMPACT_DTYPE.names:
        np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
    # The impact arrives with the first tick at or after it.
    stamp = next(s for s, b in batches if b['time'].size)
    assert IMPACT_TIME <= stamp < IMPACT_TIME + 0.5


def test_viewer_prints_the_impact(head_on_scene):
    # The node waits, paused, until it records impacts for the viewer, so a slow
    # viewer start cannot miss the impact at 4 s.
    node = NodeUnderTest(['-p', f'scene:={head_on_scene}', '-p', 'paused:=true'])
    try:
        viewer = subprocess.Popen([executable('viewer'), '--collisions', '--once', '--timeout',
                                   '60'], env=ros_env(node.domain_id), stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        # The node says when it records impacts for a subscriber (status, every 0.5 s).
        node.probe.next_message(
            node.statuses, timeout=60.0,
            where=lambda m: json.loads(m.data)['recording_impacts'] or viewer.poll() is not None)
        answer = node.request(String, 'step', String(data=json.dumps({'steps': STEPS})))
        assert answer['accepted'], answer
        stdout, stderr = viewer.communicate(timeout=90)
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    assert viewer.returncode == 0, stderr
    line, = stdout.splitlines()
    assert line.startswith(('t = 4.000500 s  0 - 1  at (', 't = 4.000500 s  1 - 0  at (')), line
    assert line.endswith('J = 1.5 N s  Jt = 0 N s  closing 1 m/s'), line
