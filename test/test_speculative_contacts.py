"""Speculative contacts and momentum in the step-end contact solve, at every stepped preset.

A pair found before it touches (its gap below the step's speculative
distance) may close by at most its gap in the next step, so slow contact
is held before it overlaps; every impulse and push between two dynamic
particles is equal and opposite, so a cluster that no wall or static
particle touches keeps its momentum exactly (p0 + M g t) under gravity.
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import parse_scene, World
from collision_node.physics.model.accuracy import PRESETS

STEPPED = [name for name, settings in PRESETS.items() if settings.mode == 'step']


def falling_cluster(preset: str) -> World:
    """Return 27 touching spheres (3 x 3 x 3, r = 5 cm) with small random speeds, no walls."""
    rng = np.random.default_rng(27)
    r = 0.05
    particles = []
    for x in range(3):
        for y in range(3):
            for z in range(3):
                particles.append({
                    'position': [2 * r * x, 2 * r * y + 1.0, 2 * r * z],
                    'velocity': rng.uniform(-0.3, 0.3, 3).tolist(),
                    'radius': r, 'mass': 0.1})
    return World(parse_scene({
        'dimensions': 3, 'dt': 1.0 / 60.0, 'accuracy': preset,
        'effects': {'gravity': [0.0, -9.81, 0.0], 'restitution': 0.5, 'friction': 0.3},
        'particles': particles}, 'falling cluster'))


@pytest.mark.parametrize('preset', STEPPED)
def test_a_falling_cluster_keeps_its_momentum_under_contact(preset):
    world = falling_cluster(preset)
    mass = 1.0 / world.state.inv_mass
    gravity = np.array([0.0, -9.81, 0.0])
    p0 = world.momentum().copy()
    collisions = 0
    for step in range(1, 121):
        world.step()
        expected = p0 + mass.sum() * gravity * world.time
        scale = np.linalg.norm(expected)
        np.testing.assert_allclose(world.momentum(), expected, rtol=0, atol=1e-12 * scale,
                                   err_msg=f'step {step}')
        collisions = world.stats.collisions
    # The contacts did work: the cluster is not a set of free particles.
    assert collisions > 27
    assert world.stats.dissipated.get('restitution', 0.0) > 0.0


def approaching_pair(preset: str, gap: float) -> World:
    """Return two 0.1 m balls closing at 0.2 m/s, below a 0.5 m/s restitution threshold."""
    return World(parse_scene({
        'dimensions': 2, 'dt': 0.01, 'accuracy': preset,
        'effects': {'restitution': 0.5, 'restitution_threshold': 0.5},
        'particles': [
            {'position': [0.0, 0.0], 'velocity': [0.1, 0.0], 'radius': 0.1, 'mass': 1.0},
            {'position': [0.2 + gap, 0.0], 'velocity': [-0.1, 0.0], 'radius': 0.1,
             'mass': 1.0}]}, 'approaching pair'))


def pair_gap(world: World) -> float:
    """Return the distance between the two balls' surfaces, m."""
    p = world.state.position
    return float(np.linalg.norm(p[1] - p[0]) - 0.2)


def test_a_speculative_pair_closes_by_its_gap_in_the_next_step():
    # fast: at the first step's end the gap is 1 mm, inside the speculative
    # distance (0.5 m/s x 0.01 s plus 2 % of r): the solve lets the pair close
    # by 1 mm in the next step (0.1 m/s), equal and opposite, and no more.
    world = approaching_pair('fast', 3e-3)
    world.step()
    assert pair_gap(world) == pytest.approx(1e-3, abs=1e-15)
    v = world.state.velocity
    assert v[0, 0] - v[1, 0] == pytest.approx(0.1, abs=1e-12)
    assert v[0, 0] + v[1, 0] == pytest.approx(0.0, abs=1e-15)
    world.step()
    # It touches at the step's end, and the touching contact (slower than the
    # threshold: e = 0) stops the approach.
    assert pair_gap(world) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(world.state.velocity, 0.0, atol=1e-12)


@pytest.mark.parametrize('preset', STEPPED)
def test_slow_contact_never_overlaps(preset):
    world = approaching_pair(preset, 3e-3)
    momentum = world.momentum().copy()
    for _ in range(20):
        world.step()
        assert pair_gap(world) >= -1e-12
        np.testing.assert_allclose(world.momentum(), momentum, rtol=0, atol=1e-15)
    np.testing.assert_allclose(world.state.velocity, 0.0, atol=1e-12)
    assert pair_gap(world) == pytest.approx(0.0, abs=1e-12)


def test_an_impact_found_before_it_touches_keeps_the_lecture_impulse():
    # Closing at 2 m/s (faster than the threshold) with a gap the next step
    # closes: the speculative contact is left alone, and the impact is the
    # lecture's, e = 0.5 of the closing speed, when the pair meets.
    for preset in STEPPED:
        world = approaching_pair(preset, 5e-3)
        world.state.velocity[0, 0], world.state.velocity[1, 0] = 1.0, -1.0
        world.step(10)
        v = world.state.velocity
        assert v[1, 0] - v[0, 0] == pytest.approx(1.0, rel=1e-12), preset
        assert v[0, 0] + v[1, 0] == pytest.approx(0.0, abs=1e-15), preset
