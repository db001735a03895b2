"""Throughput: ns per particle-step of a 3-D elastic gas at fixed density.

``python -m collision_node.bench throughput`` builds a gas of N particles
(radius 0.05 m, mass 1 kg, speed 1 m/s, e = 1) in a walled cube whose side
grows as N^(1/3), so the number density (and the collision rate per
particle) is the same for every N, as in ``scenes/gas_10k.yaml`` (4.2 %
volume fraction), or ``--fraction`` (e.g. 0.1) if given. It times
whole world steps (every stage of the pipeline, walls included) and
prints a Markdown table with the growth exponent between successive N:
log(t2 / t1) / log(N2 / N1) for the wall time per step, 1.0 being linear.
The CPU-time column is this process's CPU time: on a shared machine it
shows how much of the wall time was waiting for a core. ``--profile``
adds each run's wall time per stage (``World.profile``).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from typing import Optional

from ..physics.model.scene import parse_scene
from ..physics.step.world import World
from ..scenarios import gas

DEFAULT_COUNTS = (1_000, 10_000, 100_000)
# Density of scenes/gas_10k.yaml: 10,000 particles in a 5 m cube (4.2 % volume fraction).
REFERENCE_COUNT = 10_000
REFERENCE_SIDE = 5.0
RADIUS = 0.05
DT = 1.0 / 240.0


def gas_scene(count: int, seed: int = 7, fraction: Optional[float] = None) -> dict:
    """Return the scene mapping of a walled 3-D gas of ``count`` particles.

    The density is that of gas_10k, or the volume ``fraction`` if given.
    """
    if fraction is None:
        half = 0.5 * REFERENCE_SIDE * (count / REFERENCE_COUNT) ** (1.0 / 3.0)
    else:
        half = 0.5 * (count * 4.0 / 3.0 * math.pi * RADIUS ** 3 / fraction) ** (1.0 / 3.0)
    return gas(count, RADIUS, 1.0, seed=seed, low=-half, high=half, wall_restitution=1.0,
               effects={'restitution': 1.0}, name=f'gas_{count}', dt=DT)


def time_gas(count: int, steps: int, warmup: int, accuracy: str = 'balanced',
             fraction: Optional[float] = None) -> dict:
    """Step a gas of ``count`` particles; return timing and conservation numbers."""
    world = World(parse_scene(dict(gas_scene(count, fraction=fraction), accuracy=accuracy),
                              f'gas_{count}'))
    world.step(warmup)
    energy_start = world.kinetic_energy()
    collisions_start = world.stats.collisions
    start, cpu_start = time.perf_counter(), time.process_time()
    world.step(steps)
    seconds = time.perf_counter() - start
    cpu_seconds = time.process_time() - cpu_start
    return {
        'count': count,
        'steps': steps,
        'seconds': seconds,
        'ns_per_particle_step': seconds / (steps * count) * 1e9,
        'cpu_ns_per_particle_step': cpu_seconds / (steps * count) * 1e9,
        'collisions_per_step': (world.stats.collisions - collisions_start) / steps,
        'energy_drift': world.kinetic_energy() / energy_start - 1.0,
        'profile': world.profile(),
    }


def growth_exponent(smaller: dict, larger: dict) -> float:
    """Return log(t2 / t1) / log(N2 / N1) for the time per step; 1.0 is linear."""
    per_step = larger['seconds'] / larger['steps']
    smaller_per_step = smaller['seconds'] / smaller['steps']
    return math.log(per_step / smaller_per_step) / math.log(larger['count'] / smaller['count'])


def steps_for(count: int, budget_particle_steps: float) -> int:
    """Return how many steps give about ``budget_particle_steps`` of work (>= 5)."""
    return max(5, int(budget_particle_steps / count))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare the subcommand's options."""
    parser.add_argument('--counts', type=int, nargs='+', default=list(DEFAULT_COUNTS),
                        help='particle counts (default: 1000 10000 100000)')
    parser.add_argument('--work', type=float, default=5e6,
                        help='particle-steps timed per count (default: 5e6)')
    parser.add_argument('--warmup', type=int, default=10, help='untimed steps first')
    parser.add_argument('--accuracy', default='balanced',
                        help='accuracy preset of the gas (default: balanced, the default preset)')
    parser.add_argument('--fraction', type=float, default=None,
                        help='volume fraction of the gas (default: the density of gas_10k, '
                             '4.2 %%)')
    parser.add_argument('--profile', action='store_true',
                        help='after the table, the wall time per stage of each count\'s run '
                             '(warm-up and timed steps; the first step apart)')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the Markdown table."""
    if args.fraction is not None and not 0.0 < args.fraction <= 0.3:
        print(f'bench throughput: --fraction must be in (0, 0.3], got {args.fraction:g}')
        return 2
    rows = [time_gas(n, steps_for(n, args.work), args.warmup, args.accuracy, args.fraction)
            for n in sorted(args.counts)]
    load = os.getloadavg()
    machine = platform.processor() or platform.machine()
    density = (f'{REFERENCE_COUNT} per {REFERENCE_SIDE:g} m cube' if args.fraction is None
               else f'volume fraction {args.fraction:g}')
    print(f'3-D elastic gas in walls, radius {RADIUS} m, {density}, '
          f'dt = 1/240 s, accuracy {args.accuracy}; '
          f'{machine}, {os.cpu_count()} cores, '
          f'load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}')
    print()
    print('| N | steps | ns per particle-step | growth exponent | CPU ns per particle-step '
          '| collisions per step | relative energy change |')
    print('|---:|---:|---:|---:|---:|---:|---:|')
    previous = None
    for row in rows:
        growth = '-'
        if previous is not None:
            growth = f'{growth_exponent(previous, row):.3f}'
        print(f'| {row["count"]:,} | {row["steps"]} | {row["ns_per_particle_step"]:.0f} '
              f'| {growth} | {row["cpu_ns_per_particle_step"]:.0f} '
              f'| {row["collisions_per_step"]:.1f} | {row["energy_drift"]:.1e} |')
        previous = row
    if len(rows) > 2:
        print()
        print(f'Growth exponent from N = {rows[0]["count"]:,} to {rows[-1]["count"]:,}: '
              f'{growth_exponent(rows[0], rows[-1]):.3f}')
    if args.profile:
        for row in rows:
            print()
            print(f'Per stage, N = {row["count"]:,} ({args.accuracy}):')
            print()
            print(row['profile'].table())
    return 0
