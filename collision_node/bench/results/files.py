"""Benchmark results as JSON: what ran, on which machine, and the tables it printed.

Every benchmark subcommand takes ``--out FILE`` or ``--results-dir [DIR]``
(``DIR/NAME.json``, DIR by default :data:`RESULTS_DIR`); the dispatcher
adds both, so a benchmark module needs nothing of its own. While the
benchmark runs, what it prints still goes to the terminal and is kept; at
the end the file gets the exact command, the parsed options (the sizes
that ran, defaults included), the machine (CPU model, cores, OS, Python,
numpy, numba and the peers' versions), the load average at the start and
at the end, and the printed output split into text lines and Markdown
tables (columns, alignment, rows as printed), and the machine's speed
before the run (``speed_reference``: two fixed tasks, timed). ``bench report`` renders
docs/performance.md from these files.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import os
import platform
import re
import shlex
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterator, Optional, Sequence, TextIO

# Where ``--results-dir`` writes when given no folder (relative to the working directory).
RESULTS_DIR = Path('docs/performance')
# Version of the file layout below; ``bench report`` refuses other versions.
FORMAT = 1
# Distributions whose versions a result names when installed (peers included).
VERSIONS = ('numpy', 'numba', 'scipy', 'ros-jazzy-rclpy', 'rclpy', 'pymunk', 'mujoco',
            'pybullet')
# Environment variables that change what a benchmark measures.
ENVIRONMENT = ('NUMBA_CACHE_DIR', 'NUMBA_DISABLE_JIT', 'RMW_IMPLEMENTATION')
PROGRAM = 'python -m collision_node.bench'
SEPARATOR = re.compile(r'^\|(\s*:?-{3,}:?\s*\|)+\s*$')
# A JSON list of scalars as json.dumps(indent=1) writes it, one item a line.
_SCALAR = r'(?:"(?:[^"\\]|\\.)*"|-?[\d.eE+-]+|true|false|null)'
SCALAR_LIST = re.compile(r'\[\s*' + _SCALAR + r'(?:,\s*' + _SCALAR + r')*\s*\]')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--out`` and ``--results-dir`` to a benchmark subcommand's parser."""
    group = parser.add_argument_group('results file')
    where = group.add_mutually_exclusive_group()
    where.add_argument('--out', metavar='FILE', default=None,
                       help='also write the results as JSON to FILE')
    where.add_argument('--results-dir', metavar='DIR', nargs='?', const=str(RESULTS_DIR),
                       default=None,
                       help=f'also write the results as JSON to DIR/NAME.json '
                            f'(DIR default: {RESULTS_DIR})')


def target(name: str, args: argparse.Namespace) -> Optional[Path]:
    """Return the results file asked for by ``--out`` or ``--results-dir``, or None."""
    if getattr(args, 'out', None):
        return Path(args.out)
    if getattr(args, 'results_dir', None):
        return Path(args.results_dir) / f'{name}.json'
    return None


def cpu_model() -> str:
    """Return the CPU's model name (``/proc/cpuinfo``), or what the platform says."""
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as cpuinfo:
            for line in cpuinfo:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def os_name() -> str:
    """Return the OS's pretty name (``/etc/os-release``) and kernel release."""
    name = platform.system()
    try:
        with open('/etc/os-release', encoding='utf-8') as release:
            for line in release:
                if line.startswith('PRETTY_NAME='):
                    name = line.split('=', 1)[1].strip().strip('"')
    except OSError:
        pass
    return f'{name}, kernel {platform.release()}'


def versions() -> dict[str, str]:
    """Return the installed versions of :data:`VERSIONS` (missing ones left out)."""
    found = {}
    for name in VERSIONS:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return found


def machine() -> dict[str, Any]:
    """Describe this machine: CPU model, cores, architecture, OS, Python, library versions."""
    return {'cpu': cpu_model(), 'cores': os.cpu_count(), 'architecture': platform.machine(),
            'os': os_name(), 'python': platform.python_version(), 'versions': versions()}


# Sizes of the machine's speed reference (``speed_reference``).
REFERENCE_LOOP_STEPS = 1_000_000
REFERENCE_GATHER_ITEMS = 4_000_000


