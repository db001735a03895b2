"""Benchmark commands: ``python -m collision_node.bench SUBCOMMAND [options]``.

Each subcommand lives in a module of its own that exposes
``add_arguments(parser)`` and ``run(args) -> int``. Registering one is a
one-line change: add ``'NAME': 'collision_node.bench.NAME'`` to
``SUBCOMMANDS`` (the contact benchmarks, ``pile``, ``stacks`` and
``resting``, live in the subpackage ``bench.contact``). Modules are
imported only when their subcommand runs, so
one that needs ROS (``bench.node``) costs the others nothing. Every
subcommand but those in ``OWN_RESULTS`` also takes ``--out FILE`` and
``--results-dir [DIR]`` and then writes its results as JSON
(:mod:`collision_node.bench.results.files`); ``report`` renders
docs/performance.md from those files. Every subcommand takes
``--threads N``: the thread count of every world it builds (0, the
default: every core).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Optional, Sequence

# Subcommand name -> module with add_arguments(parser) and run(args).
SUBCOMMANDS: dict[str, str] = {
    'throughput': 'collision_node.bench.throughput',
    'node': 'collision_node.bench.node_ticks',
    'effects': 'collision_node.bench.effect_costs',
    'accuracy': 'collision_node.bench.accuracy_ladder',
    'node-load': 'collision_node.bench.node_load',
    'commands': 'collision_node.bench.spawn_burst',
    'pile': 'collision_node.bench.contact.pile',
    'mixed': 'collision_node.bench.mixed',
    'exact': 'collision_node.bench.exact',
    'node-start': 'collision_node.bench.node_start',
    'resting': 'collision_node.bench.contact.resting',
    'report': 'collision_node.bench.results.page',
    'stacks': 'collision_node.bench.contact.stacks',
    'scaling': 'collision_node.bench.scaling',
    'compile': 'collision_node.bench.compile_time',
}
# Subcommands that write files of their own instead of a results file (as does any
# subcommand that declares an --out of its own).
OWN_RESULTS = frozenset({'accuracy', 'report'})


def _with_threads(args: argparse.Namespace) -> int:
    """Make ``args.threads`` every world's thread count; return 0, or 2 with a reason."""
    from ..physics.model.validation import SceneError
    from ..physics.step.threads import set_default
    try:
        set_default(args.threads)
    except SceneError as error:
        print(f'bench {args.command}: {error}', file=sys.stderr)
        return 2
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse the subcommand, hand the rest to its module; return the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog='python -m collision_node.bench',
                                     description='collision_node benchmarks.')
    commands = parser.add_subparsers(dest='command', metavar='SUBCOMMAND', required=True)
    if argv and argv[0] in SUBCOMMANDS:
        # Import only the module that will run; list the others by name.
        module = importlib.import_module(SUBCOMMANDS[argv[0]])
        sub = commands.add_parser(argv[0], help=(module.__doc__ or '').split('\n')[0])
        module.add_arguments(sub)
        if '--threads' not in sub._option_string_actions:
            sub.add_argument('--threads', type=int, default=0, metavar='N',
                             help='threads the kernels of every world share (default 0: every '
                                  'core; 1: single-thread kernels)')
        # A module with an --out of its own writes its own files.
        if argv[0] in OWN_RESULTS or '--out' in sub._option_string_actions:
            args = parser.parse_args(argv)
            return _with_threads(args) or int(module.run(args))
        from .results import files
        files.add_arguments(sub)
        args = parser.parse_args(argv)
        return _with_threads(args) or files.run_recorded(argv[0], module.run, args, argv)
    for name in SUBCOMMANDS:
        commands.add_parser(name)
    parser.parse_args(argv)  # prints usage and exits 2 for an unknown subcommand
    return 2
