"""A terminal viewer for a running collision_node: a live summary line and PNG snapshots.

    viewer                         # one live line: particles, time, RTF, collisions/s, energy
    viewer --once                  # print one summary and exit
    viewer --snapshot world.png    # draw the particles into a PNG and exit
    viewer --collisions            # one line per impact the node resolves (--once: one batch)

It subscribes to the node's ``status`` (JSON), for a snapshot to
``particles/state`` and for ``--collisions`` to ``particles/collisions``
(PointClouds, decoded by :mod:`msg_adapters`). Topic
names are relative: ``--ros-args -r __ns:=/ns`` follows a namespaced node.
Exit codes: 0 done or Ctrl-C, 1 nothing heard before ``--timeout``,
2 bad arguments or an unwritable snapshot path.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Optional, TextIO

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from msg_adapters import impacts_from_point_cloud, seconds_from_stamp, state_from_point_cloud

from .qos import COLLISIONS_QOS, STATE_QOS, STATUS_QOS

DEFAULT_ONE_SHOT_TIMEOUT = 10.0


def summary_line(status: Mapping[str, Any]) -> str:
    """Return the one-line summary of a node status."""
    flags = []
    if status.get('paused'):
        flags.append('paused')
    if not status.get('keeping_up', True):
        flags.append('cannot keep up')
    if status.get('error'):
        flags.append(f'stopped: {status["error"]}')
    return (f'{status["scene"]}: {status["particles"]} particles  '
            f't = {status["time"]:.3f} s  '
            f'RTF {status["measured_real_time_factor"]:.2f} '
            f'(target {status["real_time_factor"]:g})  '
            f'{status["collisions_per_second"]:.1f} collisions/s  '
            f'KE {status["kinetic_energy"]:.6g} J'
            + (f'  [{", ".join(flags)}]' if flags else ''))


def collision_lines(impacts: Mapping[str, np.ndarray]) -> list[str]:
    """Return one line per impact of a decoded ``particles/collisions`` message."""
    lines = []
    for k in range(len(impacts['time'])):
        j = int(impacts['j'][k])
        other = 'wall' if j < 0 else str(j)
        point = ' '.join(f'{v:.6g}' for v in impacts['point'][k])
        normal = ' '.join(f'{v:.6g}' for v in impacts['normal'][k])
        lines.append(f't = {impacts["time"][k]:.6f} s  {int(impacts["i"][k])} - {other}  '
                     f'at ({point})  normal ({normal})  '
                     f'J = {impacts["normal_impulse"][k]:.6g} N s  '
                     f'Jt = {impacts["tangential_impulse"][k]:.6g} N s  '
                     f'closing {impacts["closing_speed"][k]:.6g} m/s')
    return lines


def draw_snapshot(state: Mapping[str, np.ndarray], title: str, path: Path) -> None:
    """Draw the particles (x-y plane, to scale, coloured by speed) into a PNG."""
    import matplotlib
    matplotlib.use('Agg')
    from matplotlib import pyplot
    from matplotlib.collections import EllipseCollection

    position, radius = state['position'], state['radius']
    speed = np.linalg.norm(state['velocity'], axis=1)
    low, high = np.array([-1.0, -1.0]), np.array([1.0, 1.0])
    if radius.size:
        low = (position[:, :2] - radius[:, None]).min(axis=0)
        high = (position[:, :2] + radius[:, None]).max(axis=0)
        margin = 0.05 * max(float((high - low).max()), 1e-9)
        low, high = low - margin, high + margin
    # Size the figure to the world's aspect ratio (within limits) so it fills the picture.
    aspect = float(np.clip((high[1] - low[1]) / (high[0] - low[0]), 0.3, 1.5))
    figure, axes = pyplot.subplots(figsize=(9.0, 1.2 + 7.0 * aspect), dpi=100,
                                   layout='constrained')
    try:
        if radius.size:
            diameters = 2.0 * radius
            circles = EllipseCollection(diameters, diameters, np.zeros_like(radius),
                                        units='xy', offsets=position[:, :2],
                                        offset_transform=axes.transData, cmap='viridis',
                                        edgecolors='black', linewidths=0.3)
            circles.set_array(speed)
            axes.add_collection(circles)
            figure.colorbar(circles, ax=axes, label='speed (m/s)', shrink=0.8)
        axes.set_xlim(low[0], high[0])
        axes.set_ylim(low[1], high[1])
        axes.set_aspect('equal')
        axes.set_xlabel('x (m)')
        axes.set_ylabel('y (m)')
        axes.set_title(title)
        figure.savefig(path)
    finally:
        pyplot.close(figure)


class Viewer(Node):
    """Collects the newest status and (for a snapshot) the newest state."""

    def __init__(self, want_state: bool, want_collisions: bool = False) -> None:
        """Subscribe to ``status`` and, if asked, ``particles/state`` and the collisions."""
        super().__init__('collision_viewer')
        self.status: Optional[dict] = None
        self.status_count = 0
        self.state: Optional[PointCloud2] = None
        self.collisions: list[str] = []     # lines not printed yet
        self.create_subscription(String, 'status', self._on_status, STATUS_QOS)
        if want_state:
            self.create_subscription(PointCloud2, 'particles/state', self._on_state, STATE_QOS)
        if want_collisions:
            self.create_subscription(PointCloud2, 'particles/collisions', self._on_collisions,
                                     COLLISIONS_QOS)

    def _on_status(self, msg: String) -> None:
        self.status = json.loads(msg.data)
        self.status_count += 1

    def _on_state(self, msg: PointCloud2) -> None:
        self.state = msg

    def _on_collisions(self, msg: PointCloud2) -> None:
        self.collisions.extend(collision_lines(impacts_from_point_cloud(msg)))


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    """Parse the viewer's own arguments (ROS arguments already removed)."""
    parser = argparse.ArgumentParser(
        prog='viewer', description='Watch a running collision_node from the terminal.')
    parser.add_argument('--once', action='store_true',
                        help='print one summary line and exit')
    parser.add_argument('--snapshot', type=Path, metavar='FILE.png',
                        help='write a picture of the particles to FILE.png and exit')
    parser.add_argument('--collisions', action='store_true',
                        help='print one line per impact (time, ids, point, normal, impulses, '
                             'closing speed) instead of the summary; with --once, stop after '
                             'the first batch of impacts')
    parser.add_argument('--timeout', type=float, metavar='S',
                        help=f'give up after S seconds without the node (default '
                             f'{DEFAULT_ONE_SHOT_TIMEOUT:g} with --once/--snapshot, '
                             'none when live)')
    args = parser.parse_args(argv)
    if args.timeout is not None and not args.timeout > 0:
        parser.error(f'--timeout must be > 0, got {args.timeout}')
    if args.collisions and args.snapshot is not None:
        parser.error('--collisions and --snapshot do not go together')
    if args.snapshot is not None and args.snapshot.suffix.lower() != '.png':
        parser.error(f'--snapshot must name a .png file, got {args.snapshot}')
    if args.snapshot is not None and not args.snapshot.resolve().parent.is_dir():
        parser.error(f'--snapshot: directory {args.snapshot.resolve().parent} does not exist')
    return args


