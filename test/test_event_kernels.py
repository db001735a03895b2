"""The compiled event loop of the exact preset (``physics/stages/events/event_kernels.py``).

Against closed-form impact times, and against the Python loop it replaced
(``test/event_reference.py``) on random gases: the same impacts between the
same particles in the same steps, at the same times to round-off, and the
same counters, bookings and state to round-off.

Why round-off and not bits: the compiled loop predicts on another schedule
(a particle keeps its candidates across a cell crossing and predicts only
the new layer of cells; the Python loop re-predicts everything at every
crossing), and an impact time is evaluated from the moment its pair was
predicted, so the last bits of a time can differ. In a gas each impact
amplifies a difference (the dynamics are chaotic), so the runs are
compared over spans where the amplified round-off stays below the bounds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from collision_node.physics.stages.events import event_kernels as ek
from collision_node.physics.law import primitives
from collision_node.physics.model.scene import parse_scene
from collision_node.physics.step.world import World
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


# Bounds on the round-off differences (m, s, m/s; the scenes are about 1 m, 1 m/s).
TIME_TOLERANCE = 1e-10
STATE_TOLERANCE = 1e-9


def in_time_order(impacts: np.ndarray) -> np.ndarray:
    """Return a step's impacts ordered by time, then pair (the loops log ties differently)."""
    return impacts[np.lexsort((impacts['j'], impacts['i'], impacts['time']))]


def assert_same_run(scene: dict, steps: int, particles_per_cell: float,
                    restitution=None) -> World:
    """Run the compiled and the Python loop side by side; assert the same outcomes.

    The same impacts (pairs, walls) in the same steps, their times, points,
    normals and impulses to round-off; the same counters and events; state
    and bookings to round-off. Neither run may fall back.
    """
    compiled = exact_world(scene, False, particles_per_cell, restitution)
    python = exact_world(scene, True, particles_per_cell, restitution)
    for _ in range(steps):
        compiled.step()
        python.step()
        a, b = in_time_order(compiled.take_impacts()), in_time_order(python.take_impacts())
        assert len(a) == len(b)
        np.testing.assert_array_equal(a['i'], b['i'])
        np.testing.assert_array_equal(a['j'], b['j'])
        np.testing.assert_allclose(a['time'], b['time'], rtol=0, atol=TIME_TOLERANCE)
        for name in ('point', 'normal', 'normal_impulse', 'closing_speed'):
            np.testing.assert_allclose(a[name], b[name], rtol=0, atol=STATE_TOLERANCE,
                                       err_msg=name)
    np.testing.assert_allclose(compiled.state.position, python.state.position, rtol=0,
                               atol=STATE_TOLERANCE)
    np.testing.assert_allclose(compiled.state.velocity, python.state.velocity, rtol=0,
                               atol=STATE_TOLERANCE)
    for name in ('collisions', 'wall_collisions', 'fallback_steps'):
        assert getattr(compiled.stats, name) == getattr(python.stats, name), name
    assert compiled.stats.fallback_steps == 0
    assert compiled.stats.dissipated.keys() == python.stats.dissipated.keys()
    for key, value in python.stats.dissipated.items():
        assert compiled.stats.dissipated[key] == pytest.approx(value, rel=1e-12, abs=1e-15)
    assert compiled.pipeline.stages[0].events == python.pipeline.stages[0].events
    return compiled


# -- against the Python loop ---------------------------------------------------

@pytest.mark.parametrize('particles_per_cell', [8.0, 1.0])
def test_elastic_gas_matches_the_python_loop(particles_per_cell):
    w = assert_same_run(gas(150, 0.03), 40, particles_per_cell)
    assert w.stats.collisions > 50 and w.stats.wall_collisions > 50


def test_planar_gas_under_gravity_matches_the_python_loop():
    w = assert_same_run(gas(60, 0.05, dimensions=2, gravity=[0.0, -0.5], restitution=1.0),
                        30, 1.0)
    assert w.stats.collisions > 50 and w.stats.fallback_steps == 0


def test_inelastic_gas_with_per_particle_restitution_and_threshold_matches():
    """Combine rule (NaN: the scene's e), threshold e = 0, TC model without gravity.

    Five steps: in the sixth a pair stopped by the threshold (e = 0) touches
    with a closing speed of round-off size; the Python loop then meets it
    again and again at the same moment without an impulse until its event
    budget ends the step (a fallback), the compiled loop's prediction says
    it meets once more and the TC model parts it.
    """
    rng = np.random.default_rng(5)
    own = np.where(rng.random(120) < 0.5, np.nan, rng.uniform(0.0, 1.0, 120))
    scene = gas(120, 0.035, restitution=0.8, restitution_threshold=0.2, wall_restitution=0.9)
    w = assert_same_run(scene, 5, 1.0, restitution=own)
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


