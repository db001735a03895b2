"""Accuracy settings: how a step trades exactness for time.

A scene's ``accuracy`` key (the runner's ``--accuracy`` flag, the node's
``accuracy`` parameter) is a preset name or a mapping of settings,
optionally based on a preset (``{preset: fast, substeps: 2}``); every
setting not given comes from the preset (``balanced`` if none is named).
Each setting is documented on its field of :class:`AccuracySettings`.
Every numeric setting is bounded (``MAX_SUBSTEPS``, ``MAX_ITERATIONS``,
``MAX_SEPARATION_PASSES``, ``MAX_EVENT_BUDGET``, ``MAX_COLLAPSE_TIME``,
``MAX_SLEEP_TIME``; tabled in docs/scenes.md, "Limits"), so no accepted
value makes a step endless.

======== ===== ======== === ======= ========== ==========
preset   mode  substeps ccd requery ordering   iterations
======== ===== ======== === ======= ========== ==========
fast     step  1        no  --      sequential 8
balanced step  1        yes no      sequential 32
accurate step  4        yes yes     sequential 64
exact    event 1        --  --      --         --
======== ===== ======== === ======= ========== ==========

======== ================= ============= ============ ==========
preset   separation_passes collapse_time event_budget sleep_time
======== ================= ============= ============ ==========
fast     6                 (unused)      (unused)     0.5 s
balanced 6                 (unused)      (unused)     0.5 s
accurate 4                 (unused)      (unused)     off
exact    --                1e-5 s        10           --
======== ================= ============= ============ ==========

Sleeping is on where a settled pile should cost little (``fast``,
``balanced``) and off where exactness matters (``accurate``: a sleeping
particle ignores the last few mm/s of settling; ``exact``: event mode).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, Optional


from .guard import parse_text
from .validation import fail, integer, number, quote, reject_unknown_keys

MODES = ('step', 'event')
ORDERINGS = ('sequential', 'batched')
# Effects the event-driven mode simulates exactly; any other declared
# effect makes it refuse the scene.
EVENT_EFFECTS = ('gravity', 'walls', 'restitution', 'restitution_threshold')


@dataclass(frozen=True)
class AccuracySettings:
    """Tunables of the step pipeline, all in one object (presets in the module doc)."""

    # ``step``: fixed steps of dt through the stage pipeline. ``event``: the
    # exact event-driven mode (``stages/events/event_driven.py``): the world
    # moves from impact to impact, each impact time a closed-form root; only
    # for scenes whose effects it can do exactly (:data:`EVENT_EFFECTS`).
    mode: str = 'step'
    # Step mode: each step of dt is split into this many equal substeps.
    substeps: int = 1
    # Continuous collision detection (step mode): the broadphase reaches
    # radius + |v| dt and every impact, with a particle or a wall, is found
    # at its time of impact inside the step, so a small fast particle never
    # passes through another one (``stages/swept/swept_contacts.py``).
    ccd: bool = True
    # With ccd: a particle an impact sends out of the region its broadphase
    # query covered (its mid-step position, radius |v| dt / 2) is queried
    # again for the rest of its path, so no contact is found late (as an
    # overlap at the next step); costs about 30 % more on a dense gas.
    requery: bool = False
    # How contacts at the same instant sharing a particle are solved.
    # ``sequential``: one after another (colour batches; with ccd in
    # time-of-impact order), which keeps chains exact (Newton's cradle ends
    # at (0, 0, 0, 0, v0); three balls [1, 0, -1] end at [-1, 0, 1]).
    # ``batched``: every such contact gets its impulse from the same
    # velocities at once (Jacobi, shared 1/k by a particle in k contacts,
    # so it never adds energy): independent of the order and identical to
    # ``sequential`` when no particle is in two simultaneous contacts, but a
    # particle struck from two sides at once loses energy (three balls
    # [1, 0, -1] end at [0, 0, 0]). No preset uses it.
    ordering: str = 'sequential'
    # Sweeps of the contact solver per (sub)step; with ccd the rounds of
    # time-of-impact events per step (a chain of k touching balls needs k - 1).
    iterations: int = 32
    # Step mode under gravity: Gauss-Seidel passes of the separation stage per
    # (sub)step, each from the positions the last one left, stopping early once
    # no pair overlaps (without gravity there is one Jacobi pass). Settled
    # piles keep less overlap with more passes (their spread over pours:
    # ``bench stacks --cases pour_spread``); ``accurate``, whose 4 substeps
    # each take their passes, takes 4.
    separation_passes: int = 6
    # Event mode: t_c of the TC model, s. An impact within t_c of either
    # particle's previous impact is treated as elastic, so inelastic collapse
    # (infinitely many impacts in finite time when e < 1) cannot stall the
    # event loop; under gravity such an impact means a particle coming to
    # rest and the step goes to the step solver (see ``event_budget``).
    collapse_time: float = 1e-5
    # Event mode: events (impacts, cell crossings) a step may take per
    # particle (at least MIN_EVENT_BUDGET in all). A step that needs more, or
    # meets what it cannot do exactly under gravity (an impact onto particles
    # resting on others, a collapsing bounce), is rolled back and solved by
    # the EVENT_FALLBACK step solver (counted as ``fallback_steps``).
    event_budget: int = 10
    # Step mode under gravity: seconds an island (particles connected by
    # contacts; walls and static particles do not connect) must stay below
    # the sleep speed 2 |g| dt, in speed and in spin times radius, before it
    # falls asleep (``stages/sleeping/sleep.py``). A sleeping particle is
    # static inside a step until an awake particle comes within reach of its
    # island or a command touches it; then the whole island wakes. Falling
    # asleep zeroes velocity and spin, booked as ``sleep`` energy. None
    # (``null``/``false``): never sleep, the pipeline of a scene without it.
    sleep_time: Optional[float] = 0.5


PRESETS: dict[str, AccuracySettings] = {
    'fast': AccuracySettings(ccd=False, iterations=8),
    'balanced': AccuracySettings(),
    'accurate': AccuracySettings(substeps=4, iterations=64, requery=True, separation_passes=4,
                                 sleep_time=None),
    'exact': AccuracySettings(mode='event'),
}
DEFAULT_PRESET = 'balanced'
# Event mode: a step may always take this many events, however few particles.
MIN_EVENT_BUDGET = 1000

# Bounds of the numeric settings, checked by parse_accuracy (docs/scenes.md,
# "Limits"). Each setting multiplies the work of a step, so each is held
# where a step still ends in bounded time and every count fits an int64.
# Most substeps per step (default 1, accurate 4): each is a whole pass of
# the pipeline, so 10^9 would never finish a step; a finer split is a
# smaller dt.
MAX_SUBSTEPS = 1000
# Most solver sweeps (or ccd rounds) per (sub)step (default 32, accurate
# 64): a chain of k touching balls needs k - 1, so 10^4 covers any chain a
# scene holds in practice; the kernels count sweeps in int64.
MAX_ITERATIONS = 10_000
# Most separation passes per (sub)step under gravity (default 6, accurate 4):
# each visits every contact pair once, as a solver sweep does.
MAX_SEPARATION_PASSES = 10_000
# Most events per particle per step in event mode (default 10): a step may
# take MAX_EVENT_BUDGET x n events before it falls back, so the budget
# bounds the step's time, and 4 x budget x n (the loop's chore limit)
# stays inside int64 for any world up to scene.MAX_SCENE_PARTICLES.
MAX_EVENT_BUDGET = 10_000
# Longest collapse_time t_c, s (default 1e-5): longer than a second would
# make every impact within a second of another elastic.
MAX_COLLAPSE_TIME = 1.0
# Longest sleep_time, s (default 0.5): a larger value is almost surely a
# unit error.
MAX_SLEEP_TIME = 1e6
INTEGER_BOUNDS = {'substeps': MAX_SUBSTEPS, 'iterations': MAX_ITERATIONS,
                  'separation_passes': MAX_SEPARATION_PASSES, 'event_budget': MAX_EVENT_BUDGET}
# The step solver a too-busy event-mode step falls back to.
EVENT_FALLBACK = 'accurate'


def parse_accuracy(value: Any, where: str) -> AccuracySettings:
    """Validate an ``accuracy`` value: a preset name or a settings mapping."""
    if value is None:
        return PRESETS[DEFAULT_PRESET]
    if isinstance(value, str):
        if value not in PRESETS:
            fail(where, f'unknown preset {quote(value)} (known: {", ".join(PRESETS)})')
        return PRESETS[value]
    if not isinstance(value, dict):
        fail(where, f'expected a preset name or a mapping, got {quote(value)}')
    names = [f.name for f in fields(AccuracySettings)]
    reject_unknown_keys(value, ['preset'] + names, where)
    base = parse_accuracy(value.get('preset', DEFAULT_PRESET), f'{where}.preset')
    changes: dict[str, Any] = {}
    for key, most in INTEGER_BOUNDS.items():
        if key in value:
            changes[key] = integer(value[key], f'{where}.{key}', minimum=1, maximum=most)
    for key, known in (('mode', MODES), ('ordering', ORDERINGS)):
        if key in value:
            if value[key] not in known:
                fail(f'{where}.{key}',
                     f'unknown {key} {quote(value[key])} (known: {", ".join(known)})')
            changes[key] = value[key]
    for key in ('ccd', 'requery'):
        if key in value:
            if not isinstance(value[key], bool):
                fail(f'{where}.{key}', f'expected true or false, got {quote(value[key])}')
            changes[key] = value[key]
    if 'collapse_time' in value:
        changes['collapse_time'] = number(value['collapse_time'], f'{where}.collapse_time',
                                          minimum=0.0, maximum=MAX_COLLAPSE_TIME)
    if 'sleep_time' in value:
        changes['sleep_time'] = parse_sleep_time(value['sleep_time'], f'{where}.sleep_time')
    return replace(base, **changes)


def parse_sleep_time(value: Any, where: str) -> Optional[float]:
    """Return seconds (> 0) before an island sleeps, or None for ``null``/``false`` (never)."""
    if value is None or value is False:
        return None
    if value is True:
        fail(where, 'expected seconds (e.g. 0.5) or null/false to turn sleeping off, got true')
    return number(value, where, minimum=0.0, exclusive_minimum=True, maximum=MAX_SLEEP_TIME)


def parse_accuracy_text(text: str, effects: Any, where: str) -> AccuracySettings:
    """Parse a preset name or a YAML/JSON mapping (runner flag, node parameter).

    The result is checked against the scene's ``effects`` (event mode
    refuses what it cannot do exactly).
    """
    value = parse_text(text, where)
    accuracy = parse_accuracy(value, where)
    check_event_mode(accuracy, effects, where)
    return accuracy


def check_event_mode(accuracy: AccuracySettings, effects: Any, where: str) -> None:
    """Refuse a scene the event-driven mode cannot simulate exactly.

    ``effects`` is the scene's :class:`~collision_node.effects.Effects`;
    every declared effect outside :data:`EVENT_EFFECTS` is refused, so an
    effect added later is refused until the event mode learns it.
    """
    if accuracy.mode != 'event':
        return
    unsupported = [f.name for f in fields(effects)
                   if f.name not in EVENT_EFFECTS and getattr(effects, f.name) is not None]
    if unsupported:
        fail(where, f'mode event (preset exact) cannot simulate {", ".join(unsupported)} '
                    f'exactly (it supports {", ".join(EVENT_EFFECTS)}); '
                    'pick a step preset such as accurate')
