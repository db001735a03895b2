"""The runner's pictures: the snapshot is to scale, the energy plot sums to the balance.

The figures are checked by what they hold (axes limits, circle centres and
radii, wall segments, where metres land in pixels, the plotted series), not
by comparing pixels; the written PNG files by their declared size.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from collision_node.pictures import (ENERGY_HEIGHT_IN, FIGURE_DPI, FIGURE_WIDTH_IN,
                                     SNAPSHOT_MARGIN, EnergyRecorder, energy_figure,
                                     snapshot_figure)
from collision_node.simulate import main

TABLE = {'min': [-1.27, -0.635], 'max': [1.27, 0.635], 'restitution': 0.8}


def png_size(path: Path) -> tuple[int, int]:
    """Return (width, height) in pixels from a PNG file's header."""
    data = path.read_bytes()
    assert data[:8] == b'\x89PNG\r\n\x1a\n', f'{path} is not a PNG file'
    return struct.unpack('>II', data[16:24])


def by_gid(items, gid: str) -> list:
    """Return the artists of ``items`` whose gid is ``gid``."""
    return [item for item in items if item.get_gid() == gid]


def table_world(world_from):
    """Return a 2-D table with walls, three moving balls and a static post."""
    return world_from(dimensions=2, dt=0.001, effects={'walls': TABLE, 'restitution': 0.9},
                      particles=[
                          {'position': [-0.6, 0.0], 'velocity': [3.0, 0.4],
                           'radius': 0.03, 'mass': 0.17},
                          {'position': [0.5, 0.1], 'radius': 0.03, 'mass': 0.17},
                          {'position': [0.8, -0.3], 'velocity': [-1, 0], 'radius': 0.06,
                           'mass': 0.5},
                          {'position': [0.0, 0.4], 'radius': 0.1, 'mass': float('inf')}])


def test_snapshot_draws_every_particle_to_scale_inside_the_walls(world_from):
    world = table_world(world_from)
    world.step(200)
    figure = snapshot_figure(world)
    figure.draw_without_rendering()          # lays out the axes: transData is final
    axes = figure.axes[0]
    margin = SNAPSHOT_MARGIN * 2.54
    # The view is the table (the balls lie inside it) plus the margin, in metres.
    np.testing.assert_allclose(axes.get_xlim(), (-1.27 - margin, 1.27 + margin), rtol=1e-12)
    np.testing.assert_allclose(axes.get_ylim(), (-0.635 - margin, 0.635 + margin),
                               rtol=1e-12)
    state = world.state
    dynamic, = by_gid(axes.collections, 'dynamic')
    static, = by_gid(axes.collections, 'static')
    np.testing.assert_array_equal(dynamic.get_offsets(), state.position[:3, :2])
    np.testing.assert_array_equal(dynamic.get_widths(), 2 * state.radius[:3])
    np.testing.assert_array_equal(dynamic.get_heights(), 2 * state.radius[:3])
    np.testing.assert_array_equal(static.get_offsets(), [[0.0, 0.4]])
    np.testing.assert_array_equal(static.get_widths(), [0.2])
    # Static grey, dynamic coloured by speed from 0.
    np.testing.assert_allclose(static.get_facecolor()[0][:3], [0.6, 0.6, 0.6])
    np.testing.assert_allclose(dynamic.get_array(),
                               np.linalg.norm(state.velocity[:3], axis=1))
    assert dynamic.get_clim()[0] == 0.0
    # The four cushions: the rectangle of the walls exactly.
    walls = sorted(tuple(map(tuple, np.column_stack(line.get_data()).round(12)))
                   for line in by_gid(axes.get_lines(), 'wall'))
    assert walls == sorted([((-1.27, -0.635), (-1.27, 0.635)), ((1.27, -0.635), (1.27, 0.635)),
                            ((-1.27, -0.635), (1.27, -0.635)), ((-1.27, 0.635), (1.27, 0.635))])
    # In pixels: one metre spans the same along x and y, so the 2.54 m x 1.27 m
    # table is twice as wide as tall, and a ball's radius is r metres of it.
    corners = axes.transData.transform([[-1.27, -0.635], [1.27, 0.635]])
    width, height = corners[1] - corners[0]
    assert width / height == pytest.approx(2.0, rel=1e-9)
    per_metre = width / 2.54
    assert per_metre > 200                   # the table fills most of a 900-pixel figure
    centre, rim = axes.transData.transform([state.position[2, :2],
                                            state.position[2, :2] + [0.06, 0.0]])
    assert rim[0] - centre[0] == pytest.approx(0.06 * per_metre, rel=1e-9)
    figure_px = figure.get_size_inches() * FIGURE_DPI
    assert corners.min() >= 0 and (corners <= figure_px).all()


