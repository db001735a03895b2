"""Field checks shared by every entry point (scene file, spawn topic, API).

Each check raises :class:`SceneError` whose message names where the bad
value sits (file, particle index, field) and what is wrong with it, so a
user sees one clear line and nothing is half-applied.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Optional

import numpy as np


class SceneError(ValueError):
    """A scene, spawn request or API argument that cannot be accepted."""


def fail(where: str, message: str) -> None:
    """Raise a :class:`SceneError` for the value found at ``where``."""
    raise SceneError(f'{where}: {message}')


def require_mapping(value: Any, where: str) -> Mapping:
    """Return ``value`` if it is a mapping, otherwise raise."""
    if not isinstance(value, Mapping):
        fail(where, f'expected a mapping, got {type(value).__name__}')
    return value


def reject_unknown_keys(data: Mapping, allowed: Iterable[str], where: str, *,
                        separator: str = '.') -> None:
    """Raise if ``data`` has a key outside ``allowed``.

    The key is appended to ``where`` with ``separator``: '.' inside a
    section (``effects.magnetism``), ': ' at the top of a source
    (``scene.yaml: speed``).
    """
    allowed = list(allowed)
    for key in data:
        if key not in allowed:
            fail(f'{where}{separator}{key}' if where else str(key),
                 f'unknown key (allowed: {", ".join(allowed)})')


class OverflowedNumber(float):
    """A numeral too large for a 64-bit float, such as ``1e999``.

    It reads as inf but, unlike ``.inf``, was never meant as infinity (a
    mass of 1e999 would silently become a static particle): rejected.
    """

    def __new__(cls, text: str) -> 'OverflowedNumber':
        """Keep the numeral's text for the error message."""
        negative = text.strip().startswith('-')
        number = super().__new__(cls, -math.inf if negative else math.inf)
        number.text = text
        return number


def number(value: Any, where: str, *, minimum: Optional[float] = None,
           maximum: Optional[float] = None, exclusive_minimum: bool = False,
           allow_inf: bool = False) -> float:
    """Return ``value`` as a float after checking type, finiteness and range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        fail(where, f'expected a number, got {value!r}')
    if isinstance(value, OverflowedNumber):
        fail(where, f'{value.text} overflows a 64-bit float')
    try:
        value = float(value)
    except OverflowError:
        fail(where, f'an integer of {len(str(abs(value)))} digits overflows a 64-bit float')
    if math.isnan(value):
        fail(where, 'must not be NaN')
    if math.isinf(value) and not (allow_inf and value > 0):
        fail(where, f'must be finite, got {value}')
    if minimum is not None:
        if exclusive_minimum and not value > minimum:
            fail(where, f'must be > {minimum:g}, got {value:g}')
        if not exclusive_minimum and value < minimum:
            fail(where, f'must be >= {minimum:g}, got {value:g}')
    if maximum is not None and value > maximum:
        fail(where, f'must be <= {maximum:g}, got {value:g}')
    return value


def integer(value: Any, where: str, *, minimum: int = 0) -> int:
    """Return ``value`` as an int after checking type and lower bound."""
    if isinstance(value, bool) or not isinstance(value, int):
        fail(where, f'expected an integer, got {value!r}')
    if value < minimum:
        fail(where, f'must be >= {minimum}, got {value}')
    return int(value)


def vector(value: Any, where: str, dimensions: int, *,
           max_abs: Optional[float] = None) -> np.ndarray:
    """Return a finite 3-vector from a list of 3 numbers (or 2 in a 2-D scene).

    A 2-D scene lives in the x-y plane: it accepts [x, y] or [x, y, 0].
    """
    if not isinstance(value, (list, tuple)):
        fail(where, f'expected a list of {dimensions} numbers, got {value!r}')
    if dimensions == 2:
        if len(value) not in (2, 3):
            fail(where, f'expected [x, y] or [x, y, 0] in a 2-D scene, got {len(value)} values')
    elif len(value) != 3:
        fail(where, f'expected [x, y, z], got {len(value)} values')
    components = [number(c, f'{where}[{k}]') for k, c in enumerate(value)]
    if dimensions == 2 and len(components) == 3 and components[2] != 0.0:
        fail(where, 'z must be 0 in a 2-D scene (it lives in the x-y plane)')
    if max_abs is not None:
        for k, c in enumerate(components):
            if abs(c) > max_abs:
                fail(f'{where}[{k}]', f'magnitude {abs(c):g} exceeds the supported {max_abs:g}')
    out = np.zeros(3)
    out[:len(components)] = components
    return out
