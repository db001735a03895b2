"""A step's memory is bounded: pair explosions are searched along paths or refused in one line.

The broadphase never holds more candidate pairs than the step's memory
budget allows (``broadphase.MAX_PAIRS``). Fast movers whose reach |v| dt is
far wider than the particles are searched along their straight paths; a
world whose pairs still do not fit is refused at the request (scene load,
spawn) or at the step with ``StepTooLarge``, one line, never a crash.
"""

from __future__ import annotations

import os
import re
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from collision_node import World, parse_scene
from collision_node.physics.model.validation import SceneError
from collision_node.physics.stages.detection import broadphase
from collision_node.physics.stages.detection.broadphase import (BroadphaseStage, StepTooLarge,
                                                                swept_allowance, swept_pairs)

ROOT = Path(__file__).resolve().parent.parent
# 99,984 particles of radius 1 um at 1 m/s in a 1 mm square: each one's reach
# in a step (|v| dt = 4.2 mm) is wider than the region, so every pair (5e9)
# would be a candidate of the sphere search.
EXPLOSION = ('{kind: gas, count: 99984, radius: 1e-6, mass: 1, speed: 1, seed: 3, '
             'region: {min: [0, 0], max: [1e-3, 1e-3]}}')
# Address space for the runner: the interpreter, numpy, numba and the loaded
# kernels take about 0.5 GB of it, so the step's budget (2 GiB) does not fit
# beside them: the run must refuse before it allocates, not run out.
ADDRESS_SPACE = 2 << 30


def limited_address_space() -> None:
    """Cap the child's address space (run in the child before it executes)."""
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def test_the_pair_explosion_scene_is_refused_in_one_line_under_a_memory_limit(tmp_path):
    scene = tmp_path / 'explosion.yaml'
    scene.write_text(f'dimensions: 2\ngenerate:\n  - {EXPLOSION}\n')
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    run = subprocess.run([sys.executable, '-m', 'collision_node.simulate', str(scene),
                          '--steps', '3', '--quiet'], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=600, preexec_fn=limited_address_space)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and 'Traceback' not in run.stderr, run.stderr
    line = lines[0]
    assert line.startswith(f'simulate: error: {scene}: the contact search needs about ')
    assert 'STEP_MEMORY_BUDGET' in line and '99984 particles reach 0.0042 m' in line
    assert 'too many along their paths too' in line
    # The estimate is of the sphere search's pairs: all 5e9 of them, to a few per cent.
    needed = float(line.split('needs about ')[1].split(' ')[0])
    assert 4e9 < needed < 6e9


def test_a_spawn_of_the_explosion_is_refused_and_nothing_is_added():
    world = World(parse_scene({'dimensions': 2, 'particles': [
        {'position': [0.5, 0.5], 'radius': 1e-3, 'mass': 1.0}]}, 'small'))
    with pytest.raises(StepTooLarge) as caught:
        world.spawn_text(EXPLOSION)
    assert isinstance(caught.value, SceneError) and isinstance(caught.value, MemoryError)
    text = str(caught.value)
    assert re.match(r'spawn: the contact search needs (about|more than) \d', text), text
    assert '\n' not in text and len(text) < 300
    assert len(world.state) == 1 and world.next_id == 1
    world.step(1)


def test_a_pile_over_the_budget_is_refused_at_the_step(monkeypatch):
    # 500 particles on one point: 124,750 real overlaps, over a budget of 10,000 pairs.
    monkeypatch.setattr(broadphase, 'MAX_PAIRS', 10_000)
    n = 500
    with pytest.raises(StepTooLarge, match=r'needs about 1\.2e\+05 candidate pairs'):
        BroadphaseStage().find(np.zeros((n, 3)), np.full(n, 0.1), np.zeros((n, 3)),
                               np.ones(n), 0.01)


def path_pairs(position, velocity, radius, dt, slack):
    """Return the pairs whose straight paths come within (r_i + r_j)(1 + slack), by brute force."""
    i, j = np.triu_indices(position.shape[0], k=1)
    d = position[i] - position[j]
    u = (velocity[i] - velocity[j]) * dt
    uu = np.einsum('ij,ij->i', u, u)
    s = np.clip(-np.einsum('ij,ij->i', d, u) / np.where(uu > 0, uu, 1.0), 0.0, 1.0)
    closest = np.linalg.norm(d + s[:, None] * u, axis=1)
    hit = closest <= (radius[i] + radius[j]) * (1.0 + slack)
    return set(zip(i[hit].tolist(), j[hit].tolist()))


@pytest.mark.parametrize('dims', [2, 3])
def test_fast_movers_are_searched_along_their_paths(monkeypatch, dims):
    # 2,000 particles, a tenth of them crossing the whole world in a step: their
    # spheres of reach hold about 4e5 pairs, over a budget of 10,000; along their
    # paths they meet far fewer, and exactly those are found.
    rng = np.random.default_rng(dims)
    n, dt = 2000, 0.01
    position = np.zeros((n, 3))
    position[:, :dims] = rng.uniform(0.0, 1.0, (n, dims))
    velocity = np.zeros((n, 3))
    velocity[:, :dims] = rng.normal(scale=0.05, size=(n, dims))
    fast = rng.random(n) < 0.1
    velocity[fast, :dims] *= 4000.0
    radius = rng.uniform(0.004, 0.006, n)
    extra = swept_allowance(velocity, np.ones(n, dtype=bool), dt, None)
    sphere_i, _ = broadphase.candidate_pairs(position, radius + extra)
    monkeypatch.setattr(broadphase, 'MAX_PAIRS', 10_000)
    assert sphere_i.size > 30 * broadphase.MAX_PAIRS
    i, j = swept_pairs(position, radius, extra, velocity, dt)
    found = set(zip(i.tolist(), j.tolist()))
    assert np.all(np.diff(i * n + j) > 0)
    assert path_pairs(position, velocity, radius, dt, -1e-6) <= found
    assert found <= path_pairs(position, velocity, radius, dt, 1e-6)
    assert 20 < len(found) < broadphase.MAX_PAIRS
    # Every pair whose positions at some moment of the step overlap is among them.
    for t in np.linspace(0.0, dt, 11):
        moved = position + velocity * t
        a, b = np.triu_indices(n, k=1)
        gap = np.linalg.norm(moved[a] - moved[b], axis=1) < radius[a] + radius[b]
        assert set(zip(a[gap].tolist(), b[gap].tolist())) <= found


def test_the_stage_takes_the_path_search_when_movers_explode(monkeypatch):
    # Through the Verlet list: every particle a mover, the sphere search over the
    # budget; the stage returns the path pairs.
    monkeypatch.setattr(broadphase, 'MAX_PAIRS', 5_000)
    rng = np.random.default_rng(9)
    n, dt = 1000, 0.01
    position = rng.uniform(0.0, 1.0, (n, 3))
    velocity = rng.normal(scale=40.0, size=(n, 3))
    radius = np.full(n, 0.005)
    extra = swept_allowance(velocity, np.ones(n, dtype=bool), dt, None)
    i, j = BroadphaseStage().find(position, radius, velocity, np.ones(n), dt, extra)
    found = set(zip(i.tolist(), j.tolist()))
    assert path_pairs(position, velocity, radius, dt, -1e-6) <= found
    assert found <= path_pairs(position, velocity, radius, dt, 1e-6)
