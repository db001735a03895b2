"""Offline runner: ``python -m collision_node.simulate SCENE [options]``.

Runs a scene without ROS, prints a short summary, and writes the final
state and statistics as JSON. A bad scene or argument exits with code 2
and one line on stderr, before any step is taken (``--out`` included).
Ctrl-C (SIGINT) or SIGTERM stops the run within a second: at the step
boundary if the step in flight ends within ``STOP_GRACE_S``, else the step in
flight is abandoned and the last completed state is reported. The summary
and the JSON of that state (``"interrupted": true``) are still written, and
the exit code is 130; a second signal exits at once (130, nothing written).
The steps run on a worker thread (the compiled kernels release the GIL), so
the main thread answers signals whatever the step is doing.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import os
import signal
import stat
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
from tqdm import tqdm

from .physics.accuracy import parse_accuracy_text
from .physics.kernels import prepare as prepare_kernels
from .physics.scene import load_scene
from .physics.validation import SceneError
from .physics.world import NonFiniteStateError, World

# Runs shorter than this never show a progress bar.
PROGRESS_DELAY_S = 2.0
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
# After SIGINT/SIGTERM, seconds the step in flight may take to end before it is
# abandoned and the last completed state is reported (the exit then comes
# within a second of the signal, writing the result included for mid-size worlds).
STOP_GRACE_S = 0.5
# A step taking longer than this makes the worker keep a copy of the state
# before each next step, so an abandoned step has a completed one to report
# (the copy costs a few per cent of such a step; faster steps end within the
# grace anyway).
SNAPSHOT_AFTER_S = 0.05
# Seconds between two looks of the main thread at the run (progress bar, signals).
POLL_S = 0.1
# More steps than this is a typo or an overflow (1e9 steps of a single
# particle already take hours), refused before the run.
MAX_STEPS = 10 ** 9


class UsageError(Exception):
    """A command-line argument the runner cannot accept."""


class _Parser(argparse.ArgumentParser):
    """An argument parser that reports errors as one line, no usage block."""

    def error(self, message: str) -> None:  # noqa: D102 (argparse hook)
        raise UsageError(message)


def build_parser() -> argparse.ArgumentParser:
    """Return the runner's command-line parser."""
    parser = _Parser(prog='simulate', description='Run a collision_node scene offline.')
    parser.add_argument('scene', help='scene file, or the name of a shipped scene')
    length = parser.add_mutually_exclusive_group()
    length.add_argument('--duration', type=float, help='simulated seconds (default: scene)')
    length.add_argument('--steps', type=int, help='number of steps')
    parser.add_argument('--out', help='write the final state and stats as JSON to this file')
    parser.add_argument('--explain', action='store_true',
                        help='print the step pipeline and exit')
    parser.add_argument('--quiet', action='store_true', help='no summary on stdout')
    parser.add_argument('--accuracy', help='preset (fast, balanced, accurate, exact) or a '
                        'YAML/JSON mapping such as "{preset: fast, substeps: 2}"; '
                        'overrides the scene\'s accuracy')
    return parser


def particle_records(world: World) -> list[dict]:
    """Return the final state as JSON-ready records, one per particle."""
    s = world.state
    mass = s.mass
    records = []
    for k in range(len(s)):
        records.append({
            'id': int(s.ids[k]),
            'position': s.position[k].tolist(),
            'velocity': s.velocity[k].tolist(),
            'radius': float(s.radius[k]),
            'mass': None if math.isinf(mass[k]) else float(mass[k]),
        })
    if s.angular_velocity is not None:
        # Spin exists only when the scene declares friction.
        for k, record in enumerate(records):
            record['angular_velocity'] = s.angular_velocity[k].tolist()
            record['orientation'] = s.orientation[k].tolist()
    return records


