"""Accumulated resting impulses, warm-started from the previous step (issue 11).

The compiled contact solve keeps each resting contact's normal and
tangential impulse from one step to the next, keyed by stable particle
ids (``sequential_impulses.ContactCache``), applies it first and lets
the sweeps correct it (the accumulated impulse clamped at 0 and into the
Coulomb cone). Here: a resting pile converges in few sweeps, the cache
follows particles through deletes and spawns, energy never rises in a
settled pile, and an isolated impact is bit for bit what it was without
warm starting.
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World, parse_scene
from collision_node.physics.model.accuracy import PRESETS
from collision_node.physics.model.scene import load_scene
from collision_node.physics.stages.solve.sequential_impulses import (ContactCache,
                                                                     SequentialImpulseStage)
from collision_node.physics.model.state import ParticleState
from collision_node.physics.model.tunables import COLD_START_SWEEPS
from collision_node.scenarios import disc_pyramid, STACK_MASS, sphere_column
from solve_reference import lookup, store

G = 9.81
RADIUS = 0.05


def solver_of(world: World) -> SequentialImpulseStage:
    """Return the world's contact solve stage."""
    (stage,) = [s for s in world.pipeline.stages if isinstance(s, SequentialImpulseStage)]
    return stage


def packed_pile(warm: bool, iterations: int = 64) -> World:
    """Return 100 discs packed in 10 hexagonal rows on a floor between walls (e 0.3, mu 0.5)."""
    height = np.sqrt(3.0) * RADIUS
    particles = [{'position': [(RADIUS if row % 2 == 0 else 2 * RADIUS) + 2 * RADIUS * k,
                               RADIUS + height * row], 'radius': RADIUS, 'mass': 1.0}
                 for row in range(10) for k in range(10)]
    world = World(parse_scene({
        'dimensions': 2, 'dt': 1.0 / 120.0, 'particles': particles,
        'accuracy': {'preset': 'fast', 'iterations': iterations},
        'effects': {'gravity': [0, -G], 'restitution': 0.3, 'friction': 0.5,
                    'walls': {'min': [0.0, 0.0], 'max': [21 * RADIUS, None]}}}, 'warm'))
    solver_of(world).warm_start = warm
    return world


def sweeps_per_step(world: World, steps: int) -> list[int]:
    """Step ``world`` and return the sweeps its solve ran in each step."""
    solver = solver_of(world)
    out = []
    for _ in range(steps):
        world.step()
        out.append(solver.last_sweeps)
    return out


def test_resting_pile_converges_in_few_sweeps_with_warm_starting():
    # Measured: warm 17 sweeps a step once settled (steps 120-240: the resting
    # contacts hold the discs up in their grooves, see contact_kernels.support_shift);
    # cold never gets below the tolerance and runs all 64 of them at every step.
    warm = sweeps_per_step(packed_pile(True), 240)
    cold = sweeps_per_step(packed_pile(False), 240)
    assert np.mean(warm[120:]) <= 20
    assert max(warm[200:]) < 64                          # stops before its budget
    assert min(cold[120:]) == 64
    assert len(solver_of(packed_pile(True)).cache) == 0  # a new world starts cold


@pytest.mark.parametrize('restitution', [0.0, 1.0])
def test_energy_never_rises_in_a_settling_pile_with_warm_starting(restitution):
    """500 discs packed on a floor (as test_hard_cases case 7), warm starting engaged.

    Measured: about 1,200 cached contacts warm-started in every step from the
    third on, total energy never rising.
    """
    height = np.sqrt(3.0) * RADIUS
    particles = [{'position': [(RADIUS if row % 2 == 0 else 2 * RADIUS) + 2 * RADIUS * k,
                               RADIUS + height * row], 'radius': RADIUS, 'mass': 1.0}
                 for row in range(20) for k in range(25)]
    world = World(parse_scene({
        'dimensions': 2, 'dt': 1.0 / 240.0, 'particles': particles, 'accuracy': 'fast',
        'effects': {'gravity': [0, -G], 'restitution': restitution,
                    'walls': {'min': [0.0, 0.0], 'max': [51 * RADIUS, None]}}}, 'warm'))
    solver = solver_of(world)
    previous = world.energy()['total']
    warm_steps = 0
    for _ in range(72):
        cached = len(solver.cache)
        world.step()
        warm_steps += cached > 1000
        total = world.energy()['total']
        assert total <= previous + 1e-12 * abs(previous)
        previous = total
    assert warm_steps >= 60
    assert abs(world.energy()['balance_error']) < 1e-9


