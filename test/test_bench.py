"""The benchmark command: dispatcher and the throughput table (not timed)."""

from __future__ import annotations

import importlib.util
import math
import sys

import numpy as np
import pytest

from collision_node import bench
from collision_node.bench.throughput import gas_scene, growth_exponent


def test_throughput_prints_a_markdown_row_per_count(capsys):
    assert bench.main(['throughput', '--counts', '400', '100', '--work', '4000',
                       '--warmup', '1']) == 0
    lines = capsys.readouterr().out.splitlines()
    assert 'load average' in lines[0]
    table = [line for line in lines if line.startswith('|')]
    assert table[0].startswith('| N | steps | ns per particle-step | growth exponent')
    rows = [[cell.strip() for cell in line.strip('|').split('|')] for line in table[2:]]
    assert [row[0] for row in rows] == ['100', '400']          # sorted by N
    assert [row[1] for row in rows] == ['40', '10']            # work / N steps
    assert rows[0][3] == '-' and math.isfinite(float(rows[1][3]))
    assert all(float(row[2]) > 0 and float(row[4]) > 0 for row in rows)
    # e = 1 everywhere: the energy column is round-off.
    assert all(abs(float(row[6])) < 1e-12 for row in rows)


def test_gas_scene_keeps_the_density_of_gas_10k():
    for count in (1_000, 100_000):
        side = gas_scene(count)['effects']['walls']['max'][0] * 2
        assert count / side ** 3 == pytest.approx(10_000 / 5.0 ** 3, rel=1e-12)


def test_growth_exponent_of_linear_and_quadratic_cost():
    small = {'count': 1000, 'steps': 10, 'seconds': 1.0}
    assert growth_exponent(small, {'count': 10_000, 'steps': 10, 'seconds': 10.0}) == \
        pytest.approx(1.0)
    assert growth_exponent(small, {'count': 10_000, 'steps': 5, 'seconds': 50.0}) == \
        pytest.approx(2.0)


def test_unknown_subcommand_exits_two(capsys):
    with pytest.raises(SystemExit) as exit_info:
        bench.main(['nonsense'])
    assert exit_info.value.code == 2
    assert "invalid choice: 'nonsense'" in capsys.readouterr().err


def _table(out: str) -> list[list[str]]:
    """Return the body rows of every Markdown table in ``out``, cells stripped."""
    return [[cell.strip() for cell in line.strip('|').split('|')]
            for line in out.splitlines()
            if line.startswith('|') and not line.startswith('|--') and
            not line.startswith('| run') and not line.startswith('| preset') and
            not line.startswith('| large') and not line.startswith('| N ')]


def test_throughput_fraction_sets_the_volume_fraction():
    scene = gas_scene(2000, fraction=0.1)
    side = scene['effects']['walls']['max'][0] * 2
    volume = 2000 * 4.0 / 3.0 * math.pi * scene['generate'][0]['radius'] ** 3
    assert volume / side ** 3 == pytest.approx(0.1, rel=1e-12)


def test_pile_bench_rows_and_pymunk_missing_message(capsys, monkeypatch):
    import sys
    # A None entry makes ``import pymunk`` raise ImportError, installed or not.
    monkeypatch.setitem(sys.modules, 'pymunk', None)
    monkeypatch.setitem(sys.modules, 'mujoco', None)
    assert bench.main(['pile', '--steps', '3', '--presets', 'fast', 'exact',
                       '--count3d', '60', '--steps3d', '2']) == 0
    out = capsys.readouterr().out
    assert 'pymunk not installed (pip install pymunk==7.x): comparison row skipped' in out
    assert 'mujoco not installed (pip install -r bench-requirements.txt)' in out
    rows = _table(out)
    fast, exact, pour = rows
    assert fast[0] == 'fast' and fast[1] == '3' and float(fast[2]) > 0
    # Discs poured from 0.5 m up are still falling after 3 steps: above the threshold.
    assert float(fast[6]) > 0.164 and fast[7] == 'no'
    assert exact[0] == 'exact' and 'cannot simulate friction' in exact[1]
    assert exact[2:] == [''] * 10
    assert pour[0] == 'balanced' and pour[1] == '2' and float(pour[4]) > 0
    # Still falling after 2 steps: no overlap (contacts only where the lattice meets a
    # wall); the top is the pour's; no solver of a peer, no solver contacts.
    assert pour[9:11] == ['0', '0'] and int(pour[11]) >= 0 and float(pour[12]) > 0.5
    assert pour[13:] == ['-', '-']


