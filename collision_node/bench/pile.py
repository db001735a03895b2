"""Pile: cost and quality of a pile poured under gravity, per preset (2-D and 3-D).

``python -m collision_node.bench pile`` runs the shipped ``pile`` scene
(240 discs of r = 5 cm poured into a 1.6 m wide box, e = 0.3, mu = 0.5,
dt = 1/120 s) for 480 steps (4 s) under each preset and prints a Markdown
table: wall and CPU ms per step, the settled pile's deepest overlap as a
fraction of the radius (between discs and against the walls), and the
fastest disc at the end against the restitution threshold (2 |g| dt, the
closing speed below which contacts are perfectly inelastic: a pile at rest
has every disc below it). A run stops after ``--max-seconds`` and says how
many steps it did; ``exact`` (event mode) refuses friction, and its row
says so.

If pymunk is installed (it is not a dependency: ``pip install pymunk==7.x``
for this benchmark only), the same discs, walls (static segments), e, mu
and dt run in pymunk in the same process as a comparison row. pymunk
combines the coefficients of two shapes by their product, so each shape
gets sqrt(e) and sqrt(mu); its allowed overlap (``collision_slop``) is set
to 1 % of the radius (its default, 0.1, is meant for pixels).

The second table (skip it with ``--no-3d``) pours ``--count3d`` spheres
(default 10,000, r = 5 cm, same materials) into a box at dt = 1/60 s under
``balanced`` and reports the real-time factor (simulated over wall
seconds, one process, one core) over ``--steps3d`` steps (default 60:
1 s; the pour takes about 2 s to land, so longer runs include the settled
pile). ``--profile`` adds every run's wall time per stage (``World.profile``).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from typing import Optional

import numpy as np

from ..physics.step.kernels import prepare as prepare_kernels
from ..physics.step.reference import end_penetration
from ..physics.model.scene import load_scene, parse_scene
from ..physics.model.validation import SceneError
from ..physics.step.world import World

PRESETS = ('fast', 'balanced', 'accurate', 'exact')
PYMUNK_MISSING = 'pymunk not installed (pip install pymunk==7.x): comparison row skipped'
# pymunk's allowed overlap as a fraction of the disc radius.
PYMUNK_SLOP_RADII = 0.01


def wall_penetration(position: np.ndarray, radius: np.ndarray, low: np.ndarray,
                     high: np.ndarray, dimensions: int) -> float:
    """Return the deepest overlap of a particle with an axis-aligned wall, m (0 if none)."""
    x, r = position[:, :dimensions], radius[:, None]
    inside_low = x - r - low[:dimensions]
    inside_high = high[:dimensions] - (x + r)
    # Infinite planes (absent walls) give +inf gaps: never an overlap.
    deepest = -min(float(np.min(inside_low)), float(np.min(inside_high)))
    return max(0.0, deepest)


def pile_quality(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                 low: np.ndarray, high: np.ndarray, dimensions: int) -> dict:
    """Return the deepest overlap over the radius and the fastest particle's speed."""
    from ..physics.model.state import ParticleState
    n = position.shape[0]
    padded = np.zeros((n, 3))
    padded[:, :dimensions] = position[:, :dimensions]
    state = ParticleState(ids=np.arange(n), position=padded, velocity=np.zeros((n, 3)),
                          radius=radius, inv_mass=np.ones(n))
    pairs = end_penetration(state)
    walls = wall_penetration(padded, radius, low, high, dimensions)
    scale = float(np.median(radius))
    return {'overlap_pairs_r': pairs / scale, 'overlap_walls_r': walls / scale,
            'fastest': float(np.max(np.linalg.norm(velocity, axis=1)))}


def run_preset(scene, preset: str, steps: int, max_seconds: float) -> dict:
    """Step ``scene`` under ``preset``; stop early after ``max_seconds`` of wall time."""
    try:
        world = World(scene.with_accuracy(_settings(preset)))
    except SceneError as error:
        # exact (event mode) refuses friction: say so in the table.
        return {'label': preset, 'skipped': str(error).rsplit(': ', 1)[-1]}
    done, wall, cpu = 0, 0.0, 0.0
    while done < steps and wall < max_seconds:
        start, cpu_start = time.perf_counter(), time.process_time()
        world.step()
        wall += time.perf_counter() - start
        cpu += time.process_time() - cpu_start
        done += 1
    s, walls = world.state, scene.effects.walls
    quality = pile_quality(s.position, s.velocity, s.radius, walls.low, walls.high,
                           scene.dimensions)
    return dict(quality, label=preset, steps=done, ms=1e3 * wall / done, cpu_ms=1e3 * cpu / done,
                profile=world.profile())


