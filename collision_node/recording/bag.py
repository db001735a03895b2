"""A rosbag2 bag in MCAP storage, laid out as ``ros2 bag record -s mcap -o PATH`` writes it.

The bag is a new folder ``PATH`` holding ``PATH_0.mcap`` (the ``ros2``
MCAP profile: a ``ros2msg`` schema per message type, a ``cdr`` channel per
topic with its ``offered_qos_profiles`` and ``topic_type_hash``, chunked and
indexed, uncompressed as rosbag2's default) and, once the bag is closed,
``metadata.yaml`` (rosbag2 metadata version 9, as ROS 2 Jazzy writes it).
The MCAP file also holds that metadata as its ``rosbag2`` metadata record,
written when the bag is opened and again when it is closed, as rosbag2 does.

Messages are CDR bytes as a publisher sends them; times are integer
nanoseconds. Nothing here imports ROS: the type definitions come from
:mod:`.definitions`.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any, Optional

import yaml
from mcap import __version__ as MCAP_VERSION
from mcap.writer import CompressionType, Writer

from .definitions import message_definition, type_hash

METADATA_VERSION = 9          # rosbag2_storage BagMetadata in ROS 2 Jazzy
METADATA_FILE = 'metadata.yaml'
STORAGE_IDENTIFIER = 'mcap'
# The distribution whose interface packages the project pins (requirements.txt),
# unless the environment names one (rosbag2 writes ROS_DISTRO).
DEFAULT_ROS_DISTRO = 'jazzy'
CHUNK_SIZE = 768 * 1024       # bytes; rosbag2's MCAP writer default
# rmw's RMW_DURATION_INFINITE, as rosbag2 writes an unset deadline, lifespan or lease.
INFINITE_DURATION = {'sec': 9223372036, 'nsec': 854775807}
# rosbag2's starting time before any message (std::chrono::nanoseconds::max()).
NO_START = 2 ** 63 - 1


class BagTargetError(Exception):
    """A bag path that cannot be written; the message says why."""


def offered_qos(reliability: str, durability: str) -> dict[str, Any]:
    """Return a publisher's QoS as rosbag2 records it from discovery (version 9 form).

    Discovery does not carry history and depth, so rosbag2 sees them as
    ``unknown`` and 0; the node sets no deadline, lifespan or liveliness.
    """
    return {'history': 'unknown', 'depth': 0, 'reliability': reliability,
            'durability': durability, 'deadline': dict(INFINITE_DURATION),
            'lifespan': dict(INFINITE_DURATION), 'liveliness': 'automatic',
            'liveliness_lease_duration': dict(INFINITE_DURATION),
            'avoid_ros_namespace_conventions': False}


def check_target(path: str) -> None:
    """Raise :class:`BagTargetError` unless ``path`` can become a new bag folder.

    The folder is made and removed again (asking ``os.access`` says yes to
    root everywhere), so nothing is left behind before the run starts.
    """
    if path == '':
        raise BagTargetError('empty path')
    target = Path(path)
    if target.exists() or target.is_symlink():
        raise BagTargetError('File exists (a bag is never overwritten)')
    try:
        os.mkdir(target)
    except FileNotFoundError:
        raise BagTargetError(f'No such file or directory ({target.parent} is not a '
                             'directory)') from None
    except OSError as error:
        raise BagTargetError(error.strerror or str(error)) from None
    os.rmdir(target)


class _Dumper(yaml.SafeDumper):
    """YAML as yaml-cpp emits rosbag2's metadata: indented lists, ``""`` and ``~``."""

    def increase_indent(self, flow: bool = False, indentless: bool = False) -> None:
        return super().increase_indent(flow, False)


def _represent_str(dumper: yaml.SafeDumper, value: str) -> yaml.Node:
    style = '"' if value == '' else None
    return dumper.represent_scalar('tag:yaml.org,2002:str', value, style=style)


def _represent_none(dumper: yaml.SafeDumper, value: None) -> yaml.Node:
    return dumper.represent_scalar('tag:yaml.org,2002:null', '~')


_Dumper.add_representer(str, _represent_str)
_Dumper.add_representer(type(None), _represent_none)


def dump_yaml(document: Any) -> str:
    """Return ``document`` as block YAML in rosbag2's layout (keys in the given order)."""
    return yaml.dump(document, Dumper=_Dumper, sort_keys=False, default_flow_style=False,
                     width=float('inf'), allow_unicode=True)