PILE_2D_COLUMNS = ['run', 'steps', 'ms per step', 'CPU ms per step',
                   'deepest overlap / r (discs)', 'deepest overlap / r (walls)',
                   'fastest disc m/s', 'below threshold 0.164 m/s', 'pairs over 1 % r',
                   'pairs over 10 % r', 'contacts (gap < 1 % r)', 'top m']
PILE_3D_COLUMNS = ['run', 'steps', 'ms per step', 'CPU ms per step', 'real-time factor',
                   'real-time factor (CPU)', 'deepest overlap / r (spheres)',
                   'deepest overlap / r (walls)', 'fastest sphere m/s', 'pairs over 1 % r',
                   'pairs over 10 % r', 'contacts (gap < 1 % r)', 'top m',
                   'solver contacts (most in a step)', 'solver contacts (at the end)']


def test_pile_bench_records_its_tables(tmp_path, monkeypatch, capsys):
    import json
    import sys
    monkeypatch.setitem(sys.modules, 'pymunk', None)
    monkeypatch.setitem(sys.modules, 'mujoco', None)
    out = tmp_path / 'pile.json'
    assert bench.main(['pile', '--steps', '2', '--presets', 'fast', '--count3d', '30',
                       '--steps3d', '1', '--out', str(out)]) == 0
    data = json.loads(out.read_text())
    assert data['benchmark'] == 'pile' and '--count3d 30' in data['command']
    assert data['options']['count3d'] == 30 and data['options']['no_mujoco'] is False
    pile2d, pour = _recorded_tables(out)
    assert pile2d['columns'] == PILE_2D_COLUMNS and pour['columns'] == PILE_3D_COLUMNS
    (fast,) = pile2d['rows']
    assert fast[:2] == ['fast', '2'] and float(fast[2]) > 0
    (balanced,) = pour['rows']
    assert balanced[:2] == ['balanced', '1'] and balanced[9] == '0' and float(balanced[4]) > 0


def test_pile_bench_3d_runs_name_a_preset_and_its_substeps(capsys, monkeypatch):
    from collision_node.bench.contact.pile import pile3d_run
    assert pile3d_run('fast') == ('fast', 0) and pile3d_run('balanced:4') == ('balanced', 4)
    for bad, why in (('exact', 'the preset must be one of fast, balanced, accurate'),
                     ('fast:x', "accuracy.substeps: expected an integer, got 'x'"),
                     ('fast:0', 'accuracy.substeps: must be >= 1, got 0'),
                     ('fast:1001', 'accuracy.substeps: must be <= 1000, got 1001')):
        with pytest.raises(SystemExit):
            bench.main(['pile', '--presets3d', bad])
        assert f"argument --presets3d: '{bad}': {why}" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, 'mujoco', None)
    assert bench.main(['pile', '--steps', '1', '--presets', 'fast', '--no-pymunk',
                       '--count3d', '30', '--steps3d', '2', '--presets3d', 'fast',
                       'fast:3']) == 0
    fast, substepped = _table(capsys.readouterr().out)[1:]
    assert fast[:2] == ['fast', '2'] and substepped[:2] == ['fast, 3 substeps', '2']


def _pile_with_mujoco(out) -> list:
    """Run the tiny pile bench with the MuJoCo row asked for; return the 3-D table's rows."""
    assert bench.main(['pile', '--steps', '1', '--presets', 'fast', '--no-pymunk',
                       '--count3d', '30', '--steps3d', '2', '--out', str(out)]) == 0
    return _recorded_tables(out)[1]['rows']


def test_pile_bench_without_mujoco_says_so_and_keeps_its_own_rows(
        tmp_path, capsys, monkeypatch):
    """Without MuJoCo (an import that fails) there is no peer row, and a note says why."""
    from collision_node.bench.contact.pile import MUJOCO_MISSING
    monkeypatch.setitem(sys.modules, 'mujoco', None)
    rows = _pile_with_mujoco(tmp_path / 'pile.json')
    assert [row[0] for row in rows] == ['balanced']
    assert MUJOCO_MISSING in capsys.readouterr().out


