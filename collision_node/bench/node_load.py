"""Load benchmark of the node: spawn floods, garbage input, real-time factor, latency.

    python -m collision_node.bench node-load [--spawns 10000] [--garbage 10000]
        [--without TEXT] [--floor]
        [--particles 10000] [--latency-samples 50] [--rtf-particles 1000]
        [--rtf-seconds 5] [--stall-particles 20000] [--burst 500]
        [--step-particles 100000] [--pause-samples 20] [--timeout 60]

The node runs as its own process (``python -m collision_node.ros.node``, so
this checkout's code) on a ROS domain of its own; this process is one
client. Six parts, printed as one Markdown table:

(a) ``--spawns`` valid single-particle spawns (non-overlapping, on a lattice
    in a walled box), published back to back by one publisher with the
    node's command QoS: how many are accepted, rejected or never answered
    (answers matched by ``request_id`` when the node echoes it), and the
    rate of ``particles/poses`` meanwhile against ``publish_rate``.
(b) ``--garbage`` malformed requests cycling through every kind below
    (YAML alias bombs, nesting 5000 deep, 1 MiB strings, random text,
    invalid UTF-8 sent as raw CDR, absurd numbers, wrong types): answers,
    rejections per second, the node's CPU time meanwhile, its resident
    memory (VmRSS before, after and 2 s later, VmHWM peak) and whether it
    survived.
(c) real-time factor measured from ``/clock`` against wall time at
    ``publish_rate`` 30 and 1000 on a gas of ``--rtf-particles``, before and
    after a stall (a spawn of ``--stall-particles`` that is rejected at its
    last entry, so the node parses and validates it all and the world stays
    the same); "first 1 s after" shows a catch-up burst if the node chases
    the time the stall cost.
(d) spawn-to-answer latency (one request at a time) with a running world
    of ``--particles`` gas particles: median, 90th percentile, maximum.
(e) ``--burst`` concurrent ``/pause`` calls from one client, once with a
    KEEP_ALL client (the node's service QoS) and once with the services
    default (keep last 10): answered / sent, latency from the burst's start.
(f) ``/pause`` round trip while a 2-D gas of ``--step-particles`` (the
    issue's: radius 0.8 mm on the default table) takes a 10,000-step
    request: median / p90 / max of ``--pause-samples`` calls, the seconds
    per step, where the time limit ends the request, and a reset's reply
    (after RESET_REPLY_WAIT; the reset follows the step in flight).

Every number is what was measured; a node that dies, hangs or drops
answers is reported as such, never retried into a good figure.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, qos_profile_services_default,
                       ReliabilityPolicy)
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Empty, String
from std_srvs.srv import SetBool, Trigger

from msg_adapters import seconds_from_stamp
from msg_adapters.cdr import CdrWriter
from msg_adapters.strings import string_bytes

from ..ros.qos import COMMAND_QOS, fastdds_profiles, SERVICE_QOS, STATE_QOS, STATUS_QOS
from .node_ticks import spin_until_stopped

NODE_NAME = 'collision_node'
SPAWN_RADIUS = 0.005          # m, the flood's and the latency probes' particles
LATTICE = 0.02                # m between flood spawns (4 radii: none overlap)
GAS_RADIUS = 0.01             # m
GAS_FRACTION = 0.05           # volume fraction of the latency world's gas
GAS_SPEED = 0.1               # m/s
DT = 1.0 / 60.0               # s, every bench scene but part (f)'s
STEP_REQUEST = 10_000         # (f) steps asked for while the pause calls are timed
QUIET_SECONDS = 5.0           # (e) no answer for this long: the rest are lost
SETTLE_SECONDS = 2.0          # s after the garbage flood's last answer, memory read again
# Answers are taken with KEEP_ALL: the bench must not lose what the node sent.
ANSWER_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)


# -- scenes -----------------------------------------------------------------

def lattice_positions(count: int) -> np.ndarray:
    """Return ``count`` lattice points LATTICE apart, starting one LATTICE from the origin."""
    side = int(np.ceil(count ** (1.0 / 3.0)))
    k = np.arange(count)
    return LATTICE * (1 + np.stack([k % side, (k // side) % side, k // side ** 2], axis=1))


def box_scene_text(count: int) -> str:
    """Return an empty walled box that holds ``count`` lattice spawns (and a gas later)."""
    side = LATTICE * (int(np.ceil(count ** (1.0 / 3.0))) + 1)
    side = max(side, 0.5)
    return (f'name: load_box\ndimensions: 3\ndt: {DT!r}\n'
            f'effects:\n  walls: {{min: [0, 0, 0], max: [{side!r}, {side!r}, {side!r}]}}\n')


def box_side(text: str) -> float:
    """Return the side of a box written by ``box_scene_text`` or ``gas_scene_text``."""
    return float(text.split('max: [')[1].split(',')[0])


def gas_scene_text(count: int) -> str:
    """Return a 3-D gas of ``count`` particles in the lower 80 % of a walled cube."""
    volume = count * (4.0 / 3.0) * np.pi * GAS_RADIUS ** 3 / GAS_FRACTION
    side = round(max(0.5, (volume / 0.8) ** (1.0 / 3.0)), 3)
    return (f'name: load_gas_{count}\ndimensions: 3\ndt: {DT!r}\n'
            f'effects:\n  walls: {{min: [0, 0, 0], max: [{side!r}, {side!r}, {side!r}]}}\n'
            f'generate:\n  - {{kind: gas, count: {count}, radius: {GAS_RADIUS}, mass: 1.0, '
            f'speed: {GAS_SPEED}, seed: 3, region: {{min: [0, 0, 0], '
            f'max: [{side!r}, {side!r}, {0.8 * side!r}]}}}}\n')


def table_gas_text(count: int) -> str:
    """Return the issue's slow world: ``count`` particles of radius 0.8 mm on the default table."""
    return ('name: table_gas\ndimensions: 2\ndt: 0.004166666666666667\n'
            'effects:\n  walls: {min: [-1.27, -0.635], max: [1.27, 0.635]}\n'
            f'generate:\n  - {{kind: gas, count: {count}, radius: 0.0008, mass: 1.0, '
            'speed: 1.0, seed: 5, region: {min: [-1.2, -0.6], max: [1.2, 0.6]}}\n')


