"""msg_adapters: exact message contents, byte layouts and round trips."""

from __future__ import annotations

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseArray, VelocityStamped
from rclpy.serialization import deserialize_message, serialize_message
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from cdr_check import assert_same_cdr
from msg_adapters import (body_frame_id, clock_bytes, clock_message, nanoseconds_from_seconds,
                          particle_id_from_frame, point_cloud_bytes, poses_from_pose_array,
                          seconds_from_stamp, stamp_from_seconds, state_from_point_cloud,
                          velocities_bytes)
from msg_adapters.cdr import byte_view, CdrWriter, ENCAPSULATION_CDR_LE
from msg_adapters.cloud import POINT_STEP, point_cloud_writer
from msg_adapters.markers import PALETTE, STATIC_COLOUR, marker_array_writer, sphere_groups
from msg_adapters.poses import pose_array_writer


def particles(n: int, seed: int = 1) -> dict:
    """Return random particle arrays; every third particle static."""
    rng = np.random.default_rng(seed)
    inv_mass = rng.uniform(0.5, 2.0, n)
    inv_mass[::3] = 0.0
    return {
        'ids': np.arange(n, dtype=np.int64),
        'position': rng.normal(size=(n, 3)),
        'velocity': rng.normal(size=(n, 3)) * (inv_mass > 0)[:, None],
        'radius': rng.choice([0.1, 0.25], n),
        'inv_mass': inv_mass,
    }


def header_time(seconds: float) -> Time:
    """Return the stamp a message for ``seconds`` must carry."""
    sec, nanosec = stamp_from_seconds(seconds)
    return Time(sec=sec, nanosec=nanosec)


@pytest.mark.parametrize('seconds, expected', [
    (0.0, (0, 0)), (1.5, (1, 500_000_000)), (2.9999999999, (3, 0)),
    (1 / 3, (0, 333_333_333)), (12345.000000001, (12345, 1))])
def test_stamp_from_seconds_rounds_and_carries(seconds, expected):
    assert stamp_from_seconds(seconds) == expected


@pytest.mark.parametrize('bad', [-1.0, float('nan'), float('inf')])
def test_stamp_refuses_negative_and_non_finite(bad):
    with pytest.raises(ValueError):
        stamp_from_seconds(bad)


def test_clock_message_carries_simulated_time():
    msg = clock_message(7.25)
    assert isinstance(msg, Clock)
    assert (msg.clock.sec, msg.clock.nanosec) == (7, 250_000_000)
    assert seconds_from_stamp(msg.clock) == 7.25


@pytest.mark.parametrize('seconds', [0.0, 7.25, 1 / 3, 2.9999999999, 86400.000000001])
def test_clock_bytes_equal_rclpy_serialisation(seconds):
    assert clock_bytes(seconds) == serialize_message(clock_message(seconds))
    stamp = deserialize_message(clock_bytes(seconds), Clock).clock
    assert nanoseconds_from_seconds(seconds) == stamp.sec * 10 ** 9 + stamp.nanosec


def test_writer_aligns_float64_after_odd_string():
    writer = CdrWriter()
    writer.string('ab')          # 4 + 3 bytes: the double must skip one byte
    writer.float64s(np.array([1.0]))
    data = writer.bytes()
    assert writer.padding == [(11, 1)]
    assert data[4:8] == (3).to_bytes(4, 'little') and data[8:11] == b'ab\x00'
    assert np.frombuffer(data[12:], '<f8')[0] == 1.0


@pytest.mark.parametrize('layout', ['C', 'F', 'strided', 'float32', 'big-endian'])
def test_writer_takes_any_array_layout_as_its_little_endian_bytes_in_c_order(layout):
    values = np.arange(12.0).reshape(3, 4) * 0.1
    given = {'C': values, 'F': np.asfortranarray(values), 'strided': values[:, ::2],
             'float32': values.astype(np.float32), 'big-endian': values.astype('>f8')}[layout]
    writer = CdrWriter()
    writer.float64s(given)
    expected = np.ascontiguousarray(given, dtype='<f8').tobytes()
    assert writer.bytes() == ENCAPSULATION_CDR_LE + expected
    assert byte_view(given).tobytes() == np.ascontiguousarray(given).tobytes()


