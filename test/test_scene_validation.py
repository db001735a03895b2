"""Every scene error is one line naming the file, the particle index and the field.

The same schema guards scene files and spawn requests (``parse_spawn``);
a rejected file or request leaves nothing behind (nothing half-loaded).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from collision_node import (SceneError, World, load_scene, parse_scene, parse_scene_text,
                            parse_spawn)

P = '{position: [0, 0, 0], radius: 0.5, mass: 1}'   # a valid 3-D particle

# (scene text, the "where" part the message must name, what it must say)
BAD_SCENES = [
    ('particles: [{position: [0, 0], radius: 1, mass: 1}', '', 'not valid YAML'),
    ('- 1\n- 2\n', '', 'expected a mapping, got list'),
    ('speed: 3\n', 'speed', 'unknown key'),
    (f'particles: [{P}, {P}, {{position: [3, 0, 0], radius: 1, mass: 1, colour: red}}]',
     'particles[2].colour', 'unknown key'),
    ('particles: {position: [0, 0, 0]}', 'particles', 'expected a list'),
    (f'particles: [{P}, {P}, 7]', 'particles[2]', 'expected a mapping'),
    ('particles: [{position: [0, 0], radius: 1, mass: 1}]', 'particles[0].position',
     'expected [x, y, z], got 2 values'),
    ('particles: [{position: [0, 0, 0, 0], radius: 1, mass: 1}]', 'particles[0].position',
     'got 4 values'),
    ('dimensions: 2\nparticles: [{position: [0, 0, 1], radius: 1, mass: 1}]',
     'particles[0].position', 'z must be 0 in a 2-D scene'),
    ('dimensions: 2\nparticles: [{position: [0, 0, 0, 0], radius: 1, mass: 1}]',
     'particles[0].position', 'expected [x, y] or [x, y, 0]'),
    ('particles: [{position: 5, radius: 1, mass: 1}]', 'particles[0].position',
     'expected a list of 3 numbers'),
    ('particles: [{position: [0, x, 0], radius: 1, mass: 1}]', 'particles[0].position[1]',
     'expected a number'),
    (f'particles: [{P}, {{position: [0, .nan, 0], radius: 1, mass: 1}}]',
     'particles[1].position[1]', 'must not be NaN'),
    (f'particles: [{P}, {{position: [3, 0, 0], velocity: [.inf, 0, 0], radius: 1, mass: 1}}]',
     'particles[1].velocity[0]', 'must be finite'),
    ('particles: [{position: [-.inf, 0, 0], radius: 1, mass: 1}]',
     'particles[0].position[0]', 'must be finite'),
    ('particles: [{position: [1.0e13, 0, 0], radius: 1, mass: 1}]',
     'particles[0].position[0]', 'exceeds the supported'),
    ('particles: [{position: [0, 0, 0], velocity: [3.0e8, 3.0e8, 0], radius: 1, mass: 1}]',
     'particles[0].velocity', 'speed exceeds'),
    (f'particles: [{P}, {P}, {{position: [3, 0, 0], radius: 0, mass: 1}}]',
     'particles[2].radius', 'must be >= 1e-30, got 0'),
    ('particles: [{position: [0, 0, 0], radius: -1, mass: 1}]', 'particles[0].radius',
     'got -1'),
    ('particles: [{position: [0, 0, 0], radius: .nan, mass: 1}]', 'particles[0].radius',
     'must not be NaN'),
    ('particles: [{position: [0, 0, 0], radius: true, mass: 1}]', 'particles[0].radius',
     'expected a number'),
    ('particles: [{position: [0, 0, 0], radius: 1, mass: 0}]', 'particles[0].mass',
     'got 0'),
    ('particles: [{position: [0, 0, 0], radius: 1, mass: -2}]', 'particles[0].mass',
     'got -2'),
    ('particles: [{position: [0, 0, 0], radius: 1, mass: -.inf}]', 'particles[0].mass',
     'must be finite'),
    ('particles: [{position: [0, 0, 0], radius: 1, mass: 1.0e31}]', 'particles[0].mass',
     'or .inf (static)'),
    ('particles: [{position: [0, 0, 0], velocity: [1, 0, 0], radius: 1, mass: .inf}]',
     'particles[0].velocity', 'a static particle (mass .inf) cannot move'),
    ('particles: [{position: [0, 0, 0], radius: 1}]', 'particles[0].mass', 'missing'),
    ('particles: [{position: [0, 0, 0], radius: 1, mass: 1, restitution: 1.5}]',
     'particles[0].restitution', 'must be <= 1'),
    ('generate: [{kind: gas, count: 1000, radius: 0.5, mass: 1,'
     ' region: {min: [0, 0, 0], max: [2, 2, 2]}}]', 'generate[0]', 'do not fit the region'),
    ('generate: [{kind: liquid, count: 1, radius: 0.5, mass: 1,'
     ' region: {min: [0, 0, 0], max: [2, 2, 2]}}]', 'generate[0].kind', 'unknown kind'),
    ('generate: [{kind: gas, count: 0, radius: 0.5, mass: 1,'
     ' region: {min: [0, 0, 0], max: [2, 2, 2]}}]', 'generate[0].count', 'must be >= 1'),
    ('generate: [{kind: gas, count: 1, radius: 0.5, mass: 1,'
     ' region: {min: [0, 0, 0], max: [2, 0, 2]}}]', 'generate[0].region',
     'max must exceed min'),
    ('generate: [{kind: gas, count: 1, radius: 0.5, mass: 1}]', 'generate[0].region',
     'missing'),
    ('dimensions: 4\n', 'dimensions', 'must be 2 or 3'),
    ('dt: 0\n', 'dt', 'must be > 0'),
    ('dt: .nan\n', 'dt', 'must not be NaN'),
    ('duration: -1\n', 'duration', 'must be >= 0'),
    ('name: ""\n', 'name', 'non-empty string'),
    ('effects: {magnetism: 1}\n', 'effects.magnetism', 'unknown key'),
    ('effects: {walls: {min: [0, 0, 0], max: [1, 1, 1], restitution: 1.5}}\n',
     'effects.walls.restitution', 'must be <= 1'),
    ('effects: {restitution: -0.1}\n', 'effects.restitution', 'must be >= 0'),
    ('accuracy: ultra\n', 'accuracy', 'unknown preset'),
]


def assert_one_line(message: str, source: str, where: str, says: str) -> None:
    """Assert the message is '<source>: <where>: ...<says>...' on one line."""
    assert '\n' not in message
    prefix = f'{source}: {where}: ' if where else f'{source}: '
    assert message.startswith(prefix), message
    assert says in message, message


@pytest.mark.parametrize('text, where, says', BAD_SCENES)
def test_bad_scene_file_names_file_index_and_field(tmp_path, text, where, says):
    path = tmp_path / 'bad.yaml'
    path.write_text(text)
    with pytest.raises(SceneError) as error:
        load_scene(path)
    assert_one_line(str(error.value), str(path), where, says)


def test_missing_scene_file_lists_the_shipped_scenes():
    with pytest.raises(SceneError) as error:
        load_scene('no/such/scene.yaml')
    message = str(error.value)
    assert message.startswith('no/such/scene.yaml: no such scene file or shipped scene')
    assert 'oblique_pair' in message and '\n' not in message


def test_unreadable_scene_file_is_one_line(tmp_path):
    path = tmp_path / 'binary.yaml'
    path.write_bytes(b'\xff\xfe\x00bad')
    with pytest.raises(SceneError) as error:
        load_scene(path)
    assert_one_line(str(error.value), str(path), '', 'cannot read')


def test_valid_scene_defaults_and_units():
    scene = parse_scene({'particles': [
        {'position': [0, 0, 0], 'radius': 0.5, 'mass': 2},
        {'position': [2, 0, 0], 'radius': 0.5, 'mass': float('inf')},
    ]}, 'inline', default_name='from_file_name')
    assert scene.name == 'from_file_name' and scene.dimensions == 3
    assert scene.dt == pytest.approx(1 / 240) and scene.duration == 1.0
    np.testing.assert_array_equal(scene.initial.ids, [0, 1])
    np.testing.assert_array_equal(scene.initial.velocity, 0.0)
    np.testing.assert_array_equal(scene.initial.inv_mass, [0.5, 0.0])   # .inf is static
    names = World(scene).pipeline.names   # default preset balanced: swept contacts
    assert names == ['swept_contacts', 'narrowphase', 'separation']


def test_exponents_without_sign_or_dot_are_numbers(tmp_path):
    # PyYAML alone reads 1e3 as a string (YAML 1.1); scenes read it as YAML 1.2 does.
    path = tmp_path / 'sci.yaml'
    path.write_text('dt: 1e-3\nparticles: [{position: [0, 0, 0], radius: 5E-2, mass: 1e3}]\n')
    scene = load_scene(path)
    assert scene.dt == 1e-3 and scene.initial.radius[0] == 0.05
    assert scene.initial.inv_mass[0] == 1e-3


def test_two_d_scene_accepts_xy_and_xy0():
    scene = parse_scene({'dimensions': 2, 'particles': [
        {'position': [1, 2], 'velocity': [3, 4], 'radius': 0.5, 'mass': 1},
        {'position': [5, 6, 0], 'velocity': [0, 0, 0], 'radius': 0.5, 'mass': 1},
    ]}, 'inline')
    np.testing.assert_array_equal(scene.initial.position, [[1, 2, 0], [5, 6, 0]])
    np.testing.assert_array_equal(scene.initial.velocity, [[3, 4, 0], [0, 0, 0]])


def test_generated_ids_follow_the_listed_particles():
    scene = parse_scene({'particles': [{'position': [-4, -4, -4], 'radius': 0.1, 'mass': 1}],
                         'generate': [{'kind': 'gas', 'count': 50, 'radius': 0.1, 'mass': 2,
                                       'speed': 3, 'seed': 1,
                                       'region': {'min': [0, 0, 0], 'max': [2, 2, 2]}}]},
                        'inline')
    state = scene.initial
    np.testing.assert_array_equal(state.ids, np.arange(51))
    np.testing.assert_allclose(np.linalg.norm(state.velocity[1:], axis=1), 3.0, rtol=1e-15)
    generated = state.position[1:]
    assert np.all(generated >= 0.1) and np.all(generated <= 1.9)
    gaps = np.linalg.norm(generated[:, None] - generated[None], axis=2) + np.eye(50) * 9
    assert gaps.min() > 0.2   # no two generated particles overlap


# ---- spawn requests: the same schema, the same messages -------------------------------

def test_spawn_accepts_every_documented_form():
    one = parse_spawn('{position: [1, 2, 3], velocity: [1, 0, 0], radius: 0.5, mass: 2}',
                      3, first_id=7)
    np.testing.assert_array_equal(one.ids, [7])
    np.testing.assert_array_equal(one.position, [[1, 2, 3]])
    assert one.inv_mass[0] == 0.5
    listed = parse_spawn(f'[{P}, {{position: [3, 0, 0], radius: 1, mass: .inf}}]', 3, 2)
    np.testing.assert_array_equal(listed.ids, [2, 3])
    np.testing.assert_array_equal(listed.inv_mass, [1.0, 0.0])
    gas = parse_spawn('{kind: gas, count: 20, radius: 0.1, mass: 1, speed: 2, seed: 3,'
                      ' region: {min: [0, 0], max: [2, 2]}}', 2, 10)
    assert len(gas) == 20 and np.all(gas.position[:, 2] == 0.0)
    both = parse_spawn(f'{{particles: [{P}], generate: [{{kind: gas, count: 5, radius: 0.1,'
                       ' mass: 1, region: {min: [2, 2, 2], max: [3, 3, 3]}}]}', 3, 0)
    np.testing.assert_array_equal(both.ids, np.arange(6))


def test_spawn_json_is_accepted():
    state = parse_spawn('{"position": [0, 1, 0], "radius": 0.25, "mass": 4}', 3, 0)
    assert state.radius[0] == 0.25 and state.inv_mass[0] == 0.25


@pytest.mark.parametrize('text, where, says', [
    ('{position: [0, 0, 0], radius: -1, mass: 1}', 'particles[0].radius', 'got -1'),
    (f'[{P}, {P}, {{position: [0, 0, 0], radius: 1, mass: 0}}]', 'particles[2].mass', 'got 0'),
    ('{position: [0, 0], radius: 1, mass: 1}', 'particles[0].position', 'got 2 values'),
    ('{position: [0, 0, .nan], radius: 1, mass: 1}', 'particles[0].position[2]', 'NaN'),
    ('{position: [0, 0, 0], radius: 1, mass: 1, spin: 3}', 'particles[0].spin', 'unknown key'),
    ('{particles: [], colour: red}', 'colour', 'unknown key'),
    ('{kind: gas, count: 10000, radius: 1, mass: 1, region: {min: [0, 0, 0], max: [1, 1, 1]}}',
     'generate[0]', 'do not fit'),
    ('[1, 2', '', 'not valid YAML or JSON'),
    ('42', '', 'expected a mapping'),
])
def test_bad_spawn_names_index_and_field(text, where, says):
    with pytest.raises(SceneError) as error:
        parse_spawn(text, 3, first_id=0, source='/spawn')
    assert_one_line(str(error.value), '/spawn', where, says)


def test_bad_spawn_leaves_the_world_untouched(world_from):
    world = world_from(particles=[{'position': [0, 0, 0], 'radius': 0.5, 'mass': 1}])
    before = world.state.copy()
    # Two good particles, then a bad one: none of the three may arrive.
    bad = f'[{{position: [3, 0, 0], radius: 0.5, mass: 1}}, {P}, ' \
          '{position: [6, 0, 0], radius: 0.5, mass: .nan}]'
    with pytest.raises(SceneError, match=r'^spawn: particles\[2\]\.mass: must not be NaN$'):
        world.spawn_text(bad)
    assert len(world.state) == 1
    for name in ('ids', 'position', 'velocity', 'radius', 'inv_mass'):
        np.testing.assert_array_equal(getattr(world.state, name), getattr(before, name))
    new_ids = world.spawn_text(f'[{{position: [3, 0, 0], radius: 0.5, mass: 1}}, {P}]')
    np.testing.assert_array_equal(new_ids, [1, 2])
    np.testing.assert_array_equal(world.state.ids, [0, 1, 2])


def test_manual_scene_example_is_a_valid_scene():
    page = (Path(__file__).resolve().parent.parent / 'docs' / 'scenes.md').read_text()
    example = page.split('## Scene files')[1].split('```yaml')[1].split('```')[0]
    scene = parse_scene_text(example, 'docs/scenes.md')
    assert scene.name == 'oblique_pair' and scene.dimensions == 2
    assert len(scene.initial) == 3 + 100
    assert scene.initial.inv_mass[2] == 0.0 and scene.effects.walls is not None


def test_oversized_generate_spawn_is_refused_before_generating(monkeypatch):
    import collision_node.physics.model.scene as scene_module
    world = World(parse_scene({'particles': [
        {'position': [0, 0, 0], 'radius': 0.1, 'mass': 1}]}, 'room'), max_particles=10)

    def must_not_generate(*args, **kwargs):
        raise AssertionError('generated particles for a request that cannot fit')

    monkeypatch.setattr(scene_module, 'generate_state', must_not_generate)
    request = ('{kind: gas, count: 5000000, radius: 0.001, mass: 1, '
               'region: {min: [-10, -10, -10], max: [10, 10, 10]}}')
    with pytest.raises(SceneError, match=r'^spawn: 5000000 particles would make 5000001, '
                                         r'over max_particles = 10$'):
        world.spawn_text(request)
    assert len(world.state) == 1
