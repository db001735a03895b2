"""Pacing: how many fixed steps a tick takes, and the rates measured over a window."""

from __future__ import annotations

import math
from collections import deque

RATE_WINDOW = 2.0            # s of wall time over which rates are measured
STEP_BUDGET = 0.8            # share of a tick period the physics may use
BACKLOG_KEPT = 0.25          # s of wall time the physics may lag once it fell behind


class Pacer:
    """Count the fixed steps due so that simulated time follows wall time x factor.

    Simulated time is anchored to a wall instant; the anchor moves whenever
    the factor changes, the world resumes or is reset, or the physics fell
    behind (so a backlog is never chased beyond BACKLOG_KEPT: the world
    runs slower instead, stepping all the time it is given).
    """

    def __init__(self, dt: float, factor: float, wall: float, sim_time: float) -> None:
        """Anchor simulated time ``sim_time`` at wall time ``wall``."""
        self.dt = dt
        self.factor = factor
        self.restart(wall, sim_time)

    def restart(self, wall: float, sim_time: float) -> None:
        """Re-anchor: from ``wall`` on, simulated time starts at ``sim_time``."""
        self.wall_anchor = wall
        self.sim_anchor = sim_time

    def steps_due(self, wall: float, sim_time: float) -> int:
        """Return the whole steps needed to bring ``sim_time`` up to the target."""
        target = self.sim_anchor + (wall - self.wall_anchor) * self.factor
        # The small tolerance keeps float noise from deferring a step a tick.
        return max(0, math.floor((target - sim_time) / self.dt + 1e-9))


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
