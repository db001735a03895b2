"""The hard cases that break collision code, one named test per case (issue 6).

Every test runs once per accuracy preset in ``collision_node.accuracy.PRESETS``
(new presets join automatically) and asserts analytic values or stated
bounds; docs/stability.md lists each case with its outcome per preset.
The long forms (the 1,000,000-step run, the dense cluster settled to the
end) run with ``HYPOTHESIS_PROFILE=deep``.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from collision_node import World, parse_scene
from collision_node.accuracy import PRESETS
from collision_node.stages.broadphase import candidate_pairs


@pytest.fixture(params=sorted(PRESETS))
def preset(request) -> str:
    """Name of the accuracy preset a case runs under."""
    return request.param


def ball(position, radius, mass, velocity=None) -> dict:
    """Return one particle entry of a scene."""
    entry = {'position': list(map(float, position)), 'radius': radius, 'mass': mass}
    if velocity is not None:
        entry['velocity'] = list(map(float, velocity))
    return entry


def build(preset: str, particles: list, **scene) -> World:
    """Return a world for an inline scene under ``preset``."""
    return World(parse_scene(dict(scene, accuracy=preset, particles=particles), 'hard-case'))


def lecture_impact(m1, m2, v1, v2, normal):
    """Return the lecture's velocities after an elastic impact along ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a1, a2 = np.dot(v1, n), np.dot(v2, n)
    b1 = ((m1 - m2) * a1 + 2 * m2 * a2) / (m1 + m2)
    b2 = ((m2 - m1) * a2 + 2 * m1 * a1) / (m1 + m2)
    return np.asarray(v1) + (b1 - a1) * n, np.asarray(v2) + (b2 - a2) * n


def max_penetration(world: World) -> float:
    """Return the deepest overlap between any two particles, in metres."""
    s = world.state
    i, j = candidate_pairs(s.position, s.radius)
    if i.size == 0:
        return 0.0
    distance = np.linalg.norm(s.position[i] - s.position[j], axis=1)
    return float(max(0.0, np.max(s.radius[i] + s.radius[j] - distance)))


def assert_finite(world: World) -> None:
    """Fail if any position or velocity is NaN or infinite."""
    assert np.isfinite(world.state.position).all()
    assert np.isfinite(world.state.velocity).all()


# 1. Coincident centres --------------------------------------------------------------------

def test_case01_coincident_centres_moving_pair_separates_deterministically(preset):
    """Centres that meet exactly use the relative velocity as line of action."""
    dt = 1.0 / 1024.0            # powers of two: the drift lands exactly on the origin
    v1 = np.array([1.0, 2.0, 0.0])
    particles = [ball(-v1 * dt, 0.5, 1.0, v1), ball([0, 0, 0], 0.5, 3.0)]
    worlds = [build(preset, particles, dt=dt) for _ in range(2)]
    for world in worlds:
        world.step()
        assert_finite(world)
    expected1, expected2 = lecture_impact(1.0, 3.0, v1, np.zeros(3), -v1)
    np.testing.assert_allclose(expected1, [-0.5, -1.0, 0.0], atol=1e-15)   # hand check
    world = worlds[0]
    np.testing.assert_allclose(world.state.velocity[0], expected1, atol=1e-15)
    np.testing.assert_allclose(world.state.velocity[1], expected2, atol=1e-15)
    np.testing.assert_allclose(world.momentum(), v1, atol=1e-15)
    assert world.kinetic_energy() == pytest.approx(2.5, rel=1e-15)
    # Deterministic: a second world gives bit-identical results.
    np.testing.assert_array_equal(worlds[1].state.position, world.state.position)
    np.testing.assert_array_equal(worlds[1].state.velocity, world.state.velocity)
    # They fly apart along the line of action and never meet again.
    world.step(1000)
    assert world.stats.collisions == 1
    assert np.linalg.norm(world.state.position[0] - world.state.position[1]) > 1.0
    np.testing.assert_allclose(world.state.velocity[0], expected1, atol=1e-15)


