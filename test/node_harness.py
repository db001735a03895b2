"""Start the installed executables as processes and talk to them over real topics.

Every process gets ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and a
``ROS_DOMAIN_ID`` of its own (leased through a lock file, see
:func:`unique_domain_id`), so concurrent test runs and tests do not hear
each other.
Synchronisation is always "spin until a message says so, or time out".
"""

from __future__ import annotations

import fcntl
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Optional

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

_domains = itertools.count()
# Domain id -> the open lock file that holds it, oldest first.
_leases: dict[int, Any] = {}
_KEPT_LEASES = 8
STATUS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


def unique_domain_id() -> int:
    """Return a ROS domain id in 1..101 that no other test process on this machine holds.

    Each id is leased through an exclusive lock on a file in the temporary
    directory, so concurrent test runs (two checkouts, a benchmark's run)
    never share a domain and hear each other; a process keeps its last
    ``_KEPT_LEASES`` leases (tests run one after another) and frees older ones.
    101 is the highest id whose ports stay out of Linux's ephemeral range.
    """
    first = (os.getpid() * 7 + 13 * next(_domains)) % 101
    for step in range(101):
        domain = 1 + (first + step) % 101
        if domain in _leases:
            continue
        path = os.path.join(tempfile.gettempdir(), f'collision_node_test_domain_{domain}.lock')
        handle = open(path, 'a')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _leases[domain] = handle
        while len(_leases) > _KEPT_LEASES:
            oldest = next(iter(_leases))
            _leases.pop(oldest).close()
        return domain
    raise RuntimeError('every ROS domain id 1..101 is held by another test process')


def executable(name: str) -> str:
    """Return the installed console script ``name`` (the venv's bin first)."""
    found = shutil.which(name, path=os.pathsep.join(
        [str(Path(sys.prefix) / 'bin'), os.environ.get('PATH', '')]))
    assert found, f'{name} is not installed in {sys.prefix}/bin or on PATH'
    return found


def ros_env(domain_id: int) -> dict[str, str]:
    """Return the environment of a child process on ``domain_id``, this machine only."""
    env = dict(os.environ)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['AMENT_PREFIX_PATH'] = sys.prefix
    env['PYTHONUNBUFFERED'] = '1'
    return env


def start(name: str, args: list[str], domain_id: int,
          preexec: Optional[Callable[[], None]] = None) -> subprocess.Popen:
    """Start an installed executable on ``domain_id``.

    Its output goes to unnamed temporary files (a pipe nobody reads while
    the test runs could fill up and block the process); ``output`` reads them.
    ``preexec`` runs in the child before the executable (e.g. to set a limit).
    """
    out, err = tempfile.TemporaryFile('w+'), tempfile.TemporaryFile('w+')
    process = subprocess.Popen([executable(name), *args], env=ros_env(domain_id),
                               stdout=out, stderr=err, text=True, preexec_fn=preexec)
    process.output_files = (out, err)
    return process


def output(process: subprocess.Popen) -> tuple[str, str]:
    """Return what the process has written so far to stdout and stderr."""
    texts = []
    for file in process.output_files:
        file.seek(0)
        texts.append(file.read())
    return texts[0], texts[1]


def stop(process: subprocess.Popen, sig: int = signal.SIGINT,
         timeout: float = 15.0) -> tuple[int, str, str]:
    """Send ``sig`` and return (exit code, stdout, stderr)."""
    if process.poll() is None:
        process.send_signal(sig)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
    out, err = output(process)
    for file in process.output_files:
        file.close()
    return process.returncode, out, err


class Probe:
    """A test-side node in its own context on the node's domain."""

    def __init__(self, domain_id: int) -> None:
        """Create the context, node and executor."""
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(f'probe_{os.getpid()}', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def collect(self, msg_type: Any, topic: str, qos: Any = 10) -> list:
        """Subscribe and return the list the received messages are appended to."""
        received: list = []
        self.node.create_subscription(msg_type, topic, received.append, qos)
        return received

    def drain(self, rounds: int = 100) -> None:
        """Take every message already queued for this probe (each subscription keeps up to 10).

        A probe spins only while a test waits, so messages published before
        the test's last answer may still be queued; counting 'the next two'
        would count those first.
        """
        for _ in range(rounds):
            self.executor.spin_once(timeout_sec=0.0)

    def wait_for(self, predicate: Callable[[], Any], timeout: float = 15.0) -> Any:
        """Spin until ``predicate()`` is truthy and return it; fail after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            value = predicate()
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f'timed out after {timeout} s waiting for a condition')
            self.executor.spin_once(timeout_sec=0.05)

    def next_message(self, received: list, timeout: float = 15.0,
                     where: Optional[Callable[[Any], bool]] = None) -> Any:
        """Return the first message received from now on (matching ``where``)."""
        start = len(received)

        def found():
            for msg in received[start:]:
                if where is None or where(msg):
                    return msg
            return None
        return self.wait_for(found, timeout)

    def call(self, client: Any, request: Any, timeout: float = 15.0) -> Any:
        """Call a service and return its response."""
        assert client.wait_for_service(timeout_sec=timeout)
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        assert future.done(), 'service call timed out'
        return future.result()

    def close(self) -> None:
        """Destroy the node and shut the context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)


