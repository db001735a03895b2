"""Mixed sizes: a 3-D gas with some particles ten times larger, against one size.

``python -m collision_node.bench mixed`` builds a 3-D elastic gas of N
particles (default 10,000) at a volume fraction of 10 % in a walled cube:
small particles of r = 5 cm and a share of them (default 10 % and 20 %)
at ``--factor`` (default 10) times that radius, of the same density
(mass 1 kg per small particle, scaled by r^3), all at 1 m/s in random
directions, e = 1, dt = 1/240 s. Positions are drawn at random and
redrawn for the smaller particle of every overlapping pair until no two
overlap. It times whole world steps under each preset (fast, balanced)
and prints ns per particle-step beside the single-size gas of the same N
and volume fraction, measured in the same run.

A second table times the broadphase search alone (``candidate_pairs``)
on static sets: pairs found against the real contacts, so a quadratic
search (pairing the large particles all-to-all) shows at once.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time

import numpy as np

from ..physics.model.scene import parse_scene
from ..physics.stages.detection.broadphase import candidate_pairs
from ..physics.step.world import World

RADIUS = 0.05
DT = 1.0 / 240.0
PLACEMENT_ROUNDS = 500


def mixed_radii(count: int, share: float, factor: float, seed: int) -> np.ndarray:
    """Return ``count`` radii: a random ``share`` of them ``factor`` times RADIUS."""
    rng = np.random.default_rng(seed)
    radius = np.full(count, RADIUS)
    large = rng.choice(count, size=int(round(share * count)), replace=False)
    radius[large] *= factor
    return radius


def box_side(radius: np.ndarray, fraction: float, dimensions: int = 3) -> float:
    """Return the side of the cube that holds ``radius``'s spheres at ``fraction``."""
    unit = math.pi if dimensions == 2 else 4.0 / 3.0 * math.pi
    return (float(np.sum(unit * radius ** dimensions)) / fraction) ** (1.0 / dimensions)


def place(radius: np.ndarray, side: float, seed: int, dimensions: int = 3) -> np.ndarray:
    """Return random positions in [0, side]^d, no two spheres overlapping.

    Every overlapping pair redraws its smaller member (the later one of
    equal size), so the large spheres settle first; the broadphase finds
    the overlaps, so this costs a few searches, not O(n^2).
    """
    rng = np.random.default_rng(seed)
    r = radius[:, None]
    position = rng.uniform(r, side - r, (radius.size, dimensions))
    for _ in range(PLACEMENT_ROUNDS):
        i, j = candidate_pairs(position, radius)
        gap = np.linalg.norm(position[i] - position[j], axis=1) - (radius[i] + radius[j])
        i, j = i[gap < 0.0], j[gap < 0.0]
        if not i.size:
            return position
        smaller = np.where(radius[j] > radius[i], i, j)
        redo = np.unique(smaller)
        position[redo] = rng.uniform(r[redo], side - r[redo], (redo.size, dimensions))
    raise RuntimeError(f'bench mixed: no overlap-free placement after {PLACEMENT_ROUNDS} '
                       'rounds (volume fraction too high?)')


def gas_mapping(radius: np.ndarray, fraction: float, seed: int) -> dict:
    """Return the scene mapping of a walled elastic gas with these radii."""
    side = box_side(radius, fraction)
    position = place(radius, side, seed)
    rng = np.random.default_rng(seed + 1)
    direction = rng.normal(size=(radius.size, 3))
    velocity = direction / np.linalg.norm(direction, axis=1)[:, None]
    mass = (radius / RADIUS) ** 3
    particles = [{'position': position[k].tolist(), 'velocity': velocity[k].tolist(),
                  'radius': float(radius[k]), 'mass': float(mass[k])}
                 for k in range(radius.size)]
    return {'dimensions': 3, 'dt': DT, 'particles': particles,
            'effects': {'walls': {'min': [0.0] * 3, 'max': [side] * 3, 'restitution': 1.0},
                        'restitution': 1.0}}