def test_pile_bench_mujoco_row_is_a_peer_row(tmp_path, capsys):
    """With MuJoCo installed, its row starts with its name and gets the peer ratio."""
    from collision_node.bench.results import files, page
    if importlib.util.find_spec('mujoco') is None:
        # Optional peer (bench-requirements.txt): its absence is the case above.
        rows = _pile_with_mujoco(tmp_path / 'pile.json')
        assert [row[0] for row in rows] == ['balanced']
        return
    out = tmp_path / 'pile.json'
    balanced, peer = _pile_with_mujoco(out)
    assert peer[0].startswith('MuJoCo ') and peer[1] == '2' and int(peer[13]) >= 0
    assert balanced[13:] == ['-', '-']
    rendered = page.peer_columns(page.tables(files.read(out))[1])
    assert rendered['columns'][-1] == f'CPU time / {peer[0]}'


def test_pile_quality_counts_overlaps_and_contacts():
    import numpy as np
    from collision_node.bench.contact.pile import pile_quality
    r = 0.05
    # Pairs 0-1 overlap by 2 % of r, 2-3 by 20 %, 4-5 touch within 0.5 % r; 6 rests on the floor.
    x = [0.0, 2 * r - 0.02 * r, 1.0, 1.0 + 2 * r - 0.2 * r, 2.0, 2.0 + 2 * r + 0.005 * r, 3.0]
    position = np.array([[v, 1.0] for v in x[:6]] + [[x[6], r]])
    quality = pile_quality(position, np.zeros((7, 2)), np.full(7, r),
                           np.array([-10.0, 0.0, -np.inf]), np.array([10.0, 10.0, np.inf]), 2)
    assert quality['pairs_over_0.01r'] == 2 and quality['pairs_over_0.1r'] == 1
    assert quality['contacts'] == 4 and quality['top'] == pytest.approx(1.0 + r)
    assert quality['overlap_pairs_r'] == pytest.approx(0.2)


def _recorded_tables(path) -> list[dict]:
    """Return the tables a results file recorded, in the order printed."""
    import json
    data = json.loads(path.read_text())
    assert data['format'] == 1 and data['exit_code'] == 0
    return [block for block in data['output'] if block['kind'] == 'table']


def test_stacks_bench_records_its_tables(tmp_path, capsys):
    out = tmp_path / 'stacks.json'
    assert bench.main(['stacks', '--presets', 'fast', 'exact', '--cases', 'cluster', 'column',
                       '--out', str(out)]) == 0
    captured = capsys.readouterr()
    assert 'refused: ' in captured.out and 'cannot simulate friction' in captured.out
    assert 'cluster under fast: done' in captured.err      # progress: not in the results
    columns, table = _recorded_tables(out)
    # The column: exact keeps its top at the exact height, both rows give it.
    assert columns['columns'][:5] == ['case', 'preset', 'steps', 'ms per step',
                                      'CPU ms per step']
    assert columns['columns'][5:] == ['top m', 'exact top m', 'top error / r',
                                      'largest error / r']
    assert [row[:3] for row in columns['rows']] == [['column', 'fast', '600'],
                                                    ['column', 'exact', '600']]
    assert abs(float(columns['rows'][1][7])) < 1e-6
    assert table['columns'] == ['case', 'preset', 'steps', 'ms per step', 'CPU ms per step',
                                'collisions', 'momentum error']
    fast, exact = table['rows']
    assert fast[:3] == ['cluster', 'fast', '120'] and float(fast[3]) > 0
    assert int(fast[5]) > 0 and 0.0 <= float(fast[6]) < 1.0
    assert exact[:3] == ['cluster', 'exact', 'refused'] and exact[3:] == [''] * 4


