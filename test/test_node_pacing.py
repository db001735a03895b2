"""The node's pacing arithmetic: steps due so simulated time follows wall time."""

from __future__ import annotations

import pytest

from collision_node import load_scene, World
from collision_node.ros.pacing import came_short, Lag, LAG_WINDOW, Pacer, RateMeter
from collision_node.ros.parameters import DEFAULT_SCENE, PARAMETERS

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros


def test_steps_due_follow_wall_time_times_factor():
    pacer = Pacer(dt=0.01, factor=1.0, wall=100.0, sim_time=0.0)
    assert pacer.steps_due(100.0, 0.0) == 0
    assert pacer.steps_due(100.095, 0.0) == 9          # 9.5 steps due: whole ones only
    assert pacer.steps_due(100.1, 0.0) == 10            # float noise does not defer a step
    assert pacer.steps_due(100.1, 0.05) == 5            # steps already taken count
    pacer.factor = 2.5
    assert pacer.steps_due(101.0, 0.0) == 250


def test_restart_moves_the_anchor_and_never_asks_for_negative_steps():
    pacer = Pacer(dt=0.01, factor=1.0, wall=0.0, sim_time=0.0)
    pacer.restart(wall=5.0, sim_time=1.0)               # e.g. resumed after a pause
    assert pacer.steps_due(5.0, 1.0) == 0
    assert pacer.steps_due(5.2, 1.0) == 20
    assert pacer.steps_due(5.2, 3.0) == 0                # ahead of wall time: wait


def test_drop_backlog_keeps_one_tick_and_never_raises_the_target():
    pacer = Pacer(dt=0.01, factor=2.0, wall=0.0, sim_time=0.0)
    # 0.5 s of wall time passed while the world stood at 0: 1.0 s of simulated time due.
    dropped = pacer.drop_backlog(0.5, 0.0, tick=0.1)
    keep = 0.01 + 2.0 * 0.1
    assert dropped == pytest.approx(1.0 - keep) and pacer.dropped == pytest.approx(dropped)
    assert pacer.target(0.5) == pytest.approx(keep)
    assert pacer.steps_due(0.5, 0.0) == 21
    # Within the allowance nothing is dropped and the target follows wall time.
    assert pacer.drop_backlog(0.55, 0.15, tick=0.1) == 0.0
    assert pacer.target(0.55) == pytest.approx(keep + 0.1)


def test_simulated_time_never_runs_ahead_of_wall_time_through_slow_ticks():
    """A world that falls behind, then runs fast again, never passes wall x factor."""
    dt, factor, tick = 1.0 / 240.0, 1.0, 1.0 / 30.0
    pacer = Pacer(dt=dt, factor=factor, wall=0.0, sim_time=0.0)
    steps, wall = 0, 0.0
    for k in range(600):
        wall += tick * (10.0 if k == 100 else 1.0)      # one tick stalls for 10 periods
        pacer.drop_backlog(wall, steps * dt, tick)
        due = pacer.steps_due(wall, steps * dt)
        steps += due if not 100 <= k < 110 else min(due, 2)   # then a slow stretch
        assert steps * dt <= wall * factor + 1e-9
    # After the stall and the slow stretch it runs at the requested rate, not faster.
    assert pacer.dropped > 0.2
    assert steps * dt == pytest.approx(wall * factor - pacer.dropped, abs=dt + factor * tick)


def run_ticks(ticks: int, capacity, late: dict = {}, factor: float = 1.0,
              dt: float = 1.0 / 240.0, period: float = 1.0 / 30.0):
    """Drive a Pacer and a Lag as the node's ticks do, on a fake wall clock.

    Tick k comes ``period`` (plus ``late[k]``) after the one before and takes
    at most ``capacity(k)`` steps. Return the episode changes as (change,
    wall time, tick), the pacer and the lag.
    """
    pacer, lag = Pacer(dt=dt, factor=factor, wall=0.0, sim_time=0.0), Lag()
    steps, wall, changes = 0, 0.0, []
    for k in range(ticks):
        wall += period + late.get(k, 0.0)
        dropped = pacer.drop_backlog(wall, steps * dt, period)
        due = pacer.steps_due(wall, steps * dt)
        done = min(due, capacity(k))
        steps += done
        change = lag.note(wall, steps * dt, factor, came_short(done, due, dropped, dt), dropped)
        if change:
            changes.append((change, wall, k))
    return changes, pacer, lag


