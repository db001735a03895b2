"""The guard: every text entry point refuses oversized, deep or aliased input cheaply.

Entry points: scene files (``load_scene``), scene text (``parse_scene_text``),
spawn requests (``parse_spawn``, ``World.spawn_text``, which the node's spawn
topic calls) and accuracy text (``--accuracy``, the node parameter). Each
refusal is one short line that quotes at most a short prefix of the input
and never an interpreter message; a refused spawn leaves the world as it was.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import yaml

from collision_node import SceneError, World, load_scene, parse_scene, parse_spawn
from collision_node.physics.model.accuracy import PRESETS, parse_accuracy_text
from collision_node.physics.model.effects import Effects
from collision_node.physics.model.guard import MAX_DEPTH, MAX_TEXT_BYTES, parse_text
from collision_node.physics.model.scene import parse_scene_text
from collision_node.physics.model.validation import MAX_QUOTE, quote

GOOD = [{'position': [-2.0, 0.0, 0.0], 'velocity': [1.0, 0.0, 0.0], 'radius': 0.5, 'mass': 1.0},
        {'position': [2.0, 0.0, 0.0], 'radius': 0.5, 'mass': 2.0}]
INTERPRETER_WORDS = ('Error', 'Traceback', 'recursion', 'numpy', 'exceeds the limit')


def alias_bomb(levels: int = 8) -> str:
    """Return a spawn whose position expands to 9**levels numbers through aliases.

    Every level is nested one deeper inside ``position``, each an anchored
    list of nine aliases of the level below (the "billion laughs").
    """
    inner = '&l0 [1, 1, 1, 1, 1, 1, 1, 1, 1]'
    for level in range(1, levels + 1):
        inner = f'&l{level} [{inner}, ' + ', '.join([f'*l{level - 1}'] * 8) + ']'
    return f'{{radius: 0.5, mass: 1, position: {inner}}}'


def world_with_pair() -> World:
    """Return a stepped two-particle world to spawn into."""
    world = World(parse_scene({'particles': GOOD}, 'api'))
    world.step(2)
    return world


def snapshot(world: World) -> dict:
    """Return copies of everything a spawn could change."""
    s = world.state
    return {'ids': s.ids.copy(), 'position': s.position.copy(), 'velocity': s.velocity.copy(),
            'radius': s.radius.copy(), 'inv_mass': s.inv_mass.copy(), 'steps': world.steps}


def assert_unchanged(world: World, before: dict) -> None:
    """Fail if the world differs from ``before``."""
    after = snapshot(world)
    for key, value in before.items():
        np.testing.assert_array_equal(after[key], value, err_msg=key)


def assert_short_reason(error: SceneError, prefix: str, *words: str) -> str:
    """Check one line, short, with ``prefix`` and ``words``, and no interpreter text."""
    message = str(error)
    assert '\n' not in message and len(message) <= 300, message[:400]
    assert message.startswith(prefix), message
    for word in words:
        assert word in message, message
    for word in INTERPRETER_WORDS:
        assert word not in message, message
    return message


def refuse_spawn(text: str, *words: str) -> str:
    """Spawn ``text`` into a world, expect a refusal; return its message."""
    world = world_with_pair()
    before = snapshot(world)
    with pytest.raises(SceneError) as caught:
        world.spawn_text(text)
    assert_unchanged(world, before)
    # The world goes on: the next good spawn gets the next id.
    assert world.spawn_text(json.dumps(dict(GOOD[0], position=[0, 9, 0]))).tolist() == [2]
    return assert_short_reason(caught.value, 'spawn: ', *words)


def test_alias_bomb_in_a_spawn_is_refused_without_expanding():
    text = alias_bomb(8)
    assert len(text) < 500                   # a few hundred bytes, 9**9 numbers expanded
    refuse_spawn(text, 'aliases', 'not accepted', 'line 1')


def test_alias_bomb_in_a_scene_file_is_refused(tmp_path):
    path = tmp_path / 'bomb.yaml'
    path.write_text(f'particles:\n  - {alias_bomb(8)}\n')
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    assert_short_reason(caught.value, f'{path}: ', 'aliases', 'line 2')


def test_a_single_alias_is_refused_too():
    # An anchor and one alias expand to nothing much, but the rule is simple.
    with pytest.raises(SceneError, match=r'^s: YAML aliases \(\*name\) are not accepted'):
        parse_text('a: &x 1\nb: *x\n', 's')
    assert parse_text('a: &x 1\nb: 2\n', 's') == {'a': 1, 'b': 2}   # an anchor alone is fine


@pytest.mark.parametrize('text', ['[' * 5000, '{' * 2000, '- ' * 5000 + 'x',
                                  '[' * 5000 + ']' * 5000, '{"a": ' * 2000 + '1' + '}' * 2000],
                         ids=['[x5000', '{x2000', 'block-x5000', 'closed[x5000', 'json{x2000'])
def test_deep_nesting_is_refused_by_depth_everywhere(tmp_path, text):
    refuse_spawn(text, f'nested deeper than {MAX_DEPTH} levels')
    with pytest.raises(SceneError) as caught:
        parse_scene_text(text, 'scene.yaml')
    assert_short_reason(caught.value, 'scene.yaml: ', 'nested deeper')
    with pytest.raises(SceneError) as caught:
        parse_accuracy_text(text, Effects(), '--accuracy')
    assert_short_reason(caught.value, '--accuracy: ', 'nested deeper')
    path = tmp_path / 'deep.yaml'
    path.write_text(text)
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    assert_short_reason(caught.value, f'{path}: ', 'nested deeper')


@pytest.mark.parametrize('style', ['json', 'flow', 'block'])
def test_depth_limit_is_exactly_32_levels(style):
    def nested(depth: int) -> str:
        if style == 'block':
            return ''.join('  ' * k + 'a:\n' for k in range(depth - 1)) + '  ' * depth + 'a: 1\n'
        if style == 'json':
            return '{"a": ' * depth + '1' + '}' * depth
        return '[' * depth + '1' + ']' * depth
    data = parse_text(nested(MAX_DEPTH), 's')
    for _ in range(MAX_DEPTH):
        data = data['a'] if isinstance(data, dict) else data[0]
    assert data == 1
    with pytest.raises(SceneError, match=r'^s: nested deeper than 32 levels \(line'):
        parse_text(nested(MAX_DEPTH + 1), 's')


def test_text_over_one_mib_is_refused_by_size(tmp_path):
    request = json.dumps([dict(GOOD[0], position=[0, 3 * k, 0]) for k in range(30000)])
    assert 2 ** 21 <= len(request) < 2 ** 22                    # 2 to 4 MiB of good particles
    refuse_spawn(request, f'over the limit of {MAX_TEXT_BYTES} bytes (1 MiB)')
    path = tmp_path / 'big.yaml'
    path.write_text(f'particles: {request}\n')
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    assert_short_reason(caught.value, f'{path}: ', 'over the limit', 'not a scene file')
    # Multi-byte characters count as bytes: 400 000 characters of 3 bytes each.
    with pytest.raises(SceneError, match='1200007 bytes'):
        parse_text('name: ' + '\u20ac' * 400_000 + '\n', 's')


def test_huge_string_in_a_number_field_gives_a_short_reason():
    # 10 MB: refused by size before any parser runs.
    refuse_spawn(json.dumps(dict(GOOD[0], radius='x' * 10_000_000)), 'over the limit')
    # Just under the limit: parsed, and the reason quotes a 40-character prefix.
    for text in (json.dumps(dict(GOOD[0], radius='y' * 1_000_000)),
                 'position: [0, 3, 0]\nmass: 1\nradius: ' + 'y' * 1_000_000 + '\n'):
        message = refuse_spawn(text, 'particles[0].radius: expected a number, got ', "'yyy")
        assert message.endswith('...') and message.count('y') <= MAX_QUOTE


def test_long_numerals_are_not_converted():
    refuse_spawn(json.dumps(GOOD[0]).replace('0.5', '9' * 100_000),
                 'particles[0].radius: an integer of 100000 digits overflows a 64-bit float')
    refuse_spawn('{position: [0, 3, 0], mass: 1, radius: ' + '1:' * 100_000 + '1}',
                 'particles[0].radius: a numeral of 200001 characters is too long to read')
    refuse_spawn('{position: [0, 3, 0], mass: 1, radius: 1' + '0' * 5000 + '.0e-5000}',
                 'particles[0].radius: a numeral of 5009 characters is too long to read')


def test_json_and_yaml_give_the_same_particles():
    as_json = json.dumps({'particles': GOOD, 'generate': [
        {'kind': 'gas', 'count': 4, 'radius': 0.1, 'mass': 1e-3, 'speed': 2.5, 'seed': 7,
         'region': {'min': [5, 5, 5], 'max': [6, 6, 6]}}]})
    as_yaml = yaml.safe_dump(json.loads(as_json))
    assert as_json.startswith('{') and not as_yaml.startswith('{')
    a, b = parse_spawn(as_json, 3, 0), parse_spawn(as_yaml, 3, 0)
    assert len(a) == 6
    for field in ('ids', 'position', 'velocity', 'radius', 'inv_mass'):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    # SCI notation without a dot or a sign (YAML 1.2, JSON) is a number in both.
    assert parse_text('{"m": 1e3, "n": -2E-2}', 's') == parse_text('m: 1e3\nn: -2E-2', 's') \
        == {'m': 1000.0, 'n': -0.02}


@pytest.mark.parametrize('count', ['1e3', '1000.0', '1.0e+3'])
def test_integral_float_count_is_accepted(count):
    text = (f'generate: [{{kind: gas, count: {count}, radius: 0.01, mass: 1, '
            'region: {min: [0, 0, 0], max: [1, 1, 1]}}]\n')
    assert len(parse_scene_text(text, 's').initial) == 1000
    world = world_with_pair()
    ids = world.spawn_text(text)
    assert ids.tolist() == list(range(2, 1002))


@pytest.mark.parametrize('count, says', [('1.5', 'expected an integer, got 1.5'),
                                         ("'1e3'", "expected an integer, got '1e3'"),
                                         ('1e999', '1e999 overflows a 64-bit float'),
                                         ('-1e3', 'must be >= 1, got -1000')])
def test_non_integral_count_is_refused(count, says):
    text = (f'generate: [{{kind: gas, count: {count}, radius: 0.01, mass: 1, '
            'region: {min: [0, 0, 0], max: [1, 1, 1]}}]\n')
    refuse_spawn(text, f'generate[0].count: {says}')


@pytest.mark.parametrize('radius, low, high, says', [
    (1e-30, 0.0, 1.0, 'radius 1e-30 m makes 1.08e+89 lattice cells'),
    (1.0, -1e12, 1e12, 'radius 1 m makes 8.64e+35 lattice cells'),
    (0.5, 0.0, 1.0, '5 particles of radius 0.5 do not fit the region (room for 0'),
])
def test_generate_region_out_of_reach_is_one_line_without_numpy_warnings(radius, low, high,
                                                                         says):
    text = json.dumps({'kind': 'gas', 'count': 5, 'radius': radius, 'mass': 1.0,
                       'region': {'min': [low] * 3, 'max': [high] * 3}})
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        refuse_spawn(text, f'spawn: generate[0]: {says}')


def test_scene_that_is_not_a_scene_is_refused_without_echoing_it(tmp_path):
    secret = 'root:$6$saltsalt$0123456789abcdef:19000:0:99999:7:::'
    cases = {
        'shadow': (secret + '\ndaemon:*:19000:0:99999:7:::\n', 'a key that is not a field name'),
        'passwd': ('root:x:0:0:root:/root:/bin/bash\nbin:x:1:1:bin:/bin:/sbin/nologin\n',
                   'expected a mapping, got str'),
        'list': ('- ' + secret + '\n', 'expected a mapping, got list'),
        'string': ('"' + secret + '"\n', 'expected a mapping, got str'),
        'binary': (b'\x7fELF\x02\x01\x01\x00' + secret.encode() + b'\xff\xfe', 'not UTF-8 text'),
        'nul': (b'name: x\x00' + secret.encode(), 'not valid YAML: control characters'),
    }
    for name, (content, says) in cases.items():
        path = tmp_path / f'{name}.yaml'
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
        with pytest.raises(SceneError) as caught:
            load_scene(path)
        message = assert_short_reason(caught.value, f'{path}: ', says)[len(str(path)):]
        for word in ('root', 'salt', '0123', 'daemon', 'bash', 'ELF'):
            assert word not in message, (name, message)


@pytest.mark.parametrize('text', ['radius: !!float abc', 'radius: !!int 0x', 'radius: 2001-13-45',
                                  'radius: !!python/object:os.system x', ': : :', '{a: 1',
                                  '--- 1\n--- 2\n', 'a: 1\n\ta: 2'])
def test_malformed_yaml_is_one_line_without_interpreter_words(text):
    with pytest.raises(SceneError) as caught:
        parse_text(text, 'spawn')
    assert_short_reason(caught.value, 'spawn: ')


def test_non_finite_json_constants_are_not_numbers():
    assert parse_text('[NaN, Infinity, -Infinity]', 's') == ['NaN', 'Infinity', '-Infinity']


@pytest.mark.parametrize('preset', sorted(PRESETS))
def test_accuracy_text_still_reads_presets_and_mappings(preset):
    assert parse_accuracy_text(preset, Effects(), 'a') == PRESETS[preset]
    mapping = parse_accuracy_text(f'{{"preset": "{preset}", "substeps": 3}}', Effects(), 'a')
    assert mapping.substeps == 3
    assert parse_accuracy_text(f'{{preset: {preset}, substeps: 3}}', Effects(), 'a') == mapping


def test_quote_shows_a_short_prefix_of_anything():
    assert quote('abc') == "'abc'"
    assert quote('z' * 10_000) == "'" + 'z' * (MAX_QUOTE - 4) + '...'
    assert len(quote([[['q' * 1000] * 1000] * 1000])) <= MAX_QUOTE
    assert quote(10 ** 5000) == 'an integer of about 5001 digits'
    assert quote(-7) == '-7'
    assert '\n' not in quote('a\nb')


def test_every_reason_is_bounded_even_with_a_long_source():
    with pytest.raises(SceneError) as caught:
        parse_spawn('{position: [0, 0, 0], radius: -1, mass: 1}', 3, 0, source='s' * 5000)
    assert len(str(caught.value)) <= 300


@pytest.mark.parametrize('name', ['n' * 101, 'two\nlines', 'bell\a'])
def test_scene_name_is_a_short_printable_line(name):
    with pytest.raises(SceneError) as caught:
        parse_scene({'name': name, 'particles': GOOD}, 'api')
    assert_short_reason(caught.value, 'api: name: expected at most 100 printable characters')
    assert parse_scene({'name': 'n' * 100, 'particles': GOOD}, 'api').name == 'n' * 100
