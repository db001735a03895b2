"""Stacks: do columns, pyramids and piles stand, wake and conserve, per preset.

``python -m collision_node.bench stacks [--presets ...] [--cases ...]``
runs the stack scenarios of ``collision_node.scenarios`` under each preset
(``exact`` where it accepts the scene: it refuses friction) and prints one
Markdown table per kind of case, one row per case and preset, each with the
steps, the wall and CPU ms per step and the case's outcomes:

- ``column``: 20 spheres on a floor, touching exactly (dt = 1/60 s), 10 s:
  the top centre's height error over r at the end, and its largest over the run;
  ``column_5cm`` the same with r = 5 cm, whose gaps are rounded (1e-16 m);
- ``pyramid`` / ``pyramid_mu0``: 55 discs, the bottom row spanning its box
  (mu = 0.5 / no friction), 10 s: the largest displacement of a disc over r;
- ``pile``: the shipped ``pile`` after 480 steps: the deepest overlap over r
  (discs and walls) and the pairs overlapping by more than 1 % of r;
- ``drop_pile`` / ``drop_column``: that settled pile (the column after 10 s)
  with a ball dropped from 0.3 m above its top, then as long again: the
  particles it moved by more than 1 % of r, the fastest speed at the end
  against the restitution threshold, the deepest overlap over r at the end;
- ``cluster``: 27 touching spheres (e = 0.5, mu = 0.3) moving at 0.5 m/s in
  random directions, falling without walls for 120 steps: the largest relative
  error of the momentum against p0 + M g t over the steps;
- ``pour_spread``: the 2-D pour of 100 discs once per seed (``--seeds``,
  default 1 to 6), settled 360 steps, then a ball dropped on it and 360 steps
  more: the median, least and most of the deepest overlap over r (discs and
  walls) and how many seeds end above 1 % of r, settled and after the drop.
  A pile is chaotic: a change of the last bit of one push ends it elsewhere,
  so one pour says on which side of a bound that pour fell, the spread how
  near the bound the preset sits.

A preset that refuses a scene gives a row saying so, the reason printed
below the tables. ``--out FILE`` / ``--results-dir [DIR]`` (the dispatcher's)
record the tables as JSON. Limits of what the numbers say: one run each, on
a shared machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Callable, Optional

import numpy as np

from ...physics.model.validation import SceneError
from ...physics.step.kernels import prepare as prepare_kernels
from ...physics.step.world import World
from ...scenarios import (PILE_SETTLE_STEPS, pour2d, STACK_DT, STACK_RADIUS, column_top,
                          disc_pyramid, drop_ball, falling_cluster, shipped_pile, sphere_column)
from .pile import _load_line, pile_quality

PRESETS = ('fast', 'balanced', 'accurate', 'exact')
# Steps of the column and the pyramid: 10 s at dt = 1/60 s.
STACK_STEPS = round(10.0 / STACK_DT)
# Steps of the falling cluster, and its spheres' initial speed, m/s.
CLUSTER_STEPS = 120
CLUSTER_SPEED = 0.5
CLUSTER_SEED = 1
# m: height of the dropped ball's lowest point above the highest particle's top.
DROP_HEIGHT = 0.3
# A particle counts as moved when it is displaced by more than this fraction of r.
MOVED_RADII = 0.01
# The spread of settled pours: discs, steps to settle (and after the drop), seeds.
SPREAD_DISCS = 100
SPREAD_STEPS = 360
SPREAD_SEEDS = (1, 2, 3, 4, 5, 6)
# Most seeds one run takes (each pours, settles and drops once per preset).
MAX_SEEDS = 64
# Of r: the bound the spread counts the seeds above.
OVERLAP_BOUND = 0.01
CASES = ('column', 'column_5cm', 'pyramid', 'pyramid_mu0', 'pile', 'drop_pile', 'drop_column',
         'cluster', 'pour_spread')


def timed_steps(world: World, steps: int,
                each: Optional[Callable[[World], None]] = None) -> tuple[float, float]:
    """Step ``world`` ``steps`` times calling ``each`` after every step.

    Returns the wall and the CPU seconds of the steps (``each`` not counted).
    """
    wall, cpu = 0.0, 0.0
    for _ in range(steps):
        start, cpu_start = time.perf_counter(), time.process_time()
        world.step()
        wall += time.perf_counter() - start
        cpu += time.process_time() - cpu_start
        if each is not None:
            each(world)
    return wall, cpu


def _times(seconds: tuple[float, float], steps: int) -> dict:
    """Return the steps and the wall and CPU ms per step of ``seconds`` (wall, CPU)."""
    return {'steps': steps, 'ms': 1e3 * seconds[0] / steps, 'cpu_ms': 1e3 * seconds[1] / steps}


def quality(world: World) -> dict:
    """Return the pile quality of ``world``'s state (overlaps, contacts, fastest speed)."""
    s, walls, dims = world.state, world.scene.effects.walls, world.scene.dimensions
    low = walls.low if walls is not None else np.full(3, -np.inf)
    high = walls.high if walls is not None else np.full(3, np.inf)
    return pile_quality(s.position, s.velocity, s.radius, low, high, dims)


