"""Figures and the decision table of the accuracy benchmark, built from its results.

Every function here reads the run records of ``accuracy_ladder`` (the
``runs`` of ``results.json``) or the cost-growth records of
``cost_growth``, so the pictures and the table in docs/accuracy.md are
redrawn from the results file alone (``--from-results``) and always
show its numbers. Each figure function returns the matplotlib Figure
(Agg), which the tests inspect: data per panel, label boxes, bar segments.

Scenes are grouped by kind (:data:`KINDS`); each kind has one error
measure (:data:`MEASURES`). A preset's point in a kind is its worst error
over the kind's scenes at each scene's own dt, and its cost the sum of
their wall seconds per simulated second (the wall time one simulated
second of each of the kind's scenes takes).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Optional, Sequence

PRESETS = ('fast', 'balanced', 'accurate', 'exact')
COLOURS = {'fast': 'tab:red', 'balanced': 'tab:blue', 'accurate': 'tab:green',
           'exact': 'black'}

# Kind of scene -> the benchmark's scenes of that kind.
KINDS: dict[str, tuple[str, ...]] = {
    'isolated impacts': ('oblique_pair', 'bullet_target'),
    'chains and cradles': ('cradle_5', 'billiards_break'),
    'gas': ('gas_1k', 'gas_fast'),
    'gravity and bounces': ('bouncing_ball',),
    'piles': ('pile',),
}
# Errors of exactly 0 (the reference itself, round-off-free runs) are drawn here.
ZERO_FLOOR = 1e-16

# Thresholds of what a run gets wrong (the decision table's flags).
# Relative energy change of an elastic scene beyond which it is energy drift.
ENERGY_DRIFT = 1e-9
# Deepest overlap during a run over the smallest radius beyond which it is overlap.
OVERLAP_R = 1e-3
# Final position difference from exact over r beyond which impacts were taken
# at the wrong time or in the wrong order (isolated impacts, chains). Below
# it lies round-off that a chaotic scene amplifies (the billiards break ends
# some 1e-6 r from exact under every ccd preset).
ORDER_R = 1e-4

# Per kind: y-axis label, the per-run error function, and the tolerance a
# preset must meet to be recommended.
MeasureFn = Callable[[dict], Optional[float]]


def _position_over_r(r: dict) -> Optional[float]:
    """Return the final position error against exact over the smallest radius."""
    if r.get('position_error') is None:
        return None
    return r['position_error'] / r['radius_min']


def _overlap_during(r: dict) -> Optional[float]:
    """Return the deepest overlap met during the run over the smallest radius."""
    if r.get('max_penetration') is None:
        return None
    return r['max_penetration'] / r['radius_min']


MEASURES: dict[str, tuple[str, MeasureFn, float]] = {
    'isolated impacts': ('position error vs exact at the end / r', _position_over_r, ORDER_R),
    'chains and cradles': ('position error vs exact at the end / r', _position_over_r,
                           ORDER_R),
    # The gases are chaotic: any change of impact order diverges from the
    # reference by the box size, so their measure is the overlap a run allows.
    'gas': ('deepest overlap during the run / r', _overlap_during, OVERLAP_R),
    'gravity and bounces': ('apex error vs e^(2k) h, over h',
                            lambda r: r.get('apex_error'), 1e-9),
    'piles': ('deepest overlap at the end / r', lambda r: r.get('pile_overlap_r'), 0.05),
}


def base_runs(results: Sequence[dict]) -> list[dict]:
    """Return the runs of the four presets at each scene's own dt (no sweep, no variant)."""
    return [r for r in results if r['accuracy'] in PRESETS and r['dt'] == r['scene_dt']]


def kind_summary(results: Sequence[dict]) -> dict[str, list[dict]]:
    """Return, per kind that ran, one row per preset that ran: error, cost, problems.

    A row holds ``preset``, ``error`` (worst over the kind's scenes),
    ``cost`` (sum of wall s per simulated s), ``scenes``, ``problems`` (what
    it gets wrong, see :func:`problems`) and ``runs``.
    """
    runs = base_runs(results)
    out: dict[str, list[dict]] = {}
    for kind, names in KINDS.items():
        _, measure, _ = MEASURES[kind]
        rows = []
        for preset in PRESETS:
            mine = [r for r in runs if r['scene'] in names and r['accuracy'] == preset]
            errors = [measure(r) for r in mine]
            if not mine or any(e is None for e in errors):
                continue
            worst: dict[str, tuple[float, str, str]] = {}
            for r in mine:
                for name, value, text in problems(r, kind):
                    if name not in worst or value > worst[name][0]:
                        worst[name] = (value, text, r['scene'])
            found = [f'{name} ({text}, {scene})' if len(mine) > 1 else f'{name} ({text})'
                     for name, (_, text, scene) in worst.items()]
            rows.append({'preset': preset, 'error': max(errors),
                         'cost': sum(r['wall_s_per_sim_s'] for r in mine),
                         'scenes': [r['scene'] for r in mine], 'problems': found,
                         'runs': mine})
        if rows:
            out[kind] = rows
    return out


