"""particles/velocities: one geometry_msgs/VelocityStamped per particle.

``body_frame_id`` is ``particle_<id>`` and ``reference_frame_id`` the
world frame. All messages of a tick share the layout except the length
of ``particle_<id>``, so particles are grouped by the number of digits
of their id and each group is written as one numpy array of records.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .cdr import ENCAPSULATION_CDR_LE, CdrWriter
from .stamp import stamp_from_seconds

BODY_FRAME_PREFIX = 'particle_'


def body_frame_id(particle_id: int) -> str:
    """Return the body frame of one particle."""
    return f'{BODY_FRAME_PREFIX}{int(particle_id)}'


def particle_id_from_frame(frame: str) -> int:
    """Return the particle id encoded in a body frame ``particle_<id>``."""
    if not frame.startswith(BODY_FRAME_PREFIX):
        raise ValueError(f'not a particle frame: {frame!r}')
    return int(frame[len(BODY_FRAME_PREFIX):])


def twist_rows(velocity: np.ndarray, angular_velocity: Optional[np.ndarray]) -> np.ndarray:
    """Return (n, 6) linear then angular velocity (zero spin without spin)."""
    rows = np.zeros((velocity.shape[0], 6))
    rows[:, :3] = velocity
    if angular_velocity is not None:
        rows[:, 3:] = angular_velocity
    return rows


def _template(sec: int, nanosec: int, frame_id: str, body_length: int) -> tuple[bytes, int, int]:
    """Return one message with a blank body frame, and where its name and twist go."""
    writer = CdrWriter()
    writer.header(sec, nanosec, frame_id)
    writer.uint32(body_length + 1)
    body_at = writer.offset + len(ENCAPSULATION_CDR_LE)
    writer.raw(b'\x00' * (body_length + 1))
    writer.string(frame_id)
    writer.align(8)
    twist_at = writer.offset + len(ENCAPSULATION_CDR_LE)
    writer.float64s(np.zeros(6))
    return writer.bytes(), body_at, twist_at


def velocities_bytes(ids: np.ndarray, velocity: np.ndarray,
                     angular_velocity: Optional[np.ndarray], seconds: float,
                     frame_id: str) -> list[bytes]:
    """Return one serialised VelocityStamped per particle, in the order of ``ids``."""
    n = ids.shape[0]
    out: list[bytes] = [b''] * n
    if n == 0:
        return out
    sec, nanosec = stamp_from_seconds(seconds)
    twist = twist_rows(velocity, angular_velocity)
    digits = np.char.str_len(ids.astype(np.int64).astype('S20'))
    for length in np.unique(digits):
        rows = np.flatnonzero(digits == length)
        body_length = len(BODY_FRAME_PREFIX) + int(length)
        template, body_at, twist_at = _template(sec, nanosec, frame_id, body_length)
        size = len(template)
        records = np.tile(np.frombuffer(template, dtype=np.uint8), (rows.size, 1))
        names = np.char.add(BODY_FRAME_PREFIX.encode(), ids[rows].astype(np.int64).astype('S20'))
        records[:, body_at:body_at + body_length] = np.frombuffer(
            names.astype(f'S{body_length}').tobytes(), dtype=np.uint8).reshape(-1, body_length)
        records[:, twist_at:twist_at + 48] = np.ascontiguousarray(
            twist[rows], dtype='<f8').view(np.uint8)
        blob = records.tobytes()
        for k, row in enumerate(rows.tolist()):
            out[row] = blob[k * size:(k + 1) * size]
    return out