@pytest.mark.parametrize('field', ['position', 'velocity', 'inv_mass', 'radius'])
def test_a_state_changed_between_steps_is_predicted_afresh(field):
    """An in-place change to any particle between steps makes the stage rebuild.

    The stage keeps its particles in cell order; its check reads the world's
    arrays in the world's order, so every particle is compared with its own.
    """
    w = exact_world(gas(200, 0.02, dt=0.01))
    w.step(2)
    stage = w.pipeline.stages[0]
    assert stage._still_valid(w.state)
    moved = np.flatnonzero(stage.order != np.arange(len(w.state)))
    assert moved.size > 100                   # the cell order is not the world's
    for k in moved[::20]:
        values = getattr(w.state, field)
        before = values[k].copy()
        values[k] = np.nextafter(before, np.inf)      # one ulp is a change
        assert not stage._still_valid(w.state)
        values[k] = before
        assert stage._still_valid(w.state)
    # A changed velocity is taken up: the world goes on from it exactly as a
    # fresh world started from the same state.
    w.state.velocity[moved[0]] *= -1.0
    fresh = exact_world(gas(200, 0.02, dt=0.01))
    fresh.state = w.state.copy()
    fresh.pipeline.stages[0].time = stage.time
    w.step(3)
    fresh.step(3)
    np.testing.assert_array_equal(w.state.position, fresh.state.position)
    np.testing.assert_array_equal(w.state.velocity, fresh.state.velocity)


# -- the heap of particles and the candidate lists -------------------------------

def test_heap_keeps_the_earliest_particle_on_top_as_keys_change():
    """Keys rise and fall (many ties): the top is always the least (time, index)."""
    rng = np.random.default_rng(2)
    n = 300
    schedule, heap = ek.new_schedule(n, 0.0), ek.new_heap(n)
    schedule['next_time'] = rng.integers(0, 50, n).astype(float)
    ek.heapify(heap, schedule)
    for _ in range(2000):
        p = int(rng.integers(n))
        schedule['next_time'][p] = float(rng.integers(0, 50)) if rng.random() < 0.9 else math.inf
        ek.heap_update(heap, schedule, p)
        order = heap.particle
        np.testing.assert_array_equal(heap.slot[order], np.arange(n))
        keys = schedule['next_time'][order]
        np.testing.assert_array_equal(heap.key, keys)
        children = np.arange(1, n)
        parents = (children - 1) // 2
        assert np.all((keys[parents] < keys[children])
                      | ((keys[parents] == keys[children]) & (order[parents] < order[children])))
        top = min(range(n), key=lambda k: (schedule['next_time'][k], k))
        assert order[0] == top


def test_a_crowded_particle_refreshes_and_misses_no_impact():
    """More pair candidates than a list holds: the latest become a refresh, none is lost.

    Twelve balls head for a ball at rest at the centre of a box, the first
    eleven each stopped on the way by a static ball in its path (it bounces
    straight back), the twelfth, the slowest, not. The centre ball's first
    prediction finds all twelve impacts (straight paths); its list keeps the
    earliest eight and schedules a refresh at the ninth. That refresh must
    find the twelfth ball, which then strikes it at the closed-form time, as
    the Python loop (which keeps every prediction) says.
    """
    angles = np.linspace(0.0, 2.0 * math.pi, 12, endpoint=False)
    speeds = 1.0 - 0.05 * np.arange(12)
    balls = [{'position': [0.5, 0.5], 'velocity': [0.0, 0.0], 'radius': 0.02, 'mass': 1.0}]
    for a, speed in zip(angles, speeds):
        direction = np.array([math.cos(a), math.sin(a)])
        balls.append({'position': list(0.5 + 0.3 * direction),
                      'velocity': list(-speed * direction), 'radius': 0.02, 'mass': 1.0})
    for a in angles[:11]:
        balls.append({'position': [0.5 + 0.15 * math.cos(a), 0.5 + 0.15 * math.sin(a)],
                      'radius': 0.03, 'mass': math.inf})
    scene = {'dimensions': 2, 'dt': 0.05, 'particles': balls, 'effects': {
        'walls': {'min': [0, 0], 'max': [1, 1], 'restitution': 1.0}}}
    assert 12 > ek.CANDIDATES
    compiled = exact_world(scene, particles_per_cell=40.0)     # one cell: all neighbours
    compiled.step(14)
    impacts = compiled.take_impacts()
    assert compiled.pipeline.stages[0].refreshes >= 1
    centre = impacts[(impacts['i'] == 0) & (impacts['j'] >= 1)]
    assert centre['j'].tolist() == [12]
    assert centre['time'][0] == pytest.approx((0.3 - 0.04) / speeds[11], rel=1e-12)
    assert_same_run(scene, 14, 40.0)


@pytest.mark.parametrize('gap, rate, curvature', [
    (1.0, -2.0, 0.0), (1.0, 2.0, 0.0), (1.0, 0.5, -9.81), (1.0, -0.5, 9.81), (1.0, -3.0, 9.81),
    (0.0, -1.0, 0.0), (0.0, 0.0, -1.0), (-1e-9, 1.0, 0.0), (math.inf, -1.0, -9.81),
    (1e-300, -1e-300, 0.0)])
def test_the_compiled_entering_time_is_the_oracle_s(gap, rate, curvature):
    from oracles.paths import entering_time
    expected = entering_time(np.array([gap]), np.array([rate]), np.array([curvature]))[0]
    assert primitives.entering_time(gap, rate, curvature) == expected