def test_case01_coincident_centres_at_rest_separate_along_x_without_energy(preset):
    """No relative velocity: the fallback line of action is +x; nothing gains speed."""
    centre = [0.25, -0.5, 1.0]
    world = build(preset, [ball(centre, 0.5, 1.0), ball(centre, 0.5, 2.0)], dt=0.01)
    world.step()
    assert_finite(world)
    np.testing.assert_array_equal(world.state.velocity, 0.0)
    p1, p2 = world.state.position
    np.testing.assert_allclose(p1 - p2, [1.0, 0.0, 0.0], atol=1e-15)
    # The push is shared by inverse mass, so the centre of mass stays put.
    np.testing.assert_allclose((1.0 * p1 + 2.0 * p2) / 3.0, centre, atol=1e-15)
    world.step(10)
    assert world.kinetic_energy() == 0.0
    assert world.stats.collisions == 0


# 2. Near-coincident centres ---------------------------------------------------------------

NEAR_DISTANCES = [1e-300, 1e-150, 1e-12, 5e-324]


def exact_unit(offset: np.ndarray) -> np.ndarray:
    """Return offset / |offset| after an exact power-of-two rescale (no underflow)."""
    exponent = np.frexp(np.max(np.abs(offset)))[1]
    scaled = np.ldexp(offset, 60 - exponent)
    return scaled / np.linalg.norm(scaled)


@pytest.mark.parametrize('distance', NEAR_DISTANCES, ids=lambda d: f'{d:g}')
def test_case02_near_coincident_centres_at_rest_separate_along_their_offset(preset, distance):
    """Offsets whose squares underflow still give the exact line of action."""
    direction = np.array([0.6, 0.8, 0.0])
    offset = direction * distance            # as stored: 5e-324 rounds to (1, 1) ulps
    normal = exact_unit(offset)
    world = build(preset, [ball(offset, 0.5, 1.0), ball([0, 0, 0], 0.5, 1.0)], dt=0.01)
    world.step()
    assert_finite(world)
    np.testing.assert_array_equal(world.state.velocity, 0.0)
    p1, p2 = world.state.position
    np.testing.assert_allclose(p1 - p2, normal, atol=2e-15)      # pushed to |p1-p2| = 1
    np.testing.assert_allclose(p1 + p2, offset, atol=1e-15)      # equal masses, equal push


@pytest.mark.parametrize('distance', NEAR_DISTANCES, ids=lambda d: f'{d:g}')
def test_case02_near_coincident_impact_uses_the_tiny_offset_as_line_of_action(
        preset, distance):
    """Ball 1 arrives (at step end) a tiny distance from ball 0: lecture update along it."""
    dt = 1.0 / 1024.0
    offset = np.array([0.6, 0.8, 0.0]) * distance
    normal = exact_unit(offset)
    v2 = np.array([0.5, 0.0, 0.0])                        # approaching: v2 . N = 0.3 > 0
    world = build(preset, [ball(offset, 0.5, 1.0), ball(-v2 * dt, 0.5, 1.0, v2)], dt=dt)
    world.step()
    assert_finite(world)
    expected1, expected2 = lecture_impact(1.0, 1.0, np.zeros(3), v2, normal)
    np.testing.assert_allclose(world.state.velocity[0], expected1, atol=1e-15)
    np.testing.assert_allclose(world.state.velocity[1], expected2, atol=1e-15)
    np.testing.assert_allclose(world.momentum(), v2, atol=1e-15)
    assert world.kinetic_energy() == pytest.approx(0.125, rel=1e-15)
    assert world.stats.collisions == 1


# 3. Extreme mass ratios -------------------------------------------------------------------

@pytest.mark.parametrize('m1, m2', [(1e12, 1.0), (1e-12, 1.0), (1.0, 1e12)],
                         ids=['1e12', '1e-12', '1:1e12'])
