"""Resting contact in the ``exact`` preset: supports, curved pair times, what falls back.

Under gravity ``exact`` finds the resting contacts at each step's start,
zeroes their normal speeds (booking the energy), solves their support
forces and moves each supported particle with its own constant
acceleration (``resting_kernels``, ``stages/events/event_driven.py``). A pair whose
accelerations differ meets at the first root of a quartic
(``event_kernels.curved_delay``), checked here against closed forms and
a brute-force search.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from collision_node.physics.stages.events import event_kernels as ek
from collision_node.physics.model.scene import parse_scene
from collision_node.physics.step.world import World

G = 9.81


def exact(particles: list, dimensions: int = 2, dt: float = 1.0 / 240.0, **effects) -> World:
    """Return an exact-preset world under gravity (-y) with a floor at y = 0 unless given."""
    effects.setdefault('gravity', [0.0, -G] + [0.0] * (dimensions - 2))
    effects.setdefault('walls', {'min': [None, 0.0] + [None] * (dimensions - 2)})
    world = World(parse_scene({'accuracy': 'exact', 'dimensions': dimensions, 'dt': dt,
                               'effects': effects, 'particles': particles}, 'resting'))
    world.record_impacts(True)
    return world


def ball(x, y, velocity=(0.0, 0.0), radius=0.05, mass=1.0) -> dict:
    """Return one 2-D particle entry."""
    return {'position': [float(x), float(y)], 'velocity': [float(v) for v in velocity],
            'radius': radius, 'mass': mass}


def stage(world: World):
    """Return the world's event-driven stage."""
    return world.pipeline.stages[0]


# -- the quartic ---------------------------------------------------------------------------

def test_curved_delay_ball_falling_onto_a_held_ball_meets_at_the_parabola_time():
    """Offset 1 m straight up, reach 0.1 m, relative acceleration -g: s = sqrt(2 (1 - 0.1) / g)."""
    s = ek.curved_delay(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -G, 0.0, 0.1, 1.0)
    assert s == pytest.approx(math.sqrt(2.0 * 0.9 / G), rel=1e-13)
    # The same pair beyond the horizon: no impact within it.
    assert ek.curved_delay(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -G, 0.0, 0.1, 0.4) == math.inf


def test_curved_delay_at_contact_and_while_overlapping():
    """Touching and closing: 0. Overlapping and parting but pulled back: when it turns."""
    assert ek.curved_delay(0.0, 0.1, 0.0, 0.0, -1.0, 0.0, 0.0, -G, 0.0, 0.1, 1.0) == 0.0
    # 0.09 m apart (reach 0.1), parting at 0.01 m/s, pulled together at g: it
    # turns at s = 0.01 / g, still overlapping (it rises only 5e-6 m).
    s = ek.curved_delay(0.0, 0.09, 0.0, 0.0, 0.01, 0.0, 0.0, -G, 0.0, 0.1, 1.0)
    assert s == pytest.approx(0.01 / G, rel=1e-12)
    # Parting and never pulled back within the horizon: none.
    assert ek.curved_delay(0.0, 0.09, 0.0, 0.0, 1.0, 0.0, 0.0, -G, 0.0, 0.1, 0.05) == math.inf


def brute_force_delay(d, u, a, reach, horizon, samples=200001) -> float:
    """First sampled time the pair is within reach and closing, refined by bisection."""
    s = np.linspace(0.0, horizon, samples)
    offset = d[None, :] + u[None, :] * s[:, None] + 0.5 * a[None, :] * s[:, None] ** 2
    inside = np.einsum('ij,ij->i', offset, offset) <= reach * reach
    if not inside.any():
        return math.inf
    k = int(np.argmax(inside))
    if k == 0:
        return 0.0
    lo, hi = s[k - 1], s[k]
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        x = d + u * mid + 0.5 * a * mid * mid
        if x @ x > reach * reach:
            lo = mid
        else:
            hi = mid
    return lo


def test_curved_delay_matches_a_brute_force_search_on_random_pairs():
    """300 random pairs in 3-D, 45 of them meeting within the horizon: the same first time."""
    rng = np.random.default_rng(11)
    met = 0
    for _ in range(300):
        d = rng.uniform(-1.0, 1.0, 3)
        d *= rng.uniform(0.12, 0.6) / np.linalg.norm(d)
        u = -d / np.linalg.norm(d) * rng.uniform(0.0, 2.0) + rng.normal(0.0, 0.5, 3)
        a = rng.normal(0.0, 10.0, 3)
        expected = brute_force_delay(d, u, a, 0.1, 0.5)
        got = ek.curved_delay(*d, *u, *a, 0.1, 0.5)
        if expected == math.inf:
            # A graze the samples step over (between two samples) is the only other outcome.
            if got != math.inf:
                x = d + u * got + 0.5 * a * got * got
                assert np.linalg.norm(x) == pytest.approx(0.1, rel=1e-9)
            continue
        met += 1
        assert got == pytest.approx(expected, abs=1e-12)
    assert met >= 40


# -- supports ------------------------------------------------------------------------------

