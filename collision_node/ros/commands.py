"""The node's commands: topics and services in, one JSON answer per request on ``events``.

Topics (``std_msgs/String``, YAML or JSON, parsed by the physics'
``parse_request``): ``spawn``, ``delete``, ``teleport``, ``impulse``,
``step``; ``reset`` (``std_msgs/Empty``). Services: ``reset``
(``std_srvs/Trigger``) and ``pause`` (``std_srvs/SetBool``). Each request
gets exactly one answer on ``events``::

    {"seq": 7, "request": "spawn", "request_id": "a1", "accepted": true,
     "ids": [[16, 17]], "particles": 18}
    {"seq": 8, "request": "teleport", "request_id": null, "accepted": false,
     "reason": "teleport: id: no particle with id 99", "particles": 18}

``seq`` counts answers from 1; ``request_id`` echoes the request's own
(null without one); ``ids`` are inclusive ``[first, last]`` ranges. The
checks themselves live in :mod:`collision_node.physics.model.world_commands`; this
module only routes messages and formats answers.

While a slice of steps runs (node.py, stepper.py) a request waits for
its end, at most the step in flight; a ``step`` request is itself taken in
slices, bounded by ``STEP_REQUEST_SECONDS`` of wall time as well as by its
count, and answered when it ends. The status goes out after every
accepted request (once per batch taken).
"""

from __future__ import annotations

import ctypes
import json
import time
from typing import Any, Callable, Optional

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.parameter import Parameter
from rclpy.task import Future
from std_msgs.msg import Empty, String
from std_srvs.srv import SetBool, Trigger

from msg_adapters.strings import string_bytes, string_size, string_text, StringMessageError

from ..physics.model.world_commands import (delete_request, id_ranges, impulse_request,
                                            parse_request, request_id_of, spawn_request,
                                            step_count, teleport_request)
from ..physics.model.guard import MAX_TEXT_BYTES
from ..physics.model.validation import SceneError
from .qos import COMMAND_QOS, EVENTS_QOS, SERVICE_QOS

MAX_REASON = 400             # characters of a refusal reason in an answer
# Queued requests one callback may take after its own (see _subscribe).
DRAIN_MESSAGES = 256
DRAIN_SECONDS = 0.01
LOG_PERIOD = 1.0             # s between two log lines of one kind (spawns, deletes)
# Request bytes taken after which the heap is trimmed once the queue is empty (see _trim).
TRIM_BYTES = 16 << 20
TRIM_PERIOD = 1.0            # s between checks for a trim the drain did not make
_MALLOC_TRIM = getattr(ctypes.CDLL(None), 'malloc_trim', None)     # glibc only
# Refusals logged a second at most (each is answered on events anyway).
LOGGED_PER_SECOND = 20
# Wall seconds one step request may take (besides its count, 1..10,000 steps):
# it then ends, answered with the steps it took and "stopped": "time limit".
STEP_REQUEST_SECONDS = 10.0
# Requests held while a step is in flight (taken at its end). Beyond either
# bound the node waits for that step before it takes more, so a flood stays
# in the middleware's queues (reliable flow control) instead of in memory.
PENDING_REQUESTS = 1000
PENDING_BYTES = 16 << 20
# What a handler returns for a request it answers later (a step request).
LATER = None
# Seconds a reset service call waits for the step in flight before it is
# answered anyway (the reset then follows that step).
RESET_REPLY_WAIT = 0.05


def out_of_memory(error: MemoryError, doing: str) -> str:
    """Return one line saying a ``MemoryError`` stopped ``doing`` (it has few words of its own)."""
    detail = ' '.join(str(error).split())[:80]
    return f'out of memory {doing} (MemoryError{": " + detail if detail else ""})'


class LogBudget:
    """At most ``LOGGED_PER_SECOND`` refusals logged a second; the rest counted, then said."""

    def __init__(self, logger: Any) -> None:
        """Start a window with the whole budget."""
        self.logger = logger
        self.window_start = -1.0
        self.logged = self.suppressed = 0

    def spend(self, now: float) -> bool:
        """Return whether a refusal at ``now`` may be logged; report what was held back."""
        if now - self.window_start >= 1.0:
            if self.suppressed:
                self.logger.warning(f'{self.suppressed} more requests were rejected in a '
                                    'second without a log line (each was answered on events)')
            self.window_start, self.logged, self.suppressed = now, 0, 0
        if self.logged < LOGGED_PER_SECOND:
            self.logged += 1
            return True
        self.suppressed += 1
        return False


