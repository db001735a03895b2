"""The compiled event loop of the exact preset (``physics/event_kernels.py``).

Against closed-form impact times, and against the Python loop it replaced
(``test/event_reference.py``) on random gases: the same impacts at the same
times, bit for bit, and the same state, counters and bookings.
"""

from __future__ import annotations

import heapq
import math

import numpy as np
import pytest

from collision_node.physics import event_kernels as ek
from collision_node.physics.scene import parse_scene
from collision_node.physics.world import World
from event_reference import PythonEventStage


def exact_world(scene: dict, reference: bool = False, particles_per_cell: float = 1.0,
                restitution=None) -> World:
    """Return an exact-preset world recording impacts; ``reference``: the Python loop."""
    w = World(parse_scene(dict(accuracy='exact', **scene), 'test-scene'))
    stage = w.pipeline.stages[0]
    if reference:
        w.pipeline.stages[0] = PythonEventStage(stage.effects, stage.accuracy,
                                                stage._build_fallback, particles_per_cell)
    else:
        stage.particles_per_cell = particles_per_cell
    if restitution is not None:
        w.state.restitution = np.array(restitution, float)
    w.record_impacts(True)
    return w


def gas(count, radius, dimensions=3, dt=0.01, seed=3, walls=True, **effects) -> dict:
    """Return a gas scene in the unit box (walls optional) with extra ``effects``."""
    box = {'min': [0.0] * dimensions, 'max': [1.0] * dimensions}
    if walls:
        effects['walls'] = dict(box, restitution=effects.pop('wall_restitution', 1.0))
    return dict(dimensions=dimensions, dt=dt, effects=effects,
                generate=[{'kind': 'gas', 'count': count, 'radius': radius, 'mass': 1.0,
                           'speed': 1.0, 'seed': seed, 'region': box}])


def assert_same_run(scene: dict, steps: int, particles_per_cell: float,
                    restitution=None) -> World:
    """Run the compiled and the Python loop side by side; assert identical outcomes."""
    compiled = exact_world(scene, False, particles_per_cell, restitution)
    python = exact_world(scene, True, particles_per_cell, restitution)
    for _ in range(steps):
        compiled.step()
        python.step()
        a, b = compiled.take_impacts(), python.take_impacts()
        assert len(a) == len(b)
        for name in a.dtype.names:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    np.testing.assert_array_equal(compiled.state.position, python.state.position)
    np.testing.assert_array_equal(compiled.state.velocity, python.state.velocity)
    for name in ('collisions', 'wall_collisions', 'fallback_steps'):
        assert getattr(compiled.stats, name) == getattr(python.stats, name), name
    assert compiled.stats.dissipated == python.stats.dissipated
    assert compiled.pipeline.stages[0].events == python.pipeline.stages[0].events
    return compiled


# -- against the Python loop ---------------------------------------------------

@pytest.mark.parametrize('particles_per_cell', [8.0, 1.0])
def test_elastic_gas_matches_the_python_loop(particles_per_cell):
    w = assert_same_run(gas(150, 0.03), 40, particles_per_cell)
    assert w.stats.collisions > 50 and w.stats.wall_collisions > 50


def test_planar_gas_under_gravity_matches_the_python_loop():
    w = assert_same_run(gas(60, 0.05, dimensions=2, gravity=[0.0, -0.5], restitution=1.0),
                        60, 1.0)
    assert w.stats.collisions > 50 and w.stats.fallback_steps == 0


def test_inelastic_gas_with_per_particle_restitution_and_threshold_matches():
    """Combine rule (NaN: the scene's e), threshold e = 0, TC model without gravity."""
    rng = np.random.default_rng(5)
    own = np.where(rng.random(120) < 0.5, np.nan, rng.uniform(0.0, 1.0, 120))
    scene = gas(120, 0.035, restitution=0.8, restitution_threshold=0.2, wall_restitution=0.9)
    w = assert_same_run(scene, 40, 1.0, restitution=own)
    assert w.stats.dissipated['restitution'] > 0.0 and w.stats.dissipated['walls'] > 0.0


def test_open_scene_outgrowing_its_cell_table_matches():
    """No walls: the gas spreads far past the cells the table was sized for."""
    w = assert_same_run(gas(80, 0.04, walls=False, dt=0.05), 60, 1.0)
    assert np.ptp(w.state.position, axis=0).max() > 3.0     # well beyond the unit box
    assert w.stats.collisions > 10


def test_static_mirror_in_a_gas_matches():
    scene = gas(50, 0.04)
    scene['particles'] = [{'position': [0.5, 0.5, 0.5], 'radius': 0.1, 'mass': math.inf}]
    scene['generate'][0]['region'] = {'min': [0.0, 0.0, 0.0], 'max': [1.0, 1.0, 0.35]}
    w = assert_same_run(scene, 60, 1.0)
    hits = w.stats.collisions
    assert hits > 0
    np.testing.assert_array_equal(w.state.position[0], [0.5, 0.5, 0.5])


# -- closed forms --------------------------------------------------------------

