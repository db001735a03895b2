"""Commands on a live world: request parsing, id lists, placement checks, request bodies.

Every command's text goes through :func:`parse_request` (the YAML/JSON
loader of scene files). A request is a mapping whose optional
``request_id`` (a string or a number) the answer echoes; spawn and
teleport also take ``allow_overlap``. Every check here raises
:class:`SceneError` with one line naming the source and the field, before
anything changes, so a refused command leaves the world as it was.

Ids are stable: a particle keeps its id until a reset; ``delete`` leaves
gaps and spawns take ids after the largest one ever given. Id lists in
answers are inclusive ``[first, last]`` ranges (:func:`id_ranges`).
Everything is vectorised numpy (and scipy's k-d tree for large overlap
checks); nothing here knows about ROS.
"""

from __future__ import annotations

import math
from typing import Any, Optional, Union

import numpy as np
from scipy.spatial import cKDTree

from .effects import Walls
from .particles import MAX_COORDINATE, MAX_SPEED
from .scene import parse_request, parse_spawn_data
from .state import rows_named
from .validation import fail, reject_unknown_keys, vector

# The request functions take a ``World`` (typed Any: world.py imports this
# module, and the package keeps no import circle, not even for annotations).
World = Any

RequestId = Union[str, int, float, None]

MAX_REQUEST_ID = 256          # characters of a string request_id
MAX_STEPS = 10_000            # steps one ``step`` request may ask for
# Largest impulse component, N s: keeps the velocity change of the lightest
# particle finite in float64 (the speed bound itself is checked after it).
MAX_IMPULSE = 1e30
# Two spheres overlap when their centres are closer than this share of the
# sum of their radii: touching (a rack of balls placed edge to edge) is
# allowed despite the last bit of rounding.
OVERLAP_SHARE = 1.0 - 1e-9
# Up to this many (new x existing) distances the overlap check is one numpy
# broadcast (a single spawn into 100,000 particles costs well under a ms);
# beyond it a k-d tree finds the close pairs.
BRUTE_FORCE_PAIRS = 1_000_000


# -- request envelope -------------------------------------------------------

def request_id_of(data: Any, source: str) -> RequestId:
    """Return the request's ``request_id`` (None if absent); raise if it is malformed."""
    if not isinstance(data, dict) or 'request_id' not in data:
        return None
    value = data['request_id']
    if isinstance(value, str):
        if len(value) > MAX_REQUEST_ID:
            fail(f'{source}: request_id', f'longer than {MAX_REQUEST_ID} characters')
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (
            isinstance(value, float) and not math.isfinite(value)):
        fail(f'{source}: request_id', f'expected a string or a finite number, '
                                      f'got {_short(value)}')
    if isinstance(value, int) and abs(value) >= 2 ** 63:
        fail(f'{source}: request_id', 'integer does not fit 64 bits')
    return value


def take_options(data: Any, source: str, options: tuple[str, ...] = ()) -> tuple[Any, dict]:
    """Split a request mapping into its body and its options (``request_id`` and ``options``).

    A list or scalar request has no options. ``allow_overlap`` must be a
    boolean when present.
    """
    if not isinstance(data, dict):
        return data, {}
    body = dict(data)
    found = {'request_id': body.pop('request_id', None)}
    for name in options:
        if name in body:
            found[name] = body.pop(name)
    if 'allow_overlap' in found and not isinstance(found['allow_overlap'], bool):
        fail(f'{source}: allow_overlap', f'expected true or false, got '
                                         f'{_short(found["allow_overlap"])}')
    return body, found


