"""The collision_node ROS 2 node: a live particle world on topics.

The node owns timing and ROS I/O only: the physics is a core
:class:`~collision_node.physics.step.world.World`, and every numpy-to-message
conversion lives in :mod:`msg_adapters`. Topics, QoS and parameters are
tabled in docs/node.md.
"""

from __future__ import annotations

import functools
import json
import sys
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Optional

import rclpy
from geometry_msgs.msg import PoseArray, VelocityStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from msg_adapters import clock_bytes, velocities_bytes
from msg_adapters.strings import string_bytes

from ..id_order import InIdOrder
from ..physics.model.accuracy import parse_accuracy_text
from ..physics.step.kernels import prepare as prepare_kernels
from ..physics.model.scene import load_scene
from ..physics.model.validation import SceneError
from ..physics.step.world import NonFiniteStateError, World
from ..physics.step.threads import resolve as resolve_threads
from ..recording.bag import BagTargetError, check_target
from ..recording.definitions import DefinitionError
from ..recording.recorder import FRAME_MESSAGES, Recorder
from .cli import check_command_line
from .commands import CommandInterface, DRAIN_SECONDS, out_of_memory
from .pacing import came_short, Lag, Pacer, RateMeter, STEP_BUDGET
from .parameters import (as_double, DEFAULT_SCENE, integers_as_doubles, invalid_parameter,
                         PARAMETERS)
from .qos import fastdds_profiles, STATE_QOS, STATUS_QOS, VELOCITY_QOS
from .reports import Reports
from .status import status_report
from .stepper import SliceResult, Stepper

NODE_NAME = 'collision_node'
RCLError = _rclpy.RCLError
STATUS_PERIOD = 0.5          # s of wall time between status messages (and after each change)
# Share of the node's time the statuses after commands may take at most (see flush_status).
STATUS_SHARE = 0.1
# At exit, seconds to wait for the step in flight to end before leaving it to the process's end.
EXIT_WAIT = 1.0


@dataclass
class TickPlan:
    """The steps one tick asked for (``due``), taken in slices until ``deadline``."""

    due: int
    dropped: float               # simulated seconds of backlog the tick dropped
    deadline: float              # time.monotonic() after which no further step is begun
    done: int = 0


@dataclass
class StepRequest:
    """A ``step`` request being taken in slices (answered once it ends, commands.py)."""

    request_id: Any
    count: int
    deadline: float              # time.monotonic() at which it stops (STEP_REQUEST_SECONDS)
    done: int = 0


