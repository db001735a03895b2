"""Recordings of the offline runner (``simulate --record``) and the bag format they share.

Every bag is read back by two independent readers (test/bag_check.py): the
``mcap`` reader with rclpy's ``deserialize_message``, and ``rosbags``'
rosbag2 reader with a type store built from the bag's own definitions.
"""

from __future__ import annotations

import json
import math
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, LivelinessPolicy, QoSProfile

from bag_check import check_bag, cloud_records, mcap_messages, rosbag2_qos, stamp_ns
from collision_node.recording.definitions import (dependencies, message_definition,
                                                  SEPARATOR, share_directory, type_hash)
from collision_node.recording.definitions import ament_prefixes
from collision_node.recording.recorder import default_names
from collision_node.ros.parameters import PARAMETERS
from collision_node.ros.qos import COLLISIONS_QOS, STATE_QOS, STATUS_QOS
from collision_node.simulate import main
from msg_adapters import impacts_from_point_cloud, state_from_point_cloud
from test_runner import wait_for_output

# The recordings are ROS 2 messages; the node tests start the node.
pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parent.parent
NODE_QOS = {'clock': STATE_QOS, 'poses': STATE_QOS, 'state': STATE_QOS, 'markers': STATE_QOS,
            'collisions': COLLISIONS_QOS, 'status': STATUS_QOS}
INFINITE = Duration(nanoseconds=2 ** 63 - 1)


def discovered(profile: QoSProfile) -> QoSProfile:
    """Return a publisher's profile as discovery reports it (test_node_recording checks that).

    History and depth do not travel; the system defaults arrive resolved
    (automatic liveliness, no deadline, lifespan or lease).
    """
    return QoSProfile(history=HistoryPolicy.UNKNOWN, depth=0, reliability=profile.reliability,
                      durability=profile.durability, deadline=INFINITE, lifespan=INFINITE,
                      liveliness=LivelinessPolicy.AUTOMATIC, liveliness_lease_duration=INFINITE)


# What rosbag2 records for the node's publishers (one publisher per topic).
OFFERED = {key: [rosbag2_qos(discovered(profile))] for key, profile in NODE_QOS.items()}