def spawn_text(position: np.ndarray, request_id: Optional[str]) -> str:
    """Return one single-particle spawn request (JSON), with ``request_id`` if given."""
    request: dict[str, Any] = {} if request_id is None else {'request_id': request_id}
    request.update(position=[round(float(c), 9) for c in position], radius=SPAWN_RADIUS,
                   mass=0.001)
    return json.dumps(request)


# -- garbage ----------------------------------------------------------------

def alias_bomb(field: str) -> str:
    """Return a 'billion laughs' YAML whose ``field`` expands to 9**9 strings."""
    lines = ['l0: &l0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]']
    for level in range(1, 9):
        refs = ', '.join([f'*l{level - 1}'] * 9)
        lines.append(f'l{level}: &l{level} [{refs}]')
    # The anchors must be defined before use, so they sit under a key the
    # request does not know; the bomb is then referenced where a value goes.
    return '{' + ', '.join(lines) + f', {field}: *l8, radius: 0.01, mass: 1}}'


def invalid_utf8_cdr(rng: random.Random) -> bytes:
    """Return a serialised std_msgs/String whose data is not valid UTF-8."""
    payload = bytes([0xff, 0xfe, 0xc0, 0x80]) + bytes(rng.randrange(256) for _ in range(60))
    writer = CdrWriter()
    writer.uint32(len(payload) + 1)
    writer.raw(payload + b'\x00')
    return writer.bytes()


ABSURD = [
    '{position: [0, 0, 0], radius: 1e308, mass: 1}',
    '{position: [1e999, 0, 0], radius: 0.01, mass: 1}',
    '{position: [0, 0, 0], radius: 0.01, mass: 1e-400}',
    '{position: [0, 0, 0], radius: ' + '9' * 5000 + ', mass: 1}',
    '{position: [0, 0, 0], radius: -0.0, mass: .nan}',
    '{kind: gas, count: 1000000000000, radius: 0.01, mass: 1, '
    'region: {min: [0, 0, 0], max: [1, 1, 1]}}',
    '{kind: gas, count: 100000000, radius: 1e-9, mass: 1, '
    'region: {min: [0, 0, 0], max: [1, 1, 1]}}',
    '{position: [0, 0, 0], velocity: [1e300, 1e300, 1e300], radius: 0.01, mass: 1}',
]
WRONG_TYPES = ['[' + ', '.join(['null'] * 1000) + ']', 'true', '', '{}', '- - -',
               '{position: yes, radius: [], mass: {}}', '"\\ud800"', '!!python/object:os.system',
               '{particles: 5, generate: "x"}', '%YAML 9.9\n---\n1']


def garbage_kinds() -> list[tuple[str, Callable[[int, random.Random], Any]]]:
    """Return (kind, maker) pairs; a maker returns a str (a String's data) or raw CDR bytes."""
    mib = 1 << 20
    return [
        ('YAML alias bomb (position)', lambda k, rng: alias_bomb('position')),
        ('YAML alias bomb (request_id)', lambda k, rng: alias_bomb('request_id')),
        ('nesting 5000 deep, list', lambda k, rng: '[' * 5000),
        ('nesting 5000 deep, mapping', lambda k, rng: '{"a": ' * 5000 + '1' + '}' * 5000),
        ('1 MiB string', lambda k, rng: '"' + 'x' * mib + '"'),
        ('1 MiB field in a particle', lambda k, rng: '{position: [0, 0, 0], radius: 0.01, '
                                                     'mass: 1, colour: ' + 'y' * mib + '}'),
        ('random text (1 KiB)',
         lambda k, rng: bytes(rng.randrange(1, 256) for _ in range(1024)).decode('latin-1')),
        ('invalid UTF-8 (raw CDR)', lambda k, rng: invalid_utf8_cdr(rng)),
        ('absurd numbers', lambda k, rng: ABSURD[k % len(ABSURD)]),
        ('wrong types', lambda k, rng: WRONG_TYPES[k % len(WRONG_TYPES)]),
    ]


