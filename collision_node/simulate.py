"""Offline runner: ``python -m collision_node.simulate SCENE [options]``.

Runs a scene without ROS, prints a short summary, and writes the final
state and statistics as JSON, and on request pictures of the final state
and of the energy over time (drawn by ``collision_node.pictures``). A bad
scene or argument exits with code 2 and one line on stderr, before any
step is taken (every output path included).
Ctrl-C (SIGINT) or SIGTERM stops the run within a second: at the step
boundary if the step in flight ends within ``STOP_GRACE_S``, else the step in
flight is abandoned and the last completed state is reported. The summary
and the JSON of that state (``"interrupted": true``) are still written, and
the exit code is 130; a second signal exits at once (130, nothing written).
The steps run on a worker thread (the compiled kernels release the GIL), so
the main thread answers signals whatever the step is doing. A world too
large for the machine's memory (``MemoryError`` while loading or stepping)
is one line and exit 2.
``--profile`` adds the wall time per stage (``World.profile``) to the
output and the JSON. ``--record PATH`` also writes the run as a rosbag2 bag
(MCAP) of what the node would publish, stamped with simulated time
(:mod:`collision_node.recording`; it needs the ROS 2 message packages,
imported only then).
output and the JSON. ``--compare-presets`` runs the scene under every
preset it accepts instead and prints one table of their costs and their
differences from ``exact`` (``collision_node.preset_compare``).
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

from .physics.model.accuracy import parse_accuracy_text
from .physics.step.kernels import prepare as prepare_kernels
from .physics.model.scene import load_scene
from .physics.model.validation import SceneError, one_line
from .physics.step.world import NonFiniteStateError, World
from .physics.step.threads import set_default as set_default_threads

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
# particle already take hours), refused before the run: --steps, and the
# steps --duration (or the scene's duration) makes at the scene's dt.
MAX_STEPS = 10 ** 9


class UsageError(Exception):
    """A command-line argument the runner cannot accept."""


def out_of_memory(error: MemoryError, doing: str) -> str:
    """Return the one-line report of a ``MemoryError`` met while ``doing``."""
    detail = one_line(str(error), 80)
    return f'out of memory {doing} (MemoryError{": " + detail if detail else ""})'


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
    parser.add_argument('--snapshot', metavar='FILE.png',
                        help='draw the final state to scale (x-y plane, walls, static '
                        'particles grey) into this picture')
    parser.add_argument('--energy-plot', metavar='FILE.png',
                        help='plot kinetic and potential energy over time above the losses '
                        'per effect into this picture')
    parser.add_argument('--explain', action='store_true',
                        help='print the step pipeline and exit')
    parser.add_argument('--quiet', action='store_true', help='no summary on stdout')
    parser.add_argument('--profile', action='store_true',
                        help='print the wall time per stage (ms per step and share; the '
                             'first step, which loads the compiled code, apart)')
    parser.add_argument('--record', metavar='PATH',
                        help='also write the run as a rosbag2 bag (MCAP) in the new folder PATH')
    parser.add_argument('--record-rate', type=float, metavar='HZ',
                        help='frames per simulated second in the bag (default: 30, the '
                        "node's publish_rate; at most one per step)")
    parser.add_argument('--compare-presets', action='store_true',
                        help='run the scene under every preset it accepts for its duration '
                             '(or --steps/--duration) and print one table: cost per '
                             'simulated second and the difference from exact (or accurate '
                             'where exact does not apply) at the end')
    parser.add_argument('--accuracy', help='preset (fast, balanced, accurate, exact) or a '
                        'YAML/JSON mapping such as "{preset: fast, substeps: 2}"; '
                        'overrides the scene\'s accuracy')
    parser.add_argument('--threads', type=int, default=0, metavar='N',
                        help='threads the compiled kernels share a step among (default 0: '
                             'every core; 1: single-thread kernels); the results are the '
                             'same for every N')
    return parser


def particle_records(world: World) -> list[dict]:
    """Return the final state as JSON-ready records, one per particle."""
    s = world.state.in_id_order()
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
        stop: Optional['_StopRequest'] = None,
        after_step: Optional[Callable[[], None]] = None) -> tuple[float, World]:
    """Step ``world`` ``steps`` times; return the wall-clock seconds and the world to report.

    The steps run on a worker thread (the kernels release the GIL), so the
    calling thread keeps answering signals. ``stop`` is asked before every
    step; once it answers true the run ends at the next step boundary, or,
    if the step in flight has not ended ``STOP_GRACE_S`` after the signal,
    at the last completed step the worker kept: that copy is returned
    instead of ``world`` (a step is never cut in half in what is reported;
    the abandoned one goes on in the background until the process ends).
    ``after_step`` is called after each step, on the worker thread, never
    once the run was abandoned. An exception of a step is raised here.
    """
    start = time.perf_counter()
    worker = _Worker(world, steps, stop, after_step)
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

    def __init__(self, world: World, steps: int, stop: Optional[Callable[[], bool]],
                 after_step: Optional[Callable[[], None]]) -> None:
        super().__init__(name='simulate steps', daemon=True)
        self.world, self.steps, self.stop, self.after_step = world, steps, stop, after_step
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
                if self.after_step is not None:
                    with self._lock:
                        if self._abandoned:
                            break
                        self.after_step()
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


def _calls(*hooks: Optional[Callable[[], None]]) -> Optional[Callable[[], None]]:
    """Return one hook that calls every given one in order (None when none is given)."""
    given = [hook for hook in hooks if hook is not None]
    if len(given) <= 1:
        return given[0] if given else None

    def every() -> None:
        for hook in given:
            hook()
    return every


def check_out(out: str, flag: str = '--out') -> None:
    """Refuse a ``flag`` target (``--out``) that cannot be written, before any step is run.

    A device that fails only when written to (``/dev/full``) can only be
    found at the end; :func:`main` reports that after the summary.
    """
    if out == '':
        raise UsageError(f'{flag}: empty file name')
    path = Path(out)
    if path.is_dir():
        raise UsageError(f'{flag} {out}: Is a directory')
    parent = path.parent
    if not parent.is_dir():
        raise UsageError(f'{flag} {out}: No such file or directory ({parent} is not a '
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
        raise UsageError(f'{flag} {out}: {error.strerror}') from None


def check_pictures(args: argparse.Namespace) -> None:
    """Refuse ``--snapshot``/``--energy-plot`` targets before the run, like ``--out``.

    Also refused: a suffix matplotlib cannot write, and one file named by
    two outputs (the second would overwrite the first).
    """
    asked = (('--snapshot', args.snapshot), ('--energy-plot', args.energy_plot))
    pictures = [(flag, value) for flag, value in asked if value is not None]
    if not pictures:
        return
    from .pictures import picture_format
    for flag, value in pictures:
        check_out(value, flag)
        try:
            picture_format(value)
        except ValueError as error:
            raise UsageError(f'{flag} {value}: {error}') from None
    seen: dict[Path, str] = {}
    for flag, value in ([('--out', args.out)] if args.out is not None else []) + pictures:
        key = Path(value).resolve()
        if key in seen:
            raise UsageError(f'{flag} {value}: also the file of {seen[key]}')
        seen[key] = flag


def check_record(args: argparse.Namespace) -> None:
    """Refuse ``--record`` and ``--record-rate`` values that cannot work, before any step."""
    if args.record_rate is not None:
        if args.record is None:
            raise UsageError('--record-rate needs --record PATH')
        if not (math.isfinite(args.record_rate) and args.record_rate > 0.0):
            raise UsageError(f'--record-rate must be a finite number > 0, got {args.record_rate}')
    if args.record is not None:
        try:
            from .recording.bag import BagTargetError, check_target
        except ImportError as error:
            raise UsageError(f'--record needs {error.name} (pip install -r requirements.txt)'
                             ) from None
        try:
            check_target(args.record)
        except BagTargetError as error:
            raise UsageError(f'--record {args.record}: {error}') from None


def open_recording(args: argparse.Namespace, world: World) -> Any:
    """Return the run's recording (:class:`~.recording.offline.RunRecording`), or None."""
    if args.record is None:
        return None
    from .recording.bag import BagTargetError
    from .recording.definitions import DefinitionError
    from .recording.offline import DEFAULT_RATE, RunRecording
    rate = DEFAULT_RATE if args.record_rate is None else args.record_rate
    try:
        return RunRecording(args.record, world, rate)
    except (BagTargetError, DefinitionError, OSError) as error:
        text = error.strerror if isinstance(error, OSError) and error.strerror else error
        raise UsageError(f'--record {args.record}: {text}') from None


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
    except MemoryError as error:
        # Loading and stepping say where; this is the net for the rest (the
        # summary or the JSON of a huge world).
        print(f'simulate: error: {out_of_memory(error, "writing the results")}',
              file=sys.stderr)
        return EXIT_BAD_INPUT


