"""Continuous detection (``ccd``) under gravity, drag, friction and a restitution threshold.

The stepped presets ``balanced`` and ``accurate`` find every impact at its
time of impact with every effect declared: two falling particles close on a
straight line (the quadratic root of the drag-free case), a particle meets a
floor on its parabola, a falling particle meets a static one on a parabola
(a quartic root); the contact law applies restitution, friction and the
threshold at the impact; resting contact is solved at the step end.
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World, parse_scene
from lecture_reference import lecture_update

G = 9.81
GRAVITY3 = [0.0, -G, 0.0]


def make(accuracy, particles, effects, dt=1 / 60, dimensions=3):
    """Return a world for inline particles and effects."""
    return World(parse_scene({'dimensions': dimensions, 'dt': dt, 'accuracy': accuracy,
                              'effects': effects, 'particles': particles}, 'test-scene'))


def assert_balance(world, rel=1e-9):
    """E_now + dissipated = E_start, relative to the energies involved."""
    report = world.energy()
    scale = max(abs(report['start']), abs(report['total']),
                sum(abs(v) for v in report['dissipated'].values()), 1e-300)
    assert abs(report['balance_error']) <= rel * scale, report


# --- the bullet, with gravity declared ---------------------------------------

BULLET = [{'position': [0, 0, 0], 'velocity': [756.0, 0, 0], 'radius': 0.0045, 'mass': 0.15},
          {'position': [1.0, 0, 0], 'radius': 0.025, 'mass': 1.0}]


@pytest.mark.parametrize('preset', ['balanced', 'accurate'])
def test_bullet_under_gravity_hits_a_falling_target(preset):
    """Both fall with g: the relative path is the straight one, the impulse the lecture's."""
    world = make(preset, BULLET, {'gravity': GRAVITY3})
    world.record_impacts(True)
    world.step(1)
    assert world.stats.collisions == 1
    impacts = world.take_impacts()
    assert len(impacts) == 1
    hit = (1.0 - 0.0045 - 0.025) / 756.0
    assert impacts['time'][0] == pytest.approx(hit, rel=1e-12)
    e1, e2 = lecture_update(0.15, 1.0, np.array([756.0, 0, 0]), np.zeros(3), [1, 0, 0])
    fall = np.array([0.0, -G / 60, 0.0])
    np.testing.assert_allclose(world.state.velocity, [e1 + fall, e2 + fall], rtol=0,
                               atol=1e-12 * 756)
    assert_balance(world)


@pytest.mark.parametrize('preset', ['balanced', 'accurate'])
def test_bullet_under_gravity_hits_a_static_target(preset):
    """A static target does not fall: the relative path is a parabola (quartic root)."""
    particles = [dict(BULLET[0]), {'position': [1.0, 0, 0], 'radius': 0.025,
                                   'mass': float('inf')}]
    world = make(preset, particles, {'gravity': GRAVITY3})
    world.record_impacts(True)
    world.step(1)
    assert world.stats.collisions == 1
    impact = world.take_impacts()[0]
    t = impact['time']
    # At the recorded time the bullet, on its parabola, touches the target.
    at = np.array([756.0 * t, -0.5 * G * t * t, 0.0])
    assert np.linalg.norm(at - [1.0, 0.0, 0.0]) == pytest.approx(0.0295, rel=1e-12)
    assert world.state.velocity[0, 0] < -755.0          # bounced back, did not tunnel
    assert world.state.position[0, 0] < 1.0 - 0.0295
    assert_balance(world)


def test_bullet_under_gravity_tunnels_without_ccd():
    """The same scene at ``fast`` passes through (so the tests above can fail)."""
    world = make('fast', BULLET, {'gravity': GRAVITY3})
    world.step(1)
    assert world.stats.collisions == 0
    assert world.state.position[0, 0] > 1.0 + 0.0295


def test_bullet_with_drag_and_gravity_does_not_tunnel():
    """Drag: impact solved on the drag-free path, the bullet still hits its target."""
    world = make('balanced', BULLET, {'gravity': GRAVITY3, 'drag': {'linear': 0.01}})
    world.step(1)
    assert world.stats.collisions == 1
    # The lecture's impulse, then drag (rate k/m = 0.067/s, 1/60 s) on the way out.
    e1, e2 = lecture_update(0.15, 1.0, np.array([756.0, 0, 0]), np.zeros(3), [1, 0, 0])
    np.testing.assert_allclose(world.state.velocity[:, 0], [e1[0], e2[0]], rtol=2e-3)
    assert world.energy()['dissipated']['drag'] > 0.0
    assert_balance(world)