# -- the node process and the client ----------------------------------------

class NodeProcess:
    """The node in a process of its own on ``domain_id``."""

    def __init__(self, scene: Path, domain_id: int, parameters: dict[str, str],
                 command: tuple[str, ...] = ('-m', 'collision_node.ros.node')) -> None:
        """Start ``python -m collision_node.ros.node`` (or ``command``) on the scene."""
        self.log = tempfile.TemporaryFile('w+')
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
        args = ['--ros-args', '-p', f'scene:={scene}']
        for name, value in parameters.items():
            args += ['-p', f'{name}:={value}']
        self.process = subprocess.Popen([sys.executable, *command, *args],
                                        env=env, stdout=self.log, stderr=subprocess.STDOUT)

    def alive(self) -> bool:
        """Tell whether the process still runs."""
        return self.process.poll() is None

    def memory_kib(self, field: str = 'VmRSS') -> Optional[int]:
        """Return a /proc/PID/status memory field in KiB (None once the process is gone)."""
        try:
            with open(f'/proc/{self.process.pid}/status', encoding='ascii') as status:
                for line in status:
                    if line.startswith(field + ':'):
                        return int(line.split()[1])
        except OSError:
            return None
        return None

    def cpu_seconds(self) -> Optional[float]:
        """Return the CPU time the process used so far, every thread (None once it is gone)."""
        try:
            with open(f'/proc/{self.process.pid}/stat', encoding='ascii') as stat:
                fields = stat.read().rsplit(')', 1)[1].split()
        except OSError:
            return None
        # utime and stime are fields 14 and 15 of stat(5); the split starts at field 3.
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

    def tail(self, lines: int = 3) -> str:
        """Return the last lines the node wrote."""
        self.log.seek(0)
        return ' | '.join(self.log.read().strip().splitlines()[-lines:])

    def stop(self) -> Optional[int]:
        """Stop the node with SIGINT (then SIGKILL); return its exit code."""
        if self.alive():
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()
        return self.process.returncode


