"""The accuracy ladder: presets, ccd, contact ordering and the exact event mode."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from collision_node import SceneError, World, load_scene, parse_scene, scenarios
from collision_node.physics.model.accuracy import (PRESETS, AccuracySettings, check_event_mode,
                                                   parse_accuracy)
from collision_node.physics.step.reference import missed_collisions
from collision_node.physics.model.effects import Effects
from collision_node.simulate import main as simulate_main
from collision_node.physics.stages.detection.broadphase import ALL_PAIRS_UP_TO
from lecture_reference import lecture_update


def world(accuracy, **scene) -> World:
    """Return a world for an inline scene under ``accuracy``."""
    return World(parse_scene(dict(accuracy=accuracy, **scene), 'test-scene'))


def gas(count, radius, speed, dt, seed=3, size=1.0, dimensions=3, restitution=None):
    """Return an inline gas-in-a-box scene mapping."""
    return scenarios.gas(count, radius, speed, seed=seed, high=size, dimensions=dimensions,
                         effects=None if restitution is None else {'restitution': restitution},
                         dt=dt)


# -- settings ---------------------------------------------------------------

def test_presets_are_documented_sets_and_override_key_by_key():
    assert parse_accuracy(None, 'x') == PRESETS['balanced']
    assert parse_accuracy('exact', 'x').mode == 'event'
    assert not parse_accuracy('fast', 'x').ccd
    custom = parse_accuracy({'preset': 'fast', 'ccd': True, 'substeps': 3}, 'x')
    assert custom == AccuracySettings(ccd=True, substeps=3, iterations=8, separation_passes=6)
    assert parse_accuracy('accurate', 'x').requery and not parse_accuracy(None, 'x').requery
    assert parse_accuracy({'ordering': 'batched'}, 'x').ccd  # based on balanced


def test_separation_passes_reach_the_separation_stage_under_gravity():
    # fast and balanced take 6 passes, accurate 4; a mapping overrides them; each pass is a
    # Gauss-Seidel pass over the pairs, so more passes leave a pile less overlapped.
    pile = load_scene('pile')
    passes = {}
    custom = {'preset': 'balanced', 'separation_passes': 9}
    for accuracy in ('fast', 'balanced', 'accurate', custom):
        settings = parse_accuracy(accuracy, 'x')
        world = World(pile.with_accuracy(settings))
        [stage] = [s for s in world.pipeline.stages if s.name == 'separation']
        passes[str(accuracy)] = stage.passes
    assert list(passes.values()) == [6, 6, 4, 9]
    depth = {}
    for count in (1, 6):
        settings = parse_accuracy({'preset': 'fast', 'separation_passes': count}, 'x')
        world = World(pile.with_accuracy(settings))
        world.step(240)
        x, r = world.state.position, world.state.radius
        gap = np.linalg.norm(x[:, None] - x[None, :], axis=2) - (r[:, None] + r[None, :])
        np.fill_diagonal(gap, np.inf)
        depth[count] = -float(gap.min()) / float(r.max())
    assert depth[6] < 0.5 * depth[1], depth


@pytest.mark.parametrize('value, message', [
    ('fastest', "s.yaml: accuracy: unknown preset 'fastest'"),
    ({'ccd': 1}, 's.yaml: accuracy.ccd: expected true or false, got 1'),
    ({'mode': 'exactly'}, "s.yaml: accuracy.mode: unknown mode 'exactly'"),
    ({'ordering': 'random'}, "s.yaml: accuracy.ordering: unknown ordering 'random'"),
    ({'substeps': 0}, 's.yaml: accuracy.substeps: must be >= 1, got 0'),
    ({'separation_passes': 0}, 's.yaml: accuracy.separation_passes: must be >= 1, got 0'),
    ({'collapse_time': -1}, 's.yaml: accuracy.collapse_time: must be >= 0, got -1'),
    ({'speed': 2}, 's.yaml: accuracy.speed: unknown key'),
])
def test_bad_accuracy_is_one_clear_line(value, message):
    with pytest.raises(SceneError) as error:
        parse_accuracy(value, 's.yaml: accuracy')
    assert str(error.value).startswith(message)


def test_event_mode_refuses_effects_it_cannot_do_exactly():
    @dataclass(frozen=True)
    class WithDrag(Effects):
        drag: object = None

    check_event_mode(PRESETS['exact'], WithDrag(gravity=np.zeros(3)), 'x')  # allowed
    with pytest.raises(SceneError, match=r'^s\.yaml: accuracy: mode event .* cannot simulate '
                                         r'drag exactly'):
        check_event_mode(PRESETS['exact'], WithDrag(drag=0.1), 's.yaml: accuracy')
    check_event_mode(PRESETS['accurate'], WithDrag(drag=0.1), 'x')  # step mode: fine


STATIC_UNDER_GRAVITY = [{'position': [0, 0, 0], 'radius': 0.1, 'mass': 1.0},
                        {'position': [0, 0, -1], 'radius': 0.1, 'mass': float('inf')}]


def test_exact_ball_falls_onto_a_static_ball_at_the_parabola_time():
    """A ball falls 0.8 m onto a static ball (e = 1): it meets it at sqrt(2 0.8 / g).

    The static ball does not fall, so their relative path is a parabola
    (a quartic's root); the ball leaves at its impact speed and is back at
    its start height at twice that time. No step solver step.
    """
    g = 9.81
    w = world('exact', dt=0.01, effects={'gravity': [0, 0, -g]}, particles=STATIC_UNDER_GRAVITY)
    w.record_impacts(True)
    fall = np.sqrt(2 * 0.8 / g)
    w.step(int(np.ceil(fall / 0.01)))
    impacts = w.take_impacts()
    assert len(impacts) == 1
    assert impacts['time'][0] == pytest.approx(fall, rel=1e-12)
    assert impacts['closing_speed'][0] == pytest.approx(g * fall, rel=1e-12)
    np.testing.assert_allclose(impacts['normal'][0], [0, 0, 1], atol=1e-12)
    np.testing.assert_array_equal(w.state.position[1], [0, 0, -1])
    assert w.state.velocity[0, 2] == pytest.approx(g * fall - g * (w.time - fall), rel=1e-12)
    assert w.stats.fallback_steps == 0


def test_exact_ball_rests_on_a_static_ball_held_by_its_support():
    """A ball touching a static one from above at rest: it stays, event-driven."""
    particles = [{'position': [0, 0, -0.8], 'radius': 0.1, 'mass': 1.0},
                 STATIC_UNDER_GRAVITY[1]]
    w = world('exact', dt=0.01, effects={'gravity': [0, 0, -9.81]}, particles=particles)
    w.step(100)
    np.testing.assert_array_equal(w.state.velocity, 0.0)
    np.testing.assert_allclose(w.state.position[0], [0, 0, -0.8], atol=1e-15)
    assert w.stats.fallback_steps == 0


def test_exact_takes_a_static_spawn_under_gravity():
    """A static particle spawned under gravity joins the exact world; a ball lands on it."""
    w = world('exact', dt=0.01, effects={'gravity': [0, 0, -9.81]},
              particles=STATIC_UNDER_GRAVITY[:1])
    w.step()
    w.spawn_text('{particles: [{position: [0, 0, -1], radius: 0.1, mass: .inf}]}')
    assert len(w.state) == 2
    w.step(60)
    assert w.stats.collisions == 1
    assert w.state.position[0, 2] > -0.8
    np.testing.assert_array_equal(w.state.position[1], [0, 0, -1])
    assert w.stats.fallback_steps == 0


# -- exact mode: the lecture's formulas ---------------------------------------

def test_exact_oblique_pair_matches_lecture_at_contact():
    w = World(load_scene('oblique_pair').with_accuracy(PRESETS['exact']))
    p0, v0 = w.state.position.copy(), w.state.velocity.copy()
    # |d + u s| = r1 + r2 with d = (-2, 0.25), u = (2, 0): s = 1 - sqrt(15/16) / 2.
    contact = 1.0 - np.sqrt(15.0 / 16.0) / 2.0
    w.step(1000)                                   # 1 s, well past the impact
    assert w.stats.collisions == 1
    at_contact = p0 + v0 * contact
    e1, e2 = lecture_update(1.0, 3.0, v0[0], v0[1], at_contact[0] - at_contact[1])
    np.testing.assert_allclose(w.state.velocity, [e1, e2], rtol=1e-12, atol=1e-15)
    expected = at_contact + np.array([e1, e2]) * (1.0 - contact)
    np.testing.assert_allclose(w.state.position, expected, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize('m1, m2', [(1.0, 1.0), (1.0, 3.0), (3.0, 1.0), (1e-6, 1e6)])
def test_exact_head_on_matches_lecture(m1, m2):
    w = world('exact', dt=0.01, particles=[
        {'position': [-0.7, 0, 0], 'velocity': [2.0, 0, 0], 'radius': 0.5, 'mass': m1},
        {'position': [0.6, 0, 0], 'velocity': [-0.5, 0, 0], 'radius': 0.5, 'mass': m2}])
    w.step(100)
    e1, e2 = lecture_update(m1, m2, np.array([2.0, 0, 0]), np.array([-0.5, 0, 0]), [1, 0, 0])
    np.testing.assert_allclose(w.state.velocity, [e1, e2], rtol=1e-12, atol=1e-15)
    contact = 0.3 / 2.5                            # gap 0.3 m closing at 2.5 m/s
    x1 = -0.7 + 2.0 * contact + e1[0] * (1.0 - contact)
    x2 = 0.6 - 0.5 * contact + e2[0] * (1.0 - contact)
    np.testing.assert_allclose(w.state.position[:, 0], [x1, x2], rtol=1e-12)


@pytest.mark.parametrize('preset', ['exact', 'balanced', 'accurate', 'fast'])
def test_cradle_ends_at_last_ball_moving(preset):
    balls = scenarios.cradle(5, 0.5, 1.0, 1.5, -0.5, first=1, dimensions=2)
    w = world(preset, dimensions=2, dt=0.01, particles=balls)
    w.step(100)
    np.testing.assert_allclose(w.state.velocity[:, 0], [0, 0, 0, 0, 1.5], atol=1e-15)
    assert w.stats.collisions == 4


def test_exact_gas_in_a_box_conserves_energy_for_ten_seconds():
    w = world('exact', **gas(count=40, radius=0.04, speed=1.0, dt=0.1))
    energy = w.kinetic_energy()
    w.step(100)                                    # 10 simulated seconds
    assert w.stats.collisions > 50 and w.stats.wall_collisions > 100
    assert abs(w.kinetic_energy() - energy) / energy < 1e-12
    s = w.state
    gaps = np.linalg.norm(s.position[:, None] - s.position[None], axis=2) - 0.08
    assert gaps[np.triu_indices(len(s), 1)].min() > -1e-12
    assert s.position.min() > 0.04 - 1e-12 and s.position.max() < 1 - 0.04 + 1e-12


def test_exact_bounce_under_gravity_matches_closed_form():
    g, h, e, r = 9.81, 1.0, 0.5, 0.1
    w = world('exact', dt=0.01, effects={'gravity': [0, 0, -g], 'walls': {
        'min': [-1, -1, 0], 'max': [1, 1, 3], 'restitution': e}},
        particles=[{'position': [0, 0, h + r], 'velocity': [0.3, 0, 0], 'radius': r,
                    'mass': 2.0}])
    w.step(60)
    fall = np.sqrt(2 * h / g)
    up = e * g * fall                              # rebound speed
    t = 0.6 - fall                                 # 0.6 s < fall + 2 up / g: one bounce
    assert w.stats.wall_collisions == 1
    np.testing.assert_allclose(w.state.position[0], [0.18, 0, r + up * t - g * t * t / 2],
                               rtol=1e-12)
    np.testing.assert_allclose(w.state.velocity[0], [0.3, 0, up - g * t], rtol=1e-12)


def test_exact_inelastic_collapse_does_not_hang():
    """Three balls with e = 0.05 (below the 1-D collapse bound 7 - 4 sqrt 3) on a line."""
    w = world({'preset': 'exact', 'collapse_time': 1e-6}, dimensions=2, dt=0.5,
              effects={'restitution': 0.05}, particles=[
                  {'position': [-0.5, 0], 'velocity': [1.0, 0], 'radius': 0.1, 'mass': 1.0},
                  {'position': [0.0, 0], 'radius': 0.1, 'mass': 1.0},
                  {'position': [0.21, 0], 'radius': 0.1, 'mass': 1.0}])
    w.step(4)
    stage = w.pipeline.stages[0]
    assert 10 <= w.stats.collisions <= stage.events < 10_000
    # They end as one cluster at 1/3 m/s each: 1/6 J of the 1/2 J is left.
    assert w.kinetic_energy() == pytest.approx(1 / 6, rel=1e-6)
    np.testing.assert_allclose(w.momentum(), [1.0, 0, 0], rtol=1e-14)


def test_exact_ball_bouncing_to_rest_falls_back_only_for_its_collapse():
    """Bounces stay exact; the collapse goes to the step solver; at rest it is held.

    e = 0.5 from 1 m: the bounces end after fall (1 + 2e / (1 - e)) = 1.35 s
    (infinitely many in finite time). Before that every step is exact
    (the first bounce to 1e-12, see above); the steps of the collapse are
    rolled back and solved by the step solver (measured: 2), and once the
    ball rests on the floor its support holds it, event-driven (no more
    fallbacks). All the energy it had above the floor is booked to the wall.
    """
    g, r = 9.81, 0.1
    w = world('exact', dt=0.1,
              effects={'gravity': [0, 0, -g], 'walls': {
                  'min': [-1, -1, 0], 'max': [1, 1, 3], 'restitution': 0.5}},
              particles=[{'position': [0, 0, 1.0 + r], 'radius': r, 'mass': 1.0}])
    w.step(13)                                     # 1.3 s: still bouncing
    assert w.stats.fallback_steps == 0
    assert w.stats.dissipated['walls'] > 0.0
    previous = w.energy()['total']
    for _ in range(17):
        w.step()
        assert w.energy()['total'] <= previous + 1e-12 * abs(previous)
        previous = w.energy()['total']
    assert 1 <= w.stats.fallback_steps <= 3
    settled = w.stats.fallback_steps
    w.step(20)
    assert w.stats.fallback_steps == settled
    assert abs(w.state.position[0, 2] - r) <= 1e-9
    assert np.max(np.abs(w.state.velocity)) <= 1e-9
    assert w.stats.dissipated['walls'] == pytest.approx(g * 1.0, rel=1e-9)


# -- ccd ---------------------------------------------------------------------

BULLET = [{'position': [0, 0, 0], 'velocity': [756.0, 0, 0], 'radius': 0.0045, 'mass': 0.15},
          {'position': [1.0, 0, 0], 'radius': 0.025, 'mass': 1.0}]


@pytest.mark.parametrize('preset', ['balanced', 'accurate', 'exact'])
def test_bullet_hits_target_at_sixtieth_of_a_second(preset):
    w = world(preset, dt=1 / 60, particles=BULLET)
    w.step(1)
    assert w.stats.collisions == 1
    e1, e2 = lecture_update(0.15, 1.0, np.array([756.0, 0, 0]), np.zeros(3), [1, 0, 0])
    np.testing.assert_allclose(w.state.velocity, [e1, e2], rtol=1e-12)


def test_bullet_passes_through_without_ccd():
    w = world('fast', dt=1 / 60, particles=BULLET)
    w.step(1)
    assert w.stats.collisions == 0                 # why ccd exists


@pytest.mark.parametrize('preset, radii_per_step', [('balanced', 2.0), ('balanced', 8.0),
                                                    ('accurate', 8.0)])
def test_no_missed_collisions_in_a_fast_gas(preset, radii_per_step):
    radius, dt = 0.02, 0.01
    w = world(preset, **gas(count=300, radius=radius, speed=radii_per_step * radius / dt,
                            dt=dt, seed=5))
    missed = 0
    for _ in range(60):
        before = w.state.copy()
        w.step()
        missed += sum(missed_collisions(before, w.state, w.scene.effects.walls))
    assert w.stats.collisions > 100
    assert missed == 0


def test_fast_gas_without_ccd_does_tunnel():
    """The same check finds pass-throughs when ccd is off (so it can fail)."""
    radius, dt = 0.02, 0.01
    w = world('fast', **gas(count=300, radius=radius, speed=8 * radius / dt, dt=dt, seed=5))
    missed = 0
    for _ in range(60):
        before = w.state.copy()
        w.step()
        missed += sum(missed_collisions(before, w.state, w.scene.effects.walls))
    assert missed > 0


def test_requery_finds_contacts_of_particles_sped_up_by_an_impact():
    """A heavy ball hits a light one, which reaches a third ball outside its query."""
    balls = [{'position': [0.0, 0, 0], 'velocity': [1.0, 0, 0], 'radius': 0.1, 'mass': 1e6},
             {'position': [0.21, 0, 0], 'radius': 0.1, 'mass': 1.0},
             {'position': [0.565, 0, 0], 'radius': 0.1, 'mass': 1.0}]
    # The light ball, hit at t = 0.01 s, leaves at about 2 m/s and reaches the
    # third at t = 0.0875 s, inside the step; at rest, the two were 0.355 m
    # apart, past r_i + r_j + the Verlet skin (0.35 m), so not candidates.
    # Far-away resting filler makes the world larger than the broadphase's
    # all-pairs size, so candidates come from the Verlet list, as in real scenes.
    filler = [{'position': [10.0 + 0.5 * k, 5.0, 0], 'radius': 0.1, 'mass': 1.0}
              for k in range(ALL_PAIRS_UP_TO)]
    late = world('balanced', dt=0.12, particles=balls + filler)
    late.step()
    gap = np.linalg.norm(late.state.position[1] - late.state.position[2]) - 0.2
    assert late.stats.collisions == 1 and gap < -0.05   # found only at the next step
    full = world({'requery': True}, dt=0.12, particles=balls + filler)
    full.step()
    assert full.stats.collisions == 2
    assert np.linalg.norm(full.state.position[1] - full.state.position[2]) > 0.2 - 1e-12
    np.testing.assert_allclose(full.state.velocity[2, 0], 2.0 - 2e-6, rtol=1e-5)


def test_balanced_elastic_gas_keeps_energy_for_ten_seconds():
    w = world('balanced', **gas(count=200, radius=0.02, speed=1.0, dt=0.01))
    energy = w.kinetic_energy()
    w.step(1000)
    assert w.stats.collisions > 500
    assert abs(w.kinetic_energy() - energy) / energy < 1e-9


# -- ordering ----------------------------------------------------------------

THREE = [{'position': [-1.0, 0], 'velocity': [1.0, 0], 'radius': 0.5, 'mass': 1},
         {'position': [0.0, 0], 'radius': 0.5, 'mass': 1},
         {'position': [1.0, 0], 'velocity': [-1.0, 0], 'radius': 0.5, 'mass': 1}]


@pytest.mark.parametrize('accuracy', ['fast', 'balanced', 'exact'])
def test_sequential_orderings_keep_three_balls_elastic(accuracy):
    w = world(accuracy, dimensions=2, dt=0.001, particles=THREE)
    w.step(1)
    np.testing.assert_allclose(w.state.velocity[:, 0], [-1.0, 0.0, 1.0], atol=1e-15)


@pytest.mark.parametrize('ccd', [False, True])
def test_batched_ordering_loses_the_three_ball_energy_but_never_adds(ccd):
    w = world({'ordering': 'batched', 'ccd': ccd, 'iterations': 64}, dimensions=2,
              dt=0.001, particles=THREE)
    w.step(1)
    np.testing.assert_allclose(w.state.velocity[:, 0], [0.0, 0.0, 0.0], atol=1e-9)
    g = world({'preset': 'fast', 'ordering': 'batched'},
              **gas(count=200, radius=0.02, speed=1.0, dt=0.01))
    energy = g.kinetic_energy()
    for _ in range(200):
        before = g.kinetic_energy()
        g.step()
        assert g.kinetic_energy() <= before * (1 + 1e-14)
    assert g.kinetic_energy() < energy


# -- runner flag ---------------------------------------------------------------

def test_runner_accuracy_flag(tmp_path, capsys):
    out = tmp_path / 'out.json'
    assert simulate_main(['oblique_pair', '--accuracy', 'exact', '--out', str(out),
                          '--quiet']) == 0
    assert simulate_main(['oblique_pair', '--accuracy', '{preset: fast, substeps: 2}',
                          '--explain']) == 0
    assert 'drift' in capsys.readouterr().out
    assert simulate_main(['oblique_pair', '--accuracy', 'fastest']) == 2
    assert "--accuracy: unknown preset 'fastest'" in capsys.readouterr().err
