"""The node's reports beside its state: ``/diagnostics`` and ``particles/collisions``.

Both are built only while somebody subscribes. The impacts cost the physics
something to record, so recording is switched on when the first subscriber
of ``particles/collisions`` appears and off when the last one leaves
(``World.record_impacts``); each tick then publishes the impacts resolved
since the previous one. A recording of the node (``recorder``) counts as a
listener: it gets the same bytes.
"""

from __future__ import annotations

from typing import Any, Callable, Optional

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2

from msg_adapters import impact_cloud_bytes

from ..physics.step.world import World
from ..recording.recorder import Recorder
from .diagnostics import diagnostic_array
from .qos import COLLISIONS_QOS, DIAGNOSTICS_QOS

DIAGNOSTICS_PERIOD = 1.0     # s of wall time between /diagnostics messages


class Reports:
    """Publishers and timer of the reports; the node calls ``publish_collisions`` each tick."""

    def __init__(self, node: Node, status: Callable[[], dict[str, Any]], steady: Clock,
                 when_idle: Optional[Callable[[str, Callable[[], None]], None]] = None) -> None:
        """Create the publishers on ``node`` and the 1 Hz diagnostics timer on ``steady``.

        ``when_idle(key, work)`` runs work that reads the world once no step
        is in flight (the node's ``when_idle``); without it, at once.
        """
        self.node = node
        self.when_idle = when_idle or (lambda key, work: work())
        self.status = status
        self.name = f'{node.get_fully_qualified_name().lstrip("/")}: simulation'
        self.pub_diagnostics = node.create_publisher(DiagnosticArray, '/diagnostics',
                                                     DIAGNOSTICS_QOS)
        self.pub_collisions = node.create_publisher(PointCloud2, 'particles/collisions',
                                                    COLLISIONS_QOS)
        self.timer = node.create_timer(
            DIAGNOSTICS_PERIOD, lambda: self.when_idle('diagnostics', self.publish_diagnostics),
            clock=steady)
        self.recorder: Optional[Recorder] = None

    def publish_diagnostics(self) -> None:
        """Publish the node's health on /diagnostics, stamped with the node's clock."""
        if self.pub_diagnostics.get_subscription_count():
            self.pub_diagnostics.publish(diagnostic_array(
                self.status(), self.name, self.node.get_clock().now().to_msg()))

    def publish_collisions(self, world: World, seconds: float, frame_id: str) -> None:
        """Publish the impacts since the last tick; have them recorded only while listened to."""
        if world.impact_log is not None:
            impacts = world.take_impacts()
            listened = self.pub_collisions.get_subscription_count() > 0
            if listened or self._recording():
                data = impact_cloud_bytes(impacts, seconds, frame_id)
                if listened:
                    self.pub_collisions.publish(data)
                if self._recording():
                    self.recorder.write('collisions', data, seconds)
        self.follow_listeners(world)

    def _recording(self) -> bool:
        """Tell whether the node's recording takes the impacts."""
        return self.recorder is not None and self.recorder.active

    def follow_listeners(self, world: World) -> None:
        """Record impacts iff somebody subscribes or the node records (also before a step)."""
        listening = self.pub_collisions.get_subscription_count() > 0 or self._recording()
        if listening != (world.impact_log is not None):
            world.record_impacts(listening)
