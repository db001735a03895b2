"""Benchmark: resting contact under gravity, what each preset pays to hold a pile still.

    python -m collision_node.bench resting [--presets fast balanced accurate exact]
                                            [--scenes column pile drop]

Three 2-D scenes under gravity (g = 9.81 m/s^2, dt = 1/240 s, discs of
r = 5 cm, 1 kg, e = 0, no friction):

- ``column``: 20 discs stacked on a floor, at rest (240 timed steps);
- ``pile``: 500 discs in 20 hexagonal rows of 25 between two walls, at
  rest (24 timed steps: the `accurate` solver takes over a second a step);
- ``drop``: the pile with one more disc dropped from 0.3 m above it into a
  hollow of its top row (60 timed steps: the landing and after).

The table gives CPU ms per step, the steps the `exact` preset handed to
its step solver (``fallback_steps``), the fastest disc at the end (m/s) and
the deepest overlap at the end as a fraction of r. Two untimed steps come
first. A command, not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from ...physics.step import kernels
from ...physics.model.scene import parse_scene
from ...physics.stages.detection.broadphase import candidate_pairs
from ...physics.step.world import World
from ...scenarios import ball, resting_column, resting_pile

RADIUS = 0.05
WARM_STEPS = 2
STEPS = {'column': 240, 'pile': 24, 'drop': 60}
PRESETS = ('fast', 'balanced', 'accurate', 'exact')


def scene(name: str, preset: str) -> dict:
    """Return the scene ``name`` under ``preset``."""
    if name == 'column':
        mapping = resting_column(20, 0.0, RADIUS)
    else:
        mapping = resting_pile(0.0, 20, 25, RADIUS)
        if name == 'drop':
            top = RADIUS + math.sqrt(3.0) * RADIUS * 19
            mapping['particles'].append(ball([26 * RADIUS, top + 2 * RADIUS + 0.3],
                                             RADIUS, 1.0))
    return dict(mapping, accuracy=preset)


def deepest_overlap(world: World) -> float:
    """Return the deepest overlap between two discs as a fraction of r."""
    s = world.state
    i, j = candidate_pairs(s.position, s.radius)
    if i.size == 0:
        return 0.0
    gap = np.linalg.norm(s.position[i] - s.position[j], axis=1) - (s.radius[i] + s.radius[j])
    return float(max(0.0, -gap.min())) / RADIUS


def measure(name: str, preset: str, steps: int) -> tuple[float, int, float, float]:
    """Return (CPU ms per step, fallback steps, fastest speed m/s, overlap / r)."""
    world = World(parse_scene(scene(name, preset), f'bench:resting_{name}'))
    world.step(WARM_STEPS)
    start = time.process_time()
    world.step(steps)
    cpu = time.process_time() - start
    fastest = float(np.max(np.linalg.norm(world.state.velocity, axis=1)))
    return (cpu / steps * 1e3, world.stats.fallback_steps, fastest, deepest_overlap(world))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this benchmark's options."""
    parser.add_argument('--presets', nargs='+', default=list(PRESETS), choices=PRESETS,
                        help='presets to run (default: all four)')
    parser.add_argument('--scenes', nargs='+', default=list(STEPS), choices=list(STEPS),
                        help='scenes to run (default: column pile drop)')


def run(args: argparse.Namespace) -> int:
    """Print one row per scene and preset."""
    kernels.prepare(print)
    print(f'# resting contact under gravity, 2-D discs r = {RADIUS} m, dt = 1/240 s, e = 0; '
          f'CPU time; load average {" ".join(f"{x:.2f}" for x in os.getloadavg())}, '
          f'{os.cpu_count()} CPUs')
    print('| scene | preset | steps | ms/step | fallback steps | fastest at end m/s '
          '| deepest overlap / r |')
    print('|---|---|---|---|---|---|---|')
    for name in args.scenes:
        for preset in args.presets:
            ms, fallbacks, fastest, overlap = measure(name, preset, STEPS[name])
            print(f'| {name} | {preset} | {STEPS[name]} | {ms:.3g} | {fallbacks} '
                  f'| {fastest:.2g} | {overlap:.3g} |', flush=True)
    return 0
