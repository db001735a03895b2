"""Scaling: cost per particle-step and parallel efficiency for 1, 2, ... threads.

``python -m collision_node.bench scaling`` steps the 3-D elastic gas (10 %
volume fraction, dt = 1/240 s; 10k, 100k and 1M particles), the 3-D pour
of 10,000 spheres (dt = 1/60 s, pour and settling) and the shipped 2-D
pile (240 discs) at each thread count, in one process, after warm-up
steps (the first step loads the compiled code). It prints the wall ns per
particle-step, the speed-up over one thread and the parallel efficiency
(speed-up / threads), whether the final state is bit-identical to the
one-thread run's (it must be), and how many of the timed steps searched the
pair list afresh (each costs several plain steps; a gas case times at least
``GAS_MIN_STEPS`` steps so that several fall in its window, as in a long
run). The memory column is a gas case of at least ``MEMORY_FROM``
particles run again alone, in a fresh process (kernels loaded and the
scene generated first): its peak resident memory over what it held before
the world was built, per particle. In the timing process an earlier case's freed memory, kept for
reuse (``step/memory.py``), would count against the case that reuses it.

A world of at least ``SPATIAL_ORDER_MIN_PARTICLES`` keeps its rows in
cell order (``physics/stages/ordering``), renumbered at each full pair
search. ``--id-order`` also times each gas with that order turned off: its
rows stay in id order, which for the generated gas is a random order in
space, so every pair reads its partner from a random place in memory. The
two rows side by side say what the order gains.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import resource
import subprocess
import sys
import time
from typing import Callable

import numpy as np

from ..physics.model.scene import parse_scene
from ..physics.model.validation import SceneError
from ..physics.step import threads as thread_count
from ..physics.step.kernels import prepare
from ..physics.step.world import World
from ..scenarios import pour3d, shipped_pile
from .throughput import gas_scene

DEFAULT_GAS_COUNTS = (10_000, 100_000, 1_000_000)
GAS_FRACTION = 0.1
POUR_COUNT = 10_000
# Particle-steps timed per gas case (the steps of a count: this over the count, at least
# GAS_MIN_STEPS).
GAS_WORK = 2e6
# Fewest timed steps of a gas case: the pair list is searched afresh every few steps (about
# one step in seven in the gas) and each search costs several plain steps, so a window of
# a few steps holds one search or none by chance; this many hold several, as a long run does.
GAS_MIN_STEPS = 30


def _state_digest(world: World) -> str:
    """Return a short digest of the positions and velocities in id order, bit for bit."""
    state = world.state.in_id_order()
    digest = hashlib.sha256(np.ascontiguousarray(state.position).tobytes())
    digest.update(np.ascontiguousarray(state.velocity).tobytes())
    return digest.hexdigest()[:12]


def in_id_order(world: World) -> World:
    """Turn ``world``'s spatial order off: its rows stay in id order at any size."""
    if world.pipeline.spatial_order is not None:
        world.pipeline.spatial_order.min_particles = sys.maxsize
    return world


def _resident_bytes() -> int:
    """Return this process's resident memory now, bytes (Linux /proc; 0 elsewhere)."""
    try:
        with open('/proc/self/statm') as statm:
            return int(statm.read().split()[1]) * os.sysconf('SC_PAGE_SIZE')
    except (OSError, ValueError, IndexError):
        return 0


def _peak_bytes() -> int:
    """Return this process's peak resident memory so far, bytes.

    Linux's VmHWM, which ``_forget_peak`` resets; ``ru_maxrss`` (elsewhere)
    also counts the parent's resident memory when the process was forked.
    """
    try:
        with open('/proc/self/status') as status:
            for line in status:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


# Gas cases of at least this many particles measure their memory alone, in a fresh process.
MEMORY_FROM = 100_000


