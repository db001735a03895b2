"""Benchmark the node: cost per publish tick of each output, and the real-time factor.

    python -m collision_node.bench node [--sizes 1000 10000] [--seconds 5] [--repeat 20]
    python -m collision_node.bench.node_ticks ...      (the same)

Part 1 builds every output from a gas world of N particles with
:mod:`msg_adapters` and publishes it through a real rclpy publisher
matched by a subscriber in another process, reporting milliseconds per
tick (build and publish separately), next to PoseArray built from
message objects (per-particle outputs up to PER_PARTICLE_UP_TO only).
Part 2 runs the real node in this process on the same gas, with
``particles/state`` and ``particles/poses`` subscribed at 30 Hz, and
reports the real-time factor it sustains at dt = 1/60 and 1/240 s (after
1 s of warm-up): once asked for real time (factor 1) and once asked to go
as fast as it can.
Prints Markdown tables and the machine load (``os.getloadavg``).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import rclpy
from geometry_msgs.msg import Pose, PoseArray, VelocityStamped
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from msg_adapters import (clock_message, marker_array_bytes, point_cloud_bytes,
                          pose_array_bytes, time_message, velocities_bytes)

from ..physics import parse_scene_text
from ..physics.model.state import ParticleState
from ..physics.step.world import World
from ..ros.node import CollisionNode
from ..ros.qos import STATE_QOS, VELOCITY_QOS

GAS_RADIUS = 0.05     # m
GAS_SPEED = 1.0       # m/s
WARM_UP = 1.0         # s of wall time the node runs before a real-time-factor run is timed
# Largest N whose per-particle outputs (N VelocityStamped samples, N Pose objects) are timed:
# beyond it one build takes seconds.
PER_PARTICLE_UP_TO = 100_000


def gas_scene_text(count: int, dt: float, accuracy: str = 'balanced') -> str:
    """Return a 3-D gas of ``count`` particles in a walled cube, ~8 % volume fraction."""
    side = round(max(1.0, (count * (4.0 / 3.0) * np.pi * GAS_RADIUS ** 3 / 0.08) ** (1 / 3)), 3)
    return (f'name: gas_{count}\ndimensions: 3\ndt: {dt!r}\naccuracy: {accuracy}\n'
            f'effects:\n  walls: {{min: [0, 0, 0], max: [{side}, {side}, {side}]}}\n'
            f'generate:\n  - {{kind: gas, count: {count}, radius: {GAS_RADIUS}, mass: 1.0, '
            f'speed: {GAS_SPEED}, seed: 1, region: {{min: [0, 0, 0], '
            f'max: [{side}, {side}, {side}]}}}}\n')


def pose_array_objects(state: ParticleState, seconds: float, frame: str) -> PoseArray:
    """Build a PoseArray the usual way, one Pose object per particle (for comparison)."""
    msg = PoseArray()
    msg.header.stamp = time_message(seconds)
    msg.header.frame_id = frame
    poses = []
    for x, y, z in state.position.tolist():
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = x, y, z
        pose.orientation.w = 1.0
        poses.append(pose)
    msg.poses = poses
    return msg


def best_ms(action: Callable[[], object], repeat: int) -> float:
    """Return the median wall time of ``action`` in milliseconds."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


BENCH_TOPICS = {'bench/poses': (PoseArray, STATE_QOS), 'bench/state': (PointCloud2, STATE_QOS),
                'bench/markers': (MarkerArray, STATE_QOS),
                'bench/velocities': (VelocityStamped, VELOCITY_QOS),
                'bench/clock': (Clock, STATE_QOS),
                'particles/state': (PointCloud2, STATE_QOS),
                'particles/poses': (PoseArray, STATE_QOS)}


def spin_until_stopped(node: Node) -> int:
    """Spin ``node`` until Ctrl-C, SIGTERM or shutdown, then clean up; return 0."""
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def run_sink() -> int:
    """Subscribe (raw, no deserialising) to every benchmark topic until interrupted.

    Run in its own process, as a real subscriber is: a reader in the
    publishing process would add its own work to the publisher's time.
    """
    rclpy.init()
    node = Node('bench_sink')
    for name, (msg_type, qos) in BENCH_TOPICS.items():
        node.create_subscription(msg_type, name, lambda _: None, qos, raw=True)
    return spin_until_stopped(node)