def column(preset: str, radius: float = STACK_RADIUS) -> dict:
    """Stand the column of 20 spheres for 10 s; return the top centre's height error over r."""
    world = World(sphere_column(radius=radius, accuracy=preset))
    r, exact = radius, column_top(radius=radius)
    worst = [0.0]

    def track(w: World) -> None:
        worst[0] = max(worst[0], abs(float(w.state.position[-1, 1]) - exact) / r)

    seconds = timed_steps(world, STACK_STEPS, track)
    top = float(world.state.position[-1, 1])
    return dict(_times(seconds, STACK_STEPS), top_m=top, exact_m=exact,
                top_error_r=(top - exact) / r, worst_error_r=worst[0])


def pyramid(preset: str, friction: Optional[float]) -> dict:
    """Stand the pyramid of 55 discs for 10 s; return the largest displacement over r."""
    world = World(disc_pyramid(friction=friction, accuracy=preset))
    start, r = world.state.position.copy(), float(world.state.radius[0])
    worst = [0.0]

    def track(w: World) -> None:
        moved = np.linalg.norm(w.state.position - start, axis=1).max() / r
        worst[0] = max(worst[0], float(moved))

    seconds = timed_steps(world, STACK_STEPS, track)
    final = float(np.linalg.norm(world.state.position - start, axis=1).max()) / r
    return dict(_times(seconds, STACK_STEPS), displacement_r=final,
                worst_displacement_r=worst[0])


def pile(preset: str) -> dict:
    """Settle the shipped pile for 480 steps; return its deepest overlap, pairs over 1 % r."""
    world = World(shipped_pile(preset))
    seconds = timed_steps(world, PILE_SETTLE_STEPS)
    return dict(quality(world), **_times(seconds, PILE_SETTLE_STEPS))


def drop(world: World, settle_steps: int) -> dict:
    """Settle ``world``, drop a ball on it, step as long again: what moved, whether it rests."""
    wall, cpu = timed_steps(world, settle_steps)
    before = world.state.position.copy()
    asleep_before = world.asleep_count
    r = float(world.state.radius[0])
    drop_ball(world, height=DROP_HEIGHT)
    more = timed_steps(world, settle_steps)
    moved = np.linalg.norm(world.state.position[:len(before)] - before, axis=1) / r
    threshold = world.scene.effects.threshold(world.scene.dt)
    out = quality(world)
    return dict(out, moved=int(np.count_nonzero(moved > MOVED_RADII)),
                largest_move_r=float(moved.max()), asleep_before=asleep_before,
                asleep_after=world.asleep_count, particles=len(world.state),
                at_rest=bool(out['fastest'] < threshold), threshold=threshold,
                **_times((wall + more[0], cpu + more[1]), 2 * settle_steps))


def cluster(preset: str) -> dict:
    """Drop 27 touching spheres freely; return the largest relative error vs p0 + M g t."""
    world = World(falling_cluster(speed=CLUSTER_SPEED, seed=CLUSTER_SEED, accuracy=preset))
    s = world.state
    mass = 1.0 / s.inv_mass
    p0 = (mass[:, None] * s.velocity).sum(axis=0)
    weight = mass.sum() * world.scene.effects.gravity
    worst = [0.0]

    def track(w: World) -> None:
        expected = p0 + weight * w.time
        error = np.linalg.norm(w.momentum() - expected) / np.linalg.norm(expected)
        worst[0] = max(worst[0], float(error))

    seconds = timed_steps(world, CLUSTER_STEPS, track)
    return dict(_times(seconds, CLUSTER_STEPS), momentum_error=worst[0],
                collisions=world.stats.collisions)


def deepest_overlap(world: World) -> float:
    """Return the deepest overlap of a pair or of a particle with a wall, over r."""
    found = quality(world)
    return max(found['overlap_pairs_r'], found['overlap_walls_r'])