def problems(r: dict, kind: str) -> list[tuple[str, float, str]]:
    """Return what run ``r`` gets wrong, as (problem, size, size as text).

    The problems: tunnelling, overlap, energy drift and impact time/order
    (thresholds :data:`OVERLAP_R`, :data:`ENERGY_DRIFT`, :data:`ORDER_R`).
    """
    found = []
    missed = (r.get('missed_pairs') or 0) + (r.get('missed_walls') or 0)
    if missed > 0:
        found.append(('tunnelling', float(missed), f'{missed} missed'))
    overlap = r.get('pile_overlap_r') if kind == 'piles' else _overlap_during(r)
    if overlap is not None and overlap > OVERLAP_R:
        found.append(('overlap', overlap, f'{_num(overlap)} r'))
    if r.get('energy_rel_error') is not None and r['energy_rel_error'] > ENERGY_DRIFT:
        found.append(('energy drift', r['energy_rel_error'], _num(r['energy_rel_error'])))
    if kind in ('isolated impacts', 'chains and cradles'):
        error = _position_over_r(r)
        if error is not None and error > ORDER_R:
            found.append(('impact time/order', error, f'{_num(error)} r off'))
    return found


def recommend(rows: Sequence[dict], tolerance: float) -> tuple[dict, str]:
    """Return the cheapest row within ``tolerance`` (else the least error) and why."""
    good = [row for row in rows if row['error'] <= tolerance]
    if good:
        best = min(good, key=lambda row: row['cost'])
        return best, f'the cheapest with error <= {_num(tolerance)}'
    best = min(rows, key=lambda row: (row['error'], row['cost']))
    return best, f'none reaches {_num(tolerance)}: the least error'


def _ran(rows: Sequence[dict]) -> list[str]:
    """Return the scenes a kind's rows ran, in the kind's order."""
    return list(dict.fromkeys(name for row in rows for name in row['scenes']))


def _num(value: float) -> str:
    """Format a number as the table prints it (3 significant digits)."""
    return '0' if value == 0 else f'{value:.3g}'


def decision_table(results: Sequence[dict]) -> str:
    """Return the Markdown decision table: per kind, each preset's error, cost, problems."""
    lines = []
    for kind, rows in kind_summary(results).items():
        label, _, tolerance = MEASURES[kind]
        best, why = recommend(rows, tolerance)
        lines += [f'**{kind}** ({", ".join(_ran(rows))}; error: {label})', '',
                  '| preset | error | wall s / sim s | what it gets wrong |',
                  '|---|---:|---:|---|']
        for row in rows:
            wrong = '; '.join(row['problems']) or 'nothing measured'
            lines.append(f'| `{row["preset"]}` | {_num(row["error"])} | '
                         f'{_num(row["cost"])} | {wrong} |')
        cheapest = min(rows, key=lambda row: row['cost'])
        also = '' if cheapest is best else (
            f'; the cheapest, `{cheapest["preset"]}`, costs {_num(cheapest["cost"])} '
            f'with an error of {_num(cheapest["error"])}')
        lines += ['', f'Recommended for {kind}: `{best["preset"]}` ({why}, '
                  f'{_num(best["cost"])} wall s per simulated s{also}).', '']
    return '\n'.join(lines).rstrip('\n')


TABLE_BEGIN = '<!-- decision table: generated by python -m collision_node.bench accuracy -->'
TABLE_END = '<!-- end of decision table -->'


def replace_table(text: str, table: str) -> str:
    """Return ``text`` with the generated decision table between its two markers."""
    if TABLE_BEGIN not in text or TABLE_END not in text:
        raise ValueError(f'docs/accuracy.md: the markers {TABLE_BEGIN!r} and {TABLE_END!r} '
                         'are missing')
    head, rest = text.split(TABLE_BEGIN, 1)
    _, tail = rest.split(TABLE_END, 1)
    return f'{head}{TABLE_BEGIN}\n{table}\n{TABLE_END}{tail}'


