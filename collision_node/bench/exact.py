"""Benchmark: the `exact` preset against `balanced` on the 3-D elastic gas.

    python -m collision_node.bench exact [--counts 1000 10000] [--steps 120 12]

The gas of ``bench throughput`` at a volume fraction of 10 % (walls,
e = 1, dt = 1/240 s) runs under `balanced` and `exact` from the same start;
the table gives CPU ns per particle-step, the ratio exact / balanced, the
impacts resolved per CPU second (particle-particle and particle-wall
impacts) and the events per CPU second. *Events* are what the exact
preset's event loop takes and acts on (``EventDrivenStage.events``): the
impacts, the cell crossings (a particle entering the next cell of the
neighbour grid, no impact: the table gives their number) and wall visits
without an impact (rare). Dropping a prediction that went stale is not an
event, nor is a refresh of a particle whose candidate list was full. Both
rates divide by the whole step's CPU time, so at a small dt they include
each step's per-particle work (publishing the state at the step end). The
events per second depend on the cell size (smaller cells: more crossings);
the impacts per second and the ns per particle-step are the measure of
speed. A command, not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Optional, Sequence

from ..physics.step import kernels
from ..physics.model.scene import parse_scene
from ..physics.step.world import World
from .throughput import gas_scene

FRACTION = 0.1          # volume fraction of the gas
WARM_STEPS = 2          # untimed steps first (first contacts, lists built)


def measure(count: int, steps: int, preset: str) -> tuple[float, float, int, float, int, int]:
    """Time ``steps`` steps of the gas under ``preset``.

    Returns CPU ns per particle-step, impacts per CPU s, impacts, events per
    CPU s, events and cell crossings (0 for a stepped preset).
    """
    scene = dict(gas_scene(count, fraction=FRACTION), accuracy=preset)
    world = World(parse_scene(scene, f'bench:gas_{count}'))
    world.step(WARM_STEPS)
    stage = world.pipeline.stages[0]
    before = world.stats.collisions + world.stats.wall_collisions
    events = getattr(stage, 'events', 0)
    crossings = getattr(stage, 'crossings', 0)
    start = time.process_time()
    world.step(steps)
    cpu = time.process_time() - start
    impacts = world.stats.collisions + world.stats.wall_collisions - before
    events = getattr(stage, 'events', 0) - events
    crossings = getattr(stage, 'crossings', 0) - crossings
    return cpu / (steps * count) * 1e9, impacts / cpu, impacts, events / cpu, events, crossings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this benchmark's options (for ``python -m collision_node.bench exact``)."""
    parser.add_argument('--counts', type=int, nargs='+', default=[1000, 10_000],
                        help='gas sizes (default 1000 10000)')
    parser.add_argument('--steps', type=int, nargs='+', default=[120, 12],
                        help='timed steps per size, one value or one per size')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the table; return the exit code."""
    steps = args.steps if len(args.steps) == len(args.counts) else args.steps[:1] * len(
        args.counts)
    kernels.prepare()
    load = os.getloadavg()
    print(f'# 3-D elastic gas, volume fraction {FRACTION:g}; CPU time; load average '
          f'{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, {os.cpu_count()} CPUs')
    print('| N | steps | balanced ns/particle-step | exact ns/particle-step | exact / balanced '
          '| exact impacts per CPU s | exact events per CPU s | impacts | events '
          '| cell crossings |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    for count, k in zip(args.counts, steps):
        balanced = measure(count, k, 'balanced')[0]
        exact, rate, impacts, event_rate, events, crossings = measure(count, k, 'exact')
        print(f'| {count} | {k} | {balanced:.0f} | {exact:.0f} | {exact / balanced:.2f} '
              f'| {rate:.0f} | {event_rate:.0f} | {impacts} | {events} | {crossings} |',
              flush=True)
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse options and run (``python -m collision_node.bench.exact``)."""
    parser = argparse.ArgumentParser(prog='python -m collision_node.bench.exact',
                                     description=__doc__.split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
