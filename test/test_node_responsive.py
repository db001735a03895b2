"""The node stays responsive while a 100,000-particle world steps (a step takes ~0.5-1 s here).

One paused node on a 2-D gas of 100,000 particles serves the module. Its
steps run in slices on a worker thread; services are answered meanwhile,
and pause, reset and a new step request take effect after the step in
flight. Every wait is on a message (a status, an answer, a reply).
"""

from __future__ import annotations

import json
import statistics
import time

import pytest
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger

from collision_node.physics.step.kernels import all_kernels
from collision_node.ros.commands import STEP_REQUEST_SECONDS
from collision_node.ros.qos import EVENTS_QOS
from msg_adapters.strings import string_bytes, string_text
from node_harness import InProcessNode, NodeUnderTest

pytestmark = pytest.mark.ros

DT = 1.0 / 240.0
PARTICLES = 100_000
# A large world: 100,000 particles of radius 0.8 mm on the default table.
SCENE = f'''name: gas_100k
dimensions: 2
dt: {DT!r}
effects:
  walls: {{min: [-1.27, -0.635], max: [1.27, 0.635]}}
generate:
  - {{kind: gas, count: {PARTICLES}, radius: 0.0008, mass: 1.0, speed: 1.0, seed: 5,
     region: {{min: [-1.2, -0.6], max: [1.2, 0.6]}}}}
'''


@pytest.fixture(scope='module')
def node(tmp_path_factory):
    """One paused node on the 100,000-particle gas."""
    scene = tmp_path_factory.mktemp('responsive') / 'gas_100k.yaml'
    scene.write_text(SCENE)
    running = NodeUnderTest(['-p', f'scene:={scene}', '-p', 'paused:=true',
                             '-p', f'max_particles:={PARTICLES}'])
    running.answers = running.probe.collect(String, 'events', EVENTS_QOS)
    running.pause_client = running.probe.node.create_client(SetBool, 'pause')
    running.reset_client = running.probe.node.create_client(Trigger, 'reset')
    assert running.status()['particles'] == PARTICLES
    yield running
    code, _, err = running.stop()
    assert code == 0, err
    assert 'Traceback' not in err


@pytest.fixture
def fresh(node):
    """Reset the world (service) before a test; give the node."""
    assert node.probe.call(node.reset_client, Trigger.Request(), timeout=60).success
    node.next_status(lambda s: s['steps'] == 0 and s['paused'])
    return node


def send_step(node, steps: int, request_id: str) -> None:
    """Publish a step request (its answer comes when it ends)."""
    node.publisher(String, 'step').publish(
        String(data=json.dumps({'steps': steps, 'request_id': request_id})))


def answer(node, request: str, request_id=None, timeout: float = 60.0) -> dict:
    """Return the answer to ``request`` (with ``request_id``) once it arrives."""
    def found():
        for message in node.answers:
            event = json.loads(message.data)
            if event['request'] == request and event['request_id'] == request_id:
                return event
        return None
    return node.probe.wait_for(found, timeout)


def under_way(node, after: int = 0) -> dict:
    """Return a status showing steps beyond ``after``: the slices are running."""
    return node.next_status(lambda s: s['steps'] > after)


def pause(node, paused: bool) -> tuple[SetBool.Response, float]:
    """Call the pause service; return its reply and the round trip in seconds."""
    assert node.pause_client.wait_for_service(timeout_sec=15)
    start = time.monotonic()
    reply = node.probe.call(node.pause_client, SetBool.Request(data=paused))
    return reply, time.monotonic() - start


def test_pause_is_answered_within_100_ms_while_a_long_step_request_runs(fresh):
    send_step(fresh, 10_000, 'long')
    under_way(fresh)
    trips = []
    for _ in range(9):
        reply, trip = pause(fresh, True)
        # Answered while a step was in flight, not after it.
        assert reply.success and reply.message.startswith('paused after the step in flight')
        trips.append(trip)
    # The bound. The median of nine calls: on a loaded 2-core machine one
    # call can meet a scheduling stall of the test process itself; half of them
    # cannot. (Before the worker thread each call waited for whole steps: 11-17 s.)
    assert statistics.median(trips) < 0.1, [round(t, 3) for t in trips]
    # The request is bounded by time as well: it ends after STEP_REQUEST_SECONDS.
    done = answer(fresh, 'step', 'long', timeout=STEP_REQUEST_SECONDS + 60)
    assert done['accepted'] and done['stopped'] == f'time limit of {STEP_REQUEST_SECONDS:g} s'
    assert 1 <= done['steps'] < 10_000 and done['steps_requested'] == 10_000
    assert done['time'] == pytest.approx(done['steps'] * DT, rel=1e-12)
    assert fresh.next_status()['steps'] == done['steps']