def test_pile_quality_measures_overlap_and_speed():
    from collision_node.bench.contact.pile import pile_quality
    import numpy as np
    position = np.array([[0.1, 0.05], [0.18, 0.05], [1.0, 0.04]])
    velocity = np.array([[0.0, 0.0], [0.3, 0.4], [0.0, 0.0]])
    radius = np.full(3, 0.05)
    quality = pile_quality(position, velocity, radius, np.array([0.0, 0.0, -np.inf]),
                           np.array([1.6, 20.0, np.inf]), 2)
    assert quality['overlap_pairs_r'] == pytest.approx(0.02 / 0.05)   # 0.1 - 0.08
    assert quality['overlap_walls_r'] == pytest.approx(0.01 / 0.05)   # 0.04 above the floor
    assert quality['fastest'] == pytest.approx(0.5)


def test_mixed_bench_places_without_overlap_and_searches_exactly(capsys):
    import numpy as np
    from collision_node.bench.mixed import box_side, mixed_radii, place
    radius = mixed_radii(500, 0.2, 10.0, seed=1)
    assert np.count_nonzero(radius > 0.05) == 100
    side = box_side(radius, 0.1)
    position = place(radius, side, seed=2)
    i, j = np.triu_indices(500, k=1)
    gap = np.linalg.norm(position[i] - position[j], axis=1) - (radius[i] + radius[j])
    assert gap.min() >= 0.0
    assert np.all(position >= radius[:, None]) and np.all(position <= side - radius[:, None])
    assert bench.main(['mixed', '--count', '300', '--shares', '0.1', '--steps', '2',
                       '--warmup', '1', '--presets', 'fast']) == 0
    rows = _table(capsys.readouterr().out)
    assert [row[0] for row in rows[:2]] == ['0', '0.1'] and rows[0][4] == '1.00'
    # The search alone finds exactly the real contacts of the static sets.
    for row in rows[2:]:
        assert row[4] == row[5]


def test_apex_error_of_the_analytic_bounce_sequence():
    from collision_node.bench.accuracy_ladder import BALL_RESTITUTION, apex_error
    g, track = 9.81, [(1.1, 0.0)]
    for k in range(1, 7):
        # Just after the k-th bounce: 2 cm up, moving up toward the apex e^(2k) h.
        apex = BALL_RESTITUTION ** (2 * k)
        v = (2.0 * g * (apex - 0.02)) ** 0.5
        track += [(0.3, -1.0), (0.12, v), (0.11 + apex, 0.0)]
    assert apex_error(track) < 1e-12
    track[5] = (0.12, track[5][1] * 1.01)           # second bounce 1 % too fast in speed
    assert apex_error(track) == pytest.approx(
        (1.01 ** 2 - 1) * (BALL_RESTITUTION ** 4 - 0.02), rel=1e-9)
    assert apex_error(track[:7]) == 1.0            # two apexes only: the ball stopped early


def test_accuracy_scenes_include_the_gravity_scenes():
    from collision_node.bench.accuracy_ladder import plan, scenes
    quick = scenes(quick=True)
    assert quick['bouncing_ball']['effects']['gravity'] == [0.0, -9.81]
    assert quick['pile']['effects']['friction'] == 0.5 and quick['pile']['duration'] == 2.0
    pile_runs = [(accuracy, dt) for name, _, accuracy, dt, _ in plan(quick=True)
                 if name == 'pile']
    # No exact reference (event mode refuses friction), no dt sweep.
    assert pile_runs == [(p, 1 / 120) for p in ('fast', 'balanced', 'accurate')]


def test_exact_bench_prints_a_row_per_size(capsys):
    assert bench.main(['exact', '--counts', '200', '--steps', '4']) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith('| 200 |')]
    assert len(rows) == 1
    cells = [cell.strip() for cell in rows[0].strip('|').split('|')]
    balanced, exact, ratio = float(cells[2]), float(cells[3]), float(cells[4])
    assert balanced > 0 and exact > 0
    assert ratio == pytest.approx(exact / balanced, abs=0.06)


