"""The compiled narrowphase and separation do exactly what their numpy statements do.

``narrowphase_kernels.find_overlaps``, ``project_overlaps`` and ``pay_for_lift``
write the narrowphase's contact test and the separation stage's projection,
wall clamp and per-cluster lift budget one particle or pair at a time. Here
they and their vectorised references (``test/oracles``) run on the same
inputs (random overlaps, and every step of the shipped pile pouring and
settling) and must keep the same contacts and give the same positions,
velocities and booked energy.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from collision_node import World
from collision_node.physics.model.accuracy import parse_accuracy
from collision_node.physics.model.effects import Effects, Walls
from collision_node.physics.model.scene import load_scene
from collision_node.physics.stages.detection.narrowphase import find_contacts, NarrowphaseStage
from collision_node.physics.stages.correction.separation import SeparationStage
from collision_node.physics.model.state import ParticleState
from collision_node.physics.step.pipeline import StepContext, StepStats
from oracles.narrowphase_oracle import find_contacts as reference_contacts, NarrowphaseOracle
from oracles.separation_oracle import clusters, SeparationOracle

GRAVITY = np.array([0.0, -9.81, 0.0])


def overlapping_state(rng: np.random.Generator, n: int, dims: int, box: float) -> ParticleState:
    """Return n particles packed into a box so that many overlap; some static, two coincident."""
    position = np.zeros((n, 3))
    position[:, :dims] = rng.uniform(0.0, box, size=(n, dims))
    position[1] = position[0]                         # coincident, moving apart
    position[3] = position[2]                         # coincident, at rest relative
    velocity = np.zeros((n, 3))
    velocity[:, :dims] = rng.normal(scale=0.5, size=(n, dims))
    velocity[3] = velocity[2]
    inv_mass = rng.uniform(0.5, 4.0, n)
    inv_mass[rng.choice(n, n // 10, replace=False)] = 0.0
    inv_mass[:4] = 1.0
    radius = rng.uniform(0.05, 0.12, n)
    return ParticleState(ids=np.arange(n), position=position, velocity=velocity,
                         radius=radius, inv_mass=inv_mass)


def all_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return every pair (i < j) as candidates."""
    i, j = np.triu_indices(n, 1)
    return i.astype(np.int64), j.astype(np.int64)


def context(state: ParticleState, effects: Effects, dims: int, losses=None) -> StepContext:
    """Return a step context on ``state`` (the per-particle losses given or zero)."""
    ctx = StepContext(state=state, dt=0.01, dimensions=dims, effects=effects,
                      accuracy=parse_accuracy('fast', 'test'), stats=StepStats())
    if losses is not None:
        ctx.losses = losses.copy()
    return ctx


def assert_contacts_equal(a, b) -> None:
    """Assert two contact sets are the same pairs with the same normals and overlaps."""
    np.testing.assert_array_equal(a.i, b.i)
    np.testing.assert_array_equal(a.j, b.j)
    np.testing.assert_array_equal(a.normal, b.normal)
    np.testing.assert_array_equal(a.penetration, b.penetration)


def assert_same_outcome(ref: StepContext, new: StepContext) -> None:
    """Assert the kernels and the reference moved, slowed and booked the same.

    Bit for bit: the kernels do the same floating-point operations in the
    same order (sums per particle and per cluster in numpy's order).
    """
    np.testing.assert_array_equal(new.state.position, ref.state.position)
    np.testing.assert_array_equal(new.state.velocity, ref.state.velocity)
    assert new.stats.dissipated == ref.stats.dissipated
    if ref.losses is None:
        assert new.losses is None
    else:
        np.testing.assert_array_equal(new.losses, ref.losses)