def _settings(preset: str):
    """Return the accuracy settings of a preset by name."""
    from ..physics.model.accuracy import parse_accuracy
    return parse_accuracy(preset, 'bench pile: accuracy')


def run_pymunk(scene, steps: int) -> Optional[dict]:
    """Run the same discs in pymunk; return the row, or None if pymunk is missing."""
    try:
        import pymunk
    except ImportError:
        return None
    effects, s = scene.effects, scene.initial
    e_root = math.sqrt(effects.particle_restitution)
    mu_root = math.sqrt(effects.friction or 0.0)
    space = pymunk.Space()
    space.gravity = tuple(float(g) for g in effects.gravity[:2])
    space.collision_slop = PYMUNK_SLOP_RADII * float(np.median(s.radius))
    for k in range(len(s)):
        mass, r = 1.0 / float(s.inv_mass[k]), float(s.radius[k])
        # Solid spheres, as the friction model of this package (I = 2/5 m r^2).
        body = pymunk.Body(mass, 0.4 * mass * r * r)
        body.position = (float(s.position[k, 0]), float(s.position[k, 1]))
        body.velocity = (float(s.velocity[k, 0]), float(s.velocity[k, 1]))
        shape = pymunk.Circle(body, r)
        shape.elasticity, shape.friction = e_root, mu_root
        space.add(body, shape)
    walls = effects.walls
    (x0, y0), (x1, y1) = walls.low[:2], walls.high[:2]
    thick = 0.5
    # Thick static segments whose inner faces are the walls' planes.
    for a, b in (((x0 - thick, y0 - thick), (x1 + thick, y0 - thick)),
                 ((x0 - thick, y0 - thick), (x0 - thick, y1 + thick)),
                 ((x1 + thick, y0 - thick), (x1 + thick, y1 + thick)),
                 ((x0 - thick, y1 + thick), (x1 + thick, y1 + thick))):
        segment = pymunk.Segment(space.static_body, a, b, thick)
        segment.elasticity = walls.restitution / e_root if e_root else 0.0
        segment.friction = mu_root
        space.add(segment)
    start, cpu_start = time.perf_counter(), time.process_time()
    for _ in range(steps):
        space.step(scene.dt)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    bodies = space.bodies
    position = np.array([[b.position.x, b.position.y] for b in bodies])
    velocity = np.array([[b.velocity.x, b.velocity.y] for b in bodies])
    radius = np.array([next(iter(b.shapes)).radius for b in bodies])
    quality = pile_quality(position, velocity, radius, walls.low, walls.high, 2)
    return dict(quality, label=f'pymunk {pymunk.version}', steps=steps,
                ms=1e3 * wall / steps, cpu_ms=1e3 * cpu / steps)


def pile3d_scene(count: int, radius: float = 0.05) -> dict:
    """Return a 3-D pour of ``count`` spheres into a box about ten layers deep."""
    side = math.sqrt(count / 10.0) * 2.0 * radius          # ~10 layers when settled
    spacing = 2.0 * radius * 1.05
    layers = math.ceil(count / (math.floor(side / spacing) ** 2)) + 1
    top = 0.5 + layers * spacing
    return {
        'name': f'pile3d_{count}', 'dimensions': 3, 'dt': 1.0 / 60.0,
        'effects': {'gravity': [0.0, -9.81, 0.0], 'restitution': 0.3, 'friction': 0.5,
                    'walls': {'min': [0.0, 0.0, 0.0], 'max': [side, top + 1.0, side],
                              'restitution': 0.3}},
        'generate': [{'kind': 'gas', 'count': count, 'radius': radius, 'mass': 0.1,
                      'speed': 1.0, 'seed': 5,
                      'region': {'min': [0.0, 0.5, 0.0], 'max': [side, top, side]}}],
    }