def test_a_new_step_request_or_a_reset_ends_the_one_under_way(fresh):
    send_step(fresh, 10_000, 'first')
    under_way(fresh)
    send_step(fresh, 2, 'second')
    first, second = answer(fresh, 'step', 'first'), answer(fresh, 'step', 'second')
    assert first['accepted'] and first['stopped'] == 'a new step request'
    assert 1 <= first['steps'] < 10_000
    assert second['accepted'] and second['steps'] == 2 and 'stopped' not in second
    assert second['time'] == pytest.approx((first['steps'] + 2) * DT, rel=1e-12)
    assert second['seq'] > first['seq']
    send_step(fresh, 10_000, 'third')
    under_way(fresh, after=first['steps'] + 2)
    reply = fresh.probe.call(fresh.reset_client, Trigger.Request(), timeout=60)
    # Answered at once; the reset follows the step in flight (RESET_REPLY_WAIT).
    assert reply.success and reply.message.startswith('resetting after the step in flight')
    third = answer(fresh, 'step', 'third')
    assert third['accepted'] and third['stopped'] == 'reset' and third['steps'] >= 1
    reset = fresh.probe.wait_for(
        lambda: [e for e in map(json.loads, (m.data for m in fresh.answers))
                 if e['request'] == 'reset' and e['seq'] > third['seq']])[0]
    assert reset['accepted'] and reset['ids'] == [[0, PARTICLES - 1]]
    assert fresh.next_status(lambda s: s['steps'] == 0)['time'] == 0.0


def test_resume_ends_a_step_request_and_pause_stops_after_the_step_in_flight(fresh):
    send_step(fresh, 10_000, 'resumed')
    under_way(fresh)
    reply, _ = pause(fresh, False)
    assert reply.success
    ended = answer(fresh, 'step', 'resumed')
    assert ended['accepted'] and ended['stopped'] == 'resumed'
    running = fresh.next_status(lambda s: not s['paused'] and s['steps'] > ended['steps'])
    seen = len(fresh.answers)
    reply, trip = pause(fresh, True)
    assert reply.success
    stopped = fresh.probe.wait_for(lambda: [json.loads(m.data) for m in fresh.answers[seen:]
                                            if json.loads(m.data)['request'] == 'pause'])[0]
    assert stopped['paused'] is True and stopped['time'] >= running['time']
    # The world stopped at that step boundary: later statuses keep its time.
    after = fresh.next_status(lambda s: s['paused'])
    assert after['time'] == stopped['time']
    assert fresh.next_status()['time'] == stopped['time']


def test_every_kernel_called_from_python_releases_the_gil():
    """The stepping threads of the node and the runner rely on it (stepper.py)."""
    kernels = all_kernels()
    assert len(kernels) > 30
    assert [k.py_func.__name__ for k in kernels if not k.targetoptions.get('nogil')] == []


class Recorder:
    """Stands in for the node's status publisher: keeps what is published."""

    def __init__(self) -> None:
        """Start with nothing published."""
        self.published: list[dict] = []

    def publish(self, message) -> None:
        """Keep the status a message holds (a String, or its serialised bytes)."""
        text = string_text(message) if isinstance(message, bytes) else message.data
        self.published.append(json.loads(text))


@pytest.fixture
def in_process():
    """Give a paused node in this process, its 0.5 s status timer cancelled."""
    harness = InProcessNode([Parameter('paused', Parameter.Type.BOOL, True)])
    try:
        harness.node.status_timer.cancel()     # every status from now on comes from a command
        harness.node.pub_status = Recorder()
        yield harness
    finally:
        harness.close()


def deliver(harness, topic: str, text: str) -> dict:
    """Hand a request to the node's subscription callback; return the status that follows."""
    statuses = harness.node.pub_status.published
    seen = len(statuses)
    harness.deliver(topic, string_bytes(text))
    harness.spin_until(lambda: len(statuses) > seen)
    return statuses[-1]


def test_every_accepted_command_publishes_the_status(in_process):
    """The periodic status is off: each status below comes from the command."""
    node = in_process.node
    assert deliver(in_process, 'spawn', '{position: [0.5, 0.3], radius: 0.05, '
                                        'mass: 2.0}')['particles'] == 17
    status = deliver(in_process, 'teleport', '{id: 0, velocity: [1.0, 0.0]}')
    # The cue ball's 5 m/s became 1 m/s; the new particle rests.
    assert status['particles'] == 17
    assert status['kinetic_energy'] == pytest.approx(0.5 * 0.17 * 1.0, rel=1e-12)
    assert deliver(in_process, 'delete', '{ids: [16]}')['particles'] == 16
    status = deliver(in_process, 'step', '{steps: 3}')        # answered when the steps end
    assert status['steps'] == 3 and status['time'] == pytest.approx(3 * DT)
    # A refusal changes nothing and sends no status.
    count = len(node.pub_status.published)
    in_process.deliver('teleport', string_bytes('{id: 99, velocity: [1.0, 0.0]}'))
    assert len(node.pub_status.published) == count and not node._status_due
    assert deliver(in_process, 'impulse', '{id: 1, impulse: [0.017, 0.0]}')[
        'kinetic_energy'] == pytest.approx(0.5 * 0.17 * (1.0 + 0.01), rel=1e-12)