class NodeUnderTest:
    """The installed ``collision_node`` in a process, with a probe on its domain."""

    def __init__(self, args: list[str], namespace: str = '',
                 preexec: Optional[Callable[[], None]] = None) -> None:
        """Start the node and wait until its first status arrives."""
        self.domain_id = unique_domain_id()
        ros_args = ['--ros-args', *(['-r', f'__ns:={namespace}'] if namespace else []), *args]
        self.process = start('collision_node', ros_args, self.domain_id, preexec)
        self.probe = Probe(self.domain_id)
        self.prefix = namespace.rstrip('/') + '/' if namespace else ''
        self.statuses = self.probe.collect(String, self.prefix + 'status', STATUS_QOS)
        self.events = self.probe.collect(String, self.prefix + 'events', 50)
        self.requests = {}
        try:
            self.probe.wait_for(lambda: self.statuses or self.process.poll() is not None, 30.0)
        except BaseException:
            self.stop()
            raise
        if self.process.poll() is not None:
            code, out, err = self.stop()
            raise AssertionError(f'collision_node exited with {code}: {err}')

    def status(self) -> dict:
        """Return the newest status received."""
        return json.loads(self.statuses[-1].data)

    def next_status(self, where: Optional[Callable[[dict], bool]] = None) -> dict:
        """Return the first status from now on that satisfies ``where``."""
        msg = self.probe.next_message(
            self.statuses, where=lambda m: where is None or where(json.loads(m.data)))
        return json.loads(msg.data)

    def publisher(self, msg_type: Any, topic: str) -> Any:
        """Return a publisher to the node, after the node has subscribed to it."""
        key = (msg_type, topic)
        if key not in self.requests:
            pub = self.probe.node.create_publisher(msg_type, self.prefix + topic, 50)
            self.probe.wait_for(lambda: pub.get_subscription_count() > 0)
            self.requests[key] = pub
        return self.requests[key]

    def request(self, msg_type: Any, topic: str, msg: Any) -> dict:
        """Publish a command and return the first event from now on that answers its kind.

        Events and service replies travel on different topics, so an event
        of an earlier service call may still arrive after that call's reply;
        it is of another kind, or taken by ``reset`` below.
        """
        pub = self.publisher(msg_type, topic)
        return self.next_event(topic, lambda: pub.publish(msg))[0]

    def next_event(self, kind: str, send: Callable[[], Any]) -> tuple[dict, Any]:
        """Run ``send``; return the first event of ``kind`` received after it, and what it gave."""
        start = len(self.events)
        result = send()

        def answered():
            for message in self.events[start:]:
                event = json.loads(message.data)
                if event['request'] == kind:
                    return event
            return None
        return self.probe.wait_for(answered), result

    def reset(self, client: Any, timeout: float = 15.0) -> Any:
        """Call the ``reset`` service; return its response once its event has arrived too."""
        return self.next_event('reset', lambda: self.probe.call(client, Trigger.Request(),
                                                                timeout))[1]

    def stop(self, sig: int = signal.SIGINT) -> tuple[int, str, str]:
        """Stop the probe and the node; return the node's exit code and output."""
        try:
            self.probe.close()
        finally:
            result = stop(self.process, sig)
        return result


class InProcessNode:
    """A collision_node in this process, with an executor that only the test spins.

    Requests are handed to the subscription callbacks as the executor
    would; nothing runs unless the test spins, so no timer fires meanwhile.
    """

    def __init__(self, overrides: list) -> None:
        """Create the node (parameter ``overrides``) in a context of its own."""
        from collision_node.ros.node import CollisionNode
        self.context = Context()
        rclpy.init(context=self.context, domain_id=unique_domain_id())
        self.node = CollisionNode(context=self.context, parameter_overrides=overrides)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def deliver(self, topic: str, data: bytes) -> None:
        """Hand a serialised request to the node's ``topic`` subscription callback."""
        subscription = next(s for s in self.node.subscriptions
                            if s.topic_name.endswith('/' + topic))
        subscription.callback(data)

    def spin_until(self, predicate: Callable[[], Any], timeout: float = 30.0) -> Any:
        """Spin the node until ``predicate()`` is truthy and return it; fail after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            value = predicate()
            if value:
                return value
            assert time.monotonic() < deadline, f'timed out after {timeout} s'
            self.executor.spin_once(timeout_sec=0.05)

    def close(self) -> None:
        """Stop the stepping thread, destroy the node and shut the context down."""
        self.node.stepper.close(1.0)
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