def test_cache_lookup_follows_ids_not_rows():
    cache = ContactCache()
    ids = np.array([3, 7, 8, 12], dtype=np.int64)
    i, j = np.array([0, 1, 2]), np.array([1, 2, 3])          # pairs (3,7) (7,8) (8,12)
    acc = np.array([1.0, 0.0, 2.0])                          # (7,8) holds nothing
    acc_t = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.2, 0.0]])
    w_index, w_code = np.array([0, 3]), np.array([2, 3])
    cache.adopt(store(ids, i, j, acc, acc_t, w_index, w_code, np.array([4.0, 5.0]),
                      np.zeros((2, 3))))
    assert len(cache) == 4
    # Particle 7 deleted and 20 spawned: rows shift, (8, 12) now rows (1, 2),
    # written the other way round (its tangential impulse is on the other one).
    ids2 = np.array([3, 8, 12, 20], dtype=np.int64)
    got, got_t, w_got, _ = lookup(cache, ids2, np.array([2, 0, 3]), np.array([1, 1, 2]),
                                  np.array([2, 0, 3]), np.array([3, 2, 3]))
    np.testing.assert_array_equal(got, [2.0, 0.0, 0.0])     # (12,8), (3,8) new, (20,12) new
    np.testing.assert_array_equal(got_t[0], [0.0, -0.2, 0.0])
    np.testing.assert_array_equal(got_t[1:], 0.0)
    np.testing.assert_array_equal(w_got, [5.0, 4.0, 0.0])   # 12 and 3 on their planes
    # The same particle on another plane is another contact.
    _, _, w_other, _ = lookup(cache, ids2, np.zeros(0, np.int64), np.zeros(0, np.int64),
                              np.array([0]), np.array([0]))
    np.testing.assert_array_equal(w_other, [0.0])


def settled_world(steps: int = 200) -> World:
    """Return the shipped 2-D pile under `fast` after ``steps`` steps."""
    world = World(load_scene('pile').with_accuracy(PRESETS['fast']))
    world.step(steps)
    return world


def test_cache_survives_delete_and_spawn():
    world = settled_world()
    cache = solver_of(world).cache
    before = {(int(a), int(b)): float(p) for a, b, p in zip(cache.lo, cache.hi, cache.normal)}
    assert len(before) > 300
    # Delete the disc with the most cached contacts, spawn one far above the pile.
    counts = np.bincount(np.concatenate([cache.lo, cache.hi]))
    gone = int(np.argmax(counts))
    world.delete(np.array([gone]))
    spawned = world.spawn(ParticleState(
        ids=np.zeros(1, np.int64), position=np.array([[0.8, 1.5, 0.0]]),
        velocity=np.zeros((1, 3)), radius=np.array([RADIUS]), inv_mass=np.array([1.0])))
    s = world.state
    # Every surviving cached pair maps to its own value through the new rows.
    row = {int(pid): r for r, pid in enumerate(s.ids)}
    pairs = [(a, b) for (a, b) in before if gone not in (a, b)]
    i = np.array([row[a] for a, b in pairs])
    j = np.array([row[b] for a, b in pairs])
    got, _, _, _ = lookup(cache, s.ids, i, j, np.zeros(0, np.int64), np.zeros(0, np.int64))
    np.testing.assert_array_equal(got, [before[p] for p in pairs])
    # Contacts of the deleted disc are gone (its id is never reused).
    assert int(spawned[0]) not in (gone,)
    lost = [(a, b) for (a, b) in before if gone in (a, b)]
    assert lost
    world.step(150)                      # the new disc lands at 0.45 s, the pile settles
    assert abs(world.energy()['balance_error']) < 1e-9
    assert np.isfinite(world.state.velocity).all()
    # The pile rests again with its contacts cached, none with the deleted disc.
    assert len(cache) > 300
    assert gone not in set(cache.lo) | set(cache.hi)


