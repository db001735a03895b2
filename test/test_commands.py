"""Commands on a world without ROS: delete, teleport, impulse, placement checks, id ranges."""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World, load_scene, parse_scene_text
from collision_node.physics.model.world_commands import (MAX_STEPS, delete_request, find_overlap,
                                                         id_ranges, impulse_request, parse_ids,
                                                         parse_request, request_id_of,
                                                         spawn_request, step_count, take_options,
                                                         teleport_request)
from collision_node.physics.model.validation import SceneError

TABLE = ('name: table\ndimensions: 2\ndt: 0.01\n'
         'effects: {walls: {min: [-1.25, -0.65], max: [1.25, 0.65]}}\n'
         'particles:\n'
         '  - {position: [0, 0], velocity: [1, 0], radius: 0.1, mass: 2}\n'
         '  - {position: [0.5, 0], radius: 0.1, mass: 1}\n'
         '  - {position: [-0.5, 0], radius: 0.1, mass: .inf}\n')


@pytest.fixture
def world() -> World:
    return World(parse_scene_text(TABLE, 'table.yaml'), max_particles=1000)


def snapshot(world: World) -> dict:
    s = world.state
    return {k: getattr(s, k).copy() for k in ('ids', 'position', 'velocity', 'radius',
                                              'inv_mass')}


def assert_unchanged(world: World, before: dict) -> None:
    for key, value in before.items():
        np.testing.assert_array_equal(getattr(world.state, key), value)


def balance(world: World) -> float:
    return world.energy()['balance_error']


def test_id_ranges_are_inclusive_runs_of_consecutive_ids():
    assert id_ranges(np.array([16, 17, 18, 20, 30, 31])) == [[16, 18], [20, 20], [30, 31]]
    assert id_ranges(np.arange(16, 10016)) == [[16, 10015]]
    assert id_ranges(np.zeros(0)) == []


def test_parse_ids_takes_single_ids_and_ranges_and_refuses_huge_ranges():
    assert parse_ids([3, [5, 7], 3], 'ids', 100).tolist() == [3, 5, 6, 7]
    assert parse_ids(4, 'ids', 100).tolist() == [4]
    with pytest.raises(SceneError, match=r'^ids\[0\]: range \[0, 1000000000000\] holds'):
        parse_ids([[0, 10 ** 12]], 'ids', 100)
    with pytest.raises(SceneError, match=r'^ids\[1\]\[1\]: expected an integer id'):
        parse_ids([1, [2, 'x']], 'ids', 100)
    with pytest.raises(SceneError, match=r'ends before it starts'):
        parse_ids([[5, 2]], 'ids', 100)


def test_request_id_and_options_are_taken_off_the_body():
    data = parse_request('{request_id: abc, allow_overlap: true, position: [0, 0]}', 'spawn')
    assert request_id_of(data, 'spawn') == 'abc'
    body, options = take_options(data, 'spawn', ('allow_overlap',))
    assert body == {'position': [0, 0]} and options == {'request_id': 'abc',
                                                        'allow_overlap': True}
    assert request_id_of({'request_id': 7}, 'x') == 7
    with pytest.raises(SceneError, match=r'^x: request_id: expected a string or a finite'):
        request_id_of({'request_id': [1]}, 'x')
    with pytest.raises(SceneError, match=r'^x: allow_overlap: expected true or false'):
        take_options({'allow_overlap': 'yes'}, 'x', ('allow_overlap',))
    with pytest.raises(SceneError, match=r'^spawn: not valid YAML or JSON'):
        parse_request('{a: [1', 'spawn')