def time_world(mapping: dict, preset: str, steps: int, warmup: int) -> dict:
    """Step the gas under ``preset``; return ns per particle-step (wall and CPU)."""
    world = World(parse_scene(dict(mapping, accuracy=preset), 'bench mixed'))
    world.step(warmup)
    collisions = world.stats.collisions
    start, cpu_start = time.perf_counter(), time.process_time()
    world.step(steps)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    n = len(world.state)
    return {'ns': wall / (steps * n) * 1e9, 'cpu_ns': cpu / (steps * n) * 1e9,
            'collisions': (world.stats.collisions - collisions) / steps}


def time_search(count: int, share: float, factor: float, fraction: float,
                seed: int) -> dict:
    """Time one ``candidate_pairs`` search on a static random mixed set."""
    radius = mixed_radii(count, share, factor, seed)
    rng = np.random.default_rng(seed)
    side = box_side(radius, fraction)
    position = rng.uniform(0.0, side, (count, 3))
    start = time.perf_counter()
    i, j = candidate_pairs(position, radius)
    seconds = time.perf_counter() - start
    contacts = int(np.sum(np.linalg.norm(position[i] - position[j], axis=1)
                          < radius[i] + radius[j]))
    return {'ms': seconds * 1e3, 'pairs': int(i.size), 'contacts': contacts}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare the subcommand's options."""
    parser.add_argument('--count', type=int, default=10_000, help='particles (10,000)')
    parser.add_argument('--shares', type=float, nargs='+', default=[0.1, 0.2],
                        help='shares of large particles (default: 0.1 0.2)')
    parser.add_argument('--factor', type=float, default=10.0,
                        help='radius of a large particle over a small one (10)')
    parser.add_argument('--fraction', type=float, default=0.1,
                        help='volume fraction of the gas (0.1)')
    parser.add_argument('--presets', nargs='+', default=['fast', 'balanced'],
                        help='presets (default: fast balanced)')
    parser.add_argument('--steps', type=int, default=100, help='timed steps per run (100)')
    parser.add_argument('--warmup', type=int, default=5, help='untimed steps first (5)')
    parser.add_argument('--seed', type=int, default=3, help='placement seed')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the Markdown tables."""
    if args.count < 2 or args.steps < 1 or not 0.0 < args.fraction < 0.5:
        print('bench mixed: need --count >= 2, --steps >= 1, 0 < --fraction < 0.5')
        return 2
    load = os.getloadavg()
    print(f'3-D elastic gas, N = {args.count:,}, volume fraction {args.fraction:g}, small '
          f'r = {RADIUS} m, large r = {args.factor:g} x that, dt = 1/240 s, {args.steps} '
          f'timed steps; {platform.processor() or platform.machine()}, {os.cpu_count()} '
          f'cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}')
    print()
    print('| large share | preset | ns per particle-step | CPU ns per particle-step '
          '| vs single size (CPU) | collisions per step |')
    print('|---:|---|---:|---:|---:|---:|')
    gases = {share: gas_mapping(mixed_radii(args.count, share, args.factor, args.seed),
                                args.fraction, args.seed)
             for share in [0.0] + list(args.shares)}
    for preset in args.presets:
        single = None
        for share, mapping in gases.items():
            row = time_world(mapping, preset, args.steps, args.warmup)
            single = single or row
            print(f'| {share:g} | {preset} | {row["ns"]:.0f} | {row["cpu_ns"]:.0f} '
                  f'| {row["cpu_ns"] / single["cpu_ns"]:.2f} | {row["collisions"]:.1f} |')
    print()
    print('Broadphase search alone (`candidate_pairs`, static random positions, '
          'overlaps allowed):')
    print()
    print('| N | large share | factor | ms per search | pairs found | real contacts |')
    print('|---:|---:|---:|---:|---:|---:|')
    for share, factor in ((0.2, 10.0), (0.45, 5.0)):
        row = time_search(8_000, share, factor, args.fraction, args.seed)
        print(f'| 8,000 | {share:g} | {factor:g} | {row["ms"]:.1f} | {row["pairs"]:,} '
              f'| {row["contacts"]:,} |')
    return 0