def test_ball_sliding_on_a_floor_strikes_a_resting_ball_exactly_without_fallback():
    """Pool table: equal balls resting on the floor; one slides at 1 m/s into the other.

    Both are held by the floor (acceleration 0), so the pair meets on a
    straight line at (0.5 - 0.1) / 1 s, the struck ball leaves at 1 m/s
    and neither leaves the floor: exact, no fallback.
    """
    r = 0.05
    world = exact([ball(0.0, r, (1.0, 0.0)), ball(0.5, r)], dt=1.0 / 60.0)
    world.step(60)
    impacts = world.take_impacts()
    pairs = impacts[impacts['j'] >= 0]
    assert len(pairs) == 1
    assert pairs['time'][0] == pytest.approx(0.4, rel=1e-13)
    np.testing.assert_allclose(world.state.velocity, [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
                               atol=1e-14)
    np.testing.assert_array_equal(world.state.position[:, 1], r)
    assert world.stats.fallback_steps == 0
    assert stage(world).supported_steps == 60


def test_slow_landing_is_zeroed_and_its_energy_booked_to_the_wall():
    """A ball touching the floor, closing at 0.01 m/s (below 2 g dt): resting.

    Its normal speed is set to 0 at the step's start, which removes
    m v^2 / 2 = 5e-5 J, booked to the walls; it then stays on the floor.
    """
    world = exact([ball(0.3, 0.05, (0.2, -0.01), mass=1.0)])
    before = world.energy()['total']
    world.step(24)
    assert world.state.velocity[0, 1] == 0.0
    assert world.state.velocity[0, 0] == 0.2
    assert world.state.position[0, 1] == 0.05
    assert world.stats.dissipated['walls'] == pytest.approx(0.5 * 0.01 ** 2, rel=1e-12)
    assert world.energy()['total'] == pytest.approx(before - 0.5 * 0.01 ** 2, rel=1e-12)
    assert world.stats.fallback_steps == 0


def test_column_sits_still_and_the_supports_carry_the_weight():
    """Five balls of 1, 2, 3, 4, 5 kg stacked on a floor: every acceleration is 0.

    The support forces are the weights above each contact: the floor
    carries 15 g N; solved from cold, then warm (one sweep).
    """
    r = 0.05
    world = exact([ball(0.0, r + 2 * r * k, mass=k + 1.0) for k in range(5)])
    world.step()
    supports = stage(world)._supports
    np.testing.assert_allclose(supports.acceleration[:, :2], 0.0, atol=1e-9)
    assert supports.supported.tolist() == [1] * 5
    assert supports.wall_mask[0] == 1 << 2               # the floor: axis 1, low side
    floor = stage(world)._old_partner[0].tolist().index(-2 - 2)
    assert stage(world)._old_force[0, floor] == pytest.approx(15.0 * G, rel=1e-10)
    world.step(10)
    # Warm: one over-relaxed sweep, one plain.
    assert stage(world).resting_info['force_sweeps'] == 2
    np.testing.assert_allclose(stage(world)._supports.acceleration[:, :2], 0.0, atol=1e-9)
    assert np.abs(world.state.velocity).max() < 1e-12
    assert world.stats.fallback_steps == 0


def test_ball_dropped_on_a_resting_ball_falls_back_only_while_it_lands():
    """A ball dropped 0.2 m onto a ball resting on the floor (e = 0).

    The impact would change the lower ball's support: that step (and the
    held ones after it) go to the step solver, counted; once the two rest
    stacked, every step is event-driven again. Energy never rises in an
    event-driven step (the step solver's own bound is hard case 7's; it
    lifted this pair out of overlap with 8.5e-10 of the energy more than
    the step's losses, measured).
    """
    r = 0.05
    world = exact([ball(0.0, r), ball(0.0, 3 * r + 0.2)], restitution=0.0)
    start = previous = world.energy()['total']
    landed = math.sqrt(2 * 0.2 / G)
    for _ in range(240):
        fallbacks = world.stats.fallback_steps
        world.step()
        total = world.energy()['total']
        if world.stats.fallback_steps == fallbacks:
            assert total <= previous + 1e-12 * abs(previous)
        previous = total
        if world.time < landed - world.dt:
            assert world.stats.fallback_steps == 0
    assert 1 <= world.stats.fallback_steps <= 16
    assert previous < start
    settled = world.stats.fallback_steps
    world.step(60)
    assert world.stats.fallback_steps == settled
    assert np.abs(world.state.velocity).max() < 1e-9
    np.testing.assert_allclose(world.state.position[:, 0], 0.0, atol=1e-12)


def test_bouncing_ball_bounces_exactly_then_comes_to_rest_on_the_floor():
    """A ball of e = 0.5 dropped from 0.5 m: first impacts exact, then it rests.

    The bounces shrink geometrically until the collapse regime hands a few
    steps to the step solver; after that the ball rests and no step falls
    back.
    """
    world = exact([ball(0.0, 0.55)], restitution=0.5,
                  walls={'min': [None, 0.0], 'restitution': 0.5})
    world.step(240)
    impacts = world.take_impacts()
    assert impacts['time'][0] == pytest.approx(math.sqrt(2 * 0.5 / G), rel=1e-12)
    assert impacts['closing_speed'][1] == pytest.approx(0.5 * math.sqrt(2 * G * 0.5), rel=1e-12)
    settled = world.stats.fallback_steps
    assert settled <= 16
    world.step(120)
    assert world.stats.fallback_steps == settled
    assert world.state.velocity[0, 1] == 0.0
    assert world.state.position[0, 1] == pytest.approx(0.05, abs=1e-6)