def wait_matched(executor: SingleThreadedExecutor, publishers: list) -> None:
    """Spin until every publisher has the sink as a subscriber."""
    deadline = time.monotonic() + 20.0
    while any(p.get_subscription_count() == 0 for p in publishers):
        executor.spin_once(timeout_sec=0.05)
        if time.monotonic() > deadline:
            raise RuntimeError('the benchmark subscriber was not matched within 20 s')


def output_costs(sizes: list[int], repeat: int) -> list[str]:
    """Return Markdown rows: build and publish ms per tick of each output."""
    source = Node('bench_source')
    pubs = {name: source.create_publisher(t, name, qos)
            for name, (t, qos) in BENCH_TOPICS.items() if name.startswith('bench/')}
    executor = SingleThreadedExecutor()
    executor.add_node(source)
    wait_matched(executor, list(pubs.values()))
    rows = ['| output | N | build (ms) | publish (ms) | total per tick (ms) |',
            '|---|---:|---:|---:|---:|']
    for n in sizes:
        world = World(parse_scene_text(gas_scene_text(n, 1 / 60), 'bench'))
        s, t = world.state, 1.0
        builders: dict[str, tuple[str, Callable[[], object]]] = {
            'particles/poses (CDR from numpy)': ('bench/poses', lambda: pose_array_bytes(
                s.position, s.orientation, t, 'world')),
            'particles/state (CDR from numpy)': ('bench/state', lambda: point_cloud_bytes(
                s.ids, s.position, s.velocity, s.radius, s.inv_mass, t, 'world')),
            'particles/markers (CDR from numpy)': ('bench/markers', lambda: marker_array_bytes(
                s.position, s.radius, s.inv_mass, t, 'world')),
            'particles/velocities (N messages)': ('bench/velocities', lambda: velocities_bytes(
                s.ids, s.velocity, s.angular_velocity, t, 'world')),
            '/clock': ('bench/clock', lambda: clock_message(t)),
            'particles/poses (Pose objects, for comparison)': (
                'bench/poses', lambda: pose_array_objects(s, t, 'world')),
        }
        for label, (topic, build) in builders.items():
            per_particle = 'objects' in label or 'velocities' in label
            if per_particle and n > PER_PARTICLE_UP_TO:
                # Seconds per build (one Python object or DDS sample per particle).
                rows.append(f'| {label} | {n:,} | not timed (over {PER_PARTICLE_UP_TO:,}) '
                            '| - | - |')
                continue
            reps = max(3, repeat // 4) if per_particle else repeat
            message = build()
            publish = pubs[topic].publish
            if isinstance(message, list):
                def send(batch=message):
                    for item in batch:
                        publish(item)
            else:
                def send(one=message):
                    publish(one)
            build_ms = best_ms(build, reps)
            publish_ms = best_ms(send, reps)
            executor.spin_once(timeout_sec=0.0)
            rows.append(f'| {label} | {n:,} | {build_ms:.2f} | {publish_ms:.2f} | '
                        f'{build_ms + publish_ms:.2f} |')
    executor.shutdown()
    source.destroy_node()
    return rows


def sustained_rtf(scene_path: Path, factor: float, seconds: float,
                  publish_rate: float = 30.0) -> dict:
    """Run the node for ``seconds`` with state and poses subscribed; measure what it delivers."""
    node = CollisionNode(parameter_overrides=[
        Parameter('scene', Parameter.Type.STRING, str(scene_path)),
        Parameter('real_time_factor', Parameter.Type.DOUBLE, factor),
        Parameter('publish_rate', Parameter.Type.DOUBLE, publish_rate),
        Parameter('publish_clock', Parameter.Type.BOOL, True)])
    ticks = []
    publish = node.publish_outputs

    def counted() -> None:
        ticks.append(time.monotonic())
        publish()
    node.publish_outputs = counted
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        wait_matched(executor, [node.pub_state, node.pub_poses])
        # Warm up first: a start-up hiccup leaves a backlog the node works off.
        warm_up_end = time.monotonic() + WARM_UP
        while time.monotonic() < warm_up_end:
            executor.spin_once(timeout_sec=0.05)
        start_wall, start_sim = time.monotonic(), node.world.time
        end = start_wall + seconds
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        wall = time.monotonic() - start_wall
        sim = node.world.time - start_sim
        return {'rtf': sim / wall, 'steps_per_second': sim / node.world.dt / wall,
                'publish_hz': sum(t >= start_wall for t in ticks) / wall}
    finally:
        executor.shutdown()
        node.destroy_node()


def rtf_rows(sizes: list[int], seconds: float, accuracy: str = 'balanced') -> list[str]:
    """Return Markdown rows: sustained real-time factor per size and dt."""
    rows = ['| N | dt (s) | one step alone (ms) | asked | real-time factor | steps/s | '
            'state + poses published (Hz) |',
            '|---:|---|---:|---|---:|---:|---:|']
    with tempfile.TemporaryDirectory() as directory:
        for n in sizes:
            for label, dt in (('1/60', 1 / 60), ('1/240', 1 / 240)):
                path = Path(directory) / f'gas_{n}_{label.replace("/", "_")}.yaml'
                path.write_text(gas_scene_text(n, dt, accuracy))
                world = World(parse_scene_text(path.read_text(), str(path)))
                world.step(2)
                step = best_ms(lambda: world.step(1), 5)
                for factor in (1.0, 1000.0):
                    r = sustained_rtf(path, factor, seconds)
                    asked = 'real time' if factor == 1.0 else 'max'
                    rows.append(f'| {n:,} | {label} | {step:.1f} | {asked} | {r["rtf"]:.2f} | '
                                f'{r["steps_per_second"]:.0f} | {r["publish_hz"]:.1f} |')
    return rows


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options (``python -m collision_node.bench node``)."""
    parser.add_argument('--sizes', type=int, nargs='+', default=[1000, 10000])
    parser.add_argument('--seconds', type=float, default=5.0,
                        help='wall seconds per real-time-factor run (default 5)')
    parser.add_argument('--repeat', type=int, default=20,
                        help='timed repetitions per output (default 20)')
    parser.add_argument('--skip-rtf', action='store_true', help='only time the outputs')
    parser.add_argument('--accuracy', default='balanced',
                        help='accuracy preset of the simulated gas (default balanced)')
    parser.add_argument('--sink', action='store_true', help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    """Run both parts and print Markdown; 2 on bad options."""
    if args.sink:
        return run_sink()
    if any(n < 1 for n in args.sizes) or args.seconds <= 0 or args.repeat < 1:
        print('bench node: sizes, seconds and repeat must be positive', file=sys.stderr)
        return 2
    sink = subprocess.Popen([sys.executable, '-m', 'collision_node.bench.node_ticks', '--sink'])
    rclpy.init()
    try:
        load = os.getloadavg()
        print(f'load average before: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} '
              f'({os.cpu_count()} CPUs)\n')
        print('\n'.join(output_costs(args.sizes, args.repeat)) + '\n')
        if not args.skip_rtf:
            print(f'accuracy preset: {args.accuracy}\n')
            print('\n'.join(rtf_rows(args.sizes, args.seconds, args.accuracy)) + '\n')
        load = os.getloadavg()
        print(f'load average after: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}')
    finally:
        rclpy.try_shutdown()
        sink.send_signal(signal.SIGINT)
        sink.wait(timeout=20)
    return 0


def main(argv: Optional[list[str]] = None) -> int:
    """Parse options and run (``python -m collision_node.bench.node_ticks``)."""
    parser = argparse.ArgumentParser(prog='python -m collision_node.bench.node_ticks',
                                     description=__doc__.split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    raise SystemExit(main())
