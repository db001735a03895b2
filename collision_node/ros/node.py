"""The collision_node ROS 2 node: a live particle world on topics.

The node owns timing and ROS I/O only: the physics is a core
:class:`~collision_node.physics.step.world.World`, and every numpy-to-message
conversion lives in :mod:`msg_adapters`. Topics, QoS and parameters are
tabled in docs/node.md.
"""

from __future__ import annotations

import json
import sys
import time
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

from ..physics.model.accuracy import parse_accuracy_text
from ..physics.step.kernels import prepare as prepare_kernels
from ..physics.model.scene import load_scene
from ..physics.model.validation import SceneError
from ..physics.step.world import NonFiniteStateError, World
from ..recording.bag import BagTargetError, check_target
from ..recording.definitions import DefinitionError
from ..recording.recorder import FRAME_MESSAGES, Recorder
from .cli import check_command_line
from .commands import CommandInterface, out_of_memory
from .pacing import Lag, Pacer, RateMeter, STEP_BUDGET
from .parameters import (as_double, DEFAULT_SCENE, integers_as_doubles, invalid_parameter,
                         PARAMETERS)
from .qos import fastdds_profiles, STATE_QOS, STATUS_QOS, VELOCITY_QOS
from .reports import Reports
from .status import status_report

NODE_NAME = 'collision_node'
RCLError = _rclpy.RCLError
STATUS_PERIOD = 0.5          # s of wall time between status messages


class CollisionNode(Node):
    """Steps a world in (scaled) real time and publishes it; takes commands (commands.py)."""

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
        self.world = World(self.scene, max_particles=value['max_particles'])
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
        self.reports = Reports(self, self.status, self.steady)   # /diagnostics, collisions
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
        """Apply accepted runtime changes from the next tick on."""
        now = time.monotonic()
        for p in parameters:
            if p.name == 'real_time_factor':
                self.real_time_factor = p.value
                self.pacer.factor = p.value
                self.pacer.restart(now, self.world.time)
                self.lag.clear()
                self.keeping_up = True
            elif p.name == 'publish_rate':
                self.publish_rate = p.value
                # The new period counts from now: without the reset the next
                # tick would still come a whole old period (up to 10 s) later.
                self.tick_timer.timer_period_ns = int(1e9 / p.value)
                self.tick_timer.reset()
            elif p.name == 'paused':
                self.paused = p.value
                self.pacer.restart(now, self.world.time)
                self.lag.clear()
            elif p.name == 'publish_clock':
                self.publish_clock = p.value
            elif p.name == 'frame_id':
                self.frame_id = p.value
            self.get_logger().info(f'parameter {p.name} = {p.value!r}')
        self._publish_status()

    # -- stepping and publishing ------------------------------------------

    def _collisions(self) -> int:
        """Particle and wall collisions so far."""
        return self.world.stats.collisions + self.world.stats.wall_collisions

    def _advance(self) -> None:
        """Take the steps due within this tick's budget; drop a backlog, never run ahead."""
        start = time.monotonic()
        dropped = self.pacer.drop_backlog(start, self.world.time, 1.0 / self.publish_rate)
        due = self.pacer.steps_due(start, self.world.time)
        deadline = start + STEP_BUDGET / self.publish_rate
        done = 0
        try:
            while done < due:
                self.world.step(1)
                done += 1
                if done < due and time.monotonic() > deadline:
                    break
        except NonFiniteStateError as error:
            self.failed = str(error)
            self.get_logger().error(f'stopped stepping: {error}; reset to go on')
            return
        except MemoryError as error:
            # The step may be half done: stop stepping (status error, an ERROR
            # diagnostic) until a reset, as on a non-finite state.
            self.failed = out_of_memory(error, f'in step {self.world.steps + 1}')
            self.get_logger().error(f'stopped stepping: {self.failed}; reset to go on')
            return
        # Behind: the physics could not do what was due, or a late tick cost more
        # than a step (less is scheduler jitter: dropped and counted, not a lag).
        behind = done < due or dropped > self.world.dt
        change = self.lag.note(time.monotonic(), behind, dropped)
        self.keeping_up = not self.lag.behind
        if change == 'start':
            self.get_logger().warning(
                f'cannot keep up with real-time factor {self.real_time_factor:g}: '
                f'{len(self.world.state)} particles at dt = {self.world.dt:g} s; running '
                'slower than requested, dropping the backlog (status: dropped_backlog_s)')
        elif change == 'end':
            self.get_logger().info(f'keeping up again; {self.lag.dropped:g} s of simulated '
                                   'time were dropped while behind')

    def _tick(self) -> None:
        """Step, then publish every output somebody subscribes to."""
        if self.ticks == 0:
            # Simulated time starts with the first tick, not at construction: the
            # start-up (interfaces, kernels from the cache) is no backlog to drop.
            self.pacer.restart(time.monotonic(), self.world.time)
        self.ticks += 1
        if not self.paused and self.failed is None:
            self._advance()
        self.meter.add(time.monotonic(), self.world.time, self._collisions())
        self.publish_outputs()

    def publish_outputs(self) -> None:
        """Publish the current state; all messages carry the same stamp and frame.

        A message is built only when somebody subscribes or the node records;
        the recording gets the bytes that are published.
        """
        s, t, frame = self.world.state, self.world.time, self.frame_id
        recorder = self.recorder if self.recorder is not None and self.recorder.active else None
        if self.publish_clock:
            clock = clock_bytes(t)
            self.pub_clock.publish(clock)
            if recorder is not None:
                recorder.write('clock', clock, t)
        for key, publisher in self.state_publishers.items():
            listened = publisher.get_subscription_count() > 0
            if listened or recorder is not None:
                data = FRAME_MESSAGES[key](s, t, frame)
                if listened:
                    publisher.publish(data)
                if recorder is not None:
                    recorder.write(key, data, t)
        if self.pub_velocities.get_subscription_count():
            publish = self.pub_velocities.publish
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
        """Publish the status on ``status`` (JSON), and record it."""
        data = string_bytes(json.dumps(self.status()))
        self.pub_status.publish(data)
        if self.recorder is not None:
            self.recorder.write('status', data, self.world.time)
            self._report_recording_error()

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
        """Return to the scene's initial state at time 0; return the log line."""
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
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
