"""particles/collisions: sensor_msgs/PointCloud2 with one point per resolved impact.

Fields (little endian, point_step 88, no padding): ``time`` float64 at 0
(simulated time of the impact, s), ``i`` and ``j`` int32 at 8 and 12 (the
particle ids; ``j`` = -1 for a wall; PointField has no 64-bit integer),
then float64 ``x y z`` (contact point, m), ``nx ny nz`` (unit normal from
``j`` to ``i``), ``normal_impulse`` and ``tangential_impulse`` (N s) and
``closing_speed`` (m/s) at 16..80. The input is any structured array with
the fields of the core's impact record (``time i j point normal
normal_impulse tangential_impulse closing_speed``); the data block is one
``tobytes`` of a numpy structured array.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from .cdr import CdrWriter
from .cloud import records_from_point_cloud, unordered_cloud_writer

FIELDS = (('time', '<f8'), ('i', '<i4'), ('j', '<i4'),
          ('x', '<f8'), ('y', '<f8'), ('z', '<f8'),
          ('nx', '<f8'), ('ny', '<f8'), ('nz', '<f8'),
          ('normal_impulse', '<f8'), ('tangential_impulse', '<f8'), ('closing_speed', '<f8'))
IMPACT_POINT_DTYPE = np.dtype(list(FIELDS))   # packed: every float64 lands 8-aligned
IMPACT_POINT_STEP = IMPACT_POINT_DTYPE.itemsize
_DATATYPE = {'<f8': PointField.FLOAT64, '<i4': PointField.INT32}
# (name, offset, PointField datatype) in field order.
IMPACT_POINT_FIELDS = tuple((name, IMPACT_POINT_DTYPE.fields[name][1], _DATATYPE[fmt])
                            for name, fmt in FIELDS)
_SCALARS = ('time', 'normal_impulse', 'tangential_impulse', 'closing_speed')


def impact_points(impacts: np.ndarray) -> np.ndarray:
    """Return the impacts as a structured array of IMPACT_POINT_DTYPE."""
    points = np.empty(impacts.shape[0], dtype=IMPACT_POINT_DTYPE)
    for name in _SCALARS:
        points[name] = impacts[name]
    points['i'] = impacts['i']
    points['j'] = impacts['j']
    for axis, name in enumerate('xyz'):
        points[name] = impacts['point'][:, axis]
        points['n' + name] = impacts['normal'][:, axis]
    return points


def impact_cloud_writer(impacts: np.ndarray, seconds: float, frame_id: str) -> CdrWriter:
    """Return the CDR writer holding the impacts as an unordered PointCloud2."""
    # is_dense: every impact is finite.
    return unordered_cloud_writer(impact_points(impacts), IMPACT_POINT_FIELDS,
                                  IMPACT_POINT_STEP, seconds, frame_id)


def impact_cloud_bytes(impacts: np.ndarray, seconds: float, frame_id: str) -> bytes:
    """Return a serialised PointCloud2 of the impacts, ready for ``Publisher.publish``."""
    return impact_cloud_writer(impacts, seconds, frame_id).bytes()


def impacts_from_point_cloud(msg: PointCloud2) -> Mapping[str, np.ndarray]:
    """Return the impacts of a ``particles/collisions`` cloud as arrays.

    Keys: ``time``, ``i``, ``j`` (int64), ``point`` and ``normal`` (n x 3),
    ``normal_impulse``, ``tangential_impulse``, ``closing_speed``.
    """
    records = records_from_point_cloud(msg)
    impacts = {name: records[name].copy() for name in _SCALARS}
    impacts['i'] = records['i'].astype(np.int64)
    impacts['j'] = records['j'].astype(np.int64)
    impacts['point'] = np.stack([records[a] for a in 'xyz'], axis=1)
    impacts['normal'] = np.stack([records['n' + a] for a in 'xyz'], axis=1)
    return impacts
