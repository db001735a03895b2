"""The node's recording (parameter ``record``) and its parameters file, on a real node process.

The bag is read back by both readers (test/bag_check.py) and compared with
what a subscriber received and with the offline runner's run of the same
steps; its QoS and type hashes with what discovery reports of the node.
"""

from __future__ import annotations

import json
import resource
import signal
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from bag_check import check_bag, rosbag2_qos, stamp_ns, TYPES
from collision_node.simulate import main
from msg_adapters import impacts_from_point_cloud, state_from_point_cloud
from node_harness import NodeUnderTest, output, start, stop, unique_domain_id

# The recordings are ROS 2 messages; the node tests start the node.
pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parent.parent
PARAMETERS_FILE = ROOT / 'config' / 'collision_node.yaml'
STEPS = 600                  # oblique_pair (dt = 1 ms): the pair meets at 0.5 s
RELATIVE = {'clock': '/clock', 'poses': 'particles/poses', 'state': 'particles/state',
            'markers': 'particles/markers', 'collisions': 'particles/collisions',
            'status': 'status'}


def absolute(namespace: str) -> dict[str, str]:
    """Return the recorded topics' names for a node in ``namespace``."""
    return {key: name if name.startswith('/') else f'{namespace}/{name}'
            for key, name in RELATIVE.items()}


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_node_records_what_it_publishes(tmp_path, sig):
    bag, out = tmp_path / 'node_bag', tmp_path / 'runner.json'
    names = absolute('/sim')
    node = NodeUnderTest(['-p', 'scene:=oblique_pair', '-p', 'paused:=true',
                          '-p', f'record:={bag}'], namespace='/sim')
    try:
        # What rosbag2 would see of the node: the offered QoS and type hash of each publisher.
        infos = {key: node.probe.wait_for(
            lambda name=name: node.probe.node.get_publishers_info_by_topic(name))
            for key, name in names.items()}
        received: list[bytes] = []
        node.probe.node.create_subscription(PointCloud2, names['state'], received.append, 10,
                                            raw=True)
        answer = node.request(String, 'step', String(data=json.dumps({'steps': STEPS})))
        assert answer['accepted'], answer
        node.next_status(lambda s: s['steps'] == STEPS)
        # A subscriber's copy of the stepped state: the bag must hold these very bytes.
        node.probe.wait_for(lambda: any(
            stamp_ns(state_header(data)) == STEPS * 10 ** 6 for data in received))
    finally:
        code, _, err = node.stop(sig)
    assert code == 0, err
    assert 'recorded ' in err and f'messages into {bag}' in err
    assert 'ERROR' not in err
    offered = {key: [rosbag2_qos(info.qos_profile) for info in infos[key]] for key in names}
    for key, found in infos.items():
        assert [info.topic_type for info in found] == [TYPES[key]]
    messages, info = check_bag(bag, names, offered)
    for key, found in infos.items():
        topic = next(t['topic_metadata'] for t in info['topics_with_message_count']
                     if t['topic_metadata']['name'] == names[key])
        assert topic['type_description_hash'] == str(found[0].topic_type_hash)
    # One message of each state topic per tick, all stamped with the tick's simulated time.
    clock = [log for log, _, _ in messages['/clock']]
    assert [stamp_ns(m.clock) for _, _, m in messages['/clock']] == clock
    for key in ('poses', 'state', 'collisions'):
        assert [stamp_ns(m.header.stamp) for _, _, m in messages[names[key]]] == clock
    assert len(messages[names['markers']]) == len(clock)
    assert clock == sorted(clock) and clock[0] == 0 and clock[-1] == STEPS * 10 ** 6
    # The bytes a subscriber received are the bytes recorded (the middleware pads a
    # message to a multiple of 4 bytes on the wire).
    recorded = set(raw_state(bag, names['state']))
    for data in received:
        assert any(data[:len(r)] == r and data[len(r):] == bytes(-len(r) % 4)
                   for r in recorded)
    # The last state is the runner's after the same steps, bit for bit.
    assert main(['oblique_pair', '--quiet', '--steps', str(STEPS), '--out', str(out)]) == 0
    result = json.loads(out.read_text())
    state = state_from_point_cloud(messages[names['state']][-1][2])
    assert np.array_equal(state['position'], [p['position'] for p in result['particles']])
    assert np.array_equal(state['velocity'], [p['velocity'] for p in result['particles']])
    impacts = sum(len(impacts_from_point_cloud(m)['i'])
                  for _, _, m in messages[names['collisions']])
    assert impacts == result['stats']['collisions'] == 1
    statuses = [json.loads(m.data) for _, _, m in messages[names['status']]]
    assert statuses[0]['steps'] == 0 and statuses[-1]['steps'] == STEPS
    assert all(s['recording_impacts'] for s in statuses)


