"""Property-based fuzzing of whole steps: random small scenes, invariants after every step.

Scenes: 2 to 8 particles in 2-D or 3-D, radii over 1.5 orders of
magnitude, masses over 12 (and static ones), speeds over 9 (aimed mostly
inwards so that impacts happen), any subset of the effects (walls with
their restitution, particle restitution, gravity in any direction from 0.1
to 30 m/s^2, friction, linear and quadratic drag; the event preset gets
the ones it simulates), any accuracy preset, dt from 1e-4 to 1e-2 s.
Invariants after every step:

- every position and velocity is finite; static particles never move;
  a 2-D scene stays in the z = 0 plane;
- momentum is conserved when nothing external acts (no walls, gravity,
  drag or static particles): to 1e-12 of the sum of |m v|;
- total energy (kinetic, rotational and gravitational potential) never
  increases (all e <= 1): by at most 1e-12 of the kinetic energy plus
  each particle's |m g . x|, plus, under gravity, m |g| times the deepest
  overlap left by the step before, summed over the particles (separation
  restoring height that an earlier step lost to overlap: found by the
  fuzzer, 2.7e-8 J when two balls came to rest on a floor);
- starting without overlap and without static particles, no overlap ever
  exceeds three steps of closing travel, 6 v_max dt (v_max: the largest
  speed seen so far): one step for a pair; squeezes of a small ball whose
  contacts alternate reached 1.33 and 2.16 steps in the deep search (kept
  as examples). The bound is empirical: see docs/stability.md.
  With static particles this is a documented limitation (a light ball
  pressed into a static one by a heavy one is overrun, see
  docs/stability.md and test_case09_ball_pressed_against_a_static_ball_*).

CI runs the ``fast`` profile (derandomized); the deep search is
``HYPOTHESIS_PROFILE=deep python -m pytest test/test_fuzz.py`` (see
docs/stability.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, event, example, given, strategies as st

from collision_node import World, parse_scene
from collision_node.physics.model.accuracy import PRESETS
from conftest import HYPOTHESIS_PROFILE
from test_hard_cases import max_penetration

STEPS = 200 if HYPOTHESIS_PROFILE == 'deep' else 30
ENERGY_TOLERANCE = 1e-12
OVERLAP_STEPS = 3.0          # overlap bound, in steps of closing travel 2 v_max dt
MOMENTUM_TOLERANCE = 1e-12
BOX = 0.6


def log_uniform(low_exponent: float, high_exponent: float):
    """Return a strategy for 10**u with u uniform in [low, high]."""
    return st.floats(low_exponent, high_exponent).map(lambda u: float(10.0 ** u))


@st.composite
def effects_subsets(draw, dimensions: int, event_mode: bool) -> dict:
    """Draw any subset of the effects (event mode: those it simulates)."""
    effects = {}
    if draw(st.booleans()):
        walls = {'min': [-BOX - 0.4] * dimensions, 'max': [BOX + 0.4] * dimensions}
        if draw(st.booleans()):
            walls['restitution'] = draw(st.floats(0.0, 1.0))
        effects['walls'] = walls
    if draw(st.booleans()):
        effects['restitution'] = draw(st.floats(0.0, 1.0))
    if draw(st.integers(0, 2)) == 0:
        # Any direction, 0.1 to 30 m/s^2.
        direction = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(dimensions)])
        direction[-1] -= 0.5                       # mostly down
        length = float(np.linalg.norm(direction))
        if length < 1e-3:                          # about the zero vector: straight down
            direction, length = np.eye(dimensions)[-1] * -1.0, 1.0
        direction /= length
        effects['gravity'] = (draw(log_uniform(-1.0, 1.5)) * direction).tolist()
    if not event_mode:
        if draw(st.integers(0, 3)) == 0:
            effects['friction'] = draw(st.floats(0.0, 1.0))
        if draw(st.integers(0, 3)) == 0:
            effects['drag'] = {'linear': draw(log_uniform(-4.0, 0.0)),
                               'quadratic': draw(st.sampled_from([0.0, 0.01, 0.1]))}
    return effects


@st.composite
def scenes(draw) -> dict:
    """Draw a small random scene mapping (as a scene file would hold it)."""
    dimensions = draw(st.sampled_from([2, 3]))
    count = draw(st.integers(2, 8))
    dt = draw(log_uniform(-4.0, -2.0))
    accuracy = draw(st.sampled_from(sorted(PRESETS)))
    event_mode = PRESETS[accuracy].mode == 'event'
    effects = draw(effects_subsets(dimensions, event_mode))
    coordinate = st.floats(-BOX, BOX)
    particles = []
    for _ in range(count):
        position = np.array([draw(coordinate) for _ in range(dimensions)])
        # Mostly towards the middle, so that impacts happen within the run: the
        # distance covered over the run is drawn, from 0.1 to 3 box widths, and
        # one particle in four is slowed by up to 6 orders of magnitude.
        inward = -position / max(float(np.linalg.norm(position)), 1e-9)
        direction = inward + np.array([draw(st.floats(-0.3, 0.3)) for _ in range(dimensions)])
        direction /= max(float(np.linalg.norm(direction)), 1e-9)
        speed = draw(log_uniform(-1.0, np.log10(6.0 * BOX))) / (STEPS * dt)
        if draw(st.integers(0, 3)) == 0:
            speed *= draw(log_uniform(-6.0, 0.0))
        static = draw(st.integers(0, 5)) == 0    # one in six is static
        particles.append({
            'position': position.tolist(),
            'velocity': [0.0] * dimensions if static else (speed * direction).tolist(),
            'radius': draw(log_uniform(-2.0, -0.5)),
            'mass': float('inf') if static else draw(log_uniform(-6.0, 6.0)),
        })
    return {'dimensions': dimensions, 'dt': dt, 'accuracy': accuracy, 'effects': effects,
            'particles': particles}


def overlapping(world: World) -> bool:
    """Say whether any two particles overlap."""
    return max_penetration(world) > 0.0


# Found by the deep profile: a ball driven into a wall by a 10 times heavier one
# (e = 0) was overrun a little more every step, until separation learnt that a
# wall holds what it pushes into.
PRESSED_AGAINST_A_WALL = {
    'dimensions': 2, 'dt': 0.01, 'accuracy': sorted(PRESETS)[0],
    'effects': {'walls': {'min': [-1.0, -1.0], 'max': [1.0, 1.0]}, 'restitution': 0.0},
    'particles': [{'position': [-0.65, 0.0], 'velocity': [-0.5, 0.0], 'radius': 0.1, 'mass': 10.0},
                  {'position': [-0.9, 0.0], 'radius': 0.1, 'mass': 1.0}]}


# Found next: a 1e-6 kg ball driven into a static ball by a 1 kg one at 50 m/s
# (the overlap part is a documented limitation; the rest must hold).
PRESSED_AGAINST_A_STATIC_BALL = {
    'dimensions': 2, 'dt': 1e-4, 'accuracy': sorted(PRESETS)[0], 'effects': {},
    'particles': [{'position': [-0.6, 0.0], 'velocity': [50.0, 0.0], 'radius': 0.01, 'mass': 1.0},
                  {'position': [0.3726, 0.0], 'radius': 0.01, 'mass': float('inf')},
                  {'position': [0.0, 0.0], 'radius': 0.272, 'mass': 1e-6}]}


# Found by the deep profile once gravity joined the effects: a ball reflected
# while overlapping a static one, then lifted out of it by separation, gained
# m g times the overlap (5.3e-4 J) at each elastic bounce.
BOUNCE_ON_A_STATIC_BALL = {
    'dimensions': 3, 'dt': 0.01, 'accuracy': 'accurate',
    'effects': {'gravity': [0.0, 0.0, -1.0], 'friction': 0.0},
    'particles': [{'position': [0.0, 0.0, 0.25], 'radius': 0.1, 'mass': float('inf')},
                  {'position': [0.0, 0.0, 0.0], 'radius': 0.1, 'mass': float('inf')},
                  {'position': [0.0, 0.0, 0.5], 'velocity': [0.0, 0.0, -0.5], 'radius': 0.1,
                   'mass': 1.0}]}


# And next: the ball glancing off a static one is still falling after the
# impulse; it must pay for its lift from its speed along the push too.
GLANCING_OFF_A_STATIC_BALL = {
    'dimensions': 3, 'dt': 0.01, 'accuracy': 'accurate', 'effects': {'gravity': [0.0, 0.0, -1.0]},
    'particles': [{'position': [0.0, 0.0, 0.0], 'radius': 0.1, 'mass': float('inf')},
                  {'position': [0.0, 0.0, 0.5], 'radius': 0.1, 'mass': float('inf')},
                  {'position': [0.0, 0.5625, 0.5], 'radius': 0.31622776601683794, 'mass': 1.0,
                   'velocity': [0.0, -0.3737046593418299, -0.33218191941495995]}]}


# And then: two balls coming to rest on a floor. The sweeps left them sinking
# at the solver's tolerance and separation lifted them back each step (fixed:
# shock passes finish at tolerance 0); the projection also restores overlap
# left by the step before (the stated allowance above).
TWO_BALLS_COME_TO_REST_ON_A_FLOOR = {
    'dimensions': 3, 'dt': 0.01, 'accuracy': 'accurate',
    'effects': {'walls': {'min': [-1.0, -1.0, -1.0], 'max': [1.0, 1.0, 1.0], 'restitution': 0.0},
                'gravity': [0.0, 0.0, -1.0]},
    'particles': [{'position': [0.0, 0.0, 0.0], 'radius': 0.1, 'mass': 1.0},
                  {'position': [0.0, 0.0, 0.5], 'velocity': [0.0, 0.0, -0.5], 'radius': 0.1,
                   'mass': 1.0}]}


# Found by the deep profile: a 1 cm ball squeezed in a converging column (e = 0)
# reaches 1.33 steps of closing travel before the column resolves.
SQUEEZED_COLUMN = {
    'dimensions': 2, 'dt': 0.01, 'accuracy': sorted(PRESETS)[0],
    'effects': {'restitution': 0.0},
    'particles': [{'position': [0.0, y], 'velocity': [0.0, v], 'radius': r, 'mass': m}
                  for y, v, r, m in [(0.5, -0.5, 0.1, 1.0), (0.0, 0.0, 0.1, 1.0),
                                     (-0.5, 0.5, 0.1, 1.0), (0.125, -0.5, 0.01, 0.1),
                                     (0.25, -0.5, 0.1, 1.0)]]}


# And deeper: three balls closing on a 2.4 cm one (e = 0) reach 2.16 steps.
SQUEEZED_STAR = {
    'dimensions': 2, 'dt': 0.01, 'accuracy': sorted(PRESETS)[0],
    'effects': {'restitution': 0.0},
    'particles': [{'position': p, 'velocity': v, 'radius': r, 'mass': m}
                  for p, v, r, m in [([0.0, 0.0], [0.0, 0.0], 0.023713737056616554, 0.1),
                                     ([0.125, 0.0], [-0.5, 0.0], 0.1, 1.0),
                                     ([0.0, 0.5], [0.0, -0.5], 0.1, 1.0),
                                     ([-0.125, 0.0], [0.5, 0.0], 0.01, 1.0)]]}


# Found by the deep profile (e = 0, gravity at 1 m/s^2 pointing into a column of five
# static balls): the ball slides over a static ball's curved surface, and per substep
# separation lifted it by m g_n times an overlap of dt^2 (g_n - v_t^2 / R) / 2 while
# the solve removed only the approach speed dt (g_n - v_t^2 / R), whose energy is
# smaller by dt^2 (g_n - v_t^2 / R) v_t^2 / R / 2 (2.1e-7 J at step 45, then about
# 2e-6 J a step). Fixed: a lift no loss or speed pays is not made.
SLIDING_OVER_A_STATIC_COLUMN = {
    'dimensions': 2, 'dt': 0.01, 'accuracy': 'accurate',
    'effects': {'restitution': 0.0, 'gravity': [0.8944271909999159, -0.4472135954999579]},
    'particles': [{'position': [0.0, y], 'radius': 0.1, 'mass': float('inf')}
                  for y in (-0.5, -0.25, 0.0, 0.25, 0.5)]
    + [{'position': [-0.5, 0.0], 'velocity': [0.5, 0.0], 'radius': 0.1, 'mass': 1.0}]}


@given(scenes())
@example(SLIDING_OVER_A_STATIC_COLUMN)
@example(SQUEEZED_STAR)
@example(BOUNCE_ON_A_STATIC_BALL)
@example(GLANCING_OFF_A_STATIC_BALL)
@example(TWO_BALLS_COME_TO_REST_ON_A_FLOOR)
@example(SQUEEZED_COLUMN)
@example(PRESSED_AGAINST_A_WALL)
@example(PRESSED_AGAINST_A_STATIC_BALL)
def test_fuzz_invariants_hold_after_every_step(scene):
    world = World(parse_scene(scene, 'fuzz'))
    assume(not overlapping(world))
    s = world.state
    static = ~s.dynamic
    static_position = s.position[static].copy()
    external = {'walls', 'gravity', 'drag'} & set(scene['effects'])
    isolated = not external and not static.any()
    gravity = np.zeros(3)
    gravity[:scene['dimensions']] = scene['effects'].get('gravity', [0.0] * scene['dimensions'])
    dt = world.dt
    fastest = 0.0
    for step in range(STEPS):
        fastest = max(fastest, float(np.max(np.linalg.norm(s.velocity, axis=1))))
        before = world.energy()
        # What rounding acts on: kinetic energy plus each particle's |potential|.
        dynamic = s.dynamic
        energy_scale = (before['kinetic_linear'] + before['kinetic_rotational']
                        + float(np.sum(np.abs(s.position[dynamic] @ gravity)
                                       / s.inv_mass[dynamic])))
        # Separation may restore height that earlier steps lost to overlap: at most
        # m |g| times the deepest overlap left at the start of this step, per particle.
        restore = (max_penetration(world) * float(np.linalg.norm(gravity))
                   * float(np.sum(1.0 / s.inv_mass[dynamic])))
        momentum = world.momentum()
        momentum_scale = float(np.sum(np.linalg.norm(s.velocity[~static], axis=1)
                                      / s.inv_mass[~static]))
        world.step()
        s = world.state
        where = f'step {step + 1}'
        assert np.isfinite(s.position).all() and np.isfinite(s.velocity).all(), where
        np.testing.assert_array_equal(s.position[static], static_position, err_msg=where)
        if scene['dimensions'] == 2:
            np.testing.assert_array_equal(s.position[:, 2], 0.0, err_msg=where)
            np.testing.assert_array_equal(s.velocity[:, 2], 0.0, err_msg=where)
        after = world.energy()
        assert after['total'] <= before['total'] + ENERGY_TOLERANCE * energy_scale + restore, where
        if isolated:
            drift = np.max(np.abs(world.momentum() - momentum))
            assert drift <= MOMENTUM_TOLERANCE * momentum_scale, where
        if not static.any():
            assert max_penetration(world) <= OVERLAP_STEPS * 2.0 * fastest * dt + 1e-15, where
    event(f'collisions: {"none" if world.stats.collisions == 0 else "some"}')


@pytest.mark.parametrize('accuracy', sorted(PRESETS))
def test_ball_sliding_over_a_static_column_never_gains_energy(accuracy):
    """The found scene, past the step it failed at, held to rounding alone.

    No allowance for restored overlap: total energy never rises by more than
    1e-12 of itself in a step. The lift the losses cannot pay is left as
    overlap instead (measured over 100 steps: at most 0.30 mm `fast`,
    0.28 mm `balanced`, 0.07 mm `accurate`, 3e-6 m `exact`, of a 0.1 m ball).
    """
    world = World(parse_scene(dict(SLIDING_OVER_A_STATIC_COLUMN, accuracy=accuracy), 'fuzz'))
    previous = world.energy()['total']
    deepest = 0.0
    for step in range(100):
        world.step()
        total = world.energy()['total']
        assert total <= previous + 1e-12 * abs(previous), f'step {step + 1}'
        previous = total
        deepest = max(deepest, max_penetration(world))
    assert world.stats.collisions > 0
    assert deepest <= 1e-3
