"""particles/markers: visualization_msgs/MarkerArray of sphere lists for RViz.

A SPHERE_LIST marker draws many spheres of one diameter in one draw call,
so particles are grouped by (radius, static) and each group is one marker
whose ``points`` are the particle centres (one numpy block per group).
The array starts with a DELETEALL marker so groups that vanished (after
a reset) disappear from RViz too.
"""

from __future__ import annotations

import numpy as np
from visualization_msgs.msg import Marker

from .cdr import CdrWriter
from .stamp import stamp_from_seconds

NAMESPACE = 'particles'
# Dynamic groups cycle through these colours (RGBA); static particles are grey.
PALETTE = np.array([
    [0.12, 0.47, 0.71, 1.0], [1.00, 0.50, 0.05, 1.0], [0.17, 0.63, 0.17, 1.0],
    [0.84, 0.15, 0.16, 1.0], [0.58, 0.40, 0.74, 1.0], [0.55, 0.34, 0.29, 1.0],
])
STATIC_COLOUR = np.array([0.5, 0.5, 0.5, 1.0])


def sphere_groups(radius: np.ndarray, inv_mass: np.ndarray) -> list[tuple[float, bool,
                                                                          np.ndarray]]:
    """Return (radius, static, particle indices) per group, by radius then static."""
    static = inv_mass == 0.0
    radii, radius_index = np.unique(radius, return_inverse=True)
    # One integer key per (radius, static): sorting ints is far cheaper than rows.
    keys, inverse = np.unique(radius_index.reshape(-1) * 2 + static, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind='stable')
    bounds = np.searchsorted(inverse[order], np.arange(keys.size + 1))
    return [(float(radii[keys[g] // 2]), bool(keys[g] % 2), order[bounds[g]:bounds[g + 1]])
            for g in range(keys.size)]


def _marker_head(writer: CdrWriter, sec: int, nanosec: int, frame_id: str, marker_id: int,
                 marker_type: int, action: int) -> None:
    writer.header(sec, nanosec, frame_id)
    writer.string(NAMESPACE)
    writer.int32(marker_id)
    writer.int32(marker_type)
    writer.int32(action)


def _marker_tail(writer: CdrWriter) -> None:
    """Write the fields after ``colors`` that sphere lists leave empty."""
    writer.string('')                # texture_resource
    writer.header(0, 0, '')          # texture (CompressedImage): header
    writer.string('')                # texture.format
    writer.uint32(0)                 # texture.data
    writer.uint32(0)                 # uv_coordinates
    writer.string('')                # text
    writer.string('')                # mesh_resource
    writer.string('')                # mesh_file.filename
    writer.uint32(0)                 # mesh_file.data
    writer.uint8(0)                  # mesh_use_embedded_materials


def marker_array_writer(position: np.ndarray, radius: np.ndarray, inv_mass: np.ndarray,
                        seconds: float, frame_id: str) -> CdrWriter:
    """Return the CDR writer holding DELETEALL plus one SPHERE_LIST per group."""
    sec, nanosec = stamp_from_seconds(seconds)
    groups = sphere_groups(radius, inv_mass)
    writer = CdrWriter()
    writer.uint32(1 + len(groups))
    markers = [(0, Marker.DELETEALL, None)] + [
        (k + 1, Marker.ADD, group) for k, group in enumerate(groups)]
    for marker_id, action, group in markers:
        _marker_head(writer, sec, nanosec, frame_id, marker_id,
                     Marker.SPHERE_LIST if group else Marker.SPHERE, action)
        writer.float64s(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))   # pose: identity
        diameter = 2.0 * group[0] if group else 1.0
        writer.float64s(np.full(3, diameter))                           # scale
        if group is None:
            colour = np.zeros(4)
        elif group[1]:
            colour = STATIC_COLOUR
        else:
            colour = PALETTE[(marker_id - 1) % len(PALETTE)]
        writer.float32s(colour)
        writer.stamp(0, 0)           # lifetime 0: until replaced
        writer.uint8(0)              # frame_locked
        indices = group[2] if group else np.zeros(0, dtype=np.int64)
        writer.uint32(indices.size)
        if indices.size:
            writer.float64s(position[indices])
        writer.uint32(0)             # colors: the marker colour applies to all
        _marker_tail(writer)
    return writer


def marker_array_bytes(position: np.ndarray, radius: np.ndarray, inv_mass: np.ndarray,
                       seconds: float, frame_id: str) -> bytes:
    """Return a serialised MarkerArray ready for ``Publisher.publish``."""
    return marker_array_writer(position, radius, inv_mass, seconds, frame_id).bytes()
