"""Pile: cost and quality of a pile poured under gravity, per preset (2-D and 3-D).

``python -m collision_node.bench pile`` runs the shipped ``pile`` scene
(240 discs of r = 5 cm poured into a 1.6 m wide box, e = 0.3, mu = 0.5,
dt = 1/120 s) for 480 steps (4 s) under each preset and prints a Markdown
table: wall and CPU ms per step, the settled pile's deepest overlap as a
fraction of the radius (between discs and against the walls), the fastest
disc at the end against the restitution threshold (2 |g| dt, the closing
speed below which contacts are perfectly inelastic: a pile at rest has
every disc below it), the pairs overlapping by more than 1 % and 10 % of r,
the contacts (pairs and wall contacts closer than 1 % of r) and the pile's
top. A run stops after ``--max-seconds`` and says how many steps it did;
``exact`` (event mode) refuses friction, and its row says so.

If pymunk is installed (it is not a dependency: ``pip install pymunk==7.x``
for this benchmark only), the same discs, walls (static segments), e, mu
and dt run in pymunk in the same process as a comparison row. pymunk
combines the coefficients of two shapes by their product, so each shape
gets sqrt(e) and sqrt(mu); its allowed overlap (``collision_slop``) is set
to 1 % of the radius (its default, 0.1, is meant for pixels).

The second table (skip it with ``--no-3d``) pours ``--count3d`` spheres
(default 10,000, r = 5 cm, m = 0.1 kg, e = 0.3, mu = 0.5) into a 2.53 m
square box (``scenarios.pour3d``) at dt = 1/60 s under ``balanced`` (or
the runs of ``--presets3d``: ``fast:4`` is ``fast`` at 4 substeps a step) for
``--steps3d`` steps (default 240: 4 s, the pour and its settling) and
reports ms per step, the real-time factor (simulated over wall seconds,
one process, one core), the deepest overlap at the end over r (between
spheres and against the walls) and the 2-D table's counts and top. If
MuJoCo is installed (``pip install -r bench-requirements.txt``; never a
dependency of the package or the tests), the same spheres, box, mu and dt
run in MuJoCo (PGS solver, its default soft contact, which has no
restitution) as a comparison row, stopped after ``--max-seconds`` like
every run, with the contacts its solver held (the most in a step, and at
the end); without it the row is skipped with a printed note. Peers' rows
start with the peer's name (``bench report`` adds their time ratio).
``--out FILE`` / ``--results-dir [DIR]`` (the dispatcher's) record the
tables as JSON. ``--profile`` adds every run's wall time per stage
(``World.profile``), after each table.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import time
from typing import Optional

import numpy as np

from ...physics.step.kernels import prepare as prepare_kernels
from ...physics.step.reference import end_penetration
from ...physics.model.accuracy import parse_accuracy
from ...physics.model.scene import load_scene
from ...physics.model.validation import SceneError
from ...physics.step.world import World
from ...physics.stages.detection.broadphase import candidate_pairs
from ...scenarios import pour3d

PRESETS = ('fast', 'balanced', 'accurate', 'exact')
PYMUNK_MISSING = 'pymunk not installed (pip install pymunk==7.x): comparison row skipped'
MUJOCO_MISSING = ('mujoco not installed (pip install -r bench-requirements.txt): '
                  'comparison row skipped')
# pymunk's allowed overlap as a fraction of the disc radius.
PYMUNK_SLOP_RADII = 0.01
# Overlaps counted, as fractions of the radius; and the gap below which two
# particles (or a particle and a wall) count as a contact, over the radius.
OVERLAP_COUNTS_RADII = (0.01, 0.1)
CONTACT_GAP_RADII = 0.01
# MuJoCo's arena for the 3-D pour (its constraint rows for 10^4 spheres).
MUJOCO_MEMORY = '4G'


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
    """Return the deepest overlap over the radius, overlap and contact counts, the top, speed.

    ``pairs_over_*`` count the pairs overlapping by more than that fraction
    of the (median) radius; ``contacts`` the pairs and particle-wall pairs
    closer than CONTACT_GAP_RADII of it; ``top`` the highest point (max of
    y + r), m.
    """
    from ...physics.model.state import ParticleState
    n = position.shape[0]
    padded = np.zeros((n, 3))
    padded[:, :dimensions] = position[:, :dimensions]
    state = ParticleState(ids=np.arange(n), position=padded, velocity=np.zeros((n, 3)),
                          radius=radius, inv_mass=np.ones(n))
    pairs = end_penetration(state)
    walls = wall_penetration(padded, radius, low, high, dimensions)
    scale = float(np.median(radius))
    i, j = candidate_pairs(padded, radius + 0.5 * CONTACT_GAP_RADII * scale)
    gap = np.linalg.norm(padded[i] - padded[j], axis=1) - (radius[i] + radius[j])
    x, r = padded[:, :dimensions], radius[:, None]
    wall_gap = np.concatenate([(x - r - low[:dimensions]).ravel(),
                               (high[:dimensions] - (x + r)).ravel()])
    out = {'overlap_pairs_r': pairs / scale, 'overlap_walls_r': walls / scale,
           'fastest': float(np.max(np.linalg.norm(velocity, axis=1))),
           'contacts': int(np.count_nonzero(gap < CONTACT_GAP_RADII * scale)
                           + np.count_nonzero(wall_gap < CONTACT_GAP_RADII * scale)),
           'top': float(np.max(padded[:, 1] + radius))}
    for fraction in OVERLAP_COUNTS_RADII:
        out[f'pairs_over_{fraction:g}r'] = int(np.count_nonzero(-gap > fraction * scale))
    return out


def timed_steps(world: World, steps: int, max_seconds: float) -> tuple[int, float, float]:
    """Step ``world`` up to ``steps`` times or for ``max_seconds``; return (steps, s, CPU s)."""
    done, wall, cpu = 0, 0.0, 0.0
    while done < steps and wall < max_seconds:
        start, cpu_start = time.perf_counter(), time.process_time()
        world.step()
        wall += time.perf_counter() - start
        cpu += time.process_time() - cpu_start
        done += 1
    return done, wall, cpu


def run_preset(scene, preset: str, steps: int, max_seconds: float) -> dict:
    """Step ``scene`` under ``preset``; stop early after ``max_seconds`` of wall time."""
    try:
        world = World(scene.with_accuracy(_settings(preset)))
    except SceneError as error:
        # exact (event mode) refuses friction: say so in the table.
        return {'label': preset, 'skipped': str(error).rsplit(': ', 1)[-1]}
    done, wall, cpu = timed_steps(world, steps, max_seconds)
    s, walls = world.state, scene.effects.walls
    quality = pile_quality(s.position, s.velocity, s.radius, walls.low, walls.high,
                           scene.dimensions)
    return dict(quality, label=preset, steps=done, ms=1e3 * wall / done, cpu_ms=1e3 * cpu / done,
                profile=world.profile())


def _settings(preset: str):
    """Return the accuracy settings of a preset by name."""
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


def pile3d_run(text: str) -> tuple[str, int]:
    """Parse a 3-D pile run, ``PRESET`` or ``PRESET:SUBSTEPS``; return (preset, substeps).

    ``fast:4`` is ``fast``'s settings at 4 substeps a step (0: the preset's own);
    the substeps are checked by the scene's accuracy validator.
    """
    name, _, count = text.partition(':')
    if name not in PRESETS[:3]:
        raise argparse.ArgumentTypeError(
            f'{text[:40]!r}: the preset must be one of {", ".join(PRESETS[:3])}')
    if not count:
        return name, 0
    try:
        settings = parse_accuracy({'preset': name, 'substeps': int(count) if count.isdigit()
                                   else count}, 'accuracy')
    except SceneError as error:
        raise argparse.ArgumentTypeError(f'{text[:40]!r}: {error}') from None
    return name, settings.substeps


def _pile3d_option(text: str) -> str:
    """Check a ``--presets3d`` item (``pile3d_run``) and keep it as written, for the record."""
    pile3d_run(text)
    return text


def pile3d_label(preset: str, substeps: int = 0) -> str:
    """Return a 3-D pile run's row label: the preset, and its substeps if given."""
    return preset if not substeps else f'{preset}, {substeps} substeps'