def run_pile3d(count: int, steps: int, preset: str) -> dict:
    """Pour the 3-D pile under ``preset``; return the real-time factor and quality."""
    scene = parse_scene(dict(pile3d_scene(count), accuracy=preset), 'bench pile3d')
    world = World(scene)
    start, cpu_start = time.perf_counter(), time.process_time()
    world.step(steps)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    s, walls = world.state, scene.effects.walls
    quality = pile_quality(s.position, s.velocity, s.radius, walls.low, walls.high, 3)
    return dict(quality, label=preset, steps=steps, ms=1e3 * wall / steps,
                cpu_ms=1e3 * cpu / steps, real_time=steps * scene.dt / wall,
                cpu_real_time=steps * scene.dt / cpu, profile=world.profile())


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare the subcommand's options."""
    parser.add_argument('--steps', type=int, default=480, help='steps of the 2-D pile (480)')
    parser.add_argument('--presets', nargs='+', default=list(PRESETS), choices=PRESETS,
                        help='presets of the 2-D pile (default: all four)')
    parser.add_argument('--max-seconds', type=float, default=300.0,
                        help='wall-time budget per preset run; a run stops early past it')
    parser.add_argument('--no-pymunk', action='store_true', help='skip the pymunk row')
    parser.add_argument('--no-3d', action='store_true', help='skip the 3-D pile')
    parser.add_argument('--count3d', type=int, default=10_000, help='spheres of the 3-D pile')
    parser.add_argument('--steps3d', type=int, default=60,
                        help='steps of the 3-D pile at dt = 1/60 (default 60: 1 s)')
    parser.add_argument('--presets3d', nargs='+', default=['balanced'], choices=PRESETS[:3],
                        help='presets of the 3-D pile (default: balanced)')
    parser.add_argument('--profile', action='store_true',
                        help='after each table, the wall time per stage of every run '
                             '(the first step apart)')


def _load_line() -> str:
    """Describe the machine and its load."""
    load = os.getloadavg()
    machine = platform.processor() or platform.machine()
    return (f'{machine}, {os.cpu_count()} cores, load average '
            f'{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the Markdown tables."""
    if args.steps < 1 or args.steps3d < 1 or args.count3d < 2:
        print('bench pile: --steps and --steps3d must be >= 1, --count3d >= 2')
        return 2
    # Compile (first run) or load the contact kernels outside the timed runs.
    took = prepare_kernels()
    scene = load_scene('pile')
    threshold = scene.effects.threshold(scene.dt)
    print(f'2-D pile (scenes/pile.yaml): {len(scene.initial)} discs, dt = {scene.dt:.6g} s, '
          f'{args.steps} steps; {_load_line()}; contact kernels ready in {took:.2f} s')
    rows = [run_preset(scene, preset, args.steps, args.max_seconds) for preset in args.presets]
    if not args.no_pymunk:
        reference = run_pymunk(scene, args.steps)
        if reference is None:
            print(PYMUNK_MISSING)
        else:
            rows.append(reference)
    print()
    print(f'| run | steps | ms per step | CPU ms per step | deepest overlap / r (discs) '
          f'| deepest overlap / r (walls) | fastest disc m/s | below threshold '
          f'{threshold:.3g} m/s |')
    print('|---|---:|---:|---:|---:|---:|---:|---|')
    for row in rows:
        if 'skipped' in row:
            print(f'| {row["label"]} | not run: {row["skipped"]} | | | | | | |')
            continue
        print(f'| {row["label"]} | {row["steps"]} | {row["ms"]:.3g} | {row["cpu_ms"]:.3g} '
              f'| {row["overlap_pairs_r"]:.3g} | {row["overlap_walls_r"]:.3g} '
              f'| {row["fastest"]:.3g} | {"yes" if row["fastest"] < threshold else "no"} |')
    if args.profile:
        print_profiles('2-D pile', rows)
    if args.no_3d:
        return 0
    print()
    print(f'3-D pile: {args.count3d} spheres (r = 5 cm, e = 0.3, mu = 0.5) poured into a box, '
          f'dt = 1/60 s, {args.steps3d} steps; {_load_line()}')
    print()
    print('| preset | steps | ms per step | CPU ms per step | real-time factor '
          '| real-time factor (CPU) | deepest overlap / r | fastest sphere m/s |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|')
    rows3d = []
    for preset in args.presets3d:
        row = run_pile3d(args.count3d, args.steps3d, preset)
        print(f'| {preset} | {row["steps"]} | {row["ms"]:.4g} | {row["cpu_ms"]:.4g} '
              f'| {row["real_time"]:.3g} | {row["cpu_real_time"]:.3g} '
              f'| {max(row["overlap_pairs_r"], row["overlap_walls_r"]):.3g} '
              f'| {row["fastest"]:.3g} |')
        rows3d.append(row)
    if args.profile:
        print_profiles('3-D pile', rows3d)
    return 0


def print_profiles(title: str, rows: list) -> None:
    """Print the per-stage profile of every row that has one (pymunk's has none)."""
    for row in rows:
        if 'profile' in row:
            print()
            print(f'{title}, {row["label"]}, per stage:')
            print()
            print(row['profile'].table())