class HoldableGroup(MutuallyExclusiveCallbackGroup):
    """A callback group whose messages stay queued in the middleware while ``held``.

    The node holds its command topics while a slice of steps runs: a
    request could not touch the world before the slice ends anyway, and
    left in the (KEEP_ALL, reliable) reader it costs neither memory nor the
    stepping thread's share of the interpreter; the slice's end releases it
    and the batch is taken as usual.
    """

    def __init__(self) -> None:
        """Start released."""
        super().__init__()
        self.held = False

    def can_execute(self, entity: Any) -> bool:
        """Tell whether ``entity``'s callback may run: never while held."""
        return not self.held and super().can_execute(entity)

    def beginning_execution(self, entity: Any) -> bool:
        """Begin ``entity``'s callback unless held (its message then stays queued)."""
        return not self.held and super().beginning_execution(entity)


class CommandInterface:
    """Subscriptions and services of the node's commands, and its answers on ``events``."""

    def __init__(self, node: Any) -> None:
        """Create ``events`` and every command subscription and service on ``node``.

        ``node`` is the :class:`~collision_node.ros.node.CollisionNode` (typed
        Any: node.py imports this module and the package keeps no import circle).
        """
        self.node = node
        self.seq = 0
        self.log_budget = LogBudget(node.get_logger())
        self._logged: dict[str, float] = {}     # monotonic time of each kind's last log line
        self._taken = 0                         # request bytes taken since the last trim
        self.pub_events = node.create_publisher(String, 'events', EVENTS_QOS)
        # The command topics, held while a slice of steps runs (node.py).
        self.topics = HoldableGroup()
        handlers: dict[str, Callable[[Any], dict]] = {
            'spawn': self._spawn, 'delete': self._delete, 'teleport': self._teleport,
            'impulse': self._impulse, 'step': self._step}
        for name, handler in handlers.items():
            self._subscribe(name, handler)
        node.create_subscription(Empty, 'reset', self._on_reset_topic, COMMAND_QOS,
                                 callback_group=self.topics)
        # Its own callback group: a reset call waiting for the step in flight must
        # not hold back the node's other callbacks (the slice's end among them).
        node.create_service(Trigger, 'reset', self._on_reset_service, qos_profile=SERVICE_QOS,
                            callback_group=ReentrantCallbackGroup())
        node.create_service(SetBool, 'pause', self._on_pause_service, qos_profile=SERVICE_QOS)
        # A burst can end without its last drain finding the queue empty.
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        node.create_timer(TRIM_PERIOD, lambda: self._trim(1 << 20), clock=self.steady)

    def _subscribe(self, name: str, handler: Callable[[Any], dict]) -> None:
        """Subscribe to one command topic raw; each callback also drains what is queued.

        The messages arrive as their CDR bytes: a request's size is read from
        the length field and a too-long one refused before any text is made
        of it (rclpy would first copy it into a C string and a Python str).
        """
        subscription = None

        def on_message(data: bytes) -> None:
            self.take(name, data, handler)
            # The executor hands over one message per wait, which costs more than
            # most requests do; take what is already queued here, within a bound so
            # the tick (stepping and publishing) still runs on time.
            deadline = time.monotonic() + DRAIN_SECONDS
            handle = subscription.handle
            for _ in range(DRAIN_MESSAGES):
                if time.monotonic() > deadline:
                    break
                with handle:
                    taken = handle.take_message(String, True)
                if taken is None:
                    self._trim()
                    break
                self.take(name, taken[0], handler)
            self.node.flush_status()

        subscription = self.node.create_subscription(String, name, on_message, COMMAND_QOS,
                                                     raw=True, callback_group=self.topics)

    def take(self, request: str, data: bytes, handler: Callable[[Any], dict]) -> None:
        """Handle a request now, or in turn once the slice in flight ends (see PENDING_*).

        The slice is not cut short for it: it ends within STEP_BUDGET of a
        tick period or after its step in flight, whichever is later, and what
        came meanwhile is then taken in one batch. Beyond PENDING_* the node
        waits for the slice here, so a flood stays in the middleware's queue.
        """
        node = self.node
        if not node.stepper.busy and not node.pending:
            self.handle_bytes(request, data, handler)
            return
        node.at_boundary(lambda: self.handle_bytes(request, data, handler), interrupt=False,
                         size=len(data))
        while len(node.pending) >= PENDING_REQUESTS or node.pending_bytes >= PENDING_BYTES:
            if node.stepper.busy:
                node.stepper.wait()
            else:
                node.run_pending()

    # -- answers ------------------------------------------------------------

    def answer(self, request: str, request_id: Any, accepted: bool, **fields: Any) -> None:
        """Publish one answer on ``events`` (serialised here, no message object)."""
        self.seq += 1
        event = {'seq': self.seq, 'request': request, 'request_id': request_id,
                 'accepted': accepted, **fields, 'particles': len(self.node.world.state)}
        self.pub_events.publish(string_bytes(json.dumps(event)))

    def _trim(self, at_least: int = TRIM_BYTES) -> None:
        """Give the heap's free pages back to the system after a burst of large requests.

        A flood of 1 MiB requests leaves glibc holding what they used (its
        mmap threshold grows with the first freed large block, so the next
        ones come from the heap and stay there); trimming once the queue is
        empty costs a few milliseconds per TRIM_BYTES of requests.
        """
        if self._taken >= at_least and _MALLOC_TRIM is not None:
            _MALLOC_TRIM(0)
            self._taken = 0

    def handle_bytes(self, request: str, data: bytes, handler: Callable[[Any], dict]) -> None:
        """Check a serialised String's size, read its text and handle it; refuse if unreadable."""
        self._taken += len(data)
        try:
            size = string_size(data)
            if size > MAX_TEXT_BYTES:
                # The guard's own words (it would say the same after decoding).
                raise SceneError(f'{request}: text of {size} bytes (or more) is over the '
                                 f'limit of {MAX_TEXT_BYTES} bytes (1 MiB)')
            text = string_text(data)
        except StringMessageError as error:
            self.refuse(request, None, f'{request}: not a std_msgs/String: {error}')
        except SceneError as error:
            self.refuse(request, None, str(error))
        else:
            self.handle(request, text, handler)

    def handle(self, request: str, text: str, handler: Callable[[Any], dict]) -> None:
        """Parse a command's text, run it, and answer once (accepted or with the reason)."""
        request_id = None
        try:
            data = parse_request(text, request)
            request_id = request_id_of(data, request)
            fields = handler(data)
        except SceneError as error:
            reason = str(error)
        except MemoryError as error:
            reason = f'{request}: {out_of_memory(error, "handling the request")}'
        except Exception as error:  # noqa: B902 - a bad request must never stop the node
            reason = f'{request}: {type(error).__name__}: {error}'
        else:
            if fields is not LATER:
                self.answer(request, request_id, True, **fields)
                self.node.status_changed()
            return
        self.refuse(request, request_id, reason)

    def refuse(self, request: str, request_id: Any, reason: str) -> None:
        """Answer a refusal with its reason made one bounded line."""
        reason = ' '.join(reason.split())
        if len(reason) > MAX_REASON:
            reason = reason[:MAX_REASON] + '...'
        # Every refusal is answered on events; the log (console and /rosout) gets
        # each one too, up to a budget a second, so a flood does not flood it.
        if self.log_budget.spend(time.monotonic()):
            self.node.get_logger().warning(f'rejected {reason}')
        self.answer(request, request_id, False, reason=reason)

    def _may_log(self, kind: str) -> bool:
        """Tell whether a ``kind`` line may be logged now (at most one per LOG_PERIOD).

        The throttle is kept here: rclpy's ``throttle_duration_sec`` finds the
        caller's source file on every call, throttled or not (about 0.4 ms,
        more than most refusals cost).
        """
        now = time.monotonic()
        if now - self._logged.get(kind, float('-inf')) < LOG_PERIOD:
            return False
        self._logged[kind] = now
        return True

    # -- commands -------------------------------------------------------------

    def _spawn(self, data: Any) -> dict:
        """Spawn particles; answer their ids."""
        ids = spawn_request(self.node.world, data)
        if self._may_log('spawned'):
            self.node.get_logger().info(f'spawned {ids.size} particles (ids {ids[0]}..{ids[-1]})'
                                        if ids.size else 'spawn request held no particles')
        return {'ids': id_ranges(ids)}

    def _delete(self, data: Any) -> dict:
        """Delete particles; answer the deleted ids."""
        ids = delete_request(self.node.world, data)
        if self._may_log('deleted'):
            self.node.get_logger().info(f'deleted {ids.size} particles')
        return {'ids': id_ranges(ids)}

    def _teleport(self, data: Any) -> dict:
        """Set a particle's position and/or velocity."""
        pid = teleport_request(self.node.world, data)
        return self._particle(pid)

    def _impulse(self, data: Any) -> dict:
        """Apply an impulse to a particle."""
        pid = impulse_request(self.node.world, data)
        return self._particle(pid)

    def _particle(self, pid: int) -> dict:
        """Answer fields for one particle: its id, position and velocity now."""
        world = self.node.world
        row = int(world.rows([pid])[0])
        return {'ids': [[pid, pid]], 'position': world.state.position[row].tolist(),
                'velocity': world.state.velocity[row].tolist()}

    def _step(self, data: Any) -> Optional[dict]:
        """Begin N steps while paused; they run in slices and are answered at their end."""
        count = step_count(data)
        node = self.node
        if not node.paused:
            raise SceneError('step: the world is running; pause it first (service pause or '
                             'parameter paused)')
        if node.failed is not None:
            raise SceneError(f'step: stepping stopped ({node.failed}); reset to go on')
        # A subscriber that appeared since the last tick sees these steps' impacts too.
        node.reports.follow_listeners(node.world)
        node.begin_step_request(request_id_of(data, 'step'), count, STEP_REQUEST_SECONDS)
        return LATER

    def answer_step(self, request_id: Any, done: int, count: int,
                    stopped: Optional[str]) -> None:
        """Answer a step request that ended: all ``count`` steps, or ``done`` and why not."""
        fields: dict[str, Any] = {'steps': done, 'time': self.node.world.time}
        if stopped is not None:
            limit = f' of {STEP_REQUEST_SECONDS:g} s' if stopped == 'time limit' else ''
            fields.update(steps_requested=count, stopped=stopped + limit)
        self.answer('step', request_id, True, **fields)
        self.node.status_changed()

    # -- reset and pause --------------------------------------------------------

    def _on_reset_topic(self, msg: Empty) -> None:
        """Reset on a message on the ``reset`` topic (at the end of the step in flight)."""
        self.node.at_boundary(self._reset)

    async def _on_reset_service(self, request: Trigger.Request,
                                response: Trigger.Response) -> Trigger.Response:
        """Reset on a ``reset`` service call; reply once done, or after RESET_REPLY_WAIT.

        The reset waits for the end of the step in flight. A step that ends
        within RESET_REPLY_WAIT (any small world's) gets the usual reply,
        after the reset and its status; a longer one gets a reply at once
        saying the reset follows that step. The executor serves other
        callbacks meanwhile.
        """
        node = self.node
        replied = Future()
        since = node.world.time

        def reset() -> None:
            message = self._reset()
            if not replied.done():
                replied.set_result(message)
        node.at_boundary(reset)
        if not replied.done():
            timer = node.create_timer(RESET_REPLY_WAIT, lambda: replied.done() or (
                replied.set_result(f'resetting after the step in flight (from time {since:g} '
                                   's)')), clock=self.steady)
            try:
                await replied
            finally:
                node.destroy_timer(timer)
        response.message = replied.result()
        response.success = True
        return response

    def _reset(self) -> str:
        """Reset the world and answer with the ids it holds again."""
        message = self.node.reset_world()
        self.answer('reset', None, True, ids=id_ranges(self.node.world.state.ids))
        return message

    def _on_pause_service(self, request: SetBool.Request,
                          response: SetBool.Response) -> SetBool.Response:
        """Pause (data true) or resume through the ``paused`` parameter, and reply at once.

        The world stops (or goes on) after the step in flight, if one is;
        the answer on ``events`` then carries the time it stopped at.
        """
        paused = bool(request.data)
        node = self.node
        result = node.set_parameters([Parameter('paused', Parameter.Type.BOOL, paused)])[0]
        response.success = result.successful
        state = 'paused' if paused else 'running'
        if not result.successful:
            response.message = f'pause: {result.reason}'
            self.answer('pause', None, False, reason=response.message)
        else:
            if node.stepper.busy:
                response.message = (f'{state} after the step in flight (from time '
                                    f'{node.world.time:g} s)')
            else:
                response.message = f'{state} at time {node.world.time:g} s'
            node.at_boundary(lambda: self.answer('pause', None, True, paused=paused,
                                                 time=node.world.time))
        return response
