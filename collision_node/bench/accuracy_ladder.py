"""Accuracy benchmark: what each preset buys and what it costs in time.

``python -m collision_node.bench.accuracy_ladder [--quick] [--out DIR]`` (also
``python -m collision_node.bench accuracy`` once registered) runs a fixed
set of scenes under every preset and a dt sweep, with a progress bar, and
writes ``results.md``, ``results.csv``, ``results.json`` and
``error_vs_cost.png`` to ``DIR`` (default ``docs/accuracy``).

Per run: wall and CPU seconds per simulated second (only the
``World.step`` calls are timed; the ratio to ``fast`` uses CPU time, which
other work on a shared machine disturbs less; the 10,000-particle cost runs
are repeated three times, interleaved, and the fastest kept), relative energy error,
momentum error against the exact reference, missed collisions (pairs that
moved straight through a step, so received no impulse, yet came closer
than r1 + r2 in between; wall tunnelling likewise), maximum penetration, the largest position error
against the exact event-driven run at the end, and the cradle's outcome.

Two scenes under gravity show what the presets buy there: a ball dropped
on a floor with e = 0.8 (error: the largest deviation of its first five
apexes from the analytic e^(2k) h, relative to the drop h) and the shipped
``pile`` (240 discs, friction; error: the settled pile's deepest overlap
over the radius, and whether the fastest disc is below the restitution
threshold, i.e. at rest). The pile runs only at its own dt and has no
exact reference (event mode refuses friction); ``--quick`` shortens it to 2 s.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from ..physics.step.reference import end_penetration, missed_collisions
from ..physics.model.scene import parse_scene
from ..physics.step.world import World
from ..scenarios import cradle, gas

PRESET_ORDER = ('fast', 'balanced', 'accurate', 'exact')
DT_FACTORS = (0.25, 1.0, 4.0)
COST_REPEATS = 3


# -- scenes ------------------------------------------------------------------


def _gas(count: int, radius: float, speed: float, dt: float, duration: float,
         seed: int) -> dict:
    """Return an elastic gas in a 1 m box."""
    return gas(count, radius, speed, mass=0.01, seed=seed, dt=dt, duration=duration)


def _billiards() -> dict:
    """Return an elastic 2-D break: 15 racked balls (0.1 mm gaps), cue ball at 8 m/s."""
    r, gap = 0.028575, 1e-4
    pitch = 2 * r + gap
    balls = [{'position': [-0.635, 0.0], 'velocity': [8.0, 0.0], 'radius': r, 'mass': 0.17}]
    for row in range(5):
        for k in range(row + 1):
            balls.append({'position': [0.635 + row * pitch * math.sqrt(3) / 2,
                                       (k - row / 2) * pitch], 'radius': r, 'mass': 0.17})
    box = {'min': [-1.27, -0.635], 'max': [1.27, 0.635]}
    return {'dimensions': 2, 'dt': 1 / 240, 'duration': 3.0, 'effects': {'walls': box},
            'particles': balls}


# The bouncing ball: a ball of r = 10 cm dropped with its bottom BALL_DROP above
# the floor; with restitution e its k-th apex is e^(2k) BALL_DROP (analytic).
BALL_DROP = 1.0
BALL_RESTITUTION = 0.8
BALL_APEXES = 5
# Scenes that run only at their own dt (no dt sweep, no batched run): the
# pile's 480 steps cost seconds each under every preset, and batched
# ordering falls back to sequential under friction anyway.
SINGLE_DT = ('pile',)


def _bouncing_ball() -> dict:
    """Return one ball dropped on a floor (e = 0.8) under gravity, 2-D, 3 s."""
    ball = {'position': [0.0, BALL_DROP + 0.1], 'radius': 0.1, 'mass': 0.5}
    return {'dimensions': 2, 'dt': 1 / 240, 'duration': 3.0, 'particles': [ball],
            'effects': {'gravity': [0.0, -9.81],
                        'walls': {'min': [None, 0.0], 'restitution': BALL_RESTITUTION}}}


def _pile(quick: bool) -> dict:
    """Return the shipped pile scene (240 discs poured under gravity, friction)."""
    from ..physics.model.guard import parse_text
    from ..physics.model.scene import resolve_scene_path
    path = resolve_scene_path('pile')
    mapping = parse_text(path.read_text(encoding='utf-8'), str(path))
    mapping.pop('name', None)
    if quick:
        mapping['duration'] = 2.0
    return mapping


def apex_error(track: list, gravity: float = 9.81) -> float:
    """Return max_k |apex_k - e^(2k) h| / h over the first BALL_APEXES apexes.

    ``track`` holds the ball's (centre height, vertical velocity) after
    every step, the drop first. After each bounce (the vertical velocity
    turns upward) the apex follows from the first state on the way up,
    y + v^2 / (2 g): exact for free flight, so the step's sampling does not
    count as error, only the bounce does. A missing apex (the ball came to
    rest early) counts as an error of 1.
    """
    y, v = np.asarray(track, dtype=float).T
    up = np.flatnonzero((v[1:] > 0.0) & (v[:-1] <= 0.0)) + 1
    apex = (y[up] + v[up] ** 2 / (2.0 * gravity) - 0.1)[:BALL_APEXES]
    expected = BALL_DROP * BALL_RESTITUTION ** (2 * np.arange(1, apex.size + 1))
    worst = float(np.max(np.abs(apex - expected))) / BALL_DROP if apex.size else 1.0
    return worst if apex.size == BALL_APEXES else max(worst, 1.0)


def scenes(quick: bool) -> dict[str, dict]:
    """Return the benchmark's scenes as scene mappings (``quick``: smaller, shorter)."""
    balls = cradle(5, 0.0625, 0.5, 1.0, -0.25, first=1, dimensions=2)
    out = {
        'oblique_pair': {'dimensions': 2, 'dt': 0.001, 'duration': 2.0, 'particles': [
            {'position': [-1.0, 0.25], 'velocity': [2.0, 0.0], 'radius': 0.5, 'mass': 1.0},
            {'position': [1.0, 0.0], 'radius': 0.5, 'mass': 3.0}]},
        'cradle_5': {'dimensions': 2, 'dt': 0.01, 'duration': 1.0, 'particles': balls},
        'bullet_target': {'dimensions': 3, 'dt': 1 / 60, 'duration': 0.1, 'particles': [
            {'position': [0.0, 0.0, 0.0], 'velocity': [756.0, 0.0, 0.0], 'radius': 0.0045,
             'mass': 0.15},
            {'position': [1.0, 0.0, 0.0], 'radius': 0.025, 'mass': 1.0}]},
        'gas_1k': _gas(300 if quick else 1000, 0.01, 1.0, 0.01, 2.0 if quick else 10.0, 1),
        'billiards_break': _billiards(),
        'gas_fast': _gas(300, 0.01, 8.0, 0.01, 0.5 if quick else 1.0, 2),
        'bouncing_ball': _bouncing_ball(),
        'pile': _pile(quick),
    }
    if quick:
        out['billiards_break']['duration'] = 1.0
    for name, mapping in out.items():
        # Every dt of the sweep must land on the same end time as the reference.
        longest = (1.0 if name in SINGLE_DT else max(DT_FACTORS)) * mapping['dt']
        mapping['duration'] = math.ceil(mapping['duration'] / longest - 1e-9) * longest
    return out