def speed_reference() -> dict[str, float]:
    """Time two fixed tasks: how fast this machine runs now, to compare runs on other days.

    ``python_loop_ms``: a Python loop adding REFERENCE_LOOP_STEPS integers
    (the interpreter, where a step's set-up runs); ``gather_ns``: numpy's
    gather of REFERENCE_GATHER_ITEMS rows of an array of that many 3-vectors
    in a fixed random order, per row (memory latency, what a large world's
    kernels wait on). Best of three each. A shared virtual machine can run
    the same code 2 to 3 times slower on one day than on another; a
    benchmark's figures are comparable across runs only with these beside them.
    """
    import numpy as np

    loop = []
    for _ in range(3):
        start = time.perf_counter()
        total = 0
        for step in range(REFERENCE_LOOP_STEPS):
            total += step
        loop.append(time.perf_counter() - start)
    rows = np.random.default_rng(0).permutation(REFERENCE_GATHER_ITEMS)
    points = np.ones((REFERENCE_GATHER_ITEMS, 3))
    gather = []
    for _ in range(3):
        start = time.perf_counter()
        points.take(rows, axis=0)
        gather.append(time.perf_counter() - start)
    return {'python_loop_ms': round(min(loop) * 1e3, 1),
            'gather_ns': round(min(gather) / REFERENCE_GATHER_ITEMS * 1e9, 2)}


def load_average() -> list[float]:
    """Return the 1, 5 and 15 minute load averages, rounded to 0.01."""
    return [round(value, 2) for value in os.getloadavg()]


def local_paths() -> list[tuple[str, str]]:
    """Return (path, stand-in) pairs for the machine paths a result must not name."""
    pairs = [(str(Path.cwd()), '.'), (tempfile.gettempdir(), '<temporary folder>'),
             (str(Path.home()), '~')]
    return [(path, stand_in) for path, stand_in in pairs if len(path) > 1]


def scrub(text: str) -> str:
    """Replace this machine's working, temporary and home folders in ``text`` by stand-ins."""
    for path, stand_in in local_paths():
        text = re.sub(re.escape(path) + r'[^\s\'",;:)\]]*',
                      lambda match, p=path, s=stand_in: s + match.group(0)[len(p):]
                      if s == '.' else s, text)
    return text


def split_cells(line: str) -> list[str]:
    """Return the stripped cells of a Markdown table line."""
    return [cell.strip() for cell in line.strip().strip('|').split('|')]


def alignment(separator: str) -> list[str]:
    """Return 'left', 'right' or 'center' per column of a Markdown separator line."""
    kinds = []
    for cell in split_cells(separator):
        if cell.startswith(':') and cell.endswith(':'):
            kinds.append('center')
        elif cell.endswith(':'):
            kinds.append('right')
        else:
            kinds.append('left')
    return kinds


def parse_output(text: str) -> list[dict[str, Any]]:
    """Split printed output into blocks: ``text`` (non-empty lines) and ``table``.

    A table is a ``|``-line followed by a separator line and its rows; a
    row with more cells than columns (a ``|`` inside a value) keeps the
    surplus in its last cell.
    """
    blocks: list[dict[str, Any]] = []
    lines = text.splitlines()
    k = 0
    while k < len(lines):
        line = lines[k].rstrip()
        is_table = (line.startswith('|') and k + 1 < len(lines) and
                    SEPARATOR.match(lines[k + 1].strip()) is not None)
        if is_table:
            columns = split_cells(line)
            rows = []
            k += 2
            while k < len(lines) and lines[k].strip().startswith('|'):
                cells = split_cells(lines[k])
                if len(cells) > len(columns):
                    cells = cells[:len(columns) - 1] + [' | '.join(cells[len(columns) - 1:])]
                rows.append(cells + [''] * (len(columns) - len(cells)))
                k += 1
            blocks.append({'kind': 'table', 'columns': columns,
                           'align': alignment(lines[k - len(rows) - 1])[:len(columns)],
                           'rows': rows})
            continue
        if line.strip():
            if blocks and blocks[-1]['kind'] == 'text':
                blocks[-1]['lines'].append(line.strip())
            else:
                blocks.append({'kind': 'text', 'lines': [line.strip()]})
        k += 1
    return blocks