def run_collisions(viewer: Viewer, args: argparse.Namespace, out: TextIO) -> int:
    """Print impact lines as they come; with --once stop after the first batch.

    Live, ``--timeout`` ends the listening (exit 0); with ``--once`` it is an
    error (exit 1) when no impact came.
    """
    timeout = args.timeout if args.timeout is not None else (
        DEFAULT_ONE_SHOT_TIMEOUT if args.once else None)
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        rclpy.spin_once(viewer, timeout_sec=0.1)
        if viewer.collisions:
            out.write(''.join(line + '\n' for line in viewer.collisions))
            out.flush()
            viewer.collisions.clear()
            if args.once:
                return 0
        if deadline is not None and time.monotonic() > deadline:
            if args.once:
                print(f'viewer: no impact from collision_node within {timeout:g} s '
                      '(is it running, on the same ROS_DOMAIN_ID and namespace?)',
                      file=sys.stderr)
                return 1
            return 0


def run(viewer: Viewer, args: argparse.Namespace, out: TextIO) -> int:
    """Spin until the request is served; return the exit code."""
    if getattr(args, 'collisions', False):
        return run_collisions(viewer, args, out)
    one_shot = args.once or args.snapshot is not None
    timeout = args.timeout if args.timeout is not None else (
        DEFAULT_ONE_SHOT_TIMEOUT if one_shot else None)
    deadline = None if timeout is None else time.monotonic() + timeout
    live = out.isatty()
    shown = 0
    while True:
        rclpy.spin_once(viewer, timeout_sec=0.1)
        if viewer.status_count > shown:
            shown = viewer.status_count
            if not one_shot:
                line = summary_line(viewer.status)
                out.write(f'\r\x1b[2K{line}' if live else line + '\n')
                out.flush()
        if one_shot and viewer.status is not None and (
                args.snapshot is None or viewer.state is not None):
            break
        if deadline is not None and time.monotonic() > deadline:
            missing = 'status' if viewer.status is None else 'particles/state'
            print(f'viewer: no {missing} from collision_node within {timeout:g} s '
                  '(is it running, on the same ROS_DOMAIN_ID and namespace?)', file=sys.stderr)
            return 1
    print(summary_line(viewer.status), file=out)
    if args.snapshot is not None:
        state = state_from_point_cloud(viewer.state)
        title = (f'{viewer.status["scene"]}: {len(state["ids"])} particles, '
                 f't = {seconds_from_stamp(viewer.state.header.stamp):.3f} s')
        try:
            draw_snapshot(state, title, args.snapshot)
        except OSError as error:
            print(f'viewer: cannot write {args.snapshot}: {error}', file=sys.stderr)
            return 2
        print(f'wrote {args.snapshot}', file=out)
    return 0


def main(args: Optional[list[str]] = None) -> int:
    """Run the viewer; see the module docstring for options and exit codes."""
    argv = sys.argv if args is None else ['viewer', *args]
    options = parse_arguments(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    viewer = None
    try:
        viewer = Viewer(want_state=options.snapshot is not None,
                        want_collisions=options.collisions)
        return run(viewer, options, sys.stdout)
    except (KeyboardInterrupt, ExternalShutdownException):
        if sys.stdout.isatty():
            print()
        return 0
    finally:
        if viewer is not None:
            viewer.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    raise SystemExit(main())