@pytest.mark.parametrize('n', [0, 1, 5, 37])
@pytest.mark.parametrize('frame', ['w', 'world', 'odom_frame'])
def test_pose_array_bytes_equal_rclpy_serialisation(n, frame):
    p = particles(n)
    orientation = None if n % 2 else np.tile([0.0, 0.6, 0.0, 0.8], (n, 1))
    writer = pose_array_writer(p['position'], orientation, 3.5, frame)
    reference = PoseArray()
    reference.header.stamp = header_time(3.5)
    reference.header.frame_id = frame
    q = [0.0, 0.0, 0.0, 1.0] if orientation is None else [0.0, 0.6, 0.0, 0.8]
    for x, y, z in p['position']:
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = float(x), float(y), float(z)
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = q
        reference.poses.append(pose)
    assert_same_cdr(writer.bytes(), writer.padding, reference)


def test_pose_array_round_trip_keeps_id_order():
    p = particles(9)
    msg = deserialize_message(pose_array_writer(p['position'], None, 0.25, 'world').bytes(),
                              PoseArray)
    position, orientation = poses_from_pose_array(msg)
    assert msg.header.frame_id == 'world'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 250_000_000)
    np.testing.assert_array_equal(position, p['position'])
    np.testing.assert_array_equal(orientation, np.tile([0.0, 0.0, 0.0, 1.0], (9, 1)))


def test_body_frame_ids_name_particles():
    assert body_frame_id(42) == 'particle_42'
    assert particle_id_from_frame('particle_42') == 42
    with pytest.raises(ValueError):
        particle_id_from_frame('world')


@pytest.mark.parametrize('spin', [False, True])
def test_velocities_bytes_equal_rclpy_serialisation_for_every_id_length(spin):
    # Ids of 1 to 5 digits give bodies of different lengths and paddings.
    ids = np.array([0, 7, 10, 99, 100, 4321, 12345], dtype=np.int64)
    rng = np.random.default_rng(3)
    velocity = rng.normal(size=(ids.size, 3))
    angular = rng.normal(size=(ids.size, 3)) if spin else None
    messages = velocities_bytes(ids, velocity, angular, 1.75, 'world')
    assert len(messages) == ids.size
    for k, particle in enumerate(ids):
        reference = VelocityStamped()
        reference.header.stamp = header_time(1.75)
        reference.header.frame_id = 'world'
        reference.body_frame_id = f'particle_{particle}'
        reference.reference_frame_id = 'world'
        lin = reference.velocity.linear
        lin.x, lin.y, lin.z = (float(v) for v in velocity[k])
        if spin:
            ang = reference.velocity.angular
            ang.x, ang.y, ang.z = (float(v) for v in angular[k])
        # An independent sequential writing of the same fields gives the gaps.
        sequential = CdrWriter()
        sequential.header(1, 750_000_000, 'world')
        sequential.string(f'particle_{particle}')
        sequential.string('world')
        sequential.float64s(np.concatenate([velocity[k], angular[k] if spin else np.zeros(3)]))
        assert messages[k] == sequential.bytes()
        assert_same_cdr(messages[k], sequential.padding, reference)


def test_velocities_round_trip_by_body_frame():
    p = particles(12)
    decoded = {particle_id_from_frame(m.body_frame_id): m for m in (
        deserialize_message(b, VelocityStamped)
        for b in velocities_bytes(p['ids'], p['velocity'], None, 2.0, 'map'))}
    assert sorted(decoded) == list(range(12))
    for i, msg in decoded.items():
        assert msg.reference_frame_id == 'map' and msg.header.frame_id == 'map'
        v = msg.velocity
        assert [v.linear.x, v.linear.y, v.linear.z] == p['velocity'][i].tolist()
        assert [v.angular.x, v.angular.y, v.angular.z] == [0.0, 0.0, 0.0]


def test_velocities_of_no_particles_is_empty():
    assert velocities_bytes(np.zeros(0, np.int64), np.zeros((0, 3)), None, 0.0, 'w') == []


def reference_cloud(p: dict, seconds: float, frame: str) -> PointCloud2:
    """Build the expected cloud field by field with message objects."""
    n = p['ids'].size
    msg = PointCloud2()
    msg.header.stamp = header_time(seconds)
    msg.header.frame_id = frame
    msg.height, msg.width = 1, n
    names = ['id', 'x', 'y', 'z', 'vx', 'vy', 'vz', 'radius', 'mass']
    msg.fields = [PointField(name='id', offset=0, datatype=PointField.UINT32, count=1)] + [
        PointField(name=name, offset=8 * k, datatype=PointField.FLOAT64, count=1)
        for k, name in enumerate(names) if k > 0]
    msg.is_bigendian = False
    msg.point_step, msg.row_step = 72, 72 * n
    data = bytearray()
    for i in range(n):
        mass = 1.0 / p['inv_mass'][i] if p['inv_mass'][i] > 0 else np.inf
        values = [*p['position'][i], *p['velocity'][i], p['radius'][i], mass]
        data += int(p['ids'][i]).to_bytes(4, 'little') + bytes(4)
        data += np.array(values, '<f8').tobytes()
    msg.data = bytes(data)
    msg.is_dense = True
    return msg