def run_pile3d(count: int, steps: int, preset: str, max_seconds: float = math.inf,
               substeps: int = 0) -> dict:
    """Pour the 3-D pile under ``preset`` (at ``substeps`` a step, 0: the preset's own).

    Returns the real-time factor and quality.
    """
    accuracy = {'preset': preset, 'substeps': substeps} if substeps else preset
    scene = pour3d(count, accuracy=accuracy)
    world = World(scene)
    done, wall, cpu = timed_steps(world, steps, max_seconds)
    s, walls = world.state, scene.effects.walls
    quality = pile_quality(s.position, s.velocity, s.radius, walls.low, walls.high, 3)
    return dict(quality, label=pile3d_label(preset, substeps), steps=done, ms=1e3 * wall / done,
                cpu_ms=1e3 * cpu / done, real_time=done * scene.dt / wall,
                cpu_real_time=done * scene.dt / cpu, profile=world.profile())


def mujoco_model(scene) -> str:
    """Return MJCF for ``scene``'s spheres as free bodies in its box of walls (planes)."""
    s, walls = scene.initial, scene.effects.walls
    mu = scene.effects.friction or 0.0
    g = ' '.join(f'{c:.17g}' for c in scene.effects.gravity)
    planes = []
    for axis in range(3):
        for bound, sign in ((walls.low[axis], 1.0), (walls.high[axis], -1.0)):
            if math.isfinite(bound):
                normal, pos = [0.0] * 3, [0.0] * 3
                normal[axis], pos[axis] = sign, float(bound)
                planes.append(f'<geom type="plane" size="0 0 1" pos="{_xyz(pos)}" '
                              f'zaxis="{_xyz(normal)}" friction="{mu:.17g} 0 0"/>')
    bodies = [f'<body pos="{_xyz(s.position[k])}"><freejoint/><geom type="sphere" '
              f'size="{float(s.radius[k]):.17g}" mass="{1.0 / float(s.inv_mass[k]):.17g}" '
              f'friction="{mu:.17g} 0 0"/></body>' for k in range(len(s))]
    return (f'<mujoco><size memory="{MUJOCO_MEMORY}"/>'
            f'<option timestep="{scene.dt:.17g}" gravity="{g}" solver="PGS"/>'
            f'<worldbody>{"".join(planes)}{"".join(bodies)}</worldbody></mujoco>')


