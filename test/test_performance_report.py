"""docs/performance.md is rendered from the committed benchmark results and cannot drift.

The page must be exactly what ``python -m collision_node.bench report``
renders from docs/performance/*.json and its template; every results file
names the machine it ran on and the command that produced it, and names
no path of that machine; the page still covers every topic it covered as
hand-written prose. The writer and the renderer are checked on small
inputs (not timed: only what the files hold is compared).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from collision_node import bench
from collision_node.bench.results import files as results, page as report

ROOT = Path(__file__).resolve().parent.parent
FOLDER = ROOT / 'docs' / 'performance'
PAGE = ROOT / 'docs' / 'performance.md'
FILES = sorted(FOLDER.glob('*.json'))

# Every topic the hand-written page covered, with a phrase that must still be on the page.
TOPICS = [
    ('in short', '## In short'),
    ('the targets', '## Against the targets'),
    ('the benchmark commands', '## The benchmarks'),
    ('the 2-D pile against pymunk', '## The 2-D pile against pymunk'),
    ('the pymunk row', '| pymunk 7.3.1 |'),
    ('the pile against its peer', 'CPU time / pymunk 7.3.1'),
    ('warm starting', 'Warm starting'),
    ('the 3-D pour', '## The 3-D pour'),
    ('gas throughput', '## Gas throughput'),
    ('the 10 % gas', 'volume fraction 0.1'),
    ('mixed sizes', '## Mixed sizes'),
    ('exact against balanced', '## `exact` against `balanced`'),
    ('resting contact', '## Resting contact under gravity'),
    ('sleeping islands', '## Sleeping islands'),
    ('effects', '## Effects'),
    ('the node per tick', '## Node'),
    ('the node real-time factor', '| real-time factor |'),
    ('start-up', '## Start-up'),
    ('a burst of spawns', '## A burst of spawns'),
    ('the node under load', '## The node under load'),
    ('garbage flood', 'rejections per second'),
    ('service bursts', 'concurrent /pause'),
    ('the broadphase', 'size classes'),
]
# Benchmarks the page has results of (each with the command that produced them).
BENCHMARKS = ['pile', 'throughput', 'mixed', 'exact', 'resting', 'effects', 'node',
              'node-start', 'commands', 'node-load']
MACHINE_PATHS = re.compile(r'/tmp/|/work/|/home/|/root\b')


def test_the_page_is_what_the_report_renders_from_the_results():
    template = (FOLDER / 'template.md.in').read_text()
    rendered = report.render(template, report.load_results(FOLDER))
    assert PAGE.read_text() == rendered, \
        'docs/performance.md differs: run python -m collision_node.bench report'


@pytest.mark.parametrize('path', FILES, ids=lambda p: p.name)
def test_each_results_file_names_its_machine_and_command(path):
    data = results.read(path)
    machine = data['machine']
    assert machine['cpu'] and machine['cores'] >= 1 and machine['os'] and machine['python']
    assert {'numpy', 'numba'} <= set(machine['versions'])
    assert data['command'].split(' -m collision_node.bench ')[1].split()[0] == \
        data['benchmark']
    assert len(data['load_average_start']) == 3 and data['exit_code'] == 0
    assert any(block['kind'] == 'table' for block in data['output']) or \
        data['benchmark'] == 'node-start'
    # The page names the machine and the command of every file.
    page = PAGE.read_text()
    assert data['command'] in page
    assert report.machine_text(data) in page


@pytest.mark.parametrize('path', FILES, ids=lambda p: p.name)
def test_no_results_file_names_a_path_of_the_machine(path):
    assert MACHINE_PATHS.findall(path.read_text()) == []


def test_the_results_cover_every_benchmark_the_page_shows():
    names = {results.read(path)['benchmark'] for path in FILES}
    assert set(BENCHMARKS) <= names


@pytest.mark.parametrize('topic, phrase', TOPICS, ids=[t[0] for t in TOPICS])
def test_the_page_covers_every_topic_it_covered(topic, phrase):
    assert phrase in PAGE.read_text(), f'{topic}: {phrase!r} not in docs/performance.md'


OUTPUT = """# a benchmark, load average 1.00
| run | steps | ms per step | CPU ms per step |
|---|---:|---:|---:|
| fast | 10 | 0.5 | 0.4 |
| pymunk 7.3.1 | 10 | 0.25 | 0.2 |

