"""Reference checks on a step's outcome, shared by the tests and the accuracy benchmark.

They judge what a step did from the outside (positions and velocities
before and after), independently of the stages that did it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..stages.detection.broadphase import candidate_pairs
from ..model.state import ParticleState

# Relative slack on r1 + r2 and on wall distances: below it a path is a miss.
MISS_TOLERANCE = 1e-6


def missed_collisions(before: ParticleState, after: ParticleState,
                      walls: Any = None) -> tuple[int, int]:
    """Return (pairs, wall crossings) that a step passed through without an impact.

    A particle whose velocity did not change in the step moved on a straight
    line (no gravity, no impulse). Two such particles that were apart at the
    start and at the end of the step but closer than r1 + r2 in between
    passed through each other; one whose straight path went past a wall
    (by more than the tolerance) tunnelled into it.
    """
    x0, x1 = before.position, after.position
    n = min(len(before), len(after))
    x0, x1 = x0[:n], x1[:n]
    straight = np.all(before.velocity[:n] == after.velocity[:n], axis=1)
    radius = before.radius[:n]
    travel = np.linalg.norm(x1 - x0, axis=1)
    i, j = candidate_pairs(x0, radius + travel)
    keep = straight[i] & straight[j]
    i, j = i[keep], j[keep]
    reach = (radius[i] + radius[j]) * (1.0 - MISS_TOLERANCE)
    start, end = x0[i] - x0[j], x1[i] - x1[j]
    path = end - start
    length2 = np.einsum('ij,ij->i', path, path)
    with np.errstate(divide='ignore', invalid='ignore'):
        tau = np.clip(-np.einsum('ij,ij->i', start, path) / length2, 0.0, 1.0)
    tau = np.where(length2 > 0.0, tau, 0.0)
    closest = np.linalg.norm(start + path * tau[:, None], axis=1)
    pairs = int(np.sum((np.linalg.norm(start, axis=1) >= reach)
                       & (np.linalg.norm(end, axis=1) >= reach) & (closest < reach)))
    crossings = 0
    if walls is not None:
        slack = MISS_TOLERANCE * radius[:, None]
        low = walls.low + radius[:, None] - slack
        high = walls.high - radius[:, None] + slack
        started_inside = np.all((x0 >= low) & (x0 <= high), axis=1)
        went_out = np.any((np.minimum(x0, x1) < low) | (np.maximum(x0, x1) > high), axis=1)
        crossings = int(np.sum(straight & started_inside & went_out))
    return pairs, crossings


def end_penetration(state: ParticleState) -> float:
    """Return the deepest overlap r1 + r2 - |p1 - p2| left at the end of a step, m."""
    i, j = candidate_pairs(state.position, state.radius)
    if not i.size:
        return 0.0
    gap = np.linalg.norm(state.position[i] - state.position[j], axis=1) - \
        (state.radius[i] + state.radius[j])
    return float(max(0.0, -gap.min()))
