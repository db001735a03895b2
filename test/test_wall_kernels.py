"""The compiled walls stage does exactly what the vectorised wall law does.

``wall_kernels.wall_pass`` writes ``contact_law.reflect_on_plane``, the
combine rule at a wall and the wall friction with spin one particle at a
time. Here the stage and its numpy reference (``solve_reference``) run on
the same contexts
(random particles past every plane of a box, with and without gravity,
per-particle restitution and friction, a restitution threshold, 2-D and
3-D, and every step of the shipped pile) and must give identical
positions, velocities, spins, booked energy (totals and per particle),
wall-collision counts and impact records, bit for bit.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from collision_node import World
from collision_node.physics.model.accuracy import parse_accuracy
from collision_node.physics.model.effects import Effects, Walls
from collision_node.physics.model.impacts import ImpactLog
from collision_node.physics.model.scene import load_scene
from collision_node.physics.model.tunables import WALL_ULPS
from collision_node.physics.stages.solve.walls import near_wall_distance, WallStage
from collision_node.physics.model.state import ParticleState
from collision_node.physics.step.pipeline import StepContext, StepStats
from solve_reference import WallReference

GRAVITY = np.array([0.0, -9.81, 0.0])


def crowded_state(rng: np.random.Generator, n: int, dims: int, per_particle: bool,
                  scale: float = 1.0, offset: float = 0.0) -> ParticleState:
    """Return n particles in and around the box [0, scale]^dims (+ offset), many past a wall.

    Some are static, some sit in corners (past two planes), some are past
    a plane while moving away from it (put back, not reflected).
    """
    position = np.zeros((n, 3))
    position[:, :dims] = offset + scale * rng.uniform(-0.1, 1.1, size=(n, dims))
    velocity = np.zeros((n, 3))
    velocity[:, :dims] = rng.normal(scale=2.0, size=(n, dims)) * scale
    velocity[:5, :dims] = 1e-4 * scale                 # slow: below any threshold
    inv_mass = rng.uniform(0.5, 4.0, n)
    inv_mass[rng.choice(n, n // 10, replace=False)] = 0.0
    radius = scale * rng.uniform(0.02, 0.08, n)
    state = ParticleState(ids=np.arange(n), position=position, velocity=velocity,
                          radius=radius, inv_mass=inv_mass,
                          angular_velocity=np.zeros((n, 3)))
    state.angular_velocity[:, 2] = rng.normal(size=n)
    if dims == 3:
        state.angular_velocity[:, :2] = rng.normal(size=(n, 2))
    if per_particle:
        state.restitution = np.where(rng.random(n) < 0.5, np.nan, rng.uniform(0.0, 1.0, n))
        state.friction = np.where(rng.random(n) < 0.5, np.nan, rng.uniform(0.0, 1.0, n))
    return state


def context(state: ParticleState, effects: Effects, dims: int, dt: float) -> StepContext:
    """Return a step context on ``state`` that records impacts."""
    ctx = StepContext(state=state, dt=dt, dimensions=dims, effects=effects,
                      accuracy=parse_accuracy('fast', 'test'), stats=StepStats(), time=1.25)
    ctx.impacts = ImpactLog()
    if ctx.losses is not None:
        ctx.losses[:] = np.linspace(0.0, 1.0, ctx.losses.size)
    return ctx


def twin_of(ctx: StepContext) -> StepContext:
    """Return an independent copy of a context (state, counters, losses, impact log)."""
    twin = copy.copy(ctx)
    twin.state, twin.stats = copy.deepcopy(ctx.state), ctx.stats.copy()
    twin.losses = None if ctx.losses is None else ctx.losses.copy()
    twin.impacts = None if ctx.impacts is None else copy.deepcopy(ctx.impacts)
    return twin


def assert_same_outcome(ref: StepContext, new: StepContext) -> None:
    """Assert the two contexts hold identical states, bookings and impact records."""
    for name in ('position', 'velocity', 'angular_velocity'):
        np.testing.assert_array_equal(getattr(new.state, name), getattr(ref.state, name),
                                      err_msg=name)
    assert new.stats.dissipated == ref.stats.dissipated
    assert new.stats.wall_collisions == ref.stats.wall_collisions
    if ref.losses is not None:
        np.testing.assert_array_equal(new.losses, ref.losses)
    if ref.impacts is not None:
        taken_ref, taken_new = ref.impacts.take(), new.impacts.take()
        assert taken_new.dtype == taken_ref.dtype and taken_new.size == taken_ref.size
        for field in taken_ref.dtype.names:
            np.testing.assert_array_equal(taken_new[field], taken_ref[field], err_msg=field)


def run_both(ctx: StepContext, walls: Walls, friction) -> tuple[StepContext, StepContext]:
    """Run the numpy and the compiled walls stage on twins of ``ctx``; return (ref, new)."""
    ref = twin_of(ctx)
    WallReference(walls, friction=friction).run(ref)
    WallStage(walls, friction=friction).run(ctx)
    return ref, ctx


@pytest.mark.parametrize('dims', [2, 3])
@pytest.mark.parametrize('gravity', [False, True])
@pytest.mark.parametrize('friction', [None, 0.4])
@pytest.mark.parametrize('per_particle, threshold', [(False, None), (True, None),
                                                     (True, 0.5)])
def test_compiled_walls_equal_numpy(dims, gravity, friction, per_particle, threshold):
    rng = np.random.default_rng(dims + 10 * gravity + (friction is not None) * 100
                                + per_particle * 1000 + (threshold is not None) * 7)
    state = crowded_state(rng, 400, dims, per_particle)
    walls = Walls(low=np.zeros(3), high=np.ones(3), restitution=0.7)
    effects = Effects(gravity=GRAVITY if gravity else None, walls=walls, friction=friction,
                      restitution_threshold=threshold)
    ref, new = run_both(context(state, effects, dims, dt=0.05), walls, friction)
    assert_same_outcome(ref, new)
    # Something of every kind happened: impacts, put-backs, bookings, records.
    assert ref.stats.wall_collisions > 50
    assert ref.stats.dissipated['walls'] != 0.0
    assert len(new.impacts) == 0          # taken by the comparison
    inside = np.all((new.state.position[:, :dims] - new.state.radius[:, None] >= -1e-12)
                    & (new.state.position[:, :dims] + new.state.radius[:, None]
                       <= 1.0 + 1e-12), axis=1)
    assert inside[new.state.inv_mass > 0.0].all()


@pytest.mark.parametrize('scale, offset', [(1e-6, 0.0), (1.0, 1e9), (1e-6, 1e9 * 1e-6)])
def test_compiled_walls_equal_numpy_far_away_and_small(scale, offset):
    rng = np.random.default_rng(3)
    state = crowded_state(rng, 300, 3, True, scale=scale, offset=offset)
    walls = Walls(low=np.full(3, offset), high=np.full(3, offset + scale), restitution=0.5)
    effects = Effects(gravity=GRAVITY * scale, walls=walls, friction=0.3)
    ref, new = run_both(context(state, effects, 3, dt=0.05), walls, 0.3)
    assert_same_outcome(ref, new)
    assert ref.stats.wall_collisions > 50


def test_single_plane_and_no_recording():
    # A floor only (other sides open), no impact log and no spin array: the
    # kernel must not need either.
    rng = np.random.default_rng(9)
    state = crowded_state(rng, 200, 3, False)
    state.angular_velocity = None
    walls = Walls(low=np.array([-np.inf, 0.0, -np.inf]), high=np.full(3, np.inf),
                  restitution=0.9)
    effects = Effects(gravity=GRAVITY, walls=walls)
    ctx = context(state, effects, 3, dt=0.02)
    ctx.impacts = None
    ref, new = run_both(ctx, walls, None)
    assert_same_outcome(ref, new)
    assert ref.stats.wall_collisions > 5


def test_compiled_walls_equal_numpy_at_every_step_of_the_pile():
    # The shipped pile poured and settling (fast: walls with friction and
    # gravity): at every step the stage and its reference run on the same context.
    # Sleeping off: a sleeping pile skips its stages, and every step is compared.
    world = World(load_scene('pile').with_accuracy(
        parse_accuracy({'preset': 'fast', 'sleep_time': None}, 'test')))
    world.record_impacts(True)
    stages = world.pipeline.stages
    checked = []

    class Both:
        def __init__(self, stage):
            self.stage, self.name = stage, stage.name
            self.reference = WallReference(stage.walls, friction=stage.friction)

        def run(self, ctx):
            twin = twin_of(ctx)
            self.reference.run(twin)
            self.stage.run(ctx)
            assert_same_outcome(twin, twin_of(ctx))
            checked.append(ctx.stats.wall_collisions)

    (at,) = [k for k, stage in enumerate(stages) if isinstance(stage, WallStage)]
    stages[at] = Both(stages[at])
    world.step(240)
    assert len(checked) == 240 and checked[-1] > 100


@pytest.mark.parametrize('dims, gravity, threshold, n, threads', [
    (2, True, None, 400, 1), (3, False, None, 400, 1), (3, True, 0.5, 400, 1),
    (3, True, None, 5000, 2)])
def test_the_near_list_holds_every_dynamic_particle_within_the_wall_contact_distance(
        dims, gravity, threshold, n, threads):
    """The list the contact solve and the clamp rely on: exactly the particles near a plane.

    Tested where the pass leaves the particles (those it moved included),
    against a plain numpy test of every particle; 5,000 particles on 2
    threads take the shared marking loop.
    """
    rng = np.random.default_rng(dims + 10 * n)
    state = crowded_state(rng, n, dims, per_particle=False)
    walls = Walls(low=np.zeros(3), high=np.ones(3), restitution=0.7)
    effects = Effects(gravity=GRAVITY if gravity else None, walls=walls,
                      restitution_threshold=threshold)
    ctx = context(state, effects, dims, dt=0.05)
    ctx.threads = threads
    WallStage(walls).run(ctx)
    slop, ahead = near_wall_distance(float(effects.threshold(ctx.dt)), ctx.dt)
    s = ctx.state
    planes = walls.planes(dims)
    largest_ulps = max(WALL_ULPS * np.spacing(abs(plane)) for _, plane, _ in planes)
    exact = np.zeros(n, dtype=bool)       # the solve's widest wall contact, plane by plane
    least = np.full(n, np.inf)
    for axis, plane, inward in planes:
        gap = inward * (s.position[:, axis] - plane) - s.radius
        exact |= gap <= slop * s.radius + WALL_ULPS * np.spacing(abs(plane)) + ahead
        least = np.minimum(least, gap)
    dynamic = s.inv_mass > 0.0
    expected = np.flatnonzero(exact & dynamic)
    # Every particle the solve could find is listed (ascending), and no particle farther
    # than the largest plane's spacings allow.
    assert np.all(np.diff(ctx.near_walls) > 0)
    assert np.isin(expected, ctx.near_walls).all()
    bound = slop * s.radius + (largest_ulps + ahead)
    np.testing.assert_array_equal(ctx.near_walls, np.flatnonzero(dynamic & (least <= bound)))
    # Some particles are near a plane and many are not (the list saves work).
    assert 0 < expected.size < n
    if threshold is not None or gravity:
        assert ahead > 0.0
