"""The accuracy benchmark's figures, decision table and the runner's --compare-presets.

The figures are checked by content, not pixels: every panel has data,
preset labels (boxes from the figure's renderer) do not overlap, the
stacked bars' segments are the profile's stages, and the decision table
in docs/accuracy.md carries the numbers of docs/accuracy/results.json.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from pathlib import Path

import matplotlib
import numpy as np
import pytest

from collision_node.bench import accuracy_figures as figures
from collision_node.bench import cost_growth
from collision_node.physics.model.accuracy import PRESETS, check_event_mode
from collision_node.physics.model.scene import load_scene
from collision_node.physics.model.validation import SceneError
from collision_node.simulate import main as simulate

matplotlib.use('Agg')

ROOT = Path(__file__).resolve().parents[1]
RESULTS = json.loads((ROOT / 'docs' / 'accuracy' / 'results.json').read_text(encoding='utf-8'))
SHIPPED = sorted(p.stem for p in (ROOT / 'scenes').glob('*.yaml'))


def boxes(ax) -> list:
    """Return the window extents of the preset labels in ``ax``."""
    renderer = ax.figure.canvas.get_renderer()
    return [t.get_window_extent(renderer) for t in ax.texts if t.get_text() in figures.PRESETS]


def overlapping(extents) -> list:
    """Return the pairs of boxes that overlap."""
    return [(a, b) for a, b in itertools.combinations(extents, 2) if a.overlaps(b)]


def test_error_vs_cost_has_a_panel_per_kind_with_data_and_labels_apart():
    fig = figures.error_vs_cost_figure(RESULTS['runs'])
    summary = figures.kind_summary(RESULTS['runs'])
    assert list(summary) == list(figures.KINDS)     # every kind ran: five panels
    assert len(fig.axes) == len(summary)
    for ax, (kind, rows) in zip(fig.axes, summary.items()):
        assert kind in ax.get_title()
        offsets = np.concatenate([c.get_offsets() for c in ax.collections])
        assert len(offsets) == len(rows) >= 3
        assert np.all(np.isfinite(offsets)) and np.all(offsets > 0)
        # One label per marker, named for its preset, inside the panel, none overlapping.
        assert sorted(t.get_text() for t in ax.texts) == sorted(r['preset'] for r in rows)
        frame = ax.get_window_extent(fig.canvas.get_renderer())
        for box in boxes(ax):
            assert frame.x0 <= box.x0 and box.x1 <= frame.x1
            assert frame.y0 <= box.y0 and box.y1 <= frame.y1
        assert overlapping(boxes(ax)) == []
        # The Pareto front: the drawn line runs through the points no other beats.
        front = [line for line in ax.lines if line.get_label() == 'Pareto front']
        xs = sorted(front[0].get_xdata())
        points = [(r['cost'], max(r['error'], figures.ZERO_FLOOR)) for r in rows]
        assert xs == sorted(points[k][0] for k in figures.pareto(points))


def test_labels_of_coincident_points_are_moved_apart():
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(3, 3))
    points = [(1.0, 1.0)] * 4
    ax.scatter(*zip(*points))
    ax.set_xlim(0, 2)
    ax.set_ylim(0, 2)
    naive = [ax.annotate(name, p, xytext=(5, 5), textcoords='offset points')
             for name, p in zip(figures.PRESETS, points)]
    assert overlapping(boxes(ax)) != []           # the check does find overlaps
    for text in naive:
        text.remove()
    figures.place_labels(ax, points, list(figures.PRESETS))
    assert len(boxes(ax)) == 4 and overlapping(boxes(ax)) == []
    plt.close(fig)


def test_where_time_goes_stacks_the_profile_stages():
    fig = figures.where_time_goes_figure(RESULTS['runs'])
    summary = figures.kind_summary(RESULTS['runs'])
    assert len(fig.axes) == len(summary)
    for ax, (kind, rows) in zip(fig.axes, summary.items()):
        for row in rows:
            expected = {}
            for r in row['runs']:
                for name, ms in r['profile']['stages']:
                    expected[name] = expected.get(name, 0.0) + ms * 1e-3 / r['dt']
            segments = {p.get_gid().split('|', 1)[1]: p for p in ax.patches
                        if p.get_gid() and p.get_gid().startswith(row['preset'] + '|')}
            assert list(segments) == list(expected), (kind, row['preset'])
            bottom = 0.0
            for name, patch in segments.items():
                assert patch.get_height() == pytest.approx(expected[name], rel=1e-12)
                assert patch.get_y() == pytest.approx(bottom, rel=1e-12, abs=1e-300)
                bottom += patch.get_height()
            assert bottom > 0


def test_cost_growth_shows_every_preset_with_its_fitted_exponent():
    growth = cost_growth.measured(RESULTS['growth'])
    fig = figures.cost_growth_figure(growth)
    assert len(fig.axes) == len(cost_growth.SCENES)
    for ax, scene in zip(fig.axes, cost_growth.SCENES):
        lines = {line.get_label().split(':')[0]: line for line in ax.lines}
        assert set(lines) == set(cost_growth.PRESETS)
        for preset, line in lines.items():
            mine = sorted((g for g in growth if g['scene'] == scene and g['preset'] == preset),
                          key=lambda g: g['count'])
            assert list(line.get_xdata()) == [g['count'] for g in mine]
            assert len(mine) >= 2 and mine[0]['count'] <= 1000
            slope = np.polyfit(np.log([g['count'] for g in mine]),
                               np.log([g['ms_per_step'] for g in mine]), 1)[0]
            assert f'N^{slope:.2f}' in line.get_label()
    # 1k to 1M for the cheap presets on both scenes.
    for scene in cost_growth.SCENES:
        largest = max(g['count'] for g in growth if g['scene'] == scene
                      and g['preset'] == 'fast')
        assert largest >= 999_000


def test_growth_runs_skip_large_counts_for_costly_presets(monkeypatch):
    monkeypatch.setattr(cost_growth, 'LARGE_COUNT', 150)
    records = cost_growth.run_growth(counts=(100, 200), steps=2)
    ran = {(r['scene'], r['preset'], r['count']) for r in cost_growth.measured(records)}
    for scene in cost_growth.SCENES:
        for preset in cost_growth.PRESETS:
            assert (scene, preset, 100) in ran
            assert ((scene, preset, 200) in ran) == (preset in cost_growth.CHEAP_PRESETS)
    for r in cost_growth.measured(records):
        assert r['ns_per_particle_step'] > 0
        assert [name for name, _ in r['stages']][-1] == '(outside the stages)'


def _doc_table() -> str:
    text = (ROOT / 'docs' / 'accuracy.md').read_text(encoding='utf-8')
    return text.split(figures.TABLE_BEGIN, 1)[1].split(figures.TABLE_END, 1)[0]


def test_decision_table_in_the_docs_carries_the_numbers_of_results_json():
    table = _doc_table()
    assert RESULTS['header'] in table
    runs = [r for r in RESULTS['runs'] if r['dt'] == r['scene_dt']]
    for kind, scenes in figures.KINDS.items():
        section = table.split(f'**{kind}**', 1)[1].split('**', 1)[0]
        label, measure, tolerance = figures.MEASURES[kind]
        rows = {}
        for line in section.splitlines():
            match = re.match(r'\| `(\w+)` \| ([^|]+) \| ([^|]+) \|', line)
            if match:
                rows[match[1]] = (float(match[2]), float(match[3]))
        assert set(rows) >= {'fast', 'balanced', 'accurate'}
        for preset, (error, cost) in rows.items():
            mine = [r for r in runs if r['scene'] in scenes and r['accuracy'] == preset]
            assert sorted(r['scene'] for r in mine) == sorted(scenes)
            assert error == pytest.approx(max(measure(r) for r in mine), rel=5e-3, abs=0)
            assert cost == pytest.approx(sum(r['wall_s_per_sim_s'] for r in mine), rel=5e-3)
        recommended = re.search(rf'Recommended for {kind}: `(\w+)`', section)[1]
        within = {p: v for p, v in rows.items() if v[0] <= tolerance}
        if within:
            assert recommended == min(within, key=lambda p: within[p][1])


def test_problems_name_tunnelling_overlap_drift_and_order():
    run = {'missed_pairs': 3, 'missed_walls': 1, 'max_penetration': 0.002, 'radius_min': 0.01,
           'energy_rel_error': 0.03, 'position_error': 0.001, 'pile_overlap_r': None}
    found = figures.problems(run, 'chains and cradles')
    names = [name for name, _, _ in found]
    assert names == ['tunnelling', 'overlap', 'energy drift', 'impact time/order']
    clean = dict(run, missed_pairs=0, missed_walls=0, max_penetration=0.0,
                 energy_rel_error=1e-15, position_error=1e-12)
    assert figures.problems(clean, 'chains and cradles') == []


@pytest.mark.parametrize('scene', SHIPPED)
def test_compare_presets_runs_every_shipped_scene(scene, capsys):
    assert simulate([scene, '--compare-presets', '--steps', '3']) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [re.split(r'\s*\|\s*', line.strip('| ')) for line in lines
            if line.startswith('| ') and not line.startswith('| preset')]
    names = [row[0].split(' ')[0] for row in rows]
    effects = load_scene(scene).effects
    try:
        check_event_mode(PRESETS['exact'], effects, 'x')
        refused = False
    except SceneError:
        refused = True
    reference = 'accurate' if refused else 'exact'
    assert f'compared with `{reference}`' in lines[0]
    assert names == (['fast', 'balanced', 'accurate'] + ([] if refused else ['exact']))
    for row in rows:
        assert float(row[1]) > 0                          # cost per simulated second
        if row[0] == f'{reference} (reference)':
            assert row[2:5] == ['0', '0', '0']
        assert math.isfinite(float(row[2])) and float(row[2]) >= 0
    if refused:
        assert any(line.startswith('exact: not run (mode event (preset exact) cannot simulate')
                   for line in lines)


def test_compare_presets_shows_fast_tunnelling_through_the_bullets_target(tmp_path, capsys):
    scene = tmp_path / 'bullet.yaml'
    scene.write_text('dimensions: 3\ndt: 0.016666666666666666\nduration: 0.1\nparticles:\n'
                     '  - {position: [0, 0, 0], velocity: [756, 0, 0], radius: 0.0045, '
                     'mass: 0.15}\n'
                     '  - {position: [1, 0, 0], radius: 0.025, mass: 1.0}\n', encoding='utf-8')
    out = tmp_path / 'out.json'
    assert simulate([str(scene), '--compare-presets', '--quiet', '--out', str(out)]) == 0
    result = json.loads(out.read_text(encoding='utf-8'))
    runs = {run['preset']: run for run in result['runs']}
    assert result['reference'] == 'exact' and result['refused'] == {}
    assert runs['fast']['position_diff_r'] > 1000     # passed through: metres off
    assert runs['fast']['collisions'] == 0
    for preset in ('balanced', 'accurate'):
        assert runs[preset]['position_diff_r'] < 1e-6
        assert runs[preset]['collisions'] == 1
        assert abs(runs[preset]['energy_diff_rel']) < 1e-12


def test_compare_presets_refuses_a_fixed_accuracy(capsys):
    assert simulate(['cradle', '--compare-presets', '--accuracy', 'fast']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ['simulate: error: --compare-presets runs every preset; --accuracy cannot '
                   'be combined with it']
