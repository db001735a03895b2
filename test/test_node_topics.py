"""The installed node's outputs over real topics: rates, counts, stamps, frames."""

from __future__ import annotations

import statistics
import time

import numpy as np
import pytest
from geometry_msgs.msg import PoseArray, VelocityStamped
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from msg_adapters import (particle_id_from_frame, poses_from_pose_array, seconds_from_stamp,
                          state_from_point_cloud)
from node_harness import NodeUnderTest

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

RATE = 20.0
# The default scene, scenes/elastic_break.yaml: a billiards break.
PARTICLES = 16
BALL_RADIUS = 0.028575
BALL_MASS = 0.17
CUE_SPEED = 5.0


@pytest.fixture(scope='module')
def node():
    """One node on the default scene, publishing at RATE, in a namespace."""
    running = NodeUnderTest(['-p', f'publish_rate:={RATE}'], namespace='/table')
    yield running
    code, _, err = running.stop()
    assert code == 0, err


def test_poses_arrive_at_the_publish_rate_with_every_particle(node):
    arrivals = []
    node.probe.node.create_subscription(
        PoseArray, 'table/particles/poses', lambda m: arrivals.append((time.monotonic(), m)),
        10)
    node.probe.wait_for(lambda: len(arrivals) >= 12)
    poses = [msg for _, msg in arrivals]
    assert all(len(msg.poses) == PARTICLES for msg in poses)
    assert all(msg.header.frame_id == 'world' for msg in poses)
    interval = statistics.median(np.diff([t for t, _ in arrivals]))
    assert 0.5 / RATE < interval < 2.0 / RATE
    # Simulated time follows wall time (factor 1): one publish period per message.
    stamps = [seconds_from_stamp(msg.header.stamp) for msg in poses]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert 0.5 / RATE < statistics.median(np.diff(stamps)) < 2.0 / RATE


def test_clock_advances_with_simulated_time(node):
    clock = node.probe.collect(Clock, '/clock', 10)
    node.probe.wait_for(lambda: len(clock) >= 5)
    times = [seconds_from_stamp(msg.clock) for msg in clock]
    assert all(b > a for a, b in zip(times, times[1:]))
    assert times[-1] > 0.0


def test_messages_of_one_tick_share_stamp_and_state(node):
    poses = node.probe.collect(PoseArray, 'table/particles/poses', 10)
    clouds = node.probe.collect(PointCloud2, 'table/particles/state', 10)

    def pair():
        by_stamp = {seconds_from_stamp(m.header.stamp): m for m in clouds}
        for msg in poses:
            cloud = by_stamp.get(seconds_from_stamp(msg.header.stamp))
            if cloud is not None:
                return msg, cloud
        return None
    pose_msg, cloud_msg = node.probe.wait_for(pair)
    state = state_from_point_cloud(cloud_msg)
    position, orientation = poses_from_pose_array(pose_msg)
    np.testing.assert_array_equal(state['ids'], np.arange(PARTICLES))
    np.testing.assert_array_equal(state['position'], position)
    np.testing.assert_array_equal(orientation, np.tile([0.0, 0.0, 0.0, 1.0], (PARTICLES, 1)))
    np.testing.assert_allclose(state['radius'], BALL_RADIUS)
    np.testing.assert_allclose(state['mass'], BALL_MASS)
    assert np.all(state['position'][:, 2] == 0.0)          # a 2-D scene


def test_velocities_name_every_particle_each_tick(node):
    velocities = node.probe.collect(VelocityStamped, 'table/particles/velocities', 1000)

    def full_tick():
        ticks = {}
        for msg in velocities:
            ticks.setdefault(seconds_from_stamp(msg.header.stamp), []).append(msg)
        return next((group for group in ticks.values() if len(group) == PARTICLES), None)
    tick = node.probe.wait_for(full_tick)
    assert sorted(particle_id_from_frame(m.body_frame_id) for m in tick) == list(
        range(PARTICLES))
    assert {m.reference_frame_id for m in tick} == {'world'}
    assert all(m.velocity.angular.z == 0.0 for m in tick)
    speeds = [np.hypot(m.velocity.linear.x, m.velocity.linear.y) for m in tick]
    # Elastic billiards: the kinetic energy of the 6 m/s cue ball is conserved.
    energy = 0.5 * BALL_MASS * sum(s * s for s in speeds)
    assert energy == pytest.approx(0.5 * BALL_MASS * CUE_SPEED ** 2, rel=1e-9)


def test_markers_draw_every_particle_sized_by_radius(node):
    markers = node.probe.collect(MarkerArray, 'table/particles/markers', 10)
    msg = node.probe.next_message(markers)
    assert msg.markers[0].action == Marker.DELETEALL
    spheres = msg.markers[1:]
    assert [m.type for m in spheres] == [Marker.SPHERE_LIST]
    assert spheres[0].scale.x == pytest.approx(2 * BALL_RADIUS)
    assert len(spheres[0].points) == PARTICLES


def test_status_reports_the_world(node):
    status = node.next_status(lambda s: s['time'] > 0.0)
    assert status['particles'] == PARTICLES and status['scene'] == 'elastic_break'
    assert status['kinetic_energy'] == pytest.approx(0.5 * BALL_MASS * CUE_SPEED ** 2, rel=1e-9)
    energy = status['energy']
    assert energy['total'] == pytest.approx(status['kinetic_energy'], rel=1e-12)
    assert abs(energy['balance_error']) <= 1e-9 * energy['start']
    assert status['error'] is None


def set_parameter(node, name: str, value: float) -> None:
    """Set a double parameter of the node through its parameter service."""
    client = node.probe.node.create_client(SetParameters, 'table/collision_node/set_parameters')
    request = SetParameters.Request(parameters=[Parameter(name=name, value=ParameterValue(
        type=ParameterType.PARAMETER_DOUBLE, double_value=value))])
    assert node.probe.call(client, request).results[0].successful


def test_real_time_factor_and_publish_rate_change_at_run_time(node):
    arrivals = []
    node.probe.node.create_subscription(
        Clock, '/clock', lambda m: arrivals.append((time.monotonic(), m)), 10)
    set_parameter(node, 'real_time_factor', 3.0)
    set_parameter(node, 'publish_rate', 10.0)
    try:
        start = len(arrivals)
        node.probe.wait_for(lambda: len(arrivals) >= start + 12)
        recent = arrivals[start + 2:]
        wall = [t for t, _ in recent]
        sim = [seconds_from_stamp(m.clock) for _, m in recent]
        assert 0.05 < statistics.median(np.diff(wall)) < 0.2         # 10 Hz now
        assert 2.0 < (sim[-1] - sim[0]) / (wall[-1] - wall[0]) < 4.0  # 3x wall time
    finally:
        set_parameter(node, 'real_time_factor', 1.0)
        set_parameter(node, 'publish_rate', RATE)
