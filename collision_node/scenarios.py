"""Shared scenarios: the scenes both the tests and the benchmarks build.

Each function returns the content of a scene file as a mapping (or the
particle list of one), so a caller adds what it varies (``accuracy``,
``dt``) and hands it to ``parse_scene``; the same arguments always give
the same particles in the same order. Positions are computed so that
touching particles touch exactly in binary where the docstring says so.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Sequence

# m/s^2: the gravity of the scenarios under gravity (pointing along -y).
G = 9.81
# s: the step of the resting scenarios (240 Hz).
RESTING_DT = 1.0 / 240.0


def ball(position: Sequence[float], radius: float, mass: float,
         velocity: Optional[Sequence[float]] = None) -> dict:
    """Return one ``particles`` entry (at rest when ``velocity`` is None)."""
    entry: dict[str, Any] = {'position': list(map(float, position)), 'radius': radius,
                             'mass': mass}
    if velocity is not None:
        entry['velocity'] = list(map(float, velocity))
    return entry


def gas(count: int, radius: float, speed: float, *, mass: float = 1.0, seed: int = 0,
        low: float = 0.0, high: float = 1.0, dimensions: int = 3, walls: bool = True,
        wall_restitution: Optional[float] = None, effects: Optional[Mapping] = None,
        **scene: Any) -> dict:
    """Return ``count`` particles at ``speed`` in random directions in the box [low, high]^d.

    ``walls`` closes the box (with ``wall_restitution`` if given); ``effects``
    adds effects (None and no walls: no ``effects`` key at all); ``scene``
    adds top-level keys (``dt``, ``duration``, ``name``, ``accuracy``).
    """
    box = {'min': [low] * dimensions, 'max': [high] * dimensions}
    declared = None if effects is None else dict(effects)
    if walls:
        declared = dict(declared or {}, walls=dict(box))
        if wall_restitution is not None:
            declared['walls']['restitution'] = wall_restitution
    out = dict(dimensions=dimensions, **scene)
    if declared is not None:
        out['effects'] = declared
    out['generate'] = [{'kind': 'gas', 'count': count, 'radius': radius, 'mass': mass,
                        'speed': speed, 'seed': seed, 'region': box}]
    return out


def cradle(count: int, radius: float, mass: float, speed: float, striker_x: float, *,
           first: int = 0, dimensions: int = 3) -> list:
    """Return Newton's cradle along x: a striker, then ``count - 1`` touching balls at rest.

    The striker sits at ``striker_x`` moving at ``speed`` along +x; the
    resting balls' centres are 2 r (first + k), k = 0 .. count - 2, so
    they touch exactly when 2 r is a power of two times an integer.
    """
    rest = [0.0] * (dimensions - 1)
    balls = [ball([striker_x, *rest], radius, mass, [speed, *rest])]
    balls += [ball([2 * radius * (first + k), *rest], radius, mass) for k in range(count - 1)]
    return balls


def column(count: int, radius: float = 0.05) -> list:
    """Return ``count`` 1 kg discs stacked on the floor y = 0 at x = 0, each touching the next."""
    return [ball([0, radius + 2 * radius * k], radius, 1.0) for k in range(count)]


def hexagonal_pile(radius: float, rows: int, per_row: int) -> list:
    """Return 1 kg discs packed in rows from x = 0, y = 0, each in the hollows of the row below."""
    height = math.sqrt(3.0) * radius
    return [ball([(radius if row % 2 == 0 else 2 * radius) + 2 * radius * k,
                  radius + height * row], radius, 1.0)
            for row in range(rows) for k in range(per_row)]


def resting_column(count: int = 20, restitution: float = 0.0, radius: float = 0.05) -> dict:
    """Return a 2-D column of discs at rest on a floor under gravity, 240 Hz."""
    return {'dimensions': 2, 'dt': RESTING_DT,
            'effects': {'gravity': [0.0, -G], 'walls': {'min': [None, 0.0]},
                        'restitution': restitution},
            'particles': column(count, radius)}


def resting_pile(restitution: float = 0.0, rows: int = 20, per_row: int = 25,
                 radius: float = 0.05) -> dict:
    """Return a 2-D hexagonal pile at rest on a floor between two walls under gravity, 240 Hz.

    The walls stand at x = 0 and x = (2 per_row + 1) r, so the rows that
    start one radius in fit between them.
    """
    return {'dimensions': 2, 'dt': RESTING_DT,
            'effects': {'gravity': [0.0, -G], 'restitution': restitution,
                        'walls': {'min': [0.0, 0.0], 'max': [(2 * per_row + 1) * radius, None]}},
            'particles': hexagonal_pile(radius, rows, per_row)}
