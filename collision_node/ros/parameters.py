"""The node's parameters: names, defaults, descriptors (types, ranges) and checks."""

from __future__ import annotations

import math
from typing import Any, Optional

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)

# The shipped scene the node runs when no scene is given.
DEFAULT_SCENE = 'elastic_break'


def _descriptor(description: str, kind: int, read_only: bool = False,
                floats: Optional[tuple[float, float]] = None,
                integers: Optional[tuple[int, int]] = None) -> ParameterDescriptor:
    """Return a parameter descriptor with an optional inclusive range."""
    descriptor = ParameterDescriptor(description=description, type=kind, read_only=read_only)
    if floats is not None:
        descriptor.floating_point_range = [
            FloatingPointRange(from_value=floats[0], to_value=floats[1], step=0.0)]
    if integers is not None:
        descriptor.integer_range = [
            IntegerRange(from_value=integers[0], to_value=integers[1], step=1)]
    return descriptor


PARAMETERS: dict[str, tuple[Any, ParameterDescriptor]] = {
    'scene': (DEFAULT_SCENE, _descriptor(
        'Scene file path or shipped scene name (default: the elastic billiards break)',
        ParameterType.PARAMETER_STRING, read_only=True)),
    'accuracy': ('', _descriptor(
        "Accuracy preset name or YAML mapping (e.g. '{preset: fast, substeps: 2}') "
        "overriding the scene's; empty: the scene's",
        ParameterType.PARAMETER_STRING, read_only=True)),
    'real_time_factor': (1.0, _descriptor(
        'Simulated seconds per wall second (runtime-changeable)',
        ParameterType.PARAMETER_DOUBLE, floats=(0.001, 1000.0))),
    'publish_rate': (30.0, _descriptor(
        'Hz of wall time at which outputs and /clock are published (runtime-changeable)',
        ParameterType.PARAMETER_DOUBLE, floats=(0.1, 1000.0))),
    'paused': (False, _descriptor(
        'Stop stepping; outputs keep being published (runtime-changeable)',
        ParameterType.PARAMETER_BOOL)),
    'publish_clock': (True, _descriptor(
        'Publish simulated time on /clock (runtime-changeable)',
        ParameterType.PARAMETER_BOOL)),
    'frame_id': ('world', _descriptor(
        'Frame of every output header (runtime-changeable)',
        ParameterType.PARAMETER_STRING)),
    'max_particles': (100_000, _descriptor(
        'Most particles the world may hold; larger spawns are rejected',
        ParameterType.PARAMETER_INTEGER, read_only=True, integers=(1, 10_000_000))),
}


def invalid_parameter(values: dict[str, Any]) -> Optional[str]:
    """Return why a set of parameter values is invalid, or None."""
    for name in ('real_time_factor', 'publish_rate'):
        if name in values and not math.isfinite(values[name]):
            return f'{name}: must be finite, got {values[name]!r}'
    frame = values.get('frame_id')
    if frame is not None and (not frame or frame != frame.strip() or ' ' in frame):
        return f'frame_id: must be a non-empty name without spaces, got {frame!r}'
    return None