def test_case03_extreme_mass_ratio_matches_analytic(preset, m1, m2):
    """Head-on impact, compared with the lecture formula in exact rational arithmetic."""
    v1, v2 = 2.0, -1.0
    world = build(preset, [ball([-0.6, 0, 0], 0.5, m1, [v1, 0, 0]),
                           ball([0.6, 0, 0], 0.5, m2, [v2, 0, 0])], dt=0.001)
    world.step(200)
    assert world.stats.collisions == 1
    fm1, fm2, fv1, fv2 = map(Fraction, (m1, m2, v1, v2))
    exact1 = ((fm1 - fm2) * fv1 + 2 * fm2 * fv2) / (fm1 + fm2)
    exact2 = ((fm2 - fm1) * fv2 + 2 * fm1 * fv1) / (fm1 + fm2)
    got1, got2 = world.state.velocity[:, 0]
    assert got1 == pytest.approx(float(exact1), rel=1e-12, abs=0)
    assert got2 == pytest.approx(float(exact2), rel=1e-12, abs=0)
    np.testing.assert_array_equal(world.state.velocity[:, 1:], 0.0)
    # Momentum: exact up to the rounding of the larger momentum term.
    momentum = fm1 * Fraction(got1) + fm2 * Fraction(got2)
    scale = abs(fm1 * fv1) + abs(fm2 * fv2)
    assert abs(momentum - (fm1 * fv1 + fm2 * fv2)) <= Fraction(1e-15) * scale


@pytest.mark.parametrize('direction, tangential', [
    ([1.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    ([1.0, 0.5, -0.25], [0.5, -0.5, 1.0]),
], ids=['head-on', 'oblique'])
def test_case03_infinite_mass_reflects_exactly_and_never_moves(preset, direction, tangential):
    """A static particle (mass .inf) is a mirror; the finite side's momentum is exact."""
    n = np.asarray(direction) / np.linalg.norm(direction)
    tangential = np.asarray(tangential) - np.dot(tangential, n) * n
    v = -3.0 * n + tangential                # closing speed 3 m/s along n
    dt = 1.0 / 1024.0
    start = n * 1.01 - v * dt * 8            # reaches the wall ball within ~20 steps
    static = ball([0, 0, 0], 0.5, float('inf'))
    world = build(preset, [static, ball(start, 0.51, 2.0, v)], dt=dt)
    world.step(64)
    assert world.stats.collisions == 1
    s = world.state
    np.testing.assert_array_equal(s.position[0], 0.0)
    np.testing.assert_array_equal(s.velocity[0], 0.0)
    # The contact normal is where the ball was when it touched; check the mirror law
    # against that normal: tangential part unchanged, normal part reversed.
    after = s.velocity[1]
    assert np.linalg.norm(after) == pytest.approx(np.linalg.norm(v), rel=1e-15)
    change = after - v
    hit_normal = change / np.linalg.norm(change)
    assert np.dot(v, hit_normal) < 0.0
    np.testing.assert_allclose(after, v - 2.0 * np.dot(v, hit_normal) * hit_normal,
                               atol=1e-15)
    if not np.any(tangential):
        np.testing.assert_array_equal(after, -v)   # head-on: m v becomes exactly -m v


# 6. Dense cluster -------------------------------------------------------------------------

CLUSTER_ENERGY_BOUND = 1.0 + 1e-12   # final KE <= this times the initial KE


def test_case06_dense_cluster_of_1000_resolves_without_explosion(preset, deep_profile):
    """1,000 particles spawned within 1 mm of one point, in a 2 m box."""
    rng = np.random.default_rng(6)
    count, radius = 1000, 0.05
    position = rng.normal(scale=1e-3, size=(count, 3))
    velocity = rng.normal(size=(count, 3))
    mass = 10.0 ** rng.uniform(-1.0, 1.0, size=count)
    world = build(preset, [ball(p, radius, m, v) for p, v, m in zip(position, velocity, mass)],
                  dt=1.0 / 240.0, effects={'walls': {'min': [-1, -1, -1], 'max': [1, 1, 1]}})
    energy0 = world.kinetic_energy()
    penetration0 = max_penetration(world)
    assert penetration0 > 1.9 * radius
    steps = 400 if deep_profile else 1
    for _ in range(steps):
        world.step()
        assert world.kinetic_energy() <= CLUSTER_ENERGY_BOUND * energy0
        assert np.all(np.abs(world.state.position) <= 1.0 - radius + 1e-12)
    assert_finite(world)
    # The solve is not allowed to kill the motion either (measured: loses < 1 %).
    assert world.kinetic_energy() >= 0.9 * energy0
    if deep_profile:
        assert max_penetration(world) <= 1e-3 * radius
    else:
        assert max_penetration(world) < penetration0
