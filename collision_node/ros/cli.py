"""The node's own command line: ``--help`` and refusing arguments that are not ROS ones.

Everything the node takes is a ROS argument (``--ros-args -p name:=value``,
remappings); anything else is a mistake that would otherwise be ignored.
"""

from __future__ import annotations

import sys
from typing import Optional, Sequence

from rcl_interfaces.msg import ParameterType
from rclpy.utilities import remove_ros_args

from .parameters import PARAMETERS

USAGE = 'usage: collision_node [--help] [--ros-args -p NAME:=VALUE ... -r FROM:=TO ...]'
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


def check_command_line(args: Optional[Sequence[str]] = None) -> Optional[int]:
    """Handle ``--help`` (print, 0) and non-ROS arguments (one line, 2); None: go on.

    ``args`` is a full argv (program name first), ``sys.argv`` when None.
    """
    try:
        extra = remove_ros_args(list(args) if args is not None else sys.argv)[1:]
    except Exception:  # noqa: B902 - malformed ROS arguments: rclpy.init reports them
        return None
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
