"""Node start: seconds from starting the node to its first published pose.

``python -m collision_node.bench node-start`` starts the installed
``collision_node`` executable (default scene) on a domain of its own, this
machine only, and waits for the first ``particles/poses`` message; it
prints the time from process start to that message and the node's
kernel-compile log line, if any. It also prints when the node was ready
(the time stamp of its ``scene ...`` log line, written just before its
timers start): the difference is DDS discovery between the two processes,
which the node does not control (Fast DDS announces a participant in a
burst at start, then every 3 s; a missed burst costs up to 3 s). Run it twice with the same empty
``NUMBA_CACHE_DIR`` to measure a first start (kernels compiled) and a
second start (kernels loaded from the cache).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import rclpy
from geometry_msgs.msg import PoseArray
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``node-start``."""
    parser.add_argument('--domain', type=int, default=77, help='ROS domain id (77)')
    parser.add_argument('--timeout', type=float, default=120.0, help='seconds to wait (120)')
    parser.add_argument('--node-pythonpath', default=None,
                        help="PYTHONPATH of the node (default: this process's), e.g. another "
                        'checkout to compare')


def run(args: argparse.Namespace) -> int:
    """Start the node, wait for its first pose, print the seconds taken."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               ROS_DOMAIN_ID=str(args.domain), PYTHONUNBUFFERED='1')
    if args.node_pythonpath is not None:
        env['PYTHONPATH'] = args.node_pythonpath
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(args.domain))
    rclpy.init()
    node = rclpy.create_node('node_start_bench')
    got: list[float] = []
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                     durability=DurabilityPolicy.VOLATILE)
    node.create_subscription(PoseArray, 'particles/poses',
                             lambda _msg: got.append(time.time()), qos)
    exe = shutil.which('collision_node', path=os.pathsep.join(
        [str(Path(sys.prefix) / 'bin'), os.environ.get('PATH', '')]))
    err = tempfile.TemporaryFile('w+')
    start = time.time()
    process = subprocess.Popen([exe], env=env, stdout=subprocess.DEVNULL, stderr=err, text=True)
    try:
        while not got and time.time() - start < args.timeout:
            rclpy.spin_once(node, timeout_sec=0.05)
    finally:
        process.terminate()
        process.wait(timeout=30)
        node.destroy_node()
        rclpy.shutdown()
    err.seek(0)
    lines = err.readlines()
    compile_lines = [line.strip() for line in lines if 'kernel' in line]
    ready = _ready_time(lines)
    if not got:
        print(f'no pose within {args.timeout:g} s')
        return 1
    print(f'first pose {got[0] - start:.2f} s after start; '
          f'NUMBA_CACHE_DIR={os.environ.get("NUMBA_CACHE_DIR", "(package __pycache__)")}')
    if ready is not None:
        print(f'node ready {ready - start:.2f} s after start (its scene log line); '
              f'discovery and first tick took the other {got[0] - ready:.2f} s')
    for line in compile_lines:
        print(f'  node log: {line}')
    return 0


def _ready_time(lines: list[str]) -> Optional[float]:
    """Return the epoch time stamp of the node's ``scene ...`` log line, if any."""
    for line in lines:
        # ROS console format: [INFO] [1796054923.958465051] [collision_node]: scene ...
        parts = line.split('] [')
        if len(parts) >= 3 and ']: scene ' in line:
            try:
                return float(parts[1])
            except ValueError:
                return None
    return None