def _spread(values: list, prefix: str) -> dict:
    """Return the median, least and most of ``values`` and how many exceed OVERLAP_BOUND."""
    return {f'{prefix}_median': float(np.median(values)), f'{prefix}_least': min(values),
            f'{prefix}_most': max(values),
            f'{prefix}_over': sum(value > OVERLAP_BOUND for value in values)}


def pour_spread(preset: str, seeds: tuple = SPREAD_SEEDS, discs: int = SPREAD_DISCS,
                steps: int = SPREAD_STEPS) -> dict:
    """Pour, settle and drop a ball on ``discs`` discs per seed; return the overlaps' spread."""
    settled, dropped = [], []
    wall = cpu = 0.0
    for seed in seeds:
        world = World(pour2d(discs, seed=seed, accuracy=preset))
        before = timed_steps(world, steps)
        settled.append(deepest_overlap(world))
        drop_ball(world, height=DROP_HEIGHT)
        after = timed_steps(world, steps)
        dropped.append(deepest_overlap(world))
        wall += before[0] + after[0]
        cpu += before[1] + after[1]
    return dict(_times((wall, cpu), 2 * steps * len(seeds)), seeds=len(seeds),
                **_spread(settled, 'settled'), **_spread(dropped, 'dropped'))


def run_case(case: str, preset: str, seeds: tuple = SPREAD_SEEDS) -> dict:
    """Run one case under one preset; a scene the preset refuses gives a ``skipped`` row.

    ``seeds``: the pours of ``pour_spread``.
    """
    try:
        if case in ('column', 'column_5cm'):
            row = column(preset, STACK_RADIUS if case == 'column' else 0.05)
        elif case in ('pyramid', 'pyramid_mu0'):
            row = pyramid(preset, 0.5 if case == 'pyramid' else None)
        elif case == 'pile':
            row = pile(preset)
        elif case == 'drop_pile':
            row = drop(World(shipped_pile(preset)), PILE_SETTLE_STEPS)
        elif case == 'drop_column':
            row = drop(World(sphere_column(accuracy=preset)), STACK_STEPS)
        elif case == 'pour_spread':
            row = pour_spread(preset, seeds)
        else:
            row = cluster(preset)
    except SceneError as error:
        return {'case': case, 'preset': preset, 'skipped': str(error).rsplit(': ', 1)[-1]}
    return dict(row, case=case, preset=preset)


# The columns every table starts with after case and preset: (heading, row key, format).
TIMES = (('steps', 'steps', '{}'), ('ms per step', 'ms', '{:.3g}'),
         ('CPU ms per step', 'cpu_ms', '{:.3g}'))
# The pile quality of a settled world (``pile_quality``).
QUALITY = (('deepest overlap / r (pairs)', 'overlap_pairs_r', '{:.3g}'),
           ('deepest overlap / r (walls)', 'overlap_walls_r', '{:.3g}'),
           ('pairs over 1 % r', 'pairs_over_0.01r', '{}'),
           ('pairs over 10 % r', 'pairs_over_0.1r', '{}'),
           ('contacts (gap < 1 % r)', 'contacts', '{}'),
           ('top m', 'top', '{:.4g}'),
           ('fastest m/s', 'fastest', '{:.3g}'))
