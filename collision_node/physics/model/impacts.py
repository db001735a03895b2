"""The impacts a world resolved: one record per impulse-bearing contact event.

Recording is off unless somebody asks for it (``World.record_impacts``), so
a world whose impacts nobody reads pays nothing for them. The contact law
records each impact it resolves through :meth:`ImpactLog.record`, in bulk
(numpy arrays, one row per impact); readers take what has accumulated
with :meth:`ImpactLog.take`.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

# One impact: when (simulated time, s), who (ids i and j, j = -1 for a
# wall), where (contact point, m), along what (unit normal from j to i),
# how hard (normal and tangential impulse magnitudes, N s) and how fast the
# pair closed before it (m/s, >= 0).
IMPACT_DTYPE = np.dtype([
    ('time', np.float64), ('i', np.int64), ('j', np.int64),
    ('point', np.float64, (3,)), ('normal', np.float64, (3,)),
    ('normal_impulse', np.float64), ('tangential_impulse', np.float64),
    ('closing_speed', np.float64)])

WALL = -1   # the ``j`` of an impact with a wall


class ImpactLog:
    """Impacts recorded since the last :meth:`take`, in the order they happened."""

    def __init__(self) -> None:
        """Start empty."""
        self._chunks: list[np.ndarray] = []
        # The id of each row the stages record by (``name_rows``); None: rows are ids.
        self._ids: Optional[np.ndarray] = None

    def name_rows(self, ids: np.ndarray) -> None:
        """Record from now on the particle ``ids[row]`` for each row a stage records.

        The world hands over its state's ids before each step: the stages
        know rows, a reader wants ids (rows shift at a delete, and a large
        world renumbers its rows in place, which this array follows).
        """
        self._ids = ids

    def __len__(self) -> int:
        """Return the number of impacts waiting to be taken."""
        return sum(len(chunk) for chunk in self._chunks)

    def record(self, time, i, j, point, normal, normal_impulse, tangential_impulse,
               closing_speed) -> None:
        """Append impacts; each argument is a scalar or one value (or 3-vector) per impact."""
        count = int(np.size(i))
        if count == 0:
            return
        chunk = np.empty(count, dtype=IMPACT_DTYPE)
        chunk['time'] = time
        chunk['i'] = i
        chunk['j'] = j
        chunk['point'] = point
        chunk['normal'] = normal
        if self._ids is not None:
            self._name(chunk)
        chunk['normal_impulse'] = normal_impulse
        chunk['tangential_impulse'] = tangential_impulse
        chunk['closing_speed'] = closing_speed
        self._chunks.append(chunk)

    def _name(self, chunk: np.ndarray) -> None:
        """Turn ``chunk``'s rows into ids; a pair keeps i < j, its normal from j to i."""
        wall = chunk['j'] == WALL
        chunk['i'] = self._ids[chunk['i']]
        chunk['j'] = np.where(wall, WALL, self._ids[np.where(wall, 0, chunk['j'])])
        swap = ~wall & (chunk['i'] > chunk['j'])
        if swap.any():
            chunk['i'][swap], chunk['j'][swap] = chunk['j'][swap], chunk['i'][swap].copy()
            chunk['normal'][swap] *= -1.0

    def take(self) -> np.ndarray:
        """Return the impacts recorded since the last call (IMPACT_DTYPE) and forget them."""
        if not self._chunks:
            return np.empty(0, dtype=IMPACT_DTYPE)
        taken = np.concatenate(self._chunks) if len(self._chunks) > 1 else self._chunks[0]
        self._chunks = []
        return taken


def contact_points(position: np.ndarray, radius: np.ndarray, i: np.ndarray, j: np.ndarray,
                   normal: np.ndarray) -> np.ndarray:
    """Return the contact point of pairs: midway between the two surface points."""
    return 0.5 * ((position[i] - radius[i, None] * normal)
                  + (position[j] + radius[j, None] * normal))


def record_pairs(log: Optional[ImpactLog], time, position: np.ndarray, radius: np.ndarray,
                 i: np.ndarray, j: np.ndarray, normal: np.ndarray, normal_impulse,
                 tangential_impulse, approach) -> None:
    """Append pair impacts to ``log`` (nothing without a log).

    Each pair is written with i < j and the normal from j to i, whichever
    order the solver found it in, so every preset records a pair alike.
    """
    if log is None or not np.size(i):
        return
    swap = i > j
    first, second = np.where(swap, j, i), np.where(swap, i, j)
    normal = np.where(swap[:, None], -normal, normal)
    log.record(time, first, second, contact_points(position, radius, first, second, normal),
               normal, normal_impulse, tangential_impulse, approach)


def record_walls(log: Optional[ImpactLog], time, position: np.ndarray, index: np.ndarray,
                 axis: int, plane: float, inward: float, normal_impulse, tangential_impulse,
                 approach) -> None:
    """Append wall impacts (j = -1) of particles ``index`` at one plane to ``log``.

    The contact point is on the plane, at the particle's other coordinates
    as they are when recorded.
    """
    if log is None or not np.size(index):
        return
    normal = np.zeros((np.size(index), 3))
    normal[:, axis] = inward
    point = position[index].copy()
    point[:, axis] = plane
    log.record(time, index, WALL, point, normal, normal_impulse, tangential_impulse, approach)
