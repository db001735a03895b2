"""Read a recording back with two independent readers and check it is a rosbag2 bag.

``mcap_messages`` reads the MCAP file with the ``mcap`` package and turns
every message into its rclpy class with ``rclpy.serialization``;
``rosbags_messages`` opens the bag folder with ``rosbags``' rosbag2 reader
and decodes with a type store built only from the definitions in the bag.
``check_bag`` asserts what makes the folder the bag ``ros2 bag record -s
mcap`` writes, and that both readers see the same messages.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, get_types_from_msg, Stores

from collision_node.recording.definitions import message_definition, type_hash
from msg_adapters import records_from_point_cloud

METADATA_KEYS = ['version', 'storage_identifier', 'duration', 'starting_time', 'message_count',
                 'topics_with_message_count', 'compression_format', 'compression_mode',
                 'relative_file_paths', 'files', 'custom_data', 'ros_distro']
TYPES = {'clock': 'rosgraph_msgs/msg/Clock', 'poses': 'geometry_msgs/msg/PoseArray',
         'state': 'sensor_msgs/msg/PointCloud2', 'markers': 'visualization_msgs/msg/MarkerArray',
         'collisions': 'sensor_msgs/msg/PointCloud2', 'status': 'std_msgs/msg/String'}


def message_class(type_name: str) -> Any:
    """Return the rclpy message class of ``pkg/msg/Name``."""
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def mcap_file(bag: Path) -> Path:
    """Return the bag's one MCAP file, as metadata.yaml names it."""
    return bag / f'{bag.name}_0.mcap'


def mcap_messages(bag: Path) -> dict[str, list[tuple[int, int, Any]]]:
    """Return topic -> [(log time, publish time, rclpy message)] in file order."""
    found: dict[str, list[tuple[int, int, Any]]] = {}
    with open(mcap_file(bag), 'rb') as stream:
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=False):
            msg = deserialize_message(message.data, message_class(schema.name))
            found.setdefault(channel.topic, []).append(
                (message.log_time, message.publish_time, msg))
    return found


def rosbags_messages(bag: Path) -> dict[str, list[tuple[int, Any]]]:
    """Return topic -> [(timestamp, message)] read by rosbags from the bag's own definitions."""
    store = get_typestore(Stores.EMPTY)
    found: dict[str, list[tuple[int, Any]]] = {}
    with Reader(bag) as reader:
        for connection in reader.connections:
            assert connection.msgdef.format.name == 'MSG', connection
            store.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
        for connection, timestamp, raw in reader.messages():
            found.setdefault(connection.topic, []).append(
                (timestamp, store.deserialize_cdr(raw, connection.msgtype)))
    return found


def stamp_ns(stamp: Any) -> int:
    """Return a builtin_interfaces/Time (either reader's) as nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def cloud_records(msg: Any) -> np.ndarray:
    """Return a PointCloud2's points (either reader's message) as a structured array."""
    return records_from_point_cloud(msg)


def check_bag(bag: Path, names: dict[str, str],
              offered: dict[str, list[dict]]) -> tuple[dict[str, list], dict]:
    """Assert ``bag`` is a finished rosbag2 MCAP bag of the node's topics; return its messages.

    ``names`` maps topic keys to the absolute names expected, ``offered``
    maps keys to the offered QoS profiles expected (rosbag2's form).
    Returns the mcap reader's messages and the parsed metadata.yaml body.
    """
    assert sorted(p.name for p in bag.iterdir()) == sorted([mcap_file(bag).name,
                                                            'metadata.yaml'])
    document = yaml.safe_load((bag / 'metadata.yaml').read_text())
    info = document['rosbag2_bagfile_information']
    assert list(document) == ['rosbag2_bagfile_information']
    assert list(info) == METADATA_KEYS
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == [mcap_file(bag).name]
    assert info['compression_format'] == '' and info['compression_mode'] == ''
    by_name = {t['topic_metadata']['name']: t for t in info['topics_with_message_count']}
    assert sorted(by_name) == sorted(names.values())

    with open(mcap_file(bag), 'rb') as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        assert summary is not None, 'no summary: the MCAP file was not finished'
        # The file's rosbag2 metadata record ends as metadata.yaml's body.
        records = [m for m in reader.iter_metadata() if m.name == 'rosbag2']
        assert yaml.safe_load(records[-1].metadata['serialized_metadata']) == info
    assert summary.statistics.message_count == info['message_count']
    assert len(summary.chunk_indexes) >= 1        # indexed: chunks and message indexes
    channels = {c.topic: c for c in summary.channels.values()}
    assert sorted(channels) == sorted(names.values())
    for key, name in names.items():
        channel, topic = channels[name], by_name[name]['topic_metadata']
        schema = summary.schemas[channel.schema_id]
        assert schema.name == topic['type'] == TYPES[key]
        assert schema.encoding == 'ros2msg'
        assert schema.data.decode() == message_definition(TYPES[key])
        assert channel.message_encoding == 'cdr' == topic['serialization_format']
        assert yaml.safe_load(channel.metadata['offered_qos_profiles']) == offered[key]
        assert topic['offered_qos_profiles'] == offered[key]
        assert channel.metadata['topic_type_hash'] == topic['type_description_hash'] == \
            type_hash(TYPES[key])
        assert by_name[name]['message_count'] == \
            summary.statistics.channel_message_counts[channel.id]

    ours = mcap_messages(bag)
    theirs = rosbags_messages(bag)
    assert sorted(ours) == sorted(theirs) == sorted(
        name for name, topic in by_name.items() if topic['message_count'])
    for name in ours:
        assert len(ours[name]) == len(theirs[name]) == by_name[name]['message_count']
        # Log time is publish time, the simulated time of the message.
        assert [log for log, _, _ in ours[name]] == [t for t, _ in theirs[name]]
        assert all(log == publish for log, publish, _ in ours[name])
    log_times = [log for entries in ours.values() for log, _, _ in entries]
    assert info['starting_time']['nanoseconds_since_epoch'] == min(log_times)
    assert info['duration']['nanoseconds'] == max(log_times) - min(log_times)
    assert info['message_count'] == len(log_times) == info['files'][0]['message_count']
    # The two readers decode the same contents.
    clock, state = names['clock'], names['state']
    assert [stamp_ns(m.clock) for _, _, m in ours[clock]] == \
        [stamp_ns(m.clock) for _, m in theirs[clock]]
    for (_, _, a), (_, b) in zip(ours[state], theirs[state]):
        assert stamp_ns(a.header.stamp) == stamp_ns(b.header.stamp)
        assert cloud_records(a).tobytes() == cloud_records(b).tobytes()
    status = names['status']
    assert [m.data for _, _, m in ours[status]] == [m.data for _, m in theirs[status]]
    return ours, info


def rosbag2_qos(profile: Any) -> dict:
    """Return an rclpy QoS profile (as discovery reports it) in rosbag2's version-9 form."""
    def duration(value: Any) -> dict:
        sec, nsec = divmod(value.nanoseconds, 1_000_000_000)
        return {'sec': sec, 'nsec': nsec}
    history = {0: 'system_default', 1: 'keep_last', 2: 'keep_all', 3: 'unknown'}
    return {'history': history[int(profile.history)], 'depth': profile.depth,
            'reliability': profile.reliability.name.lower(),
            'durability': profile.durability.name.lower(),
            'deadline': duration(profile.deadline), 'lifespan': duration(profile.lifespan),
            'liveliness': profile.liveliness.name.lower(),
            'liveliness_lease_duration': duration(profile.liveliness_lease_duration),
            'avoid_ros_namespace_conventions': profile.avoid_ros_namespace_conventions}
