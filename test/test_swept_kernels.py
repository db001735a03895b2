"""The compiled swept stage (``swept_kernels.sweep``) against its numpy rounds.

The rounds are ``test/swept_reference.py``.

Both run the same scenes from the same start: random gases with and
without gravity, walls, static particles (the quartic root), per-particle
restitution and friction (with spin), the restitution threshold and
resting contact, drag, at the sequential (``balanced``), requery
(``accurate``) and batched orderings. The compiled step writes each formula
in the numpy order of operations, so positions, velocities, spins and the
recorded impacts must be identical to the bit, except where a falling
particle meets a static one (the quartic's eigenvalues come from another
LAPACK routine) and with drag (libm's exponentials, not numpy's vector
loops): there they agree to a few units in the last place. The dissipated
totals are summed in another order, so they agree to rounding.
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World, parse_scene
from swept_reference import use_reference

BOX3 = {'min': [-3, -3, -3], 'max': [3, 3, 3], 'restitution': 0.8}
BOX2 = {'min': [-3, -3], 'max': [3, 3], 'restitution': 0.8}
CASES = {
    'elastic_gas': (3, {'walls': dict(BOX3, restitution=1.0), 'restitution': 1.0}, 0, False),
    'open_gas': (3, {'restitution': 0.9}, 0, False),
    'gravity': (3, {'walls': BOX3, 'restitution': 0.7, 'gravity': [0, -9.81, 0]}, 0, False),
    'static_spheres': (3, {'walls': BOX3, 'restitution': 0.9, 'gravity': [0, -9.81, 0]}, 10,
                       False),
    'friction_3d': (3, {'walls': BOX3, 'restitution': 0.5, 'gravity': [0, -9.81, 0],
                        'friction': 0.5}, 5, True),
    'pile_2d': (2, {'walls': BOX2, 'restitution': 0.3, 'gravity': [0, -9.81, 0],
                    'friction': 0.5}, 5, True),
    'threshold': (3, {'walls': BOX3, 'restitution': 0.9, 'restitution_threshold': 0.5}, 0,
                  True),
    'drag': (3, {'walls': BOX3, 'restitution': 0.9, 'drag': {'linear': 0.5, 'quadratic': 0.2}},
             0, False),
    'drag_gravity': (2, {'walls': BOX2, 'restitution': 0.6, 'gravity': [0, -9.81, 0],
                         'drag': {'linear': 0.3}}, 0, True),
    # Every eighth particle 15 times faster: impacts send slow particles far out
    # of their swept balls, so requery adds pairs.
    'bullets': (3, {'walls': dict(BOX3, restitution=1.0), 'restitution': 1.0}, 0, False),
    'bullets_friction': (3, {'walls': BOX3, 'restitution': 0.9, 'friction': 0.3}, 0, True),
    'bullets_gravity': (3, {'walls': BOX3, 'restitution': 0.8, 'gravity': [0, -9.81, 0]}, 0,
                        False),
    # Packed into a fifth of the side: particles start overlapping, so impacts
    # at the same instant share particles (batched shares their impulses).
    'dense': (3, {'walls': BOX3, 'restitution': 0.9}, 0, False),
    'dense_2d': (2, {'walls': BOX2, 'restitution': 0.7, 'gravity': [0, -9.81, 0]}, 0, False),
}
FAST = ('bullets', 'bullets_friction', 'bullets_gravity')
DENSE = ('dense', 'dense_2d')
# The sequential rounds, requery (with four substeps) and batched ordering.
ACCURACY = {'balanced': 'balanced', 'accurate': 'accurate',
            'batched': {'preset': 'balanced', 'ordering': 'batched'}}


def particles(count, dimensions, static, own, seed, case=''):
    """Return random particles; the first ``static`` are static, every third has e and mu.

    In the FAST cases every eighth particle moves 15 times faster; the
    DENSE cases are packed into a fifth of the side.
    """
    rng = np.random.default_rng(seed)
    side = 0.25 * count ** (1.0 / dimensions) * (0.2 if case in DENSE else 1.0)
    fast = case in FAST
    out = []
    for k in range(count):
        p = rng.uniform(-side, side, 3)[:dimensions].tolist()
        v = (rng.normal(0.0, 2.0, 3) * (15.0 if fast and k % 8 == 0 else 1.0))[:dimensions]
        item = {'position': p, 'velocity': v.tolist(), 'radius': float(rng.uniform(0.05, 0.1)),
                'mass': float(rng.uniform(0.5, 2.0))}
        if k < static:
            item['mass'] = float('inf')
            item['velocity'] = [0.0] * dimensions
        if own and k % 3 == 0:
            item['restitution'] = float(rng.uniform(0.2, 1.0))
            item['friction'] = 0.3
        out.append(item)
    return out


def scene_of(case, accuracy, seed):
    """Return the scene of ``case`` at ``accuracy`` (the FAST cases at a longer step)."""
    dimensions, effects, static, own = CASES[case]
    return {'dimensions': dimensions, 'dt': 1 / 15 if case in FAST else 1 / 60,
            'accuracy': ACCURACY[accuracy], 'effects': effects,
            'particles': particles(120, dimensions, static, own, seed, case)}


def run(scene, reference, steps):
    """Step a world with the compiled stage or its numpy rounds; return it and its impacts."""
    world = World(parse_scene(scene, 'test-scene'))
    if reference:
        use_reference(world)
    world.record_impacts(True)
    world.step(steps)
    return world, world.take_impacts()


@pytest.mark.parametrize('seed', [0, 1])
@pytest.mark.parametrize('accuracy', list(ACCURACY))
@pytest.mark.parametrize('case', list(CASES))
def test_compiled_sweep_matches_numpy_rounds(case, accuracy, seed):
    """Same positions, velocities, spins and impacts to the bit; same losses to rounding."""
    scene = scene_of(case, accuracy, seed)
    _, effects, static, _ = CASES[case]
    close = (static > 0 and 'gravity' in effects) or 'drag' in effects
    # Where the two round differently (close), a packed pile under gravity grows the
    # difference step by step (drag_gravity: 2e-14 m/s at 20 steps, 2e-13 at 30), and past
    # that a discrete choice of the resting-contact rules (a support level, a cold
    # contact's seed) may flip (3e-4 m/s at 40 steps): those cases compare at 30 steps.
    steps = 30 if close else 40
    fast, fast_impacts = run(scene, False, steps)
    slow, slow_impacts = run(scene, True, steps)
    assert slow.stats.collisions + slow.stats.wall_collisions > 20   # the case has impacts

    def same(actual, desired, name=''):
        if close:
            np.testing.assert_allclose(actual, desired, rtol=1e-9, atol=1e-9, err_msg=name)
        else:
            np.testing.assert_array_equal(actual, desired, err_msg=name)
    same(fast.state.position, slow.state.position)
    same(fast.state.velocity, slow.state.velocity)
    if slow.state.angular_velocity is not None:
        same(fast.state.angular_velocity, slow.state.angular_velocity)
    assert fast.stats.collisions == slow.stats.collisions
    assert fast.stats.wall_collisions == slow.stats.wall_collisions
    assert fast_impacts.dtype == slow_impacts.dtype and len(fast_impacts) == len(slow_impacts)
    for field in slow_impacts.dtype.names:
        same(fast_impacts[field], slow_impacts[field], field)
    assert fast.stats.dissipated.keys() == slow.stats.dissipated.keys()
    for effect, value in slow.stats.dissipated.items():
        assert fast.stats.dissipated[effect] == pytest.approx(value, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize('dimensions', [2, 3])
def test_in_contact_kernel_matches_numpy_formula(dimensions):
    """The compiled resting-contact marks equal the numpy expressions, entry by entry."""
    from collision_node.physics.stages.swept.swept_contacts import TOUCH_SLOP
    from collision_node.physics.stages.swept.swept_kernels import in_contact
    rng = np.random.default_rng(3)
    n = 400
    radius = rng.uniform(0.05, 0.1, n)
    x = rng.uniform(-1.0, 1.0, (n, 3))
    if dimensions == 2:
        x[:, 2] = 0.0
    a = rng.integers(0, n, 600)
    b = rng.integers(0, n, 600)
    # Pairs exactly in contact, just inside and just outside the slop.
    direction = rng.normal(size=(200, 3))
    direction[:, dimensions:] = 0.0
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    reach = radius[a[:200]] + radius[b[:200]]
    scale = 1.0 + TOUCH_SLOP * rng.choice([-1.0, 0.0, 0.999, 1.001, 2.0], 200)
    x[b[:200]] = x[a[:200]] + direction * (reach * scale)[:, None]
    low = np.array([-1.0, -1.0, -np.inf])
    high = np.array([1.0, np.inf, 1.0])
    x[:50, 0] = low[0] + radius[:50] * (1.0 + TOUCH_SLOP * rng.choice([-1.0, 0.5, 1.5], 50))
    x[50:100, 0] = high[0] - radius[50:100] * (1.0 + TOUCH_SLOP * rng.choice([0.5, 1.5], 50))
    x[100, 1] = np.nan
    pairs = np.empty(a.size, dtype=bool)
    walls = np.empty((n, 2 * dimensions), dtype=bool)
    in_contact(x, radius, a, b, TOUCH_SLOP, True, low, high, dimensions, pairs, walls)
    expected_pairs = np.linalg.norm(x[a] - x[b], axis=1) - (radius[a] + radius[b]) <= \
        TOUCH_SLOP * (radius[a] + radius[b])
    p, r = x[:, :dimensions], radius[:, None]
    expected_walls = np.empty_like(walls)
    with np.errstate(invalid='ignore'):
        expected_walls[:, 0::2] = p - (low[:dimensions] + r) <= TOUCH_SLOP * r
        expected_walls[:, 1::2] = (high[:dimensions] - r) - p <= TOUCH_SLOP * r
    assert np.array_equal(pairs, expected_pairs)
    assert np.array_equal(walls, expected_walls)
    assert 20 < pairs.sum() < 200 and 20 < walls[:, 0:2].sum() < 100   # both outcomes occur


def test_the_cases_reach_requery_and_shared_impacts(monkeypatch):
    """In the cases compared above requery adds pairs and batched rounds share particles."""
    import swept_reference
    added, shared = [], []
    new_pairs, shared_scale = swept_reference._Escapes.new_pairs, swept_reference.shared_scale

    def counting_new_pairs(self, *args):
        extra = new_pairs(self, *args)
        added.append(extra[0].size)
        return extra

    def counting_shared_scale(*args):
        scale = shared_scale(*args)
        shared.append(int(np.count_nonzero(scale < 1.0)))
        return scale
    monkeypatch.setattr(swept_reference._Escapes, 'new_pairs', counting_new_pairs)
    monkeypatch.setattr(swept_reference, 'shared_scale', counting_shared_scale)
    for case in FAST + DENSE:
        for accuracy in ('accurate', 'batched'):
            run(scene_of(case, accuracy, 0), True, 40)
    assert sum(added) > 0 and sum(shared) > 0
