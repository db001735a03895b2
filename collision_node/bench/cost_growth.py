"""How the cost of a step grows with the number of particles, per preset.

Two scenes at every N, each at a density that does not change with N:
the gas of ``bench throughput`` (3-D, elastic, r = 5 cm at the 4.2 %
volume fraction of ``scenes/gas_10k.yaml``, dt = 1/240 s) and a resting
pile (2-D, :func:`collision_node.scenarios.resting_pile`: discs of
r = 5 cm packed in :data:`PILE_ROWS` rows on a floor under gravity, e = 0,
as wide as N needs, so each disc carries the same load at every N).
Each run takes :data:`STEPS` steps; its cost is the profile's steady wall
time per step (``World.profile``, the first step apart) over N, in ns.
Counts above :data:`LARGE_COUNT` run only :data:`CHEAP_PRESETS`, and a
preset stops growing once one of its steps took :data:`STEP_LIMIT_S` (its
larger N would not finish on a shared machine); both are recorded as
skipped, with the reason.
"""

from __future__ import annotations

import time
from typing import Callable, Optional, Sequence

from ..physics.model.accuracy import PRESETS as SETTINGS
from ..physics.model.scene import Scene, parse_scene
from ..physics.step.world import World
from ..scenarios import resting_pile
from .throughput import gas_scene

PRESETS = ('fast', 'balanced', 'accurate', 'exact')
COUNTS = (1_000, 10_000, 100_000, 1_000_000)
QUICK_COUNTS = (200, 1_000)
# Steps per run: the first (loads the compiled code) and the timed ones after it.
STEPS = 4
# s: a preset whose steady step took this long runs no larger N.
STEP_LIMIT_S = 15.0
# Counts above this run only the cheap presets: on 2 shared cores a step of
# `accurate` or `exact` at 10^6 particles takes minutes.
LARGE_COUNT = 100_000
CHEAP_PRESETS = ('fast', 'balanced')
# Rows of the resting pile (its width grows with N).
PILE_ROWS = 20

SCENES: dict[str, str] = {
    'gas': '3-D elastic gas, 4.2 % volume fraction (as gas_10k)',
    'pile': f'2-D resting pile, {PILE_ROWS} rows of discs on a floor (e = 0)',
}


def build(scene: str, count: int) -> Scene:
    """Return the growth scene ``scene`` (``gas`` or ``pile``) with about ``count`` particles."""
    if scene == 'gas':
        return parse_scene(gas_scene(count), f'growth:gas_{count}')
    per_row = max(1, count // PILE_ROWS)
    return parse_scene(resting_pile(rows=PILE_ROWS, per_row=per_row), f'growth:pile_{count}')


def run_growth(counts: Sequence[int] = COUNTS, steps: int = STEPS,
               step_limit_s: float = STEP_LIMIT_S,
               progress: Optional[Callable[[str], None]] = None) -> list[dict]:
    """Run every scene, preset and count; return one record per run (and per skip)."""
    records = []
    for scene in SCENES:
        stopped: dict[str, float] = {}
        for count in counts:
            base = build(scene, count)
            for preset in PRESETS:
                record = {'scene': scene, 'title': SCENES[scene], 'preset': preset,
                          'count': len(base.initial)}
                if preset in stopped:
                    record['skipped'] = (f'a step took {stopped[preset]:.3g} s at a smaller N '
                                         f'(limit {step_limit_s:g} s)')
                elif count > LARGE_COUNT and preset not in CHEAP_PRESETS:
                    record['skipped'] = (f'N > {LARGE_COUNT:,} runs only '
                                         f'{" and ".join(CHEAP_PRESETS)}')
                if 'skipped' in record:
                    records.append(record)
                    continue
                if progress is not None:
                    progress(f'growth {scene} N={record["count"]} {preset}')
                world = World(base.with_accuracy(SETTINGS[preset]))
                start = time.perf_counter()
                world.step(steps)
                profile = world.profile()
                step_s = profile.ms_per_step * 1e-3
                record.update(steps=steps, wall_s=time.perf_counter() - start,
                              ms_per_step=profile.ms_per_step,
                              ns_per_particle_step=step_s / record['count'] * 1e9,
                              stages=[[s.name, s.ms_per_step] for s in profile.stages])
                records.append(record)
                if step_s > step_limit_s:
                    stopped[preset] = step_s
    return records


def measured(records: Sequence[dict]) -> list[dict]:
    """Return the records of runs that ran (not skipped)."""
    return [r for r in records if 'skipped' not in r]