def _main(argv: Optional[Sequence[str]]) -> int:
    args = None
    try:
        args = build_parser().parse_args(argv)
        if args.steps is not None and args.steps < 0:
            raise UsageError(f'--steps must be >= 0, got {args.steps}')
        if args.duration is not None and not (math.isfinite(args.duration)
                                              and args.duration >= 0):
            raise UsageError(f'--duration must be a finite number >= 0, got {args.duration}')
        set_default_threads(args.threads)
        if args.compare_presets:
            check_compare(args)
        if args.out is not None:
            check_out(args.out)
        check_pictures(args)
        check_record(args)
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
    except MemoryError as error:
        scene_name = getattr(args, 'scene', 'the scene')
        print(f'simulate: error: {scene_name}: {out_of_memory(error, "loading the scene")}',
              file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.explain:
        print(world.explain())
        return 0
    if args.compare_presets:
        return run_comparison(args, scene, steps)
    try:
        recording = open_recording(args, world)
    except UsageError as error:
        print(f'simulate: error: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    start = {'kinetic': world.kinetic_energy(), 'momentum': world.momentum(),
             'energy': world.energy()}
    recorder = None
    if args.energy_plot is not None:
        from .pictures import EnergyRecorder
        recorder = EnergyRecorder(world, steps)
    # The handlers stay until the outputs are written: a second signal exits at
    # once, never leaving half a file (write_result).
    with _StopRequest() as stop:
        try:
            wall_seconds, reported = run(world, steps, stop=stop,
                                         after_step=_calls(recorder, None if recording is None
                                                           else recording.after_step))
        except NonFiniteStateError as error:
            print(f'simulate: error: {scene.name}: {error}', file=sys.stderr)
            if recording is not None:
                recording.finish()
            return 1
        except MemoryError as error:
            doing = f'in step {world.steps + 1} of {steps} ({len(world.state)} particles)'
            print(f'simulate: error: {scene.name}: {out_of_memory(error, doing)}',
                  file=sys.stderr)
            if recording is not None:
                recording.finish()
            return EXIT_BAD_INPUT
        abandoned = reported is not world
        if abandoned:
            print(f'simulate: {signal.Signals(stop.signal).name}: step {world.steps + 1} did '
                  f'not end within {STOP_GRACE_S:g} s and was abandoned; reporting the state '
                  f'after step {reported.steps}', file=sys.stderr)
        code = _report(reported, start, wall_seconds, steps, args, stop, recording, recorder)
    if abandoned:
        # The abandoned step still runs on its thread and cannot be stopped:
        # end the process here, with everything written and flushed.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _report(world: World, start: dict, wall_seconds: float, steps: int,
            args: argparse.Namespace, stop: '_StopRequest', recording: Any,
            recorder: Any) -> int:
    """Print the summary of ``world`` and write its outputs; return the exit code."""
    # The bag is finished before the JSON is made: its last frame is the final state.
    record_error = None if recording is None else recording.finish()
    result = build_result(world, start, wall_seconds)
    if args.profile:
        result['profile'] = profile_record(world)
    if stop.signal is not None:
        result['interrupted'] = True
        result['steps_requested'] = steps
    if not args.quiet:
        if stop.signal is not None:
            print(f'interrupted by {signal.Signals(stop.signal).name} after {world.steps} '
                  f'of {steps} steps')
        print_summary(world, result)
    if args.profile:
        print(world.profile().table())
    sys.stdout.flush()
    if args.out is not None:
        try:
            write_result(args.out, result, stop)
        except OSError as error:
            # Checked before the run; a full disk or /dev/full shows only now.
            print(f'simulate: error: --out {args.out}: {error.strerror}', file=sys.stderr)
            return EXIT_BAD_INPUT
    pictures_written = write_pictures(args, world, recorder)
    if record_error is not None:
        # A full disk mid-run: the run went on, the bag stops where the write failed.
        print(f'simulate: error: --record {args.record}: {record_error}', file=sys.stderr)
    if not pictures_written or record_error is not None:
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