# One table per kind of case: (title, cases, outcome columns as (heading, row key, format)).
TABLES = (
    ('Columns of 20 spheres on a floor, 10 s: the top centre against its exact height',
     ('column', 'column_5cm'),
     (('top m', 'top_m', '{:.10g}'), ('exact top m', 'exact_m', '{:.10g}'),
      ('top error / r', 'top_error_r', '{:.3g}'),
      ('largest error / r', 'worst_error_r', '{:.3g}'))),
    ('Pyramids of 55 discs spanning their box (mu = 0.5 / no friction), 10 s: '
     'the largest displacement of a disc',
     ('pyramid', 'pyramid_mu0'),
     (('displacement / r at the end', 'displacement_r', '{:.3g}'),
      ('largest displacement / r', 'worst_displacement_r', '{:.3g}'))),
    ('The shipped pile settled for 480 steps',
     ('pile',),
     QUALITY),
    (f'A ball dropped from {DROP_HEIGHT:g} m onto the settled pile and the column, then as '
     f'long again: the particles it moved by more than {MOVED_RADII * 100:g} % of r, whether all '
     'rest again (fastest below the restitution threshold)',
     ('drop_pile', 'drop_column'),
     (('particles', 'particles', '{}'), ('moved', 'moved', '{}'),
      ('largest move / r', 'largest_move_r', '{:.3g}'),
      ('asleep before', 'asleep_before', '{}'), ('asleep after', 'asleep_after', '{}'),
      ('threshold m/s', 'threshold', '{:.4g}'),
      ('at rest', 'at_rest', '{}')) + QUALITY),
    (f'27 touching spheres falling freely for {CLUSTER_STEPS} steps: the largest relative '
     'error of the momentum against p0 + M g t',
     ('cluster',),
     (('collisions', 'collisions', '{}'), ('momentum error', 'momentum_error', '{:.2g}'))),
    (f'The 2-D pour of {SPREAD_DISCS} discs once per seed, settled {SPREAD_STEPS} steps, then '
     f'a ball dropped on it and {SPREAD_STEPS} steps more: the deepest overlap / r (discs and '
     f'walls) over the seeds, and the seeds above {OVERLAP_BOUND * 100:g} % of r',
     ('pour_spread',),
     (('seeds', 'seeds', '{}'), ('settled median', 'settled_median', '{:.3g}'),
      ('settled least', 'settled_least', '{:.3g}'), ('settled most', 'settled_most', '{:.3g}'),
      ('settled over 1 %', 'settled_over', '{}'),
      ('dropped median', 'dropped_median', '{:.3g}'),
      ('dropped least', 'dropped_least', '{:.3g}'), ('dropped most', 'dropped_most', '{:.3g}'),
      ('dropped over 1 %', 'dropped_over', '{}'))),
)


def _text(value: object, form: str) -> str:
    """Return a table cell: ``value`` in ``form``, a flag as yes or no."""
    if isinstance(value, bool):
        return 'yes' if value else 'no'
    return form.format(value)


def print_tables(rows: list, presets: list, cases: list) -> None:
    """Print one table per kind of case that ran: one row per case and preset."""
    found = {(row['case'], row['preset']): row for row in rows}
    for title, kinds, outcomes in TABLES:
        ran = [case for case in cases if case in kinds]
        if not ran:
            continue
        columns = TIMES + outcomes
        print()
        print(f'{title}:')
        print()
        print('| case | preset | ' + ' | '.join(heading for heading, _, _ in columns) + ' |')
        print('|---|---|' + '---:|' * len(columns))
        for case in ran:
            for preset in presets:
                row = found[(case, preset)]
                if 'skipped' in row:
                    cells = ['refused'] + [''] * (len(columns) - 1)
                else:
                    cells = [_text(row[key], form) for _, key, form in columns]
                print(f'| {case} | {preset} | ' + ' | '.join(cells) + ' |')
    refused = sorted({row['skipped'] for row in rows if 'skipped' in row})
    if refused:
        print()
    for reason in refused:
        print(f'refused: {reason}')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare the subcommand's options."""
    parser.add_argument('--presets', nargs='+', default=list(PRESETS), choices=PRESETS,
                        help='presets to run (default: all four; exact where it accepts)')
    parser.add_argument('--cases', nargs='+', default=list(CASES), choices=CASES,
                        help='cases to run (default: all)')
    parser.add_argument('--seeds', nargs='+', type=_seed, default=list(SPREAD_SEEDS),
                        help='seeds of pour_spread\'s pours (default: 1 to 6; at most '
                        f'{MAX_SEEDS} seeds, each 0 to 2^32 - 1)')


def _seed(text: str) -> int:
    """Return one seed of ``--seeds``: an integer from 0 to 2^32 - 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not an integer: {text[:20]!r}') from None
    if not 0 <= value < 2 ** 32:
        raise argparse.ArgumentTypeError(f'{value} is outside 0 .. 2^32 - 1')
    return value


def run(args: argparse.Namespace) -> int:
    """Run every case under every preset and print the tables."""
    if len(args.seeds) > MAX_SEEDS:
        print(f'stacks: --seeds: {len(args.seeds)} seeds, at most {MAX_SEEDS}', file=sys.stderr)
        return 2
    took = prepare_kernels()
    print(f'stacks: {_load_line()}; contact kernels ready in {took:.2f} s')
    rows = []
    for preset in args.presets:
        for case in args.cases:
            rows.append(run_case(case, preset, tuple(args.seeds)))
            # Progress on stderr: the results file records stdout only.
            print(f'  {case} under {preset}: done', file=sys.stderr, flush=True)
    print_tables(rows, args.presets, args.cases)
    return 0