def test_wall_impacts_at_closed_form_times():
    """One ball in a 1 m box at 1 m/s from x = 0.5, r = 0.1: walls at 0.4 + 0.8 k s."""
    w = exact_world({'dimensions': 2, 'dt': 0.25, 'effects': {
        'walls': {'min': [0, 0], 'max': [1, 1]}},
        'particles': [{'position': [0.5, 0.5], 'velocity': [1.0, 0.0], 'radius': 0.1,
                       'mass': 2.0}]})
    w.step(16)                                         # 4 s: five impacts
    impacts = w.take_impacts()
    np.testing.assert_allclose(impacts['time'], 0.4 + 0.8 * np.arange(5), rtol=1e-14)
    np.testing.assert_array_equal(impacts['j'], -1)
    np.testing.assert_array_equal(impacts['point'][:, 0], [1, 0, 1, 0, 1])
    np.testing.assert_allclose(impacts['normal_impulse'], 2 * 2.0 * 1.0)
    # At t = 4 s it has come back 0.4 m from the last impact at x = 0.9.
    np.testing.assert_allclose(w.state.position[0, :2], [0.5, 0.5], rtol=1e-13)


def test_falling_pair_meets_at_the_straight_line_time():
    """Under g the relative path is straight: gap 1 m closing at 2 m/s, reach 0.5 m."""
    w = exact_world({'dimensions': 3, 'dt': 0.1, 'effects': {'gravity': [0, 0, -9.81]},
                     'particles': [
                         {'position': [-0.5, 0, 0], 'velocity': [1.0, 0, 3.0],
                          'radius': 0.25, 'mass': 1.0},
                         {'position': [0.5, 0, 0], 'velocity': [-1.0, 0, 3.0],
                          'radius': 0.25, 'mass': 1.0}]})
    w.step(5)
    impacts = w.take_impacts()
    assert len(impacts) == 1
    when = 0.25                                        # (1 - 0.5) / 2
    assert impacts['time'][0] == pytest.approx(when, rel=1e-14)
    np.testing.assert_allclose(impacts['point'][0], [0, 0, 3.0 * when - 9.81 * when ** 2 / 2],
                               atol=1e-15)
    np.testing.assert_allclose(impacts['normal'][0], [-1, 0, 0])
    # Elastic and equal masses: they swap x velocities and keep falling together.
    np.testing.assert_allclose(w.state.velocity[:, 0], [-1.0, 1.0], rtol=1e-14)
    np.testing.assert_allclose(w.state.velocity[:, 2], 3.0 - 9.81 * 0.5, rtol=1e-14)


def test_budget_overrun_rolls_back_and_falls_back():
    """More events than the budget: the step is the fallback's, and it is counted."""
    scene = gas(300, 0.03, dt=1.0)           # over 3,000 events in one step
    w = exact_world(scene)
    w.step()
    assert w.stats.fallback_steps == 1
    assert w.pipeline.stages[0].events == 0             # the attempt's events are undone


# -- the heap ------------------------------------------------------------------

def test_heap_pops_by_time_then_push_order_and_compacts_without_reordering():
    rng = np.random.default_rng(2)
    times = rng.integers(0, 50, 400).astype(float)      # many ties
    h_time, h_int = np.empty(512), np.empty((512, 6), dtype=np.int64)
    meta = np.zeros(ek.META_SIZE, dtype=np.int64)
    count = np.zeros(400, dtype=np.int64)
    reference = []
    for k, t in enumerate(times):
        ek.heap_push(h_time, h_int, meta, t, ek.CELL, k, 0, 0, 0)
        heapq.heappush(reference, (t, k))
    count[::3] = 1                                      # a third of the events go stale
    meta[ek.COMPACT_AT] = 0
    h_time, h_int = ek._reserve(h_time, h_int, meta, count, 1)
    assert meta[ek.SIZE] == 400 - len(range(0, 400, 3))
    out, scratch = np.empty(6, dtype=np.int64), np.empty(6, dtype=np.int64)
    while reference:
        t, k = heapq.heappop(reference)
        if k % 3 == 0:
            continue
        assert ek.heap_pop(h_time, h_int, meta, out, scratch) == t
        assert out[ek.H_P] == k
    assert meta[ek.SIZE] == 0


@pytest.mark.parametrize('gap, rate, curvature', [
    (1.0, -2.0, 0.0), (1.0, 2.0, 0.0), (1.0, 0.5, -9.81), (1.0, -0.5, 9.81), (1.0, -3.0, 9.81),
    (0.0, -1.0, 0.0), (0.0, 0.0, -1.0), (-1e-9, 1.0, 0.0), (math.inf, -1.0, -9.81),
    (1e-300, -1e-300, 0.0)])
def test_entering_time_is_the_paths_module_s(gap, rate, curvature):
    from collision_node.physics.paths import entering_time
    expected = entering_time(np.array([gap]), np.array([rate]), np.array([curvature]))[0]
    assert ek.entering(gap, rate, curvature) == expected
