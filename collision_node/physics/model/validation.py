"""Field checks shared by every entry point (scene file, spawn topic, API).

Each check raises :class:`SceneError` whose message names where the bad
value sits (file, particle index, field) and what is wrong with it, so a
user sees one clear line and nothing is half-applied.
"""

from __future__ import annotations

import math
import re
import reprlib
from typing import Any, Iterable, Mapping, Optional

import numpy as np

# A reason quotes at most this many characters of an offending value, so a
# 10 MB string or an expanded structure never ends up in a log line.
MAX_QUOTE = 40
# A reason is one line of at most this many characters, whatever it holds
# (a safety net: the parts above keep real reasons well under it).
MAX_REASON = 300
# Integers longer than this are not converted (int() of a long numeral is
# quadratic, and anything past 309 digits overflows a float anyway).
MAX_INTEGER_DIGITS = 1000


class _ShortRepr(reprlib.Repr):
    """reprlib's bounded repr, but a long string shows its start, not its ends."""

    def repr_str(self, value: str, level: int) -> str:  # noqa: D102 (reprlib hook)
        if len(value) <= self.maxstring:
            return repr(value)
        return repr(value[:self.maxstring]) + '...'


_short = _ShortRepr()
_short.maxlevel, _short.maxdict, _short.maxlist, _short.maxtuple = 2, 3, 4, 4
_short.maxstring, _short.maxother, _short.maxlong = MAX_QUOTE, MAX_QUOTE, MAX_QUOTE
_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]{0,39}')


def one_line(text: str, limit: int = MAX_QUOTE) -> str:
    """Return ``text`` on one line, cut to ``limit`` characters with '...'."""
    # Look at a bounded window only: never split or copy a huge text whole.
    head = ' '.join(str(text)[:limit * 4 + 8].split())
    if len(head) > limit or len(str(text)) > limit * 4 + 8:
        return head[:max(limit - 3, 0)] + '...'
    return head


def quote(value: Any) -> str:
    """Return a short repr of ``value`` (at most ``MAX_QUOTE`` characters plus '...')."""
    if isinstance(value, int) and not isinstance(value, bool) and \
            value.bit_length() > 3 * MAX_INTEGER_DIGITS:
        return f'an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits'
    return one_line(_short.repr(value), MAX_QUOTE)


class SceneError(ValueError):
    """A scene, spawn request or API argument that cannot be accepted.

    The message is kept to one line of at most ``MAX_REASON`` characters.
    """

    def __init__(self, message: Any = '') -> None:
        """Store ``message`` on one line, cut to ``MAX_REASON`` characters."""
        super().__init__(one_line(message, MAX_REASON))


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
        if key in allowed:
            continue
        if isinstance(key, str) and _NAME.fullmatch(key):
            fail(f'{where}{separator}{key}' if where else key,
                 f'unknown key (allowed: {", ".join(allowed)})')
        # Not even a field name (a line of some other file, a number...):
        # say so without echoing it, it may be anything.
        fail(where or 'input', f'a key that is not a field name (allowed: {", ".join(allowed)})')


class OverflowedNumber(float):
    """A numeral too large for a 64-bit float, such as ``1e999``.

    It reads as inf but, unlike ``.inf``, was never meant as infinity (a
    mass of 1e999 would silently become a static particle): rejected.
    """

    def __new__(cls, text: str) -> 'OverflowedNumber':
        """Keep (the start of) the numeral's text for the error message."""
        negative = text.strip().startswith('-')
        number = super().__new__(cls, -math.inf if negative else math.inf)
        number.text = text[:MAX_QUOTE + 1]
        digits = text.strip().lstrip('+-').replace('_', '')
        number.reason = (f'an integer of {len(digits)} digits overflows a 64-bit float'
                         if digits.isdigit() else
                         f'a numeral of {len(text)} characters is too long to read'
                         if len(text) > MAX_INTEGER_DIGITS else
                         f'{one_line(text)} overflows a 64-bit float')
        return number


def number(value: Any, where: str, *, minimum: Optional[float] = None,
           maximum: Optional[float] = None, exclusive_minimum: bool = False,
           allow_inf: bool = False) -> float:
    """Return ``value`` as a float after checking type, finiteness and range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        fail(where, f'expected a number, got {quote(value)}')
    if isinstance(value, OverflowedNumber):
        fail(where, value.reason)
    try:
        value = float(value)
    except OverflowError:
        fail(where, f'{_digits(value)} overflows a 64-bit float')
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


def _digits(value: int) -> str:
    """Describe a huge integer by its length (str() refuses past 4300 digits)."""
    if value.bit_length() > 3 * MAX_INTEGER_DIGITS:
        return f'an integer of about {int(value.bit_length() * math.log10(2)) + 1} digits'
    return f'an integer of {len(str(abs(value)))} digits'


def integer(value: Any, where: str, *, minimum: int = 0,
            maximum: Optional[int] = None) -> int:
    """Return ``value`` as an int after checking type and bounds.

    A float with an integral value (``1e3``, the way scene files write big
    counts) is accepted as that integer; a refusal quotes the value as
    written (``1e+300``, not its 301 digits).
    """
    if isinstance(value, OverflowedNumber):
        fail(where, value.reason)
    written = value
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        fail(where, f'expected an integer, got {quote(value)}')
    if value < minimum:
        fail(where, f'must be >= {minimum}, got {quote(written)}')
    if maximum is not None and value > maximum:
        fail(where, f'must be <= {maximum}, got {quote(written)}')
    return int(value)


def vector(value: Any, where: str, dimensions: int, *,
           max_abs: Optional[float] = None) -> np.ndarray:
    """Return a finite 3-vector from a list of 3 numbers (or 2 in a 2-D scene).

    A 2-D scene lives in the x-y plane: it accepts [x, y] or [x, y, 0].
    """
    if not isinstance(value, (list, tuple)):
        fail(where, f'expected a list of {dimensions} numbers, got {quote(value)}')
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