def test_delete_keeps_the_other_ids_and_spawn_never_reuses_one(world):
    e0 = world.energy()['total']
    deleted = delete_request(world, {'ids': [1], 'request_id': 5})
    assert deleted.tolist() == [1]
    assert world.state.ids.tolist() == [0, 2]
    np.testing.assert_array_equal(world.state.position[1], [-0.5, 0, 0])
    assert world.energy()['total'] == pytest.approx(e0)        # particle 1 was at rest
    new = spawn_request(world, {'position': [0.8, 0.3], 'radius': 0.05, 'mass': 1})
    assert new.tolist() == [3]                                 # not 1, not 2
    assert world.state.ids.tolist() == [0, 2, 3]
    delete_request(world, [0])
    assert abs(balance(world)) < 1e-12
    assert world.energy()['commanded'] == pytest.approx(-0.5 * 2 * 1.0)
    world.reset()
    assert world.state.ids.tolist() == [0, 1, 2] and world.next_id == 3


def test_bad_delete_is_refused_whole(world):
    before = snapshot(world)
    for request, says in [({'ids': [0, 9]}, 'no particle with id 9'),
                          ({'ids': [0, [1, 5]]}, 'holds 5 ids, more than the 3 particles'),
                          ({'idz': [0]}, 'unknown key'), ({}, 'ids: missing'),
                          ({'ids': []}, 'names no particle'), ({'ids': [-1]}, 'got -1')]:
        with pytest.raises(SceneError, match=says) as error:
            delete_request(world, request)
        assert str(error.value).startswith('delete: ') and '\n' not in str(error.value)
        assert_unchanged(world, before)


def test_teleport_sets_position_and_velocity_and_books_the_energy(world):
    teleport_request(world, {'id': 1, 'position': [0.9, 0.4], 'velocity': [0, 2]})
    np.testing.assert_array_equal(world.state.position[1], [0.9, 0.4, 0])
    np.testing.assert_array_equal(world.state.velocity[1], [0, 2, 0])
    assert world.energy()['commanded'] == pytest.approx(0.5 * 1 * 4)
    assert abs(balance(world)) < 1e-12
    teleport_request(world, {'id': 2, 'position': [-0.9, -0.4]})     # static: may be moved
    np.testing.assert_array_equal(world.state.position[2], [-0.9, -0.4, 0])


@pytest.mark.parametrize('request_, says', [
    ({'id': 1, 'position': [50, 50]}, r'teleport: position: .* is not inside the walls'),
    ({'id': 1, 'position': [0.05, 0]}, 'overlaps particle 0'),
    ({'id': 7, 'position': [0.9, 0]}, 'no particle with id 7'),
    ({'id': 2, 'velocity': [1, 0]}, 'static'),
    ({'id': 1}, 'give position and/or velocity'),
    ({'id': 1, 'position': [0, 0, 1]}, 'z must be 0'),
    ({'position': [0, 0]}, 'id: missing'),
    ({'id': 1, 'speed': 3}, 'unknown key'),
])
def test_bad_teleport_is_refused_and_the_world_is_unchanged(world, request_, says):
    before = snapshot(world)
    with pytest.raises(SceneError, match=says):
        teleport_request(world, request_)
    assert_unchanged(world, before)


def test_teleport_onto_a_particle_is_allowed_when_asked(world):
    teleport_request(world, {'id': 1, 'position': [0.05, 0], 'allow_overlap': True})
    np.testing.assert_array_equal(world.state.position[1], [0.05, 0, 0])


def test_impulse_changes_velocity_by_j_over_m(world):
    impulse_request(world, {'id': 0, 'impulse': [0.5, -1.0]})       # m = 2 kg
    np.testing.assert_array_equal(world.state.velocity[0], [1.25, -0.5, 0])
    assert abs(balance(world)) < 1e-12
    before = snapshot(world)
    with pytest.raises(SceneError, match=r'^impulse: id: particle 2 is static'):
        impulse_request(world, {'id': 2, 'impulse': [1, 0]})
    with pytest.raises(SceneError, match=r'^impulse: impulse: would give particle 0 a speed'):
        impulse_request(world, {'id': 0, 'impulse': [1e9, 0]})
    with pytest.raises(SceneError, match=r'^impulse: impulse: missing'):
        impulse_request(world, {'id': 0})
    assert_unchanged(world, before)