def state_header(data: bytes):
    """Return the header stamp of a serialised PointCloud2."""
    return deserialize_message(data, PointCloud2).header.stamp


def raw_state(bag: Path, topic: str) -> list[bytes]:
    """Return the serialised messages of ``topic`` as the MCAP file holds them."""
    with open(bag / f'{bag.name}_0.mcap', 'rb') as stream:
        return [message.data for _, _, message in make_reader(stream).iter_messages(
            topics=[topic])]


@pytest.mark.parametrize('target, says', [
    ('exists', 'File exists (a bag is never overwritten)'),
    ('missing/bag', 'No such file or directory ({tmp}/missing is not a directory)'),
], ids=['existing-folder', 'missing-parent'])
def test_node_refuses_a_record_target_at_start(tmp_path, target, says):
    (tmp_path / 'exists').mkdir()
    path = tmp_path / target
    process = start('collision_node', ['--ros-args', '-p', f'record:={path}'],
                    unique_domain_id())
    process.wait(timeout=60)
    code, out, err = stop(process)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith('[ERROR]') and lines[0].endswith(
        f'[collision_node]: parameter record: {path}: {says.format(tmp=tmp_path)}'), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['exists']


def test_node_full_disk_logs_one_error_and_goes_on(tmp_path):
    bag = tmp_path / 'bag'
    limit = 4 * 1024 * 1024

    def limit_file_size() -> None:
        # Python ignores SIGXFSZ: a write past the cap fails with EFBIG, as a full disk would.
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    # 10,000 particles: several MB of messages per tick, the cap is reached in a few ticks.
    node = NodeUnderTest(['-p', 'scene:=gas_10k', '-p', 'paused:=true', '-p', f'record:={bag}'],
                         preexec=limit_file_size)
    try:
        node.probe.wait_for(lambda: 'File too large' in output(node.process)[1], 60.0)
        # The node goes on: statuses keep coming, and it still answers a command.
        node.next_status()
        answer = node.request(String, 'step', String(data=json.dumps({'steps': 1})))
        assert answer['accepted'], answer
        node.next_status(lambda s: s['steps'] == 1)
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    errors = [line for line in err.splitlines() if '[ERROR]' in line]
    assert len(errors) == 1, err
    assert f'record {bag}: File too large (recording stopped at 0 s simulated); the node ' \
        'goes on without recording' in errors[0]
    assert not (bag / 'metadata.yaml').exists()


def test_node_starts_from_the_shipped_parameters_file(tmp_path):
    node = NodeUnderTest(['--params-file', str(PARAMETERS_FILE)])
    try:
        status = node.status()
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    assert (status['scene'], status['publish_rate'], status['real_time_factor'],
            status['frame_id'], status['paused']) == ('elastic_break', 30.0, 1.0, 'world', False)
    # The same file with values changed: each takes effect.
    edited = tmp_path / 'lab.yaml'
    text = PARAMETERS_FILE.read_text()
    for old, new in [('frame_id: world', 'frame_id: lab'), ('publish_rate: 30.0',
                                                            'publish_rate: 12.5'),
                     ('paused: false', 'paused: true'), ('scene: elastic_break',
                                                         'scene: cradle')]:
        assert text.count(old) == 1
        text = text.replace(old, new)
    edited.write_text(text)
    node = NodeUnderTest(['--params-file', str(edited)])
    try:
        status = node.status()
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    assert (status['scene'], status['publish_rate'], status['frame_id'], status['paused']) == \
        ('cradle', 12.5, 'lab', True)


def test_wildcard_parameters_file_reaches_the_node_in_any_namespace(tmp_path):
    wildcard = tmp_path / 'all_nodes.yaml'
    # An integer for a double parameter is taken as in -p real_time_factor:=2.
    wildcard.write_text('/**:\n  ros__parameters:\n    frame_id: wildcard_lab\n'
                        '    real_time_factor: 2\n')
    node = NodeUnderTest(['--params-file', str(wildcard)], namespace='/robot7')
    try:
        status = node.status()
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    assert status['frame_id'] == 'wildcard_lab' and status['real_time_factor'] == 2.0