def particles(result: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ids, positions and velocities of a run's JSON."""
    records = result['particles']
    return (np.array([p['id'] for p in records]), np.array([p['position'] for p in records]),
            np.array([p['velocity'] for p in records]))


def assert_state_is_json(msg, result: dict) -> None:
    """Assert a ``particles/state`` message holds exactly the JSON's final state."""
    state = state_from_point_cloud(msg)
    ids, position, velocity = particles(result)
    assert np.array_equal(state['ids'], ids)
    assert np.array_equal(state['position'], position)     # bit for bit
    assert np.array_equal(state['velocity'], velocity)


# -- definitions ----------------------------------------------------------------


def test_definitions_are_rosbag2s_full_text_from_the_installed_files():
    text = message_definition('geometry_msgs/msg/PoseArray')
    sections = text.split(f'\n{SEPARATOR}\n')
    prefixes = ament_prefixes()

    def source(name):
        package, _, type_name = name.rpartition('/')
        package = package.split('/')[0]
        return (share_directory(package, prefixes) / 'msg' / f'{type_name}.msg').read_text()
    assert sections[0] == source('geometry_msgs/PoseArray')
    # Dependencies sorted, depth first, each once: Pose (Point, Quaternion), then Header (Time).
    headers = [s.split('\n', 1)[0] for s in sections[1:]]
    assert headers == ['MSG: geometry_msgs/Pose', 'MSG: geometry_msgs/Point',
                       'MSG: geometry_msgs/Quaternion', 'MSG: std_msgs/Header',
                       'MSG: builtin_interfaces/Time']
    for header, section in zip(headers, sections[1:]):
        assert section.split('\n', 1)[1] == source(header[len('MSG: '):])
    # Every type MarkerArray needs is defined exactly once.
    marker = message_definition('visualization_msgs/msg/MarkerArray')
    names = [line[len('MSG: '):] for line in marker.splitlines() if line.startswith('MSG: ')]
    assert len(names) == len(set(names))
    assert {'visualization_msgs/Marker', 'sensor_msgs/CompressedImage',
            'visualization_msgs/MeshFile', 'builtin_interfaces/Duration'} <= set(names)
    assert message_definition('std_msgs/msg/String') == source('std_msgs/String')


def test_dependency_scan_reads_field_types_only():
    text = ('# Header header is a comment\nint32 ARROW=0\nHeader header\n'
            'geometry_msgs/Point[] points\nstring<=8 name\nuint8[4] raw\n')
    assert dependencies(text, 'std_msgs') == ['geometry_msgs/Point', 'std_msgs/Header']


def test_type_hashes_are_rosidls():
    # The hashes rclpy reports for these types on the wire (RIHS01, ROS 2 Jazzy).
    assert type_hash('std_msgs/msg/String') == \
        'RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18'
    assert type_hash('rosgraph_msgs/msg/Clock') == \
        'RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564'


# -- the runner's recordings -----------------------------------------------------


def test_runner_recording_is_the_run(tmp_path):
    bag, out, plain = tmp_path / 'break', tmp_path / 'out.json', tmp_path / 'plain.json'
    assert main(['elastic_break', '--quiet', '--duration', '1', '--record', str(bag),
                 '--out', str(out)]) == 0
    result = json.loads(out.read_text())
    messages, info = check_bag(bag, default_names(), OFFERED)
    names = default_names()
    assert names['state'] == '/particles/state' and names['clock'] == '/clock'
    # 30 frames per simulated second from time 0 on: 1 s holds 31 of every topic.
    counts = {key: len(messages[name]) for key, name in names.items()}
    assert counts == dict.fromkeys(names, 1.0 * 30 + 1)
    # Frame k at the first step reaching k/30 s (dt = 1/240: exactly 8 steps apart).
    dt = 0.004166666666666667
    clock = [log for log, _, _ in messages['/clock']]
    assert clock == [round(8 * k * dt * 1e9) for k in range(31)]
    # /clock carries the log time; every message of a frame is stamped with it.
    assert [stamp_ns(m.clock) for _, _, m in messages['/clock']] == clock
    for key in ('poses', 'state', 'collisions'):
        assert [stamp_ns(m.header.stamp) for _, _, m in messages[names[key]]] == clock
    for (log, _, array) in messages['/particles/markers']:
        assert {stamp_ns(m.header.stamp) for m in array.markers} == {log}
    assert info['duration']['nanoseconds'] == 10 ** 9
    assert info['starting_time']['nanoseconds_since_epoch'] == 0
    # The last frame is the final state of the JSON, bit for bit.
    assert_state_is_json(messages['/particles/state'][-1][2], result)
    assert len(messages['/particles/poses'][-1][2].poses) == 16
    # Every impact is in the bag once, each in the frame after it happened.
    impacts = 0
    previous = -1
    for log, _, msg in messages['/particles/collisions']:
        found = impacts_from_point_cloud(msg)
        assert np.all((found['time'] * 1e9 > previous - 1) & (found['time'] * 1e9 <= log + 1))
        impacts += len(found['i'])
        previous = log
    assert impacts == result['stats']['collisions'] + result['stats']['wall_collisions'] == 33
    status = [json.loads(m.data) for _, _, m in messages['/status']]
    assert [s['steps'] for s in status] == [8 * k for k in range(31)]
    assert status[-1]['steps'] == result['steps'] == 240
    assert status[-1]['energy'] == result['stats']['energy']['end']
    assert set(status[-1]) >= {'scene', 'particles', 'collisions', 'publish_rate', 'frame_id'}
    # Recording changes nothing of the run.
    assert main(['elastic_break', '--quiet', '--duration', '1', '--out', str(plain)]) == 0
    assert json.loads(plain.read_text())['particles'] == result['particles']


@pytest.mark.parametrize('duration, frames', [(0.5, 7), (0.55, 8)])
def test_record_rate_sets_the_frames_and_the_final_state_is_last(tmp_path, duration, frames):
    """12 Hz: floor(12 x duration) + 1 frames, and the final state if it falls between."""
    bag, out = tmp_path / 'bag', tmp_path / 'out.json'
    assert main(['elastic_break', '--quiet', '--duration', str(duration), '--record',
                 str(bag), '--record-rate', '12', '--out', str(out)]) == 0
    result = json.loads(out.read_text())
    messages, _ = check_bag(bag, default_names(), OFFERED)
    steps = [round(k * 20) for k in range(math.floor(duration * 12 + 1e-9) + 1)]
    if steps[-1] != result['steps']:
        steps.append(result['steps'])
    assert len(steps) == frames
    dt = 0.004166666666666667
    assert [log for log, _, _ in messages['/clock']] == [round(n * dt * 1e9) for n in steps]
    assert json.loads(messages['/status'][-1][2].data)['publish_rate'] == 12.0
    assert_state_is_json(messages['/particles/state'][-1][2], result)


@pytest.mark.parametrize('target, says', [
    ('exists', 'File exists (a bag is never overwritten)'),
    ('file', 'File exists (a bag is never overwritten)'),
    ('missing/bag', 'No such file or directory ({tmp}/missing is not a directory)'),
    ('file/bag', 'Not a directory'),
    # /sys takes no new folder, not even from root.
    ('/sys/collision_node_test_bag', ('Operation not permitted', 'Permission denied')),
], ids=['existing-folder', 'existing-file', 'missing-parent', 'parent-is-a-file',
        'not-writable'])
def test_bad_record_target_is_refused_before_the_run(tmp_path, capsys, target, says):
    (tmp_path / 'exists').mkdir()
    (tmp_path / 'file').write_text('kept\n')
    path = target if target.startswith('/') else str(tmp_path / target)
    before = sorted(p.name for p in tmp_path.iterdir())
    out = tmp_path / 'out.json'
    assert main(['oblique_pair', '--steps', '5', '--record', path, '--out', str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ''          # no step was run: no summary
    accepted = says if isinstance(says, tuple) else (says,)
    assert captured.err.splitlines() in [
        [f'simulate: error: --record {path}: {text.format(tmp=tmp_path)}'] for text in accepted]
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert (tmp_path / 'file').read_text() == 'kept\n' and not os.path.exists(path + '_0')


@pytest.mark.parametrize('args, says', [
    (['--record-rate', '10'], '--record-rate needs --record PATH'),
    (['--record', 'BAG', '--record-rate', '0'], '--record-rate must be a finite number > 0'),
    (['--record', 'BAG', '--record-rate', 'nan'], '--record-rate must be a finite number > 0'),
    (['--record', 'BAG', '--record-rate', 'inf'], '--record-rate must be a finite number > 0'),
])
def test_bad_record_rate_is_refused(tmp_path, capsys, args, says):
    args = [str(tmp_path / 'bag') if a == 'BAG' else a for a in args]
    assert main(['oblique_pair', '--steps', '5', *args]) == 2
    line, = capsys.readouterr().err.splitlines()
    assert line.startswith(f'simulate: error: {says}')
    assert not (tmp_path / 'bag').exists()


def test_explain_records_nothing(tmp_path, capsys):
    assert main(['oblique_pair', '--explain', '--record', str(tmp_path / 'bag')]) == 0
    assert not (tmp_path / 'bag').exists()


def limit_file_size(limit: int):
    """Return a pre-exec function that caps every file the child writes at ``limit`` bytes.

    Python ignores SIGXFSZ, so a write past the cap fails with EFBIG ("File
    too large"), as a write to a full disk fails with ENOSPC.
    """
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_full_disk_stops_the_recording_and_the_run_goes_on(tmp_path):
    bag, out, plain = tmp_path / 'bag', tmp_path / 'out.json', tmp_path / 'plain.json'
    # The run without a recording (which also leaves the compiled kernels cached for the child).
    assert main(['elastic_break', '--quiet', '--out', str(plain)]) == 0
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    # 10 s of the break make about 1.8 MB of bag; the first 768 KiB chunk cannot be written.
    done = subprocess.run([sys.executable, '-m', 'collision_node.simulate', 'elastic_break',
                           '--record', str(bag), '--out', str(out)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120,
                          preexec_fn=limit_file_size(256 * 1024))
    assert done.returncode == 2, done.stderr
    assert done.stdout.startswith('elastic_break: 16 particles, 2400 steps (10 s simulated)')
    # stderr may hold the progress bar's carriage-return lines; one error line, the last.
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith('simulate:')]
    assert len(errors) == 1 and errors[0] == lines[-1], done.stderr
    line = errors[0]
    prefix = f'simulate: error: --record {bag}: File too large (recording stopped at '
    assert line.startswith(prefix) and line.endswith(' s simulated)'), line
    stopped = float(line[len(prefix):].split()[0])
    assert 0 < stopped < 10
    # The run went on to the end: its JSON is that of a run without a recording.
    assert json.loads(out.read_text())['particles'] == json.loads(plain.read_text())['particles']
    assert not (bag / 'metadata.yaml').exists()   # the bag stops where the write failed


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_leaves_a_finished_bag(tmp_path, sig):
    bag, out = tmp_path / 'bag', tmp_path / 'partial.json'
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    process = subprocess.Popen(
        [sys.executable, '-m', 'collision_node.simulate', 'oblique_pair', '--steps',
         str(10 ** 8), '--record', str(bag), '--record-rate', '100', '--out', str(out)],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_for_output(process, b'step/s')         # the progress bar: stepping has begun
        process.send_signal(sig)
        _, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, stderr
    assert b'simulate: error' not in stderr and b'Traceback' not in stderr
    result = json.loads(out.read_text())
    messages, info = check_bag(bag, default_names(), OFFERED)
    assert_state_is_json(messages['/particles/state'][-1][2], result)
    # dt = 1 ms, 100 Hz: a frame every 10 steps from 0, then the state the run stopped in.
    steps = result['steps']
    expected = list(range(0, steps + 1, 10)) + ([steps] if steps % 10 else [])
    assert [log for log, _, _ in messages['/clock']] == [n * 10 ** 6 for n in expected]
    assert info['duration']['nanoseconds'] == steps * 10 ** 6


def test_recorded_state_decodes_the_same_in_both_readers(tmp_path):
    """The ids, radii and masses of a frame survive the round trip (static mass: inf)."""
    scene = tmp_path / 'pair.yaml'
    scene.write_text('name: pair\ndt: 0.01\nduration: 0.1\nparticles:\n'
                     '  - {position: [-1, 0, 0], velocity: [2, 0, 0], radius: 0.5, mass: 1}\n'
                     '  - {position: [0, 5, 0], radius: 0.25, mass: .inf}\n')
    bag = tmp_path / 'pair_bag'
    assert main([str(scene), '--quiet', '--record', str(bag)]) == 0
    messages, _ = check_bag(bag, default_names(), OFFERED)
    records = cloud_records(messages['/particles/state'][0][2])
    assert records['id'].tolist() == [0, 1]
    assert records['radius'].tolist() == [0.5, 0.25]
    assert records['mass'][0] == 1.0 and math.isinf(records['mass'][1])
    assert (bag / 'pair_bag_0.mcap').is_file()
    assert mcap_messages(bag)['/clock'][-1][0] == 10 ** 8


# -- the parameters file -------------------------------------------------------


def test_parameters_file_lists_every_parameter_with_its_default():
    document = yaml.safe_load((ROOT / 'config' / 'collision_node.yaml').read_text())
    assert list(document) == ['collision_node']
    assert list(document['collision_node']) == ['ros__parameters']
    values = document['collision_node']['ros__parameters']
    assert list(values) == list(PARAMETERS)
    for name, (default, _) in PARAMETERS.items():
        assert values[name] == default and type(values[name]) is type(default), name