def test_open_floor_spans_the_view_and_a_far_lid_stays_out(world_from):
    world = world_from(dimensions=2, effects={'gravity': [0, -9.81],
                                              'walls': {'min': [0.0, 0.0], 'max': [1.6, 20.0]}},
                       particles=[{'position': [0.4, 0.3], 'radius': 0.05, 'mass': 1},
                                  {'position': [1.2, 0.1], 'radius': 0.05, 'mass': 1}])
    axes = snapshot_figure(world).axes[0]
    low, high = axes.get_ylim()
    assert high < 2.0                        # the lid at y = 20 m would shrink the discs to dots
    segments = [np.column_stack(line.get_data()) for line in by_gid(axes.get_lines(), 'wall')]
    assert len(segments) == 3                # floor and two sides, no lid
    floor = next(s for s in segments if s[0, 1] == s[1, 1])
    np.testing.assert_array_equal(floor, [[0.0, 0.0], [1.6, 0.0]])
    for side in (s for s in segments if s[0, 0] == s[1, 0]):
        np.testing.assert_array_equal(side[:, 1], [0.0, high])   # up to the view's top
    # A single floor plane (open sides) runs across the whole view.
    floor_only = world_from(effects={'walls': {'min': [None, 0.0, None]}},
                            particles=[{'position': [0, 1, 0.5], 'radius': 0.1, 'mass': 1},
                                       {'position': [2, 1, -3], 'radius': 0.2, 'mass': 1}])
    axes = snapshot_figure(floor_only).axes[0]
    line, = by_gid(axes.get_lines(), 'wall')
    np.testing.assert_array_equal(np.column_stack(line.get_data()),
                                  [[axes.get_xlim()[0], 0.0], [axes.get_xlim()[1], 0.0]])
    assert 'projected on x-y' in axes.get_title()


def stack_tops(figure) -> dict[str, np.ndarray]:
    """Return the plotted upper edge of every band and the budget line, by gid."""
    return {line.get_gid(): np.asarray(line.get_ydata()) for line in figure.axes[0].get_lines()}


