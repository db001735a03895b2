"""The offline runner's recording: frames of a run at a fixed rate of simulated time.

Frame ``k`` is written after the first step that reaches ``k / rate``
seconds (at most one frame per step), from the initial state at time 0 on,
and the state the run ends in is always the last frame, so a run of
``duration`` seconds holds ``floor(duration x rate) + 1`` frames when the
duration is a whole number of frame periods. A frame is what the node
publishes on one tick: ``/clock``, ``particles/poses``, ``particles/state``,
``particles/markers``, ``particles/collisions`` (the impacts since the
previous frame; impacts are recorded while the recording runs) and
``status`` (the node's status fields; the runner is not paced, so its
target real-time factor is the one it achieved).
"""

from __future__ import annotations

import json
import math
import time
from typing import Any, Optional

from msg_adapters import clock_bytes
from msg_adapters.strings import string_bytes

from ..id_order import InIdOrder
from ..ros.status import status_report
from .recorder import default_names, Recorder

DEFAULT_RATE = 30.0          # Hz of simulated time: the node's default publish_rate
FRAME_ID = 'world'           # the node's default frame_id
# Tolerance of the frame schedule: step n reaches frame k when n dt rate >= k - this.
_SCHEDULE_TOLERANCE = 1e-9


class RunRecording:
    """Record a run: construct before the first step, call :meth:`after_step`, then finish."""

    def __init__(self, path: str, world: Any, rate: float = DEFAULT_RATE) -> None:
        """Create the bag and write the initial frame (time 0)."""
        self.world = world
        self.rate = rate
        self.recorder = Recorder(path, default_names())
        self.frames = 0                   # frames written
        self.last_step: Optional[int] = None
        self.wall_start = time.perf_counter()
        world.record_impacts(True)
        self.frame()

    def _due(self) -> int:
        """Return the index of the newest frame the world's time has reached."""
        return math.floor(self.world.steps * self.world.dt * self.rate + _SCHEDULE_TOLERANCE)

    def after_step(self) -> None:
        """Write a frame if the step just taken reached the next frame time."""
        if self._due() >= self.frames:
            self.frame()

    def frame(self) -> None:
        """Write the world's current state as one frame."""
        world, recorder, t = self.world, self.recorder, self.world.time
        self.frames = max(self.frames, self._due()) + 1
        self.last_step = world.steps
        if not recorder.active:
            return
        recorder.write('clock', clock_bytes(t), t)
        recorder.write_state(InIdOrder(world.state), t, FRAME_ID)
        recorder.write_impacts(world.take_impacts(), t, FRAME_ID)
        recorder.write('status', string_bytes(json.dumps(self.status())), t)

    def status(self) -> dict[str, Any]:
        """Return the node's status fields for the run so far."""
        wall = time.perf_counter() - self.wall_start
        stats = self.world.stats
        collisions = stats.collisions + stats.wall_collisions
        rtf = self.world.time / wall if wall > 0.0 else 0.0
        rates = (rtf, collisions / wall if wall > 0.0 else 0.0)
        report = status_report(self.world, self.world.scene.name, rates, paused=False,
                               real_time_factor=rtf, keeping_up=True, publish_rate=self.rate,
                               frame_id=FRAME_ID, error=None)
        report['dropped_backlog_s'] = 0.0
        return report

    def finish(self) -> Optional[str]:
        """Write the final state if it is not the last frame yet, close; return any error."""
        try:
            if self.last_step != self.world.steps:
                self.frame()
        finally:
            self.world.record_impacts(False)
            error = self.recorder.close()
        return None if error is None else self.recorder.describe_error()