def check_compare(args: argparse.Namespace) -> None:
    """Refuse options ``--compare-presets`` cannot honour (it runs every preset)."""
    for flag, value in (('--accuracy', args.accuracy), ('--snapshot', args.snapshot),
                        ('--energy-plot', args.energy_plot), ('--explain', args.explain),
                        ('--profile', args.profile)):
        if value not in (None, False):
            raise UsageError(f'--compare-presets runs every preset; {flag} cannot be '
                             'combined with it')


def run_comparison(args: argparse.Namespace, scene: Any, steps: int) -> int:
    """Run ``--compare-presets``: print the table, write ``--out``; return the exit code."""
    from .preset_compare import compare_presets, json_record, table
    with _StopRequest() as stop:
        try:
            result = compare_presets(scene, steps, stop)
        except NonFiniteStateError as error:
            print(f'simulate: error: {scene.name}: {error}', file=sys.stderr)
            return 1
        if not args.quiet:
            print(table(result))
        sys.stdout.flush()
        if args.out is not None:
            try:
                with open(args.out, 'w', encoding='utf-8') as handle:
                    json.dump(json_record(result), handle, indent=1)
            except OSError as error:
                print(f'simulate: error: --out {args.out}: {error.strerror}', file=sys.stderr)
                return EXIT_BAD_INPUT
    return EXIT_INTERRUPTED if result['interrupted'] else 0


def write_pictures(args: argparse.Namespace, world: World, recorder: Any) -> bool:
    """Draw and write the pictures asked for; say whether every one was written."""
    if args.snapshot is None and recorder is None:
        return True
    from .pictures import energy_figure, save_figure, snapshot_figure
    figures = []
    if args.snapshot is not None:
        figures.append(('--snapshot', args.snapshot, lambda: snapshot_figure(world)))
    if recorder is not None:
        recorder.finish()
        figures.append(('--energy-plot', args.energy_plot,
                        lambda: energy_figure(recorder.series(), world.scene.name)))
    written = True
    for flag, path, draw in figures:
        try:
            save_figure(draw(), path)
        except OSError as error:
            print(f'simulate: error: {flag} {path}: {error.strerror}', file=sys.stderr)
            written = False
    return written


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


def profile_record(world: World) -> dict:
    """Return the world's step profile as a JSON-ready mapping (times in ms)."""
    profile = world.profile()
    return {'steps': profile.steps, 'first_step_ms': profile.first_step_ms,
            'ms_per_step': profile.ms_per_step,
            'stages': [stage._asdict() for stage in profile.stages]}


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
