"""The QoS profiles of the node's topics, in one place for the node and the viewer."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def reliable_qos(depth: int, durability: DurabilityPolicy = DurabilityPolicy.VOLATILE
                 ) -> QoSProfile:
    """Return a reliable keep-last profile (a best-effort publisher reaches no default sub)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE, durability=durability)


# State streams: keep only the newest tick; a late tick is worth less than the next one.
STATE_QOS = reliable_qos(1)
# Velocities: one message per particle per tick, so the queue holds a tick's burst.
VELOCITY_QOS = reliable_qos(1000)
# Commands: keep every request until the node has taken it (a burst of
# 10,000 spawns from one publisher all land; reliable flow control holds the
# rest at the sender while the node's queue is full).
COMMAND_QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
# Answers: none may be dropped by the node either.
EVENTS_QOS = COMMAND_QOS
# Status: the newest one, kept for late joiners (a viewer started later).
STATUS_QOS = reliable_qos(1, DurabilityPolicy.TRANSIENT_LOCAL)
# Impacts: every tick's batch counts (a listener prints each impact), so a few seconds' worth.
COLLISIONS_QOS = reliable_qos(100)
# /diagnostics: reliable keep last 10, as monitoring tools subscribe.
DIAGNOSTICS_QOS = reliable_qos(10)
