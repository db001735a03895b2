"""Pacing: how many fixed steps a tick takes, and the rates measured over a window."""

from __future__ import annotations

import math
from collections import deque
from typing import Optional

RATE_WINDOW = 2.0            # s of wall time over which rates are measured
STEP_BUDGET = 0.8            # share of a tick period the physics may use
CAUGHT_UP_AFTER = 1.0        # s of wall time keeping up that end an episode of lagging
# Falling behind is judged over LAG_WINDOW seconds of wall time: the node is
# behind when it stepped less than (1 - LAG_SHORTFALL) of the simulated time
# due in the window (a measured real-time factor below 80 % of the one asked)
# AND at least LAG_TICKS ticks of the window came short. One late tick, however
# late, is scheduler jitter on a loaded machine: its backlog is dropped and
# counted, but it starts no episode.
LAG_WINDOW = 2.0             # s of wall time
LAG_SHORTFALL = 0.2          # share of the window's simulated time not stepped
LAG_TICKS = 3                # short ticks within the window


class Pacer:
    """Count the fixed steps due so that simulated time follows wall time x factor.

    Simulated time is anchored to a wall instant: the target is
    ``sim_anchor + (wall - wall_anchor) x factor`` and the world never steps
    past it, so simulated time never runs ahead of wall time x factor. The
    anchor moves when the factor changes, the world resumes or is reset
    (:meth:`restart`), and when the physics fell behind
    (:meth:`drop_backlog`): then the target is lowered, never raised, so
    the backlog beyond one tick's worth is dropped (and counted in
    ``dropped``) instead of being chased.
    """

    def __init__(self, dt: float, factor: float, wall: float, sim_time: float) -> None:
        """Anchor simulated time ``sim_time`` at wall time ``wall``."""
        self.dt = dt
        self.factor = factor
        self.dropped = 0.0           # simulated seconds dropped so far
        self.restart(wall, sim_time)

    def restart(self, wall: float, sim_time: float) -> None:
        """Re-anchor: from ``wall`` on, simulated time starts at ``sim_time``."""
        self.wall_anchor = wall
        self.sim_anchor = sim_time

    def target(self, wall: float) -> float:
        """Return the simulated time due at wall time ``wall``."""
        return self.sim_anchor + (wall - self.wall_anchor) * self.factor

    def steps_due(self, wall: float, sim_time: float) -> int:
        """Return the whole steps needed to bring ``sim_time`` up to the target."""
        # The small tolerance keeps float noise from deferring a step a tick.
        return max(0, math.floor((self.target(wall) - sim_time) / self.dt + 1e-9))

    def drop_backlog(self, wall: float, sim_time: float, tick: float) -> float:
        """Drop the backlog beyond one tick's worth; return the simulated seconds dropped.

        A tick of ``tick`` wall seconds may carry ``dt + factor x tick`` of
        backlog (a step that did not fit the last tick, plus this tick's
        share); anything beyond is dropped by moving the anchor so the
        target is lower. The world then runs slower than asked instead of
        running faster than wall time later to catch up.
        """
        keep = self.dt + self.factor * tick
        backlog = self.target(wall) - sim_time
        if backlog <= keep:
            return 0.0
        dropped = backlog - keep
        self.sim_anchor -= dropped
        self.dropped += dropped
        return dropped


def came_short(done: int, due: int, dropped: float, dt: float) -> bool:
    """Tell whether a tick came short: it took fewer steps than due, or dropped over a step.

    A tick that came late by less than a step (scheduler jitter) dropped that
    bit of backlog too, but did not come short.
    """
    return done < due or dropped > dt


class Lag:
    """Episodes of truly falling behind, so that each is logged once.

    Each tick is noted with the simulated time reached and whether it came
    short (did not take every step due, or dropped more than a step of
    backlog). An episode starts when, over the last ``window`` seconds of
    wall time, the world advanced less than ``1 - shortfall`` of
    ``factor x window`` and at least ``ticks`` ticks came short (see
    LAG_WINDOW); it ends once no tick came short for ``caught_up_after``
    seconds. A window is judged only once the ticks noted span it: after
    the start, an episode's end, or :meth:`clear` (a reset, a resume, a new
    factor).
    """

    def __init__(self, caught_up_after: float = CAUGHT_UP_AFTER, window: float = LAG_WINDOW,
                 shortfall: float = LAG_SHORTFALL, ticks: int = LAG_TICKS) -> None:
        """Start keeping up, with an empty window."""
        self.caught_up_after = caught_up_after
        self.window, self.shortfall, self.ticks = window, shortfall, ticks
        self.behind = False
        self.since: Optional[float] = None       # wall time the ticks began to keep up
        self.dropped = 0.0                       # simulated seconds dropped this episode
        # (wall time, simulated time, came short, simulated seconds dropped) per tick.
        self.samples: deque[tuple[float, float, bool, float]] = deque()

    def note(self, wall: float, sim_time: float, factor: float, short: bool,
             dropped: float = 0.0) -> Optional[str]:
        """Record one tick; return 'start' or 'end' when an episode starts or ends."""
        samples = self.samples
        samples.append((wall, sim_time, short, dropped))
        # Keep the newest sample at or before the window's start as its reference.
        while len(samples) > 1 and samples[1][0] <= wall - self.window:
            samples.popleft()
        if self.behind:
            self.dropped += dropped
            if short:
                self.since = None
            elif self.since is None:
                self.since = wall
            elif wall - self.since >= self.caught_up_after:
                # A new episode is judged on a window of ticks after this one.
                self.behind, self.since = False, None
                samples.clear()
                samples.append((wall, sim_time, short, dropped))
                return 'end'
            return None
        span = wall - samples[0][0]
        if span < self.window:
            return None
        advanced = sim_time - samples[0][1]
        short_ticks = sum(1 for sample in list(samples)[1:] if sample[2])
        if advanced < (1.0 - self.shortfall) * factor * span and short_ticks >= self.ticks:
            self.behind, self.since = True, None
            self.dropped = sum(sample[3] for sample in list(samples)[1:])
            return 'start'
        return None

    def clear(self) -> None:
        """Forget an episode and the window (after a reset, a resume or a new factor)."""
        self.behind, self.since, self.dropped = False, None, 0.0
        self.samples.clear()


class RateMeter:
    """Rates over the last few seconds of wall time from cumulative counters."""

    def __init__(self, window: float = RATE_WINDOW) -> None:
        """Keep samples no older than ``window`` seconds."""
        self.window = window
        self.samples: deque[tuple[float, float, float]] = deque()

    def clear(self) -> None:
        """Forget every sample (after a reset the counters restart)."""
        self.samples.clear()

    def add(self, wall: float, sim_time: float, collisions: float) -> None:
        """Record cumulative simulated time and collisions at ``wall``."""
        self.samples.append((wall, sim_time, collisions))
        while len(self.samples) > 2 and wall - self.samples[0][0] > self.window:
            self.samples.popleft()

    def rates(self) -> tuple[float, float]:
        """Return (real-time factor, collisions per wall second) over the window."""
        if len(self.samples) < 2:
            return 0.0, 0.0
        (w0, s0, c0), (w1, s1, c1) = self.samples[0], self.samples[-1]
        if w1 <= w0:
            return 0.0, 0.0
        return (s1 - s0) / (w1 - w0), (c1 - c0) / (w1 - w0)