def run(world: World, steps: int, show_progress: bool = True,
        stop: Optional['_StopRequest'] = None) -> tuple[float, World]:
    """Step ``world`` ``steps`` times; return the wall-clock seconds and the world to report.

    The steps run on a worker thread (the kernels release the GIL), so the
    calling thread keeps answering signals. ``stop`` is asked before every
    step; once it answers true the run ends at the next step boundary, or,
    if the step in flight has not ended ``STOP_GRACE_S`` after the signal,
    at the last completed step the worker kept: that copy is returned
    instead of ``world`` (a step is never cut in half in what is reported;
    the abandoned one goes on in the background until the process ends).
    An exception of a step is raised here.
    """
    start = time.perf_counter()
    worker = _Worker(world, steps, stop)
    worker.start()
    reported = world
    with tqdm(total=steps, unit='step', delay=PROGRESS_DELAY_S, file=sys.stderr,
              disable=not show_progress, leave=False) as bar:
        drawn = start
        while not worker.done.wait(POLL_S):
            if stop is not None and stop() and time.monotonic() - stop.since >= STOP_GRACE_S:
                reported = worker.abandon()
                break
            now = time.perf_counter()
            if world.steps > bar.n:
                bar.update(world.steps - bar.n)
            elif show_progress and now - start >= PROGRESS_DELAY_S and now - drawn >= 1.0:
                bar.refresh()           # drawn (once a second) while one step lasts long
                drawn = now
    if worker.error is not None:
        raise worker.error
    return time.perf_counter() - start, reported


class _Worker(threading.Thread):
    """Takes the run's steps; keeps a copy of the state before each step that follows a slow one.

    The copy is what an abandoned step reports (``abandon``): the state
    after the last step that ended. Steps faster than ``SNAPSHOT_AFTER_S``
    are not copied for (they end within the grace); the initial state is.
    """

    def __init__(self, world: World, steps: int, stop: Optional[Callable[[], bool]]) -> None:
        super().__init__(name='simulate steps', daemon=True)
        self.world, self.steps, self.stop = world, steps, stop
        self.done = threading.Event()
        self.error: Optional[BaseException] = None
        self._kept: Optional[World] = None
        self._abandoned = False
        self._lock = threading.Lock()

    def run(self) -> None:
        """Step until done or asked to stop, copying the state before slow steps."""
        world, slow = self.world, True
        try:
            for _ in range(self.steps):
                if self.stop is not None and self.stop():
                    break
                if slow:
                    with self._lock:
                        if self._abandoned:
                            break
                        self._kept = None          # at most one copy alive
                        self._kept = completed_copy(world)
                began = time.perf_counter()
                world.step()
                slow = time.perf_counter() - began > SNAPSHOT_AFTER_S
        except BaseException as error:  # noqa: B902 - raised again in the caller's thread
            self.error = error
        finally:
            self.done.set()

    def abandon(self) -> World:
        """Give up the step in flight; return the last completed state kept (or the world)."""
        with self._lock:
            self._abandoned = True
            if self.done.is_set() or self._kept is None:
                # It ended meanwhile, or never began a step: the world itself is whole.
                return self.world
            return self._kept


def completed_copy(world: World) -> World:
    """Return a copy of ``world`` for reporting: its state and counters, not shared."""
    kept = copy.copy(world)
    kept.state, kept.stats = world.state.copy(), world.stats.copy()
    return kept


def check_out(out: str) -> None:
    """Refuse an ``--out`` target that cannot be written, before any step is run.

    A device that fails only when written to (``/dev/full``) can only be
    found at the end; :func:`main` reports that after the summary.
    """
    if out == '':
        raise UsageError('--out: empty file name')
    path = Path(out)
    if path.is_dir():
        raise UsageError(f'--out {out}: Is a directory')
    parent = path.parent
    if not parent.is_dir():
        raise UsageError(f'--out {out}: No such file or directory ({parent} is not a '
                         'directory)')
    # Try it rather than ask os.access (which says yes to root everywhere):
    # append to an existing file (no truncation), or create and remove.
    existed = path.exists()
    try:
        with open(path, 'a', encoding='utf-8'):
            pass
        if not existed:
            path.unlink()
    except OSError as error:
        raise UsageError(f'--out {out}: {error.strerror}') from None


