"""Pictures of a run: the state drawn to scale, and where the energy went.

``snapshot_figure`` draws a world's particles as circles of their true
radius in the x-y plane (a 3-D scene is projected on it), static ones grey,
the walls' planes as lines, axes in metres at equal aspect.
``EnergyRecorder`` samples a world's energy balance while it runs (at most
``ENERGY_SAMPLES`` points) and ``energy_figure`` stacks it: the losses booked
per effect at the bottom, potential and kinetic energy above them, so the
top of the stack meets the line of the energy put in (start + spawned +
commanded) wherever the balance holds. Both return a matplotlib figure
(made without pyplot, so no display or GUI backend is involved; png is
rendered by Agg) that ``save_figure`` writes; the runner's
``--snapshot`` and ``--energy-plot`` use them. Imports no ROS module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
from matplotlib.collections import EllipseCollection
from matplotlib.figure import Figure

from .physics.step.world import World

# Most energy samples a run keeps; a longer run samples every k-th step.
ENERGY_SAMPLES = 2000
# Width of both pictures, inches, and their resolution, dots per inch.
FIGURE_WIDTH_IN = 9.0
FIGURE_DPI = 100
ENERGY_HEIGHT_IN = 5.0
# Height over width of the snapshot's drawing area is held within these bounds.
SNAPSHOT_ASPECT = (0.3, 1.5)
# Space around the drawn content, as a share of its larger side.
SNAPSHOT_MARGIN = 0.04
STATIC_COLOUR = '0.6'
WALL_COLOUR = 'black'
# Colours of the usual effects' losses; others take the next free colour.
LOSS_COLOURS = {'restitution': 'tab:red', 'walls': 'tab:brown', 'friction': 'tab:orange',
                'drag': 'tab:purple', 'separation': 'tab:pink', 'sleep': 'tab:olive'}
SPARE_COLOURS = ('tab:cyan', 'tab:gray', 'gold', 'navy', 'lime', 'maroon')


def picture_formats() -> dict[str, str]:
    """Return the file formats the pictures can be written in (suffix -> name)."""
    return Figure().canvas.get_supported_filetypes()


def picture_format(path: str) -> str:
    """Return the format a picture named ``path`` is written in (its suffix; png if none).

    Raises ``ValueError`` naming the formats that exist for any other suffix.
    """
    suffix = Path(path).suffix.lower().lstrip('.')
    if not suffix:
        return 'png'
    formats = picture_formats()
    if suffix not in formats:
        raise ValueError(f'unknown picture format .{suffix} (one of '
                         f'{", ".join(sorted(formats))})')
    return suffix


def save_figure(figure: Figure, path: str) -> None:
    """Write ``figure`` to ``path`` in the format its suffix names (png if none)."""
    figure.savefig(path, format=picture_format(path), dpi=FIGURE_DPI)


# ---------------------------------------------------------------- snapshot


def view_box(world: World) -> tuple[np.ndarray, np.ndarray]:
    """Return the x-y extent (low, high), m, a snapshot of ``world`` shows.

    It holds every particle whole and the scene's wall planes, plus a
    margin. Only where the planes would make the picture more elongated
    than ``SNAPSHOT_ASPECT`` allows (the 20 m lid over a 1.6 m wide pile)
    are the planes of that axis farther from the particles than the
    particles' own extent left out of view, so the particles do not shrink
    to dots. Without particles, the planes alone (or a 2 m square).
    """
    state = world.state
    planes = _planes_xy(world)
    if len(state):
        xy, r = state.position[:, :2], state.radius[:, None]
        particles = ((xy - r).min(axis=0), (xy + r).max(axis=0))
    else:
        particles = (np.full(2, np.inf), np.full(2, -np.inf))
    low, high = particles[0].copy(), particles[1].copy()
    for axis, at in planes:
        low[axis], high[axis] = min(low[axis], at), max(high[axis], at)
    if len(state):
        reach = float((particles[1] - particles[0]).max())
        size = high - low
        if size[1] > SNAPSHOT_ASPECT[1] * size[0]:
            elongated = [1]
        elif size[1] < SNAPSHOT_ASPECT[0] * size[0]:
            elongated = [0]
        else:
            elongated = []
        for axis in elongated:
            near = [at for plane_axis, at in planes if plane_axis == axis
                    and particles[0][axis] - reach <= at <= particles[1][axis] + reach]
            low[axis] = min([particles[0][axis]] + near)
            high[axis] = max([particles[1][axis]] + near)
    for axis in range(2):
        if not low[axis] < high[axis]:
            centre = 0.5 * (low[axis] + high[axis]) if math.isfinite(low[axis]) else 0.0
            low[axis], high[axis] = centre - 1.0, centre + 1.0
    margin = SNAPSHOT_MARGIN * float((high - low).max())
    return low - margin, high + margin


def _planes_xy(world: World) -> list[tuple[int, float]]:
    """Return the scene's wall planes across the x-y plane as (axis 0 or 1, position)."""
    walls = world.scene.effects.walls
    if walls is None:
        return []
    return [(axis, at) for axis, at, _ in walls.planes(world.scene.dimensions) if axis < 2]