class BagWriter:
    """Write one rosbag2 bag: :meth:`add_topic`, then :meth:`write` messages, then :meth:`close`.

    Write errors (``OSError``, e.g. a full disk) propagate; the caller
    decides what to do with a bag cut short (:meth:`abandon` drops the file).
    """

    def __init__(self, path: str) -> None:
        """Create the bag folder and its MCAP file; refuse a path that exists."""
        self.path = Path(path)
        try:
            os.mkdir(self.path)
        except OSError as error:
            raise BagTargetError(error.strerror or str(error)) from None
        self.file_name = f'{self.path.name}_0.mcap'
        self._file = open(self.path / self.file_name, 'xb')
        self._mcap = Writer(self._file, chunk_size=CHUNK_SIZE, compression=CompressionType.NONE)
        self._mcap.start(profile='ros2', library=f'collision_node (python mcap {MCAP_VERSION})')
        self._schemas: dict[str, int] = {}
        # Channel id -> rosbag2 topic metadata, and messages written on it.
        self._topics: dict[int, dict[str, Any]] = {}
        self._counts: dict[int, int] = {}
        self._start = NO_START
        self._end = 0
        self.closed = False
        self._mcap.add_metadata('rosbag2', {'serialized_metadata': dump_yaml(self.metadata())})

    @property
    def message_count(self) -> int:
        """Messages written so far."""
        return sum(self._counts.values())

    def add_topic(self, name: str, type_name: str, offered_qos_profiles: list[dict]) -> int:
        """Add a topic (an absolute name) of a message type; return its channel id."""
        if type_name not in self._schemas:
            text = message_definition(type_name)
            self._schemas[type_name] = self._mcap.register_schema(
                name=type_name, encoding='ros2msg', data=text.encode('utf-8'))
        topic = {'name': name, 'type': type_name, 'serialization_format': 'cdr',
                 'offered_qos_profiles': offered_qos_profiles,
                 'type_description_hash': type_hash(type_name)}
        channel = self._mcap.register_channel(
            topic=name, message_encoding='cdr', schema_id=self._schemas[type_name],
            metadata={'offered_qos_profiles': dump_yaml(offered_qos_profiles),
                      'topic_type_hash': topic['type_description_hash']})
        self._topics[channel] = topic
        self._counts[channel] = 0
        return channel

    def write(self, channel: int, data: bytes, log_time: int,
              publish_time: Optional[int] = None) -> None:
        """Write one serialised message; times in integer nanoseconds."""
        publish_time = log_time if publish_time is None else publish_time
        self._mcap.add_message(channel_id=channel, log_time=log_time, data=data,
                               publish_time=publish_time, sequence=0)
        self._counts[channel] += 1
        self._start = min(self._start, log_time)
        self._end = max(self._end, log_time)

    def metadata(self) -> dict[str, Any]:
        """Return the bag's rosbag2 metadata, the body of ``metadata.yaml``."""
        count = self.message_count
        duration = {'nanoseconds': self._end - self._start if count else 0}
        start = {'nanoseconds_since_epoch': self._start}
        return {
            'version': METADATA_VERSION,
            'storage_identifier': STORAGE_IDENTIFIER,
            'duration': duration,
            'starting_time': start,
            'message_count': count,
            'topics_with_message_count': [
                {'topic_metadata': topic, 'message_count': self._counts[channel]}
                for channel, topic in self._topics.items()],
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [self.file_name],
            'files': [{'path': self.file_name, 'starting_time': dict(start),
                       'duration': dict(duration), 'message_count': count}],
            'custom_data': None,
            'ros_distro': os.environ.get('ROS_DISTRO') or DEFAULT_ROS_DISTRO,
        }

    def close(self) -> None:
        """Write the summary and indexes, close the file, then write ``metadata.yaml``."""
        if self.closed:
            return
        self.closed = True
        try:
            document = self.metadata()
            self._mcap.add_metadata('rosbag2', {'serialized_metadata': dump_yaml(document)})
            self._mcap.finish()
        finally:
            self._file.close()
        with open(self.path / METADATA_FILE, 'x', encoding='utf-8') as handle:
            handle.write(dump_yaml({'rosbag2_bagfile_information': document}))

    def abandon(self) -> None:
        """Close the file without finishing it (after a write failed); keep what it holds."""
        if self.closed:
            return
        self.closed = True
        try:
            self._file.close()
        except OSError:
            pass          # the buffered rest cannot be written either

    def discard(self) -> None:
        """Remove the bag folder again (set-up failed before anything was recorded)."""
        self.abandon()
        shutil.rmtree(self.path, ignore_errors=True)