# --- two falling particles: straight relative path ---------------------------

@pytest.mark.parametrize('preset', ['balanced', 'accurate'])
def test_two_falling_particles_collide_at_the_straight_path_time(preset):
    r, dt = 0.1, 1 / 60
    m1, m2 = 1.0, 3.0
    p1, p2 = np.array([0.0, 5.0, 0.0]), np.array([0.55, 5.07, 0.02])
    v1, v2 = np.array([4.0, 0.5, 0.0]), np.array([-2.0, 0.0, 0.3])
    world = make(preset, [
        {'position': p1.tolist(), 'velocity': v1.tolist(), 'radius': r, 'mass': m1},
        {'position': p2.tolist(), 'velocity': v2.tolist(), 'radius': r, 'mass': m2}],
        {'gravity': GRAVITY3}, dt=dt)
    world.record_impacts(True)
    # The smaller root of |d + u t| = 2 r (gravity cancels in d and u).
    d, u = p1 - p2, v1 - v2
    b, c = d @ u, d @ d - (2 * r) ** 2
    hit = (-b - np.sqrt(b * b - (u @ u) * c)) / (u @ u)
    steps = int(np.ceil(hit / dt))
    world.step(steps)
    impacts = world.take_impacts()
    assert len(impacts) == 1
    assert impacts['time'][0] == pytest.approx(hit, rel=1e-12)
    g = np.array(GRAVITY3)
    normal = d + u * hit
    w1, w2 = lecture_update(m1, m2, v1 + g * hit, v2 + g * hit, normal)
    end = steps * dt
    np.testing.assert_allclose(world.state.velocity, [w1 + g * (end - hit),
                                                      w2 + g * (end - hit)],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(impacts['normal'][0], normal / np.linalg.norm(normal),
                               rtol=0, atol=1e-12)
    assert_balance(world)


# --- a ball bouncing on a floor: parabola times ------------------------------

@pytest.mark.parametrize('preset', ['balanced', 'accurate'])
def test_bouncing_ball_hits_the_floor_at_the_parabola_times(preset):
    e, h, r = 0.8, 1.0, 0.1
    world = make(preset, [{'position': [0.0, h + r, 0.0], 'radius': r, 'mass': 0.5}],
                 {'gravity': GRAVITY3, 'walls': {'min': [None, 0.0, None], 'restitution': e}})
    world.record_impacts(True)
    times, apexes = [], []
    previous = 0.0
    while len(apexes) < 6:
        world.step()
        times.extend(world.take_impacts()['time'].tolist())
        vy = world.state.velocity[0, 1]
        if previous < 0.0 <= vy:
            apexes.append(world.state.position[0, 1] - r + vy * vy / (2 * G))
        previous = vy
    # Impact k at t_k = t_1 + sum_{m < k} 2 e^m v_1 / g, v_1 = sqrt(2 g h).
    v1 = np.sqrt(2 * G * h)
    flights = 2 * v1 * e ** np.arange(1, 6) / G
    expected = np.concatenate([[v1 / G], v1 / G + np.cumsum(flights)])
    np.testing.assert_allclose(times[:6], expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(apexes, h * e ** (2 * np.arange(1, 7)), rtol=1e-9)
    assert_balance(world)


# --- friction at the impact ---------------------------------------------------

def test_friction_at_a_floor_impact_books_its_work():
    """A sliding ball lands: slip friction mu j at the impact, its work booked as friction."""
    e, mu, r, m = 0.5, 0.1, 0.1, 2.0
    world = make('balanced', [{'position': [0.0, 0.6, 0.0], 'velocity': [3.0, 0.0, 0.0],
                               'radius': r, 'mass': m}],
                 {'gravity': GRAVITY3, 'friction': mu,
                  'walls': {'min': [None, 0.0, None], 'restitution': e}}, dt=1 / 60)
    world.record_impacts(True)
    while world.stats.wall_collisions == 0:
        world.step()
    impacts = world.take_impacts()
    assert len(impacts) == 1
    vn = np.sqrt(2 * G * 0.5)                      # landing speed after falling 0.5 m
    assert impacts['time'][0] == pytest.approx(vn / G, abs=1e-12)
    j = m * (1 + e) * vn
    assert impacts['normal_impulse'][0] == pytest.approx(j, rel=1e-12)
    # Slip: 3 m/s exceeds what mu j stops (mu j < m 3 / 3.5), so J_t = mu j.
    assert impacts['tangential_impulse'][0] == pytest.approx(mu * j, rel=1e-12)
    slip_after = 3.0 - 3.5 * mu * j / m
    assert slip_after > 0.0
    # Work of the friction impulse: j_t |u_t| - K j_t^2 / 2 with K = 3.5 / m.
    work = mu * j * 3.0 - 0.5 * (3.5 / m) * (mu * j) ** 2
    assert world.energy()['dissipated']['friction'] == pytest.approx(work, rel=1e-12)
    assert world.state.velocity[0, 0] == pytest.approx(3.0 - mu * j / m, rel=1e-12)
    assert world.state.angular_velocity[0, 2] == pytest.approx(-2.5 * mu * j / (m * r),
                                                               rel=1e-12)
    assert_balance(world)


def test_friction_at_a_pair_impact_books_its_work():
    """Two falling balls meet obliquely: friction at the impact, bounded by mu j."""
    mu, r, m = 0.3, 0.1, 1.0
    world = make('balanced', [
        {'position': [0.0, 3.0, 0.0], 'velocity': [2.0, 0.0, 0.0], 'radius': r, 'mass': m},
        {'position': [0.5, 3.12, 0.0], 'velocity': [-2.0, 0.0, 0.0], 'radius': r, 'mass': m}],
        {'gravity': GRAVITY3, 'friction': mu})
    world.record_impacts(True)
    while world.stats.collisions == 0:
        world.step()
    impact = world.take_impacts()[0]
    n = impact['normal']
    u = np.array([4.0, 0.0, 0.0])            # v_i - v_j, i = 0 (the normal is from j to i)
    j = 2.0 * -(u @ n) / (2 / m)             # e = 1
    assert impact['normal_impulse'] == pytest.approx(j, rel=1e-12)
    u_t = u - (u @ n) * n
    k = 3.5 * 2 / m
    jt = min(np.linalg.norm(u_t) / k, mu * j)
    assert impact['tangential_impulse'] == pytest.approx(jt, rel=1e-12)
    work = jt * np.linalg.norm(u_t) - 0.5 * k * jt * jt
    assert world.energy()['dissipated']['friction'] == pytest.approx(work, rel=1e-12)
    assert_balance(world)


def test_slow_impact_below_the_threshold_is_inelastic_at_balanced():
    """A declared threshold applies at the impact: slower closing gives e = 0."""
    world = make('balanced', [
        {'position': [0.0, 0, 0], 'velocity': [0.2, 0, 0], 'radius': 0.1, 'mass': 1.0},
        {'position': [0.3, 0, 0], 'velocity': [-0.2, 0, 0], 'radius': 0.1, 'mass': 1.0}],
        {'restitution_threshold': 0.5})
    world.step(30)
    np.testing.assert_allclose(world.state.velocity[:, 0], [0.0, 0.0], atol=1e-15)
    assert world.energy()['dissipated']['restitution'] == pytest.approx(0.04, rel=1e-12)


# --- explain ------------------------------------------------------------------

@pytest.mark.parametrize('effects', [
    {'gravity': GRAVITY3},
    {'drag': {'linear': 0.1}},
    {'friction': 0.3},
    {'restitution_threshold': 0.2},
    {'gravity': GRAVITY3, 'drag': {'quadratic': 0.01}, 'friction': 0.3,
     'walls': {'min': [None, 0.0, None]}, 'restitution_threshold': 0.1},
])
def test_explain_has_no_fallback_note_and_the_same_effects_in_stepped_presets(effects):
    texts = {}
    for preset in ('balanced', 'accurate'):
        world = make(preset, [], effects)
        text = world.explain()
        assert 'note:' not in text
        assert world.pipeline.names[0 if 'friction' not in effects else 1] == 'swept_contacts'
        texts[preset] = world.pipeline.names
    assert texts['balanced'] == texts['accurate']
    if 'drag' in effects:
        assert 'drag-free path' in make('balanced', [], effects).explain()