def steps_to_run(args: argparse.Namespace, duration: float, dt: float) -> int:
    """Return the number of steps asked for, refusing absurd ones."""
    if args.steps is not None:
        if args.steps > MAX_STEPS:
            raise UsageError(f'--steps must be <= {MAX_STEPS}, got {args.steps}')
        return args.steps
    source = 'scene duration' if args.duration is None else '--duration'
    steps = duration / dt
    if not steps <= MAX_STEPS:
        raise UsageError(f'{source} {duration:g} s is {steps:.3g} steps of dt = {dt:g} s, '
                         f'over the limit of {MAX_STEPS}')
    return int(round(steps))


class _StopRequest:
    """Turns SIGINT and SIGTERM into a flag the run checks between steps.

    A second signal ends the process at once (exit 130, one line on
    stderr), removing a result file being written (``writing``), so
    nothing half-written is left.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signal: Optional[int] = None
        self.since = math.inf                   # monotonic time of the first signal
        self.writing: Optional[str] = None      # temporary result file being written
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> '_StopRequest':
        for number in self.SIGNALS:
            self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)

    def _handle(self, number: int, frame: Any) -> None:
        if self.signal is None:
            self.signal, self.since = number, time.monotonic()
            return
        if self.writing is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.writing)
        os.write(2, f'simulate: second {signal.Signals(number).name}: exiting at once, '
                    'nothing written\n'.encode())
        os._exit(EXIT_INTERRUPTED)

    def __call__(self) -> bool:
        return self.signal is not None


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the runner; return the process exit code."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        # Ctrl-C while the scene loads: nothing has run, nothing to keep.
        print('simulate: interrupted before the run started', file=sys.stderr)
        return EXIT_INTERRUPTED


def _main(argv: Optional[Sequence[str]]) -> int:
    try:
        args = build_parser().parse_args(argv)
        if args.steps is not None and args.steps < 0:
            raise UsageError(f'--steps must be >= 0, got {args.steps}')
        if args.duration is not None and not (math.isfinite(args.duration)
                                              and args.duration >= 0):
            raise UsageError(f'--duration must be a finite number >= 0, got {args.duration}')
        if args.out is not None:
            check_out(args.out)
        scene = load_scene(args.scene)
        if args.accuracy is not None:
            scene = scene.with_accuracy(parse_accuracy_text(args.accuracy, scene.effects,
                                                            '--accuracy'))
        duration = scene.duration if args.duration is None else args.duration
        steps = steps_to_run(args, duration, scene.dt)
        world = World(scene)
        # Compiled once, then loaded from the cache; only a compile is reported.
        prepare_kernels(lambda text: print(f'simulate: {text}', file=sys.stderr))
    except (UsageError, SceneError) as error:
        print(f'simulate: error: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.explain:
        print(world.explain())
        return 0
    start = {'kinetic': world.kinetic_energy(), 'momentum': world.momentum(),
             'energy': world.energy()}
    # The handlers stay until the JSON is written: a second signal exits at
    # once, never leaving half a file (write_result).
    with _StopRequest() as stop:
        try:
            wall_seconds, reported = run(world, steps, stop=stop)
        except NonFiniteStateError as error:
            print(f'simulate: error: {scene.name}: {error}', file=sys.stderr)
            return 1
        abandoned = reported is not world
        if abandoned:
            print(f'simulate: {signal.Signals(stop.signal).name}: step {world.steps + 1} did '
                  f'not end within {STOP_GRACE_S:g} s and was abandoned; reporting the state '
                  f'after step {reported.steps}', file=sys.stderr)
        code = _report(reported, start, wall_seconds, steps, args, stop)
    if abandoned:
        # The abandoned step still runs on its thread and cannot be stopped:
        # end the process here, with everything written and flushed.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _report(world: World, start: dict, wall_seconds: float, steps: int,
            args: argparse.Namespace, stop: '_StopRequest') -> int:
    """Print the summary of ``world`` and write its JSON; return the exit code."""
    result = build_result(world, start, wall_seconds)
    if stop.signal is not None:
        result['interrupted'] = True
        result['steps_requested'] = steps
    if not args.quiet:
        if stop.signal is not None:
            print(f'interrupted by {signal.Signals(stop.signal).name} after {world.steps} '
                  f'of {steps} steps')
        print_summary(world, result)
        sys.stdout.flush()
    if args.out is not None:
        try:
            write_result(args.out, result, stop)
        except OSError as error:
            # Checked before the run; a full disk or /dev/full shows only now.
            print(f'simulate: error: --out {args.out}: {error.strerror}', file=sys.stderr)
            return EXIT_BAD_INPUT
    return EXIT_INTERRUPTED if stop.signal is not None else 0


def write_result(out: str, result: dict, stop: '_StopRequest') -> None:
    """Write the JSON ``result`` to ``out``, never leaving half a file behind a second signal.

    A regular file (or a new one) is written beside its target and renamed
    over it (keeping an existing file's permissions); a device or a
    symbolic link is written in place (/dev/full fails only there).
    """
    path = Path(out)
    handle = None
    if not path.is_symlink() and (path.is_file() or not path.exists()):
        partial = path.with_name(f'.{path.name}.partial-{os.getpid()}')
        stop.writing = str(partial)
        try:
            handle = open(partial, 'x', encoding='utf-8')
        except OSError:             # a directory we may write the file in but not create in
            stop.writing = None
    if handle is None:
        with open(out, 'w', encoding='utf-8') as handle:
            json.dump(result, handle, indent=1)
        return
    try:
        with handle:
            json.dump(result, handle, indent=1)
        if path.exists():
            os.chmod(partial, stat.S_IMODE(os.stat(path).st_mode))
        os.replace(partial, path)
    finally:
        stop.writing = None
        with contextlib.suppress(FileNotFoundError):
            os.unlink(partial)


def build_result(world: World, start: dict, wall_seconds: float) -> dict:
    """Return the JSON document of a run that started from ``start``."""
    return {
        'scene': world.scene.name,
        'time': world.time,
        'steps': world.steps,
        'particles': particle_records(world),
        'stats': {
            'collisions': world.stats.collisions,
            'wall_collisions': world.stats.wall_collisions,
            'kinetic_energy': [start['kinetic'], world.kinetic_energy()],
            'momentum': [start['momentum'].tolist(), world.momentum().tolist()],
            'dissipated': dict(world.stats.dissipated),
            'energy': {'start': start['energy'], 'end': world.energy()},
            'max_penetration': world.stats.max_penetration,
            'fallback_steps': world.stats.fallback_steps,
            # Particles asleep at the end (sleeping islands, accuracy sleep_time).
            'asleep': world.asleep_count,
            'wall_seconds': wall_seconds,
        },
    }


def print_summary(world: World, result: dict) -> None:
    """Print the run's summary lines from its JSON document."""
    stats = result['stats']
    energy_start, energy_end = stats['kinetic_energy']
    balance_start, balance_end = stats['energy']['start'], stats['energy']['end']
    d_momentum = float(np.linalg.norm(np.subtract(*stats['momentum'][::-1])))
    print(f'{result["scene"]}: {len(world.state)} particles, {world.steps} steps '
          f'({world.time:g} s simulated) in {stats["wall_seconds"]:.3f} s wall')
    print(f'collisions: {stats["collisions"]} particle, {stats["wall_collisions"]} wall')
    print(f'kinetic energy: {energy_start:.12g} -> {energy_end:.12g} J '
          f'(change {energy_end - energy_start:+.3g} J)')
    if balance_end['dissipated'] or balance_end['potential']:
        removed = ', '.join(f'{name} {value:.6g}'
                            for name, value in balance_end['dissipated'].items())
        print(f'energy (kinetic + potential): {balance_start["total"]:.12g} -> '
              f'{balance_end["total"]:.12g} J; removed by effects: {removed or "none"} J; '
              f'balance error {balance_end["balance_error"]:.3g} J')
    print(f'momentum change: {d_momentum:.3g} kg m/s; '
          f'max penetration: {stats["max_penetration"]:.3g} m')
    if stats['asleep']:
        print(f'asleep at the end: {stats["asleep"]} of {len(world.state)} particles '
              '(sleeping islands, accuracy sleep_time)')
    if stats['fallback_steps']:
        print(f'event mode: {stats["fallback_steps"]} of {world.steps} steps met an impact '
              'onto resting particles, a collapsing bounce or the event budget and were '
              'solved by the step fallback')


if __name__ == '__main__':
    sys.exit(main())