def _xyz(vector) -> str:
    """Return three numbers as MJCF writes them."""
    return ' '.join(f'{float(c):.17g}' for c in vector[:3])


def run_mujoco(count: int, steps: int, max_seconds: float) -> Optional[dict]:
    """Run the 3-D pour in MuJoCo; return the row, or None if mujoco is missing."""
    try:
        import mujoco
    except ImportError:
        return None
    scene = pour3d(count)
    model = mujoco.MjModel.from_xml_string(mujoco_model(scene))
    data = mujoco.MjData(model)
    n = len(scene.initial)
    # Each free joint: 3 translational then 3 rotational velocities.
    qvel = data.qvel.reshape(n, 6)
    qvel[:, :3] = scene.initial.velocity
    done, wall, cpu, contacts = 0, 0.0, 0.0, 0
    while done < steps and wall < max_seconds:
        start, cpu_start = time.perf_counter(), time.process_time()
        mujoco.mj_step(model, data)
        wall += time.perf_counter() - start
        cpu += time.process_time() - cpu_start
        contacts = max(contacts, int(data.ncon))
        done += 1
    position = data.qpos.reshape(n, 7)[:, :3].copy()
    velocity = data.qvel.reshape(n, 6)[:, :3].copy()
    walls = scene.effects.walls
    quality = pile_quality(position, velocity, scene.initial.radius, walls.low, walls.high, 3)
    return dict(quality, label=f'MuJoCo {mujoco.__version__} (PGS)', steps=done,
                ms=1e3 * wall / done, cpu_ms=1e3 * cpu / done,
                real_time=done * scene.dt / wall, cpu_real_time=done * scene.dt / cpu,
                solver_contacts_max=contacts, solver_contacts_end=int(data.ncon))


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
    parser.add_argument('--steps3d', type=int, default=240,
                        help='steps of the 3-D pile at dt = 1/60 (default 240: 4 s)')
    parser.add_argument('--presets3d', nargs='+', default=['balanced'], type=_pile3d_option,
                        metavar='PRESET[:SUBSTEPS]',
                        help='runs of the 3-D pile: a preset (fast, balanced, accurate), '
                             'optionally at other substeps a step (fast:4); default balanced')
    parser.add_argument('--no-mujoco', action='store_true', help='skip the MuJoCo row')
    parser.add_argument('--profile', action='store_true',
                        help='after each table, the wall time per stage of every run '
                             '(the first step apart)')


