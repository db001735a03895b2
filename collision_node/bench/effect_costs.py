"""Benchmark: cost of each effect alone and of all together, per step.

    python -m collision_node.bench effects [--count N] [--steps K] [--repeats R]
    python -m collision_node.bench.effect_costs [same options]

Runs the gas of ``scenes/gas_10k.yaml`` (10,000 particles of r = 5 cm,
1 kg, 1 m/s in a 5 m cube, dt = 1/240 s, about 80 collisions per step;
other counts keep its density) under each effect configuration and
prints the median wall time per step and its ratio to the gas without
effects, as a Markdown table (the one in
docs/performance.md). The 'none' rows are the lecture pipeline, built
from a scene without ``effects`` and from ``effects: {}``: an undeclared
effect is not in the pipeline, so both must cost the same within noise.
A command, not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from typing import Optional, Sequence

from ..physics.model.scene import parse_scene
from ..physics.step.world import World
from ..scenarios import gas

REFERENCE_COUNT = 10_000
REFERENCE_HALF = 2.5                         # m, half the side of gas_10k's cube
WALLS = 'WALLS'                              # placeholder for the count's box
CONFIGS: dict[str, Optional[dict]] = {
    'none (no effects key)': None,
    'none (effects: {})': {},
    'gravity': {'gravity': [0.0, -9.81, 0.0]},
    'walls': {'walls': WALLS},
    'restitution 0.8': {'restitution': 0.8},
    'friction 0.3': {'friction': 0.3},
    'drag': {'drag': {'linear': 0.1, 'quadratic': 0.05}},
    'all': {'gravity': [0.0, -9.81, 0.0], 'walls': WALLS, 'restitution': 0.8,
            'friction': 0.3, 'drag': {'linear': 0.1, 'quadratic': 0.05}},
}


def gas_scene(count: int, effects: Optional[dict]) -> dict:
    """Return gas_10k's gas with ``count`` particles (same density) and ``effects``."""
    half = REFERENCE_HALF * (count / REFERENCE_COUNT) ** (1.0 / 3.0)
    declared = None if effects is None else {key: value for key, value in effects.items()
                                             if value != WALLS}
    return gas(count, 0.05, 1.0, seed=7, low=-half, high=half,
               walls=effects is not None and WALLS in effects.values(), effects=declared,
               name='bench_gas', dt=1.0 / 240.0)


def time_per_step(count: int, effects: Optional[dict], steps: int, accuracy: str) -> float:
    """Return the seconds per step of one run of ``steps`` steps after a warm-up."""
    world = World(parse_scene(dict(gas_scene(count, effects), accuracy=accuracy),
                              'bench_effects'))
    world.step(2)                            # warm-up: caches, first allocations
    start = time.perf_counter()
    world.step(steps)
    return (time.perf_counter() - start) / steps


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this benchmark's options (for ``python -m collision_node.bench effects``)."""
    parser.add_argument('--count', type=int, default=10_000, help='particles (default 10000)')
    parser.add_argument('--steps', type=int, default=50, help='timed steps per run')
    parser.add_argument('--repeats', type=int, default=7, help='runs per configuration')
    # One contact path for every row: under a ccd preset the rows without
    # gravity, drag or friction would take the swept path and the others not.
    parser.add_argument('--accuracy', default='fast',
                        help='accuracy preset for every row (default fast: discrete contacts)')


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse options, run the benchmark; return the exit code."""
    parser = argparse.ArgumentParser(prog='bench_effects', description=__doc__.split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the table; return the exit code."""
    load = os.getloadavg()
    print(f'# {args.count} particles, accuracy {args.accuracy}, '
          f'{args.steps} steps x {args.repeats} runs per row, '
          f'median; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, '
          f'{os.cpu_count()} CPUs')
    print('| effects | stages | ms per step | relative to none |')
    print('|---|---|---|---|')
    # Repeats go round all configurations in turn, so a change of machine
    # load during the run spreads over every row instead of one.
    samples: dict[str, list[float]] = {label: [] for label in CONFIGS}
    for _ in range(args.repeats):
        for label, effects in CONFIGS.items():
            samples[label].append(time_per_step(args.count, effects, args.steps,
                                                args.accuracy))
    baseline = statistics.median(samples['none (no effects key)'])
    for label, effects in CONFIGS.items():
        seconds = statistics.median(samples[label])
        world = World(parse_scene(dict(gas_scene(2, effects), accuracy=args.accuracy),
                                  'bench_effects'))
        stages = ', '.join(world.pipeline.names)
        print(f'| {label} | {stages} | {seconds * 1e3:.1f} | {seconds / baseline:.2f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
