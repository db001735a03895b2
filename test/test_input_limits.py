"""Every number bounded, duplicate keys refused, scene paths named, MemoryError as one line.

Each bound is checked at its edge (the bound itself is accepted, one past it
refused) and through each entry point that reads it: the physics' parsers,
the runner (in-process and as a process) and the spawn request the node
runs. The node's own command line is in test_node_guard.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from collision_node import World, parse_scene
from collision_node.physics.model import accuracy as acc
from collision_node.physics.model.world_commands import spawn_request
from collision_node.physics.model.effects import Effects
from collision_node.physics.model.generate import MAX_GENERATED, MAX_SEED
from collision_node.physics.model.guard import parse_text
from collision_node.physics.model.scene import (MAX_SCENE_PARTICLES, MIN_DT, load_scene,
                                                parse_scene_text, parse_spawn)
from collision_node.physics.model.validation import SceneError
from collision_node.simulate import main

ROOT = Path(__file__).resolve().parent.parent
PAIR = [{'position': [-1.0, 0.0, 0.0], 'velocity': [1.0, 0.0, 0.0], 'radius': 0.5, 'mass': 1.0},
        {'position': [1.0, 0.0, 0.0], 'radius': 0.5, 'mass': 1.0}]
GAS = {'kind': 'gas', 'count': 5, 'radius': 0.01, 'mass': 1.0,
       'region': {'min': [-1, -1, -1], 'max': [1, 1, 1]}}


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """Run ``python -m collision_node.simulate`` in a fresh interpreter."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    return subprocess.run([sys.executable, '-m', 'collision_node.simulate', *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=120)


def one_line(error: BaseException) -> str:
    """Return the error's message after checking it is one bounded line."""
    text = str(error)
    assert '\n' not in text and len(text) <= 300, text
    return text


# -- accuracy settings -----------------------------------------------------------

# (setting, value as written, the refusal after 'where.setting: ').
OVERSIZED_ACCURACY = [
    ('substeps', '1000000000', 'must be <= 1000, got 1000000000'),
    ('substeps', '1001', 'must be <= 1000, got 1001'),
    ('iterations', '10001', 'must be <= 10000, got 10001'),
    ('iterations', '1e300', 'must be <= 10000, got 1e+300'),
    ('separation_passes', '10001', 'must be <= 10000, got 10001'),
    ('event_budget', '9223372036854775807', 'must be <= 10000, got 9223372036854775807'),
    ('event_budget', '1e300', 'must be <= 10000, got 1e+300'),
    ('event_budget', '10001', 'must be <= 10000, got 10001'),
    ('collapse_time', '1.5', 'must be <= 1, got 1.5'),
    ('sleep_time', '1e7', 'must be <= 1e+06, got 1e+07'),
]
ACCURACY_IDS = [f'{key}={value}' for key, value, _ in OVERSIZED_ACCURACY]


@pytest.mark.parametrize('key, value, says', OVERSIZED_ACCURACY, ids=ACCURACY_IDS)
def test_oversized_accuracy_setting_is_refused_by_the_parser_and_in_a_scene(key, value, says):
    preset = 'exact' if key in ('event_budget', 'collapse_time') else 'fast'
    with pytest.raises(SceneError) as caught:
        acc.parse_accuracy_text(f'{{preset: {preset}, {key}: {value}}}', Effects(), '--accuracy')
    assert one_line(caught.value) == f'--accuracy.{key}: {says}'
    with pytest.raises(SceneError) as caught:
        parse_scene_text(f'accuracy: {{preset: {preset}, {key}: {value}}}\n', 'x.yaml')
    assert one_line(caught.value) == f'x.yaml: accuracy.{key}: {says}'


@pytest.mark.parametrize('key, value, says', OVERSIZED_ACCURACY, ids=ACCURACY_IDS)
def test_oversized_accuracy_flag_exits_2_with_one_line(capsys, key, value, says):
    preset = 'exact' if key in ('event_budget', 'collapse_time') else 'fast'
    assert main(['oblique_pair', '--accuracy', f'{{preset: {preset}, {key}: {value}}}']) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert captured.err.splitlines() == [f'simulate: error: --accuracy.{key}: {says}']


@pytest.mark.parametrize('setting', ['{preset: fast, substeps: 1000000000}',
                                     '{preset: exact, event_budget: 9223372036854775807}',
                                     '{preset: exact, event_budget: 1e300}'])
