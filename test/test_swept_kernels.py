"""The compiled swept stage (``swept_kernels.sweep``) against the numpy rounds it replaces.

Both paths of ``SweptContactStage`` run the same scenes from the same
start: random gases with and without gravity, walls, static particles (the
quartic root), per-particle restitution and friction (with spin), the
restitution threshold and resting contact. The compiled step writes each
formula in the numpy order of operations, so positions, velocities, spins
and the recorded impacts must be identical to the bit, except where a
falling particle meets a static one: the quartic's eigenvalues come from
another LAPACK routine (complex in numba, real in numpy), equal after the
Newton steps to a few units in the last place, not to the bit. The
dissipated totals are summed in another order, so they agree to rounding.
"""

from __future__ import annotations

import numpy as np
import pytest

from collision_node import World, parse_scene

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
}


def particles(count, dimensions, static, own, seed):
    """Return random particles; the first ``static`` are static, every third has e and mu."""
    rng = np.random.default_rng(seed)
    side = 0.25 * count ** (1.0 / dimensions)
    out = []
    for k in range(count):
        p = rng.uniform(-side, side, 3)[:dimensions].tolist()
        v = rng.normal(0.0, 2.0, 3)[:dimensions].tolist()
        item = {'position': p, 'velocity': v, 'radius': float(rng.uniform(0.05, 0.1)),
                'mass': float(rng.uniform(0.5, 2.0))}
        if k < static:
            item['mass'] = float('inf')
            item['velocity'] = [0.0] * dimensions
        if own and k % 3 == 0:
            item['restitution'] = float(rng.uniform(0.2, 1.0))
            item['friction'] = 0.3
        out.append(item)
    return out


def run(scene, compiled, steps):
    """Step a world with the compiled or the numpy swept stage; return it and its impacts."""
    world = World(parse_scene(scene, 'test-scene'))
    stages = [s for s in world.pipeline.stages if s.name == 'swept_contacts']
    assert len(stages) == 1
    stages[0].compiled = compiled
    world.record_impacts(True)
    world.step(steps)
    return world, world.take_impacts()


@pytest.mark.parametrize('seed', [0, 1])
@pytest.mark.parametrize('case', list(CASES))
def test_compiled_sweep_matches_numpy_rounds(case, seed):
    """Same positions, velocities, spins and impacts to the bit; same losses to rounding."""
    dimensions, effects, static, own = CASES[case]
    scene = {'dimensions': dimensions, 'dt': 1 / 60, 'accuracy': 'balanced',
             'effects': effects, 'particles': particles(120, dimensions, static, own, seed)}
    fast, fast_impacts = run(scene, True, 40)
    slow, slow_impacts = run(scene, False, 40)
    assert slow.stats.collisions + slow.stats.wall_collisions > 20   # the case has impacts
    quartic = static > 0 and 'gravity' in effects

    def same(actual, desired, name=''):
        if quartic:
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


def test_compiled_sweep_runs_the_balanced_preset():
    """``balanced`` takes the compiled path; its settings are the ones the kernel covers."""
    dimensions, effects, static, own = CASES['gravity']
    world = World(parse_scene({'dimensions': 3, 'dt': 1 / 60, 'accuracy': 'balanced',
                               'effects': effects,
                               'particles': particles(20, 3, 0, False, 0)}, 'test-scene'))
    stage = world.pipeline.stages[0]
    assert stage.name == 'swept_contacts' and stage.compiled
    assert stage.ordering == 'sequential' and stage.drag is None and not stage.requery


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