class Tee(io.TextIOBase):
    """A text stream that writes to another stream and keeps a copy."""

    def __init__(self, stream: TextIO) -> None:
        """Write to ``stream``, keeping a copy in ``self.copy``."""
        super().__init__()
        self.stream = stream
        self.copy = io.StringIO()

    def write(self, text: str) -> int:
        """Write ``text`` to the stream and to the copy."""
        self.copy.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        """Flush the underlying stream."""
        self.stream.flush()


@contextlib.contextmanager
def captured() -> Iterator[Tee]:
    """Copy everything printed to ``sys.stdout`` meanwhile (it is still printed)."""
    tee = Tee(sys.stdout)
    with contextlib.redirect_stdout(tee):
        yield tee


def options(args: argparse.Namespace) -> dict[str, Any]:
    """Return the parsed options as JSON values, the results options left out."""
    found = {}
    for key, value in sorted(vars(args).items()):
        if key in ('out', 'results_dir', 'command'):
            continue
        if isinstance(value, (str, int, float, bool, list, type(None))):
            found[key] = scrub(value) if isinstance(value, str) else value
        else:
            found[key] = scrub(str(value))
    return found


def command_line(argv: Sequence[str]) -> str:
    """Return the shell command that ran the benchmark."""
    prefix = ''.join(f'{name}=... ' for name in ENVIRONMENT if name in os.environ)
    return scrub(prefix + PROGRAM + ' ' + shlex.join(argv))


def record(name: str, argv: Sequence[str], args: argparse.Namespace, output: str,
           exit_code: int, started: dict[str, Any]) -> dict[str, Any]:
    """Return the results record of one benchmark run."""
    return {
        'format': FORMAT,
        'benchmark': name,
        'command': command_line(argv),
        'environment': {key: ('set' if key == 'NUMBA_CACHE_DIR' else os.environ[key])
                        for key in ENVIRONMENT if key in os.environ},
        'options': options(args),
        'machine': started['machine'],
        'started_utc': started['utc'],
        'seconds': round(time.monotonic() - started['clock'], 1),
        'load_average_start': started['load'],
        'load_average_end': load_average(),
        'speed_reference': started.get('speed_reference'),
        'exit_code': exit_code,
        'output': parse_output(scrub(output)),
    }


def run_recorded(name: str, run: Callable[[argparse.Namespace], int],
                 args: argparse.Namespace, argv: Sequence[str]) -> int:
    """Run a benchmark; with ``--out``/``--results-dir``, write its results file too."""
    path = target(name, args)
    if path is None:
        return int(run(args))
    if path.exists() and path.is_dir():
        print(f'bench {name}: --out {path}: is a folder', file=sys.stderr)
        return 2
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        print(f'bench {name}: --out {path}: cannot write: {error.strerror}', file=sys.stderr)
        return 2
    if not os.access(path if path.exists() else path.parent, os.W_OK):
        print(f'bench {name}: --out {path}: cannot write: permission denied', file=sys.stderr)
        return 2
    started = {'machine': machine(), 'load': load_average(),
               'speed_reference': speed_reference(), 'clock': time.monotonic(),
               'utc': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M')}
    with captured() as tee:
        exit_code = int(run(args))
    result = record(name, argv, args, tee.copy.getvalue(), exit_code, started)
    path.write_text(dumps(result), encoding='utf-8')
    print(f'results: {path}', file=sys.stderr)
    return exit_code


def dumps(data: dict[str, Any]) -> str:
    """Return ``data`` as indented JSON with every list of scalars (a table row) on one line."""
    text = json.dumps(data, indent=1, ensure_ascii=False)
    compact = SCALAR_LIST.sub(lambda match: json.dumps(json.loads(match.group(0)),
                                                       ensure_ascii=False), text)
    # A list written inside a string value could have been matched too: keep the plain text.
    return (compact if json.loads(compact) == data else text) + '\n'


def read(path: Path) -> dict[str, Any]:
    """Read one results file; raise ValueError naming the file and what is wrong."""
    try:
        data = json.loads(path.read_text(encoding='utf-8'))
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f'{path}: not a results file: {error}') from None
    if not isinstance(data, dict) or data.get('format') != FORMAT:
        raise ValueError(f'{path}: not a results file of format {FORMAT}')
    for key in ('benchmark', 'command', 'machine', 'output', 'load_average_start'):
        if key not in data:
            raise ValueError(f'{path}: no "{key}"')
    return data