def _short(value: Any, limit: int = 40) -> str:
    """Return a short printable prefix of ``value`` for an error message."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + '...'


# -- ids --------------------------------------------------------------------

def id_ranges(ids: np.ndarray) -> list[list[int]]:
    """Return sorted ids as inclusive ``[first, last]`` ranges of consecutive ids."""
    ids = np.unique(np.asarray(ids, dtype=np.int64))
    if ids.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(ids) != 1) + 1
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks - 1, [ids.size - 1]])
    return np.stack([ids[starts], ids[ends]], axis=1).tolist()


def _one_id(value: Any, where: str) -> int:
    """Return a non-negative integer id."""
    if isinstance(value, bool) or not isinstance(value, int):
        fail(where, f'expected an integer id, got {_short(value)}')
    if value < 0 or value >= 2 ** 63:
        fail(where, f'ids are 0 .. 2^63-1, got {value}')
    return int(value)


def parse_ids(value: Any, where: str, limit: int) -> np.ndarray:
    """Return the sorted unique ids of an id list: ints and inclusive ``[first, last]`` ranges.

    A range holding more than ``limit`` ids (the world's particle count)
    must name a missing particle and is refused before it is expanded.
    """
    if not isinstance(value, list):
        value = [value]
    parts = []
    for k, item in enumerate(value):
        if isinstance(item, list):
            if len(item) != 2:
                fail(f'{where}[{k}]', f'a range is [first, last], got {len(item)} values')
            first = _one_id(item[0], f'{where}[{k}][0]')
            last = _one_id(item[1], f'{where}[{k}][1]')
            if last < first:
                fail(f'{where}[{k}]', f'range [{first}, {last}] ends before it starts')
            if last - first + 1 > limit:
                fail(f'{where}[{k}]', f'range [{first}, {last}] holds {last - first + 1} ids, '
                                      f'more than the {limit} particles')
            parts.append(np.arange(first, last + 1, dtype=np.int64))
        else:
            parts.append(np.array([_one_id(item, f'{where}[{k}]')], dtype=np.int64))
    if not parts:
        fail(where, 'names no particle')
    return np.unique(np.concatenate(parts))


def rows_of(ids: np.ndarray, wanted: np.ndarray, where: str) -> np.ndarray:
    """Return the rows of ``wanted`` ids among ``ids``; raise naming a missing one."""
    rows = rows_named(ids, wanted)
    found = rows >= 0
    if not found.all():
        missing = wanted[~found]
        more = f' (and {missing.size - 1} more)' if missing.size > 1 else ''
        fail(where, f'no particle with id {missing[0]}{more}')
    return rows


# -- placement ----------------------------------------------------------------

def check_inside_walls(position: np.ndarray, radius: np.ndarray, walls: Optional[Walls],
                       dimensions: int, where: str) -> None:
    """Raise unless every sphere lies inside the walls' box (touching a wall is inside)."""
    if walls is None or position.shape[0] == 0:
        return
    p, r = position[:, :dimensions], radius[:, None]
    outside = ((p - r < walls.low[:dimensions]) | (p + r > walls.high[:dimensions])).any(axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        low = ', '.join(f'{v:g}' for v in walls.low[:dimensions])
        high = ', '.join(f'{v:g}' for v in walls.high[:dimensions])
        count = int(outside.sum())
        more = f' ({count} particles are)' if count > 1 else ''
        fail(where.format(k), f'position [{", ".join(f"{v:g}" for v in p[k])}] with radius '
                              f'{radius[k]:g} is not inside the walls [{low}] .. [{high}]{more}')


def _close_pairs(a_pos: np.ndarray, a_r: np.ndarray, b_pos: np.ndarray,
                 b_r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (i, j): sphere a[i] overlaps sphere b[j]."""
    if a_pos.shape[0] == 0 or b_pos.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    if a_pos.shape[0] * b_pos.shape[0] <= BRUTE_FORCE_PAIRS:
        gap = a_pos[:, None, :] - b_pos[None, :, :]
        d2 = np.einsum('ijk,ijk->ij', gap, gap)
        reach = (a_r[:, None] + b_r[None, :]) * OVERLAP_SHARE
        return np.nonzero(d2 < reach * reach)
    found = cKDTree(a_pos).sparse_distance_matrix(cKDTree(b_pos), float(a_r.max() + b_r.max()),
                                                  output_type='ndarray')
    hit = found['v'] < (a_r[found['i']] + b_r[found['j']]) * OVERLAP_SHARE
    return found['i'][hit].astype(np.int64), found['j'][hit].astype(np.int64)


def find_overlap(position: np.ndarray, radius: np.ndarray, ids: np.ndarray,
                 new_position: np.ndarray, new_radius: np.ndarray
                 ) -> Optional[tuple[int, str]]:
    """Return (new index, what it overlaps) for the first new sphere that overlaps, or None.

    New spheres are checked against the existing ones (named by id) and
    against each other (named by index in the request).
    """
    i, j = _close_pairs(new_position, new_radius, position, radius)
    first: Optional[tuple[int, str]] = None
    if i.size:
        k = int(np.argmin(i))
        first = (int(i[k]), f'particle {int(ids[j[k]])}')
    n = new_position.shape[0]
    if n > 1:
        if n * n <= BRUTE_FORCE_PAIRS:
            a, b = _close_pairs(new_position, new_radius, new_position, new_radius)
            keep = a < b
            a, b = a[keep], b[keep]
        else:
            tree = cKDTree(new_position)
            pairs = tree.query_pairs(float(2.0 * new_radius.max()), output_type='ndarray')
            gap = new_position[pairs[:, 0]] - new_position[pairs[:, 1]]
            d = np.sqrt(np.einsum('ij,ij->i', gap, gap))
            hit = d < (new_radius[pairs[:, 0]] + new_radius[pairs[:, 1]]) * OVERLAP_SHARE
            low, high = pairs[hit].min(axis=1), pairs[hit].max(axis=1)
            a, b = low, high
        if b.size:
            k = int(np.argmin(b))
            if first is None or int(b[k]) < first[0]:
                first = (int(b[k]), f'the request\'s particle {int(a[k])}')
    return first


def check_no_overlap(position: np.ndarray, radius: np.ndarray, ids: np.ndarray,
                     new_position: np.ndarray, new_radius: np.ndarray, where: str) -> None:
    """Raise if a new sphere overlaps an existing one or another new one."""
    found = find_overlap(position, radius, ids, new_position, new_radius)
    if found is not None:
        k, other = found
        fail(where.format(k), f'overlaps {other} (send allow_overlap: true to place it anyway)')


# -- request bodies -------------------------------------------------------------

def spawn_request(world: World, data: Any, source: str = 'spawn') -> np.ndarray:
    """Spawn a parsed request's particles (refusing overlaps unless ``allow_overlap``)."""
    body, options = take_options(data, source, ('allow_overlap',))
    particles = parse_spawn_data(body, world.scene.dimensions, len(world.state), source,
                                 world.max_particles)
    return world.spawn(particles, allow_overlap=options.get('allow_overlap', False),
                       allow_outside=False, source=source)


def delete_request(world: World, data: Any, source: str = 'delete') -> np.ndarray:
    """Delete the particles a request names: ``{ids: [...]}``, a list, or one id."""
    body, _ = take_options(data, source)
    where = f'{source}: ids'
    if isinstance(body, dict):
        reject_unknown_keys(body, ('ids',), source, separator=': ')
        if 'ids' not in body:
            fail(where, 'missing (e.g. {ids: [3, [10, 20]]})')
        body = body['ids']
    return world.delete(parse_ids(body, where, len(world.state)), source=source)


def _particle_id(body: Any, source: str, keys: tuple[str, ...]) -> int:
    """Check a single-particle request's keys and return its ``id``."""
    if not isinstance(body, dict):
        fail(source, f'expected a mapping with {", ".join(keys)}, got {_short(body)}')
    reject_unknown_keys(body, keys, source, separator=': ')
    if 'id' not in body:
        fail(f'{source}: id', 'missing')
    return _one_id(body['id'], f'{source}: id')


def teleport_request(world: World, data: Any, source: str = 'teleport') -> int:
    """Set one particle's position and/or velocity: ``{id, position?, velocity?}``."""
    body, options = take_options(data, source, ('allow_overlap',))
    pid = _particle_id(body, source, ('id', 'position', 'velocity'))
    if 'position' not in body and 'velocity' not in body:
        fail(source, 'give position and/or velocity')
    d = world.scene.dimensions
    position = (vector(body['position'], f'{source}: position', d, max_abs=MAX_COORDINATE)
                if 'position' in body else None)
    velocity = (vector(body['velocity'], f'{source}: velocity', d, max_abs=MAX_SPEED)
                if 'velocity' in body else None)
    world.teleport(pid, position, velocity, allow_overlap=options.get('allow_overlap', False),
                   source=source)
    return pid


def impulse_request(world: World, data: Any, source: str = 'impulse') -> int:
    """Apply an impulse (N s) to one particle: ``{id, impulse: [jx, jy(, jz)]}``."""
    body, _ = take_options(data, source)
    pid = _particle_id(body, source, ('id', 'impulse'))
    if 'impulse' not in body:
        fail(f'{source}: impulse', 'missing (N s, e.g. [0.1, 0])')
    impulse = vector(body['impulse'], f'{source}: impulse', world.scene.dimensions,
                     max_abs=MAX_IMPULSE)
    world.apply_impulse(pid, impulse, source=source)
    return pid


def step_count(data: Any, source: str = 'step') -> int:
    """Return the steps a ``step`` request asks for: ``{steps: N}`` or a bare N (1..MAX_STEPS)."""
    body, _ = take_options(data, source)
    if isinstance(body, dict):
        reject_unknown_keys(body, ('steps',), source, separator=': ')
        body = body.get('steps', 1)
    if isinstance(body, bool) or not isinstance(body, int):
        fail(f'{source}: steps', f'expected an integer, got {_short(body)}')
    if not 1 <= body <= MAX_STEPS:
        fail(f'{source}: steps', f'must be 1 .. {MAX_STEPS}, got {body}')
    return int(body)


__all__ = ['MAX_STEPS', 'check_inside_walls', 'check_no_overlap', 'delete_request',
           'find_overlap', 'id_ranges', 'impulse_request', 'parse_ids', 'parse_request',
           'request_id_of', 'rows_of', 'spawn_request', 'step_count', 'take_options',
           'teleport_request']
