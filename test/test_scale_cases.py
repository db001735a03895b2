"""Scale hard cases: walls, gravity and a small pile 1e9 m from the origin and at 1e-6 m.

Tolerances in the solvers are relative to the particle (a fraction of its
radius) and to the floating-point spacing at its coordinate, never a
fraction of the coordinate; potential energy is measured from a grid point
near the scene (``energy.reference_point``) and every loss is booked from
the impulses or displacements that cause it, so far from the origin
nothing is booked that did not happen. What float64 cannot do at 1e9 m is
hold a position finer than its spacing there (1.2e-7 m): the energy
balance holds to m |g| times that spacing per particle and (sub)step, which
is the bound asserted (measured: 4.8e-4 J for 5 discs over 240 steps under
`fast`, bound 1.4e-3 J).
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World, parse_scene
from collision_node.physics.model.accuracy import PRESETS

G = 9.81
FAR = 1.0e9
ALL = sorted(PRESETS)
STEPPED = [name for name in ALL if PRESETS[name].mode == 'step']


def world(preset: str, particles: list, effects: dict, dt: float = 1 / 240) -> World:
    """Return a 2-D world for an inline scene under ``preset``."""
    return World(parse_scene({'dimensions': 2, 'dt': dt, 'accuracy': preset,
                              'effects': effects, 'particles': particles}, 'scale-case'))


def grid_drift(w: World, coordinate: float) -> float:
    """Return one float spacing at ``coordinate`` per (sub)step run so far, m.

    Each (sub)step adds the drift and gravity's g dt^2 / 2 to a position,
    two roundings of half a spacing; the same increment rounds the same way
    step after step, so these add up. The event mode may hand a step to
    the `accurate` solver's 4 substeps.
    """
    accuracy = w.scene.accuracy
    substeps = accuracy.substeps if accuracy.mode == 'step' else 4
    return float(np.spacing(coordinate)) * w.steps * substeps


def rounding_bound(w: World, coordinate: float) -> float:
    """Return m |g| times ``grid_drift`` summed over the dynamic particles, J."""
    mass = float(np.sum(1.0 / w.state.inv_mass[w.state.dynamic]))
    return mass * G * grid_drift(w, coordinate)


@pytest.mark.parametrize('preset', ALL)
def test_particle_near_a_wall_far_from_the_origin_is_not_reflected(preset):
    """A wall at x = 1e9, r = 0.1, 0.49 m away and closing at 1 mm/s: nothing happens.

    The wall slop used to be 1e-9 of (r + |plane|), about 1 m here, so the
    particle counted as touching and was reflected.
    """
    w = world(preset, [{'position': [FAR + 0.59, 0.0], 'velocity': [-1e-3, 0.0],
                        'radius': 0.1, 'mass': 1.0}],
              {'walls': {'min': [FAR, None]}})
    w.step(10)
    assert w.state.velocity[0, 0] == -1e-3
    assert w.stats.wall_collisions == 0


@pytest.mark.parametrize('preset', ALL)
def test_elastic_floor_far_from_the_origin_books_no_loss_and_keeps_the_apex(preset):
    """Drop a ball 1 m onto an e = 1 floor at y = 1e9: no wall loss, apex kept.

    It used to book 4 J of wall loss that never happened (a difference of
    kinetic plus potential totals of 1e10 J).
    """
    w = world(preset, [{'position': [0.0, FAR + 1.1], 'radius': 0.1, 'mass': 1.0}],
              {'gravity': [0, -G], 'walls': {'min': [None, FAR]}})
    apexes, rising = [], False
    while len(apexes) < 3:
        w.step()
        velocity = w.state.velocity[0, 1]
        if rising and velocity <= 0.0:
            apexes.append(w.state.position[0, 1] - FAR)
        rising = velocity > 0.0
        assert w.time < 5.0
    report = w.energy()
    assert w.stats.wall_collisions >= 3
    assert abs(report['dissipated'].get('walls', 0.0)) <= 1e-9 * G * 1.0
    # The apex is sampled at step ends (within g dt^2 / 8 = 2e-5 m of it)
    # and held on the 1.2e-7 m grid of positions at 1e9 m.
    np.testing.assert_allclose(apexes, 1.1, atol=3e-5 + grid_drift(w, FAR))
    assert abs(report['balance_error']) <= rounding_bound(w, FAR)
    # Potential energy is measured near the scene, not from the origin.
    assert abs(report['potential']) < 1e7


@pytest.mark.parametrize('preset', ALL)
def test_free_fall_far_from_the_origin_books_its_potential_from_the_displacement(preset):
    """Free fall at (1e9, 1e9): the parabola to the position grid, potential from near by."""
    w = world(preset, [{'position': [FAR, FAR], 'radius': 0.1, 'mass': 2.0}],
              {'gravity': [0, -G]}, dt=0.01)
    start = w.energy()
    w.step(100)
    end = w.energy()
    fallen = FAR - w.state.position[0, 1]
    assert fallen == pytest.approx(0.5 * G * 1.0, abs=grid_drift(w, FAR))
    change = end['potential'] - start['potential']
    assert change == pytest.approx(-2.0 * G * fallen, rel=1e-14)
    assert end['dissipated'] == {}
    assert abs(end['balance_error']) <= rounding_bound(w, FAR)


def small_pile(offset: float, scale: float, preset: str) -> World:
    """Five discs (r = 5 cm x scale) dropped in a column onto a floor in a 0.6 x scale box.

    dt grows as sqrt(scale), so the scene at scale s is the unit scene
    with lengths times s, times times sqrt(s) and speeds times sqrt(s).
    """
    r = 0.05 * scale
    particles = [{'position': [offset + k * 0.75 * r,
                               offset + r + k * 2.2 * r + 0.5 * scale],
                  'radius': r, 'mass': 1.0} for k in range(5)]
    return world(preset, particles,
                 {'gravity': [0, -G], 'restitution': 0.5,
                  'walls': {'min': [offset - 0.3 * scale, offset],
                            'max': [offset + 0.3 * scale, None]}},
                 dt=np.sqrt(scale) / 240)


@pytest.mark.parametrize('preset', STEPPED)
def test_small_pile_far_from_the_origin_keeps_its_energy_balance(preset):
    """Drop five discs at 1e9 m: balance to the position grid, no energy gained, settled."""
    w = small_pile(FAR, 1.0, preset)
    start = w.energy()['total']
    for _ in range(240):
        w.step()
        # Never above the start by more than the rounding of positions at 1e9.
        assert w.energy()['total'] <= start + rounding_bound(w, FAR)
    report = w.energy()
    assert abs(report['balance_error']) <= rounding_bound(w, FAR)
    assert report['dissipated']['restitution'] > 0.9 * (start - report['total'])
    heights = w.state.position[:, 1] - FAR
    assert heights.min() >= 0.05 - 1e-6                    # none sunk into the floor
    assert heights.max() < 0.5                              # all came down


@pytest.mark.parametrize('preset', STEPPED)
def test_small_pile_at_a_micrometre_is_the_metre_pile_scaled(preset):
    """Scale the pile's lengths by 1e-6: positions and energies scale exactly (to 1e-6)."""
    unit, micro = small_pile(0.0, 1.0, preset), small_pile(0.0, 1e-6, preset)
    unit.step(240)
    micro.step(240)
    np.testing.assert_allclose(micro.state.position / 1e-6, unit.state.position, atol=1e-6)
    np.testing.assert_allclose(micro.state.velocity / 1e-3, unit.state.velocity, atol=1e-6)
    a, b = unit.energy(), micro.energy()
    for name, value in a['dissipated'].items():
        assert b['dissipated'][name] / 1e-6 == pytest.approx(value, abs=1e-6 * a['start'])
    assert abs(b['balance_error']) <= 1e-12 * abs(b['start'])


