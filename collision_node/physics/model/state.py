"""Particle state as structure-of-arrays numpy buffers.

Every stage of a step reads and writes these arrays in place; nothing in
the hot path iterates over particles in Python.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Optional

import numpy as np


def ids_ascending(ids: np.ndarray) -> bool:
    """Say whether ``ids`` ascend strictly (rows in id order)."""
    return bool(ids.size < 2 or np.all(ids[1:] > ids[:-1]))


# Ids spread over at most this many times the particle count are ordered by
# placing each row at its id (linear time); sparser ids are sorted.
DENSE_IDS = 4


def id_order(ids: np.ndarray) -> np.ndarray:
    """Return the rows sorted by id (``ids`` unique, non-negative)."""
    if not ids.size:
        return np.zeros(0, dtype=np.int64)
    span = int(ids.max()) + 1
    if span > DENSE_IDS * ids.size:
        return np.argsort(ids, kind='stable')
    row_at = np.full(span, -1, dtype=np.int64)
    row_at[ids] = np.arange(ids.size)
    return row_at[row_at >= 0]


def rows_named(ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Return the row of each ``wanted`` id among ``ids`` (unique, any order); -1 if absent."""
    wanted = np.asarray(wanted, dtype=np.int64)
    if not ids.size:
        return np.full(wanted.shape, -1, dtype=np.int64)
    by_id = None if ids_ascending(ids) else id_order(ids)
    ordered = ids if by_id is None else ids[by_id]
    at = np.minimum(np.searchsorted(ordered, wanted), ids.size - 1)
    rows = at if by_id is None else by_id[at]
    return np.where(ordered[at] == wanted, rows, -1).astype(np.int64)


@dataclass
class ParticleState:
    """All particles of a world, one row per particle.

    The rows are in id order, except in a world large enough to keep them
    in spatial order (``stages/ordering``): there an id names a particle,
    ``rows_named`` finds its row, and ``in_id_order`` gives the state in
    id order.

    Units are SI (REP-103): metres, metres per second, kilograms.
    ``inv_mass`` is 1/mass; 0 marks a static particle of infinite mass,
    which keeps the impulse formulas free of inf/inf.
    The optional arrays exist only when a declared effect needs them
    (an undeclared effect costs nothing, not even memory).
    """

    ids: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    radius: np.ndarray
    inv_mass: np.ndarray
    restitution: Optional[np.ndarray] = None
    friction: Optional[np.ndarray] = None
    angular_velocity: Optional[np.ndarray] = None
    orientation: Optional[np.ndarray] = None
    # Sleeping (``stages/sleeping/sleep.py``; None until a pipeline with sleeping
    # runs): which particles sleep, seconds each has stayed below the sleep
    # speed, and the id naming a sleeping particle's island (-1 if awake).
    asleep: Optional[np.ndarray] = None
    still_time: Optional[np.ndarray] = None
    island: Optional[np.ndarray] = None

    @classmethod
    def empty(cls) -> 'ParticleState':
        """Return a state with no particles."""
        return cls(
            ids=np.zeros(0, dtype=np.int64),
            position=np.zeros((0, 3)),
            velocity=np.zeros((0, 3)),
            radius=np.zeros(0),
            inv_mass=np.zeros(0),
        )

    def __len__(self) -> int:
        """Return the number of particles."""
        return int(self.ids.shape[0])

    @property
    def mass(self) -> np.ndarray:
        """Return masses in kg, ``inf`` for static particles."""
        with np.errstate(divide='ignore'):
            return np.where(self.inv_mass > 0.0, 1.0 / self.inv_mass, np.inf)

    @property
    def dynamic(self) -> np.ndarray:
        """Return the mask of particles that can move (finite mass)."""
        return self.inv_mass > 0.0

    def copy(self) -> 'ParticleState':
        """Return an independent copy: every array is copied, none shared."""
        kwargs = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value = value.copy()
            kwargs[f.name] = value
        return ParticleState(**kwargs)

    def concatenate(self, other: 'ParticleState') -> 'ParticleState':
        """Return a new state with ``other``'s particles appended.

        An optional array present on one side only is filled with its neutral
        value on the other side (NaN for per-particle coefficients, meaning
        "use the scene's value"; zero spin; identity orientation; awake).
        """
        neutral = {
            'restitution': lambda n: np.full(n, np.nan),
            'friction': lambda n: np.full(n, np.nan),
            'angular_velocity': lambda n: np.zeros((n, 3)),
            'orientation': lambda n: np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
            'asleep': lambda n: np.zeros(n, dtype=bool),
            'still_time': lambda n: np.zeros(n),
            'island': lambda n: np.full(n, -1, dtype=np.int64),
        }
        kwargs = {}
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if mine is None and theirs is None:
                kwargs[f.name] = None
                continue
            if mine is None:
                mine = neutral[f.name](len(self))
            if theirs is None:
                theirs = neutral[f.name](len(other))
            kwargs[f.name] = np.concatenate([mine, theirs])
        return ParticleState(**kwargs)

    def subset(self, rows: np.ndarray) -> 'ParticleState':
        """Return a new state of the particles ``rows`` (indices or a mask), arrays copied."""
        kwargs = {}
        for f in fields(self):
            value = getattr(self, f.name)
            kwargs[f.name] = None if value is None else value[rows].copy()
        return ParticleState(**kwargs)

    def in_id_order(self) -> 'ParticleState':
        """Return this state if its rows are in id order, else a copy sorted by id."""
        if ids_ascending(self.ids):
            return self
        return self.subset(id_order(self.ids))

    def with_arrays(self, **arrays: np.ndarray) -> 'ParticleState':
        """Return a shallow copy with some arrays replaced."""
        return replace(self, **arrays)

    def momentum(self) -> np.ndarray:
        """Total linear momentum of the dynamic particles, kg m/s."""
        dyn = self.dynamic
        return np.sum(self.velocity[dyn] / self.inv_mass[dyn, None], axis=0)
