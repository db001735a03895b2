"""Accuracy settings: how a step trades exactness for time.

A scene's ``accuracy`` key is a preset name or a mapping of settings,
optionally based on a preset (``{preset: fast, substeps: 2}``); every
setting not given comes from the preset.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

from .validation import fail, integer, reject_unknown_keys

ORDERINGS = ('sequential',)


@dataclass(frozen=True)
class AccuracySettings:
    """Tunables of the contact pipeline, all in one object."""

    substeps: int = 1
    ordering: str = 'sequential'
    iterations: int = 32


PRESETS: dict[str, AccuracySettings] = {
    'balanced': AccuracySettings(),
}
DEFAULT_PRESET = 'balanced'


def parse_accuracy(value: Any, where: str) -> AccuracySettings:
    """Validate an ``accuracy`` value: a preset name or a settings mapping."""
    if value is None:
        return PRESETS[DEFAULT_PRESET]
    if isinstance(value, str):
        if value not in PRESETS:
            fail(where, f'unknown preset {value!r} (known: {", ".join(PRESETS)})')
        return PRESETS[value]
    if not isinstance(value, dict):
        fail(where, f'expected a preset name or a mapping, got {value!r}')
    names = [f.name for f in fields(AccuracySettings)]
    reject_unknown_keys(value, ['preset'] + names, where)
    base = parse_accuracy(value.get('preset', DEFAULT_PRESET), f'{where}.preset')
    changes = {}
    for key in ('substeps', 'iterations'):
        if key in value:
            changes[key] = integer(value[key], f'{where}.{key}', minimum=1)
    if 'ordering' in value:
        if value['ordering'] not in ORDERINGS:
            fail(f'{where}.ordering',
                 f'unknown ordering {value["ordering"]!r} (known: {", ".join(ORDERINGS)})')
        changes['ordering'] = value['ordering']
    return replace(base, **changes)
