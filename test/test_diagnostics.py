"""The status -> diagnostic_msgs conversion: levels, message and values."""

from __future__ import annotations

import math

import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus

from collision_node.physics.model.scene import load_scene
from collision_node.physics.step.world import World
from collision_node.ros.diagnostics import (BALANCE_TOLERANCE, diagnostic_array,
                                            diagnostic_status, relative_balance_error)
from collision_node.ros.status import status_report

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros


def world_status(**overrides) -> dict:
    """Return the status of the oblique pair after 10 steps, with ``overrides`` applied."""
    world = World(load_scene('oblique_pair'))
    world.step(10)
    status = status_report(world, 'oblique_pair', (0.98, 0.0), paused=False,
                           real_time_factor=1.0, keeping_up=True, publish_rate=30.0,
                           frame_id='world', error=None)
    status.update(overrides)
    return status


def values(diagnostic: DiagnosticStatus) -> dict:
    """Return the KeyValues as a dict."""
    return {kv.key: kv.value for kv in diagnostic.values}


def test_a_healthy_world_is_ok_with_its_numbers():
    status = world_status()
    diagnostic = diagnostic_status(status, 'collision_node: simulation')
    assert diagnostic.level == DiagnosticStatus.OK
    assert (diagnostic.name, diagnostic.message, diagnostic.hardware_id) == (
        'collision_node: simulation', 'running', 'oblique_pair')
    kv = values(diagnostic)
    assert kv['particles'] == '2' and kv['steps'] == '10' and kv['fallback_steps'] == '0'
    assert kv['real_time_factor'] == '1.0' and kv['measured_real_time_factor'] == '0.98'
    assert kv['keeping_up'] == 'true' and kv['paused'] == 'false'
    assert kv['dropped_backlog_s'] == '0.0'      # the status has no counter yet: 0
    assert float(kv['energy_balance_error']) == status['energy']['balance_error']
    assert float(kv['energy_balance_relative_error']) <= 1e-15
    assert kv['time'] == repr(status['time']) and kv['error'] == ''


def test_dropped_backlog_is_read_when_the_status_has_it():
    kv = values(diagnostic_status(world_status(dropped_backlog_s=2.5), 'n'))
    assert kv['dropped_backlog_s'] == '2.5'


def test_paused_is_ok_and_says_so():
    diagnostic = diagnostic_status(world_status(paused=True), 'n')
    assert (diagnostic.level, diagnostic.message) == (DiagnosticStatus.OK, 'paused')


def test_not_keeping_up_warns_with_target_and_measured_factor():
    diagnostic = diagnostic_status(
        world_status(keeping_up=False, real_time_factor=4.0, measured_real_time_factor=1.25),
        'n')
    assert diagnostic.level == DiagnosticStatus.WARN
    assert diagnostic.message == 'not keeping up with real-time factor 4 (measured 1.25)'
    assert values(diagnostic)['keeping_up'] == 'false'


def test_a_stopped_world_is_an_error_before_the_warning():
    diagnostic = diagnostic_status(
        world_status(error='non-finite velocity of particle 3', keeping_up=False), 'n')
    assert diagnostic.level == DiagnosticStatus.ERROR
    assert diagnostic.message.startswith('stopped: non-finite velocity of particle 3; '
                                         'not keeping up')
    assert values(diagnostic)['error'] == 'non-finite velocity of particle 3'


@pytest.mark.parametrize('factor, level', [(0.5, DiagnosticStatus.OK),
                                           (2.0, DiagnosticStatus.ERROR)])
def test_energy_balance_error_beyond_the_tolerance_is_an_error(factor, level):
    status = world_status()
    energy = dict(status['energy'])
    scale = energy['start']                      # 2 J: the oblique pair's kinetic energy
    assert scale == pytest.approx(2.0)
    energy['balance_error'] = factor * BALANCE_TOLERANCE * scale
    diagnostic = diagnostic_status({**status, 'energy': energy}, 'n')
    assert diagnostic.level == level
    assert float(values(diagnostic)['energy_balance_relative_error']) == pytest.approx(
        factor * BALANCE_TOLERANCE)
    if level == DiagnosticStatus.ERROR:
        assert diagnostic.message == 'energy balance error 2e-06 of the energy (limit 1e-06)'


def test_relative_error_of_a_still_empty_world_and_of_nan():
    empty = {'kinetic_linear': 0.0, 'kinetic_rotational': 0.0, 'potential': 0.0,
             'start': 0.0, 'spawned': 0.0, 'dissipated': {}, 'balance_error': 0.0}
    assert relative_balance_error(empty) == 0.0
    assert relative_balance_error({**empty, 'balance_error': 1e-300}) == math.inf
    status = world_status()
    energy = {**status['energy'], 'balance_error': math.nan}
    assert diagnostic_status({**status, 'energy': energy}, 'n').level == DiagnosticStatus.ERROR


def test_dissipated_energy_counts_in_the_scale():
    energy = {'kinetic_linear': 1.0, 'kinetic_rotational': 0.0, 'potential': 0.0,
              'start': 10.0, 'spawned': 5.0, 'dissipated': {'walls': 14.0, 'separation': -1.0},
              'balance_error': 3e-5}
    assert relative_balance_error(energy) == pytest.approx(3e-5 / 15.0)


def test_array_carries_the_stamp_and_one_status():
    array = diagnostic_array(world_status(), 'n', Time(sec=12, nanosec=5))
    assert (array.header.stamp.sec, array.header.stamp.nanosec) == (12, 5)
    assert [s.name for s in array.status] == ['n']