class Client:
    """One client node: publishes requests, collects answers, status, /clock and poses."""

    def __init__(self, domain_id: int) -> None:
        """Create the context, node, publishers and subscriptions."""
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(f'load_bench_{os.getpid()}', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.events: list[tuple[float, dict]] = []
        self.statuses: list[dict] = []
        self.clock: list[tuple[float, float]] = []
        self.poses: list[float] = []
        self.node.create_subscription(String, 'events', self._on_event, ANSWER_QOS)
        self.node.create_subscription(String, 'status', self._on_status, STATUS_QOS)
        self.node.create_subscription(Clock, '/clock', self._on_clock, STATE_QOS)
        self.spawn = self.node.create_publisher(String, 'spawn', COMMAND_QOS)
        self.reset = self.node.create_publisher(Empty, 'reset', COMMAND_QOS)
        self.parameters = self.node.create_client(SetParameters,
                                                  f'/{NODE_NAME}/set_parameters')
        self._poses_subscription = None

    def _on_event(self, msg: String) -> None:
        try:
            event = json.loads(msg.data)
        except ValueError:
            event = {'unparsed': msg.data[:80]}
        self.events.append((time.monotonic(), event))

    def _on_status(self, msg: String) -> None:
        self.statuses.append(json.loads(msg.data))

    def _on_clock(self, msg: Clock) -> None:
        self.clock.append((time.monotonic(), seconds_from_stamp(msg.clock)))

    def _on_poses(self, _: bytes) -> None:
        self.poses.append(time.monotonic())

    def count_poses(self, enabled: bool) -> None:
        """Subscribe to particles/poses (raw, not decoded) or drop the subscription."""
        if enabled and self._poses_subscription is None:
            self._poses_subscription = self.node.create_subscription(
                PoseArray, 'particles/poses', self._on_poses, STATE_QOS, raw=True)
        elif not enabled and self._poses_subscription is not None:
            self.node.destroy_subscription(self._poses_subscription)
            self._poses_subscription = None

    def spin(self, seconds: float) -> None:
        """Take callbacks for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))

    def wait(self, condition: Callable[[], Any], timeout: float,
             node: Optional[NodeProcess] = None) -> bool:
        """Spin until ``condition()`` holds; False on timeout or when ``node`` died."""
        end = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > end or (node is not None and not node.alive()):
                return bool(condition())
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def set_parameter(self, name: str, value: float, timeout: float) -> bool:
        """Set a double parameter of the node; return whether it was accepted."""
        if not self.parameters.wait_for_service(timeout_sec=timeout):
            return False
        request = SetParameters.Request(parameters=[Parameter(name=name, value=ParameterValue(
            type=ParameterType.PARAMETER_DOUBLE, double_value=float(value)))])
        future = self.parameters.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        return bool(future.done() and future.result().results[0].successful)

    def close(self) -> None:
        """Destroy the node and shut the context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


def start_node(scene_text: str, workdir: Path, name: str, domain_id: int,
               timeout: float, floor: bool = False,
               parameters: Optional[dict[str, str]] = None) -> tuple[NodeProcess, Client]:
    """Write the scene, start the node and a client; wait for its status and subscriptions.

    ``floor`` starts :func:`responder` in the node's place.
    """
    path = workdir / f'{name}.yaml'
    path.write_text(scene_text)
    node = NodeProcess(path, domain_id, parameters or {},
                       ('-m', 'collision_node.bench.node_load', RESPONDER) if floor else
                       ('-m', 'collision_node.ros.node'))
    client = Client(domain_id)
    ready = client.wait(lambda: client.statuses and client.spawn.get_subscription_count() > 0
                        and client.reset.get_subscription_count() > 0, timeout, node)
    if not ready:
        tail = node.tail()
        client.close()
        node.stop()
        raise RuntimeError(f'node on {name} did not come up within {timeout:g} s: {tail}')
    return node, client


def answers_since(client: Client, start: int) -> list[tuple[float, dict]]:
    """Return the answers received from index ``start`` on."""
    return client.events[start:]


def wait_answers(client: Client, node: NodeProcess, start: int, expected: int,
                 quiet: float) -> None:
    """Spin until ``expected`` answers came, the node died or none came for ``quiet`` s."""
    while len(client.events) - start < expected and node.alive():
        before = len(client.events)
        client.wait(lambda: len(client.events) > before, quiet, node)
        if len(client.events) == before:
            return


# -- the parts ----------------------------------------------------------------

Row = tuple[str, str, str]


def probe_request_id(client: Client, node: NodeProcess, position: np.ndarray,
                     timeout: float) -> bool:
    """Spawn one particle with a request_id; tell whether the node echoes it."""
    start = len(client.events)
    client.spawn.publish(String(data=spawn_text(position, 'probe')))
    client.wait(lambda: len(client.events) > start, timeout, node)
    answers = answers_since(client, start)
    return bool(answers and answers[0][1].get('request_id') == 'probe'
                and answers[0][1].get('accepted'))


def spawn_flood(client: Client, node: NodeProcess, count: int, timeout: float) -> list[Row]:
    """Part (a): ``count`` valid spawns back to back; answers and the poses rate meanwhile."""
    positions = lattice_positions(count + 1)
    with_ids = probe_request_id(client, node, positions[0], timeout)
    publish_rate = client.statuses[-1].get('publish_rate', float('nan'))
    client.count_poses(True)
    client.wait(lambda: client.poses, timeout, node)
    start, poses_start = len(client.events), len(client.poses)
    texts = [spawn_text(p, f'f{k}' if with_ids else None)
             for k, p in enumerate(positions[1:])]
    t0 = time.monotonic()
    for text in texts:
        client.spawn.publish(String(data=text))
    t_published = time.monotonic()
    wait_answers(client, node, start, count, timeout)
    t_end = time.monotonic()
    window_poses = [t for t in client.poses[poses_start:] if t0 <= t <= t_end]
    client.count_poses(False)
    answers = [event for _, event in answers_since(client, start)
               if event.get('request') == 'spawn']
    if with_ids:
        wanted = {f'f{k}' for k in range(count)}
        answers = [a for a in answers if a.get('request_id') in wanted]
    accepted = sum(1 for a in answers if a.get('accepted'))
    reasons = sorted({a.get('reason', '')[:70] for a in answers if not a.get('accepted')})
    rows = [
        ('a', 'spawns published (one publisher, back to back)',
         f'{count} in {t_published - t0:.2f} s'),
        ('a', 'answers matched by', 'request_id' if with_ids else
         'count (the node does not echo request_id)'),
        ('a', 'accepted / rejected / unanswered',
         f'{accepted} / {len(answers) - accepted} / {count - len(answers)}'),
        ('a', 'time to the last answer', f'{(t_end - t0):.2f} s'),
        ('a', 'particles/poses rate meanwhile vs publish_rate',
         f'{len(window_poses) / max(t_end - t0, 1e-9):.1f} Hz vs {publish_rate:g} Hz'),
    ]
    if reasons:
        rows.append(('a', 'rejection reasons (first 70 chars)', '; '.join(reasons[:3])))
    if not node.alive():
        rows.append(('a', 'node', f'DIED (exit {node.process.returncode}): {node.tail()}'))
    return rows


def garbage_flood(client: Client, node: NodeProcess, count: int, timeout: float,
                  seed: int = 5, without: tuple[str, ...] = ()) -> list[Row]:
    """Part (b): ``count`` malformed requests of every kind; answers, rate and memory.

    ``without`` leaves out the kinds whose name contains one of its texts.
    """
    rng = random.Random(seed)
    kinds = [(name, make) for name, make in garbage_kinds()
             if not any(text in name for text in without)]
    raw = client.node.create_publisher(String, 'spawn', COMMAND_QOS)
    client.wait(lambda: raw.get_subscription_count() > 0, timeout, node)
    rss_before, cpu_before = node.memory_kib(), node.cpu_seconds()
    start = len(client.events)
    sent = {name: 0 for name, _ in kinds}
    t0 = time.monotonic()
    died_at = None
    for k in range(count):
        name, make = kinds[k % len(kinds)]
        message = make(k // len(kinds), rng)
        if isinstance(message, bytes):
            raw.publish(message)
        else:
            client.spawn.publish(String(data=message))
        sent[name] += 1
        if k % 50 == 49:
            # Take answers as they come so the client's own queue stays small.
            client.executor.spin_once(timeout_sec=0)
            if not node.alive():
                died_at = name
                break
    t_published = time.monotonic()
    total = sum(sent.values())
    wait_answers(client, node, start, total, timeout)
    answers = answers_since(client, start)
    t_last = answers[-1][0] if answers else time.monotonic()
    rejected = sum(1 for _, e in answers if not e.get('accepted', False))
    rss_after, hwm, cpu_after = node.memory_kib(), node.memory_kib('VmHWM'), node.cpu_seconds()
    client.node.destroy_publisher(raw)
    # The node's memory a while later: what it keeps, not what it is still freeing.
    client.spin(SETTLE_SECONDS)
    rss_settled = node.memory_kib()

    def mib(kib: Optional[int]) -> str:
        return '-' if kib is None else f'{kib / 1024:.0f} MiB'
    rows = [
        ('b', 'garbage published', f'{total} ({len(kinds)} kinds, '
                                   f'{total // len(kinds)}+ each) in {t_published - t0:.2f} s'),
        ('b', 'answers (rejections) / published', f'{len(answers)} ({rejected}) / {total}'),
        ('b', 'rejections per second', f'{rejected / max(t_last - t0, 1e-9):.0f}'),
        ('b', f'node VmRSS before / after / {SETTLE_SECONDS:g} s later, VmHWM',
         f'{mib(rss_before)} / {mib(rss_after)} / {mib(rss_settled)}, {mib(hwm)}'),
        ('b', 'node CPU time (all threads) from the first request to the last answer',
         '-' if cpu_before is None or cpu_after is None else
         f'{cpu_after - cpu_before:.2f} s ({1e3 * (cpu_after - cpu_before) / total:.2f} ms '
         'per request)'),
        ('b', 'node', 'alive' if node.alive() else
         f'DIED (exit {node.process.returncode}) during "{died_at or "the answers"}": '
         f'{node.tail()}'),
    ]
    accepted = [e for _, e in answers if e.get('accepted')]
    if accepted:
        rows.append(('b', 'garbage ACCEPTED', f'{len(accepted)}: '
                                              f'{json.dumps(accepted[0])[:80]}'))
    return rows


def measure_rtf(client: Client, seconds: float) -> tuple[float, float]:
    """Return (real-time factor over ``seconds``, over its first second) from /clock."""
    start = len(client.clock)
    client.spin(seconds)
    samples = client.clock[start:]
    if len(samples) < 2:
        return float('nan'), float('nan')
    wall = np.array([w for w, _ in samples])
    sim = np.array([s for _, s in samples])
    whole = (sim[-1] - sim[0]) / (wall[-1] - wall[0])
    first = wall <= wall[0] + 1.0
    early = ((sim[first][-1] - sim[0]) / (wall[first][-1] - wall[0])
             if first.sum() > 1 else float('nan'))
    return float(whole), float(early)


def stall_request(count: int) -> str:
    """Return a spawn of ``count`` particles whose last one is invalid (rejected whole)."""
    rows = [f'{{"position": [{0.01 * (k % 50) + 0.01}, {0.01 * (k // 50 % 50) + 0.01}, '
            f'{0.01 * (k // 2500) + 0.01}], "radius": 0.001, "mass": 1}}' for k in range(count)]
    rows[-1] = '{"position": [0, 0, 0], "radius": -1, "mass": 1}'
    return '{"particles": [' + ', '.join(rows) + ']}'


def rtf_around_stall(client: Client, node: NodeProcess, particles: int, seconds: float,
                     stall_particles: int, side: float, timeout: float) -> list[Row]:
    """Part (c): RTF at publish_rate 30 and 1000, before and after a stall."""
    start = len(client.events)
    client.reset.publish(Empty())
    client.wait(lambda: len(client.events) > start, timeout, node)
    start = len(client.events)
    client.spawn.publish(String(data=json.dumps({
        'kind': 'gas', 'count': particles, 'radius': SPAWN_RADIUS, 'mass': 0.001,
        'speed': 0.2, 'seed': 1, 'region': {'min': [0, 0, 0], 'max': [side] * 3}})))
    client.wait(lambda: len(client.events) > start, timeout, node)
    gas = answers_since(client, start)
    rows: list[Row] = [('c', 'world', f'{particles}-particle gas, dt = {DT:.4g} s, factor 1: '
                        + ('spawned' if gas and gas[0][1].get('accepted') else
                           f'spawn refused: {gas[0][1].get("reason", "")[:60]}' if gas
                           else 'spawn unanswered'))]
    stall = stall_request(stall_particles)
    for rate in (30.0, 1000.0):
        if not node.alive():
            break
        if not client.set_parameter('publish_rate', rate, timeout):
            rows.append(('c', f'publish_rate {rate:g}', 'refused or unanswered'))
            continue
        client.spin(1.0)
        before, _ = measure_rtf(client, seconds)
        start = len(client.events)
        t0 = time.monotonic()
        client.spawn.publish(String(data=stall))
        client.wait(lambda: len(client.events) > start, timeout, node)
        stall_s = time.monotonic() - t0
        after, first = measure_rtf(client, seconds)
        rows.append(('c', f'RTF at publish_rate {rate:g}: before / after stall '
                          f'(first 1 s after)', f'{before:.3f} / {after:.3f} ({first:.3f})'))
        rows.append(('c', f'stall at publish_rate {rate:g} (spawn of {stall_particles}, '
                          'rejected)', f'{stall_s:.2f} s to its answer'))
    client.set_parameter('publish_rate', 30.0, timeout)
    return rows


def spawn_latency(client: Client, node: NodeProcess, samples: int, particles: int,
                  side: float, timeout: float) -> list[Row]:
    """Part (d): spawn-to-answer latency, one request at a time, in a running gas."""
    rng = np.random.default_rng(11)
    with_ids = probe_request_id(client, node, np.array([0.5, 0.5, 0.9]) * side, timeout)
    rtf, _ = measure_rtf(client, 2.0)
    latencies, accepted, lost = [], 0, 0
    for k in range(samples):
        position = np.array([rng.uniform(0.1, 0.9) * side, rng.uniform(0.1, 0.9) * side,
                             rng.uniform(0.86, 0.97) * side])
        request_id = f'l{k}' if with_ids else None
        start = len(client.events)
        t0 = time.monotonic()
        client.spawn.publish(String(data=spawn_text(position, request_id)))

        def answered() -> Optional[tuple[float, dict]]:
            for t, event in client.events[start:]:
                if event.get('request') == 'spawn' and (
                        request_id is None or event.get('request_id') == request_id):
                    return t, event
            return None
        if not client.wait(answered, timeout, node):
            lost += 1
            if not node.alive():
                break
            continue
        t, event = answered()
        latencies.append(t - t0)
        accepted += bool(event.get('accepted'))
    ms = 1e3 * np.array(latencies) if latencies else np.array([np.nan])
    rows = [
        ('d', 'world', f'{particles}-particle gas, dt = {DT:.4g} s, measured RTF {rtf:.3f}'),
        ('d', 'spawn-to-answer latency median / p90 / max',
         f'{np.median(ms):.1f} / {np.percentile(ms, 90):.1f} / {ms.max():.1f} ms'),
        ('d', 'requests answered (accepted) / sent / unanswered',
         f'{len(latencies)} ({accepted}) / {samples} / {lost}'),
    ]
    if not node.alive():
        rows.append(('d', 'node', f'DIED (exit {node.process.returncode}): {node.tail()}'))
    return rows


def milliseconds(seconds: list[float]) -> str:
    """Return 'median / p90 / max ms' of some durations ('-' for none)."""
    if not seconds:
        return '-'
    ms = 1e3 * np.array(seconds)
    return f'{np.median(ms):.1f} / {np.percentile(ms, 90):.1f} / {ms.max():.1f} ms'


def pause_burst(client: Client, node: NodeProcess, count: int, timeout: float) -> list[Row]:
    """Part (e): ``count`` concurrent /pause calls from one client; answered and latency."""
    rows: list[Row] = []
    for label, qos in (('KEEP_ALL client', SERVICE_QOS),
                       ('services-default client (keep last 10)', qos_profile_services_default)):
        pause = client.node.create_client(SetBool, 'pause', qos_profile=qos)
        if not pause.wait_for_service(timeout_sec=timeout):
            rows.append(('e', label, 'no /pause service'))
            continue
        t0 = time.monotonic()
        futures = [pause.call_async(SetBool.Request(data=True)) for _ in range(count)]
        answered: dict[int, float] = {}
        quiet_since = time.monotonic()
        while len(answered) < count and node.alive() and \
                time.monotonic() - quiet_since < QUIET_SECONDS:
            client.executor.spin_once(timeout_sec=0.02)
            now = time.monotonic()
            for k, future in enumerate(futures):
                if k not in answered and future.done():
                    answered[k] = now
                    quiet_since = now
        for future in futures:
            if not future.done():
                pause.remove_pending_request(future)
        client.node.destroy_client(pause)
        latency = [t - t0 for t in answered.values()]
        rows.append(('e', f'{count} concurrent /pause calls, {label}: answered / sent',
                     f'{len(answered)} / {count}'))
        rows.append(('e', f'{label}: latency from the burst, median / p90 / max',
                     milliseconds(latency)))
    if not node.alive():
        rows.append(('e', 'node', f'DIED (exit {node.process.returncode}): {node.tail()}'))
    return rows


def pause_while_stepping(workdir: Path, domain_id: int, particles: int, samples: int,
                         timeout: float) -> list[Row]:
    """Part (f): /pause round trips while a ``particles`` gas takes a long step request."""
    node, client = start_node(table_gas_text(particles), workdir, 'table_gas', domain_id,
                              timeout, parameters={'paused': 'true',
                                                   'max_particles': str(particles)})
    rows: list[Row] = []
    try:
        step = client.node.create_publisher(String, 'step', COMMAND_QOS)
        pause = client.node.create_client(SetBool, 'pause', qos_profile=SERVICE_QOS)
        reset = client.node.create_client(Trigger, 'reset', qos_profile=SERVICE_QOS)
        client.wait(lambda: step.get_subscription_count() > 0, timeout, node)

        def call(service: Any, request: Any) -> Optional[float]:
            if not service.wait_for_service(timeout_sec=timeout):
                return None
            t0 = time.monotonic()
            future = service.call_async(request)
            client.executor.spin_until_future_complete(future, timeout_sec=timeout)
            return time.monotonic() - t0 if future.done() else None

        def stepped(after: int) -> bool:
            return client.wait(lambda: client.statuses[-1].get('steps', 0) > after, timeout,
                               node)

        start = len(client.events)
        t0 = time.monotonic()
        step.publish(String(data=json.dumps({'steps': STEP_REQUEST, 'request_id': 'long'})))
        stepped(0)
        trips = [call(pause, SetBool.Request(data=True)) for _ in range(samples)]
        lost = sum(t is None for t in trips)
        rows.append(('f', 'world', f'{particles}-particle 2-D gas (radius 0.8 mm), '
                     f'{STEP_REQUEST}-step request under way'))
        rows.append(('f', f'/pause round trip while it steps, median / p90 / max '
                          f'({samples} calls{f", {lost} unanswered" if lost else ""})',
                     milliseconds([t for t in trips if t is not None])))

        def step_answer() -> Optional[dict]:
            for _, event in client.events[start:]:
                if event.get('request') == 'step' and event.get('request_id') == 'long':
                    return event
            return None
        client.wait(step_answer, timeout + 60.0, node)
        ended = step_answer()
        if ended:
            took = time.monotonic() - t0
            rows.append(('f', 'the step request ended', f'after {took:.1f} s, {ended["steps"]} '
                              f'steps ({took / max(ended["steps"], 1):.2f} s per step), '
                              f'{ended.get("stopped", "complete")}'))
        else:
            rows.append(('f', 'the step request ended', 'no answer'))
        steps_before = client.statuses[-1].get('steps', 0)
        step.publish(String(data=json.dumps({'steps': STEP_REQUEST, 'request_id': 'again'})))
        stepped(steps_before)
        waited = call(reset, Trigger.Request())
        rows.append(('f', '/reset reply while it steps (the reset follows the step)',
                     '-' if waited is None else f'{1e3 * waited:.0f} ms'))
    finally:
        client.close()
        code = node.stop()
    rows.append(('-', 'table gas node exit code', str(code)))
    return rows


# -- the floor: a stand-in that only takes and answers ------------------------

RESPONDER = '--responder'


def responder() -> int:
    """Stand in for the node: take every spawn raw and answer it with a fixed refusal.

    It takes requests as the node does (raw, draining the queue in one
    callback, the node's Fast DDS profile) and publishes a pre-serialised
    answer, but reads nothing: the
    rate it reaches under ``--floor`` is what the client and the middleware
    allow, the ceiling of the node's own rate on the same machine.
    """
    rclpy.init()
    with fastdds_profiles():             # the node's middleware settings
        node = rclpy.create_node(NODE_NAME)
    events = node.create_publisher(String, 'events', COMMAND_QOS)
    status = node.create_publisher(String, 'status', STATUS_QOS)
    seq = [0]

    def answer(request: str) -> None:
        seq[0] += 1
        events.publish(string_bytes(f'{{"seq": {seq[0]}, "request": "{request}", '
                                    '"request_id": null, "accepted": false, '
                                    '"reason": "floor", "particles": 0}'))

    def on_spawn(_: bytes) -> None:
        answer('spawn')
        with spawn.handle:
            while spawn.handle.take_message(String, True) is not None:
                answer('spawn')

    spawn = node.create_subscription(String, 'spawn', on_spawn, COMMAND_QOS, raw=True)
    node.create_subscription(Empty, 'reset', lambda _: answer('reset'), COMMAND_QOS)
    node.create_timer(0.5, lambda: status.publish(String(data='{}')))
    return spin_until_stopped(node)


# -- command ----------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options."""
    parser.add_argument('--spawns', type=int, default=10_000, metavar='N',
                        help='(a) valid single-particle spawns (default 10000)')
    parser.add_argument('--garbage', type=int, default=10_000, metavar='N',
                        help='(b) malformed requests (default 10000)')
    parser.add_argument('--without', action='append', default=[], metavar='TEXT',
                        help='(b) leave out the garbage kinds whose name contains TEXT, '
                             'e.g. "1 MiB" (repeatable)')
    parser.add_argument('--floor', action='store_true',
                        help='(b only) flood a stand-in that answers without reading, to '
                             'measure what the client and the middleware allow')
    parser.add_argument('--rtf-particles', type=int, default=1_000, metavar='N',
                        help='(c) gas particles while the real-time factor is measured '
                             '(default 1000)')
    parser.add_argument('--rtf-seconds', type=float, default=5.0, metavar='S',
                        help='(c) seconds per real-time-factor measurement (default 5)')
    parser.add_argument('--stall-particles', type=int, default=20_000, metavar='N',
                        help='(c) size of the rejected spawn that stalls the node '
                             '(default 20000)')
    parser.add_argument('--particles', type=int, default=10_000, metavar='N',
                        help='(d) gas particles of the running world (default 10000)')
    parser.add_argument('--latency-samples', type=int, default=50, metavar='K',
                        help='(d) spawns timed one at a time (default 50)')
    parser.add_argument('--burst', type=int, default=500, metavar='N',
                        help='(e) concurrent /pause calls from one client (default 500)')
    parser.add_argument('--step-particles', type=int, default=100_000, metavar='N',
                        help='(f) particles of the world stepped while /pause is timed '
                             '(default 100000)')
    parser.add_argument('--pause-samples', type=int, default=20, metavar='K',
                        help='(f) /pause calls timed (default 20)')
    parser.add_argument('--timeout', type=float, default=60.0, metavar='S',
                        help='give up waiting for the node after S quiet seconds (default 60)')
    parser.add_argument('--parts', default='abcdef',
                        help='which parts to run, e.g. "ad" (default abcdef)')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS domain of the node and the client (default: from the pid)')


def run(args: argparse.Namespace) -> int:
    """Run the parts asked for and print the table; 0 unless the node would not start."""
    parts = set(args.parts)
    for name in ('spawns', 'garbage', 'rtf_particles', 'stall_particles', 'particles',
                 'latency_samples', 'burst', 'step_particles', 'pause_samples'):
        if getattr(args, name) < 1:
            print(f'node-load: --{name.replace("_", "-")} must be >= 1', file=sys.stderr)
            return 2
    kinds = [name for name, _ in garbage_kinds()
             if not any(text in name for text in args.without)]
    if not kinds:
        print('node-load: --without leaves no garbage kind', file=sys.stderr)
        return 2
    if args.floor and parts != {'b'}:
        print('node-load: --floor runs part b only (--parts b)', file=sys.stderr)
        return 2
    if not parts <= set('abcdef') or not parts:
        print(f'node-load: --parts takes letters of abcdef, got {args.parts!r}',
              file=sys.stderr)
        return 2
    domain_id = args.domain_id if args.domain_id is not None else 1 + os.getpid() % 100
    load = os.getloadavg()
    print(f'node-load: load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} '
          f'({os.cpu_count()} CPUs), ROS domain {domain_id}')
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix='node_load_') as workdir:
        if parts & set('abce'):
            text = box_scene_text(max(args.spawns + 1, args.rtf_particles))
            node, client = start_node(text, Path(workdir), 'box', domain_id, args.timeout,
                                      args.floor)
            try:
                if 'a' in parts:
                    rows += spawn_flood(client, node, args.spawns, args.timeout)
                if 'b' in parts and node.alive():
                    start = len(client.events)
                    client.reset.publish(Empty())
                    client.wait(lambda: len(client.events) > start, args.timeout, node)
                    rows += garbage_flood(client, node, args.garbage, args.timeout,
                                          without=tuple(args.without))
                if 'c' in parts and node.alive():
                    rows += rtf_around_stall(client, node, args.rtf_particles,
                                             args.rtf_seconds, args.stall_particles,
                                             box_side(text), args.timeout)
                if 'e' in parts and node.alive():
                    rows += pause_burst(client, node, args.burst, args.timeout)
            finally:
                client.close()
                code = node.stop()
            rows.append(('-', 'box node exit code', str(code)))
        if 'd' in parts:
            text = gas_scene_text(args.particles)
            node, client = start_node(text, Path(workdir), 'gas', domain_id, args.timeout)
            try:
                rows += spawn_latency(client, node, args.latency_samples, args.particles,
                                      box_side(text), args.timeout)
            finally:
                client.close()
                code = node.stop()
            rows.append(('-', 'gas node exit code', str(code)))
        if 'f' in parts:
            rows += pause_while_stepping(Path(workdir), domain_id, args.step_particles,
                                         args.pause_samples, args.timeout)
    print('| part | measure | value |')
    print('|---|---|---|')
    for part, measure, value in rows:
        print(f'| {part} | {measure} | {value} |')
    return 0


def main(argv: Optional[list[str]] = None) -> int:
    """Run as ``python -m collision_node.bench.node_load``."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == [RESPONDER]:
        return responder()
    parser = argparse.ArgumentParser(prog='python -m collision_node.bench node-load',
                                     description=__doc__.split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    raise SystemExit(main())