def test_resting_bench_rows_say_what_each_preset_kept(capsys):
    """The column under `fast` and `exact`: one row each, exact at rest, no fallback."""
    assert bench.main(['resting', '--presets', 'fast', 'exact', '--scenes', 'column']) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith('|')]
    assert table[0].startswith('| scene | preset | steps | ms/step | fallback steps')
    rows = [[cell.strip() for cell in line.strip('|').split('|')] for line in table[2:]]
    assert [row[:3] for row in rows] == [['column', 'fast', '240'], ['column', 'exact', '240']]
    assert rows[1][4] == '0'                         # no step went to the step solver
    assert float(rows[1][5]) < 1e-9                  # at rest
    assert float(rows[1][6]) < 1e-9                  # overlap / r: round-off


def test_resting_bench_drop_scene_puts_a_disc_above_a_hollow_of_the_top_row():
    """The dropped disc is 0.3 m above touching the top row, over a hollow (x = 26 r)."""
    from collision_node.bench.contact.resting import RADIUS, scene
    particles = scene('drop', 'exact')['particles']
    assert len(particles) == 501
    top = max(p['position'][1] for p in particles[:-1])
    assert particles[-1]['position'][1] == pytest.approx(top + 2 * RADIUS + 0.3)
    assert particles[-1]['position'][0] == pytest.approx(26 * RADIUS)


def test_scaling_bench_rows_say_each_thread_count_gave_the_same_state(capsys):
    """One row per case and thread count; the state column checks the count changed nothing."""
    assert bench.main(['scaling', '--counts', '5000', '--presets', 'fast', '--pour-steps', '0',
                       '--pile-steps', '2', '--thread-counts', '1', '1']) == 0
    lines = capsys.readouterr().out.splitlines()
    table = [line for line in lines if line.startswith('|')]
    assert table[0].startswith('| case | threads | steps | ms per step')
    rows = [[cell.strip() for cell in line.strip('|').split('|')] for line in table[2:]]
    assert [(row[0], row[1]) for row in rows] == [
        ('gas 5,000 (fast)', '1'), ('gas 5,000 (fast)', '1'),
        ('pile 240 (fast)', '1'), ('pile 240 (fast)', '1')]
    assert all(row[8] == 'yes' for row in rows)
    # The gas searched its pair list afresh in its timed steps, as often at each count.
    assert rows[0][10] == rows[1][10] and int(rows[0][10]) > 0
    # Each case's first row is its own base.
    assert (rows[0][6], rows[0][7], rows[2][6], rows[2][7]) == ('1.00x', '100%', '1.00x', '100%')
    assert any(line.startswith('numba threading layer:') for line in lines)


def test_scaling_bench_refuses_a_thread_count_over_the_pool(capsys):
    assert bench.main(['scaling', '--counts', '5000', '--pour-steps', '0', '--pile-steps', '0',
                       '--thread-counts', '1000']) == 2
    assert 'bench scaling: --thread-counts: 1000 threads asked for, but this process can run ' \
        'at most' in capsys.readouterr().err


def test_scaling_bench_times_the_gas_in_id_order_beside_it(capsys):
    from collision_node import World
    from collision_node.bench.scaling import in_id_order
    from collision_node.physics.model.scene import parse_scene
    world = in_id_order(World(parse_scene(gas_scene(300, fraction=0.1), 'gas')))
    assert world.pipeline.spatial_order.min_particles == sys.maxsize
    assert bench.main(['scaling', '--counts', '5000', '--presets', 'fast', '--pour-steps', '0',
                       '--pile-steps', '0', '--thread-counts', '1', '--id-order']) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith('|')]
    rows = [[cell.strip() for cell in line.strip('|').split('|')] for line in table[2:]]
    assert [row[0] for row in rows] == ['gas 5,000 (fast)', 'gas 5,000 (fast, id order)']
    assert all(int(row[10]) > 0 for row in rows)


def _deepest_overlap_over_r(world) -> float:
    """Return the deepest overlap of two discs or a disc and a wall over r, by brute force."""
    s, walls = world.state, world.scene.effects.walls
    i, j = np.triu_indices(len(s), 1)
    gap = np.linalg.norm(s.position[i] - s.position[j], axis=1) - (s.radius[i] + s.radius[j])
    x, r = s.position[:, :2], s.radius[:, None]
    inside = np.concatenate([(x - r - walls.low[:2]).ravel(), (walls.high[:2] - x - r).ravel()])
    return max(0.0, -float(gap.min()), -float(inside.min())) / float(np.median(s.radius))


