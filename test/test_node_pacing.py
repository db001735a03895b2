"""The node's pacing arithmetic: steps due so simulated time follows wall time."""

from __future__ import annotations

import pytest

from collision_node import load_scene, World
from collision_node.ros.pacing import Pacer, RateMeter
from collision_node.ros.parameters import DEFAULT_SCENE, PARAMETERS


def test_steps_due_follow_wall_time_times_factor():
    pacer = Pacer(dt=0.01, factor=1.0, wall=100.0, sim_time=0.0)
    assert pacer.steps_due(100.0, 0.0) == 0
    assert pacer.steps_due(100.095, 0.0) == 9          # 9.5 steps due: whole ones only
    assert pacer.steps_due(100.1, 0.0) == 10            # float noise does not defer a step
    assert pacer.steps_due(100.1, 0.05) == 5            # steps already taken count
    pacer.factor = 2.5
    assert pacer.steps_due(101.0, 0.0) == 250


def test_restart_moves_the_anchor_and_never_asks_for_negative_steps():
    pacer = Pacer(dt=0.01, factor=1.0, wall=0.0, sim_time=0.0)
    pacer.restart(wall=5.0, sim_time=1.0)               # e.g. resumed after a pause
    assert pacer.steps_due(5.0, 1.0) == 0
    assert pacer.steps_due(5.2, 1.0) == 20
    assert pacer.steps_due(5.2, 3.0) == 0                # ahead of wall time: wait


def test_rate_meter_measures_over_its_window():
    meter = RateMeter(window=1.0)
    assert meter.rates() == (0.0, 0.0)
    for k in range(31):                                  # 3 s at 10 Hz, sim at half speed
        meter.add(wall=0.1 * k, sim_time=0.05 * k, collisions=7 * k)
    rtf, collisions = meter.rates()
    assert rtf == pytest.approx(0.5) and collisions == pytest.approx(70.0)
    assert meter.samples[-1][0] - meter.samples[0][0] <= 1.0 + 1e-9
    meter.clear()
    assert meter.rates() == (0.0, 0.0)


def test_default_scene_is_a_valid_break_with_collisions_soon():
    assert PARAMETERS['scene'][0] == DEFAULT_SCENE == 'elastic_break'
    world = World(load_scene(DEFAULT_SCENE))
    assert len(world.state) == 16 and world.scene.dimensions == 2
    world.step(round(0.5 / world.dt))
    assert world.stats.collisions > 0
    assert world.kinetic_energy() == pytest.approx(0.5 * 0.17 * 25.0, rel=1e-9)
