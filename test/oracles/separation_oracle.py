"""The separation stage's projection and lift budget, vectorised: its compiled kernels' reference.

``SeparationOracle`` is the stage with its two compiled parts replaced by
numpy statements of the same law, in the same floating-point order, so the
kernels must match it bit for bit (``test/test_separation_kernels.py``).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from collision_node.physics.model.effects import Walls
from collision_node.physics.model.tunables import (STACK_ALIGNMENT, SUPPORT_SLOP, SUPPORT_SWEEPS,
                                                   SUPPORT_TOLERANCE)
from collision_node.physics.stages.correction.separation import SeparationStage
from collision_node.physics.stages.detection.narrowphase import line_of_action
from collision_node.physics.step.pipeline import StepContext

UNSUPPORTED = np.iinfo(np.int64).max


def support_levels(position: np.ndarray, radius: np.ndarray, dynamic: np.ndarray,
                   i: np.ndarray, j: np.ndarray, walls: Optional[Walls],
                   gravity: np.ndarray, dimensions: int) -> np.ndarray:
    """Return each particle's distance in contacts from a floor it touches or a static one."""
    supported = ~dynamic
    if walls is not None:
        for axis, value, inward in walls.planes(dimensions):
            if not inward * gravity[axis] < 0.0:
                continue
            gap = inward * (position[:, axis] - value) - radius
            supported = supported | (gap <= SUPPORT_SLOP * radius)
    level = np.where(supported, 0, UNSUPPORTED).astype(np.int64)
    k = 0
    while True:
        reached = np.concatenate([j[(level[i] == k) & (level[j] == UNSUPPORTED)],
                                  i[(level[j] == k) & (level[i] == UNSUPPORTED)]])
        if reached.size == 0:
            return level
        level[reached] = k + 1
        k += 1


def held_by_walls(position: np.ndarray, radius: np.ndarray, push: np.ndarray, walls: Walls,
                  dimensions: int) -> np.ndarray:
    """Return the mask of pushed particles that reach a wall the push points into.

    ``position`` is where the push would take them, ``push`` its direction.
    """
    p, d, r = position[:, :dimensions], push[:, :dimensions], radius[:, None]
    into_low = (p <= walls.low[:dimensions] + r) & (d < 0.0)
    into_high = (p >= walls.high[:dimensions] - r) & (d > 0.0)
    return np.any(into_low | into_high, axis=1)


def _dot(a: tuple, b: tuple) -> float:
    """Return a . b, summed as the kernels' ``dot3``: (x + z) + y."""
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def _outside_two(position: np.ndarray, radius: np.ndarray, p: int, q1: int, q2: int) -> bool:
    """Move p to the nearest point overlapping neither support (the kernel's closed form).

    False, moving nothing, where it does not apply; the sweeps run then.
    """
    reach1, reach2 = float(radius[p] + radius[q1]), float(radius[p] + radius[q2])
    at, one, two = (tuple(float(x) for x in position[row]) for row in (p, q1, q2))
    o1 = tuple(at[d] - one[d] for d in range(3))
    o2 = tuple(at[d] - two[d] for d in range(3))
    d1, d2 = math.sqrt(_dot(o1, o1)), math.sqrt(_dot(o2, o2))
    if d1 == 0.0 or d2 == 0.0:
        return False
    if d1 >= reach1 and d2 >= reach2:
        return True
    for (d, reach, o, centre, other, other_reach) in ((d1, reach1, o1, one, two, reach2),
                                                      (d2, reach2, o2, two, one, reach1)):
        if d < reach:
            scale = reach / d
            x = tuple(centre[k] + scale * o[k] for k in range(3))
            e = tuple(x[k] - other[k] for k in range(3))
            if _dot(e, e) >= other_reach * other_reach:
                position[p] = x
                return True
    u = tuple(two[d] - one[d] for d in range(3))
    apart = math.sqrt(_dot(u, u))
    if apart == 0.0:
        return False
    u = tuple(x / apart for x in u)
    a = (apart * apart + reach1 * reach1 - reach2 * reach2) / (2.0 * apart)
    h2 = reach1 * reach1 - a * a
    if not h2 > 0.0:
        return False
    centre = tuple(one[d] + a * u[d] for d in range(3))
    w = tuple(at[d] - centre[d] for d in range(3))
    along = _dot(w, u)
    w = tuple(w[d] - along * u[d] for d in range(3))
    size = math.sqrt(_dot(w, w))
    if size == 0.0:
        return False
    scale = math.sqrt(h2) / size
    position[p] = tuple(centre[d] + scale * w[d] for d in range(3))
    return True


