"""The QoS profiles of the node's topics, in one place for the node and the viewer."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from typing import Iterator, Mapping

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
# Services (reset, pause): requests are kept until taken, so a burst of 500
# concurrent calls from one client is answered whole (the services default,
# keep last 10, answered 13 of 500). A client that sends such bursts needs a
# deep response queue too (this profile), or it drops its own answers.
SERVICE_QOS = COMMAND_QOS
# Status: the newest one, kept for late joiners (a viewer started later).
STATUS_QOS = reliable_qos(1, DurabilityPolicy.TRANSIENT_LOCAL)
# Impacts: every tick's batch counts (a listener prints each impact), so a few seconds' worth.
COLLISIONS_QOS = reliable_qos(100)
# /diagnostics: reliable keep last 10, as monitoring tools subscribe.
DIAGNOSTICS_QOS = reliable_qos(10)


# -- Fast DDS settings of the node's own process ------------------------------
#
# rmw_fastrtps gives every reader the history memory policy
# PREALLOCATED_WITH_REALLOC: a sample's buffer, once grown for a 1 MiB
# request, goes back to a pool that never shrinks, so a flood of large
# requests queued in a KEEP_ALL reader left the node 1.5 GiB larger for
# good. Every reader of the node takes requests (command topics and
# services), so the node's readers are DYNAMIC (a buffer per sample, freed
# when taken). With RMW_FASTRTPS_USE_QOS_FROM_XML=1 rmw_fastrtps takes the
# memory policy, publication mode and data sharing from the XML instead of
# its own defaults, so the profile restates those defaults for everything
# else (writers: PREALLOCATED_WITH_REALLOC, SYNCHRONOUS, data sharing off;
# readers: data sharing off). History, depth, reliability and durability
# still come from the profiles above: rmw applies the ROS QoS on top.
FASTDDS_PROFILES_XML = '''<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <data_writer profile_name="collision_node writers" is_default_profile="true">
      <qos>
        <publishMode><kind>SYNCHRONOUS</kind></publishMode>
        <data_sharing><kind>OFF</kind></data_sharing>
      </qos>
      <historyMemoryPolicy>PREALLOCATED_WITH_REALLOC</historyMemoryPolicy>
    </data_writer>
    <data_reader profile_name="collision_node readers" is_default_profile="true">
      <qos>
        <data_sharing><kind>OFF</kind></data_sharing>
      </qos>
      <historyMemoryPolicy>DYNAMIC</historyMemoryPolicy>
    </data_reader>
  </profiles>
</dds>
'''
# Settings by which a user configures the middleware; the node then leaves it alone.
MIDDLEWARE_SETTINGS = ('RMW_FASTRTPS_USE_QOS_FROM_XML', 'FASTRTPS_DEFAULT_PROFILES_FILE',
                       'FASTDDS_DEFAULT_PROFILES_FILE')


def own_fastdds_profiles(environ: Mapping[str, str]) -> bool:
    """Tell whether the node should load FASTDDS_PROFILES_XML in an environment.

    Only under rmw_fastrtps_cpp (the default) and only when the user has not
    configured Fast DDS through its own XML.
    """
    return (environ.get('RMW_IMPLEMENTATION', '') in ('', 'rmw_fastrtps_cpp')
            and not any(environ.get(name) for name in MIDDLEWARE_SETTINGS))


@contextmanager
def fastdds_profiles() -> Iterator[bool]:
    """Within this block, a new DDS participant of this process loads FASTDDS_PROFILES_XML.

    Create the node inside it: the participant reads the profile when it
    is created (rmw keeps its flag, Fast DDS the profiles); the file and
    the variables are gone afterwards. Yields whether the profile is used
    (see :func:`own_fastdds_profiles`).
    """
    if not own_fastdds_profiles(os.environ):
        yield False
        return
    with tempfile.NamedTemporaryFile('w', prefix='collision_node_fastdds_', suffix='.xml',
                                     delete=False) as profiles:
        profiles.write(FASTDDS_PROFILES_XML)
    os.environ.update(RMW_FASTRTPS_USE_QOS_FROM_XML='1',
                      FASTRTPS_DEFAULT_PROFILES_FILE=profiles.name)
    try:
        yield True
    finally:
        os.unlink(profiles.name)
        for name in ('RMW_FASTRTPS_USE_QOS_FROM_XML', 'FASTRTPS_DEFAULT_PROFILES_FILE'):
            os.environ.pop(name, None)