def two_ball_impact(warm: bool, restitution: float, friction: float) -> World:
    """Two balls meeting obliquely at 2 m/s, spinning, under gravity above a floor."""
    world = World(parse_scene({
        'dimensions': 3, 'dt': 1.0 / 120.0, 'accuracy': 'fast',
        'particles': [
            {'position': [0.0, 0.5, 0.0], 'radius': 0.1, 'mass': 1.0,
             'velocity': [1.0, 0.3, 0.1], 'angular_velocity': [0.0, 0.0, 5.0]},
            {'position': [0.205, 0.53, 0.02], 'radius': 0.1, 'mass': 2.0,
             'velocity': [-1.0, 0.0, 0.0]},
            {'position': [1.0, 0.1, 0.0], 'radius': 0.1, 'mass': 1.0,
             'velocity': [0.0, -2.0, 0.5]}],
        'effects': {'gravity': [0, -G, 0], 'restitution': restitution, 'friction': friction,
                    'walls': {'min': [None, 0.0, None], 'restitution': restitution}}}, 'imp'))
    solver_of(world).warm_start = warm
    return world


@pytest.mark.parametrize('restitution', [0.0, 0.5, 1.0])
@pytest.mark.parametrize('friction', [0.0, 0.4])
def test_isolated_impacts_are_unchanged_by_warm_starting(restitution, friction):
    warm, cold = two_ball_impact(True, restitution, friction), \
        two_ball_impact(False, restitution, friction)
    for _ in range(4):
        warm.step()
        cold.step()
        np.testing.assert_array_equal(warm.state.velocity, cold.state.velocity)
        np.testing.assert_array_equal(warm.state.position, cold.state.position)
        np.testing.assert_array_equal(warm.state.angular_velocity,
                                      cold.state.angular_velocity)
    assert warm.stats.collisions == cold.stats.collisions == 1
    assert warm.stats.wall_collisions == cold.stats.wall_collisions >= 1
    assert warm.stats.dissipated == cold.stats.dissipated


@pytest.mark.parametrize('preset', ['fast', 'balanced', 'accurate'])
def test_cold_column_starts_from_the_weight_each_contact_carries(preset):
    """A column of 20 that starts touching carries its weight down within the first step.

    The load seed (``contact_kernels._seed_loads``) starts each cold resting
    contact from the weight above it (k m g h for contact k from the top, h
    the substep), and the sweeps correct it by a few percent near the floor.
    Without the seed the sweeps of one step leave the floor far from 20 m g h.
    """
    world = World(sphere_column(20, accuracy=preset))
    weight = STACK_MASS * G * world.scene.dt / world.scene.accuracy.substeps  # m g h, N s
    world.step()
    cache = solver_of(world).cache
    ids = world.state.ids
    order = np.argsort(world.state.position[:, 1])
    # Pairs (k, k + 1) from the bottom, keyed by (lower id, higher id), carry 19 ... 1.
    carried = {(min(int(ids[a]), int(ids[b])), max(int(ids[a]), int(ids[b]))): above
               for a, b, above in zip(order[:-1], order[1:], range(19, 0, -1))}
    got = {(int(a), int(b)): float(p) for a, b, p in zip(cache.lo, cache.hi, cache.normal)}
    assert got.keys() == carried.keys()
    for pair, above in carried.items():
        assert got[pair] == pytest.approx(above * weight, rel=0.05)
    # The top two carry exactly what the seed gave them: the corrections start below.
    for pair, above in carried.items():
        if above <= 2:
            assert got[pair] == pytest.approx(above * weight, rel=1e-9)
    assert cache.wall_normal.size == 1
    assert float(cache.wall_normal[0]) == pytest.approx(20 * weight, rel=0.05)


@pytest.mark.parametrize('friction', [0.5, None])
def test_a_cold_stack_solves_with_the_cold_start_budget_then_with_the_presets(friction):
    # Every resting contact of a pyramid built in place starts cold: its first solve
    # may take up to COLD_START_SWEEPS (and needs more than fast's 8 to hold the rows'
    # thrust); from the second step on its contacts are warm and fast keeps its 8.
    world = World(disc_pyramid(10, friction=friction, accuracy='fast'))
    sweeps = sweeps_per_step(world, 4)
    assert PRESETS['fast'].iterations == 8
    assert 8 < sweeps[0] <= COLD_START_SWEEPS
    assert max(sweeps[1:]) <= 8


def test_a_pour_keeps_the_presets_budget():
    # A pour's new contacts come in a few at a time among warm ones (and land as
    # impacts first): only while its first layer lands on the floor (measured: 19
    # solves, steps 9 to 44, 33 to 128 sweeps) does a solve of the shipped pile take
    # more than balanced's 32 sweeps.
    world = World(load_scene('pile').with_accuracy(PRESETS['balanced']))
    sweeps = sweeps_per_step(world, 240)
    assert max(sweeps[60:]) <= 32
    assert sum(s > 32 for s in sweeps) <= 30
