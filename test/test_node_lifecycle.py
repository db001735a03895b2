"""The installed executables as a user runs them: scene files, signals, the viewer."""

from __future__ import annotations

import signal
import subprocess

import matplotlib.image
import pytest

from node_harness import NodeUnderTest, executable, ros_env, unique_domain_id

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros


def run_viewer(domain_id: int, *args: str) -> subprocess.CompletedProcess:
    """Run the installed viewer to completion on ``domain_id``."""
    return subprocess.run([executable('viewer'), *args], env=ros_env(domain_id),
                          capture_output=True, text=True, timeout=60)


def test_viewer_prints_a_summary_and_writes_a_png_then_sigint_exits_zero(tmp_path):
    node = NodeUnderTest([])
    try:
        once = run_viewer(node.domain_id, '--once', '--timeout', '30')
        assert once.returncode == 0, once.stderr
        assert 'elastic_break: 16 particles' in once.stdout
        assert 'collisions/s' in once.stdout and 'KE ' in once.stdout
        picture = tmp_path / 'world.png'
        snap = run_viewer(node.domain_id, '--snapshot', str(picture), '--timeout', '30')
        assert snap.returncode == 0, snap.stderr
        assert f'wrote {picture}' in snap.stdout
        assert picture.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
        image = matplotlib.image.imread(picture)
        assert image.shape[0] > 200 and image.shape[1] > 400
        assert image[..., :3].std() > 0.05          # not a blank canvas
    finally:
        code, _, err = node.stop(signal.SIGINT)
    assert code == 0, err
    assert 'Traceback' not in err


def test_scene_file_parameter_then_sigterm_exits_zero(tmp_path):
    scene = tmp_path / 'three.yaml'
    scene.write_text('name: three\ndimensions: 3\ndt: 0.01\nparticles:\n'
                     '  - {position: [0, 0, 0], radius: 0.1, mass: 1}\n'
                     '  - {position: [1, 0, 0], velocity: [-1, 0, 0], radius: 0.1, mass: 1}\n'
                     '  - {position: [0, 1, 0], radius: 0.2, mass: .inf}\n')
    node = NodeUnderTest(['-p', f'scene:={scene}', '-p', 'real_time_factor:=2.0',
                          '-p', 'accuracy:=balanced'])
    try:
        status = node.status()
        assert (status['scene'], status['particles'], status['dt']) == ('three', 3, 0.01)
        assert status['real_time_factor'] == 2.0
        assert node.next_status(lambda s: s['collisions'] >= 1)['momentum'] == \
            pytest.approx([-1.0, 0.0, 0.0], abs=1e-12)
    finally:
        code, _, err = node.stop(signal.SIGTERM)
    assert code == 0, err
    assert 'Traceback' not in err


@pytest.mark.parametrize('parameter, message', [
    ('scene:={tmp}/nope.yaml', 'no such scene file'),
    ('accuracy:=sloppy', 'parameter accuracy: unknown preset'),
    ('frame_id:=my frame', 'frame_id: must be a frame name'),
    ('max_particles:=3', 'exceed max_particles = 3'),
    ('threads:=1000', 'parameter threads: 1000 threads asked for, but this process can run '
                      'at most'),
])
def test_bad_start_up_exits_2_with_one_error_line(tmp_path, parameter, message):
    result = subprocess.run(
        [executable('collision_node'), '--ros-args', '-p', parameter.format(tmp=tmp_path)],
        env=ros_env(unique_domain_id()), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if '[ERROR]' in line]
    assert len(errors) == 1 and message in errors[0]
    assert 'Traceback' not in result.stderr


def test_viewer_without_a_node_gives_up_after_its_timeout():
    result = run_viewer(unique_domain_id(), '--once', '--timeout', '1')
    assert result.returncode == 1
    assert 'no status from collision_node within 1 s' in result.stderr


def test_a_node_that_cannot_keep_up_says_so_once_and_keeps_stepping():
    node = NodeUnderTest(['-p', 'real_time_factor:=1000.0', '-p', 'publish_rate:=20.0'])
    try:
        behind = node.next_status(lambda s: not s['keeping_up'])
        later = node.next_status(lambda s: s['steps'] > behind['steps'] + 100)
        assert not later['keeping_up']
        assert 0.0 < later['measured_real_time_factor'] < 1000.0
    finally:
        code, _, err = node.stop(signal.SIGINT)
    assert code == 0, err
    assert len([line for line in err.splitlines() if 'cannot keep up' in line]) == 1
