"""Compare the accuracy presets on one scene: ``simulate SCENE --compare-presets``.

Runs the scene under every preset it accepts (``exact`` refuses effects
the event mode cannot do exactly), each for the same number of steps
from the same initial state, and reports per preset its cost in wall
seconds per simulated second and how far its end state is from the
reference run's: ``exact``, or ``accurate`` where ``exact`` does not
apply. The position difference is the largest over particles of
|x - x_ref| / r (particles matched by id), the energy difference that
of the total energy (kinetic + potential), in J and over the start's.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Optional

import numpy as np

from .physics.model.accuracy import PRESETS
from .physics.model.scene import Scene
from .physics.model.validation import SceneError
from .physics.step.world import World

ORDER = ('fast', 'balanced', 'accurate', 'exact')


def compare_presets(scene: Scene, steps: int,
                    stop: Optional[Callable[[], bool]] = None) -> dict:
    """Run ``scene`` for ``steps`` steps under each preset; return the comparison.

    The result holds ``reference`` (the preset the others are compared
    with), ``runs`` (one record per preset run, in :data:`ORDER`),
    ``refused`` (preset -> why the scene refuses it) and ``interrupted``
    (``stop`` answered true: the runs after it did not start).
    """
    accepted, refused = {}, {}
    for preset in ORDER:
        try:
            accepted[preset] = scene.with_accuracy(PRESETS[preset])
        except SceneError as error:
            # The reason without the scene's path, which the heading names.
            refused[preset] = str(error).split(': accuracy: ', 1)[-1]
    reference = 'exact' if 'exact' in accepted else 'accurate'
    runs: dict[str, dict] = {}
    interrupted = False
    # The reference first, so a stopped comparison still compares what ran.
    for preset in [reference] + [p for p in ORDER if p in accepted and p != reference]:
        if stop is not None and stop():
            interrupted = True
            break
        runs[preset] = run_preset(preset, accepted[preset], steps, stop)
        interrupted = interrupted or runs[preset]['steps'] < steps
        if interrupted:
            break
    ref = runs.get(reference)
    for preset, record in runs.items():
        record.update(difference(record, ref) if ref is not None else
                      {'position_diff_r': None, 'energy_diff_j': None, 'energy_diff_rel': None})
    return {'scene': scene.name, 'steps': steps, 'dt': scene.dt, 'reference': reference,
            'runs': [runs[p] for p in ORDER if p in runs], 'refused': refused,
            'interrupted': interrupted}


def run_preset(preset: str, scene: Scene, steps: int,
               stop: Optional[Callable[[], bool]]) -> dict:
    """Step ``scene`` (under ``preset``) ``steps`` times or until ``stop``; return cost, end."""
    world = World(scene)
    start_energy = world.energy()['total']
    wall = 0.0
    for _ in range(steps):
        if stop is not None and stop():
            break
        begin = time.perf_counter()
        world.step()
        wall += time.perf_counter() - begin
    profile = world.profile()
    simulated = world.steps * scene.dt
    # The first step loads the compiled code: the steady steps after it are the cost.
    steady = profile.ms_per_step * 1e-3 / scene.dt if world.steps > 1 else \
        (wall / simulated if simulated else math.nan)
    order = np.argsort(world.state.ids)
    return {'preset': preset,
            'steps': world.steps, 'wall_s': wall, 'wall_s_per_sim_s': steady,
            'collisions': world.stats.collisions, 'fallback_steps': world.stats.fallback_steps,
            'energy_start': start_energy, 'energy_end': world.energy()['total'],
            'ids': world.state.ids[order], 'position': world.state.position[order],
            'radius': world.state.radius[order]}


def difference(record: dict, ref: dict) -> dict:
    """Return the largest position difference over r and the energy difference to ``ref``."""
    common, mine, theirs = np.intersect1d(record['ids'], ref['ids'], assume_unique=True,
                                          return_indices=True)
    if common.size:
        gap = np.linalg.norm(record['position'][mine] - ref['position'][theirs], axis=1)
        position = float(np.max(gap / ref['radius'][theirs]))
    else:
        position = 0.0
    energy = record['energy_end'] - ref['energy_end']
    scale = abs(ref['energy_start'])
    return {'position_diff_r': position, 'energy_diff_j': energy,
            'energy_diff_rel': energy / scale if scale > 0 else None}


def _num(value: Optional[float], fmt: str = '.3g') -> str:
    """Format one table cell ('-' for None)."""
    if value is None:
        return '-'
    return '0' if value == 0 else format(value, fmt)


def table(result: dict) -> str:
    """Return the comparison as text: a heading line and one Markdown table."""
    ref = result['reference']
    lines = [f'{result["scene"]}: {result["steps"]} steps of dt = {result["dt"]:g} s under each '
             f'preset, compared with `{ref}` at the end', '',
             '| preset | wall s / sim s | max position diff / r | energy diff J | '
             'energy diff / start | impacts |', '|---|---:|---:|---:|---:|---:|']
    for run in result['runs']:
        name = f'{run["preset"]} (reference)' if run['preset'] == ref else run['preset']
        lines.append(f'| {name} | {_num(run["wall_s_per_sim_s"])} | '
                     f'{_num(run["position_diff_r"])} | {_num(run["energy_diff_j"], "+.3g")} | '
                     f'{_num(run["energy_diff_rel"], "+.3g")} | {run["collisions"]} |')
    for preset, why in result['refused'].items():
        lines.append(f'{preset}: not run ({why})')
    if result['interrupted']:
        lines.append('interrupted: the presets missing above did not run to the end')
    return '\n'.join(lines)


def json_record(result: dict) -> dict:
    """Return the comparison without the end states, ready for JSON."""
    keep = ('preset', 'steps', 'wall_s', 'wall_s_per_sim_s', 'collisions', 'fallback_steps',
            'energy_start', 'energy_end', 'position_diff_r', 'energy_diff_j', 'energy_diff_rel')
    return dict(result, runs=[{k: run[k] for k in keep} for run in result['runs']])