def cost_scene(quick: bool) -> dict:
    """Return the 10,000-particle gas used only for the time cost (fast vs others)."""
    return _gas(2000 if quick else 10_000, 0.004, 1.0, 0.01, 0.2 if quick else 1.0, 4)


# -- runs --------------------------------------------------------------------

def run_case(name: str, mapping: dict, accuracy: Any, dt: float, check: bool = True) -> dict:
    """Run one scene under one accuracy and dt; return its measurements."""
    scene = parse_scene(dict(mapping, dt=dt, accuracy=accuracy), f'bench:{name}')
    world = World(scene)
    steps = max(1, int(round(scene.duration / dt)))  # durations are multiples of every dt
    energy0, momentum0 = world.kinetic_energy(), world.momentum()
    walls = scene.effects.walls
    wall_seconds = cpu_seconds = 0.0
    missed_pairs = missed_walls = 0
    penetration = 0.0
    heights = [(float(world.state.position[0, 1]), float(world.state.velocity[0, 1]))]
    for _ in range(steps):
        before = world.state.copy() if check else None
        start, cpu_start = time.perf_counter(), time.process_time()
        world.step()
        wall_seconds += time.perf_counter() - start
        cpu_seconds += time.process_time() - cpu_start
        if check:
            pairs, crossings = missed_collisions(before, world.state, walls)
            missed_pairs += pairs
            missed_walls += crossings
            penetration = max(penetration, end_penetration(world.state))
        heights.append((float(world.state.position[0, 1]), float(world.state.velocity[0, 1])))
    energy1 = world.kinetic_energy()
    s = world.state
    measures = gravity_measures(name, world, heights)
    return {
        'scene': name,
        'accuracy': accuracy if isinstance(accuracy, str) else json.dumps(accuracy),
        'dt': dt,
        'particles': len(s),
        'steps': steps,
        'simulated_s': steps * dt,
        'wall_s': wall_seconds,
        'wall_s_per_sim_s': wall_seconds / (steps * dt),
        'cpu_s_per_sim_s': cpu_seconds / (steps * dt),
        # Kinetic energy is no conserved measure under gravity (and these scenes dissipate).
        'energy_rel_error': None if world.scene.effects.gravity is not None else
        abs(energy1 - energy0) / energy0 if energy0 else 0.0,
        'momentum': world.momentum().tolist(),
        'momentum_scale': float(np.sum(np.linalg.norm(s.velocity, axis=1) / s.inv_mass)),
        'momentum0': momentum0.tolist(),
        'collisions': world.stats.collisions,
        'wall_collisions': world.stats.wall_collisions,
        'missed_pairs': missed_pairs if check else None,
        'missed_walls': missed_walls if check else None,
        'max_penetration': max(penetration, world.stats.max_penetration) if check else None,
        'final_position': s.position.tolist(),
        'final_velocity': s.velocity.tolist(),
        'radius_min': float(s.radius.min()),
        **measures,
    }


