"""Bulk particle generators for a scene's ``generate`` entries.

A generator places particles without overlap (each in its own cell of a
lattice whose spacing exceeds the diameter) and gives them random
directions at a fixed speed, reproducibly from ``seed``.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from .particles import MAX_COORDINATE, MAX_SPEED, MIN_VALUE, MAX_MASS, MAX_RADIUS
from .state import ParticleState
from .validation import fail, integer, number, quote, reject_unknown_keys, require_mapping, vector

GENERATE_KEYS = ('kind', 'count', 'radius', 'mass', 'speed', 'seed', 'region')
GENERATOR_KINDS = ('gas',)
# Most particles one entry may generate (the scene's total is bounded by
# scene.MAX_SCENE_PARTICLES, the same number).
MAX_GENERATED = 10_000_000
# Largest seed: seeds are 64-bit numbers, as in every generator's API; a
# longer one is a typing error and only costs time to hash.
MAX_SEED = 2 ** 64 - 1
# Lattice cells are numbered in int64; stay well inside it.
MAX_LATTICE_CELLS = 2 ** 62


def parse_region(value: Any, where: str, dimensions: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate an axis-aligned box ``{min: [...], max: [...]}``."""
    value = require_mapping(value, where)
    reject_unknown_keys(value, ('min', 'max'), where)
    for key in ('min', 'max'):
        if key not in value:
            fail(f'{where}.{key}', 'missing (required: min, max)')
    low = vector(value['min'], f'{where}.min', dimensions, max_abs=MAX_COORDINATE)
    high = vector(value['max'], f'{where}.max', dimensions, max_abs=MAX_COORDINATE)
    for axis in range(dimensions):
        if not high[axis] > low[axis]:
            fail(where, f'max must exceed min on every axis (axis {"xyz"[axis]})')
    return low, high


def parse_generate(spec: Any, where: str, dimensions: int) -> dict:
    """Validate one ``generate`` entry and return its normalised fields."""
    spec = require_mapping(spec, where)
    reject_unknown_keys(spec, GENERATE_KEYS, where)
    for key in ('kind', 'count', 'radius', 'mass', 'region'):
        if key not in spec:
            fail(f'{where}.{key}', 'missing (required: kind, count, radius, mass, region)')
    if spec['kind'] not in GENERATOR_KINDS:
        fail(f'{where}.kind',
             f'unknown kind {quote(spec["kind"])} (known: {", ".join(GENERATOR_KINDS)})')
    out = {
        'kind': spec['kind'],
        'count': integer(spec['count'], f'{where}.count', minimum=1, maximum=MAX_GENERATED),
        'radius': number(spec['radius'], f'{where}.radius', minimum=MIN_VALUE,
                         maximum=MAX_RADIUS),
        'mass': number(spec['mass'], f'{where}.mass', minimum=MIN_VALUE, maximum=MAX_MASS),
        'speed': number(spec.get('speed', 0.0), f'{where}.speed', minimum=0.0,
                        maximum=MAX_SPEED),
        'seed': integer(spec.get('seed', 0), f'{where}.seed', minimum=0, maximum=MAX_SEED),
        'region': parse_region(spec['region'], f'{where}.region', dimensions),
    }
    low, high = out['region']
    spacing = 2.0 * out['radius'] * 1.05
    # Count the lattice in Python floats: a tiny radius in a wide region
    # makes more cells than int64 holds (numpy would wrap around silently).
    per_axis = [math.floor(float(high[axis] - low[axis]) / spacing) for axis in range(dimensions)]
    lattice = math.prod(float(cells) for cells in per_axis)
    if lattice > MAX_LATTICE_CELLS:
        fail(where, f'radius {out["radius"]:g} m makes {lattice:.3g} lattice cells in the '
                    f'region, over the {MAX_LATTICE_CELLS:.3g} a generator can index '
                    '(use a larger radius or a smaller region)')
    capacity = int(lattice)
    if capacity < out['count']:
        fail(where, f'{out["count"]} particles of radius {out["radius"]:g} do not fit the region '
                    f'(room for {capacity} without overlap)')
    return out


def generate_state(spec: Mapping, dimensions: int, first_id: int) -> ParticleState:
    """Create the particles of one validated ``generate`` entry."""
    rng = np.random.default_rng(spec['seed'])
    low, high = spec['region']
    count, radius = spec['count'], spec['radius']
    spacing = 2.0 * radius * 1.05
    cells = np.floor((high - low)[:dimensions] / spacing).astype(np.int64)
    # Pick distinct lattice cells, then jitter inside each cell by what the
    # margin allows, so particles never overlap and never touch the region edge.
    chosen = rng.choice(int(np.prod(cells)), size=count, replace=False)
    index = np.stack(np.unravel_index(chosen, tuple(cells)), axis=1).astype(float)
    slack = spacing / 2.0 - radius
    offset = (high - low)[:dimensions] - cells * spacing
    position = np.zeros((count, 3))
    position[:, :dimensions] = (low[:dimensions] + offset / 2.0 + (index + 0.5) * spacing
                                + rng.uniform(-slack, slack, size=(count, dimensions)))
    direction = np.zeros((count, 3))
    direction[:, :dimensions] = rng.normal(size=(count, dimensions))
    norms = np.linalg.norm(direction, axis=1, keepdims=True)
    norms[norms == 0.0] = 1.0
    velocity = direction / norms * spec['speed']
    return ParticleState(
        ids=np.arange(first_id, first_id + count, dtype=np.int64),
        position=position,
        velocity=velocity,
        radius=np.full(count, radius),
        inv_mass=np.full(count, 1.0 / spec['mass']),
    )
