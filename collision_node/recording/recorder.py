"""Record what the node publishes into a rosbag2 bag, stamped with simulated time.

:data:`TOPICS` lists the recorded topics with their message types and the
QoS the node offers them with; :data:`FRAME_MESSAGES` builds a tick's state
messages with the same :mod:`msg_adapters` functions the node publishes, so
the bag holds the very bytes a subscriber receives. A :class:`Recorder`
writes them with log time = publish time = the simulated time of the
message in nanoseconds (the time ``/clock`` carries), as ``ros2 bag
record --use-sim-time`` would. A write that fails (a full disk) stops the
recording: :attr:`Recorder.error` says why, and everything after is dropped
while the simulation goes on.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional

from msg_adapters import (impact_cloud_bytes, marker_array_bytes, nanoseconds_from_seconds,
                          point_cloud_bytes, pose_array_bytes)

from .bag import BagWriter, offered_qos


@dataclass(frozen=True)
class RecordedTopic:
    """A topic of the node that a recording holds."""

    key: str            # short name used in code
    name: str           # the name the node creates it with (relative: under its namespace)
    type_name: str      # ROS 2 message type, pkg/msg/Name
    durability: str     # of the node's publisher (all are reliable), see ros/qos.py


TOPICS = (
    RecordedTopic('clock', '/clock', 'rosgraph_msgs/msg/Clock', 'volatile'),
    RecordedTopic('poses', 'particles/poses', 'geometry_msgs/msg/PoseArray', 'volatile'),
    RecordedTopic('state', 'particles/state', 'sensor_msgs/msg/PointCloud2', 'volatile'),
    RecordedTopic('markers', 'particles/markers', 'visualization_msgs/msg/MarkerArray',
                  'volatile'),
    RecordedTopic('collisions', 'particles/collisions', 'sensor_msgs/msg/PointCloud2',
                  'volatile'),
    RecordedTopic('status', 'status', 'std_msgs/msg/String', 'transient_local'),
)
TOPIC_KEYS = tuple(topic.key for topic in TOPICS)

# A tick's state messages: (particle state, simulated seconds, frame id) -> CDR bytes.
FRAME_MESSAGES: dict[str, Callable[[Any, float, str], bytes]] = {
    'poses': lambda s, t, frame: pose_array_bytes(s.position, s.orientation, t, frame),
    'state': lambda s, t, frame: point_cloud_bytes(s.ids, s.position, s.velocity, s.radius,
                                                   s.inv_mass, t, frame),
    'markers': lambda s, t, frame: marker_array_bytes(s.position, s.radius, s.inv_mass, t,
                                                      frame),
}


def default_names(namespace: str = '/') -> dict[str, str]:
    """Return each recorded topic's absolute name for a node in ``namespace``."""
    prefix = namespace.rstrip('/') + '/'
    return {topic.key: topic.name if topic.name.startswith('/') else prefix + topic.name
            for topic in TOPICS}


class Recorder:
    """One recording: open a bag, :meth:`write` messages by topic key, :meth:`close`.

    ``names`` maps every key of :data:`TOPICS` to the absolute topic name
    the bag uses (the node passes its resolved names, remappings included).
    Raises :class:`~.bag.BagTargetError` when the bag cannot be created.
    """

    def __init__(self, path: str, names: Optional[Mapping[str, str]] = None) -> None:
        """Create the bag and its topics."""
        names = default_names() if names is None else names
        self.path = path
        self.error: Optional[str] = None
        self.stopped_at: Optional[float] = None     # simulated s of the failed write
        self.bag = BagWriter(path)
        try:
            self.channels = {
                topic.key: self.bag.add_topic(names[topic.key], topic.type_name,
                                              [offered_qos('reliable', topic.durability)])
                for topic in TOPICS}
        except BaseException:
            self.bag.discard()
            raise

    @property
    def active(self) -> bool:
        """True until the recording is closed or a write failed."""
        return self.error is None and not self.bag.closed

    def write(self, key: str, data: bytes, seconds: float) -> None:
        """Write one message of topic ``key`` stamped ``seconds`` of simulated time."""
        if not self.active:
            return
        try:
            self.bag.write(self.channels[key], data, nanoseconds_from_seconds(seconds))
        except OSError as error:
            self._fail(error, seconds)

    def write_state(self, state: Any, seconds: float, frame_id: str) -> None:
        """Write the state messages of one tick (poses, state, markers)."""
        for key, build in FRAME_MESSAGES.items():
            if not self.active:
                return
            self.write(key, build(state, seconds, frame_id), seconds)

    def write_impacts(self, impacts: Any, seconds: float, frame_id: str) -> None:
        """Write the impacts taken this tick as ``particles/collisions``."""
        if self.active:
            self.write('collisions', impact_cloud_bytes(impacts, seconds, frame_id), seconds)

    def _fail(self, error: OSError, seconds: float) -> None:
        """Stop recording after a failed write; keep the bag's file as far as it got."""
        self.error = error.strerror or str(error)
        self.stopped_at = seconds
        self.bag.abandon()

    def close(self) -> Optional[str]:
        """Finish the bag (index, summary, metadata.yaml); return the error that stopped it."""
        if self.active:
            try:
                self.bag.close()
            except OSError as error:
                self.error = error.strerror or str(error)
                self.bag.abandon()
        return self.error

    def describe_error(self) -> str:
        """Return why the recording stopped, and where, as one phrase."""
        where = '' if self.stopped_at is None else \
            f' (recording stopped at {self.stopped_at:g} s simulated)'
        return f'{self.error}{where}'