def gravity_measures(name: str, world: World, heights: list) -> dict:
    """Return the error measures of the scenes under gravity (None elsewhere).

    ``apex_error``: the bouncing ball's apexes against e^(2k) h (relative to
    h). ``pile_overlap_r``: the settled pile's deepest overlap, between two
    discs or with a wall, over the radius. ``fastest``: the fastest
    particle's speed at the end, and ``threshold`` the restitution
    threshold it must be below for the pile to be at rest.
    """
    out = {'apex_error': None, 'pile_overlap_r': None, 'fastest': None, 'threshold': None}
    if name == 'bouncing_ball':
        out['apex_error'] = apex_error(heights)
    elif name == 'pile':
        from .pile import pile_quality
        s, walls = world.state, world.scene.effects.walls
        quality = pile_quality(s.position, s.velocity, s.radius, walls.low, walls.high,
                               world.scene.dimensions)
        out['pile_overlap_r'] = max(quality['overlap_pairs_r'], quality['overlap_walls_r'])
        out['fastest'] = quality['fastest']
        out['threshold'] = world.scene.effects.threshold(world.dt)
    return out


def plan(quick: bool) -> list[tuple[str, dict, Any, float, bool]]:
    """Return every run: (scene, mapping, accuracy, dt, check misses)."""
    runs = []
    for name, mapping in scenes(quick).items():
        base = mapping['dt']
        if name in SINGLE_DT:
            # exact (event mode) refuses friction: the pile has no reference run.
            runs.extend((name, mapping, preset, base, True) for preset in PRESET_ORDER[:3])
            continue
        runs.append((name, mapping, 'exact', base, True))
        for preset in PRESET_ORDER[:3]:
            for factor in DT_FACTORS:
                runs.append((name, mapping, preset, base * factor, True))
        runs.append((name, mapping, {'preset': 'fast', 'ordering': 'batched'}, base, True))
    cost = cost_scene(quick)
    for _ in range(COST_REPEATS):
        # Interleaved repeats; the fastest of each is kept (see merge_repeats).
        for preset in PRESET_ORDER[:3]:
            runs.append(('gas_10k_cost', cost, preset, cost['dt'], False))
        runs.append(('gas_10k_cost', cost, {'preset': 'fast', 'ordering': 'batched'},
                     cost['dt'], False))
    return runs


def merge_repeats(results: list[dict]) -> list[dict]:
    """Keep, of runs repeated with the same scene, accuracy and dt, the least CPU time.

    Other work on the machine only ever adds time, so the minimum of
    interleaved repeats is the steadiest estimate of a run's own cost.
    """
    best: dict = {}
    for r in results:
        key = (r['scene'], r['accuracy'], r['dt'])
        if key not in best or r['cpu_s_per_sim_s'] < best[key]['cpu_s_per_sim_s']:
            best[key] = r
    return [r for r in results if best[(r['scene'], r['accuracy'], r['dt'])] is r]