def test_energy_plot_stacks_to_the_energy_put_in_at_every_sample(world_from):
    # Gravity, walls, restitution and friction: potential, spin and four kinds of loss.
    world = world_from(dimensions=2, dt=1 / 240, accuracy='fast',
                       effects={'gravity': [0, -9.81], 'restitution': 0.5, 'friction': 0.4,
                                'walls': {'min': [0, 0], 'max': [1, 3], 'restitution': 0.6}},
                       generate=[{'kind': 'gas', 'count': 40, 'radius': 0.04, 'mass': 0.2,
                                  'speed': 1.5, 'seed': 3,
                                  'region': {'min': [0, 0.5], 'max': [1, 2]}}])
    steps = 600
    recorder = EnergyRecorder(world, steps, max_samples=101)
    for _ in range(steps // 2):
        world.step()
        recorder()
    ids = world.spawn_text('{position: [0.5, 2.8], velocity: [0, -1], radius: 0.04, '
                           'mass: 0.3}')
    assert len(ids) == 1
    recorder.sample()                        # the spawn's energy enters the budget here
    for _ in range(steps // 2):
        world.step()
        recorder()
    recorder.finish()
    series = recorder.series()
    assert recorder.stride == 6 and len(series.time) == 102
    assert series.time[0] == 0.0 and series.time[-1] == world.time
    assert {'restitution', 'walls', 'friction'} <= set(series.losses)
    assert series.kinetic_rotational.any() and series.potential.any()
    # The budget steps up by the spawned particle's energy, nowhere else.
    jumps = np.flatnonzero(np.diff(series.budget))
    assert len(jumps) == 1 and series.time[jumps[0] + 1] == series.time[jumps[0]]
    # Kinetic + potential + every loss = start + spawned + commanded, at every sample.
    total = (series.kinetic_linear + series.kinetic_rotational + series.potential
             + sum(series.losses.values()))
    np.testing.assert_allclose(total - series.budget, series.balance_error, rtol=0, atol=1e-12)
    assert np.abs(series.balance_error).max() < 1e-9 * series.budget.max()
    # The last sample is the world's own balance.
    end = world.energy()
    assert series.kinetic_linear[-1] == end['kinetic_linear']
    assert {name: values[-1] for name, values in series.losses.items()} == end['dissipated']
    # The figure plots exactly these bands, and the top one lies on the budget line.
    tops = stack_tops(energy_figure(series))
    names = [name for name, _ in series.stack()]
    assert names[-3:] == ['potential', 'kinetic_rotational', 'kinetic_linear']
    assert set(names[:-3]) == set(series.losses)
    lower = np.zeros_like(series.time)
    for name, values in series.stack():
        np.testing.assert_allclose(tops[f'top:{name}'] - lower, values, rtol=0, atol=1e-9)
        lower = tops[f'top:{name}']
    np.testing.assert_array_equal(tops['budget'], series.budget)
    error = np.abs(tops[f'top:{names[-1]}'] - tops['budget'])
    assert (error <= np.abs(series.balance_error) + 1e-12 * series.budget.max()).all()


def test_energy_samples_stay_bounded_and_end_at_the_state_reached(world_from):
    world = world_from(particles=[{'position': [0, 0, 0], 'velocity': [1, 0, 0],
                                   'radius': 0.1, 'mass': 1}])
    recorder = EnergyRecorder(world, 5000)
    for _ in range(5000):
        world.step()
        recorder()
    recorder.finish()
    assert len(recorder.series().time) <= 2000
    # A run stopped part way (an interrupt) still ends on the state it reached.
    stopped = EnergyRecorder(world, 5000)
    world.step(7)
    stopped()
    stopped.finish()
    series = stopped.series()
    assert len(series.time) == 2 and series.time[-1] == world.time
    assert series.potential.tolist() == [0.0, 0.0] and 'potential' not in dict(series.stack())


def test_runner_writes_both_pictures_at_their_declared_size(tmp_path, capsys):
    snapshot, plot, out = tmp_path / 'break.png', tmp_path / 'energy.png', tmp_path / 'o.json'
    assert main(['billiards_break', '--steps', '400', '--quiet', '--out', str(out),
                 '--snapshot', str(snapshot), '--energy-plot', str(plot)]) == 0
    assert capsys.readouterr().err == ''
    width = round(FIGURE_WIDTH_IN * FIGURE_DPI)
    assert png_size(plot) == (width, round(ENERGY_HEIGHT_IN * FIGURE_DPI))
    swidth, sheight = png_size(snapshot)
    # The table (2.54 m x 1.27 m plus margins) sets the snapshot's shape.
    assert swidth == width and 400 < sheight < 600


@pytest.mark.parametrize('flag', ['--snapshot', '--energy-plot'])
@pytest.mark.parametrize('target, says', [
    ('', ': empty file name'),
    ('TMP', ' TMP: Is a directory'),
    ('TMP/no/such.png', ' TMP/no/such.png: No such file or directory'),
    ('TMP/x.notapicture', ' TMP/x.notapicture: unknown picture format .notapicture (one of '),
])
def test_bad_picture_target_is_refused_before_the_run(tmp_path, capsys, flag, target, says):
    target = target.replace('TMP', str(tmp_path))
    code = main(['gas_10k', '--steps', '2000', '--out', str(tmp_path / 'o.json'),
                 flag, target])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ''          # no summary: nothing ran
    lines = captured.err.splitlines()
    says = says.replace('TMP', str(tmp_path))
    assert len(lines) == 1 and lines[0].startswith(f'simulate: error: {flag}{says}'), lines
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize('args, says', [
    (('--out', 'TMP/a.png', '--snapshot', 'TMP/a.png'), '--snapshot TMP/a.png: also the file '
     'of --out'),
    (('--snapshot', 'TMP/a.png', '--energy-plot', 'TMP/../' + 'TMP_NAME/a.png'),
     '--energy-plot TMP/../TMP_NAME/a.png: also the file of --snapshot'),
])
def test_one_file_for_two_outputs_is_refused(tmp_path, capsys, args, says):
    def fill(text: str) -> str:
        return text.replace('TMP_NAME', tmp_path.name).replace('TMP', str(tmp_path))

    assert main(['oblique_pair', '--steps', '3', *map(fill, args)]) == 2
    assert capsys.readouterr().err.splitlines() == [f'simulate: error: {fill(says)}']
    assert list(tmp_path.iterdir()) == []


def test_picture_that_fails_at_write_is_reported_after_the_summary(capsys):
    assert main(['oblique_pair', '--steps', '5', '--snapshot', '/dev/full']) == 2
    captured = capsys.readouterr()
    assert 'oblique_pair: 2 particles, 5 steps' in captured.out
    assert captured.err.splitlines() == [
        'simulate: error: --snapshot /dev/full: No space left on device']
