"""The viewer's summary line and snapshot drawing, without a running node."""

from __future__ import annotations

import matplotlib.image
import numpy as np
import pytest

from collision_node.ros.viewer import (collision_lines, draw_snapshot, parse_arguments,
                                       summary_line)

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

STATUS = {'scene': 'gas', 'particles': 1000, 'time': 12.3456, 'real_time_factor': 1.0,
          'measured_real_time_factor': 0.987, 'collisions_per_second': 412.25,
          'kinetic_energy': 3.0625, 'paused': False, 'keeping_up': True, 'error': None}


def test_summary_line_shows_particles_time_rtf_collision_rate_and_energy():
    assert summary_line(STATUS) == ('gas: 1000 particles  t = 12.346 s  RTF 0.99 (target 1)  '
                                    '412.2 collisions/s  KE 3.0625 J')


def test_summary_line_flags_pause_and_falling_behind():
    line = summary_line({**STATUS, 'paused': True, 'keeping_up': False})
    assert line.endswith('[paused, cannot keep up]')


def test_snapshot_draws_particles_to_scale(tmp_path):
    path = tmp_path / 'w.png'
    state = {'position': np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0]]),
             'velocity': np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
             'radius': np.array([0.25, 0.1])}
    draw_snapshot(state, 'two', path)
    image = matplotlib.image.imread(path)
    assert image.shape[1] == 900 and image[..., :3].std() > 0.05


@pytest.mark.parametrize('argv', [['--timeout', '0'], ['--snapshot', 'x.jpg'],
                                  ['--snapshot', '/no/such/dir/x.png']])
def test_bad_arguments_exit_2(argv):
    with pytest.raises(SystemExit) as stop:
        parse_arguments(argv)
    assert stop.value.code == 2


def test_collision_lines_name_ids_or_wall_point_normal_impulses_and_speed():
    impacts = {'time': np.array([1.25, 2.0]), 'i': np.array([3, 7]), 'j': np.array([4, -1]),
               'point': np.array([[0.5, -0.25, 0.0], [1.0, 2.0, 3.0]]),
               'normal': np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
               'normal_impulse': np.array([1.5, 0.125]),
               'tangential_impulse': np.array([0.0, 0.0625]),
               'closing_speed': np.array([2.0, 0.5])}
    assert collision_lines(impacts) == [
        't = 1.250000 s  3 - 4  at (0.5 -0.25 0)  normal (1 0 0)  J = 1.5 N s  Jt = 0 N s  '
        'closing 2 m/s',
        't = 2.000000 s  7 - wall  at (1 2 3)  normal (0 -1 0)  J = 0.125 N s  '
        'Jt = 0.0625 N s  closing 0.5 m/s']


def test_collisions_and_snapshot_exclude_each_other():
    with pytest.raises(SystemExit) as stop:
        parse_arguments(['--collisions', '--snapshot', 'x.png'])
    assert stop.value.code == 2
    assert parse_arguments(['--collisions', '--once']).collisions
