"""The node's own command line: ``--help``, and one line for every argument it cannot take.

Everything the node takes is a ROS argument (``--ros-args -p name:=value``,
remappings, ``--params-file``); anything else is a mistake that would
otherwise be ignored. ROS arguments that rcl cannot parse (a ``-p`` value
that is not YAML, a missing or malformed parameters file, a remap without
``:=``) are found here as well, before ``rclpy.init``, and reported as one
line naming the argument instead of rcl's traceback.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
from typing import Optional, Sequence

from rcl_interfaces.msg import ParameterType
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.utilities import remove_ros_args

from .parameters import ACCURACY_EXAMPLE, PARAMETERS

USAGE = 'usage: collision_node [--help] [--ros-args -p NAME:=VALUE ... -r FROM:=TO ...]'
# Characters of an argument quoted in an error line.
MAX_SHOWN = 80
# rcl's words: "Couldn't parse <what>: '<argument>'. Error: <detail>, at <file>:<line>".
_RCL_RULE = re.compile(r"Couldn't parse (?P<what>[^:']+): '(?P<argument>.*)'\. "
                       r"Error: (?P<detail>.*)", re.DOTALL)
_RCL_WHERE = re.compile(r',? at /\S*:\d+')
# A line rcl logs: "[WARN] [1796154877.576942725] [rcl]: <reason>".
_RCL_LOGGED = re.compile(r'^\[(?:WARN|ERROR)\] \[[\d.]+\] \[rcl\]: (.*)$', re.MULTILINE)
TYPE_NAMES = {ParameterType.PARAMETER_BOOL: 'bool', ParameterType.PARAMETER_INTEGER: 'integer',
              ParameterType.PARAMETER_DOUBLE: 'double', ParameterType.PARAMETER_STRING: 'string'}
TOPICS = (
    ('particles/poses', 'out', 'geometry_msgs/PoseArray'),
    ('particles/velocities', 'out', 'geometry_msgs/VelocityStamped, one per particle'),
    ('particles/state', 'out', 'sensor_msgs/PointCloud2 (id x y z vx vy vz radius mass)'),
    ('particles/markers', 'out', 'visualization_msgs/MarkerArray'),
    ('/clock', 'out', 'rosgraph_msgs/Clock, global: not moved by a namespace'),
    ('status', 'out', 'std_msgs/String, JSON'),
    ('events', 'out', 'std_msgs/String, JSON: one answer per request'),
    ('spawn', 'in', 'std_msgs/String, YAML/JSON particles or generate entry'),
    ('delete', 'in', 'std_msgs/String, {ids: [3, [10, 20]]}'),
    ('teleport', 'in', 'std_msgs/String, {id: 3, position: [..], velocity: [..]}'),
    ('impulse', 'in', 'std_msgs/String, {id: 3, impulse: [..]} in N s'),
    ('step', 'in', 'std_msgs/String, {steps: N} while paused'),
    ('reset', 'in', 'std_msgs/Empty'),
    ('reset', 'service', 'std_srvs/Trigger'),
    ('pause', 'service', 'std_srvs/SetBool (true: pause, false: resume)'),
)


def help_text() -> str:
    """Return the ``--help`` text: usage, parameters and topics."""
    lines = [USAGE, '', 'Simulates impulse collisions between spherical particles and '
             'publishes them.', '', 'parameters (-p NAME:=VALUE):']
    for name, (default, descriptor) in PARAMETERS.items():
        kind = TYPE_NAMES.get(descriptor.type, '?')
        extra = ', read-only' if descriptor.read_only else ''
        lines.append(f'  {name} ({kind}, default {default!r}{extra}): {descriptor.description}')
    lines += ['', 'topics and services (relative names follow -r __ns:=/NS):']
    lines += [f'  {name:<22} {direction:<8} {what}' for name, direction, what in TOPICS]
    lines += ['', 'docs/node.md has the details.']
    return '\n'.join(lines)


def _shown(text: str) -> str:
    """Return ``text`` on one line, cut to ``MAX_SHOWN`` characters."""
    text = ' '.join(text.split())
    return text if len(text) <= MAX_SHOWN else text[:MAX_SHOWN] + '...'


def _file_problem(path: str) -> Optional[str]:
    """Say why ``path`` cannot be a parameters file, or None if it is a readable file."""
    if not os.path.exists(path):
        return 'no such file'
    if os.path.isdir(path):
        return 'is a directory, not a parameters file'
    if not os.path.isfile(path):
        return 'is not a regular file'
    if not os.access(path, os.R_OK):
        return 'cannot be read (permission denied)'
    return None


def _parse_capturing_stderr(argv: list[str]
                            ) -> tuple[list[str], str, Optional[Exception]]:
    """Remove ``argv``'s ROS arguments: return the rest, what rcl logged, and its error if any.

    rcl logs some reasons on stderr before it fails (``-r __ns:=relative``:
    "Namespace not remapped to a fully qualified name"); they are caught
    here so a refusal stays one line, and give that line its reason.
    """
    sys.stderr.flush()
    failure: Optional[Exception] = None
    rest: list[str] = []
    with tempfile.TemporaryFile() as captured:
        saved = os.dup(2)
        os.dup2(captured.fileno(), 2)
        try:
            rest = remove_ros_args(argv)
        except (_rclpy.RCLError, _rclpy.UnknownROSArgsError) as error:
            failure = error
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        said = captured.read(1 << 16).decode('utf-8', errors='replace')
    return rest, said, failure


def ros_argument_error(message: str, said: str = '') -> str:
    """Turn rcl's message about a ROS argument it cannot parse into one line naming it.

    ``said`` is what rcl logged while parsing: its last warning, when there
    is one, is the reason (the lexer's words in ``message`` are not).
    """
    message = ' '.join(_RCL_WHERE.sub('', message).split())
    message = message.removeprefix('Failed to parse ROS arguments: ')
    match = _RCL_RULE.search(message)
    if match is None:
        return f'bad ROS argument: {_shown(message.rstrip(" ."))} (see --help)'
    what, argument = match.group('what'), match.group('argument')
    warnings = _RCL_LOGGED.findall(said)
    detail = _shown((warnings[-1] if warnings else match.group('detail')).rstrip(' .'))
    if what == 'params file':
        path = argument.split(' ', 1)[-1]
        problem = _file_problem(path) or f'not a valid parameters file ({detail})'
        return f'--params-file {_shown(path)}: {problem}'
    hint = {
        'parameter override rule': 'write -p NAME:=VALUE as one shell word; the value is '
                                   'YAML, so a mapping or text with spaces is quoted: '
                                   f'{ACCURACY_EXAMPLE}',
        'remap rule': 'a remap is -r FROM:=TO, e.g. -r __ns:=/table',
    }.get(what, 'see --help')
    return f"bad ROS argument '{_shown(argument)}': not a valid {what} ({detail}); {hint}"


def check_command_line(args: Optional[Sequence[str]] = None) -> Optional[int]:
    """Handle ``--help`` (print, 0) and arguments the node cannot take (one line, 2).

    Returns None when the node should go on. ``args`` is a full argv
    (program name first), ``sys.argv`` when None.
    """
    argv = list(args) if args is not None else sys.argv
    rest, said, failure = _parse_capturing_stderr(argv)
    if isinstance(failure, _rclpy.UnknownROSArgsError):
        unknown = ' '.join(re.findall(r"'([^']*)'", str(failure))) or str(failure)
        print(f'collision_node: error: unknown ROS arguments: {_shown(unknown)} '
              '(after --ros-args: -p NAME:=VALUE, -r FROM:=TO, --params-file FILE; '
              'see --help)', file=sys.stderr)
        return 2
    if failure is not None:
        print(f'collision_node: error: {ros_argument_error(str(failure), said)}',
              file=sys.stderr)
        return 2
    sys.stderr.write(said)
    extra = rest[1:]
    if any(a in ('-h', '--help') for a in extra):
        print(help_text())
        return 0
    if extra:
        shown = ' '.join(extra)
        shown = shown if len(shown) <= 80 else shown[:80] + '...'
        print(f'collision_node: error: unrecognized arguments: {shown} '
              '(node settings are ROS parameters: --ros-args -p NAME:=VALUE; see --help)',
              file=sys.stderr)
        return 2
    return None
