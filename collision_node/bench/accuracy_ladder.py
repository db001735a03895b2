"""Accuracy benchmark: what each preset buys and what it costs in time.

``python -m collision_node.bench accuracy [--quick] [--out DIR]`` runs a
fixed set of scenes under every preset and a dt sweep, and the cost-growth
runs (``cost_growth``), with a progress bar, and writes ``results.md``,
``results.csv``, ``results.json`` and three figures (``accuracy_figures``):
``error_vs_cost.png``, ``where_time_goes.png`` and ``cost_growth.png`` to
``DIR`` (default ``docs/accuracy``), and the decision table into
``docs/accuracy.md`` (``--doc``). ``--from-results`` redraws the figures
and the table from an existing ``results.json`` without running anything.

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
    """Run one scene under one accuracy and dt; return its measurements and step profile."""
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
    profile = world.profile()
    return {
        'scene': name,
        'accuracy': accuracy if isinstance(accuracy, str) else json.dumps(accuracy),
        'dt': dt,
        # The scene's own dt (the dt sweep multiplies it).
        'scene_dt': mapping['dt'],
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
        # Steady wall ms per step of each stage (the first step apart, World.profile).
        'profile': {'ms_per_step': profile.ms_per_step, 'first_step_ms': profile.first_step_ms,
                    'stages': [[stage.name, stage.ms_per_step] for stage in profile.stages]},
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
        from .contact.pile import pile_quality
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


def write_outputs(results: list[dict], growth: list[dict], out: Path, header: str,
                  doc: Optional[Path]) -> None:
    """Write results.md, .csv, .json and the three figures to ``out``; the table to ``doc``."""
    out.mkdir(parents=True, exist_ok=True)
    keys = [k for k, _ in COLUMNS]
    with open(out / 'results.csv', 'w', newline='', encoding='utf-8') as handle:
        writer = csv.writer(handle)
        writer.writerow(keys)
        for r in results:
            writer.writerow([r.get(k) for k in keys])
    slim = [{k: v for k, v in r.items() if k not in ('final_position', 'final_velocity')}
            for r in results]
    (out / 'results.json').write_text(
        json.dumps({'header': header, 'runs': slim, 'growth': growth}, indent=1),
        encoding='utf-8')
    lines = [header, '', '| ' + ' | '.join(t for _, t in COLUMNS) + ' |',
             '|' + '---|' * len(COLUMNS)]
    for r in results:
        lines.append('| ' + ' | '.join(_cell(r.get(k)) for k in keys) + ' |')
    lines += ['', 'Cost growth (ns per particle-step, steady steps):', '',
              '| scene | preset | N | ms per step | ns per particle-step |',
              '|---|---|---:|---:|---:|']
    for g in growth:
        if 'skipped' in g:
            lines.append(f'| {g["scene"]} | {g["preset"]} | {g["count"]} | skipped: '
                         f'{g["skipped"]} | - |')
        else:
            lines.append(f'| {g["scene"]} | {g["preset"]} | {g["count"]} | '
                         f'{g["ms_per_step"]:.4g} | {g["ns_per_particle_step"]:.4g} |')
    (out / 'results.md').write_text('\n'.join(lines) + '\n', encoding='utf-8')
    draw(slim, growth, out, header, doc)


def draw(results: list[dict], growth: list[dict], out: Path, header: str,
         doc: Optional[Path]) -> None:
    """Draw the three figures into ``out`` and write the decision table into ``doc``."""
    import matplotlib.pyplot as plt

    from . import accuracy_figures as figures
    from .cost_growth import measured
    made = [('error_vs_cost.png', figures.error_vs_cost_figure(results))]
    if any(r.get('profile') for r in results):
        made.append(('where_time_goes.png', figures.where_time_goes_figure(results)))
    if measured(growth):
        made.append(('cost_growth.png', figures.cost_growth_figure(measured(growth))))
    for name, fig in made:
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
    if doc is not None:
        table = f'{header}\n\n{figures.decision_table(results)}'
        text = doc.read_text(encoding='utf-8')
        doc.write_text(figures.replace_table(text, table), encoding='utf-8')


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add this benchmark's options to ``parser``."""
    parser.add_argument('--quick', action='store_true',
                        help='smaller gases, shorter runs (about 5 minutes, most of it the pile)')
    parser.add_argument('--out', default='docs/accuracy',
                        help='directory for results.md/.csv/.json and the three figures')
    parser.add_argument('--doc', default='docs/accuracy.md',
                        help='page whose decision table is rewritten (between its markers); '
                             '"" leaves every page alone')
    parser.add_argument('--only', help='comma-separated scene names to run')
    parser.add_argument('--growth-counts', type=int, nargs='+', metavar='N',
                        help='particle counts of the cost-growth runs (default 1,000 to '
                             '1,000,000; --quick: 200 and 1,000); 0 skips them')
    parser.add_argument('--from-results', action='store_true',
                        help='run nothing: redraw the figures and the table from '
                             'OUT/results.json')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark (or redraw from its results); return the exit code."""
    from tqdm import tqdm

    from .cost_growth import COUNTS, QUICK_COUNTS, run_growth
    out = Path(args.out)
    doc = Path(args.doc) if args.doc else None
    if args.from_results:
        saved = json.loads((out / 'results.json').read_text(encoding='utf-8'))
        draw(saved['runs'], saved.get('growth', []), out, saved['header'], doc)
        print(f'redrew the figures in {out} from {out / "results.json"}'
              + (f' and the decision table in {doc}' if doc else ''))
        return 0
    runs = plan(args.quick)
    if args.only:
        wanted = set(args.only.split(','))
        runs = [r for r in runs if r[0] in wanted]
    counts = args.growth_counts or (QUICK_COUNTS if args.quick else COUNTS)
    counts = [n for n in counts if n > 0]
    load = os.getloadavg()
    results = []
    start = time.perf_counter()
    bar = tqdm(runs, unit='run', file=sys.stderr)
    for name, mapping, accuracy, dt, check in bar:
        results.append(run_case(name, mapping, accuracy, dt, check))
    results = merge_repeats(results)
    compare(results)
    growth = run_growth(counts, progress=lambda text: bar.write(text, file=sys.stderr))
    command = 'python -m collision_node.bench accuracy' + (' --quick' if args.quick else '')
    if args.only:
        command += f' --only {args.only}'
    if args.growth_counts:
        command += ' --growth-counts ' + ' '.join(map(str, args.growth_counts))
    header = (f'Command: `{command}`; {len(runs)} runs and {len(growth)} cost-growth runs in '
              f'{time.perf_counter() - start:.0f} s; load average before: '
              f'{load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs; '
              f'{time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}.')
    write_outputs(results, growth, out, header, doc)
    print(header)
    print(f'wrote {out}/results.md, results.csv, results.json, error_vs_cost.png, '
          'where_time_goes.png, cost_growth.png'
          + (f' and the decision table in {doc}' if doc else ''))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Parse the command line and run the benchmark."""
    parser = argparse.ArgumentParser(prog='python -m collision_node.bench accuracy',
                                     description=(__doc__ or '').split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