def test_the_reported_hang_and_overflow_settings_exit_2_from_a_process(setting):
    done = run_cli('oblique_pair', '--steps', '3', '--accuracy', setting)
    assert done.returncode == 2 and done.stdout == ''
    assert 'Traceback' not in done.stderr and 'OverflowError' not in done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith('simulate: error: --accuracy.')
    assert 'must be <= ' in lines[0]


def test_accuracy_settings_at_their_bounds_are_accepted_and_a_step_runs(tmp_path, capsys):
    """The largest event budget steps without overflow; the other bounds parse."""
    settings = acc.parse_accuracy_text(
        f'{{preset: exact, event_budget: {acc.MAX_EVENT_BUDGET}, '
        f'collapse_time: {acc.MAX_COLLAPSE_TIME}}}', Effects(), 'a')
    assert settings.event_budget == 10_000 and settings.collapse_time == 1.0
    settings = acc.parse_accuracy_text(
        f'{{substeps: {acc.MAX_SUBSTEPS}, iterations: {acc.MAX_ITERATIONS}, '
        f'sleep_time: {acc.MAX_SLEEP_TIME}}}', Effects(), 'a')
    assert (settings.substeps, settings.iterations, settings.sleep_time) == (1000, 10_000, 1e6)
    out = tmp_path / 'out.json'
    assert main(['oblique_pair', '--quiet', '--steps', '40', '--out', str(out), '--accuracy',
                 f'{{preset: exact, event_budget: {acc.MAX_EVENT_BUDGET}}}']) == 0
    result = json.loads(out.read_text())
    assert result['steps'] == 40 and result['stats']['fallback_steps'] == 0
    assert capsys.readouterr().err == ''


# -- scene, particles, generate ----------------------------------------------------

@pytest.mark.parametrize('text, says', [
    ('dt: 1e-10\n', 'x.yaml: dt: must be >= 1e-09 s, got 1e-10'),
    ('particles: [{position: [0, 0, 0], radius: 1, mass: 1, friction: 1001}]\n',
     'x.yaml: particles[0].friction: must be <= 1000, got 1001'),
    ('effects: {gravity: [0, -1.1e6, 0]}\n',
     'x.yaml: effects.gravity[1]: magnitude 1.1e+06 exceeds the supported 1e+06'),
    ('generate: [{kind: gas, count: 10000001, radius: 1e-5, mass: 1, '
     'region: {min: [0, 0, 0], max: [1, 1, 1]}}]\n',
     'x.yaml: generate[0].count: must be <= 10000000, got 10000001'),
    ('generate: [{kind: gas, count: 5, radius: 0.01, mass: 1, seed: 18446744073709551616, '
     'region: {min: [0, 0, 0], max: [1, 1, 1]}}]\n',
     'x.yaml: generate[0].seed: must be <= 18446744073709551615, got 18446744073709551616'),
    ('generate: [{kind: gas, count: 5, radius: 0.01, mass: 1, seed: 1e300, '
     'region: {min: [0, 0, 0], max: [1, 1, 1]}}]\n',
     'x.yaml: generate[0].seed: must be <= 18446744073709551615, got 1e+300'),
    ('generate:\n' + ''.join(['  - {kind: gas, count: 6e6, radius: 1e-5, mass: 1, '
                              'region: {min: [0, 0, 0], max: [1, 1, 1]}}\n'] * 2),
     'x.yaml: 12000000 particles are over the limit of 10000000 one scene or request may hold'),
], ids=['dt', 'friction', 'gravity', 'count', 'seed', 'seed-float', 'total'])
def test_oversized_scene_numbers_are_refused_naming_the_field_and_bound(text, says):
    with pytest.raises(SceneError) as caught:
        parse_scene_text(text, 'x.yaml')
    assert one_line(caught.value) == says


def test_scene_numbers_at_their_bounds_are_accepted():
    scene = parse_scene_text(f'dt: {MIN_DT}\nparticles: [{{position: [0, 0, 0], radius: 1, '
                             'mass: 1, friction: 1000}]\n', 'x.yaml')
    assert scene.dt == 1e-9 and scene.initial.friction.tolist() == [1000.0]
    spec = dict(GAS, seed=MAX_SEED)
    assert len(parse_scene({'generate': [spec]}, 'api').initial) == 5
    spec = dict(GAS, count=MAX_GENERATED, radius=1e-5)
    with pytest.raises(SceneError) as caught:          # one entry at its bound, plus one more
        parse_scene({'generate': [spec, GAS]}, 'api')
    assert one_line(caught.value) == (f'api: {MAX_SCENE_PARTICLES + 5} particles are over the '
                                      f'limit of {MAX_SCENE_PARTICLES} one scene or request '
                                      'may hold')


