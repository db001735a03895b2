"""Sleeping islands: a settled pile sleeps, stays put, and wakes when touched."""

import numpy as np
import pytest

from collision_node.physics.model.accuracy import parse_accuracy
from collision_node.physics.model.world_commands import impulse_request, teleport_request
from collision_node.physics.model.scene import load_scene, parse_scene
from collision_node.physics.stages.sleeping.sleep import sleep_speed
from collision_node.physics.model.validation import SceneError
from collision_node.physics.step.world import World


def _pile(preset='fast', **settings):
    """Return a world of the shipped pile under ``preset`` (plus settings)."""
    scene = load_scene('pile')
    return World(scene.with_accuracy(parse_accuracy(dict(preset=preset, **settings), 'test')))


@pytest.fixture(scope='module')
def sleeping_pile():
    """Return the shipped pile under fast, stepped until its one island sleeps."""
    world = _pile()
    for _ in range(720):
        world.step()
        if world.asleep_count == len(world.state):
            return world
    raise AssertionError(f'pile did not fall asleep: {world.asleep_count} of 240 asleep')


def _balance_scale(world):
    """Return a yardstick for the energy balance error: the energies involved, J."""
    report = world.energy()
    return abs(report['start']) + abs(report['potential']) + sum(
        abs(v) for v in report['dissipated'].values())


def test_settled_pile_falls_asleep_and_does_not_move(sleeping_pile):
    world = sleeping_pile
    s = world.state
    assert world.asleep_count == 240
    assert np.all(s.velocity == 0.0) and np.all(s.angular_velocity == 0.0)
    # One island for the pile; a disc that came to rest apart (touching no other
    # disc within the sleep stage's 2 % of r) is an island of its own.
    pile = np.bincount(s.island).argmax()
    for p in np.flatnonzero(s.island != pile):
        gaps = np.linalg.norm(s.position - s.position[p], axis=1) - (s.radius + s.radius[p])
        gaps[p] = np.inf
        assert gaps.min() > 0.02 * s.radius[p]
        assert np.count_nonzero(s.island == s.island[p]) == 1
    position = s.position.copy()
    report = world.energy()
    world.step(60)
    assert np.array_equal(world.state.position, position)
    assert np.all(world.state.velocity == 0.0)
    # Sleeping books the kinetic energy it removed, a little per disc.
    removed = report['dissipated']['sleep']
    mass = 1.0 / s.inv_mass
    assert 0.0 <= removed <= 0.5 * float(np.sum(mass)) * sleep_speed(
        world.scene.effects.gravity, world.dt) ** 2
    assert world.energy()['dissipated'] == report['dissipated']
    assert abs(world.energy()['balance_error']) <= 1e-12 * _balance_scale(world)
    assert world.energy()['total'] == pytest.approx(report['total'], abs=1e-12)


def test_sleep_off_is_bitwise_the_pipeline_without_it():
    """Until the first island sleeps, sleeping changes nothing; off adds no stage."""
    on, off = _pile('balanced'), _pile('balanced', sleep_time=None)
    assert on.pipeline.names == off.pipeline.names
    lines = on.explain().splitlines()
    assert lines[0].startswith('before 1, wake: ')
    assert lines[-1].startswith(f'after {len(on.pipeline.names)}, sleep: ')
    assert lines[1:-1] == off.explain().splitlines()
    # Measured: the first island sleeps at step 117 (warm-started contacts settle
    # the pile that soon); every step before it is compared.
    compared = 0
    for _ in range(120):
        on.step()
        off.step()
        if on.asleep_count:
            break
        compared += 1
        assert np.array_equal(on.state.position, off.state.position)
        assert np.array_equal(on.state.velocity, off.state.velocity)
        assert np.array_equal(on.state.angular_velocity, off.state.angular_velocity)
        assert on.stats.dissipated == off.stats.dissipated
    assert compared >= 100


@pytest.mark.parametrize('accuracy, staged', [
    ('fast', True), ('balanced', True), ('accurate', False),
    ({'preset': 'balanced', 'sleep_time': None}, False),
    ({'preset': 'accurate', 'sleep_time': 0.25}, True)])
def test_explain_shows_sleep_only_when_it_can_act(accuracy, staged):
    gravity = {'gravity': [0.0, -9.81], 'walls': {'min': [0, 0], 'max': [1, 1]}}
    for effects, wanted in ((gravity, staged), ({'walls': gravity['walls']}, False)):
        scene = parse_scene({'dimensions': 2, 'dt': 0.01, 'effects': effects,
                             'accuracy': accuracy,
                             'particles': [{'position': [0.5, 0.5], 'radius': 0.1,
                                            'mass': 1.0}]}, 'test')
        text = World(scene).explain()
        assert (', wake:' in text and ', sleep:' in text) == wanted, text


@pytest.mark.parametrize('value, message', [
    (-1, 'must be > 0'), (0, 'must be > 0'), ('soon', 'expected a number'),
    (True, 'got true'), (1e9, 'must be <= ')])
def test_sleep_time_is_validated(value, message):
    with pytest.raises(SceneError) as error:
        parse_accuracy({'sleep_time': value}, 's.yaml: accuracy')
    text = str(error.value)
    assert text.startswith('s.yaml: accuracy.sleep_time') and message in text
    assert '\n' not in text


