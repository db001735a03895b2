"""The offline runner: its JSON output, its summary and its exit codes."""

from __future__ import annotations

import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from collision_node import simulate
from collision_node.physics.model.scene import load_scene
from collision_node.simulate import main

ROOT = Path(__file__).resolve().parent.parent


def run_cli(*args: str, cwd: Path = ROOT, **environment: str) -> subprocess.CompletedProcess:
    """Run ``python -m collision_node.simulate`` in a fresh interpreter (``environment`` added)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''),
               **environment)
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
    (('oblique_pair', '--threads', '-1'), '--threads: must be an integer in 0..1024'),
    (('oblique_pair', '--threads', '1000'), '--threads: 1000 threads asked for, but this '
                                            'process can run at most'),
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


def test_every_thread_count_writes_the_same_final_state(tmp_path):
    """The 10k gas under fast: its loops are shared among threads, its result is one."""
    states = []
    for threads in ('1', '2'):
        out = tmp_path / f'gas_{threads}.json'
        # A pool of 2 threads whatever the suite's own (NUMBA_NUM_THREADS=1 included).
        done = run_cli('gas_10k', '--steps', '4', '--accuracy', 'fast', '--threads', threads,
                       '--out', str(out), '--quiet', NUMBA_NUM_THREADS='2')
        assert done.returncode == 0, done.stderr
        states.append(json.loads(out.read_text()))
    one, two = states
    assert one['stats']['collisions'] == two['stats']['collisions'] > 0
    assert one['particles'] == two['particles']


def test_non_finite_state_is_refused(world_from):
    # A state poked to NaN from outside must stop the world, not spread.
    world = world_from(particles=[{'position': [0, 0, 0], 'radius': 0.5, 'mass': 1}])
    world.state.velocity[0, 0] = np.nan
    with pytest.raises(FloatingPointError, match='non-finite'):
        world.step()


@pytest.mark.parametrize('out, says', [
    ('', '--out: empty file name'),
    ('TMP', 'Is a directory'),
    ('/nonexistent-dir/deeper/x.json', 'No such file or directory'),
    ('/proc/x.json', '--out /proc/x.json: '),
])
def test_bad_out_is_refused_before_the_run(tmp_path, out, says):
    """The run (14 s of gas_10k) never starts: no summary, nothing to lose."""
    done = run_cli('gas_10k', '--steps', '2000', '--out', out.replace('TMP', str(tmp_path)))
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith('simulate: error: --out') and says in lines[0]
    assert done.stdout == ''                     # the summary comes after the run: none ran
    assert list(tmp_path.iterdir()) == []


def test_out_that_fails_at_write_still_prints_the_summary():
    done = run_cli('oblique_pair', '--steps', '5', '--out', '/dev/full')
    assert done.returncode == 2
    assert 'oblique_pair: 2 particles, 5 steps' in done.stdout
    assert done.stderr.splitlines() == [
        'simulate: error: --out /dev/full: No space left on device']


@pytest.mark.parametrize('args, says', [
    (('--duration', '1e308'), '--duration 1e+308 s is inf steps of dt = 0.001 s, over'),
    (('--duration', '1e7'), '--duration 1e+07 s is 1e+10 steps of dt = 0.001 s, over'),
    (('--steps', str(10 ** 30)), '--steps must be <= 1000000000, got 1' + '0' * 30),
])
def test_absurd_run_lengths_are_refused(args, says):
    done = run_cli('oblique_pair', *args)
    assert done.returncode == 2 and done.stdout == ''
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'simulate: error: {says}')


@pytest.mark.parametrize('content, says', [
    ('[' * 5000, 'nested deeper than 32 levels (line 1, column 33)'),
    ('root:x:0:0:root:/root:/bin/bash\n', 'expected a mapping, got str'),
    ('root:$6$salt$hash:19000:0:99999:7:::\n', 'a key that is not a field name'),
    (b'\x7fELF\x02\x01root\xff', 'cannot read: not UTF-8 text (byte 10)'),
])
def test_scene_file_that_is_not_a_scene_is_one_line_without_its_content(
        tmp_path, content, says):
    path = tmp_path / 'scene.yaml'
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    done = run_cli(str(path))
    assert done.returncode == 2 and done.stdout == ''
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'simulate: error: {path}: ')
    assert says in lines[0]
    assert 'root' not in lines[0][len(f'simulate: error: {path}'):]


def wait_for_output(process: subprocess.Popen, word: bytes, timeout: float = 60.0) -> bytes:
    """Read the process's stderr until ``word`` appears; fail after ``timeout``."""
    seen = b''
    deadline = time.monotonic() + timeout
    while word not in seen:
        left = deadline - time.monotonic()
        assert left > 0, f'no {word!r} on stderr within {timeout} s: {seen[-300:]!r}'
        ready, _, _ = select.select([process.stderr], [], [], left)
        if ready:
            chunk = os.read(process.stderr.fileno(), 4096)
            assert chunk, f'stderr closed before {word!r}: {seen[-300:]!r}'
            seen += chunk
    return seen


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_signal_stops_the_run_and_keeps_the_work(tmp_path, sig):
    """A run of 10**8 steps, stopped once its progress bar shows: summary, JSON, 130."""
    out = tmp_path / 'partial.json'
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    process = subprocess.Popen(
        [sys.executable, '-m', 'collision_node.simulate', 'oblique_pair', '--steps',
         str(10 ** 8), '--out', str(out)],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        wait_for_output(process, b'step/s')         # the progress bar: stepping has begun
        process.send_signal(sig)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, stderr
    assert b'Traceback' not in stderr and b'simulate: error' not in stderr
    result = json.loads(out.read_text())
    assert result['interrupted'] is True and result['steps_requested'] == 10 ** 8
    assert 0 < result['steps'] < 10 ** 8
    assert result['time'] == pytest.approx(result['steps'] * 0.001, rel=1e-12)
    lines = stdout.decode().splitlines()
    assert lines[0] == (f'interrupted by {signal.Signals(sig).name} after {result["steps"]} '
                        f'of {10 ** 8} steps')
    assert lines[1].startswith(f'oblique_pair: 2 particles, {result["steps"]} steps')
    # The state reached is a real one: the pair still carries its momentum and energy.
    assert result['stats']['kinetic_energy'][1] == pytest.approx(
        result['stats']['kinetic_energy'][0], rel=1e-9)


# One step of this gas takes about 8 s on one thread of an idle 2-core machine (10,000
# particles, each step split into 1000 substeps of the accurate preset): a signal sent once the
# progress bar shows (2 s into the run) lands inside the first step.
HUGE_STEP_SCENE = '''name: huge_step
dimensions: 2
dt: 0.02
duration: 0.06
effects:
  walls: {min: [-1.0, -1.0], max: [1.0, 1.0]}
accuracy: {preset: accurate, substeps: 1000}
generate:
  - {kind: gas, count: 10000, radius: 0.004, mass: 1.0, speed: 1.0, seed: 1,
     region: {min: [-1.0, -1.0], max: [1.0, 1.0]}}
'''


def start_huge_step(tmp_path: Path) -> tuple[subprocess.Popen, Path, Path]:
    """Start the runner on HUGE_STEP_SCENE; return it once its first step is under way."""
    scene, out = tmp_path / 'huge_step.yaml', tmp_path / 'huge_step.json'
    scene.write_text(HUGE_STEP_SCENE)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    process = subprocess.Popen(
        [sys.executable, '-m', 'collision_node.simulate', str(scene), '--out', str(out),
         '--threads', '1'],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        # The bar is drawn 2 s into the run even while no step has ended.
        wait_for_output(process, b'0/3')
    except BaseException:
        process.kill()
        process.wait()
        raise
    return process, scene, out


def stderr_lines(stderr: bytes) -> list[str]:
    """Return stderr's lines without the progress bar's redraws."""
    return [line for line in re.split(r'[\r\n]', stderr.decode())
            if line.strip() and 'step/s' not in line]


def test_sigterm_inside_a_huge_step_ends_the_run_within_a_second(tmp_path):
    """The step in flight is abandoned; the last completed state (step 0) is reported."""
    process, scene, out = start_huge_step(tmp_path)
    try:
        sent = time.monotonic()
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=60)
        took = time.monotonic() - sent
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, stderr
    # The runner waits STOP_GRACE_S (0.5 s) for the step to end, then writes the
    # summary and 10,000 particles of JSON (0.6 s on a loaded machine): within a
    # second, plus the process's exit. 1 s more leaves room for a loaded machine,
    # not for waiting on the step (8 s).
    assert took < 2.0, f'{took:.2f} s from SIGTERM to exit'
    assert stderr_lines(stderr) == [
        f'simulate: SIGTERM: step 1 did not end within {simulate.STOP_GRACE_S:g} s and was '
        'abandoned; reporting the state after step 0']
    assert stdout.decode().splitlines()[0] == 'interrupted by SIGTERM after 0 of 3 steps'
    result = json.loads(out.read_text())
    assert result['interrupted'] is True and result['steps_requested'] == 3
    assert result['steps'] == 0 and result['time'] == 0.0
    # Step 0 is the scene's initial state, every particle exactly as generated.
    initial = load_scene(str(scene)).initial
    np.testing.assert_array_equal([p['position'] for p in result['particles']],
                                  initial.position)
    np.testing.assert_array_equal([p['velocity'] for p in result['particles']],
                                  initial.velocity)
    assert {p.name for p in tmp_path.iterdir()} == {'huge_step.yaml', 'huge_step.json'}


def test_a_second_signal_exits_at_once_writing_nothing(tmp_path):
    process, scene, out = start_huge_step(tmp_path)
    try:
        process.send_signal(signal.SIGTERM)
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, stderr
    lines = stderr_lines(stderr)
    assert len(lines) == 1 and re.fullmatch(
        r'simulate: second SIG(INT|TERM): exiting at once, nothing written', lines[0]), lines
    assert stdout == b''
    assert {p.name for p in tmp_path.iterdir()} == {'huge_step.yaml'}
