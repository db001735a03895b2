"""The node's parameters: names, defaults, descriptors (types, ranges) and checks."""

from __future__ import annotations

import math
import re
from typing import Any, Optional

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)
from rclpy.parameter import Parameter

from ..physics.model.scene import MAX_SCENE_PARTICLES
from ..physics.model.tunables import MAX_THREADS

# The shipped scene the node runs when no scene is given.
DEFAULT_SCENE = 'elastic_break'
# How a mapping is given on the command line: rcl reads a -p value as YAML, so
# the mapping travels as a YAML string (quoted inside the shell word).
ACCURACY_EXAMPLE = '-p "accuracy:=' + "'{preset: fast, substeps: 2}'" + '"'
# Bounds of the numeric parameters (rcl refuses a value outside them, at start-up
# or on a set, with the range in its reason; docs/scenes.md, "Limits").
# Simulated seconds per wall second (default 1): six decades around real time;
# outside them a value is almost surely a typing error.
REAL_TIME_FACTOR_RANGE = (0.001, 1000.0)
# Hz of wall time (default 30): below 0.1 Hz a tick comes more than 10 s after
# the last; above 1000 Hz its period would be under a millisecond.
PUBLISH_RATE_RANGE = (0.1, 1000.0)
# Particles the world may hold (default 100,000): at most what one scene may.
MAX_PARTICLES_RANGE = (1, MAX_SCENE_PARTICLES)
# Threads the kernels share a step among (default 0: every core); a count
# over what the process can run (its cores) is refused at start-up.
THREADS_RANGE = (0, MAX_THREADS)


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
        "Accuracy preset name or YAML mapping overriding the scene's, a mapping "
        f"quoted as a YAML string ({ACCURACY_EXAMPLE}); empty: the scene's",
        ParameterType.PARAMETER_STRING, read_only=True)),
    'real_time_factor': (1.0, _descriptor(
        'Simulated seconds per wall second (runtime-changeable)',
        ParameterType.PARAMETER_DOUBLE, floats=REAL_TIME_FACTOR_RANGE)),
    'publish_rate': (30.0, _descriptor(
        'Hz of wall time at which outputs and /clock are published (runtime-changeable)',
        ParameterType.PARAMETER_DOUBLE, floats=PUBLISH_RATE_RANGE)),
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
        ParameterType.PARAMETER_INTEGER, read_only=True, integers=MAX_PARTICLES_RANGE)),
    'threads': (0, _descriptor(
        'Threads the compiled kernels share each step among; 0: every core, 1: single-thread '
        'kernels (results are the same for every count)',
        ParameterType.PARAMETER_INTEGER, read_only=True, integers=THREADS_RANGE)),
    'record': ('', _descriptor(
        'Record what the node publishes as a rosbag2 bag (MCAP) in this new folder, '
        'stamped with simulated time; empty: no recording',
        ParameterType.PARAMETER_STRING, read_only=True)),
}


# Parameters of type double that also take an integer (``-p real_time_factor:=2``,
# ``ros2 param set ... 2``): the integer is converted before any check.
DOUBLE_PARAMETERS = tuple(name for name, (_, d) in PARAMETERS.items()
                          if d.type == ParameterType.PARAMETER_DOUBLE)
# A frame name as tf2 and RViz take it: a letter or underscore, then letters,
# digits, underscores and slashes (``robot1/base_link``); no whitespace or
# control characters, at most MAX_FRAME_ID characters.
FRAME_ID = re.compile(r'[A-Za-z_][A-Za-z0-9_/]*')
MAX_FRAME_ID = 256


def as_double(parameter: Parameter) -> Parameter:
    """Return ``parameter`` with an integer value turned into a double if it is a double one."""
    if parameter.name in DOUBLE_PARAMETERS and parameter.type_ == Parameter.Type.INTEGER:
        return Parameter(parameter.name, Parameter.Type.DOUBLE, float(parameter.value))
    return parameter


def integers_as_doubles(parameters: list[Parameter]) -> list[Parameter]:
    """Pre-set callback: integers given to double parameters become doubles."""
    return [as_double(p) for p in parameters]


def invalid_parameter(values: dict[str, Any]) -> Optional[str]:
    """Return why a set of parameter values is invalid, or None."""
    for name in DOUBLE_PARAMETERS:
        if name in values and isinstance(values[name], float) and \
                not math.isfinite(values[name]):
            return f'{name}: must be finite (out of range), got {values[name]!r}'
    frame = values.get('frame_id')
    if isinstance(frame, str):
        if len(frame) > MAX_FRAME_ID:
            return f'frame_id: longer than {MAX_FRAME_ID} characters ({len(frame)})'
        if not FRAME_ID.fullmatch(frame):
            return ('frame_id: must be a frame name ([A-Za-z_][A-Za-z0-9_/]*, no spaces or '
                    f'control characters), got {frame[:40]!r}')
    return None