class CollisionNode(Node):
    """Steps a world in (scaled) real time and publishes it; takes commands (commands.py).

    The steps run in slices on a worker thread (stepper.py) while this
    node's callbacks keep being served; everything that touches the world
    outside a slice runs on the executor thread between slices
    (:meth:`at_boundary`): a command waits for the slice in flight (its
    step budget, or its one step if longer); pause, reset and parameter
    changes end it after its step in flight.
    """

    def __init__(self, **kwargs: Any) -> None:
        """Declare parameters, load the scene, create the ROS interfaces."""
        super().__init__(NODE_NAME, **kwargs)
        # '-p real_time_factor:=2' arrives as an integer; declaring a double
        # parameter with it would fail, so such overrides become doubles first.
        overrides = getattr(self, '_parameter_overrides', {})
        for name in list(overrides):
            overrides[name] = as_double(overrides[name])
        for name, (default, descriptor) in PARAMETERS.items():
            self.declare_parameter(name, default, descriptor)
        value = self._parameter_values()
        problem = invalid_parameter(value)
        if problem:
            raise SceneError(f'parameter {problem}')
        if value['record']:
            # Refused before the scene is even loaded.
            self._record_target_check(value['record'], check_target)
        self.scene = load_scene(value['scene'] or DEFAULT_SCENE)
        if value['accuracy']:
            self.scene = self.scene.with_accuracy(
                parse_accuracy_text(value['accuracy'], self.scene.effects,
                                    'parameter accuracy'))
        self.world = World(self.scene, max_particles=value['max_particles'],
                           threads=resolve_threads(value['threads'], 'parameter threads'))
        # Compiled once, then loaded from the cache; only a compile is logged.
        prepare_kernels(self.get_logger().info)
        self.real_time_factor = value['real_time_factor']
        self.publish_rate = value['publish_rate']
        self.paused = value['paused']
        self.publish_clock = value['publish_clock']
        self.frame_id = value['frame_id']
        self.failed: Optional[str] = None
        self.keeping_up = True
        self.lag = Lag()
        self.pacer = Pacer(self.world.dt, self.real_time_factor, time.monotonic(),
                           self.world.time)
        self.meter = RateMeter()
        self.ticks = 0
        self.meter.add(time.monotonic(), self.world.time, self._collisions())
        # Slices of steps on the worker thread, and what waits for a slice's end.
        self.stepper = Stepper(self, self._slice_done)
        self.pending: deque[tuple[Callable[[], None], int]] = deque()
        self.pending_bytes = 0       # request bytes among the pending work (commands.py)
        self._pending_guard = self.create_guard_condition(self._on_pending)
        self._idle_work: dict[str, Callable[[], None]] = {}
        self._draining = False
        self.plan: Optional[TickPlan] = None
        self.step_request: Optional[StepRequest] = None
        self._outputs_due = False    # a tick came while a slice ran
        self._status_due = False     # an accepted command changed the world

        self.pub_poses = self.create_publisher(PoseArray, 'particles/poses', STATE_QOS)
        self.pub_velocities = self.create_publisher(VelocityStamped, 'particles/velocities',
                                                    VELOCITY_QOS)
        self.pub_state = self.create_publisher(PointCloud2, 'particles/state', STATE_QOS)
        self.pub_markers = self.create_publisher(MarkerArray, 'particles/markers', STATE_QOS)
        self.pub_clock = self.create_publisher(ClockMsg, '/clock', STATE_QOS)
        self.pub_status = self.create_publisher(String, 'status', STATUS_QOS)
        self.commands = CommandInterface(self)

        # Timers run on the steady clock: the node lives in wall time even
        # if somebody sets use_sim_time (it is the source of /clock).
        self.steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.tick_timer = self.create_timer(1.0 / self.publish_rate, self._tick,
                                            clock=self.steady)
        self.status_timer = self.create_timer(STATUS_PERIOD, self._publish_status,
                                              clock=self.steady)
        self._status_sent = self._status_cost = 0.0
        self._status_flush = self.create_timer(1.0, self._on_status_flush, clock=self.steady)
        self._status_flush.cancel()
        self.reports = Reports(self, self.status, self.steady,   # /diagnostics, collisions
                               when_idle=self.when_idle)
        self.state_publishers = {'poses': self.pub_poses, 'state': self.pub_state,
                                 'markers': self.pub_markers}
        self.recorder: Optional[Recorder] = None
        self.recording_reported = False
        if value['record']:
            self._record_target_check(value['record'], self._start_recording)
        self.add_pre_set_parameters_callback(integers_as_doubles)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self.get_logger().info(
            f'scene {self.scene.name} ({self.scene.source}): {len(self.world.state)} particles, '
            f'{self.scene.dimensions}-D, dt = {self.world.dt:g} s; publishing at '
            f'{self.publish_rate:g} Hz, real-time factor {self.real_time_factor:g}'
            f'{", paused" if self.paused else ""}')
        self.get_logger().info('step pipeline:\n' + self.world.explain())
        self._publish_status()

    # -- parameters -------------------------------------------------------

    def _parameter_values(self) -> dict[str, Any]:
        """Return every declared parameter's current value."""
        return {name: self.get_parameter(name).value for name in PARAMETERS}

    def _check_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse invalid values with a reason (types, ranges and read-only come first)."""
        problem = invalid_parameter({p.name: p.value for p in parameters})
        if problem:
            self.get_logger().warning(f'refused parameter {problem}')
            return SetParametersResult(successful=False, reason=problem)
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Apply accepted runtime changes: settings at once, their effect on the world next.

        Pausing stops the slices after the step in flight; the pacing's new
        anchor (and the end of a step request on a resume) is set at the
        boundary, when the world's time is that of a whole step.
        """
        anchor = resumed = False
        for p in parameters:
            if p.name == 'real_time_factor':
                self.real_time_factor = p.value
                self.pacer.factor = p.value
                self.keeping_up = True
                anchor = True
            elif p.name == 'publish_rate':
                self.publish_rate = p.value
                # The new period counts from now: without the reset the next
                # tick would still come a whole old period (up to 10 s) later.
                self.tick_timer.timer_period_ns = int(1e9 / p.value)
                self.tick_timer.reset()
            elif p.name == 'paused':
                resumed = self.paused and not p.value
                self.paused = p.value
                anchor = True
            elif p.name == 'publish_clock':
                self.publish_clock = p.value
            elif p.name == 'frame_id':
                self.frame_id = p.value
            self.get_logger().info(f'parameter {p.name} = {p.value!r}')

        def apply() -> None:
            if anchor:
                self.pacer.restart(time.monotonic(), self.world.time)
                self.lag.clear()
            if resumed and self.step_request is not None:
                self._finish_step_request('resumed')
            self.status_changed()
            self.flush_status()
        self.at_boundary(apply)

    # -- the world between slices -------------------------------------------

    def at_boundary(self, work: Callable[[], None], interrupt: bool = True,
                    size: int = 0) -> None:
        """Run ``work`` (it touches the world) now, or in turn between slices.

        It waits while a slice runs (with ``interrupt`` the slice ends after
        its step in flight) or while earlier work waits (the order is kept);
        waiting work runs between slices, ``DRAIN_SECONDS`` of it at a time
        so ticks and services go on meanwhile. ``size``: the request bytes
        it holds (counted in ``pending_bytes``, see commands.PENDING_BYTES).
        """
        if not self.stepper.busy and not self._draining and not self.pending:
            work()
            return
        self.pending.append((work, size))
        self.pending_bytes += size
        if self.stepper.busy:
            if interrupt:
                self.stepper.interrupt.set()
        elif not self._draining:
            self._pending_guard.trigger()

    def when_idle(self, key: str, work: Callable[[], None]) -> None:
        """Run ``work`` now if no slice runs, else once at the slice's end (one per ``key``)."""
        if not self.stepper.busy and not self._draining:
            work()
        else:
            self._idle_work[key] = work

    def run_pending(self) -> None:
        """Run waiting work for ``DRAIN_SECONDS`` at most (no slice runs); go on later if more."""
        deadline = time.monotonic() + DRAIN_SECONDS
        self._draining = True
        try:
            while self.pending:
                work, size = self.pending.popleft()
                self.pending_bytes -= size
                work()
                if time.monotonic() > deadline:
                    break
            while self._idle_work:
                self._idle_work.pop(next(iter(self._idle_work)))()
        finally:
            self._draining = False
        self.flush_status()
        if self.pending:
            self._pending_guard.trigger()

    def _on_pending(self) -> None:
        """Run waiting work between slices (guard condition), then go on stepping."""
        if not self.stepper.busy:
            self.run_pending()
            self._continue()

    def _slice_done(self, result: SliceResult) -> None:
        """Count an ended slice (executor thread), run what waited for it, go on stepping."""
        self.commands.topics.held = False
        if self.step_request is not None:
            self.step_request.done += result.steps
        elif self.plan is not None:
            self.plan.done += result.steps
        if result.error is not None:
            self._stop_stepping(result.error)
        if self.plan is not None and not result.interrupted:
            # The tick's steps are done (or its budget spent): publish first, so
            # what waited does not make the tick late; then the waiting work.
            self._continue()
            if self.stepper.busy:
                return
        self.run_pending()
        if self.step_request is not None:
            # The next slice after one executor round: the requests held during
            # this one are taken first (a new step request, a reset).
            self._pending_guard.trigger()
        else:
            self._continue()

    def _stop_stepping(self, error: BaseException) -> None:
        """Stop on a non-finite state or a MemoryError: no further step until a reset.

        A MemoryError may leave the step half done: the status carries the
        error and /diagnostics reports ERROR until a reset, as on a non-finite
        state. Any other exception of a step is a bug and is raised.
        """
        request = self.step_request
        if isinstance(error, MemoryError):
            doing = (f'in step {self.world.steps + 1}' if request is None else
                     f'in step {request.done + 1} of {request.count}')
            self.failed = out_of_memory(error, doing)
            reason = f'step: {self.failed}; reset to go on'
        elif isinstance(error, NonFiniteStateError):
            self.failed = str(error)
            reason = (f'step: stopped after {request.done} of {request.count} steps: {error}'
                      if request is not None else '')
        else:
            raise error
        self.get_logger().error(f'stopped stepping: {self.failed}; reset to go on')
        self.plan = None
        if request is not None:
            self.step_request = None
            self.commands.refuse('step', request.request_id, reason)

    def _continue(self) -> None:
        """Begin the next slice of the step request or the tick under way, or end them."""
        if self.stepper.busy or self._draining:
            return
        now = time.monotonic()
        if self.plan is not None and (self.paused or self.failed is not None):
            self.plan = None                  # cut short by a pause: no lag to judge
        request = self.step_request
        if request is not None:
            if request.done < request.count and now < request.deadline:
                if self._outputs_due:
                    self._publish_tick()
                self._start_slice(request.count - request.done,
                                  min(request.deadline, now + STEP_BUDGET / self.publish_rate))
                return
            self._finish_step_request(None if request.done >= request.count else 'time limit')
        plan = self.plan
        if plan is not None:
            if plan.done < plan.due and (plan.done == 0 or now <= plan.deadline):
                self._start_slice(plan.due - plan.done, plan.deadline)
                return
            self.plan = None
            self._end_tick(plan)
        elif self._outputs_due:
            self._publish_tick()

    def _start_slice(self, count: int, deadline: float) -> None:
        """Hand ``count`` steps (until ``deadline``) to the worker; hold the command topics."""
        self.commands.topics.held = True
        self.stepper.start(self.world, count, deadline)

    def begin_step_request(self, request_id: Any, count: int, seconds: float) -> None:
        """Take ``count`` steps in slices (while paused), for at most ``seconds`` of wall time.

        A request under way ends first (answered with the steps it took).
        """
        if self.step_request is not None:
            self._finish_step_request('a new step request')
        self.step_request = StepRequest(request_id, count, time.monotonic() + seconds)
        self._continue()

    def _finish_step_request(self, stopped: Optional[str]) -> None:
        """Answer the step request under way and forget it (``stopped``: why it ended early)."""
        request, self.step_request = self.step_request, None
        self.commands.answer_step(request.request_id, request.done, request.count, stopped)
        self.flush_status()

    # -- stepping and publishing ------------------------------------------

    def _collisions(self) -> int:
        """Particle and wall collisions so far."""
        return self.world.stats.collisions + self.world.stats.wall_collisions

    def _end_tick(self, plan: TickPlan) -> None:
        """Judge the tick's lag, then publish; log an episode's start and end."""
        short = came_short(plan.done, plan.due, plan.dropped, self.world.dt)
        change = self.lag.note(time.monotonic(), self.world.time, self.real_time_factor, short,
                               plan.dropped)
        self.keeping_up = not self.lag.behind
        if change == 'start':
            self.get_logger().warning(
                f'cannot keep up with real-time factor {self.real_time_factor:g}: '
                f'{len(self.world.state)} particles at dt = {self.world.dt:g} s; running '
                'slower than requested, dropping the backlog (status: dropped_backlog_s)')
        elif change == 'end':
            self.get_logger().info(f'keeping up again; {self.lag.dropped:g} s of simulated '
                                   'time were dropped while behind')
        self._publish_tick()

    def _tick(self) -> None:
        """Take the steps due (in slices), then publish every output somebody subscribes to."""
        self.ticks += 1
        if self.stepper.busy:
            self._outputs_due = True          # published when the slice ends
            return
        if self.ticks == 1:
            # Simulated time starts with the first tick, not at construction: the
            # start-up (interfaces, kernels from the cache) is no backlog to drop.
            self.pacer.restart(time.monotonic(), self.world.time)
        if self.paused or self.failed is not None:
            self._publish_tick()
            return
        start = time.monotonic()
        dropped = self.pacer.drop_backlog(start, self.world.time, 1.0 / self.publish_rate)
        self.plan = TickPlan(self.pacer.steps_due(start, self.world.time), dropped,
                             start + STEP_BUDGET / self.publish_rate)
        self._continue()

    def _publish_tick(self) -> None:
        """Measure the rates and publish the outputs of the state reached."""
        self._outputs_due = False
        self.meter.add(time.monotonic(), self.world.time, self._collisions())
        self.publish_outputs()

    def publish_outputs(self) -> None:
        """Publish the current state; all messages carry the same stamp and frame.

        A message is built only when somebody subscribes or the node records;
        the recording gets the bytes that are published. Particles go out in
        id order (a large world's rows are in spatial order: each array a
        message reads is sorted once per tick).
        """
        t, frame = self.world.time, self.frame_id
        state = functools.cache(lambda: InIdOrder(self.world.state))
        recorder = self.recorder if self.recorder is not None and self.recorder.active else None
        if self.publish_clock:
            clock = clock_bytes(t)
            self.pub_clock.publish(clock)
            if recorder is not None:
                recorder.write('clock', clock, t)
        for key, publisher in self.state_publishers.items():
            listened = publisher.get_subscription_count() > 0
            if listened or recorder is not None:
                data = FRAME_MESSAGES[key](state(), t, frame)
                if listened:
                    publisher.publish(data)
                if recorder is not None:
                    recorder.write(key, data, t)
        if self.pub_velocities.get_subscription_count():
            publish = self.pub_velocities.publish
            s = state()
            for message in velocities_bytes(s.ids, s.velocity, s.angular_velocity, t, frame):
                publish(message)
        self.reports.publish_collisions(self.world, t, frame)
        self._report_recording_error()

    def status(self) -> dict[str, Any]:
        """Return the node's status as a JSON-ready mapping."""
        report = status_report(self.world, self.scene.name, self.meter.rates(),
                               paused=self.paused, real_time_factor=self.real_time_factor,
                               keeping_up=self.keeping_up, publish_rate=self.publish_rate,
                               frame_id=self.frame_id, error=self.failed)
        report['dropped_backlog_s'] = self.pacer.dropped
        return report

    def _publish_status(self) -> None:
        """Publish the status on ``status`` (JSON), once the world is between slices."""
        self._status_due = False
        self.when_idle('status', self._send_status)

    def _send_status(self) -> None:
        """Build, publish and record the status now; note when, and what it cost."""
        start = time.perf_counter()
        data = string_bytes(json.dumps(self.status()))
        self.pub_status.publish(data)
        if self.recorder is not None:
            self.recorder.write('status', data, self.world.time)
            self._report_recording_error()
        self._status_sent = time.perf_counter()
        self._status_cost = self._status_sent - start

    def status_changed(self) -> None:
        """Have the status published after the command being handled (``flush_status``)."""
        self._status_due = True

    def flush_status(self) -> None:
        """Publish the status if a command changed the world since it last went out.

        At most STATUS_SHARE of the node's time goes to these statuses (one
        costs about 6 ms at 10,000 particles): one that would come sooner
        goes out when that share allows (a one-shot timer), so a burst of
        commands ends with a status of its last change.
        """
        if not self._status_due:
            return
        wait = self._status_sent + self._status_cost / STATUS_SHARE - time.perf_counter()
        if wait <= 0.0:
            self._status_flush.cancel()
            self._publish_status()
        elif self._status_flush.is_canceled():
            self._status_flush.timer_period_ns = max(1, int(wait * 1e9))
            self._status_flush.reset()

    def _on_status_flush(self) -> None:
        """One-shot timer: the status held back by STATUS_SHARE may go out now."""
        self._status_flush.cancel()
        self.flush_status()

    # -- recording (the bag itself is collision_node.recording) -----------

    @staticmethod
    def _record_target_check(path: str, action: Callable[[str], None]) -> None:
        """Run ``action(path)``; a path that cannot become a bag is a parameter error."""
        try:
            action(path)
        except BagTargetError as error:
            raise BagTargetError(f'parameter record: {path}: {error}') from None
        except OSError as error:
            raise BagTargetError(f'parameter record: {path}: {error.strerror or error}'
                                 ) from None

    def _start_recording(self, path: str) -> None:
        """Open the bag under the topics' resolved names; impacts are recorded from now on."""
        names = {key: publisher.topic_name for key, publisher in
                 [*self.state_publishers.items(), ('clock', self.pub_clock),
                  ('status', self.pub_status), ('collisions', self.reports.pub_collisions)]}
        self.recorder = Recorder(path, names)
        self.reports.recorder = self.recorder
        self.reports.follow_listeners(self.world)
        self.get_logger().info(f'recording into {path} (rosbag2, MCAP)')

    def _report_recording_error(self) -> None:
        """Log once that the recording stopped (a full disk); the node goes on."""
        recorder = self.recorder
        if recorder is not None and recorder.error is not None and not self.recording_reported:
            self.recording_reported = True
            self.get_logger().error(f'record {recorder.path}: {recorder.describe_error()}; '
                                    'the node goes on without recording')

    def close_recording(self) -> None:
        """Finish the bag (index, summary, metadata.yaml); say so, or why it could not."""
        recorder = self.recorder
        if recorder is None or recorder.bag.closed and recorder.error is None:
            return
        recorder.close()
        # After Ctrl-C or SIGTERM the context is gone, and with it /rosout: a logger
        # of its own logs to the console only.
        logger = rclpy.logging.get_logger(f'{self.get_logger().name}.recording')
        if recorder.error is None:
            logger.info(f'recorded {recorder.bag.message_count} messages into {recorder.path}')
        elif not self.recording_reported:
            self.recording_reported = True
            logger.error(f'record {recorder.path}: {recorder.describe_error()}')

    def destroy_node(self) -> None:
        """Finish the recording, then destroy the node."""
        self.close_recording()
        super().destroy_node()

    # -- commands (the topics and services are in commands.py) ------------

    def reset_world(self) -> str:
        """Return to the scene's initial state at time 0; return the log line (between slices)."""
        if self.step_request is not None:
            self._finish_step_request('reset')
        self.plan = None
        self.world.reset()
        self.failed = None
        now = time.monotonic()
        self.pacer.restart(now, self.world.time)
        self.lag.clear()
        self.meter.clear()
        self.meter.add(now, self.world.time, self._collisions())
        message = f'reset to {self.scene.name}: {len(self.world.state)} particles, time 0'
        self.get_logger().info(message)
        self._publish_status()
        return message


def main(args: Optional[list[str]] = None) -> int:
    """Run the node until Ctrl-C, SIGTERM or shutdown; 0 on a clean exit, 2 on bad set-up."""
    code = check_command_line(args)
    if code is not None:
        return code
    try:
        rclpy.init(args=args)
    except RCLError as error:
        # What check_command_line could not see (an environment rcl refuses).
        print(f'collision_node: error: cannot start ROS: {" ".join(str(error).split())[:300]}',
              file=sys.stderr)
        return 2
    node = None
    try:
        # Readers that free each request once taken (qos.py says why).
        with fastdds_profiles():
            node = CollisionNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (SceneError, ParameterException, NameValidationException, DefinitionError,
            BagTargetError) as error:
        # NameValidationException: a name rclpy refuses that rcl's parser let through.
        rclpy.logging.get_logger(NODE_NAME).error(' '.join(str(error).split()))
        return 2
    except MemoryError as error:
        doing = 'while starting' if node is None else 'in a callback'
        rclpy.logging.get_logger(NODE_NAME).error(out_of_memory(error, doing))
        return 2
    except Exception:
        # A signal during start-up shuts the context down under the
        # constructor; that is a requested exit, anything else is a bug.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.stepper.close(EXIT_WAIT)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