def test_a_single_late_tick_of_a_tiny_world_is_no_lag():
    """Stalls of a loaded machine: each tick's backlog is dropped and counted, no episode."""
    # A 2-particle world takes every step due; one tick comes 0.6 s late, then
    # (3 s apart) two more come 1.5 s and 0.2 s late.
    changes, pacer, lag = run_ticks(600, capacity=lambda k: 10 ** 6,
                                    late={100: 0.6, 200: 1.5, 300: 0.2})
    assert changes == [] and not lag.behind
    assert pacer.dropped > 0.6 + 1.5 + 0.2 - 3 * (1.0 / 240.0 + 1.0 / 30.0) - 1e-9


def test_jitter_that_keeps_the_rate_is_no_lag():
    # Every fifth tick comes two steps late: many short ticks, but 90 % of the rate kept.
    changes, pacer, lag = run_ticks(600, capacity=lambda k: 10 ** 6,
                                    late={k: 2.0 / 240.0 for k in range(0, 600, 5)})
    assert changes == [] and pacer.dropped > 0.0


def test_a_world_that_truly_falls_behind_is_reported_once_then_caught_up():
    # Ticks of 1/32 s due 8 steps of 1/256 s (binary fractions: the fake clock adds
    # up exactly); the world manages 4 (half the rate) for 180 ticks, then all.
    period = 1.0 / 32.0
    changes, pacer, lag = run_ticks(360, capacity=lambda k: 4 if k < 180 else 10 ** 6,
                                    dt=1.0 / 256.0, period=period)
    assert [c[0] for c in changes] == ['start', 'end']
    (_, started, _), (_, ended, end_tick) = changes
    # Judged once the ticks span the window (from the first tick, at `period`).
    assert started - period == LAG_WINDOW
    # Tick 180 still drops the backlog the slow ticks left; tick 181 is the first
    # to keep up, and the episode ends CAUGHT_UP_AFTER (1 s, 32 ticks) later.
    assert end_tick == 181 + 32 and ended == (end_tick + 1) * period
    assert lag.dropped > 0.0 and not lag.behind


def test_lag_window_is_forgotten_on_clear():
    lag = Lag(window=1.0, shortfall=0.2, ticks=3)
    for k in range(10):                          # 0.9 s of ticks at half the rate
        assert lag.note(0.1 * k, 0.05 * k, 1.0, short=True) is None
    lag.clear()
    for k in range(4):                           # a new window: 0.75 s, not judged yet
        assert lag.note(1.0 + 0.25 * k, 0.45 + 0.125 * k, 1.0, short=True) is None
    assert lag.note(2.0, 0.95, 1.0, short=True) == 'start'  # half the rate over 1 s


def test_rate_meter_measures_over_its_window():
    meter = RateMeter(window=1.0)
    assert meter.rates() == (0.0, 0.0)
    for k in range(31):                                  # 3 s at 10 Hz, sim at half speed
        meter.add(wall=0.1 * k, sim_time=0.05 * k, collisions=7 * k)
    rtf, collisions = meter.rates()
    assert rtf == pytest.approx(0.5) and collisions == pytest.approx(70.0)
    assert meter.samples[-1][0] - meter.samples[0][0] <= 1.0 + 1e-9
    meter.clear()
    assert meter.rates() == (0.0, 0.0)


def test_default_scene_is_a_valid_break_with_collisions_soon():
    assert PARAMETERS['scene'][0] == DEFAULT_SCENE == 'elastic_break'
    world = World(load_scene(DEFAULT_SCENE))
    assert len(world.state) == 16 and world.scene.dimensions == 2
    world.step(round(0.5 / world.dt))
    assert world.stats.collisions > 0
    assert world.kinetic_energy() == pytest.approx(0.5 * 0.17 * 25.0, rel=1e-9)


def test_log_budget_logs_single_refusals_and_bounds_a_flood():
    from collision_node.ros.commands import LOGGED_PER_SECOND, LogBudget

    class Logger:
        def __init__(self):
            self.lines = []

        def warning(self, text):
            self.lines.append(text)

    logger = Logger()
    budget = LogBudget(logger)
    assert budget.spend(10.0) and budget.spend(10.2)          # single refusals: logged
    flood = [budget.spend(10.3 + k * 1e-4) for k in range(100)]
    assert sum(flood) == LOGGED_PER_SECOND - 2                 # the rest of the budget
    assert logger.lines == []
    assert budget.spend(11.3)                                  # a new second: logged again
    assert logger.lines == [f'{100 - (LOGGED_PER_SECOND - 2)} more requests were rejected in '
                            'a second without a log line (each was answered on events)']