def _wall_segments(world: World, low: np.ndarray, high: np.ndarray) -> list[np.ndarray]:
    """Return each wall plane in view as a segment [[x0, y0], [x1, y1]], m.

    A plane x = c runs between the planes y = low and y = high where those
    exist, else to the edge of the view; likewise y = c.
    """
    walls = world.scene.effects.walls
    segments = []
    for axis, at in _planes_xy(world):
        if not low[axis] <= at <= high[axis]:
            continue
        other = 1 - axis
        start = max(float(walls.low[other]), float(low[other]))
        end = min(float(walls.high[other]), float(high[other]))
        if start >= end:
            continue
        segment = np.empty((2, 2))
        segment[:, axis] = at
        segment[:, other] = (start, end)
        segments.append(segment)
    return segments


def snapshot_figure(world: World, title: Optional[str] = None) -> Figure:
    """Return a figure of ``world``'s particles and walls to scale in the x-y plane.

    Dynamic particles are coloured by speed (with a colour bar), static
    ones grey; every circle has the particle's radius in metres
    (``EllipseCollection`` in data units), and the axes have equal aspect,
    so one metre spans as many pixels along x as along y. The collections
    carry the gids ``dynamic`` and ``static``, the wall lines ``wall``.
    """
    state = world.state
    low, high = view_box(world)
    aspect = float(np.clip((high[1] - low[1]) / (high[0] - low[0]), *SNAPSHOT_ASPECT))
    figure = Figure(figsize=(FIGURE_WIDTH_IN, 1.2 + 7.0 * aspect), dpi=FIGURE_DPI,
                    layout='constrained')
    axes = figure.add_subplot()
    xy = state.position[:, :2]
    static = state.inv_mass == 0.0
    speed = np.linalg.norm(state.velocity, axis=1)
    for gid, rows in (('static', static), ('dynamic', ~static)):
        if not rows.any():
            continue
        diameters = 2.0 * state.radius[rows]
        circles = EllipseCollection(diameters, diameters, np.zeros(int(rows.sum())),
                                    units='xy', offsets=xy[rows],
                                    offset_transform=axes.transData, edgecolors='black',
                                    linewidths=0.3)
        circles.set_gid(gid)
        if gid == 'static':
            circles.set_facecolor(STATIC_COLOUR)
        else:
            circles.set_array(speed[rows])
            circles.set_cmap('viridis')
            circles.set_clim(0.0, max(float(speed[rows].max()), 1e-9))
            figure.colorbar(circles, ax=axes, label='speed (m/s)', shrink=0.8)
        axes.add_collection(circles, autolim=False)
    for segment in _wall_segments(world, low, high):
        axes.plot(segment[:, 0], segment[:, 1], color=WALL_COLOUR, linewidth=2.0,
                  solid_capstyle='butt', gid='wall')
    axes.set_xlim(low[0], high[0])
    axes.set_ylim(low[1], high[1])
    axes.set_aspect('equal')
    axes.set_xlabel('x (m)')
    axes.set_ylabel('y (m)')
    projected = ', projected on x-y' if world.scene.dimensions == 3 else ''
    axes.set_title(title or f'{world.scene.name}: {len(state)} particles at '
                   f't = {world.time:g} s{projected}')
    return figure


# ---------------------------------------------------------------- energy


@dataclass(frozen=True)
class EnergySeries:
    """A run's energy balance at its samples, J (``time`` in s).

    At every sample ``kinetic_linear + kinetic_rotational + potential +
    sum(losses)`` equals ``budget`` (start + spawned + commanded) plus
    ``balance_error``. A loss an effect had not booked yet is 0 there.
    """

    time: np.ndarray
    kinetic_linear: np.ndarray
    kinetic_rotational: np.ndarray
    potential: np.ndarray
    losses: dict[str, np.ndarray]
    budget: np.ndarray
    balance_error: np.ndarray

    def stack(self) -> list[tuple[str, np.ndarray]]:
        """Return the bands bottom to top: each effect's loss, potential, kinetic.

        Potential and rotational kinetic energy are bands only where they are
        not zero throughout (a scene with gravity, with spin).
        """
        bands = [(name, values) for name, values in self.losses.items()]
        if self.potential.any():
            bands.append(('potential', self.potential))
        if self.kinetic_rotational.any():
            bands.append(('kinetic_rotational', self.kinetic_rotational))
        bands.append(('kinetic_linear', self.kinetic_linear))
        return bands


