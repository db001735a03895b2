"""Hard case 15: non-finite and absurd input is rejected at every entry point.

Entry points: a scene file (``load_scene``), the API (``parse_scene``), a
spawn request as YAML or JSON (``parse_spawn`` and ``World.spawn_text``,
which the node's spawn topic calls). Each rejection is one ``SceneError``
line naming the source, the particle index and the field, and a rejected
spawn leaves the world exactly as it was.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from collision_node import SceneError, World, load_scene, parse_scene, parse_spawn
from collision_node.physics.model.accuracy import PRESETS

NAN, INF = math.nan, math.inf
GOOD = [{'position': [-2.0, 0.0, 0.0], 'velocity': [1.0, 0.0, 0.0], 'radius': 0.5, 'mass': 1.0},
        {'position': [2.0, 0.0, 0.0], 'radius': 0.5, 'mass': 2.0}]

# (field, bad value, words the error must contain)
BAD_PARTICLE_FIELDS = [
    ('position', [NAN, 0.0, 0.0], 'NaN'),
    ('position', [INF, 0.0, 0.0], 'finite'),
    ('position', [0.0, -INF, 0.0], 'finite'),
    ('position', [1e308, 0.0, 0.0], 'exceeds'),
    ('position', [0.0, 0.0], 'expected [x, y, z]'),
    ('velocity', [0.0, NAN, 0.0], 'NaN'),
    ('velocity', [INF, 0.0, 0.0], 'finite'),
    ('velocity', [1e308, 0.0, 0.0], 'exceeds'),
    ('velocity', [2.5e8, 2.5e8, 0.0], 'speed exceeds'),
    ('radius', NAN, 'NaN'),
    ('radius', INF, 'finite'),
    ('radius', -1.0, 'must be >='),
    ('radius', 0.0, 'must be >='),
    ('radius', 1e308, 'must be <='),
    ('radius', True, 'expected a number'),
    ('radius', '0.5', 'expected a number'),
    ('mass', NAN, 'NaN'),
    ('mass', 0.0, 'must be >='),
    ('mass', -1.0, 'must be >='),
    ('mass', -INF, 'finite'),
    ('mass', 1e308, 'must be <='),
    ('mass', 1e-40, 'must be >='),
    ('restitution', NAN, 'NaN'),
    ('restitution', 1.5, 'must be <='),
]
FIELD_IDS = [f'{field}={value!r}' for field, value, _ in BAD_PARTICLE_FIELDS]


def with_bad_third(field, value) -> list:
    """Return three particles of which the third (index 2) has one bad field."""
    bad = {'position': [0.0, 3.0, 0.0], 'velocity': [0.0, -1.0, 0.0], 'radius': 0.5,
           'mass': 1.0}
    bad[field] = value
    return [dict(p) for p in GOOD] + [bad]


def assert_one_line(error: SceneError, prefix: str, *words: str) -> None:
    """Check the message is one line, starts with ``prefix`` and names the problem."""
    message = str(error)
    assert '\n' not in message
    assert message.startswith(prefix), message
    for word in words:
        assert word in message, message


def snapshot(world: World) -> dict:
    """Return copies of everything a spawn could change."""
    s = world.state
    return {'ids': s.ids.copy(), 'position': s.position.copy(), 'velocity': s.velocity.copy(),
            'radius': s.radius.copy(), 'inv_mass': s.inv_mass.copy(), 'steps': world.steps,
            'restitution': None if s.restitution is None else s.restitution.copy()}


def assert_unchanged(world: World, before: dict) -> None:
    """Fail if the world differs from ``before`` in any array or counter."""
    after = snapshot(world)
    assert after.keys() == before.keys()
    for key, value in before.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(after[key], value, err_msg=key)
        else:
            assert after[key] == value, key


@pytest.mark.parametrize('field, value, words', BAD_PARTICLE_FIELDS, ids=FIELD_IDS)
def test_case15_bad_particle_rejected_from_scene_file(tmp_path, field, value, words):
    path = tmp_path / 'bad.yaml'
    path.write_text(yaml.safe_dump({'particles': with_bad_third(field, value)}))
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    assert_one_line(caught.value, f'{path}: particles[2].{field}', words)


@pytest.mark.parametrize('field, value, words', BAD_PARTICLE_FIELDS, ids=FIELD_IDS)
def test_case15_bad_particle_rejected_from_api(field, value, words):
    with pytest.raises(SceneError) as caught:
        parse_scene({'particles': with_bad_third(field, value)}, 'api')
    assert_one_line(caught.value, f'api: particles[2].{field}', words)


@pytest.mark.parametrize('preset', sorted(PRESETS))
@pytest.mark.parametrize('field, value, words', BAD_PARTICLE_FIELDS, ids=FIELD_IDS)
def test_case15_bad_spawn_rejected_without_state_change(preset, field, value, words):
    world = World(parse_scene({'accuracy': preset, 'particles': GOOD}, 'api'))
    world.step(3)
    before = snapshot(world)
    text = yaml.safe_dump(with_bad_third(field, value))
    with pytest.raises(SceneError) as caught:
        world.spawn_text(text, source='spawn')
    assert_one_line(caught.value, f'spawn: particles[2].{field}', words)
    with pytest.raises(SceneError):
        parse_spawn(text, 3, len(world.state))
    assert_unchanged(world, before)
    # The world goes on as if nothing had been sent; the next good spawn gets the next id.
    assert world.spawn_text(yaml.safe_dump(GOOD[:1])).tolist() == [2]


@pytest.mark.parametrize('token', ['NaN', 'Infinity', '-Infinity', '1e999', '-1e999'])
def test_case15_non_finite_json_spawn_rejected(token):
    """JSON writers spell non-finite numbers NaN / Infinity; they never get through."""
    world = World(parse_scene({'particles': GOOD}, 'api'))
    before = snapshot(world)
    text = json.dumps([GOOD[0], GOOD[1], dict(GOOD[1], position=[0.0, 5.0, 0.0])])
    text = text.replace('"mass": 2.0}]', f'"mass": {token}}}]')
    assert token in text
    with pytest.raises(SceneError) as caught:
        world.spawn_text(text, source='spawn')
    assert_one_line(caught.value, 'spawn: particles[2].mass')
    assert_unchanged(world, before)


# Scene-level settings: (key path, bad value, words the error must contain).
BAD_SCENE_SETTINGS = [
    (('dt',), NAN, 'NaN'),
    (('dt',), INF, 'finite'),
    (('dt',), 0.0, 'must be >'),
    (('dt',), -0.01, 'must be >'),
    (('dt',), 10.0, 'must be <='),
    (('duration',), NAN, 'NaN'),
    (('duration',), INF, 'finite'),
    (('duration',), -1.0, 'must be >='),
    (('dimensions',), 4, 'must be 2 or 3'),
    (('accuracy',), 'ludicrous', 'unknown preset'),
    (('effects', 'gravity'), [0.0, NAN, 0.0], 'NaN'),
    (('effects', 'gravity'), [0.0, -INF, 0.0], 'finite'),
    (('effects', 'gravity'), [0.0, -1e300, 0.0], 'exceeds'),
    (('effects', 'restitution'), NAN, 'NaN'),
    (('effects', 'restitution'), 1.5, 'must be <='),
    (('effects', 'restitution'), -0.1, 'must be >='),
    (('effects', 'walls'), {'min': [NAN, -1, -1], 'max': [1, 1, 1]}, 'NaN'),
    (('effects', 'walls'), {'min': [-1, -1, -1], 'max': [1, INF, 1]}, 'finite'),
    (('effects', 'walls'), {'min': [1, -1, -1], 'max': [-1, 1, 1]}, 'max must exceed min'),
    (('generate',), [{'kind': 'gas', 'count': -5, 'radius': 0.1, 'mass': 1.0,
                      'region': {'min': [-1, -1, -1], 'max': [1, 1, 1]}}], 'count'),
    (('generate',), [{'kind': 'gas', 'count': 5, 'radius': NAN, 'mass': 1.0,
                      'region': {'min': [-1, -1, -1], 'max': [1, 1, 1]}}], 'radius'),
    (('generate',), [{'kind': 'gas', 'count': 5, 'radius': 0.1, 'mass': 1.0, 'speed': INF,
                      'region': {'min': [-1, -1, -1], 'max': [1, 1, 1]}}], 'speed'),
    (('generate',), [{'kind': 'gas', 'count': 5, 'radius': 0.1, 'mass': 1.0,
                      'region': {'min': [-1, -1, -1], 'max': [1, 1, INF]}}], 'region'),
]
SETTING_IDS = ['.'.join(path) + f'={value!r}'[:40] for path, value, _ in BAD_SCENE_SETTINGS]


def scene_with(path, value) -> dict:
    """Return a valid scene with the setting at ``path`` replaced by ``value``."""
    scene = {'particles': [dict(p) for p in GOOD],
             'effects': {'walls': {'min': [-5, -5, -5], 'max': [5, 5, 5]}}}
    target = scene
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = value
    return scene


@pytest.mark.parametrize('path, value, words', BAD_SCENE_SETTINGS, ids=SETTING_IDS)
def test_case15_bad_scene_setting_rejected_from_file_and_api(tmp_path, path, value, words):
    scene = scene_with(path, value)
    file = tmp_path / 'bad.yaml'
    file.write_text(yaml.safe_dump(scene))
    where = path[0] if path[0] != 'effects' else f'effects.{path[1]}'
    for source, load in [(str(file), lambda: load_scene(file)),
                         ('api', lambda: parse_scene(scene, 'api'))]:
        with pytest.raises(SceneError) as caught:
            load()
        assert_one_line(caught.value, f'{source}: {where}', words)


def test_case15_bad_generate_spawn_rejected_without_state_change():
    world = World(parse_scene({'particles': GOOD}, 'api'))
    before = snapshot(world)
    request = {'kind': 'gas', 'count': 5, 'radius': 0.1, 'mass': 1.0, 'speed': NAN,
               'region': {'min': [-1, -1, -1], 'max': [1, 1, 1]}}
    with pytest.raises(SceneError) as caught:
        world.spawn_text(yaml.safe_dump(request), source='spawn')
    assert_one_line(caught.value, 'spawn: generate[0].speed', 'NaN')
    assert_unchanged(world, before)


# Numerals that do not fit a 64-bit float, as text (a Python float cannot hold them).
OVERFLOWING = [('mass', '1e999', '1e999 overflows'),
               ('mass', '1' + '0' * 400, '401 digits overflows'),
               ('velocity', '[-2.5e999, 0, 0]', '-2.5e999 overflows'),
               ('position', '[0, 1e400, 0]', '1e400 overflows'),
               ('radius', '9' * 320, '320 digits overflows')]


@pytest.mark.parametrize('field, literal, words', OVERFLOWING,
                         ids=[f'{f}={t[:12]}' for f, t, _ in OVERFLOWING])
def test_case15_overflowing_numeral_rejected_everywhere(tmp_path, field, literal, words):
    """1e999 reads as inf, and would have made a static particle; 10**400 crashed."""
    values = {'position': '[0, 3, 0]', 'velocity': '[0, -1, 0]', 'radius': '0.5', 'mass': '1'}
    values[field] = literal
    bad = '{' + ', '.join(f'"{k}": {v}' for k, v in values.items()) + '}'
    good = ', '.join(json.dumps(p) for p in GOOD)
    text = f'[{good}, {bad}]'
    path = tmp_path / 'overflow.yaml'
    path.write_text(f'particles: {text}\n')
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    assert_one_line(caught.value, f'{path}: particles[2].{field}', words)
    world = World(parse_scene({'particles': GOOD}, 'api'))
    before = snapshot(world)
    with pytest.raises(SceneError) as caught:
        world.spawn_text(text, source='spawn')
    assert_one_line(caught.value, f'spawn: particles[2].{field}', words)
    assert_unchanged(world, before)
    # .inf is still how a scene says "static".
    world.spawn_text('{"position": [0, 9, 0], "radius": 0.5, "mass": .inf}')
    assert world.state.inv_mass[-1] == 0.0


def test_case15_huge_integer_rejected_from_api():
    scene = {'particles': [dict(GOOD[0]), dict(GOOD[1], mass=10 ** 400)]}
    with pytest.raises(SceneError) as caught:
        parse_scene(scene, 'api')
    assert_one_line(caught.value, 'api: particles[1].mass', '401 digits overflows')