def case_memory(count: int, preset: str, threads: int, steps: int, id_order: bool) -> float:
    """Return the peak bytes per particle of a gas case run alone in a fresh process."""
    code = ('from collision_node.bench.scaling import print_case_memory\n'
            f'print_case_memory({count}, {preset!r}, {threads}, {steps}, {id_order})\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True)
    return float(done.stdout.split()[-1])


def print_case_memory(count: int, preset: str, threads: int, steps: int,
                      id_order: bool) -> None:
    """Step one gas case ``steps`` steps; print its peak bytes per particle (a fresh process)."""
    prepare()
    scene = parse_scene(dict(gas_scene(count, fraction=GAS_FRACTION), accuracy=preset), 'gas')
    _forget_peak()
    before = _resident_bytes()
    world = World(scene, threads=threads)
    if id_order:
        world = in_id_order(world)
    world.step(steps)
    print((_peak_bytes() - before) / count)


def _forget_peak() -> None:
    """Start the process's peak resident memory afresh from now (Linux; elsewhere nothing)."""
    try:
        with open('/proc/self/clear_refs', 'w') as clear_refs:
            clear_refs.write('5')
    except OSError:
        pass


def _pair_searches(world: World) -> int:
    """Return the full pair searches of the world's pair list so far (0 without one).

    The list is the broadphase's, or the swept stage's own (``balanced``, ``accurate``).
    """
    return sum(int(getattr(stage, 'searches', 0)) for stage in world.pipeline.stages)


def time_case(make: Callable[[], object], threads: int, warmup: int, steps: int,
              adjust: Callable[[World], World] = lambda world: world) -> dict:
    """Step a fresh world of ``make()`` on ``threads``; return its timing and final digest.

    ``adjust``: applied to the world before its first step (``in_id_order``).
    """
    world = adjust(World(make(), threads=threads))
    world.step(warmup)
    searches = _pair_searches(world)
    start, cpu_start = time.perf_counter(), time.process_time()
    world.step(steps)
    seconds = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    searches = _pair_searches(world) - searches
    n = len(world.state)
    return {'threads': threads, 'particles': n, 'steps': steps,
            'ns': seconds / (steps * n) * 1e9, 'cpu_ns': cpu / (steps * n) * 1e9,
            'ms': seconds / steps * 1e3, 'digest': _state_digest(world), 'searches': searches}


def cases(args: argparse.Namespace) -> list[tuple]:
    """Return the cases to time, each a tuple.

    (label, scene factory, warm-up steps, timed steps, world adjustment,
    memory case): the memory case is (count, preset, id order) for a gas of
    at least ``MEMORY_FROM`` particles, else None.
    """
    out = []
    for preset in args.presets:
        for count in sorted(args.counts):
            steps = max(GAS_MIN_STEPS, int(GAS_WORK / count))

            def make(c=count, p=preset):
                return parse_scene(dict(gas_scene(c, fraction=GAS_FRACTION), accuracy=p), 'gas')
            weighed = count >= MEMORY_FROM
            out.append((f'gas {count:,} ({preset})', make, 3, steps, _as_built,
                        (count, preset, False) if weighed else None))
            if args.id_order:
                out.append((f'gas {count:,} ({preset}, id order)', make, 3, steps,
                            in_id_order, (count, preset, True) if weighed else None))
    for preset in args.presets:
        if args.pour_steps:
            out.append((f'pour {POUR_COUNT:,} ({preset})',
                        lambda p=preset: pour3d(POUR_COUNT, accuracy=p), 1, args.pour_steps,
                        _as_built, None))
        if args.pile_steps:
            out.append((f'pile 240 ({preset})', lambda p=preset: shipped_pile(p), 1,
                        args.pile_steps, _as_built, None))
    return out


def _as_built(world: World) -> World:
    """Return ``world`` as the scene built it."""
    return world


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Declare the subcommand's options."""
    parser.add_argument('--thread-counts', type=int, nargs='+', default=None,
                        help='thread counts to time (default: 1 up to every core)')
    parser.add_argument('--counts', type=int, nargs='+', default=list(DEFAULT_GAS_COUNTS),
                        help='gas particle counts (default: 10000 100000 1000000)')
    parser.add_argument('--presets', nargs='+', default=['fast', 'balanced'],
                        help='accuracy presets (default: fast balanced)')
    parser.add_argument('--pour-steps', type=int, default=240,
                        help='timed steps of the 3-D pour after its first (default 240; '
                             '0: no pour)')
    parser.add_argument('--pile-steps', type=int, default=480,
                        help='timed steps of the shipped pile after its first (default 480; '
                             '0: no pile)')
    parser.add_argument('--id-order', action='store_true',
                        help='also time each gas with its rows kept in id order (the spatial '
                             'order off)')


def run(args: argparse.Namespace) -> int:
    """Time every case at every thread count; print the Markdown table."""
    counts = args.thread_counts or list(range(1, thread_count.available() + 1))
    try:
        for count in counts:
            thread_count.resolve(count, '--thread-counts')
    except SceneError as error:
        print(f'bench scaling: {error}', file=sys.stderr)
        return 2
    # Compiled (or loaded) before any case: a first start's compile is no case's time.
    compile_seconds = prepare()
    load = os.getloadavg()
    print(f'Parallel step: {os.cpu_count()} cores, numba pool of {thread_count.available()} '
          'threads, load average '
          f'{load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; wall time per particle-step after '
          'warm-up steps, speed-up and efficiency against 1 thread in the same run')
    print()
    print('| case | threads | steps | ms per step | ns per particle-step | '
          'CPU ns per particle-step | speed-up | efficiency | same state as 1 thread | '
          'peak memory per particle, alone (B) | full pair searches |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|')
    identical = True
    for label, make, warmup, steps, adjust, weighed in cases(args):
        base = None
        for count in counts:
            row = time_case(make, count, warmup, steps, adjust)
            base = base or row
            same = row['digest'] == base['digest']
            identical &= same
            speedup = base['ns'] / row['ns']
            memory = None if weighed is None else case_memory(
                weighed[0], weighed[1], count, warmup + steps, weighed[2])
            print(f'| {label} | {count} | {steps} | {row["ms"]:.3f} | {row["ns"]:.1f} '
                  f'| {row["cpu_ns"]:.1f} | {speedup:.2f}x | {speedup / count:.0%} '
                  f'| {"yes" if same else "NO"} | {"-" if memory is None else f"{memory:.0f}"} '
                  f'| {row["searches"]} |',
                  flush=True)
    print()
    print(f'numba threading layer: {thread_count.layer()}; compiling or loading the kernels '
          f'before the first case took {compile_seconds:.1f} s')
    return 0 if identical else 1