def clusters(n: int, dynamic: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Return a cluster label per particle: the components of the contact graph.

    Only contacts between two dynamic particles connect; a static particle
    (or a wall) does not join the particles resting on it into one cluster.
    """
    both = dynamic[i] & dynamic[j]
    graph = coo_matrix((np.ones(int(both.sum())), (i[both], j[both])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def separate(position: np.ndarray, inv_mass: np.ndarray, i: np.ndarray, j: np.ndarray,
             normal: np.ndarray, penetration: np.ndarray, radius: Optional[np.ndarray] = None,
             walls: Optional[Walls] = None, dimensions: int = 3) -> None:
    """Push overlapping pairs apart in place along their normals.

    With ``walls`` (and ``radius``), a particle held by a wall does not
    move and its partner, if it can move, takes the whole push.
    """
    w_i, w_j = inv_mass[i], inv_mass[j]
    if walls is not None:
        share = (penetration / (w_i + w_j))[:, None] * normal
        held_i = held_by_walls(position[i] + w_i[:, None] * share, radius[i], normal, walls,
                               dimensions)
        held_j = held_by_walls(position[j] - w_j[:, None] * share, radius[j], -normal, walls,
                               dimensions)
        w_i, w_j = (np.where(held_i & ~held_j & (w_j > 0.0), 0.0, w_i),
                    np.where(held_j & ~held_i & (w_i > 0.0), 0.0, w_j))
    w_sum = w_i + w_j
    push_i = (penetration * w_i / w_sum)[:, None] * normal
    push_j = -(penetration * w_j / w_sum)[:, None] * normal
    n = position.shape[0]
    moves = np.bincount(i, weights=(w_i > 0), minlength=n) + \
        np.bincount(j, weights=(w_j > 0), minlength=n)
    total = np.zeros_like(position)
    np.add.at(total, i, push_i)
    np.add.at(total, j, push_j)
    moved = moves > 0
    position[moved] += total[moved] / moves[moved, None]


class SeparationOracle(SeparationStage):
    """The separation stage with its projection and lift budget as numpy statements."""

    def _pay_for_lift(self, ctx: StepContext, has_pairs: bool, start: np.ndarray,
                      added: np.ndarray, budget: np.ndarray) -> np.ndarray:
        """Take back what the projection's net lift adds to each cluster (numpy)."""
        state, c = ctx.state, ctx.contacts
        cluster = clusters(len(state), state.dynamic, c.i, c.j) if has_pairs else \
            np.arange(len(state))
        count = int(cluster.max()) + 1 if cluster.size else 0
        excess = np.bincount(cluster, weights=added, minlength=count) - \
            np.maximum(np.bincount(cluster, weights=budget, minlength=count), 0.0)
        removed = np.zeros(added.size)
        up = (added > 0.0) & (excess[cluster] > 0.0)
        if not up.any():
            return removed
        index = np.flatnonzero(up)
        raised = np.bincount(cluster[index], weights=added[index], minlength=count)
        owed = excess[cluster[index]] * added[index] / raised[cluster[index]]
        mass = 1.0 / state.inv_mass[index]
        moved = state.position[index] - start[index]
        way = moved / np.linalg.norm(moved, axis=1)[:, None]
        # One still moving against its push does not pay.
        along = np.maximum(np.einsum('ij,ij->i', state.velocity[index], way), 0.0)
        taken = np.minimum(owed, 0.5 * mass * along * along)
        slower = np.sqrt(np.maximum(along * along - 2.0 * taken / mass, 0.0))
        state.velocity[index] += (slower - along)[:, None] * way
        removed[index] = taken
        # What the speed cannot pay is not lifted: back along the push by that fraction.
        unpaid = owed - taken
        back = unpaid > 0.0
        state.position[index[back]] -= (unpaid[back] / added[index[back]])[:, None] * \
            moved[back]
        return removed

    def _project_passes(self, ctx: StepContext, has_pairs: bool, passes: int,
                        hold: bool) -> None:
        """Run the projection passes and wall clamps (numpy)."""
        s, c = ctx.state, ctx.contacts
        held_by = self.walls if hold else None
        if passes > 1:
            self._project_in_turn(ctx, has_pairs, passes, held_by)
            return
        for k in range(passes):
            if has_pairs:
                if k == 0:
                    # Speculative contacts (negative penetration) are not pushed.
                    overlapping = c.penetration > 0.0
                    normal, penetration = c.normal[overlapping], c.penetration[overlapping]
                    i, j = c.i[overlapping], c.j[overlapping]
                else:
                    normal, distance = line_of_action(s.position[c.i] - s.position[c.j],
                                                      s.velocity[c.i] - s.velocity[c.j])
                    penetration = s.radius[c.i] + s.radius[c.j] - distance
                    overlapping = penetration > 0.0
                    if not overlapping.any() and self.walls is None:
                        return
                    i, j = c.i[overlapping], c.j[overlapping]
                    normal, penetration = normal[overlapping], penetration[overlapping]
                separate(s.position, s.inv_mass, i, j, normal, penetration, s.radius,
                         held_by, ctx.dimensions)
            self._clamp_inside_walls(ctx)

    def _project_in_turn(self, ctx: StepContext, has_pairs: bool, passes: int,
                         held_by: Optional[Walls]) -> None:
        """Gauss-Seidel passes a support level at a time, then walls (see the kernel)."""
        s, c = ctx.state, ctx.contacts
        i, j = (c.i, c.j) if has_pairs else (np.zeros(0, np.int64), np.zeros(0, np.int64))
        level = support_levels(s.position, s.radius, s.dynamic, i, j, self.walls,
                               np.asarray(ctx.effects.gravity, dtype=float), ctx.dimensions)
        key = np.minimum(level[i], level[j])
        order = np.argsort(key, kind='stable')
        g = np.asarray(ctx.effects.gravity, dtype=float)
        up = -g / np.linalg.norm(g)
        for _ in range(passes):
            overlapped = False
            for block in np.split(order, np.flatnonzero(np.diff(key[order])) + 1):
                if not block.size:
                    continue
                movers = [self._mover(ctx, c.i[k], c.j[k], level, up) for k in block]
                lifted = set()
                for k, mover in zip(block, movers):
                    if mover is not None and mover >= 0:
                        overlapped = True
                        if mover not in lifted:
                            lifted.add(mover)
                            group = [kk for kk, mm in zip(block, movers) if mm == mover]
                            self._lift_off_supports(s, mover, group, c)
                        continue
                    overlapped = self._push(ctx, c.i[k], c.j[k], level, up) or overlapped
            self._clamp_inside_walls(ctx)
            if not overlapped:
                break

    def _mover(self, ctx: StepContext, a: int, b: int, level: np.ndarray,
               up: np.ndarray) -> Optional[int]:
        """Return the pair's lone mover, -1 if it shares its push, None if it does not overlap."""
        s = ctx.state
        normal, distance = line_of_action(s.position[[a]] - s.position[[b]],
                                          s.velocity[[a]] - s.velocity[[b]])
        depth = s.radius[a] + s.radius[b] - distance[0]
        if not depth > 0.0:
            return None
        walls = self.walls

        def into_wall(row, way):
            return walls is not None and bool(held_by_walls(
                s.position[[row]] + depth * way, s.radius[[row]], way, walls,
                ctx.dimensions)[0])

        if abs(float(normal[0] @ up)) < STACK_ALIGNMENT:
            return -1
        if level[a] < level[b] and s.inv_mass[b] > 0.0 and not into_wall(b, -normal):
            return int(b)
        if level[b] < level[a] and s.inv_mass[a] > 0.0 and not into_wall(a, normal):
            return int(a)
        return -1

    @staticmethod
    def _lift_off_supports(s, p: int, group: list, c) -> None:
        """Projected Gauss-Seidel on the mover's pushes out of its supports (see the kernel)."""
        if len(group) == 2:
            supports = [c.j[k] if c.i[k] == p else c.i[k] for k in group]
            if _outside_two(s.position, s.radius, p, *supports):
                return
        lifted = [0.0] * len(group)
        for _ in range(SUPPORT_SWEEPS):
            converged = True
            for t, k in enumerate(group):
                q = c.j[k] if c.i[k] == p else c.i[k]
                normal, distance = line_of_action(s.position[[p]] - s.position[[q]],
                                                  s.velocity[[p]] - s.velocity[[q]])
                push = max(lifted[t] + s.radius[p] + s.radius[q] - distance[0], 0.0)
                change = push - lifted[t]
                if change == 0.0:
                    continue
                lifted[t] = push
                s.position[p] += change * normal[0]
                if abs(change) > SUPPORT_TOLERANCE * s.radius[p]:
                    converged = False
            if converged:
                break

    def _push(self, ctx: StepContext, a: int, b: int, level: np.ndarray,
              up: np.ndarray) -> bool:
        """Push an overlapping pair apart in turn; return whether it overlapped."""
        s = ctx.state
        normal, distance = line_of_action(s.position[[a]] - s.position[[b]],
                                          s.velocity[[a]] - s.velocity[[b]])
        depth = s.radius[a] + s.radius[b] - distance[0]
        if not depth > 0.0:
            return False
        w_a, w_b = s.inv_mass[a], s.inv_mass[b]
        alone = self._mover(ctx, a, b, level, up)
        if alone == a:
            w_b = 0.0
        elif alone == b:
            w_a = 0.0
        w_sum = w_a + w_b
        if w_sum > 0.0:
            s.position[a] += (depth * w_a / w_sum) * normal[0]
            s.position[b] += -((depth * w_b / w_sum) * normal[0])
        return True

    def _clamp_inside_walls(self, ctx: StepContext) -> None:
        """Place particles found past a wall plane back on it."""
        if self.walls is None:
            return
        s = ctx.state
        dyn = s.dynamic
        for axis, plane, inward in self.walls.planes(ctx.dimensions):
            p = s.position[:, axis]
            inside = dyn & (inward * (p - plane) < s.radius)
            p[inside] = plane + inward * s.radius[inside]
