"""The offline runner: its JSON output, its summary and its exit codes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from collision_node.simulate import main

ROOT = Path(__file__).resolve().parent.parent


def run_cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """Run ``python -m collision_node.simulate`` in a fresh interpreter."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    return subprocess.run([sys.executable, '-m', 'collision_node.simulate', *args], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=120)


def test_json_holds_the_final_state_and_stats(tmp_path):
    scene = tmp_path / 'pair.yaml'
    scene.write_text('name: pair\ndt: 0.01\nduration: 1.0\nparticles:\n'
                     '  - {position: [-1, 0, 0], velocity: [2, 0, 0], radius: 0.5, mass: 1}\n'
                     '  - {position: [1, 0, 0], radius: 0.5, mass: 1}\n'
                     '  - {position: [0, 5, 0], radius: 0.5, mass: .inf}\n')
    out = tmp_path / 'out.json'
    assert main([str(scene), '--quiet', '--out', str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result) == {'scene', 'time', 'steps', 'particles', 'stats'}
    assert result['scene'] == 'pair' and result['steps'] == 100
    assert result['time'] == pytest.approx(1.0, rel=1e-15)
    particles = result['particles']
    assert [p['id'] for p in particles] == [0, 1, 2]
    assert set(particles[0]) == {'id', 'position', 'velocity', 'radius', 'mass'}
    # Equal masses, head on: the velocities swap.
    assert particles[0]['velocity'] == [0.0, 0.0, 0.0]
    assert particles[1]['velocity'] == [2.0, 0.0, 0.0]
    assert particles[0]['mass'] == 1.0 and particles[2]['mass'] is None   # static: null
    assert particles[2]['radius'] == 0.5 and particles[2]['position'] == [0.0, 5.0, 0.0]
    stats = result['stats']
    assert {'collisions', 'kinetic_energy', 'momentum', 'max_penetration',
            'wall_seconds'} <= set(stats)
    assert stats['collisions'] == 1
    assert stats['kinetic_energy'] == [2.0, 2.0]
    assert stats['momentum'] == [[2.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    # Default preset balanced (ccd): the pair meets at its time of impact, no overlap.
    assert stats['max_penetration'] == 0.0
    assert stats['wall_seconds'] >= 0.0


def test_steps_and_duration_override_the_scene(tmp_path):
    out = tmp_path / 'out.json'
    assert main(['oblique_pair', '--quiet', '--steps', '7', '--out', str(out)]) == 0
    assert json.loads(out.read_text())['steps'] == 7
    assert main(['oblique_pair', '--quiet', '--duration', '0.05', '--out', str(out)]) == 0
    result = json.loads(out.read_text())
    assert result['steps'] == 50 and result['time'] == pytest.approx(0.05)


def test_summary_on_stdout(capsys):
    assert main(['cradle']) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith('cradle: 5 particles, 1000 steps (1 s simulated) in ')
    assert lines[1] == 'collisions: 4 particle, 0 wall'
    assert lines[2] == 'kinetic energy: 0.25 -> 0.25 J (change +0 J)'


def test_explain_lists_the_pipeline(capsys):
    assert main(['billiards_break', '--explain']) == 0
    lines = capsys.readouterr().out.splitlines()
    names = [line.split(':')[0].split('. ')[1] for line in lines]
    # Default preset (balanced): swept contacts handle the table's walls in time order.
    assert names == ['swept_contacts', 'narrowphase', 'separation']
    assert 'walls' not in names


def test_cli_success_exits_zero_and_writes_json(tmp_path):
    out = tmp_path / 'o.json'
    done = run_cli('oblique_pair', '--steps', '10', '--out', str(out))
    assert done.returncode == 0, done.stderr
    assert 'oblique_pair: 2 particles, 10 steps' in done.stdout
    assert json.loads(out.read_text())['steps'] == 10


@pytest.mark.parametrize('args, says', [
    (('no_such_scene',), 'no_such_scene: no such scene file or shipped scene'),
    ((), 'the following arguments are required: scene'),
    (('oblique_pair', '--steps', '-1'), '--steps must be >= 0'),
    (('oblique_pair', '--steps', 'many'), "invalid int value: 'many'"),
    (('oblique_pair', '--duration', 'nan'), '--duration must be a finite number >= 0'),
    (('oblique_pair', '--steps', '3', '--duration', '1'), 'not allowed with argument'),
    (('oblique_pair', '--frobnicate'), 'unrecognized arguments: --frobnicate'),
    (('oblique_pair', '--steps', '1', '--out', '/nonexistent-dir/x.json'),
     '--out /nonexistent-dir/x.json: No such file or directory'),
    (('BAD',), 'particles[1].radius: must be >= 1e-30, got -0.5'),
])
def test_cli_bad_input_exits_two_with_one_line(tmp_path, args, says):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('particles:\n  - {position: [0, 0, 0], radius: 0.5, mass: 1}\n'
                   '  - {position: [2, 0, 0], radius: -0.5, mass: 1}\n')
    args = tuple(str(bad) if a == 'BAD' else a for a in args)
    done = run_cli(*args)
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith('simulate: error: ') and says in lines[0]
    assert 'Traceback' not in done.stderr and done.stdout == ''


def test_non_finite_state_is_refused(world_from):
    # A state poked to NaN from outside must stop the world, not spread.
    world = world_from(particles=[{'position': [0, 0, 0], 'radius': 0.5, 'mass': 1}])
    world.state.velocity[0, 0] = np.nan
    with pytest.raises(FloatingPointError, match='non-finite'):
        world.step()
