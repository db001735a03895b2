"""The scene's ``effects`` section: which physics a scene declares.

Only what is declared here becomes a stage of the step pipeline; an
absent key means the effect is not simulated at all (the lecture's world
of free, elastic particles).

Keys (all optional)::

    gravity: [gx, gy, gz]                 # m/s^2
    walls: {min: [...], max: [...], restitution: e}
                                          # a box; null components (or a
                                          # missing min/max) leave that side
                                          # open, so {min: [null, 0, null]}
                                          # is a single floor at y = 0
    restitution: e                        # particle-particle, in [0, 1]
    restitution_threshold: s              # m/s, closing speeds below s are
                                          # perfectly inelastic
    friction: mu                          # Coulomb, >= 0; adds spin
    drag: {linear: k1, quadratic: k2}     # F = -(k1 + k2 |v|) v, newtons

Combine rule (restitution and friction alike): each side of a contact
brings a coefficient, the contact uses their geometric mean
sqrt(c_i c_j). A particle without its own ``restitution``/``friction``
brings the contact's default: the scene's value for particle-particle
contacts, the walls' ``restitution`` (or the scene's ``friction``) at a
wall. So two particles of one material keep its value, a particle with
0 makes every contact of its own 0, and nothing changes for particles
that carry no value of their own. The rule itself is
``law/primitives.combined_coefficient``, with the rest of the contact law.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from .particles import MAX_COORDINATE, MAX_FRICTION
from .validation import fail, number, quote, reject_unknown_keys, require_mapping, vector
from ..model.tunables import GRAVITY_THRESHOLD_STEPS

EFFECT_KEYS = ('gravity', 'walls', 'restitution', 'restitution_threshold', 'friction', 'drag')
MAX_THRESHOLD = 1.0e6      # m/s
MAX_DRAG = 1.0e30          # kg/s (linear) or kg/m (quadratic)
MAX_GRAVITY = 1.0e6        # m/s^2 per component, 10^5 g: more is a unit error


@dataclass(frozen=True)
class Walls:
    """Axis-aligned planes that keep particles inside; SI metres.

    ``low``/``high`` hold the plane positions per axis; a component of
    -inf (``low``) or +inf (``high``) means no plane on that side.
    """

    low: np.ndarray
    high: np.ndarray
    restitution: float = 1.0

    def planes(self, dimensions: int) -> list[tuple[int, float, float]]:
        """Return the finite planes as (axis, position, inward sign)."""
        out = []
        for axis in range(dimensions):
            if math.isfinite(self.low[axis]):
                out.append((axis, float(self.low[axis]), 1.0))
            if math.isfinite(self.high[axis]):
                out.append((axis, float(self.high[axis]), -1.0))
        return out


@dataclass(frozen=True)
class Drag:
    """Air drag F = -(linear + quadratic |v|) v in newtons."""

    linear: float = 0.0
    quadratic: float = 0.0


@dataclass(frozen=True)
class Effects:
    """Validated effects of a scene; ``None`` means not declared."""

    gravity: Optional[np.ndarray] = None
    walls: Optional[Walls] = None
    restitution: Optional[float] = None
    restitution_threshold: Optional[float] = None
    friction: Optional[float] = None
    drag: Optional[Drag] = None

    @property
    def particle_restitution(self) -> float:
        """Particle-particle coefficient of restitution (1 when undeclared)."""
        return 1.0 if self.restitution is None else self.restitution

    def threshold(self, dt: float) -> float:
        """Restitution threshold in m/s for a (sub)step of ``dt`` seconds.

        The declared value if any; otherwise 2 |g| dt under gravity and 0
        (the lecture's exact elastic impacts) without it.
        """
        if self.restitution_threshold is not None:
            return self.restitution_threshold
        if self.gravity is None:
            return 0.0
        return GRAVITY_THRESHOLD_STEPS * float(np.linalg.norm(self.gravity)) * dt

    @property
    def spin(self) -> bool:
        """Whether particles carry angular velocity and orientation."""
        return self.friction is not None


def _parse_plane_bounds(spec: Any, where: str, dimensions: int) -> np.ndarray:
    """Validate a ``min``/``max`` list whose components may be null (open side)."""
    if not isinstance(spec, (list, tuple)):
        fail(where, f'expected a list of {dimensions} numbers or nulls, got {quote(spec)}')
    values = [0.0 if c is None else c for c in spec]
    out = vector(values, where, dimensions, max_abs=MAX_COORDINATE)
    for k, c in enumerate(spec):
        if c is None:
            out[k] = np.nan
    return out


def parse_walls(value: Any, where: str, dimensions: int) -> Walls:
    """Validate ``walls``: a box, or single planes where sides are open."""
    spec = require_mapping(value, where)
    reject_unknown_keys(spec, ('min', 'max', 'restitution'), where)
    low = np.full(3, -np.inf)
    high = np.full(3, np.inf)
    if 'min' in spec:
        parsed = _parse_plane_bounds(spec['min'], f'{where}.min', dimensions)
        low = np.where(np.isnan(parsed), -np.inf, parsed)
    if 'max' in spec:
        parsed = _parse_plane_bounds(spec['max'], f'{where}.max', dimensions)
        high = np.where(np.isnan(parsed), np.inf, parsed)
    if dimensions == 2:
        low[2], high[2] = -np.inf, np.inf
    if not (np.isfinite(low[:dimensions]).any() or np.isfinite(high[:dimensions]).any()):
        fail(where, 'no plane given (need min and/or max with at least one number)')
    for axis in range(dimensions):
        if not high[axis] > low[axis]:
            fail(where, f'max must exceed min on every axis (axis {"xyz"[axis]})')
    wall_e = number(spec.get('restitution', 1.0), f'{where}.restitution',
                    minimum=0.0, maximum=1.0)
    return Walls(low=low, high=high, restitution=wall_e)


def parse_drag(value: Any, where: str) -> Drag:
    """Validate ``drag: {linear: k1, quadratic: k2}`` (at least one of them)."""
    spec = require_mapping(value, where)
    reject_unknown_keys(spec, ('linear', 'quadratic'), where)
    if not spec:
        fail(where, 'give linear and/or quadratic')
    linear = number(spec.get('linear', 0.0), f'{where}.linear', minimum=0.0, maximum=MAX_DRAG)
    quadratic = number(spec.get('quadratic', 0.0), f'{where}.quadratic', minimum=0.0,
                       maximum=MAX_DRAG)
    return Drag(linear=linear, quadratic=quadratic)


def parse_effects(value: Any, where: str, dimensions: int) -> Effects:
    """Validate a scene's ``effects`` mapping."""
    if value is None:
        return Effects()
    value = require_mapping(value, where)
    reject_unknown_keys(value, EFFECT_KEYS, where)
    walls = None
    if 'walls' in value:
        walls = parse_walls(value['walls'], f'{where}.walls', dimensions)
    gravity = None
    if 'gravity' in value:
        gravity = vector(value['gravity'], f'{where}.gravity', dimensions, max_abs=MAX_GRAVITY)
    restitution = None
    if 'restitution' in value:
        restitution = number(value['restitution'], f'{where}.restitution', minimum=0.0,
                             maximum=1.0)
    threshold = None
    if 'restitution_threshold' in value:
        threshold = number(value['restitution_threshold'], f'{where}.restitution_threshold',
                           minimum=0.0, maximum=MAX_THRESHOLD)
    friction = None
    if 'friction' in value:
        friction = number(value['friction'], f'{where}.friction', minimum=0.0,
                          maximum=MAX_FRICTION)
    drag = None
    if 'drag' in value:
        drag = parse_drag(value['drag'], f'{where}.drag')
    return Effects(gravity=gravity, walls=walls, restitution=restitution,
                   restitution_threshold=threshold, friction=friction, drag=drag)


def check_particles_for_effects(state, effects: Effects, where: str) -> None:
    """Reject per-particle spin in a world that does not simulate spin.

    Angular velocity only changes through friction; without ``friction``
    no angular state exists, so a given ``angular_velocity`` would be
    silently dropped. ``state`` is a :class:`ParticleState`.
    """
    if effects.spin or state.angular_velocity is None:
        return
    given = np.flatnonzero(np.any(state.angular_velocity != 0.0, axis=1))
    if given.size:
        fail(f'{where}particles[{int(given[0])}].angular_velocity',
             'spin needs effects.friction (without friction no angular state is simulated)')
