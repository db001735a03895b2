"""The benchmark command: dispatcher and the throughput table (not timed)."""

from __future__ import annotations

import math

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