def _load_line() -> str:
    """Describe the machine and its load."""
    load = os.getloadavg()
    machine = platform.processor() or platform.machine()
    return (f'{machine}, {os.cpu_count()} cores, load average '
            f'{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}')


# The counts and the top of a pile (``pile_quality``), the last columns of both tables.
COUNT_COLUMNS = ('pairs over 1 % r', 'pairs over 10 % r', 'contacts (gap < 1 % r)', 'top m')


def count_cells(row: dict) -> list[str]:
    """Return the cells of COUNT_COLUMNS for a row of ``pile_quality``."""
    return [f'{row["pairs_over_0.01r"]}', f'{row["pairs_over_0.1r"]}', f'{row["contacts"]}',
            f'{row["top"]:.3f}']


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
    columns = ['run', 'steps', 'ms per step', 'CPU ms per step', 'deepest overlap / r (discs)',
               'deepest overlap / r (walls)', 'fastest disc m/s',
               f'below threshold {threshold:.3g} m/s', *COUNT_COLUMNS]
    print('| ' + ' | '.join(columns) + ' |')
    print('|---|---:|---:|---:|---:|---:|---:|---|' + '---:|' * len(COUNT_COLUMNS))
    for row in rows:
        if 'skipped' in row:
            cells = [f'not run: {row["skipped"]}'] + [''] * (len(columns) - 2)
        else:
            cells = [f'{row["steps"]}', f'{row["ms"]:.3g}', f'{row["cpu_ms"]:.3g}',
                     f'{row["overlap_pairs_r"]:.3g}', f'{row["overlap_walls_r"]:.3g}',
                     f'{row["fastest"]:.3g}', 'yes' if row['fastest'] < threshold else 'no',
                     *count_cells(row)]
        print(f'| {row["label"]} | ' + ' | '.join(cells) + ' |')
    if args.profile:
        print_profiles('2-D pile', rows)
    if not args.no_3d:
        run_3d(args)
    return 0


def run_3d(args: argparse.Namespace) -> list:
    """Pour the 3-D pile under each preset (and MuJoCo); print its table, return the rows."""
    print()
    scene = pour3d(args.count3d)
    side = float(scene.effects.walls.high[0])
    print(f'3-D pile: {args.count3d} spheres (r = 5 cm, m = 0.1 kg, e = 0.3, mu = 0.5) poured '
          f'into a {side:.3g} m square box, dt = 1/60 s, {args.steps3d} steps; {_load_line()}')
    runs = [pile3d_run(text) for text in args.presets3d]
    rows3d = [run_pile3d(args.count3d, args.steps3d, preset, args.max_seconds, substeps)
              for preset, substeps in runs]
    if not args.no_mujoco:
        reference = run_mujoco(args.count3d, args.steps3d, args.max_seconds)
        if reference is None:
            print(MUJOCO_MISSING)
        else:
            rows3d.append(reference)
    print()
    columns = ['run', 'steps', 'ms per step', 'CPU ms per step', 'real-time factor',
               'real-time factor (CPU)', 'deepest overlap / r (spheres)',
               'deepest overlap / r (walls)', 'fastest sphere m/s', *COUNT_COLUMNS,
               'solver contacts (most in a step)', 'solver contacts (at the end)']
    print('| ' + ' | '.join(columns) + ' |')
    print('|---|' + '---:|' * (len(columns) - 1))
    for row in rows3d:
        cells = [f'{row["steps"]}', f'{row["ms"]:.4g}', f'{row["cpu_ms"]:.4g}',
                 f'{row["real_time"]:.3g}', f'{row["cpu_real_time"]:.3g}',
                 f'{row["overlap_pairs_r"]:.3g}', f'{row["overlap_walls_r"]:.3g}',
                 f'{row["fastest"]:.3g}', *count_cells(row),
                 f'{row.get("solver_contacts_max", "-")}',
                 f'{row.get("solver_contacts_end", "-")}']
        print(f'| {row["label"]} | ' + ' | '.join(cells) + ' |')
    if args.profile:
        print_profiles('3-D pile', rows3d)
    return rows3d


def print_profiles(title: str, rows: list) -> None:
    """Print the per-stage profile of every row that has one (pymunk's has none)."""
    for row in rows:
        if 'profile' in row:
            print()
            print(f'{title}, {row["label"]}, per stage:')
            print()
            print(row['profile'].table())
