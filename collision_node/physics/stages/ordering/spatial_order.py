"""Rows in spatial order: a large world renumbers its rows along space at each full search.

A contact reads both particles' rows; in a world numbered in random order
(a generated gas, a pour) every partner sits at a random place in memory,
and past the caches that read costs more than the contact's arithmetic.
So a world of at least ``SPATIAL_ORDER_MIN_PARTICLES`` particles puts its
rows in cell order (``order_kernels.cell_order``) just before each full
pair search of its pair list, when the list is rebuilt anyway: the rows
move, the ids stay. Every per-row array of the state and of the step moves
with them, and every stage of the pipeline hears of it (``rows_moved``)
to drop what it kept by row. The order depends on the positions alone, so
the results stay the same for any thread count.

Smaller worlds keep their rows in id order, as the scene or the spawns
made them (their arrays fit the caches, where order matters little).
"""

from __future__ import annotations

from dataclasses import fields
from typing import Optional

import numpy as np

from ...model.tunables import SPATIAL_ORDER_CELL_RADII, SPATIAL_ORDER_MIN_PARTICLES
from ...step.pipeline import Pipeline, StepContext
from ..detection.grid_kernels import as_points
from .order_kernels import cell_order


class SpatialOrder:
    """Puts a large world's rows in cell order; the pipeline's stages hear of each move."""

    def __init__(self, pipeline: Pipeline,
                 min_particles: int = SPATIAL_ORDER_MIN_PARTICLES,
                 cell_radii: float = SPATIAL_ORDER_CELL_RADII) -> None:
        """Keep the pipeline whose stages hold rows, and from how many particles to order."""
        self.pipeline = pipeline
        self.min_particles = int(min_particles)
        self.cell_radii = float(cell_radii)
        self.moves = 0                 # times the rows were renumbered (for tests and benchmarks)

    def apply(self, ctx: StepContext) -> Optional[np.ndarray]:
        """Put ``ctx``'s rows in cell order in place; return the order (None: no move).

        New row k holds what old row ``order[k]`` held. Only a world of at
        least ``min_particles`` is ordered, and only if it is out of order.
        """
        state = ctx.state
        n = len(state)
        if n < max(self.min_particles, 2):
            return None
        side = self.cell_radii * float(np.mean(state.radius))
        if not side > 0.0:
            return None
        found = cell_order(as_points(state.position), side)
        if not found.moved:
            return None
        order = found.order
        move_rows(ctx, order)
        self.pipeline.rows_moved(order)
        self.moves += 1
        return order


def move_rows(ctx: StepContext, order: np.ndarray) -> None:
    """Permute every per-row array of ``ctx`` in place: new row k is old row ``order[k]``.

    The state's arrays keep their identity (stages compare them by it);
    the step's per-row results so far (losses, the particles near a wall,
    pairs and contacts) are renamed to the new rows.
    """
    state = ctx.state
    for item in fields(state):
        values = getattr(state, item.name)
        if isinstance(values, np.ndarray) and values.shape[:1] == order.shape:
            values[...] = values[order]
    if ctx.losses is not None:
        ctx.losses[...] = ctx.losses[order]
    new_row = np.empty_like(order)
    new_row[order] = np.arange(order.size)
    if ctx.near_walls is not None:
        ctx.near_walls = np.sort(new_row[ctx.near_walls])
    if ctx.pair_i is not None and ctx.pair_j is not None:
        ctx.pair_i, ctx.pair_j = _renamed_pairs(new_row, ctx.pair_i, ctx.pair_j)
    if ctx.contacts is not None:
        contacts = ctx.contacts
        contacts.i, contacts.j = new_row[contacts.i], new_row[contacts.j]


def _renamed_pairs(new_row: np.ndarray, first: np.ndarray, second: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Return pairs (i < j) renamed to the new rows, sorted by (i, j) as a search gives them."""
    a, b = new_row[first], new_row[second]
    low, high = np.minimum(a, b), np.maximum(a, b)
    by = np.lexsort((high, low))
    return low[by], high[by]
