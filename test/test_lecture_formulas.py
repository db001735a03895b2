"""The lecture's impulse formulas, checked against hand-computed values."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from collision_node import World, load_scene


def lecture_update(m1, m2, v1, v2, normal):
    """Return the lecture's post-impact velocities (e = 1), written as on the slides."""
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    a1, a2 = np.dot(v1, n), np.dot(v2, n)
    b1 = ((m1 - m2) * a1 + 2 * m2 * a2) / (m1 + m2)
    b2 = ((m2 - m1) * a2 + 2 * m1 * a1) / (m1 + m2)
    return v1 - a1 * n + b1 * n, v2 - a2 * n + b2 * n


@pytest.mark.parametrize('m1, m2, expected1, expected2', [
    (1.0, 1.0, [0.0, 0, 0], [2.0, 0, 0]),        # equal masses swap velocities
    (1.0, 3.0, [-1.0, 0, 0], [1.0, 0, 0]),       # (1-3)/4*2 = -1, 2*1/4*2 = 1
    (3.0, 1.0, [1.0, 0, 0], [3.0, 0, 0]),        # (3-1)/4*2 = 1, 2*3/4*2 = 3
])
def test_head_on_matches_hand_computed(world_from, m1, m2, expected1, expected2):
    world = world_from(dt=0.001, particles=[
        {'position': [-0.6, 0, 0], 'velocity': [2.0, 0, 0], 'radius': 0.5, 'mass': m1},
        {'position': [0.6, 0, 0], 'radius': 0.5, 'mass': m2},
    ])
    world.step(200)
    assert world.stats.collisions == 1
    np.testing.assert_allclose(world.state.velocity[0], expected1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(world.state.velocity[1], expected2, rtol=0, atol=1e-15)


def test_oblique_pair_matches_lecture_along_line_of_action():
    # Without ccd the impact is resolved at the end-of-step positions
    # (test_accuracy.py checks the exact contact with ccd and event mode).
    scene = load_scene('oblique_pair')
    world = World(scene.with_accuracy(replace(scene.accuracy, ccd=False)))
    v_before = world.state.velocity.copy()
    # Step until the impact, remembering the positions it used.
    while world.stats.collisions == 0:
        positions = world.state.position.copy()
        world.step()
    p1, p2 = positions + v_before * world.dt
    expected1, expected2 = lecture_update(1.0, 3.0, v_before[0], v_before[1], p1 - p2)
    np.testing.assert_allclose(world.state.velocity[0], expected1, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(world.state.velocity[1], expected2, rtol=1e-14, atol=1e-15)
    # Only the component along N changed: the tangential parts are untouched.
    n = (p1 - p2) / np.linalg.norm(p1 - p2)
    for k in range(2):
        tangential_before = v_before[k] - np.dot(v_before[k], n) * n
        tangential_after = world.state.velocity[k] - np.dot(world.state.velocity[k], n) * n
        np.testing.assert_allclose(tangential_after, tangential_before, atol=1e-15)


def test_three_balls_in_contact_keep_energy(world_from):
    """The Jacobi trap: [1, 0, -1] must not end at [0, 0, 0]."""
    world = world_from(dimensions=2, dt=0.001, particles=[
        {'position': [-1.0, 0], 'velocity': [1.0, 0], 'radius': 0.5, 'mass': 1},
        {'position': [0.0, 0], 'radius': 0.5, 'mass': 1},
        {'position': [1.0, 0], 'velocity': [-1.0, 0], 'radius': 0.5, 'mass': 1},
    ])
    world.step(1)
    np.testing.assert_allclose(world.state.velocity[:, 0], [-1.0, 0.0, 1.0], atol=1e-15)
    assert world.kinetic_energy() == pytest.approx(1.0, rel=1e-15)
