"""First-start compile: seconds to compile every kernel into an empty cache, by process count.

``python -m collision_node.bench compile`` runs ``prepare()`` in a fresh
Python process with ``NUMBA_CACHE_DIR`` set to an empty temporary folder,
once for each process count asked (``--processes 1 2``: all in one
process, then split over two), then starts once more on that cache to
time the load a later start pays. The counts run one after another, so
they do not share the cores. What ``scripts/setup`` prints on a fresh
clone is the same figure at the default count.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

CODE = ('import sys\n'
        'from collision_node.physics.step.kernels import prepare\n'
        'print(prepare(processes={processes}))\n')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``compile``."""
    parser.add_argument('--processes', type=int, nargs='+', default=[1, 2], metavar='P',
                        help='process counts to compile with, one fresh cache each (1 2)')


def run(args: argparse.Namespace) -> int:
    """Compile into an empty cache once per process count; print a table of the seconds."""
    if any(count < 1 for count in args.processes):
        print('bench compile: --processes takes counts of 1 or more', file=sys.stderr)
        return 2
    rows = []
    for count in args.processes:
        with tempfile.TemporaryDirectory(prefix='collision_node_compile_') as cache:
            compiled, wall = _prepare(cache, count)
            loaded, _ = _prepare(cache, count)
        rows.append((count, compiled, wall, loaded))
    base = rows[0][1]
    print('| processes | compile (s, prepare) | process wall (s) | over the first row '
          '| later start, load (s) |')
    print('|---:|---:|---:|---:|---:|')
    for count, compiled, wall, loaded in rows:
        print(f'| {count} | {compiled:.1f} | {wall:.1f} | {compiled / base:.2f} | {loaded:.2f} |')
    return 0


def _prepare(cache: str, processes: int) -> tuple[float, float]:
    """Run ``prepare`` in a fresh process on ``cache``; return its seconds and the wall's."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, '-c', CODE.format(processes=processes)], env=env,
                          capture_output=True, text=True, check=True)
    return float(done.stdout.split()[-1]), time.perf_counter() - start