@pytest.mark.parametrize('change, says', [
    ({'seed': 2 ** 64}, 'spawn: generate[0].seed: must be <= 18446744073709551615'),
    ({'count': 10 ** 7 + 1}, 'spawn: generate[0].count: must be <= 10000000'),
    ({'count': 1e300}, 'spawn: generate[0].count: must be <= 10000000, got 1e+300'),
])
def test_oversized_spawn_is_refused_and_the_world_is_unchanged(change, says):
    world = World(parse_scene({'particles': PAIR}, 'api'))
    before = world.state.position.copy()
    with pytest.raises(SceneError) as caught:
        spawn_request(world, dict(GAS, **change))
    assert one_line(caught.value).startswith(says)
    assert np.array_equal(world.state.position, before) and len(world.state) == 2


def test_runner_refuses_an_oversized_scene_setting_with_one_line(tmp_path):
    scene = tmp_path / 'big.yaml'
    scene.write_text('accuracy: {preset: fast, substeps: 1e9}\n'
                     'particles: [{position: [0, 0, 0], radius: 1, mass: 1}]\n')
    done = run_cli(str(scene))
    assert done.returncode == 2 and done.stdout == ''
    assert done.stderr.splitlines() == [
        f'simulate: error: {scene}: accuracy.substeps: must be <= 1000, got 1000000000.0']


# -- duplicate keys ------------------------------------------------------------------

@pytest.mark.parametrize('text, says', [
    ('dt: 0.001\ndt: 0.5\n', "x.yaml: duplicate key 'dt' (line 2, column 1)"),
    ('particles:\n  - {position: [0, 0, 0], radius: 1, mass: 1}\n'
     'particles:\n  - {position: [5, 0, 0], radius: 1, mass: 1}\n',
     "x.yaml: duplicate key 'particles' (line 3, column 1)"),
    ('particles:\n  - {position: [0, 0, 0], radius: 1, mass: 1}\n'
     '  - position: [5, 0, 0]\n    radius: 1\n    mass: 1\n    radius: 2\n',
     "x.yaml: particles[1]: duplicate key 'radius' (line 6, column 5)"),
    ('effects:\n  walls: {min: [0, 0, 0], max: [9, 9, 9], min: [1, 1, 1]}\n',
     "x.yaml: effects.walls: duplicate key 'min' (line 2, column 43)"),
    ('{"dt": 0.001, "particles": [{"position": [0, 0, 0], "radius": 1, "mass": 1, '
     '"mass": 2}]}',
     "x.yaml: particles[0]: duplicate key 'mass' (line 1, column 77)"),
    ('dt: 0.01\n"dt": 0.02\n', "x.yaml: duplicate key 'dt' (line 2, column 1)"),
    ('host one: 1\nhost one: 2\n',
     'x.yaml: duplicate key (a key that is not a field name) (line 2, column 1)'),
], ids=['top', 'section', 'particle', 'nested', 'json', 'quoted', 'not-a-name'])
def test_duplicate_key_in_a_scene_file_is_refused_naming_key_path_and_line(
        tmp_path, text, says):
    path = tmp_path / 'x.yaml'
    path.write_text(text)
    with pytest.raises(SceneError) as caught:
        load_scene(path)
    assert one_line(caught.value) == says.replace('x.yaml', str(path))


def test_a_plain_yaml_loader_would_keep_the_last_duplicate_silently():
    """What the guard prevents: the scene would run at dt = 0.5, not the 0.001 written first."""
    assert yaml.safe_load('dt: 0.001\ndt: 0.5\n') == {'dt': 0.5}
    assert json.loads('{"dt": 0.001, "dt": 0.5}') == {'dt': 0.5}