def test_spawn_outside_the_walls_or_overlapping_is_refused_unless_allowed(world):
    before = snapshot(world)
    with pytest.raises(SceneError, match=r'^spawn: particle 0 of the request: position '
                                         r'\[50, 50\] with radius 0.1 is not inside the walls'):
        spawn_request(world, parse_request('{position: [50, 50], radius: 0.1, mass: 1}',
                                           'spawn'))
    with pytest.raises(SceneError, match=r'particle 1 of the request: .*overlaps particle 1'):
        spawn_request(world, [{'position': [0.8, 0], 'radius': 0.1, 'mass': 1},
                              {'position': [0.55, 0], 'radius': 0.1, 'mass': 1}])
    with pytest.raises(SceneError, match=r"particle 1 of the request: overlaps the request's "
                                         r'particle 0'):
        spawn_request(world, [{'position': [0.8, 0], 'radius': 0.1, 'mass': 1},
                              {'position': [0.85, 0], 'radius': 0.1, 'mass': 1}])
    assert_unchanged(world, before)
    touching = spawn_request(world, {'position': [0.7, 0], 'radius': 0.1, 'mass': 1})
    assert touching.tolist() == [3]                       # exactly touching particle 1 is fine
    ids = spawn_request(world, {'particles': [{'position': [0.0, 0.0], 'radius': 0.1,
                                               'mass': 1}], 'allow_overlap': True})
    assert ids.tolist() == [4]
    with pytest.raises(SceneError, match='not inside the walls'):
        spawn_request(world, {'position': [2, 0], 'radius': 0.1, 'mass': 1,
                              'allow_overlap': True})


def test_overlap_check_of_a_large_spawn_uses_the_tree_and_agrees_with_brute_force():
    rng = np.random.default_rng(4)
    pos, r = rng.uniform(-1, 1, (1500, 3)), np.full(1500, 0.01)
    new, nr = rng.uniform(-1, 1, (1000, 3)), np.full(1000, 0.012)
    found = find_overlap(pos, r, np.arange(1500), new, nr)    # 1.5e6 pairs: the k-d tree
    gap = np.linalg.norm(new[:, None] - pos[None], axis=2) < (nr[:, None] + r[None]) * (1 - 1e-9)
    inner = np.linalg.norm(new[:, None] - new[None], axis=2) < 2 * 0.012 * (1 - 1e-9)
    later = np.tril(inner, -1).any(axis=1)      # new particle b overlaps an earlier one a < b
    first = min(np.flatnonzero(gap.any(axis=1))[0], np.flatnonzero(later)[0])
    assert found is not None and found[0] == first


def test_a_generated_gas_spawn_is_checked_against_the_world():
    world = World(load_scene('elastic_break'))
    with pytest.raises(SceneError, match='overlaps particle'):
        spawn_request(world, {'kind': 'gas', 'count': 200, 'radius': 0.01, 'mass': 0.1,
                              'region': {'min': [0.6, -0.2], 'max': [0.9, 0.2]}})
    ids = spawn_request(world, {'kind': 'gas', 'count': 200, 'radius': 0.01, 'mass': 0.1,
                                'region': {'min': [-1.2, -0.6], 'max': [-0.7, 0.6]}})
    assert id_ranges(ids) == [[16, 215]]


def test_step_count_is_bounded():
    assert step_count(5) == 5 and step_count({'steps': 3, 'request_id': 'a'}) == 3
    assert step_count({}) == 1
    for bad, says in [(0, 'must be 1'), (MAX_STEPS + 1, 'must be 1'), ('x', 'integer'),
                      (True, 'integer'), ({'n': 2}, 'unknown key')]:
        with pytest.raises(SceneError, match=says):
            step_count(bad)
