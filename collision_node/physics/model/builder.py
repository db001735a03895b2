"""Scenes built in code: typed particles, effects and settings, no YAML.

``build_scene`` turns its typed arguments into the mapping a scene file
holds (``scene_mapping``) and hands it to :func:`scene.parse_scene`, so a
scene built in code meets exactly the checks of a file and its errors are
the same one line naming the field (``build_scene: particles[1].radius:
must be >= 1e-30, got -1``). Numpy arrays and scalars are accepted where a
file holds lists and numbers.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from .accuracy import AccuracySettings
from .effects import Drag, Effects, Walls
from .scene import Scene, parse_scene
from .validation import number

# One 3-vector (or 2 in a 2-D scene): a list, tuple or numpy array.
Vector = Sequence[float]
# A preset name, settings (e.g. ``replace(PRESETS['fast'], substeps=2)``) or a mapping.
AccuracyLike = Union[str, AccuracySettings, Mapping[str, Any], None]


@dataclass(frozen=True)
class Particle:
    """One particle as a scene file's ``particles`` entry gives it (SI units)."""

    position: Vector
    radius: float
    # kg; math.inf makes the particle static.
    mass: float
    velocity: Optional[Vector] = None
    # Own coefficients (None: the contact's default, see ``effects``).
    restitution: Optional[float] = None
    friction: Optional[float] = None
    angular_velocity: Optional[Vector] = None

    def mapping(self) -> dict:
        """Return the particle as a scene file writes it, unset fields left out."""
        return {item.name: _plain(getattr(self, item.name)) for item in fields(self)
                if getattr(self, item.name) is not None}


@dataclass(frozen=True)
class Gas:
    """A ``generate`` entry: ``count`` particles at ``speed`` in random directions."""

    count: int
    radius: float
    mass: float
    # The region's corners (a box the particles are placed in without overlap).
    low: Vector
    high: Vector
    speed: float = 0.0
    seed: int = 0

    def mapping(self) -> dict:
        """Return the entry as a scene file's ``generate`` mapping."""
        return {'kind': 'gas', 'count': _plain(self.count), 'radius': _plain(self.radius),
                'mass': _plain(self.mass), 'speed': _plain(self.speed),
                'seed': _plain(self.seed),
                'region': {'min': _plain(self.low), 'max': _plain(self.high)}}


def walls_box(low: Optional[Sequence[Optional[float]]] = None,
              high: Optional[Sequence[Optional[float]]] = None,
              restitution: float = 1.0) -> Walls:
    """Return walls at these plane positions; a missing or None component leaves a side open.

    Only the components' type is checked here; ``build_scene`` checks the
    walls as a file's (bounds, max above min, restitution in [0, 1]).
    """
    def planes(values: Optional[Sequence[Optional[float]]], where: str,
               missing: float) -> np.ndarray:
        out = np.full(3, missing)
        for axis, value in enumerate(values or ()):
            if value is not None:
                out[min(axis, 2)] = number(_plain(value), f'walls_box: {where}[{axis}]',
                                           allow_inf=True)
        return out

    return Walls(low=planes(low, 'low', -math.inf), high=planes(high, 'high', math.inf),
                 restitution=restitution)


def effects_mapping(effects: Union[Effects, Mapping[str, Any], None], dimensions: int
                    ) -> Optional[dict]:
    """Return a scene file's ``effects`` mapping for ``effects`` (None: no effects key)."""
    if effects is None or isinstance(effects, Mapping):
        return None if effects is None else dict(effects)
    if not isinstance(effects, Effects):
        return effects          # the validator names what it is instead of a mapping
    out: dict[str, Any] = {}
    if effects.gravity is not None:
        out['gravity'] = _in_plane(_plain(effects.gravity), dimensions)
    if effects.walls is not None:
        out['walls'] = _walls_mapping(effects.walls, dimensions)
    for key in ('restitution', 'restitution_threshold', 'friction'):
        if getattr(effects, key) is not None:
            out[key] = _plain(getattr(effects, key))
    if effects.drag is not None:
        drag = effects.drag
        out['drag'] = ({'linear': _plain(drag.linear), 'quadratic': _plain(drag.quadratic)}
                       if isinstance(drag, Drag) else _plain(drag))
    return out


def accuracy_mapping(accuracy: AccuracyLike) -> Any:
    """Return a scene file's ``accuracy`` value (every setting, for settings given whole)."""
    if isinstance(accuracy, AccuracySettings):
        return asdict(accuracy)
    return dict(accuracy) if isinstance(accuracy, Mapping) else accuracy


def scene_mapping(particles: Sequence[Union[Particle, Mapping]] = (), *,
                  dimensions: Optional[int] = None, dt: Optional[float] = None,
                  duration: Optional[float] = None,
                  effects: Union[Effects, Mapping[str, Any], None] = None,
                  accuracy: AccuracyLike = None, generate: Sequence[Union[Gas, Mapping]] = (),
                  name: Optional[str] = None) -> dict:
    """Return the mapping a scene file with this content holds (None: the file default)."""
    data: dict[str, Any] = {}
    for key, value in (('name', name), ('dimensions', dimensions), ('dt', dt),
                       ('duration', duration), ('accuracy', accuracy_mapping(accuracy)),
                       ('effects', effects_mapping(effects, dimensions or 3))):
        if value is not None:
            data[key] = _plain(value)
    data['particles'] = [_entry(particle) for particle in particles]
    if generate:
        data['generate'] = [_entry(entry) for entry in generate]
    return data


def build_scene(particles: Sequence[Union[Particle, Mapping]] = (), *,
                dimensions: Optional[int] = None, dt: Optional[float] = None,
                duration: Optional[float] = None,
                effects: Union[Effects, Mapping[str, Any], None] = None,
                accuracy: AccuracyLike = None, generate: Sequence[Union[Gas, Mapping]] = (),
                name: Optional[str] = None, source: str = 'build_scene') -> Scene:
    """Validate a scene given in code, as a scene file with the same content would be.

    ``source`` prefixes every error message, as a file's path does.
    """
    return parse_scene(scene_mapping(particles, dimensions=dimensions, dt=dt,
                                     duration=duration, effects=effects, accuracy=accuracy,
                                     generate=generate, name=name), source)


def _entry(entry: Any) -> Any:
    """Return a ``particles`` or ``generate`` entry as a file's mapping."""
    if isinstance(entry, (Particle, Gas)):
        return entry.mapping()
    return _plain(entry)


def _walls_mapping(walls: Any, dimensions: int) -> Any:
    """Return a scene file's ``walls`` mapping (an open side, an infinite plane, as null)."""
    if not isinstance(walls, Walls):
        return _plain(walls)

    def side(values: Any, open_side: float) -> Any:
        values = _plain(values)
        if not isinstance(values, list):
            return values           # the validator says what it is instead of a list
        return [None if value == open_side else value for value in values[:dimensions]]

    return {'min': side(walls.low, -math.inf), 'max': side(walls.high, math.inf),
            'restitution': _plain(walls.restitution)}


def _in_plane(vector: Any, dimensions: int) -> Any:
    """Drop a 2-D scene's zero z component (a file gives [x, y])."""
    if dimensions == 2 and isinstance(vector, list) and len(vector) == 3 and vector[2] == 0.0:
        return vector[:2]
    return vector


def _plain(value: Any) -> Any:
    """Return numpy arrays and scalars as the lists and numbers a file holds."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, Mapping):
        return {key: _plain(item) for key, item in value.items()}
    return value