def run_both(state: ParticleState, effects: Effects, dims: int, contacts, losses=None):
    """Run the reference and the stage on copies; return (reference ctx, stage ctx)."""
    out = []
    for stage in (SeparationOracle, SeparationStage):
        ctx = context(copy.deepcopy(state), effects, dims, losses)
        ctx.contacts = contacts
        stage(walls=effects.walls).run(ctx)
        out.append(ctx)
    return out


@pytest.mark.parametrize('dims', [2, 3])
@pytest.mark.parametrize('seed', range(4))
def test_compiled_narrowphase_keeps_the_same_contacts(dims, seed):
    rng = np.random.default_rng(seed)
    state = overlapping_state(rng, 120, dims, 1.0)
    i, j = all_pairs(len(state))
    args = (state.position, state.velocity, state.radius, state.inv_mass, i, j)
    ref = reference_contacts(*args)
    assert len(ref) > 50                                 # a crowded box: many overlaps
    assert_contacts_equal(find_contacts(*args), ref)
    # The fallback lines of action of the coincident pairs are exercised.
    first = (ref.i == 0) & (ref.j == 1)
    assert first.sum() == 1
    rest = (ref.i == 2) & (ref.j == 3)
    np.testing.assert_array_equal(ref.normal[rest], [[1.0, 0.0, 0.0]])


def test_compiled_narrowphase_finds_nothing_without_overlap():
    state = overlapping_state(np.random.default_rng(1), 10, 3, 1.0)
    state.position[:, 0] = np.arange(10) * 10.0
    i, j = all_pairs(10)
    assert len(find_contacts(state.position, state.velocity, state.radius,
                             state.inv_mass, i, j)) == 0
    none = np.zeros(0, dtype=np.int64)
    assert len(find_contacts(state.position, state.velocity, state.radius,
                             state.inv_mass, none, none)) == 0


@pytest.mark.parametrize('dims', [2, 3])
@pytest.mark.parametrize('gravity', [False, True])
@pytest.mark.parametrize('walls', [False, True])
@pytest.mark.parametrize('seed', range(3))
def test_compiled_separation_equals_numpy_on_random_overlaps(dims, gravity, walls, seed):
    rng = np.random.default_rng(100 + seed)
    state = overlapping_state(rng, 150, dims, 1.0)
    # Open above the particles: the floor and the static particles lift, nothing presses down.
    wall = Walls(low=np.array([0.0, 0.0, -np.inf if dims == 2 else 0.0]),
                 high=np.array([1.0, 3.0, np.inf if dims == 2 else 1.0]), restitution=0.5)
    effects = Effects(gravity=GRAVITY if gravity else None, walls=wall if walls else None)
    i, j = all_pairs(len(state))
    contacts = reference_contacts(state.position, state.velocity, state.radius,
                                  state.inv_mass, i, j)
    # Losses that pay part of the lift in some clusters and none in others.
    losses = rng.uniform(0.0, 2e-3, len(state)) * (rng.uniform(size=len(state)) < 0.5)
    ref, new = run_both(state, effects, dims, contacts, losses if gravity else None)
    moved = np.abs(ref.state.position - state.position).max(axis=1) > 0.0
    assert moved.sum() > 30                              # the projection did work
    assert_same_outcome(ref, new)
    if gravity:
        # Some lift was paid from speed, some by the losses, and the rest not made
        # (from speed only where walls lift: pairs of dynamic particles keep their
        # centre of mass).
        assert ref.stats.dissipated['separation'] != 0.0
        assert np.any(ref.state.velocity != state.velocity) or not walls
        assert_lift_within_budget(state, ref, contacts, losses, exercised=walls)


