"""particles/state: sensor_msgs/PointCloud2 with one point per particle.

Fields (little endian, point_step 72): ``id`` uint32 at 0, then float64
``x y z vx vy vz radius mass`` at 8..64 (4 bytes of padding after ``id``
keep every float64 aligned). ``mass`` is ``inf`` for a static particle.
The data block is a numpy structured array, copied once into the message.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from .cdr import byte_view, CdrWriter
from .stamp import stamp_from_seconds

FLOAT_FIELDS = ('x', 'y', 'z', 'vx', 'vy', 'vz', 'radius', 'mass')
FIELD_NAMES = ('id',) + FLOAT_FIELDS
POINT_STEP = 72
POINT_DTYPE = np.dtype({
    'names': list(FIELD_NAMES),
    'formats': ['<u4'] + ['<f8'] * len(FLOAT_FIELDS),
    'offsets': [0] + [8 + 8 * k for k in range(len(FLOAT_FIELDS))],
    'itemsize': POINT_STEP,
})
# (name, offset, PointField datatype) in the order of FIELD_NAMES.
POINT_FIELDS = tuple(
    (name, POINT_DTYPE.fields[name][1],
     PointField.UINT32 if name == 'id' else PointField.FLOAT64)
    for name in FIELD_NAMES)

_NUMPY_OF_DATATYPE = {
    PointField.INT8: 'i1', PointField.UINT8: 'u1', PointField.INT16: 'i2',
    PointField.UINT16: 'u2', PointField.INT32: 'i4', PointField.UINT32: 'u4',
    PointField.FLOAT32: 'f4', PointField.FLOAT64: 'f8',
}


def point_records(ids: np.ndarray, position: np.ndarray, velocity: np.ndarray,
                  radius: np.ndarray, inv_mass: np.ndarray) -> np.ndarray:
    """Return the particles as a structured array of POINT_DTYPE."""
    n = ids.shape[0]
    records = np.zeros(n, dtype=POINT_DTYPE)
    records['id'] = ids
    for axis, name in enumerate('xyz'):
        records[name] = position[:, axis]
        records['v' + name] = velocity[:, axis]
    records['radius'] = radius
    with np.errstate(divide='ignore'):
        records['mass'] = np.where(inv_mass > 0.0, 1.0 / inv_mass, np.inf)
    return records


def point_cloud_writer(ids: np.ndarray, position: np.ndarray, velocity: np.ndarray,
                       radius: np.ndarray, inv_mass: np.ndarray, seconds: float,
                       frame_id: str) -> CdrWriter:
    """Return the CDR writer holding the particles as an unordered PointCloud2."""
    # is_dense: positions are always finite.
    return unordered_cloud_writer(point_records(ids, position, velocity, radius, inv_mass),
                                  POINT_FIELDS, POINT_STEP, seconds, frame_id)


def unordered_cloud_writer(records: np.ndarray, fields, point_step: int, seconds: float,
                           frame_id: str) -> CdrWriter:
    """Return the CDR writer of an unordered, dense PointCloud2 of ``records``.

    ``records`` is a structured array laid out as ``fields`` ((name, offset,
    datatype) triples) with ``point_step`` bytes per point.
    """
    data = byte_view(records)
    n = records.shape[0]
    writer = CdrWriter()
    writer.header(*stamp_from_seconds(seconds), frame_id)
    writer.uint32(1)                 # height: an unordered cloud is one row
    writer.uint32(n)                 # width
    writer.uint32(len(fields))
    for name, offset, datatype in fields:
        writer.string(name)
        writer.uint32(offset)
        writer.uint8(datatype)
        writer.uint32(1)             # count
    writer.uint8(0)                  # is_bigendian
    writer.uint32(point_step)
    writer.uint32(point_step * n)    # row_step
    writer.uint32(len(data))
    writer.raw(data)
    writer.uint8(1)                  # is_dense: every point is finite
    return writer


def point_cloud_bytes(ids: np.ndarray, position: np.ndarray, velocity: np.ndarray,
                      radius: np.ndarray, inv_mass: np.ndarray, seconds: float,
                      frame_id: str) -> bytes:
    """Return a serialised PointCloud2 ready for ``Publisher.publish``."""
    return point_cloud_writer(ids, position, velocity, radius, inv_mass, seconds,
                              frame_id).bytes()


def records_from_point_cloud(msg: PointCloud2) -> np.ndarray:
    """Return a PointCloud2's points as a structured array named by its fields.

    Works for any little-endian cloud whose fields are scalars, so a
    consumer need not rely on this module's exact layout.
    """
    if msg.is_bigendian:
        raise ValueError('big-endian point clouds are not supported')
    dtype = np.dtype({
        'names': [f.name for f in msg.fields],
        'formats': ['<' + _NUMPY_OF_DATATYPE[f.datatype] for f in msg.fields],
        'offsets': [f.offset for f in msg.fields],
        'itemsize': msg.point_step,
    })
    count = msg.width * msg.height
    return np.frombuffer(memoryview(msg.data), dtype=dtype, count=count)


def state_from_point_cloud(msg: PointCloud2) -> Mapping[str, np.ndarray]:
    """Return ids, position, velocity, radius and mass arrays from ``particles/state``."""
    records = records_from_point_cloud(msg)
    return {
        'ids': records['id'].astype(np.int64),
        'position': np.stack([records[a] for a in 'xyz'], axis=1),
        'velocity': np.stack([records['v' + a] for a in 'xyz'], axis=1),
        'radius': records['radius'].copy(),
        'mass': records['mass'].copy(),
    }
