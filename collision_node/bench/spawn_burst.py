"""Benchmark the node's commands: a burst of single spawns from one publisher, all answered.

    python -m collision_node.bench commands [--count 10000]

Starts the installed ``collision_node`` (paused, default scene) in a
process on a domain of its own, publishes ``--count`` single-particle
spawns back to back from one KEEP_ALL reliable publisher (each with a
``request_id``), and waits for the answers on ``events``. Prints how many
landed, how many answers each request got, and the wall time to the last
answer, with the machine load.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String

from ..ros.qos import COMMAND_QOS, EVENTS_QOS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Register this benchmark's options."""
    parser.add_argument('--count', type=int, default=10_000, help='spawns in the burst')
    parser.add_argument('--timeout', type=float, default=600.0, help='s to wait for answers')


def run(args: argparse.Namespace) -> int:
    """Run the burst and print the result; 0 if every request got exactly one answer."""
    domain = 1 + os.getpid() % 101
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    node = shutil.which('collision_node', path=os.pathsep.join(
        [os.path.join(sys.prefix, 'bin'), os.environ.get('PATH', '')]))
    process = subprocess.Popen([node, '--ros-args', '-p', 'paused:=true', '-p',
                                f'max_particles:={args.count + 100}'], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    try:
        probe = rclpy.create_node('bench_commands', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        answers: list = []
        probe.create_subscription(String, 'events', answers.append, EVENTS_QOS)
        pub = probe.create_publisher(String, 'spawn', COMMAND_QOS)
        deadline = time.monotonic() + 60.0
        while pub.get_subscription_count() == 0 or probe.count_publishers('events') == 0:
            if time.monotonic() > deadline:
                print('no node answered within 60 s', file=sys.stderr)
                return 1
            executor.spin_once(timeout_sec=0.05)
        # A grid in the table's free lower left (x -1.25..0.55, y -0.6..-0.05: clear of
        # the cue ball at y = 0 and of the rack), so the overlap check passes every spawn.
        spacing = (1.8 * 0.55 / args.count) ** 0.5 * 0.99
        columns = int(1.8 / spacing)
        start = time.monotonic()
        for k in range(args.count):
            x = -1.25 + spacing * (0.5 + k % columns)
            y = -0.6 + spacing * (0.5 + k // columns)
            pub.publish(String(data=json.dumps({'position': [x, y], 'radius': spacing / 4,
                                                'mass': 0.01, 'request_id': k})))
        sent = time.monotonic()
        deadline = sent + args.timeout
        while len(answers) < args.count and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        done = time.monotonic()
        events = [json.loads(m.data) for m in answers]
        per_request = Counter(e['request_id'] for e in events)
        accepted = sum(e['accepted'] for e in events)
        once = sum(1 for k in range(args.count) if per_request[k] == 1)
        print(f'| spawns sent | answered exactly once | accepted | publish s | last answer s |'
              f' load |\n|---|---|---|---|---|---|\n| {args.count} | {once} | {accepted} | '
              f'{sent - start:.2f} | {done - start:.2f} | '
              f'{" ".join(f"{v:.1f}" for v in os.getloadavg())} |')
        return 0 if once == args.count else 1
    finally:
        rclpy.shutdown(context=context)
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