@pytest.mark.parametrize('preset', ALL)
def test_micrometre_pair_and_wall_impacts_are_the_lecture_s(preset):
    """At r = 1e-7 m and 1e-3 m/s the head-on impact and a wall bounce are the lecture's."""
    w = world(preset, [{'position': [-3e-7, 0.0], 'velocity': [1e-3, 0.0], 'radius': 1e-7,
                        'mass': 1.0},
                       {'position': [0.0, 0.0], 'radius': 1e-7, 'mass': 3.0}],
              {'restitution': 0.5, 'walls': {'min': [None, -2e-7], 'max': [3e-7, None]}},
              dt=1e-5)
    w.step(100)
    # Lecture with e = 0.5: v1 = (1 - 1.5 * 3/4) v0 = -v0 / 8, v2 = 1.5 / 4 v0, then the
    # wall at x = 3e-7 (e = 1) reverses the second.
    np.testing.assert_allclose(w.state.velocity[:, 0], [-1.25e-4, -3.75e-4], rtol=1e-12)
    loss = 0.5 * (1 - 0.25) * 0.75 * 1e-6
    assert w.energy()['dissipated']['restitution'] == pytest.approx(loss, rel=1e-12)
    assert abs(w.energy()['balance_error']) <= 1e-12 * loss
