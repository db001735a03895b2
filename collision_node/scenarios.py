"""Shared scenarios: the scenes both the tests and the benchmarks build.

The first functions return the content of a scene file as a mapping (or
the particle list of one), so a caller adds what it varies (``accuracy``,
``dt``) and hands it to ``parse_scene``; the stack scenarios further down
return a validated :class:`Scene` built with the typed builder
(``physics/model/builder.py``), their accuracy an argument. The same
arguments always give the same particles in the same order. Positions are
computed so that touching particles touch exactly in binary where the
docstring says so.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from .physics.model.accuracy import parse_accuracy
from .physics.model.builder import AccuracyLike, Gas, Particle, accuracy_mapping, build_scene
from .physics.model.scene import Scene, load_scene, parse_spawn_data
from .physics.step.world import World

# m/s^2: the gravity of the scenarios under gravity (pointing along -y).
G = 9.81
# s: the step of the resting scenarios (240 Hz).
RESTING_DT = 1.0 / 240.0


def ball(position: Sequence[float], radius: float, mass: float,
         velocity: Optional[Sequence[float]] = None) -> dict:
    """Return one ``particles`` entry (at rest when ``velocity`` is None)."""
    entry: dict[str, Any] = {'position': list(map(float, position)), 'radius': radius,
                             'mass': mass}
    if velocity is not None:
        entry['velocity'] = list(map(float, velocity))
    return entry


def gas(count: int, radius: float, speed: float, *, mass: float = 1.0, seed: int = 0,
        low: float = 0.0, high: float = 1.0, dimensions: int = 3, walls: bool = True,
        wall_restitution: Optional[float] = None, effects: Optional[Mapping] = None,
        **scene: Any) -> dict:
    """Return ``count`` particles at ``speed`` in random directions in the box [low, high]^d.

    ``walls`` closes the box (with ``wall_restitution`` if given); ``effects``
    adds effects (None and no walls: no ``effects`` key at all); ``scene``
    adds top-level keys (``dt``, ``duration``, ``name``, ``accuracy``).
    """
    box = {'min': [low] * dimensions, 'max': [high] * dimensions}
    declared = None if effects is None else dict(effects)
    if walls:
        declared = dict(declared or {}, walls=dict(box))
        if wall_restitution is not None:
            declared['walls']['restitution'] = wall_restitution
    out = dict(dimensions=dimensions, **scene)
    if declared is not None:
        out['effects'] = declared
    out['generate'] = [{'kind': 'gas', 'count': count, 'radius': radius, 'mass': mass,
                        'speed': speed, 'seed': seed, 'region': box}]
    return out


def cradle(count: int, radius: float, mass: float, speed: float, striker_x: float, *,
           first: int = 0, dimensions: int = 3) -> list:
    """Return Newton's cradle along x: a striker, then ``count - 1`` touching balls at rest.

    The striker sits at ``striker_x`` moving at ``speed`` along +x; the
    resting balls' centres are 2 r (first + k), k = 0 .. count - 2, so
    they touch exactly when 2 r is a power of two times an integer.
    """
    rest = [0.0] * (dimensions - 1)
    balls = [ball([striker_x, *rest], radius, mass, [speed, *rest])]
    balls += [ball([2 * radius * (first + k), *rest], radius, mass) for k in range(count - 1)]
    return balls


def column(count: int, radius: float = 0.05) -> list:
    """Return ``count`` 1 kg discs stacked on the floor y = 0 at x = 0, each touching the next."""
    return [ball([0, radius + 2 * radius * k], radius, 1.0) for k in range(count)]


def hexagonal_pile(radius: float, rows: int, per_row: int) -> list:
    """Return 1 kg discs packed in rows from x = 0, y = 0, each in the hollows of the row below."""
    height = math.sqrt(3.0) * radius
    return [ball([(radius if row % 2 == 0 else 2 * radius) + 2 * radius * k,
                  radius + height * row], radius, 1.0)
            for row in range(rows) for k in range(per_row)]


def resting_column(count: int = 20, restitution: float = 0.0, radius: float = 0.05) -> dict:
    """Return a 2-D column of discs at rest on a floor under gravity, 240 Hz."""
    return {'dimensions': 2, 'dt': RESTING_DT,
            'effects': {'gravity': [0.0, -G], 'walls': {'min': [None, 0.0]},
                        'restitution': restitution},
            'particles': column(count, radius)}


def resting_pile(restitution: float = 0.0, rows: int = 20, per_row: int = 25,
                 radius: float = 0.05) -> dict:
    """Return a 2-D hexagonal pile at rest on a floor between two walls under gravity, 240 Hz.

    The walls stand at x = 0 and x = (2 per_row + 1) r, so the rows that
    start one radius in fit between them.
    """
    return {'dimensions': 2, 'dt': RESTING_DT,
            'effects': {'gravity': [0.0, -G], 'restitution': restitution,
                        'walls': {'min': [0.0, 0.0], 'max': [(2 * per_row + 1) * radius, None]}},
            'particles': hexagonal_pile(radius, rows, per_row)}


# -- stacks, piles and pours (issue outcomes: stand, do not sink, conserve) ----------------

# m: the radius of the stack scenarios, 5 cm rounded to a multiple of 2^-24 (2.4e-7
# relative), so that every sum of multiples of it below 2^5 m is exact in binary and
# touching neighbours touch exactly (gap 0, not a rounding's worth either way).
STACK_RADIUS = round(0.05 * 2 ** 24) / 2 ** 24
# kg, and the materials of the pile and the pour: restitution, friction coefficient.
STACK_MASS = 0.1
STACK_RESTITUTION = 0.3
STACK_FRICTION = 0.5
# s: the step of the stack scenarios and of the 3-D pour (60 Hz).
STACK_DT = 1.0 / 60.0
# Steps the shipped ``pile`` (dt = 1/120 s) takes to settle: 4 s.
PILE_SETTLE_STEPS = 480
# m: side of the 3-D pour's square box for POUR_COUNT spheres of 5 cm; a random close
# packing (volume fraction 0.64) of them fills it to 1.28 m.
POUR_COUNT = 10_000
POUR_SIDE = 2.53


def _gravity(dimensions: int) -> list:
    """Return gravity along -y in ``dimensions`` components."""
    return [0.0, -G, 0.0][:dimensions]


def sphere_column(count: int = 20, *, radius: float = STACK_RADIUS, mass: float = STACK_MASS,
                  restitution: float = STACK_RESTITUTION, friction: Optional[float] = None,
                  dimensions: int = 3, dt: float = STACK_DT, accuracy: AccuracyLike = None
                  ) -> Scene:
    """Return ``count`` spheres stacked on the floor y = 0 (no other wall), each touching the next.

    Centres at y = r + 2 r k on the y axis (exact in binary for STACK_RADIUS),
    so the top centre's exact height is :func:`column_top`. Without friction
    by default, so the ``exact`` preset accepts it.
    """
    effects = {'gravity': _gravity(dimensions), 'restitution': restitution,
               'walls': {'min': [None, 0.0, None][:dimensions], 'restitution': restitution}}
    if friction is not None:
        effects['friction'] = friction
    origin = [0.0] * dimensions
    particles = [Particle(_at(origin, 1, radius + 2 * radius * k), radius, mass)
                 for k in range(count)]
    return build_scene(particles, dimensions=dimensions, dt=dt, effects=effects,
                       accuracy=accuracy, name=f'column_{count}', source='sphere_column')


def column_top(count: int = 20, radius: float = STACK_RADIUS) -> float:
    """Return the exact height of the top centre of a column of ``count`` at rest, m."""
    return radius + 2 * radius * (count - 1)


def disc_pyramid(base: int = 10, *, friction: Optional[float] = STACK_FRICTION,
                 radius: float = STACK_RADIUS, mass: float = STACK_MASS,
                 restitution: float = STACK_RESTITUTION, dt: float = STACK_DT,
                 accuracy: AccuracyLike = None) -> Scene:
    """Return a 2-D pyramid of base (base + 1) / 2 discs between two walls, on a floor.

    The bottom row's ``base`` discs span the box exactly (walls at x = 0 and
    x = 2 base r, each disc touching its neighbours and the end ones a wall);
    every disc above rests in the groove of the two below it (rows sqrt(3) r
    apart), so the pyramid stands even without friction (``friction=None``).
    """
    effects = {'gravity': _gravity(2), 'restitution': restitution,
               'walls': {'min': [0.0, 0.0], 'max': [2 * base * radius, None],
                         'restitution': restitution}}
    if friction is not None:
        effects['friction'] = friction
    particles = [Particle([radius * (1 + row) + 2 * radius * k,
                           radius + math.sqrt(3.0) * radius * row], radius, mass)
                 for row in range(base) for k in range(base - row)]
    label = 'frictionless' if friction is None else f'mu{friction:g}'
    return build_scene(particles, dimensions=2, dt=dt, effects=effects, accuracy=accuracy,
                       name=f'pyramid_{len(particles)}_{label}', source='disc_pyramid')


def shipped_pile(accuracy: AccuracyLike = None) -> Scene:
    """Return the shipped ``pile`` scene (240 discs poured into a box) under ``accuracy``.

    Stepped PILE_SETTLE_STEPS times it is the settled pile of the stack outcomes.
    """
    scene = load_scene('pile')
    if accuracy is None:
        return scene
    return scene.with_accuracy(parse_accuracy(accuracy_mapping(accuracy), 'shipped_pile'))


def pour2d(count: int = 240, *, width: Optional[float] = None, radius: float = 0.05,
           mass: float = STACK_MASS, restitution: float = STACK_RESTITUTION,
           friction: float = STACK_FRICTION, dt: float = 1.0 / 120.0, seed: int = 4,
           speed: float = 1.0, accuracy: AccuracyLike = None) -> Scene:
    """Return a 2-D pour of ``count`` discs into a box, as the shipped ``pile`` of any size.

    The box is ``width`` wide (default 1.6 m scaled by count / 240, the
    shipped pile's depth of about 15 rows for any count); the discs start
    on a jittered lattice from 0.5 m up at ``speed`` in random directions.
    """
    if width is None:
        width = 1.6 * count / 240.0
    spacing = 2.0 * radius * 1.05           # the generator's lattice spacing
    top = 0.5 + (math.ceil(count / max(1, math.floor(width / spacing))) + 1) * spacing
    effects = {'gravity': _gravity(2), 'restitution': restitution, 'friction': friction,
               'walls': {'min': [0.0, 0.0], 'max': [width, top + 1.0],
                         'restitution': restitution}}
    return build_scene(dimensions=2, dt=dt, effects=effects, accuracy=accuracy,
                       generate=[Gas(count, radius, mass, [0.0, 0.5], [width, top],
                                     speed=speed, seed=seed)],
                       name=f'pour2d_{count}', source='pour2d')


def falling_cluster(side: int = 3, *, radius: float = STACK_RADIUS, mass: float = STACK_MASS,
                    restitution: float = 0.5, friction: Optional[float] = 0.3,
                    speed: float = 0.0, seed: int = 0, dt: float = STACK_DT,
                    accuracy: AccuracyLike = None) -> Scene:
    """Return side^3 touching spheres on a cubic lattice falling under gravity, no walls.

    Centres 2 r apart (exact in binary for STACK_RADIUS), so every neighbour
    pair touches at the start. ``speed`` > 0 gives each sphere that speed in
    a random direction (``seed``), so the cluster also collides inside;
    nothing outside acts but gravity, so the momentum is p0 + M g t.
    """
    rng = np.random.default_rng(seed)
    particles = []
    for index in itertools.product(range(side), repeat=3):
        direction = rng.normal(size=3)
        velocity = direction / np.linalg.norm(direction) * speed
        particles.append(Particle([2 * radius * k for k in index], radius, mass,
                                  velocity=velocity.tolist()))
    effects = {'gravity': _gravity(3), 'restitution': restitution}
    if friction is not None:
        effects['friction'] = friction
    return build_scene(particles, dimensions=3, dt=dt, effects=effects, accuracy=accuracy,
                       name=f'cluster_{len(particles)}', source='falling_cluster')


def pour3d(count: int = POUR_COUNT, *, side: Optional[float] = None,
           radius: float = 0.05, mass: float = STACK_MASS,
           restitution: float = STACK_RESTITUTION, friction: float = STACK_FRICTION,
           dt: float = STACK_DT, seed: int = 5, speed: float = 1.0,
           accuracy: AccuracyLike = None) -> Scene:
    """Return a 3-D pour of ``count`` spheres into a square box open at the top.

    The box's side defaults to POUR_SIDE scaled by sqrt(count / POUR_COUNT),
    so any count fills it to the same depth (1.28 m at random close
    packing). The spheres start on a jittered lattice from 0.5 m up, at
    ``speed`` in random directions, and fall under gravity.
    """
    if side is None:
        side = POUR_SIDE * math.sqrt(count / POUR_COUNT)
    spacing = 2.0 * radius * 1.05           # the generator's lattice spacing
    per_layer = max(1, math.floor(side / spacing)) ** 2
    top = 0.5 + (math.ceil(count / per_layer) + 1) * spacing
    effects = {'gravity': _gravity(3), 'restitution': restitution, 'friction': friction,
               'walls': {'min': [0.0, 0.0, 0.0], 'max': [side, top + 1.0, side],
                         'restitution': restitution}}
    return build_scene(dimensions=3, dt=dt, effects=effects, accuracy=accuracy,
                       generate=[Gas(count, radius, mass, [0.0, 0.5, 0.0], [side, top, side],
                                     speed=speed, seed=seed)],
                       name=f'pour3d_{count}', source='pour3d')


def drop_ball(world: World, *, height: float = 0.3, x: Optional[float] = None,
              radius: Optional[float] = None, mass: Optional[float] = None) -> int:
    """Spawn a ball ``height`` m above the highest particle of ``world``; return its id.

    By default it has the radius and mass of the world's first particle and
    falls from rest onto the highest one (``x`` sets its first coordinate,
    any other coordinates are the highest particle's).
    """
    state = world.state
    dims = world.scene.dimensions
    top = int(np.argmax(state.position[:, 1] + state.radius))
    radius = float(state.radius[0]) if radius is None else radius
    mass = 1.0 / float(state.inv_mass[0]) if mass is None else mass
    position = state.position[top, :dims].astype(float).copy()
    position[1] += float(state.radius[top]) + radius + height
    if x is not None:
        position[0] = x
    entry = Particle(position.tolist(), radius, mass)
    new = parse_spawn_data([entry.mapping()], dims, len(state), 'drop_ball')
    return int(world.spawn(new, source='drop_ball')[0])


def _at(origin: Sequence[float], axis: int, value: float) -> list:
    """Return ``origin`` with component ``axis`` set to ``value``."""
    out = list(origin)
    out[axis] = value
    return out
