"""Every shipped scene runs through the offline runner with the expected physics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from collision_node import load_scene
from collision_node.physics.model.scene import shipped_scene_names
from collision_node.simulate import main

SCENES = Path(__file__).resolve().parent.parent / 'scenes'


def run_scene(tmp_path, scene: str, *extra: str) -> dict:
    """Run the runner in-process on ``scene`` and return its JSON output."""
    out = tmp_path / f'{Path(scene).stem}.json'
    assert main([scene, '--quiet', '--out', str(out), *extra]) == 0
    return json.loads(out.read_text())


def velocities(result: dict) -> np.ndarray:
    """Return the final velocities in id order."""
    return np.array([p['velocity'] for p in result['particles']])


def test_every_shipped_scene_loads_and_has_a_comment():
    # Scenes added by other issues are covered too: each must load and explain itself.
    for path in sorted(SCENES.glob('*.yaml')):
        scene = load_scene(path)
        assert len(scene.initial) > 0, path
        assert path.read_text().startswith('#'), f'{path} lacks a comment saying what it shows'
    assert {'oblique_pair', 'cradle', 'bullet', 'billiards_break', 'gas_10k'} <= \
        set(shipped_scene_names())


def test_cradle_momentum_leaves_from_the_far_end(tmp_path):
    result = run_scene(tmp_path, 'cradle')
    v = velocities(result)
    # The last ball takes the first ball's 1 m/s, the other four stop.
    np.testing.assert_allclose(v[4], [1.0, 0, 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(v[:4], 0.0, rtol=0, atol=1e-15)
    # One impulse per contact of the chain, none lost, none twice.
    assert result['stats']['collisions'] == 4
    energy, momentum = result['stats']['kinetic_energy'], result['stats']['momentum']
    assert energy[1] == pytest.approx(energy[0], rel=1e-15)
    np.testing.assert_allclose(momentum[1], momentum[0], rtol=0, atol=1e-15)
    # The balls stay in line.
    positions = np.array([p['position'] for p in result['particles']])
    assert np.all(positions[:, 1:] == 0.0)


def test_bullet_matches_the_lecture_formulas(tmp_path):
    result = run_scene(tmp_path, 'bullet')
    m_bullet, m_target, speed = 0.15, 4.0, 756.0
    v = velocities(result)
    bullet_after = (m_bullet - m_target) / (m_bullet + m_target) * speed
    target_after = 2.0 * m_bullet / (m_bullet + m_target) * speed
    np.testing.assert_allclose(v[0], [bullet_after, 0, 0], rtol=1e-14)
    np.testing.assert_allclose(v[1], [target_after, 0, 0], rtol=1e-14)
    # The lecture's momentum 0.15 x 756 = 113.4 kg m/s is conserved; the
    # impulse on the target is its change of momentum.
    momentum = result['stats']['momentum']
    assert momentum[0][0] == pytest.approx(113.4, rel=1e-15)
    assert momentum[1][0] == pytest.approx(113.4, rel=1e-14)
    assert m_target * v[1][0] == pytest.approx(2 * 113.4 * m_target / 4.15, rel=1e-14)
    energy = result['stats']['kinetic_energy']
    assert energy[1] == pytest.approx(energy[0], rel=1e-14)
    assert result['stats']['collisions'] == 1


def test_billiards_break_spreads_the_rack_in_the_plane(tmp_path):
    scene = load_scene('billiards_break')
    result = run_scene(tmp_path, 'billiards_break', '--steps', '2000')
    start = scene.initial.position
    end = np.array([p['position'] for p in result['particles']])
    stats = result['stats']
    # 2-D: nothing leaves the z = 0 plane, not even by round-off.
    assert np.all(end[:, 2] == 0.0) and np.all(velocities(result)[:, 2] == 0.0)
    # Every object ball of the rack has been hit and moved.
    moved = np.linalg.norm(end[1:] - start[1:], axis=1)
    assert np.all(moved > 1e-3), moved
    # The cushions keep every ball on the table.
    low = np.array([-1.27, -0.635]) + 0.028575
    high = np.array([1.27, 0.635]) - 0.028575
    assert np.all(end[:, :2] >= low - 1e-12) and np.all(end[:, :2] <= high + 1e-12)
    # Energy only goes where it is booked: restitution and cushions.
    energy = stats['kinetic_energy']
    booked = sum(stats['dissipated'].values())
    assert 0 < booked and energy[1] < energy[0]
    assert energy[1] + booked == pytest.approx(energy[0], rel=1e-12)
    assert stats['collisions'] >= 15 and stats['wall_collisions'] > 0


def test_gas_10k_keeps_energy_to_round_off(tmp_path):
    result = run_scene(tmp_path, 'gas_10k', '--steps', '60')
    stats = result['stats']
    assert len(result['particles']) == 10_000
    energy = stats['kinetic_energy']
    assert energy[0] == pytest.approx(5000.0, rel=1e-12)   # 10,000 x 1/2 x 1 kg x (1 m/s)^2
    assert energy[1] == pytest.approx(energy[0], rel=1e-12)
    assert stats['collisions'] > 1000 and stats['wall_collisions'] > 0
    positions = np.array([p['position'] for p in result['particles']])
    assert np.isfinite(positions).all()
    assert np.all(np.abs(positions) <= 2.5 - 0.05 + 1e-12)


def test_oblique_pair_conserves_momentum_and_energy(tmp_path):
    result = run_scene(tmp_path, 'oblique_pair')
    energy, momentum = result['stats']['kinetic_energy'], result['stats']['momentum']
    assert result['stats']['collisions'] == 1
    assert energy[1] == pytest.approx(energy[0], rel=1e-15)
    np.testing.assert_allclose(momentum[1], momentum[0], rtol=0, atol=1e-15)
