"""msg_adapters.collisions: the particles/collisions cloud, byte for byte and round trip."""

from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2, PointField

from cdr_check import assert_same_cdr
from collision_node.physics.model.impacts import IMPACT_DTYPE, ImpactLog, WALL
from msg_adapters import impact_cloud_bytes, impacts_from_point_cloud, stamp_from_seconds
from msg_adapters.collisions import impact_cloud_writer, IMPACT_POINT_STEP

NAMES = ['time', 'i', 'j', 'x', 'y', 'z', 'nx', 'ny', 'nz', 'normal_impulse',
         'tangential_impulse', 'closing_speed']


def impacts(n: int, seed: int = 3) -> np.ndarray:
    """Return ``n`` random impacts through the core's own log; every third one on a wall."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    j = rng.integers(0, 10**6, n)
    j[::3] = WALL
    log = ImpactLog()
    log.record(np.sort(rng.uniform(0, 5, n)), rng.integers(0, 2**31 - 1, n), j,
               rng.normal(size=(n, 3)), normal, rng.uniform(0, 3, n), rng.uniform(0, 1, n),
               rng.uniform(0, 9, n))
    return log.take()


def reference_cloud(records: np.ndarray, seconds: float, frame: str) -> PointCloud2:
    """Build the expected cloud field by field with message objects."""
    n = records.size
    msg = PointCloud2()
    sec, nanosec = stamp_from_seconds(seconds)
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.header.frame_id = frame
    msg.height, msg.width = 1, n
    offsets = [0, 8, 12] + [16 + 8 * k for k in range(9)]
    msg.fields = [PointField(name=name, offset=offset, count=1,
                             datatype=PointField.INT32 if name in 'ij' else PointField.FLOAT64)
                  for name, offset in zip(NAMES, offsets)]
    msg.is_bigendian = False
    msg.point_step, msg.row_step = 88, 88 * n
    data = bytearray()
    for r in records:
        data += np.array([r['time']], '<f8').tobytes()
        data += np.array([r['i'], r['j']], '<i4').tobytes()
        data += np.array([*r['point'], *r['normal'], r['normal_impulse'],
                          r['tangential_impulse'], r['closing_speed']], '<f8').tobytes()
    msg.data = bytes(data)
    msg.is_dense = True
    return msg


@pytest.mark.parametrize('n', [0, 1, 7, 40])
@pytest.mark.parametrize('frame', ['w', 'world', 'odom_frame'])
def test_impact_cloud_bytes_equal_rclpy_serialisation(n, frame):
    records = impacts(n)
    writer = impact_cloud_writer(records, 2.375, frame)
    assert_same_cdr(writer.bytes(), writer.padding, reference_cloud(records, 2.375, frame))


def test_impact_cloud_round_trip_and_layout():
    records = impacts(25)
    msg = deserialize_message(impact_cloud_bytes(records, 1.5, 'world'), PointCloud2)
    assert [f.name for f in msg.fields] == NAMES
    assert [f.offset for f in msg.fields] == [0, 8, 12, 16, 24, 32, 40, 48, 56, 64, 72, 80]
    assert msg.point_step == IMPACT_POINT_STEP == 88 and len(msg.data) == 25 * 88
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 500_000_000)
    back = impacts_from_point_cloud(msg)
    for name in IMPACT_DTYPE.names:
        np.testing.assert_array_equal(back[name], records[name], err_msg=name)
    assert (back['j'][::3] == -1).all() and back['i'].dtype == np.int64


def test_no_impacts_is_an_empty_cloud():
    msg = deserialize_message(impact_cloud_bytes(np.empty(0, IMPACT_DTYPE), 0.0, 'w'),
                              PointCloud2)
    assert (msg.width, len(msg.data), len(msg.fields)) == (0, 0, 12)
    assert impacts_from_point_cloud(msg)['point'].shape == (0, 3)
