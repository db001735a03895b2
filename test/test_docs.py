"""The manual stays short, current and linked: README.md and the pages in docs/.

README.md is at most 250 lines; no page names a temporary or machine path, a
branch, a work session or an issue number (history goes to CHANGELOG.md);
every relative link points at a file that exists, and at a heading of it
when it names one; the example tests in README.md and docs/api.md run and
pass; and what the README used to hold in full is still in some page.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / 'README.md'
PAGES = sorted((ROOT / 'docs').rglob('*.md'))
MANUAL = [README] + PAGES
README_MAX_LINES = 250

# History markers a page must not carry (case-insensitive).
FORBIDDEN = {
    'a temporary path': r'/tmp/',
    'a path of the work machine': r'/work/',
    'a worktree': r'\bworktrees?\b',
    'a branch': r'\bbranch(es)?\b',
    'an issue number': r'\bissues?[- #]?\d+',
    'a work session': r'\b(first|second|third|fourth|fifth|this|that|earlier|later|'
                      r'previous|next|last) session\b',
}
LINK = re.compile(r'!?\[[^\]]*\]\(([^)\s]+)(?:\s+"[^"]*")?\)')
FENCE = re.compile(r'^(```|~~~)')
EXAMPLE_MARK = re.compile(r'^# (test_\w+\.py)\b')


def prose_lines(text: str) -> list[str]:
    """Return the lines of a markdown text outside its fenced code blocks."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(line)
    return lines


def code_blocks(text: str, language: str) -> list[str]:
    """Return the fenced blocks of ``language`` in a markdown text."""
    return re.findall(r'^```' + language + r'\n(.*?)^```', text, re.DOTALL | re.MULTILINE)


def slug(heading: str) -> str:
    """Return GitHub's anchor for a heading text (lower case, punctuation dropped)."""
    text = re.sub(r'[^\w\- ]', '', heading.strip().lower())
    return text.replace(' ', '-')


def anchors(path: Path) -> set[str]:
    """Return the anchors of a markdown file's headings (duplicates numbered as GitHub does)."""
    seen: dict[str, int] = {}
    found = set()
    for line in prose_lines(path.read_text()):
        heading = re.match(r'^#{1,6} (.*)', line)
        if not heading:
            continue
        base = slug(heading.group(1))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f'{base}-{count}')
    return found


def test_readme_is_at_most_250_lines():
    lines = README.read_text().splitlines()
    assert 0 < len(lines) <= README_MAX_LINES, f'README.md has {len(lines)} lines'