def assert_lift_within_budget(before: ParticleState, ctx: StepContext, contacts,
                              losses: np.ndarray, exercised: bool = True) -> None:
    """Assert the separation added no energy beyond each cluster's losses.

    Per cluster of touching dynamic particles, the kinetic plus potential
    energy the stage added is at most the cluster's losses (0 if negative),
    to round-off; the booking (a negative loss) is that addition exactly.
    With ``exercised``, some cluster must have had a lift its budget and
    speed could not pay (so the rule that moves particles back was
    exercised); without walls only static particles lift.
    """
    s = ctx.state
    mass = np.where(s.inv_mass > 0.0, 1.0 / np.where(s.inv_mass > 0.0, s.inv_mass, 1.0), 0.0)
    kinetic = 0.5 * mass * ((s.velocity ** 2).sum(axis=1) - (before.velocity ** 2).sum(axis=1))
    potential = -mass * ((s.position - before.position) @ GRAVITY)
    added = kinetic + potential
    np.testing.assert_allclose(-(ctx.losses - losses), added, rtol=1e-9, atol=1e-15)
    cluster = clusters(len(s), s.dynamic, contacts.i, contacts.j)
    count = int(cluster.max()) + 1
    per_cluster = np.bincount(cluster, weights=added, minlength=count)
    budget = np.maximum(np.bincount(cluster, weights=losses, minlength=count), 0.0)
    assert np.all(per_cluster <= budget + 1e-12 * (1.0 + budget))
    # Pure projection (no budget rule) would have lifted some cluster further.
    projected = context(copy.deepcopy(before), ctx.effects, ctx.dimensions, None)
    projected.contacts = contacts
    SeparationOracle(walls=ctx.effects.walls)._project(projected, True)
    lifted = -mass * ((projected.state.position - before.position) @ GRAVITY)
    over = np.bincount(cluster, weights=lifted, minlength=count) > budget + 1e-9
    assert over.any() or not exercised


def test_compiled_separation_holds_particles_at_walls_like_numpy():
    # No gravity, one pass: a light ball pressed against the floor by a heavy one stays put.
    state = ParticleState(ids=np.arange(2), position=np.array([[0.5, 0.1, 0.0],
                                                               [0.5, 0.25, 0.0]]),
                          velocity=np.zeros((2, 3)), radius=np.array([0.1, 0.1]),
                          inv_mass=np.array([10.0, 0.1]))
    wall = Walls(low=np.array([0.0, 0.0, -np.inf]), high=np.array([1.0, 1.0, np.inf]))
    effects = Effects(walls=wall)
    contacts = reference_contacts(state.position, state.velocity, state.radius,
                                  state.inv_mass, np.array([0]), np.array([1]))
    ref, new = run_both(state, effects, 2, contacts)
    assert ref.state.position[0, 1] == 0.1               # held on the floor
    assert ref.state.position[1, 1] == pytest.approx(0.3)
    assert_same_outcome(ref, new)


def test_compiled_stages_equal_numpy_at_every_step_of_the_pile():
    # The shipped pile poured and settling (fast): at every step the narrowphase and the
    # separation and their references run on the same context and must agree.
    # Sleeping off: a sleeping pile skips its stages, and every step is compared.
    world = World(load_scene('pile').with_accuracy(
        parse_accuracy({'preset': 'fast', 'sleep_time': None}, 'test')))
    stages = world.pipeline.stages
    checked = {'narrowphase': 0, 'separation': 0}

    class Both:
        def __init__(self, stage, reference):
            self.stage, self.reference, self.name = stage, reference, stage.name

        def run(self, ctx):
            twin = copy.copy(ctx)
            twin.state, twin.stats = copy.deepcopy(ctx.state), ctx.stats.copy()
            twin.losses = None if ctx.losses is None else ctx.losses.copy()
            self.reference.run(twin)
            self.stage.run(ctx)
            if self.name == 'narrowphase':
                assert_contacts_equal(ctx.contacts, twin.contacts)
            else:
                assert_same_outcome(twin, ctx)
            checked[self.name] += 1

    for k, stage in enumerate(stages):
        if isinstance(stage, NarrowphaseStage):
            stages[k] = Both(stage, NarrowphaseOracle(stage.speculative, stage.impacts))
        elif isinstance(stage, SeparationStage):
            stages[k] = Both(stage, SeparationOracle(walls=stage.walls, passes=stage.passes))
    world.step(240)
    assert checked == {'narrowphase': 240, 'separation': 240}
    assert world.stats.dissipated['separation'] != 0.0