@pytest.mark.parametrize('n', [0, 1, 6, 50])
def test_point_cloud_bytes_equal_rclpy_serialisation(n):
    p = particles(n)
    writer = point_cloud_writer(p['ids'], p['position'], p['velocity'], p['radius'],
                                p['inv_mass'], 4.125, 'world')
    assert_same_cdr(writer.bytes(), writer.padding, reference_cloud(p, 4.125, 'world'))


def test_point_cloud_round_trip_ids_state_and_layout():
    p = particles(20)
    p['ids'] = p['ids'] + 1000
    msg = deserialize_message(point_cloud_bytes(p['ids'], p['position'], p['velocity'],
                                                p['radius'], p['inv_mass'], 1.0, 'world'),
                              PointCloud2)
    assert [f.name for f in msg.fields] == ['id', 'x', 'y', 'z', 'vx', 'vy', 'vz', 'radius',
                                            'mass']
    assert [f.offset for f in msg.fields] == [0, 8, 16, 24, 32, 40, 48, 56, 64]
    assert msg.point_step == POINT_STEP and len(msg.data) == 20 * POINT_STEP
    state = state_from_point_cloud(msg)
    np.testing.assert_array_equal(state['ids'], p['ids'])
    np.testing.assert_array_equal(state['position'], p['position'])
    np.testing.assert_array_equal(state['velocity'], p['velocity'])
    np.testing.assert_array_equal(state['radius'], p['radius'])
    static = p['inv_mass'] == 0
    assert np.isinf(state['mass'][static]).all()
    np.testing.assert_allclose(state['mass'][~static], 1.0 / p['inv_mass'][~static],
                               rtol=1e-15)


def test_sphere_groups_split_by_radius_and_static():
    radius = np.array([0.1, 0.2, 0.1, 0.1, 0.2])
    inv_mass = np.array([1.0, 1.0, 0.0, 1.0, 1.0])
    groups = sphere_groups(radius, inv_mass)
    assert [(r, s, idx.tolist()) for r, s, idx in groups] == [
        (0.1, False, [0, 3]), (0.1, True, [2]), (0.2, False, [1, 4])]


def reference_markers(p: dict, seconds: float, frame: str) -> MarkerArray:
    """Build the expected MarkerArray with message objects."""
    stamp = header_time(seconds)
    clear = Marker(ns='particles', id=0, type=Marker.SPHERE, action=Marker.DELETEALL)
    clear.header.stamp, clear.header.frame_id = stamp, frame
    clear.pose.orientation.w = 1.0
    clear.scale.x = clear.scale.y = clear.scale.z = 1.0
    out = MarkerArray(markers=[clear])
    for k, (radius, static, idx) in enumerate(sphere_groups(p['radius'], p['inv_mass'])):
        m = Marker(ns='particles', id=k + 1, type=Marker.SPHERE_LIST, action=Marker.ADD)
        m.header.stamp, m.header.frame_id = stamp, frame
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = 2.0 * radius
        colour = STATIC_COLOUR if static else PALETTE[k % len(PALETTE)]
        m.color = ColorRGBA(r=float(colour[0]), g=float(colour[1]), b=float(colour[2]),
                            a=float(colour[3]))
        m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in p['position'][idx]]
        out.markers.append(m)
    return out


@pytest.mark.parametrize('n', [0, 1, 8])
@pytest.mark.parametrize('frame', ['w', 'world'])
def test_marker_array_bytes_equal_rclpy_serialisation(n, frame):
    p = particles(n)
    writer = marker_array_writer(p['position'], p['radius'], p['inv_mass'], 0.5, frame)
    assert_same_cdr(writer.bytes(), writer.padding, reference_markers(p, 0.5, frame))


def test_marker_spheres_cover_every_particle_once_sized_by_radius():
    p = particles(30)
    msg = deserialize_message(marker_array_writer(p['position'], p['radius'], p['inv_mass'],
                                                  0.0, 'world').bytes(), MarkerArray)
    assert msg.markers[0].action == Marker.DELETEALL
    seen = []
    for marker in msg.markers[1:]:
        assert marker.type == Marker.SPHERE_LIST
        for point in marker.points:
            i = int(np.flatnonzero((p['position'] == [point.x, point.y, point.z]).all(1))[0])
            assert marker.scale.x == 2.0 * p['radius'][i]
            seen.append(i)
    assert sorted(seen) == list(range(30))