@pytest.mark.parametrize('path', MANUAL, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_page_names_history_or_a_machine_path(path):
    text = path.read_text()
    found = [f'{path.relative_to(ROOT)}:{number}: {what}: {line.strip()[:80]}'
             for number, line in enumerate(text.splitlines(), 1)
             for what, pattern in FORBIDDEN.items()
             if re.search(pattern, line, re.IGNORECASE)]
    assert found == []


def test_the_history_check_would_see_each_marker():
    # Guard against patterns that cannot match.
    samples = ['written to /tmp/x.py', 'PYTHONPATH=/work/main', 'in the worktree',
               'tried, not kept (branch `gasorder`)', 'Issue-11 targets', '(issue 11)',
               'Issue 20', 'the third session']
    for sample in samples:
        assert any(re.search(p, sample, re.IGNORECASE) for p in FORBIDDEN.values()), sample
    clean = 'the swept stage skips pairs out of reach (docs/performance.md, 2026-11-30)'
    assert not any(re.search(p, clean, re.IGNORECASE) for p in FORBIDDEN.values())


def relative_links(path: Path) -> list[str]:
    """Return the relative link targets of a markdown file (prose only)."""
    targets = []
    for line in prose_lines(path.read_text()):
        targets += [t for t in LINK.findall(line) if not re.match(r'^[a-z]+:', t)]
    return targets


@pytest.mark.parametrize('path', MANUAL, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_at_a_file_and_heading_that_exist(path):
    broken = []
    for target in relative_links(path):
        file_part, _, anchor = target.partition('#')
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f'{target}: no such file')
        elif anchor and linked.suffix == '.md' and anchor not in anchors(linked):
            broken.append(f'{target}: no heading #{anchor} in {linked.name}')
    assert broken == []


def test_the_link_check_would_see_a_broken_link(tmp_path):
    page = tmp_path / 'page.md'
    page.write_text('# Top\n\n## A `b` (c)\n\n[x](page.md#a-b-c) [y](#top) [z](gone.md)\n'
                    '```\n[not a link](nowhere.md)\n```\n')
    assert relative_links(page) == ['page.md#a-b-c', '#top', 'gone.md']
    assert anchors(page) == {'top', 'a-b-c'}


def examples(path: Path) -> list[tuple[str, str]]:
    """Return the (file name, source) of every example test in a page's python blocks."""
    found = []
    for block in code_blocks(path.read_text(), 'python'):
        mark = EXAMPLE_MARK.match(block)
        if mark:
            found.append((mark.group(1), block))
    return found


@pytest.mark.parametrize('page', ['README.md', 'docs/api.md'])
def test_the_example_tests_run_and_pass(page):
    found = examples(ROOT / page)
    assert found, f'{page}: no python block starting "# test_NAME.py"'
    for name, source in found:
        namespace = {'__name__': name[:-3]}
        exec(compile(source, f'{page}:{name}', 'exec'), namespace)
        tests = [value for key, value in namespace.items()
                 if key.startswith('test_') and callable(value)]
        assert tests, f'{page}: {name} defines no test function'
        for test in tests:
            test()


def test_the_readme_picture_exists_with_the_command_that_made_it():
    text = README.read_text()
    pictures = re.findall(r'!\[[^\]]*\]\((docs/images/[^)]+\.png)\)', text)
    assert len(pictures) == 1
    assert (ROOT / pictures[0]).stat().st_size > 10_000
    assert f'--snapshot {pictures[0]}' in text
    for command in ('scripts/run ', 'scripts/test '):
        assert f'\n{command}' in text, command


def test_changelog_is_newest_first_with_an_unreleased_section():
    text = (ROOT / 'CHANGELOG.md').read_text()
    sections = re.findall(r'^## (.+)$', text, re.MULTILINE)
    assert sections[0] == 'Unreleased'
    dates = [s for s in sections[1:] if re.fullmatch(r'\d{4}-\d{2}-\d{2}', s)]
    assert dates == sorted(dates, reverse=True) and dates


# What the README held before the manual was split by topic, each section with a phrase
# that must still be found in the page it moved to.
MOVED = [
    ('Two commands', 'docs/install.md', 'apt-get install python3-venv'),
    ('compiled kernels', 'docs/install.md', '~/.cache/collision_node/numba-<digest>'),
    ('DDS discovery', 'docs/node.md', 'export ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET'),
    ('Where things are', 'README.md', '| `msg_adapters/` |'),
    ('On a ROS 2 Jazzy install', 'docs/install.md', 'colcon build --packages-select'),
    ('Offline runner', 'docs/runner.md', '"steps_requested": M'),
    ('The ROS 2 node', 'docs/node.md', 'dropped_backlog_s'),
    ('topics table', 'docs/node.md', '| `particles/collisions` | `sensor_msgs/PointCloud2` |'),
    ('QoS', 'docs/node.md', 'best-effort clock subscribers'),
    ('Commands', 'docs/node.md', '**Ids are stable**'),
    ('Parameters', 'docs/node.md', '| `max_particles` | integer | 100000 |'),
    ('With the ROS 2 command line', 'docs/node.md', 'ros2 service call /reset'),
    ('In RViz', 'docs/node.md', '*Fixed Frame*'),
    ('the viewer', 'docs/node.md', 'viewer --collisions --once'),
    ('VelocityStamped per particle', 'docs/node.md', 'geometry_msgs` has no twist array'),
    ('Message building', 'docs/node.md', 'rclpy.serialization.serialize_message'),
    ('Scene files', 'docs/scenes.md', '**2-D rule**'),
    ('Input limits', 'docs/scenes.md', 'YAML aliases (`*name`) are refused'),
    ('shipped scenes', 'docs/scenes.md', '| `spin_billiards` |'),
    ('Benchmarks', 'docs/performance.md', 'python -m collision_node.bench node-start'),
    ('Effects', 'docs/scenes.md', '**Combine rule**'),
    ('One contact law', 'docs/scenes.md', '**One contact law**'),
    ('Impacts', 'docs/api.md', 'World.record_impacts(True)'),
    ('Restitution threshold', 'docs/scenes.md', '**Restitution threshold**'),
    ('Resting piles', 'docs/scenes.md', '**Resting piles**'),
    ('Energy bookkeeping', 'docs/api.md', 'total + sum(dissipated) - start - spawned'),
    ('Accuracy', 'docs/accuracy.md', 'buys fewer missed and mis-timed impacts'),
    ('Sleeping islands', 'docs/accuracy.md', '| `sleep_time` | 0.5 s | 0.5 s |'),
    ('Stability suite', 'docs/stability.md', 'HYPOTHESIS_PROFILE=deep python -m pytest'),
]


@pytest.mark.parametrize('section, page, phrase', MOVED, ids=[m[0] for m in MOVED])
def test_what_the_readme_held_is_in_a_page(section, page, phrase):
    assert phrase in (ROOT / page).read_text(), f'{section}: not in {page}'