def compare(results: list[dict]) -> None:
    """Add errors against the exact run and cost relative to fast, in place."""
    reference = {r['scene']: r for r in results if r['accuracy'] == 'exact'}
    fast = {r['scene']: r for r in results
            if r['accuracy'] == 'fast' and r['dt'] == scenes_dt(results, r['scene'])}
    for r in results:
        ref = reference.get(r['scene'])
        if ref is not None:
            diff = np.asarray(r['final_position']) - np.asarray(ref['final_position'])
            r['position_error'] = float(np.linalg.norm(diff, axis=1).max())
            scale = ref['momentum_scale'] or 1.0
            r['momentum_error'] = float(np.linalg.norm(np.asarray(r['momentum'])
                                                       - np.asarray(ref['momentum']))) / scale
        else:
            r['position_error'] = None
            scale = r['momentum_scale'] or 1.0
            r['momentum_error'] = None
        base = fast.get(r['scene'])
        # CPU time: less disturbed than wall time by other work on a shared machine.
        r['time_vs_fast'] = r['cpu_s_per_sim_s'] / base['cpu_s_per_sim_s'] if base else None
        if r['scene'] == 'cradle_5':
            r['outcome'] = '(' + ', '.join(f'{v[0]:.3g}' for v in r['final_velocity']) + ')'
        elif r.get('fastest') is not None:
            at_rest = 'at rest' if r['fastest'] < r['threshold'] else 'moving'
            r['outcome'] = (f'{at_rest}: fastest {r["fastest"]:.3g} m/s '
                            f'(threshold {r["threshold"]:.3g})')
        else:
            r['outcome'] = ''


def scenes_dt(results: list[dict], scene: str) -> float:
    """Return the base dt of ``scene`` (the dt of its exact reference run, or first run)."""
    for r in results:
        if r['scene'] == scene and r['accuracy'] == 'exact':
            return r['dt']
    return next(r['dt'] for r in results if r['scene'] == scene)


COLUMNS = [('scene', 'scene'), ('accuracy', 'accuracy'), ('dt', 'dt s'),
           ('particles', 'n'), ('wall_s_per_sim_s', 'wall s / sim s'),
           ('cpu_s_per_sim_s', 'CPU s / sim s'), ('time_vs_fast', 'CPU time vs fast'),
           ('energy_rel_error', 'energy rel err'),
           ('momentum_error', 'momentum err'), ('missed_pairs', 'missed pairs'),
           ('missed_walls', 'wall tunnels'), ('max_penetration', 'max penetration m'),
           ('position_error', 'position err m'), ('collisions', 'impacts'),
           ('apex_error', 'ball apex rel err'), ('pile_overlap_r', 'pile overlap / r'),
           ('outcome', 'cradle / pile rest')]


def _cell(value: Any) -> str:
    """Format one table cell."""
    if value is None:
        return '-'
    if isinstance(value, float):
        if value == 0.0:
            return '0'
        return f'{value:.3g}'
    return str(value)


def write_outputs(results: list[dict], out: Path, header: str) -> None:
    """Write results.md, results.csv, results.json and error_vs_cost.png to ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    keys = [k for k, _ in COLUMNS]
    with open(out / 'results.csv', 'w', newline='', encoding='utf-8') as handle:
        writer = csv.writer(handle)
        writer.writerow(keys)
        for r in results:
            writer.writerow([r.get(k) for k in keys])
    slim = [{k: v for k, v in r.items() if k not in ('final_position', 'final_velocity')}
            for r in results]
    (out / 'results.json').write_text(json.dumps({'header': header, 'runs': slim}, indent=1),
                                      encoding='utf-8')
    lines = [header, '', '| ' + ' | '.join(t for _, t in COLUMNS) + ' |',
             '|' + '---|' * len(COLUMNS)]
    for r in results:
        lines.append('| ' + ' | '.join(_cell(r.get(k)) for k in keys) + ' |')
    (out / 'results.md').write_text('\n'.join(lines) + '\n', encoding='utf-8')
    plot(results, out / 'error_vs_cost.png')


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Return indices of the points no other point beats in both cost and error."""
    order = sorted(range(len(points)), key=lambda k: (points[k][0], points[k][1]))
    front, best = [], math.inf
    for k in order:
        if points[k][1] < best:
            front.append(k)
            best = points[k][1]
    return front


def _plot_value(r: dict, key: str) -> Optional[float]:
    """Return the error a plot row shows for run ``r`` (None: not measured)."""
    if key == 'missed':
        if r['missed_pairs'] is None:
            return None
        return (r['missed_pairs'] or 0) + (r['missed_walls'] or 0)
    if key == 'gravity':
        return r['apex_error'] if r.get('apex_error') is not None else r.get('pile_overlap_r')
    return r.get(key)


