"""Offline runner: ``python -m collision_node.simulate SCENE [options]``.

Runs a scene without ROS, prints a short summary, and writes the final
state and statistics as JSON. A bad scene or argument exits with code 2
and one line on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Optional, Sequence

import numpy as np
from tqdm import tqdm

from .physics.accuracy import parse_accuracy_text
from .physics.scene import load_scene
from .physics.validation import SceneError
from .physics.world import NonFiniteStateError, World

# Runs shorter than this never show a progress bar.
PROGRESS_DELAY_S = 2.0
EXIT_BAD_INPUT = 2


class UsageError(Exception):
    """A command-line argument the runner cannot accept."""


class _Parser(argparse.ArgumentParser):
    """An argument parser that reports errors as one line, no usage block."""

    def error(self, message: str) -> None:  # noqa: D102 (argparse hook)
        raise UsageError(message)


def build_parser() -> argparse.ArgumentParser:
    """Return the runner's command-line parser."""
    parser = _Parser(prog='simulate', description='Run a collision_node scene offline.')
    parser.add_argument('scene', help='scene file, or the name of a shipped scene')
    length = parser.add_mutually_exclusive_group()
    length.add_argument('--duration', type=float, help='simulated seconds (default: scene)')
    length.add_argument('--steps', type=int, help='number of steps')
    parser.add_argument('--out', help='write the final state and stats as JSON to this file')
    parser.add_argument('--explain', action='store_true',
                        help='print the step pipeline and exit')
    parser.add_argument('--quiet', action='store_true', help='no summary on stdout')
    parser.add_argument('--accuracy', help='preset (fast, balanced, accurate, exact) or a '
                        'YAML/JSON mapping such as "{preset: fast, substeps: 2}"; '
                        'overrides the scene\'s accuracy')
    return parser


def particle_records(world: World) -> list[dict]:
    """Return the final state as JSON-ready records, one per particle."""
    s = world.state
    mass = s.mass
    records = []
    for k in range(len(s)):
        records.append({
            'id': int(s.ids[k]),
            'position': s.position[k].tolist(),
            'velocity': s.velocity[k].tolist(),
            'radius': float(s.radius[k]),
            'mass': None if math.isinf(mass[k]) else float(mass[k]),
        })
    if s.angular_velocity is not None:
        # Spin exists only when the scene declares friction.
        for k, record in enumerate(records):
            record['angular_velocity'] = s.angular_velocity[k].tolist()
            record['orientation'] = s.orientation[k].tolist()
    return records


def run(world: World, steps: int, show_progress: bool = True) -> float:
    """Step ``world`` ``steps`` times; return the wall-clock seconds it took."""
    start = time.perf_counter()
    chunk = max(1, steps // 200)
    with tqdm(total=steps, unit='step', delay=PROGRESS_DELAY_S, file=sys.stderr,
              disable=not show_progress, leave=False) as bar:
        done = 0
        while done < steps:
            k = min(chunk, steps - done)
            world.step(k)
            done += k
            bar.update(k)
    return time.perf_counter() - start


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the runner; return the process exit code."""
    try:
        args = build_parser().parse_args(argv)
        if args.steps is not None and args.steps < 0:
            raise UsageError(f'--steps must be >= 0, got {args.steps}')
        if args.duration is not None and not (math.isfinite(args.duration)
                                              and args.duration >= 0):
            raise UsageError(f'--duration must be a finite number >= 0, got {args.duration}')
        scene = load_scene(args.scene)
        if args.accuracy is not None:
            scene = scene.with_accuracy(parse_accuracy_text(args.accuracy, scene.effects,
                                                            '--accuracy'))
        world = World(scene)
    except (UsageError, SceneError) as error:
        print(f'simulate: error: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.explain:
        print(world.explain())
        return 0
    duration = scene.duration if args.duration is None else args.duration
    steps = args.steps if args.steps is not None else int(round(duration / scene.dt))
    energy_start, momentum_start = world.kinetic_energy(), world.momentum()
    balance_start = world.energy()
    try:
        wall_seconds = run(world, steps)
    except NonFiniteStateError as error:
        print(f'simulate: error: {scene.name}: {error}', file=sys.stderr)
        return 1
    energy_end, momentum_end = world.kinetic_energy(), world.momentum()
    balance_end = world.energy()
    result = {
        'scene': scene.name,
        'time': world.time,
        'steps': world.steps,
        'particles': particle_records(world),
        'stats': {
            'collisions': world.stats.collisions,
            'wall_collisions': world.stats.wall_collisions,
            'kinetic_energy': [energy_start, energy_end],
            'momentum': [momentum_start.tolist(), momentum_end.tolist()],
            'dissipated': dict(world.stats.dissipated),
            'energy': {'start': balance_start, 'end': balance_end},
            'max_penetration': world.stats.max_penetration,
            'fallback_steps': world.stats.fallback_steps,
            'wall_seconds': wall_seconds,
        },
    }
    if args.out:
        try:
            with open(args.out, 'w', encoding='utf-8') as handle:
                json.dump(result, handle, indent=1)
        except OSError as error:
            print(f'simulate: error: --out {args.out}: {error.strerror}', file=sys.stderr)
            return EXIT_BAD_INPUT
    if not args.quiet:
        d_energy = energy_end - energy_start
        d_momentum = float(np.linalg.norm(momentum_end - momentum_start))
        print(f'{scene.name}: {len(world.state)} particles, {world.steps} steps '
              f'({world.time:g} s simulated) in {wall_seconds:.3f} s wall')
        print(f'collisions: {world.stats.collisions} particle, '
              f'{world.stats.wall_collisions} wall')
        print(f'kinetic energy: {energy_start:.12g} -> {energy_end:.12g} J '
              f'(change {d_energy:+.3g} J)')
        if balance_end['dissipated'] or balance_end['potential']:
            removed = ', '.join(f'{name} {value:.6g}'
                                for name, value in balance_end['dissipated'].items())
            print(f'energy (kinetic + potential): {balance_start["total"]:.12g} -> '
                  f'{balance_end["total"]:.12g} J; removed by effects: {removed or "none"} J; '
                  f'balance error {balance_end["balance_error"]:.3g} J')
        print(f'momentum change: {d_momentum:.3g} kg m/s; '
              f'max penetration: {world.stats.max_penetration:.3g} m')
        if world.stats.fallback_steps:
            print(f'event mode: {world.stats.fallback_steps} of {world.steps} steps met resting '
                  'contact under gravity or passed the event budget and were solved by the '
                  'step fallback')
    return 0


if __name__ == '__main__':
    sys.exit(main())
