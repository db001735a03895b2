"""The node's stepping thread: the world's steps run beside the executor, in slices.

One step of a large world takes longer than a service call may wait (a
100,000-particle gas: about half a second here, docs/performance.md), and
slicing between steps cannot cut a step. So the node hands its steps to
this worker thread, a slice at a time, and its executor thread goes on
answering services and taking messages meanwhile; the compiled kernels
release the GIL (``nogil=True``), so both threads run at once.

The world belongs to one thread at a time: while a slice runs only the
worker touches it; the executor thread touches it only between slices
(:attr:`Stepper.busy` false). Whatever must touch the world while a slice
runs (a command, a reset, a parameter's effect) waits for the slice's end,
and a slice ends after the step in flight once :attr:`Stepper.interrupt`
is set, so it waits at most one step. The end of a slice reaches the
executor thread through a guard condition.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Callable, NamedTuple, Optional

from rclpy.node import Node

from ..physics.step.world import World


class SliceResult(NamedTuple):
    """What a slice did: the steps that ended, the exception that stopped it, if any."""

    steps: int
    error: Optional[BaseException]
    interrupted: bool            # :attr:`Stepper.interrupt` was set when it ended


class Stepper:
    """Runs slices of steps of a world on a worker thread; reports each slice's end."""

    def __init__(self, node: Node, on_done: Callable[[SliceResult], None]) -> None:
        """Start the worker; ``on_done`` runs on the executor thread when a slice ends."""
        self._on_done = on_done
        self._guard = node.create_guard_condition(self._collect)
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._ended = threading.Event()
        self._result: Optional[SliceResult] = None
        # Set by the executor thread: the slice ends after the step in flight.
        self.interrupt = threading.Event()
        self.busy = False            # a slice is running (read and set on the executor thread)
        self._thread = threading.Thread(target=self._work, name='collision_node steps',
                                        daemon=True)
        self._thread.start()

    def start(self, world: World, count: int, deadline: float) -> None:
        """Take up to ``count`` steps of ``world`` on the worker.

        The slice ends after ``count`` steps, after the first step that ends
        past ``deadline`` (``time.monotonic``), or after the step in flight
        once :attr:`interrupt` is set; it always takes at least one step.
        """
        assert not self.busy, 'a slice is already running'
        self.busy = True
        self.interrupt.clear()
        self._ended.clear()
        self._jobs.put((world, count, deadline))

    def wait(self) -> None:
        """Block until the slice in flight ends (after its current step), then report it."""
        if self.busy:
            self.interrupt.set()
            self._ended.wait()
            self._collect()

    def close(self, timeout: float) -> None:
        """End the worker after the step in flight, waiting for it at most ``timeout`` s.

        The worker is a daemon: a step that takes longer ends with the process.
        """
        self.interrupt.set()
        self._jobs.put(None)
        if self.busy:
            self._ended.wait(timeout)

    def _work(self) -> None:
        """Worker thread: run each slice handed over, then trigger the guard condition."""
        while True:
            job = self._jobs.get()
            if job is None:
                return
            world, count, deadline = job
            first, error = world.steps, None
            try:
                for _ in range(count):
                    world.step(1)
                    if self.interrupt.is_set() or time.monotonic() > deadline:
                        break
            except BaseException as raised:  # noqa: B902 - handed to the executor thread
                error = raised
            self._result = SliceResult(world.steps - first, error, self.interrupt.is_set())
            self._ended.set()
            try:
                self._guard.trigger()
            except Exception:  # noqa: B902 - the node was destroyed meanwhile (exit)
                return

    def _collect(self) -> None:
        """Executor thread (guard condition or :meth:`wait`): hand an ended slice over once."""
        if not self.busy or not self._ended.is_set():
            return
        self.busy = False
        result, self._result = self._result, None
        self._on_done(result)
