"""Conservation laws as properties over random pairs and random sets (hypothesis).

Without walls or static bodies momentum is conserved to round-off; with
e = 1 kinetic energy is conserved to round-off (static bodies included);
with e < 1 it never grows; no NaN or inf appears; a 2-D world stays in
z = 0 exactly; static bodies never move.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from collision_node import World, parse_scene

ROUND_OFF = 1e-12
coordinate = st.floats(-2.0, 2.0, allow_nan=False)
speed = st.floats(-50.0, 50.0, allow_nan=False)
mass = st.floats(1e-6, 1e6)
radius = st.floats(0.05, 1.0)


def world_of(particles: list, dimensions: int = 3, restitution: float = 1.0,
             dt: float = 0.01) -> World:
    """Return a world of free particles (no walls, no other effects)."""
    return World(parse_scene({'dimensions': dimensions, 'dt': dt,
                              'effects': {'restitution': restitution},
                              'particles': particles}, 'property'))


def momentum_scale(world: World) -> float:
    """Return sum of |m v| over dynamic particles: the scale of momentum round-off."""
    s = world.state
    dyn = s.dynamic
    return float(np.sum(np.linalg.norm(s.velocity[dyn], axis=1) / s.inv_mass[dyn])) + 1e-300


def assert_finite(world: World) -> None:
    """Assert every position and velocity is finite."""
    assert np.isfinite(world.state.position).all() and np.isfinite(world.state.velocity).all()


@settings(max_examples=150, deadline=None)
@given(p1=st.tuples(coordinate, coordinate, coordinate), p2=st.tuples(coordinate, coordinate,
                                                                      coordinate),
       v1=st.tuples(speed, speed, speed), v2=st.tuples(speed, speed, speed),
       m1=mass, m2=mass, r1=radius, r2=radius, restitution=st.sampled_from([1.0, 0.7, 0.0]))
def test_random_pair_conserves_momentum_and_energy(p1, p2, v1, v2, m1, m2, r1, r2,
                                                   restitution):
    world = world_of([{'position': list(p1), 'velocity': list(v1), 'radius': r1, 'mass': m1},
                      {'position': list(p2), 'velocity': list(v2), 'radius': r2, 'mass': m2}],
                     restitution=restitution)
    momentum, energy = world.momentum(), world.kinetic_energy()
    scale = momentum_scale(world)
    world.step(5)
    assert_finite(world)
    np.testing.assert_allclose(world.momentum(), momentum, rtol=0, atol=ROUND_OFF * scale)
    if restitution == 1.0:
        assert abs(world.kinetic_energy() - energy) <= ROUND_OFF * energy
    else:
        assert world.kinetic_energy() <= energy * (1 + ROUND_OFF)


@settings(max_examples=60, deadline=None)
@given(ratio_exponent=st.integers(-12, 12), v=st.floats(-1e3, 1e3), offset=st.floats(-0.9, 0.9))
def test_extreme_mass_ratios_keep_the_lecture_result(ratio_exponent, v, offset):
    # Mass ratios up to 1e12 lose no precision: the inverse-mass form has no
    # difference of large masses. Head-on along x: lecture's 1-D formulas.
    m1, m2 = 1.0, 10.0 ** ratio_exponent
    world = world_of([{'position': [0, 0, 0], 'velocity': [v, 0, 0], 'radius': 0.5, 'mass': m1},
                      {'position': [0.99, 0, 0], 'velocity': [offset, 0, 0], 'radius': 0.5,
                       'mass': m2}], dt=1e-6)   # moves <= 1 mm of the 10 mm overlap
    approaching = v - offset > 0
    world.step(1)
    assert_finite(world)
    if approaching:
        expected1 = ((m1 - m2) * v + 2 * m2 * offset) / (m1 + m2)
        expected2 = ((m2 - m1) * offset + 2 * m1 * v) / (m1 + m2)
        scale = abs(v) + abs(offset)
        assert abs(world.state.velocity[0, 0] - expected1) <= 4e-15 * scale
        assert abs(world.state.velocity[1, 0] - expected2) <= 4e-15 * scale


def random_set(seed: int, count: int, dimensions: int, static_share: float,
               mass_decades: float) -> list:
    """Return ``count`` particle specs crowded into a small box (many contacts).

    Up to 48 particles the broadphase takes all pairs, above it keeps a
    Verlet list: counts up to 90 exercise both.
    """
    rng = np.random.default_rng(seed)
    specs = []
    for k in range(count):
        position = rng.uniform(-1.5, 1.5, dimensions).tolist()
        static = rng.random() < static_share
        velocity = [0.0] * dimensions if static else rng.normal(0, 3, dimensions).tolist()
        specs.append({'position': position, 'velocity': velocity,
                      'radius': float(rng.uniform(0.1, 0.4)),
                      'mass': float('inf') if static else
                      float(10.0 ** rng.uniform(-mass_decades, mass_decades))})
    return specs


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(2, 90),
       dimensions=st.sampled_from([2, 3]),
       mass_decades=st.floats(0.0, 3.0))
def test_random_set_conserves_momentum_and_energy(seed, count, dimensions, mass_decades):
    world = world_of(random_set(seed, count, dimensions, 0.0, mass_decades), dimensions)
    momentum, energy = world.momentum(), world.kinetic_energy()
    scale = momentum_scale(world)
    world.step(30)
    assert_finite(world)
    np.testing.assert_allclose(world.momentum(), momentum, rtol=0, atol=ROUND_OFF * scale)
    assert abs(world.kinetic_energy() - energy) <= ROUND_OFF * energy
    if dimensions == 2:
        assert np.all(world.state.position[:, 2] == 0.0)
        assert np.all(world.state.velocity[:, 2] == 0.0)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(2, 90),
       dimensions=st.sampled_from([2, 3]),
       restitution=st.sampled_from([1.0, 0.5]))
def test_static_bodies_never_move_and_take_no_energy(seed, count, dimensions, restitution):
    world = world_of(random_set(seed, count, dimensions, 0.3, 1.0), dimensions, restitution)
    static = ~world.state.dynamic
    fixed = world.state.position[static].copy()
    energy = world.kinetic_energy()
    world.step(30)
    assert_finite(world)
    np.testing.assert_array_equal(world.state.position[static], fixed)
    np.testing.assert_array_equal(world.state.velocity[static], 0.0)
    if restitution == 1.0:
        assert abs(world.kinetic_energy() - energy) <= ROUND_OFF * energy
    else:
        assert world.kinetic_energy() <= energy * (1 + ROUND_OFF)
    if dimensions == 2:
        assert np.all(world.state.position[:, 2] == 0.0)