@pytest.mark.parametrize('text, says', [
    ('{position: [0, 3, 0], radius: 0.1, mass: 1, mass: 2}',
     "spawn: duplicate key 'mass' (line 1, column 45)"),
    ('{"position": [0, 3, 0], "radius": 0.1, "mass": 1, "radius": 0.2}',
     "spawn: duplicate key 'radius' (line 1, column 51)"),
    ('[{position: [0, 3, 0], radius: 0.1, mass: 1}, '
     '{position: [0, 4, 0], radius: 0.1, mass: 1, position: [0, 5, 0]}]',
     "spawn: [1]: duplicate key 'position' (line 1, column 91)"),
    ('kind: gas\ncount: 5\nradius: 0.01\nmass: 1\n'
     'region: {min: [-1, -1, -1], max: [1, 1, 1], max: [2, 2, 2]}\n',
     "spawn: region: duplicate key 'max' (line 5, column 45)"),
], ids=['yaml', 'json', 'list', 'generate'])
def test_duplicate_key_in_a_spawn_request_is_refused(text, says):
    world = World(parse_scene({'particles': PAIR}, 'api'))
    with pytest.raises(SceneError) as caught:
        spawn_request(world, parse_text(text, 'spawn'))
    assert one_line(caught.value) == says
    with pytest.raises(SceneError):
        parse_spawn(text, 3, first_id=2)
    assert len(world.state) == 2


def test_the_same_key_in_different_mappings_is_no_duplicate():
    data = parse_text('a: {x: 1, y: 2}\nb: {x: 1, y: 2}\nc: [{x: 1}, {x: 2}]\n', 'src')
    assert data == {'a': {'x': 1, 'y': 2}, 'b': {'x': 1, 'y': 2}, 'c': [{'x': 1}, {'x': 2}]}
    assert parse_text('{"a": {"x": 1}, "b": {"x": 1}}', 'src') == {'a': {'x': 1}, 'b': {'x': 1}}


# -- scene paths -------------------------------------------------------------------------

def test_scene_paths_that_are_not_regular_files_say_what_they_are(tmp_path):
    cases = [(tmp_path, 'is a directory, not a scene file'),
             ('/dev/urandom', 'is a character device, not a scene file'),
             ('/dev/null', 'is a character device, not a scene file'),
             (tmp_path / 'missing.yaml', 'no such scene file or shipped scene (shipped: ')]
    for path, says in cases:
        with pytest.raises(SceneError) as caught:
            load_scene(path)
        assert one_line(caught.value).startswith(f'{path}: {says}')


def test_runner_names_a_directory_a_device_and_a_fifo_without_reading_them(tmp_path):
    fifo = tmp_path / 'pipe.yaml'
    os.mkfifo(fifo)                 # opening it to read would block: it is never opened
    for path, says in [(tmp_path, 'is a directory'), ('/dev/urandom', 'is a character device'),
                       (fifo, 'is a named pipe (FIFO)')]:
        done = run_cli(str(path))
        assert done.returncode == 2 and done.stdout == ''
        assert done.stderr.splitlines() == [
            f'simulate: error: {path}: {says}, not a scene file (a scene is a regular YAML '
            'file)']


def test_a_directory_named_like_a_shipped_scene_does_not_hide_it(tmp_path, monkeypatch):
    (tmp_path / 'pile').mkdir()
    monkeypatch.chdir(tmp_path)
    assert load_scene('pile').name == 'pile'


# -- MemoryError -------------------------------------------------------------------------

def test_memory_error_in_a_step_is_one_line_and_exit_2(monkeypatch, capsys):
    real = World.step

    def step(self, count=1):
        if self.steps == 2:
            raise MemoryError('Allocation failed (probably too large).')
        return real(self, count)
    monkeypatch.setattr(World, 'step', step)
    assert main(['oblique_pair', '--steps', '10']) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert captured.err.splitlines() == [
        'simulate: error: oblique_pair: out of memory in step 3 of 10 (2 particles) '
        '(MemoryError: Allocation failed (probably too large).)']


def test_memory_error_while_loading_is_one_line_and_exit_2(monkeypatch, capsys):
    def no_memory(*args, **kwargs):
        raise MemoryError()
    monkeypatch.setattr('collision_node.simulate.World', no_memory)
    assert main(['oblique_pair', '--steps', '10']) == 2
    assert capsys.readouterr().err.splitlines() == [
        'simulate: error: oblique_pair: out of memory loading the scene (MemoryError)']


def test_memory_error_while_writing_the_results_is_one_line_and_exit_2(monkeypatch, capsys):
    def no_memory(*args, **kwargs):
        raise MemoryError()
    monkeypatch.setattr('collision_node.simulate.build_result', no_memory)
    assert main(['oblique_pair', '--steps', '10']) == 2
    assert capsys.readouterr().err.splitlines() == [
        'simulate: error: out of memory writing the results (MemoryError)']
