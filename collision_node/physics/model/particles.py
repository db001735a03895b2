"""Particle specs (scene ``particles`` entries and spawn requests) to state.

The same function parses a scene file's particle list and a spawn request,
so both entry points accept exactly the same schema.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .state import ParticleState
from .validation import fail, number, reject_unknown_keys, require_mapping, vector

# Bounds that keep every later product finite in float64: kinetic energy
# 0.5 m v^2 with the largest mass and speed stays far below 1.8e308, and
# positions leave room for radii and displacements without losing all
# resolution. A value past them is almost surely a unit or typing error.
MAX_SPEED = 3.0e8          # m/s, the speed of light
MAX_COORDINATE = 1.0e12    # m
MAX_RADIUS = 1.0e9         # m
MAX_MASS = 1.0e30          # kg (inf is allowed and means static)
MIN_VALUE = 1.0e-30        # smallest radius or mass, keeps 1/m finite
MAX_FRICTION = 1.0e3       # a coefficient past this is almost surely a typing error

PARTICLE_KEYS = ('position', 'velocity', 'radius', 'mass', 'restitution', 'friction',
                 'angular_velocity')


def parse_particle(spec: Any, where: str, dimensions: int,
                   allowed_keys: Sequence[str]) -> dict:
    """Validate one particle mapping and return its normalised fields."""
    spec = require_mapping(spec, where)
    reject_unknown_keys(spec, allowed_keys, where)
    for key in ('position', 'radius', 'mass'):
        if key not in spec:
            fail(f'{where}.{key}', 'missing (required: position, radius, mass)')
    out = {
        'position': vector(spec['position'], f'{where}.position', dimensions,
                           max_abs=MAX_COORDINATE),
        'velocity': vector(spec.get('velocity', [0.0] * dimensions), f'{where}.velocity',
                           dimensions, max_abs=MAX_SPEED),
        'radius': number(spec['radius'], f'{where}.radius', minimum=MIN_VALUE,
                         maximum=MAX_RADIUS),
    }
    mass = number(spec['mass'], f'{where}.mass', minimum=MIN_VALUE, allow_inf=True)
    if mass != np.inf and mass > MAX_MASS:
        fail(f'{where}.mass', f'must be <= {MAX_MASS:g} or .inf (static), got {mass:g}')
    if np.linalg.norm(out['velocity']) > MAX_SPEED:
        fail(f'{where}.velocity', f'speed exceeds the supported {MAX_SPEED:g} m/s')
    out['inv_mass'] = 0.0 if mass == np.inf else 1.0 / mass
    if mass == np.inf and np.any(out['velocity'] != 0.0):
        fail(f'{where}.velocity', 'a static particle (mass .inf) cannot move')
    for key in ('restitution', 'friction'):
        if key in spec:
            out[key] = number(spec[key], f'{where}.{key}', minimum=0.0,
                              maximum=1.0 if key == 'restitution' else MAX_FRICTION)
    if 'angular_velocity' in spec:
        out['angular_velocity'] = vector(spec['angular_velocity'],
                                         f'{where}.angular_velocity', 3, max_abs=MAX_SPEED)
    return out


def build_state(records: Sequence[dict], first_id: int = 0) -> ParticleState:
    """Stack validated particle records into a :class:`ParticleState`."""
    n = len(records)
    if n == 0:
        return ParticleState.empty()
    state = ParticleState(
        ids=np.arange(first_id, first_id + n, dtype=np.int64),
        position=np.array([r['position'] for r in records], dtype=float).reshape(n, 3),
        velocity=np.array([r['velocity'] for r in records], dtype=float).reshape(n, 3),
        radius=np.array([r['radius'] for r in records], dtype=float),
        inv_mass=np.array([r['inv_mass'] for r in records], dtype=float),
    )
    for key in ('restitution', 'friction'):
        if any(key in r for r in records):
            setattr(state, key, np.array([r.get(key, np.nan) for r in records], dtype=float))
    if any('angular_velocity' in r for r in records):
        state.angular_velocity = np.array(
            [r.get('angular_velocity', np.zeros(3)) for r in records], dtype=float)
    return state