def test_a_ball_dropped_on_the_sleeping_pile_wakes_it(sleeping_pile):
    world = sleeping_pile
    resting = world.state.position.copy()
    top = float(np.max(resting[:, 1] + world.state.radius))
    x = float(resting[np.argmax(resting[:, 1]), 0])
    start = dict(world.energy())
    ball = world.spawn_text(f'particles: [{{position: [{x}, {top + 0.5}], velocity: [0, -3], '
                            'radius: 0.05, mass: 0.5}]')
    hit_step = None
    for k in range(120):
        world.step()
        if world.asleep_count < 240 and hit_step is None:
            hit_step = k
    assert hit_step is not None, 'the pile never woke'
    s = world.state
    pile = s.ids != ball[0]
    # The struck pile moved (it was dynamic when hit, not a static floor).
    assert float(np.max(np.abs(s.position[pile] - resting))) > 1e-3
    # The ball did not pass into the pile: it rests on or in it, no deeper
    # than the pile's own overlaps allow.
    row = int(np.flatnonzero(~pile)[0])
    gap = np.linalg.norm(s.position[pile] - s.position[row], axis=1) - s.radius[pile] - 0.05
    assert gap.min() > -0.1 * 0.05
    report = world.energy()
    assert report['spawned'] > 0.0 and report['start'] == start['start']
    assert abs(report['balance_error']) <= 1e-10 * _balance_scale(world)
    # It settles and sleeps again, ball included.
    for _ in range(600):
        world.step()
        if world.asleep_count == len(world.state):
            break
    assert world.asleep_count == len(world.state)
    assert abs(world.energy()['balance_error']) <= 1e-10 * _balance_scale(world)


def _two_stacks(gap=1.0):
    """Two separate columns of three touching balls on a floor, 2-D, friction-free."""
    particles = []
    for x in (0.5, 0.5 + gap):
        for level in range(3):
            particles.append({'position': [x, 0.1 + 0.2 * level], 'radius': 0.1,
                              'mass': 1.0})
    scene = parse_scene({'dimensions': 2, 'dt': 0.01,
                         'effects': {'gravity': [0.0, -9.81], 'restitution': 0.5,
                                     'walls': {'min': [0, 0], 'max': [3, 3]}},
                         'accuracy': {'preset': 'fast', 'sleep_time': 0.2},
                         'particles': particles}, 'test')
    world = World(scene)
    world.step(60)
    assert world.asleep_count == 6
    # Two islands: the columns do not touch (the floor does not link them).
    assert np.unique(world.state.island).size == 2
    return world


@pytest.mark.parametrize('command', ['impulse', 'teleport', 'delete'])
def test_a_command_wakes_the_island_it_touches_only(command):
    world = _two_stacks()
    before = world.state.position.copy()
    if command == 'impulse':
        impulse_request(world, {'id': 2, 'impulse': [0.5, 0.0]})
    elif command == 'teleport':
        teleport_request(world, {'id': 0, 'velocity': [0.0, 0.0]})
    else:
        world.delete(np.array([1]))
    s = world.state
    first = s.ids < 3
    assert not s.asleep[first].any() and s.asleep[~first].all()
    assert np.all(s.still_time[first] == 0.0)
    world.step()
    # The scene's ids are its original rows.
    moved = np.abs(world.state.position - before[world.state.ids]).max(axis=1)
    assert np.all(moved[~first] == 0.0)
    if command != 'teleport':
        # Knocked or left without support: the first column moves.
        assert moved[first].max() > 0.0
    assert abs(world.energy()['balance_error']) <= 1e-12 * _balance_scale(world)


def test_a_spawn_onto_a_sleeping_island_wakes_it():
    world = _two_stacks()
    # 5 cm above the first column: it lands after about 10 steps.
    world.spawn_text('particles: [{position: [0.5, 0.75], radius: 0.1, mass: 1.0}]',
                     source='spawn')
    woke = False
    for _ in range(20):
        world.step()
        s = world.state
        woke = woke or not s.asleep[s.ids < 3].any()
        assert s.asleep[(s.ids >= 3) & (s.ids < 6)].all()
    assert woke
    assert abs(world.energy()['balance_error']) <= 1e-12 * _balance_scale(world)


def test_an_island_touched_through_a_chain_wakes_together():
    """Strike one end of a sleeping row of touching balls: all wake, the far one flies."""
    row = [{'position': [1.0 + 0.2 * k, 0.1], 'radius': 0.1, 'mass': 1.0} for k in range(5)]
    scene = parse_scene({'dimensions': 2, 'dt': 0.005,
                         'effects': {'gravity': [0.0, -9.81], 'restitution': 1.0,
                                     'walls': {'min': [0, 0], 'max': [4, 2]}},
                         'accuracy': {'preset': 'fast', 'sleep_time': 0.1},
                         'particles': row}, 'test')
    world = World(scene)
    world.step(40)
    assert world.asleep_count == 5 and np.unique(world.state.island).size == 1
    world.spawn_text('particles: [{position: [0.5, 0.1], velocity: [2.0, 0.0], radius: 0.1, '
                     'mass: 1.0}]')
    all_awake = False
    for _ in range(60):
        world.step()
        all_awake = all_awake or not world.state.asleep[:5].any()
    s = world.state
    assert all_awake
    # Momentum went down the chain: the far ball leaves at about the striker's
    # speed, the striker stopped (and rests, maybe asleep again, with the rest).
    assert s.velocity[4, 0] == pytest.approx(2.0, rel=0.05)
    assert abs(s.velocity[5, 0]) < 0.1 and not s.asleep[4]
    assert abs(world.energy()['balance_error']) <= 1e-12 * _balance_scale(world)
