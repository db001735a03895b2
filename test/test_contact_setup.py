"""The contact solve's set-up, compiled (``contact_kernels.solve_step``), against numpy.

The compiled solve finds the wall contacts and keeps the warm start's
contact cache inside its one call per step. Here: it finds the same
particles on each wall plane as the numpy set-up
(``solve_reference.reference_wall_contacts``), and the cache it keeps is
sorted by key, decodes to the pairs' ids, and is found again by the numpy
look-up (``solve_reference.lookup``).
"""

from __future__ import annotations

import numpy as np

from collision_node import World
from collision_node.physics.model.accuracy import PRESETS
import numba
import pytest

from collision_node.physics.stages.solve.contact_kernels import (
    find_wall_contacts, find_wall_contacts_shared)
from collision_node.physics.stages.solve.wall_kernels import WallPlanes
from collision_node.physics.model.scene import load_scene
from collision_node.physics.model.tunables import WALL_SLOP
from collision_node.physics.stages.solve.sequential_impulses import SequentialImpulseStage
from solve_reference import lookup, reference_wall_contacts


def solver_of(world: World) -> SequentialImpulseStage:
    """Return the world's contact solve stage."""
    (stage,) = [s for s in world.pipeline.stages if isinstance(s, SequentialImpulseStage)]
    return stage


def settled_pile(steps: int = 200) -> World:
    """Return the shipped 2-D pile under `fast` after ``steps`` steps (resting on 3 walls)."""
    world = World(load_scene('pile').with_accuracy(PRESETS['fast']))
    world.step(steps)
    return world


def test_compiled_wall_contacts_are_the_numpy_ones():
    world = settled_pile()
    solver, s = solver_of(world), world.state
    expected = reference_wall_contacts(solver, s, 2, 0.1, False)
    start, index, axis, inward = find_wall_contacts(
        s.position, s.radius, s.dynamic, solver._planes(2), WALL_SLOP)
    planes = solver.walls.planes(2)
    assert start.size == len(planes) + 1
    found = {}
    for (plane_axis, plane, plane_inward), lo, hi in zip(planes, start[:-1], start[1:]):
        np.testing.assert_array_equal(axis[lo:hi], plane_axis)
        np.testing.assert_array_equal(inward[lo:hi], plane_inward)
        if hi > lo:
            found[(plane_axis, plane)] = index[lo:hi]
    # The floor and both side walls hold awake discs (sleeping ones are static and
    # touch nothing in the solve); the open top none.
    assert len(found) == 3 and sum(v.size for v in found.values()) >= 10
    assert set(found) == {(w.axis, w.plane) for w in expected}
    for wall in expected:
        np.testing.assert_array_equal(found[(wall.axis, wall.plane)], wall.index)


@pytest.mark.parametrize('threads', [1, 2])
def test_shared_wall_contacts_are_the_serial_ones(threads):
    # Each particle's planes tested on the threads into a mask, then listed
    # plane by plane in particle order: the serial result, entry for entry.
    rng = np.random.default_rng(5)
    count = 20_000
    position = rng.uniform(0.0, 1.0, (count, 3))
    radius = rng.uniform(0.005, 0.02, count)
    dynamic = rng.random(count) > 0.1
    planes = WallPlanes(np.array([0, 0, 1, 1, 2, 2]), np.array([0.0, 1.0] * 3),
                        np.array([1.0, -1.0] * 3), np.full(6, 1e-15))
    previous = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        for slop, ahead in ((WALL_SLOP, 0.0), (0.5, 0.01)):
            serial = find_wall_contacts(position, radius, dynamic, planes, slop, ahead)
            shared = find_wall_contacts_shared(position, radius, dynamic, planes, slop, ahead)
            for got, expected in zip(shared, serial):
                np.testing.assert_array_equal(got, expected)
            assert serial[1].size > 100
    finally:
        numba.set_num_threads(previous)


def test_compiled_cache_is_sorted_and_found_by_the_numpy_lookup():
    world = settled_pile()
    cache, s = solver_of(world).cache, world.state
    assert cache.key.size > 300 and cache.wall_key.size > 20
    assert np.all(np.diff(cache.key) > 0) and np.all(np.diff(cache.wall_key) > 0)
    assert np.all(cache.lo < cache.hi) and np.all(cache.normal > 0.0)
    # Each cached pair, looked up by its rows the other way round, comes back
    # with its normal impulse and its tangential impulse on the other disc.
    row = {int(pid): r for r, pid in enumerate(s.ids)}
    i = np.array([row[int(b)] for b in cache.hi])
    j = np.array([row[int(a)] for a in cache.lo])
    w_index = np.array([row[int(k) // 8] for k in cache.wall_key])
    normal, tangential, wall_normal, wall_tangential = lookup(
        cache, s.ids, i, j, w_index, cache.wall_key % 8)
    np.testing.assert_array_equal(normal, cache.normal)
    np.testing.assert_array_equal(tangential, -cache.tangential)
    np.testing.assert_array_equal(wall_normal, cache.wall_normal)
    np.testing.assert_array_equal(wall_tangential, cache.wall_tangential)