@pytest.mark.parametrize('mover_z, expected', [
    (0.0, (0.0, 0.08, 0.0)),
    # 3-D: the nearest point of the circle where the two reach spheres meet
    # (centre the origin, radius 0.08, in the y-z plane).
    (0.01, (0.0, 0.08 * 0.07 / np.hypot(0.07, 0.01), 0.08 * 0.01 / np.hypot(0.07, 0.01))),
])
def test_a_particle_sunk_into_a_groove_rises_to_touch_both_supports_exactly(mover_z, expected):
    # Two static discs 0.12 m apart (r = 0.05 m) and a disc sunk between them under
    # gravity: the separation puts it where it touches both (0.08 m up, by Pythagoras:
    # 0.1^2 = 0.06^2 + 0.08^2), straight up from where it was, to round-off (the sweeps
    # it replaced stopped at 1e-9 r). Its losses pay for the lift.
    state = ParticleState(ids=np.arange(3),
                          position=np.array([[-0.06, 0.0, 0.0], [0.06, 0.0, 0.0],
                                             [0.0, 0.07, mover_z]]),
                          velocity=np.zeros((3, 3)), radius=np.full(3, 0.05),
                          inv_mass=np.array([0.0, 0.0, 10.0]))
    effects = Effects(gravity=GRAVITY)
    contacts = reference_contacts(state.position, state.velocity, state.radius,
                                  state.inv_mass, np.array([0, 1]), np.array([2, 2]))
    assert np.all(contacts.penetration > 0.0)
    ref, new = run_both(state, effects, 3, contacts, np.array([0.0, 0.0, 1.0]))
    assert_same_outcome(ref, new)
    np.testing.assert_allclose(new.state.position[2], expected, rtol=0.0, atol=1e-16)
    gaps = np.linalg.norm(new.state.position[:2] - new.state.position[2], axis=1) - 0.1
    np.testing.assert_allclose(gaps, 0.0, rtol=0.0, atol=1e-16)


@pytest.mark.parametrize('preset', ['fast', 'balanced'])
def test_one_pass_separation_of_a_walled_gas_equals_numpy_and_keeps_its_buffers_clean(preset):
    # No gravity: one pass over the overlapping contacts, the clamps limited to the
    # particles near a wall and those of the pushed pairs, on buffers kept between steps.
    from collision_node.bench.throughput import gas_scene
    from collision_node.physics.model.scene import parse_scene
    world = World(parse_scene(dict(gas_scene(3000, fraction=0.3), accuracy=preset), 'gas'))
    stages = world.pipeline.stages
    pushed = []

    class Both:
        name = 'separation'

        def __init__(self, stage):
            self.stage = stage
            self.reference = SeparationOracle(walls=stage.walls, passes=stage.passes)

        def run(self, ctx):
            twin = copy.copy(ctx)
            twin.state, twin.stats = copy.deepcopy(ctx.state), ctx.stats.copy()
            self.reference.run(twin)
            before = ctx.state.position.copy()
            self.stage.run(ctx)
            assert_same_outcome(twin, ctx)
            pushed.append(int(np.count_nonzero(np.any(ctx.state.position != before, axis=1))))
            work = self.stage._work
            assert work is not None and work.moves.size == len(ctx.state)
            assert not np.any(work.moves) and not np.any(work.seen)

        def rows_moved(self, order):
            self.stage.rows_moved(order)

    k = next(k for k, stage in enumerate(stages) if isinstance(stage, SeparationStage))
    stages[k] = Both(stages[k])
    world.step(30)
    assert len(pushed) == 30 and sum(pushed) > 0     # the pass moved particles, and was checked
