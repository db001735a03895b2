"""Stacks stand, piles do not sink into themselves, contacts conserve momentum.

Every stepped preset (``fast``, ``balanced``, ``accurate``) must keep:

- a column of 20 spheres resting on a floor (touching exactly at the start,
  dt = 1/60 s) with its top centre within 1 % of r of its exact height for 10 s;
- a 2-D pyramid of 55 discs whose bottom row spans its box, every disc in
  a groove, with mu = 0.5 and without friction, each disc within 1 % of r
  of where it started for 10 s;
- a settled 2-D pour (the shipped ``pile``'s materials, depth and step; 100
  discs) and a small 3-D pour (400 spheres) at rest with no pair (and no
  particle against a wall) overlapping by 1 % of r;
- a ball dropped on the settled pile waking it (its discs move) and the pile
  at rest again afterwards, still within the overlap bound; a ball dropped on
  the column coming to rest on top, the new top at its exact height;
- a cluster of 27 touching spheres falling freely with contacts inside
  keeping momentum p0 + M g t to 1e-12 relative at every step.

``exact`` runs where it accepts the scene (no friction): the column and the
frictionless pyramid, which it keeps.
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node.physics.stages.detection.broadphase import candidate_pairs
from collision_node.physics.step.world import World
from collision_node.scenarios import (STACK_RADIUS, column_top, disc_pyramid, drop_ball,
                                      falling_cluster, pour2d, pour3d, sphere_column)

STEPPED = ('fast', 'balanced', 'accurate')
# Of r: the largest overlap, sink or displacement a resting stack may show.
BOUND = 0.01
# Steps of 10 s at the stacks' dt = 1/60 s.
TEN_SECONDS = 600
# The small 2-D pour: discs, and steps at dt = 1/120 s to settle (3 s).
PILE_DISCS = 100
PILE_STEPS = 360
# The small 3-D pour: spheres, and steps at dt = 1/60 s (the pour lands and settles:
# under accurate, which never sleeps, spheres still slide down the pile at 0.3 to 0.7 m/s
# near 4 s, and below 0.13 m/s from 5 s on).
POUR_SPHERES = 400
POUR_STEPS = 360
MOMENTUM_RTOL = 1e-12


def gap(reason: str):
    """Mark a target the solver does not meet yet: it still runs, and must fail (strict).

    The measured shortfall and its cause are in ``reason`` and in
    docs/stability.md ("Dense contact"); a strict mark turns into a failure
    the day the target is met, so the mark is removed with the fix.
    """
    return pytest.mark.xfail(strict=True, reason=reason)


def deepest_overlap(world: World) -> float:
    """Return the deepest overlap of a pair or a particle with a wall, as a fraction of r."""
    s, dims = world.state, world.scene.dimensions
    r = float(np.median(s.radius))
    i, j = candidate_pairs(s.position, s.radius)
    gap = np.linalg.norm(s.position[i] - s.position[j], axis=1) - (s.radius[i] + s.radius[j])
    deepest = max(0.0, -float(gap.min())) if gap.size else 0.0
    walls = world.scene.effects.walls
    if walls is not None:
        x, rad = s.position[:, :dims], s.radius[:, None]
        inside = np.concatenate([(x - rad - walls.low[:dims]).ravel(),
                                 (walls.high[:dims] - (x + rad)).ravel()])
        deepest = max(deepest, -float(inside.min()))
    return deepest / r


def at_rest(world: World) -> bool:
    """Whether every particle is slower than the restitution threshold (2 |g| dt)."""
    fastest = float(np.linalg.norm(world.state.velocity, axis=1).max())
    return fastest < world.scene.effects.threshold(world.scene.dt)


# The column's radius: STACK_RADIUS (every gap exactly 0 in binary) and 5 cm (the gaps
# of y = r + 2 r k rounded, within 1e-16 m either way).
RADII = [pytest.param(STACK_RADIUS, id='dyadic_r'), pytest.param(0.05, id='r5cm')]


@pytest.mark.parametrize('radius', RADII)
@pytest.mark.parametrize('preset', STEPPED + ('exact',))
def test_column_of_20_spheres_keeps_its_top_within_1pct_r_for_10_s(preset, radius):
    world = World(sphere_column(20, radius=radius, accuracy=preset))
    r, exact = radius, column_top(20, radius)
    assert world.state.position[-1, 1] == exact
    worst = 0.0
    for _ in range(TEN_SECONDS):
        world.step()
        worst = max(worst, abs(float(world.state.position[-1, 1]) - exact) / r)
    assert worst < BOUND, f'top off its exact height {exact} m by {worst:.3g} r'


# exact refuses friction, so it runs the frictionless pyramid only.
PYRAMIDS = [pytest.param(preset, friction, id=f'{preset}-{label}')
            for preset in STEPPED + ('exact',)
            for friction, label in ((0.5, 'mu0.5'), (None, 'frictionless'))
            if preset != 'exact' or friction is None]
POUR2D = STEPPED
# The floor row, put back on the floor by the walls stage, and the rows above it, held
# up by their resting impulses, rise apart where the sweeps of `fast` and `balanced` do
# not converge (docs/stability.md, "Dense contact"); at 4 substeps a step `fast` lands
# the pour within the bound.
POUR3D = [pytest.param(preset, marks=gap('deepest overlap above 1 % of r in a box 5 spheres '
                                         'wide'))
          for preset in ('fast', 'balanced')] + [
    pytest.param('accurate'),
    pytest.param({'preset': 'fast', 'substeps': 4}, id='fast-4-substeps')]
DROP_ON_PILE = STEPPED


@pytest.mark.parametrize('preset, friction', PYRAMIDS)
def test_pyramid_of_55_discs_moves_less_than_1pct_r_for_10_s(preset, friction):
    world = World(disc_pyramid(10, friction=friction, accuracy=preset))
    assert len(world.state) == 55
    start, r = world.state.position.copy(), float(world.state.radius[0])
    worst = 0.0
    for _ in range(TEN_SECONDS):
        world.step()
        worst = max(worst, float(np.linalg.norm(world.state.position - start, axis=1).max()))
    assert worst / r < BOUND, f'a disc moved {worst / r:.3g} r'


@pytest.mark.parametrize('preset', POUR2D)
def test_settled_2d_pile_overlaps_less_than_1pct_r(preset):
    world = World(pour2d(PILE_DISCS, accuracy=preset))
    world.step(PILE_STEPS)
    assert at_rest(world)
    deepest = deepest_overlap(world)
    assert deepest < BOUND, f'deepest overlap {deepest:.3g} r'


@pytest.mark.parametrize('preset', POUR3D)
def test_settled_3d_pour_overlaps_less_than_1pct_r(preset):
    world = World(pour3d(POUR_SPHERES, accuracy=preset))
    world.step(POUR_STEPS)
    assert at_rest(world)                                  # landed and settled
    deepest = deepest_overlap(world)
    assert deepest < BOUND, f'deepest overlap {deepest:.3g} r'


@pytest.mark.parametrize('preset', DROP_ON_PILE)
def test_ball_dropped_on_settled_pile_wakes_it_and_it_settles_again(preset):
    world = World(pour2d(PILE_DISCS, accuracy=preset))
    world.step(PILE_STEPS)
    assert at_rest(world)
    count, before = len(world.state), world.state.position.copy()
    drop_ball(world, height=0.3)
    woken = 0.0
    for _ in range(PILE_STEPS):
        world.step()
        # A disc the ball strikes (or that one strikes) answers with a speed of its own.
        woken = max(woken, float(np.linalg.norm(world.state.velocity[:count], axis=1).max()))
    assert woken > 0.0, 'no disc of the pile moved when the ball landed on it'
    assert at_rest(world)
    deepest = deepest_overlap(world)
    assert deepest < BOUND, f'deepest overlap {deepest:.3g} r after the drop'
    # The ball rests on the pile, not in it: no higher than where it fell from, and
    # above the floor by more than a disc's diameter.
    r = float(world.state.radius[-1])
    assert 2 * r < float(world.state.position[-1, 1]) < float(before[:, 1].max()) + 3 * r


@pytest.mark.parametrize('preset', STEPPED)
def test_ball_dropped_on_column_rests_on_top_at_its_exact_height(preset):
    world = World(sphere_column(20, accuracy=preset))
    world.step(TEN_SECONDS)
    drop_ball(world, height=0.3)
    world.step(TEN_SECONDS)
    r = float(world.state.radius[0])
    assert at_rest(world)
    # The ball, dropped on the column's axis, sits on top of it: 21 spheres touching.
    error = (float(world.state.position[-1, 1]) - column_top(21)) / r
    assert abs(error) < BOUND, f'the ball rests {error:.3g} r off its exact height'
    deepest = deepest_overlap(world)
    assert deepest < BOUND, f'deepest overlap {deepest:.3g} r'


@pytest.mark.parametrize('preset', STEPPED)
def test_falling_cluster_with_contacts_keeps_momentum_p0_plus_mgt(preset):
    world = World(falling_cluster(3, speed=0.5, seed=1, accuracy=preset))
    s = world.state
    mass = 1.0 / s.inv_mass
    p0 = (mass[:, None] * s.velocity).sum(axis=0)
    weight = mass.sum() * world.scene.effects.gravity
    worst = 0.0
    for _ in range(120):
        world.step()
        expected = p0 + weight * world.time
        worst = max(worst, float(np.linalg.norm(world.momentum() - expected)
                                 / np.linalg.norm(expected)))
    assert world.stats.collisions > 0                      # the cluster did collide inside
    assert worst < MOMENTUM_RTOL, f'momentum off p0 + M g t by {worst:.3g} (relative)'