def plot(results: list[dict], path: Path) -> None:
    """Log-log error against time cost, one panel per scene and error, Pareto front marked."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    names = [n for n in dict.fromkeys(r['scene'] for r in results) if n != 'gas_10k_cost']
    floor = 1e-17
    errors = [('position_error', 'position error vs exact (m)'),
              ('energy_rel_error', 'relative energy error'),
              ('missed', 'missed collisions (pairs + walls)'),
              ('gravity', 'ball: apex rel. error;\npile: deepest overlap / r')]
    colours = {'fast': 'tab:red', 'balanced': 'tab:blue', 'accurate': 'tab:green',
               'exact': 'black'}
    fig, axes = plt.subplots(len(errors), len(names), figsize=(3.4 * len(names), 12.0),
                             squeeze=False)
    for col, name in enumerate(names):
        runs = [r for r in results if r['scene'] == name]
        for row, (key, label) in enumerate(errors):
            ax = axes[row][col]
            values = [_plot_value(r, key) for r in runs]
            shown = [(r, v) for r, v in zip(runs, values) if v is not None]
            if row == 0:
                ax.set_title(name, fontsize=9)
            if col == 0:
                ax.set_ylabel(label, fontsize=8)
            if not shown:
                # No such measure for this scene (no exact reference, not a gravity scene).
                ax.text(0.5, 0.5, 'n/a', ha='center', va='center', transform=ax.transAxes)
                ax.set_xticks([])
                ax.set_yticks([])
                continue
            runs_shown = [r for r, _ in shown]
            low = 0.5 if key == 'missed' else floor
            pts = [(r['wall_s_per_sim_s'], max(value, low)) for r, value in shown]
            for r, (x, y) in zip(runs_shown, pts):
                preset = r['accuracy'] if r['accuracy'] in colours else 'fast'
                marker = 'o' if r['accuracy'] in colours else 'x'
                ax.scatter(x, y, c=colours[preset], marker=marker, s=22, zorder=3)
                base = scenes_dt(results, name)
                tag = r['accuracy'] if r['accuracy'] in colours else 'batched'
                if r['dt'] != base:
                    tag += f' dt x{r["dt"] / base:g}'
                ax.annotate(tag, (x, y), fontsize=5, xytext=(2, 2), textcoords='offset points')
            front = pareto(pts)
            fx, fy = zip(*[pts[k] for k in front])
            ax.plot(fx, fy, '--', c='grey', lw=1, zorder=2, label='Pareto front')
            ax.set_xscale('log')
            ax.set_yscale('log')
            ax.grid(True, which='major', lw=0.3)
            # A narrow log range labels its minor ticks, which then overlap.
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.yaxis.set_minor_formatter(NullFormatter())
            if row == len(errors) - 1:
                ax.set_xlabel('wall s per simulated s', fontsize=8)
            ax.tick_params(labelsize=6)
    axes[0][0].legend(fontsize=6, loc='best')
    fig.suptitle('Accuracy vs time cost (o: presets, x: fast with batched ordering; '
                 f'errors of 0 drawn at {floor:g}, 0 missed at 0.5)', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this benchmark's options to ``parser``."""
    parser.add_argument('--quick', action='store_true',
                        help='smaller gases, shorter runs (about 5 minutes, most of it the pile)')
    parser.add_argument('--out', default='docs/accuracy',
                        help='directory for results.md/.csv/.json and error_vs_cost.png')
    parser.add_argument('--only', help='comma-separated scene names to run')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark; return the exit code."""
    from tqdm import tqdm

    runs = plan(args.quick)
    if args.only:
        wanted = set(args.only.split(','))
        runs = [r for r in runs if r[0] in wanted]
    load = os.getloadavg()
    results = []
    start = time.perf_counter()
    for name, mapping, accuracy, dt, check in tqdm(runs, unit='run', file=sys.stderr):
        results.append(run_case(name, mapping, accuracy, dt, check))
    results = merge_repeats(results)
    compare(results)
    command = 'python -m collision_node.bench.accuracy_ladder' + (' --quick' if args.quick else '')
    if args.only:
        command += f' --only {args.only}'
    header = (f'Command: `{command}`; {len(runs)} runs in '
              f'{time.perf_counter() - start:.0f} s; load average before: '
              f'{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs; '
              f'{time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}.')
    write_outputs(results, Path(args.out), header)
    print(header)
    print(f'wrote {args.out}/results.md, results.csv, results.json, error_vs_cost.png')
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse the command line and run the benchmark."""
    parser = argparse.ArgumentParser(prog='python -m collision_node.bench.accuracy_ladder',
                                     description=(__doc__ or '').split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