class EnergyRecorder:
    """Samples ``World.energy()`` while a world runs, at most ``max_samples`` times.

    Call it once before the run (the start) and after every step; it keeps
    every ``stride``-th step, chosen from the ``steps`` planned so that the
    samples fit, and ``finish`` adds the last state reached if it was not a
    sample (an interrupted run included).
    """

    def __init__(self, world: World, steps: int, max_samples: int = ENERGY_SAMPLES) -> None:
        """Plan the samples of a run of ``steps`` steps and take the first."""
        if max_samples < 2:
            raise ValueError(f'max_samples must be >= 2, got {max_samples}')
        self.world = world
        self.stride = max(1, math.ceil(steps / (max_samples - 1)))
        self._samples: list[tuple[int, float, dict]] = []
        self._take()

    def _take(self) -> None:
        world = self.world
        self._samples.append((world.steps, world.time, world.energy()))

    def __call__(self) -> None:
        """Take a sample if the world's step count is due."""
        if self.world.steps % self.stride == 0:
            self._take()

    def sample(self) -> None:
        """Take a sample now (after a spawn or a command, say)."""
        self._take()

    def finish(self) -> None:
        """Take the state reached unless the last sample already holds it."""
        if self._samples[-1][0] != self.world.steps:
            self._take()

    def series(self) -> EnergySeries:
        """Return the samples taken so far as arrays."""
        reports = [report for _, _, report in self._samples]
        names: list[str] = []
        for report in reports:
            names += [name for name in report['dissipated'] if name not in names]

        def column(key: str) -> np.ndarray:
            return np.array([report[key] for report in reports], dtype=float)

        losses = {name: np.array([report['dissipated'].get(name, 0.0) for report in reports])
                  for name in names}
        return EnergySeries(
            time=np.array([t for _, t, _ in self._samples]),
            kinetic_linear=column('kinetic_linear'),
            kinetic_rotational=column('kinetic_rotational'),
            potential=column('potential'), losses=losses,
            budget=column('start') + column('spawned') + column('commanded'),
            balance_error=column('balance_error'))


_BAND_LABELS = {'potential': 'potential', 'kinetic_linear': 'kinetic',
                'kinetic_rotational': 'kinetic (rotation)'}
_BAND_COLOURS = {'potential': 'tab:green', 'kinetic_linear': 'tab:blue',
                 'kinetic_rotational': 'lightskyblue'}


def energy_figure(series: EnergySeries, title: str = 'energy') -> Figure:
    """Return a stacked plot of ``series`` over time.

    The bands, bottom to top, are the losses per effect (cumulative since
    the start), potential and kinetic energy; each band's upper edge is a
    line with gid ``top:<band>``, and the energy put in (start + spawned +
    commanded) is the dashed line with gid ``budget``. Where the balance
    holds, the stack's top lies on that line.
    """
    figure = Figure(figsize=(FIGURE_WIDTH_IN, ENERGY_HEIGHT_IN), dpi=FIGURE_DPI,
                    layout='constrained')
    axes = figure.add_subplot()
    lower = np.zeros_like(series.time)
    spare = iter(SPARE_COLOURS * (1 + len(series.losses) // len(SPARE_COLOURS)))
    for name, values in series.stack():
        upper = lower + values
        colour = _BAND_COLOURS.get(name) or LOSS_COLOURS.get(name) or next(spare)
        label = _BAND_LABELS.get(name, f'lost to {name}')
        axes.fill_between(series.time, lower, upper, color=colour, alpha=0.75,
                          linewidth=0, label=label)
        axes.plot(series.time, upper, color=colour, linewidth=0.8, gid=f'top:{name}')
        lower = upper
    axes.plot(series.time, series.budget, color='black', linestyle='--', linewidth=1.2,
              gid='budget', label='energy put in (start + spawned + commanded)')
    worst = float(np.abs(series.balance_error).max()) if series.time.size else 0.0
    axes.set_title(f'{title}: largest balance error {worst:.2g} J')
    axes.set_xlabel('time (s)')
    axes.set_ylabel('energy (J)')
    if series.time.size > 1:
        axes.set_xlim(series.time[0], series.time[-1])
    axes.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize='small')
    return figure