def test_stacks_bench_gives_the_spread_of_pours_over_seeds(tmp_path):
    from collision_node import World
    from collision_node.scenarios import drop_ball, pour2d
    out = tmp_path / 'stacks.json'
    assert bench.main(['stacks', '--presets', 'fast', '--cases', 'pour_spread', '--seeds', '1',
                       '2', '--out', str(out)]) == 0
    (table,) = _recorded_tables(out)
    assert table['columns'][5:] == ['seeds', 'settled median', 'settled least', 'settled most',
                                    'settled over 1 %', 'dropped median', 'dropped least',
                                    'dropped most', 'dropped over 1 %']
    (row,) = table['rows']
    assert row[:3] == ['pour_spread', 'fast', str(2 * 2 * 360)] and row[5] == '2'
    # The same pours stepped here: the table's figures are theirs.
    settled, dropped = [], []
    for seed in (1, 2):
        world = World(pour2d(100, seed=seed, accuracy='fast'))
        world.step(360)
        settled.append(_deepest_overlap_over_r(world))
        drop_ball(world, height=0.3)
        world.step(360)
        dropped.append(_deepest_overlap_over_r(world))
    for values, cells in ((settled, row[6:10]), (dropped, row[10:14])):
        expected = [np.median(values), min(values), max(values)]
        assert [float(cell) for cell in cells[:3]] == pytest.approx(expected, rel=5e-3)
        assert int(cells[3]) == sum(value > 0.01 for value in values)


def test_stacks_bench_refuses_a_seed_out_of_range(capsys):
    with pytest.raises(SystemExit):
        bench.main(['stacks', '--cases', 'pour_spread', '--seeds', '-1'])
    assert "-1 is outside 0 .. 2^32 - 1" in capsys.readouterr().err


def test_compile_bench_times_each_process_count_on_a_cache_of_its_own(monkeypatch, capsys):
    from collision_node.bench import compile_time
    caches, seconds = [], iter([(400.0, 401.0), (1.0, 2.0), (220.0, 221.5), (0.5, 1.5)])

    def fake_prepare(cache, processes):
        caches.append((cache, processes))
        return next(seconds)

    monkeypatch.setattr(compile_time, '_prepare', fake_prepare)
    assert bench.main(['compile', '--processes', '1', '2']) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[2] == '| 1 | 400.0 | 401.0 | 1.00 | 1.00 |'
    assert rows[3] == '| 2 | 220.0 | 221.5 | 0.55 | 0.50 |'
    # Each count compiles into an empty cache of its own, then loads from that same cache.
    assert [p for _, p in caches] == [1, 1, 2, 2]
    assert caches[0][0] == caches[1][0] != caches[2][0] == caches[3][0]


def test_compile_bench_refuses_a_count_below_one(capsys):
    assert bench.main(['compile', '--processes', '0']) == 2
    assert '--processes takes counts of 1 or more' in capsys.readouterr().err


def test_scaling_bench_weighs_a_large_gas_alone_in_a_fresh_process():
    from collision_node.bench import scaling
    held = np.ones(50_000_000)         # 400 MB here: 200,000 B per particle if counted there
    small = scaling.case_memory(2000, 'fast', 1, 2, False)
    assert held[-1] == 1.0 and 0 < small < 50_000    # the world it built alone, per particle
    args = bench_args_for_scaling(scaling, [2000, scaling.MEMORY_FROM])
    weighed = {case[0]: case[5] for case in scaling.cases(args)}
    assert weighed['gas 2,000 (fast)'] is None
    assert weighed[f'gas {scaling.MEMORY_FROM:,} (fast)'] == (scaling.MEMORY_FROM, 'fast', False)
    assert weighed[f'gas {scaling.MEMORY_FROM:,} (fast, id order)'] == (
        scaling.MEMORY_FROM, 'fast', True)
    assert weighed['pour 10,000 (fast)'] is None


def bench_args_for_scaling(scaling, counts):
    import argparse
    parser = argparse.ArgumentParser()
    scaling.add_arguments(parser)
    return parser.parse_args(['--counts', *map(str, counts), '--presets', 'fast', '--id-order'])