def _pyplot() -> Any:
    """Return pyplot on the Agg backend."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def pareto(points: Sequence[tuple[float, float]]) -> list[int]:
    """Return indices of the points no other point beats in both cost and error."""
    order = sorted(range(len(points)), key=lambda k: (points[k][0], points[k][1]))
    front, best = [], math.inf
    for k in order:
        if points[k][1] < best:
            front.append(k)
            best = points[k][1]
    return front


# Candidate label offsets from the marker, points (dx, dy, ha, va), tried in order.
LABEL_OFFSETS = [(d * sx, d * sy, 'left' if sx > 0 else 'right',
                  'bottom' if sy > 0 else 'top')
                 for d in (5, 12, 22, 34) for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))]


def place_labels(ax: Any, points: Sequence[tuple[float, float]], names: Sequence[str]) -> list:
    """Annotate each point with its name where no label overlaps another or a marker.

    Tries :data:`LABEL_OFFSETS` in order and keeps the first position whose
    box (measured by the figure's renderer) stays inside the axes and
    touches no label placed before it and no marker; if none does, the one
    with the least overlap. Call after the layout is fixed.
    """
    renderer = ax.figure.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    marks = [ax.transData.transform(p) for p in points]
    obstacles = [(x - 4, y - 4, x + 4, y + 4) for x, y in marks]
    texts = []
    for (x, y), name in zip(points, names):
        best, best_cost = None, math.inf
        for dx, dy, ha, va in LABEL_OFFSETS:
            text = ax.annotate(name, (x, y), xytext=(dx, dy), textcoords='offset points',
                               ha=ha, va=va, fontsize=8)
            box = text.get_window_extent(renderer)
            cost = sum(_overlap((box.x0, box.y0, box.x1, box.y1), o) for o in obstacles)
            outside = (max(frame.x0 - box.x0, 0) + max(box.x1 - frame.x1, 0)
                       + max(frame.y0 - box.y0, 0) + max(box.y1 - frame.y1, 0))
            cost += 1e3 * outside
            if cost < best_cost:
                if best is not None:
                    best.remove()
                best, best_cost = text, cost
            else:
                text.remove()
            if cost == 0:
                break
        box = best.get_window_extent(renderer)
        obstacles.append((box.x0 - 1, box.y0 - 1, box.x1 + 1, box.y1 + 1))
        texts.append(best)
    return texts


def _overlap(a: tuple, b: tuple) -> float:
    """Return the overlapping area of two boxes (x0, y0, x1, y1)."""
    return max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3])
                                                             - max(a[1], b[1]))


def error_vs_cost_figure(results: Sequence[dict]) -> Any:
    """Return the figure: per kind, each preset's error against its cost, Pareto front drawn."""
    plt = _pyplot()
    summary = kind_summary(results)
    fig, axes = plt.subplots(1, len(summary), figsize=(3.6 * len(summary), 3.9),
                             squeeze=False)
    panels = []
    for ax, (kind, rows) in zip(axes[0], summary.items()):
        label, _, _ = MEASURES[kind]
        points = [(row['cost'], max(row['error'], ZERO_FLOOR)) for row in rows]
        for row, (x, y) in zip(rows, points):
            ax.scatter(x, y, c=COLOURS[row['preset']], s=30, zorder=3)
        front = sorted((points[k] for k in pareto(points)))
        ax.plot(*zip(*front), '--', c='grey', lw=1, zorder=2, label='Pareto front')
        ax.set_xscale('log')
        ax.set_yscale('log')
        xs, ys = [p[0] for p in points], [p[1] for p in points]
        ax.set_xlim(min(xs) / 4, max(xs) * 4)
        ax.set_ylim(min(ys) / 30, max(ys) * 30)
        ax.set_title(f'{kind}\n({", ".join(_ran(rows))})', fontsize=9)
        ax.set_xlabel('wall s per simulated s', fontsize=8)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, which='major', lw=0.3)
        ax.tick_params(labelsize=7)
        panels.append((ax, points, [row['preset'] for row in rows]))
    handles = [plt.Line2D([], [], ls='', marker='o', c=COLOURS[p]) for p in PRESETS]
    handles.append(plt.Line2D([], [], ls='--', c='grey'))
    fig.legend(handles, [*PRESETS, 'Pareto front (no preset is both cheaper and better)'],
               loc='lower center', ncol=len(handles), fontsize=8)
    fig.suptitle('What accuracy costs, per kind of scene (each scene at its own dt; '
                 f'an error of 0 is drawn at {ZERO_FLOOR:g})', fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    for ax, points, names in panels:
        place_labels(ax, points, names)
    return fig


def _stage_names(runs: Sequence[dict]) -> list[str]:
    """Return every stage name in the runs' profiles, in order of first appearance."""
    names: list[str] = []
    for r in runs:
        for name, _ in (r.get('profile') or {}).get('stages', []):
            if name not in names:
                names.append(name)
    return names


def stage_costs(rows: dict) -> dict[str, float]:
    """Return a summary row's wall s per simulated s spent in each stage (profile, steady)."""
    out: dict[str, float] = {}
    for r in rows['runs']:
        for name, ms_per_step in r['profile']['stages']:
            out[name] = out.get(name, 0.0) + ms_per_step * 1e-3 / r['dt']
    return out


def where_time_goes_figure(results: Sequence[dict]) -> Any:
    """Return the figure: per kind, a bar per preset stacked by the step's stages.

    Each segment's height is the stage's wall seconds per simulated second
    (the profile's steady ms per step over dt, summed over the kind's
    scenes); each rectangle's gid is ``preset|stage``.
    """
    plt = _pyplot()
    summary = {kind: [row for row in rows if all(r.get('profile') for r in row['runs'])]
               for kind, rows in kind_summary(results).items()}
    summary = {kind: rows for kind, rows in summary.items() if rows}
    names = _stage_names([r for rows in summary.values() for row in rows for r in row['runs']])
    palette = [plt.get_cmap('tab10')(k) for k in range(10)] + \
        [plt.get_cmap('Dark2')(k) for k in range(8)]
    colour = {name: palette[k % len(palette)] for k, name in enumerate(names)}
    fig, axes = plt.subplots(1, len(summary), figsize=(3.3 * len(summary), 4.6),
                             squeeze=False)
    for ax, (kind, rows) in zip(axes[0], summary.items()):
        for k, row in enumerate(rows):
            bottom = 0.0
            for name, value in stage_costs(row).items():
                bar = ax.bar(k, value, bottom=bottom, color=colour[name], width=0.7,
                             edgecolor='white', lw=0.3)
                bar.patches[0].set_gid(f'{row["preset"]}|{name}')
                bottom += value
        ax.set_xticks(range(len(rows)), [row['preset'] for row in rows], fontsize=8)
        ax.set_title(f'{kind}\n({", ".join(_ran(rows))})', fontsize=9)
        ax.set_ylabel('wall s per simulated s', fontsize=8)
        ax.tick_params(axis='y', labelsize=7)
    handles = [plt.Rectangle((0, 0), 1, 1, color=colour[name]) for name in names]
    fig.legend(handles, names, loc='lower center', ncol=min(len(names), 6), fontsize=8)
    fig.suptitle('Where the time goes: wall time per stage of the step (steady steps, '
                 'World.profile)', fontsize=10)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    return fig


def fitted_exponent(counts: Sequence[float], step_seconds: Sequence[float]) -> float:
    """Return the least-squares slope of log(time per step) against log(N); 1 is linear."""
    import numpy as np
    x, y = np.log(np.asarray(counts, float)), np.log(np.asarray(step_seconds, float))
    return float(np.polyfit(x, y, 1)[0])


def cost_growth_figure(growth: Sequence[dict]) -> Any:
    """Return the figure: ns per particle-step against N, per preset, gas and pile (log-log).

    Each line's legend entry carries the fitted exponent of the time per
    step against N (1.0 is linear; the drawn ns per particle-step then is flat).
    """
    plt = _pyplot()
    scenes = {g['scene']: g['title'] for g in growth}
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.2), squeeze=False)
    for ax, (scene, title) in zip(axes[0], scenes.items()):
        for preset in PRESETS:
            mine = sorted((g for g in growth if g['scene'] == scene and g['preset'] == preset),
                          key=lambda g: g['count'])
            if not mine:
                continue
            counts = [g['count'] for g in mine]
            ns = [g['ns_per_particle_step'] for g in mine]
            if len(mine) > 1:
                exponent = fitted_exponent(counts, [v * n for v, n in zip(ns, counts)])
                label = f'{preset}: step time ~ N^{exponent:.2f}'
            else:
                label = f'{preset} (one N)'
            ax.plot(counts, ns, 'o-', c=COLOURS[preset], label=label)
        ax.set_xscale('log')
        ax.set_yscale('log')
        ax.set_xlabel('particles N', fontsize=8)
        ax.set_ylabel('wall ns per particle-step', fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.grid(True, which='major', lw=0.3)
        ax.legend(fontsize=7)
    fig.suptitle('How cost grows with the number of particles (steady steps, World.profile)',
                 fontsize=10)
    fig.tight_layout()
    return fig
