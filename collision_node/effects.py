"""The scene's ``effects`` section: which physics a scene declares.

Only what is declared here becomes a stage of the step pipeline; an
absent key means the effect is not simulated at all (the lecture's world
of free, elastic particles).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from .generate import parse_region
from .validation import number, reject_unknown_keys, require_mapping, vector

EFFECT_KEYS = ('gravity', 'walls', 'restitution')


@dataclass(frozen=True)
class Walls:
    """An axis-aligned box that keeps particles inside; SI metres."""

    low: np.ndarray
    high: np.ndarray
    restitution: float = 1.0


@dataclass(frozen=True)
class Effects:
    """Validated effects of a scene; ``None`` means not declared."""

    gravity: Optional[np.ndarray] = None
    walls: Optional[Walls] = None
    restitution: Optional[float] = None

    @property
    def particle_restitution(self) -> float:
        """Particle-particle coefficient of restitution (1 when undeclared)."""
        return 1.0 if self.restitution is None else self.restitution


def parse_effects(value: Any, where: str, dimensions: int) -> Effects:
    """Validate a scene's ``effects`` mapping."""
    if value is None:
        return Effects()
    value = require_mapping(value, where)
    reject_unknown_keys(value, EFFECT_KEYS, where)
    walls = None
    if 'walls' in value:
        spec = require_mapping(value['walls'], f'{where}.walls')
        reject_unknown_keys(spec, ('min', 'max', 'restitution'), f'{where}.walls')
        low, high = parse_region({k: spec[k] for k in ('min', 'max') if k in spec},
                                 f'{where}.walls', dimensions)
        wall_e = number(spec.get('restitution', 1.0), f'{where}.walls.restitution',
                        minimum=0.0, maximum=1.0)
        walls = Walls(low=low, high=high, restitution=wall_e)
    gravity = None
    if 'gravity' in value:
        gravity = vector(value['gravity'], f'{where}.gravity', dimensions, max_abs=1e6)
    restitution = None
    if 'restitution' in value:
        restitution = number(value['restitution'], f'{where}.restitution', minimum=0.0,
                             maximum=1.0)
    return Effects(gravity=gravity, walls=walls, restitution=restitution)