tail: 1,234 events
"""


def fake_results(tmp_path: Path, name: str = 'fake', output: str = OUTPUT) -> dict:
    """Write a results file as the writer would and return it."""
    data = {'format': results.FORMAT, 'benchmark': name,
            'command': f'python -m collision_node.bench {name} --out x.json',
            'environment': {}, 'options': {'steps': 10}, 'machine': results.machine(),
            'started_utc': '2026-12-01 23:00', 'seconds': 1.5,
            'load_average_start': [1.0, 1.5, 2.0], 'load_average_end': [1.1, 1.5, 2.0],
            'exit_code': 0, 'output': results.parse_output(output)}
    (tmp_path / f'{name}.json').write_text(json.dumps(data))
    return data


def test_the_output_parses_into_text_and_tables():
    blocks = results.parse_output(OUTPUT + '| a | b |\n|---|---|\n| x | y | z |\n')
    assert [b['kind'] for b in blocks] == ['text', 'table', 'text', 'table']
    assert blocks[1]['columns'] == ['run', 'steps', 'ms per step', 'CPU ms per step']
    assert blocks[1]['align'] == ['left', 'right', 'right', 'right']
    assert blocks[1]['rows'][1] == ['pymunk 7.3.1', '10', '0.25', '0.2']
    assert blocks[3]['rows'] == [['x', 'y | z']]        # a pipe inside the last value


def test_a_peer_row_adds_the_ratio_column_and_directives_fill_in(tmp_path):
    data = fake_results(tmp_path)
    template = ('# Page\n\n'
                'fast takes {{ ratio fake 0 fast pymunk "CPU ms per step" }}x, '
                '{{ cell fake 0 fast "ms per step" }} ms at load {{ load fake }}.\n\n'
                '{{ results fake }}\n\n{{ results fake tables=0 text=no }}\n')
    page = report.render(template, report.load_results(tmp_path))
    assert '| run | steps | ms per step | CPU ms per step | CPU time / pymunk 7.3.1 |' in page
    assert '| fast | 10 | 0.5 | 0.4 | 2.00x |' in page
    assert '| pymunk 7.3.1 | 10 | 0.25 | 0.2 | 1.00x |' in page
    assert 'fast takes 2x, 0.5 ms at load 1.0.' in page
    assert '```bash\npython -m collision_node.bench fake --out x.json\n```' in page
    # The machine and the command once; the second block of the same run says so.
    assert page.count(report.machine_text(data)) == 1 and page.count('--out x.json') == 1
    assert page.index(report.machine_text(data)) < page.index('The same run of `fake` as above.')
    assert 'a benchmark, load average 1.00' in page and '\n# a benchmark' not in page
    assert 'Other results' not in page


def test_printed_text_cannot_become_markup():
    assert report.text_line('# load __pycache__ <temporary folder> gas_10k a|b *c*') == \
        'load \\_\\_pycache\\_\\_ \\<temporary folder> gas_10k a\\|b \\*c\\*'


def test_a_results_file_no_directive_names_is_rendered_at_the_end(tmp_path):
    fake_results(tmp_path, 'fake')
    fake_results(tmp_path, 'other')
    page = report.render('# Page\n\n{{ results fake tables=0 text=no }}\n',
                         report.load_results(tmp_path))
    head, rest = page.split('## Other results')
    assert 'tail: 1,234 events' not in head and 'a benchmark' not in head
    assert '### `other` (other.json)' in rest and 'tail: 1,234 events' in rest


@pytest.mark.parametrize('template, message', [
    ('{{ results gone }}', 'no results file gone.json'),
    ('{{ results fake tables=3 }}', 'fake: no table 3 (it has 1)'),
    ('{{ results fake colour=red }}', "unknown option 'colour=red'"),
    ('x {{ cell fake 0 nobody "ms per step" }}', "0 rows start with 'nobody'"),
    ('x {{ cell fake 0 fast "ms" }}', "no column 'ms'"),
    ('x {{ cell fake 0 fast }}', 'cell: needs 4 arguments'),
    ('x {{ ratio fake 0 fast pymunk "run" }}', "no number in 'fast'"),
])
def test_a_bad_directive_is_one_error_naming_the_line(tmp_path, template, message):
    fake_results(tmp_path)
    with pytest.raises(report.ReportError) as error:
        report.render('# Page\n\n' + template + '\n', report.load_results(tmp_path))
    assert str(error.value).startswith('template line 3: ') and message in str(error.value)


def test_the_report_writes_the_page_and_check_sees_a_stale_one(tmp_path, capsys):
    fake_results(tmp_path)
    (tmp_path / 'template.md.in').write_text('# Page\n\n{{ results fake }}\n')
    page = tmp_path / 'page.md'
    arguments = ['report', '--results', str(tmp_path), '--page', str(page)]
    assert bench.main(arguments + ['--check']) == 1
    assert bench.main(arguments) == 0
    assert page.read_text().startswith(report.HEADER + '# Page\n')
    assert bench.main(arguments + ['--check']) == 0
    (tmp_path / 'broken.json').write_text('{"format": 1}')
    assert bench.main(arguments) == 2
    assert 'broken.json: no "benchmark"' in capsys.readouterr().err


def test_a_benchmark_writes_its_results_file(tmp_path, capsys):
    out = tmp_path / 'sub' / 'exact.json'
    assert bench.main(['exact', '--counts', '200', '--steps', '2', '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    data = results.read(out)
    assert data['benchmark'] == 'exact' and data['exit_code'] == 0
    # The temporary folder is not named: a committed file names no path of the machine.
    assert data['command'] == ('python -m collision_node.bench exact --counts 200 --steps 2 '
                               '--out <temporary folder>')
    # Every option with its value, the thread count of every world included (0: every core).
    assert data['options'] == {'counts': [200], 'steps': [2], 'threads': 0}
    table = [block for block in data['output'] if block['kind'] == 'table'][0]
    assert [row[0] for row in table['rows']] == ['200']
    # The machine's speed before the run, and the page says it beside the machine.
    speed = data['speed_reference']
    assert speed['python_loop_ms'] > 0.0 and speed['gather_ns'] > 0.0
    assert (f'speed reference {speed["python_loop_ms"]:g} ms for a Python loop of 1,000,000 '
            f'additions, {speed["gather_ns"]:g} ns per row of a random gather'
            in report.machine_text(data))
    # What was printed is what the file holds.
    assert '| ' + ' | '.join(table['rows'][0]) + ' |' in printed
    assert bench.main(['exact', '--counts', '200', '--steps', '1', '--results-dir',
                       str(tmp_path)]) == 0
    assert results.read(tmp_path / 'exact.json')['options']['steps'] == [1]


def test_an_unwritable_results_file_is_refused_before_the_run(tmp_path, capsys):
    assert bench.main(['exact', '--counts', '200', '--out', str(tmp_path)]) == 2
    assert 'is a folder' in capsys.readouterr().err


def test_results_dir_without_a_folder_writes_to_docs_performance(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert bench.main(['exact', '--counts', '200', '--steps', '1', '--results-dir']) == 0
    data = results.read(tmp_path / 'docs' / 'performance' / 'exact.json')
    assert data['command'] == 'python -m collision_node.bench exact --counts 200 --steps 1 ' \
        '--results-dir'
