"""Swept contacts (``ccd``): impacts found at their time of impact inside the step.

Replaces drift + broadphase + narrowphase + impulses when ``ccd`` is on.
Each particle keeps a local clock inside the step. The broadphase reaches
``radius + |v| dt / 2`` around the mid-step positions (everything a
particle can touch along its path, see ``run``); for
each candidate pair the relative motion is a straight line, so the time of
impact is the smaller root of |d + u s| = r_i + r_j, a quadratic written in
units of r_i + r_j so that no square underflows. Walls give linear roots.

The step then runs in rounds (at most ``iterations``): every particle's
earliest event (a pair or a wall) is found, a batch of events is taken, the
particles involved are moved to their event time, the impulse is applied
along the line of action at contact, and only the pairs of the particles
that changed are predicted again. ``sequential`` takes the events that are
the earliest at both of their particles (ties broken by pair order), so
touching chains are walked one pair per round in time-of-impact order (the
cradle's wave); ``batched`` takes every event whose time equals the earliest
time at both of its particles, so simultaneous impacts on one particle are
solved at once (Jacobi). Finally every particle drifts to the end of the
step with its last velocity.

With ``requery`` (preset ``accurate``), a particle that an impact sends
out of the ball its broadphase query covered (its mid-step position,
radius |v| dt / 2) is queried again for the rest of its path
(``_Escapes``); without it, such a particle's contacts outside its list
are found at the next step, as overlaps. An event found after an earlier one
changed a neighbour's path, and overlap left when the round budget runs
out, are picked up as immediate impacts (or by the separation stage)
rather than passed through.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..contact_law import (apply_pair_impulses, apply_wall_impulses, pair_coefficient,
                           record_pairs, record_walls, wall_coefficient)
from ..effects import Walls
from ..step import Stage, StepContext
from .batched_impulses import shared_scale
from .broadphase import BroadphaseStage
from .narrowphase import line_of_action


def pair_impact_times(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                      local_time: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the time of impact of pairs (a, b) on the step clock, inf for none.

    Both particles are brought to the later of their local clocks; an
    approaching pair that already overlaps impacts at once.
    """
    start = np.maximum(local_time[a], local_time[b])
    reach = radius[a] + radius[b]
    offset = (position[a] + velocity[a] * (start - local_time[a])[:, None]
              - position[b] - velocity[b] * (start - local_time[b])[:, None]) / reach[:, None]
    closing = (velocity[a] - velocity[b]) / reach[:, None]
    half_b = np.einsum('ij,ij->i', offset, closing)
    c = np.einsum('ij,ij->i', offset, offset) - 1.0
    u2 = np.einsum('ij,ij->i', closing, closing)
    disc = half_b * half_b - u2 * c
    approaching = half_b < 0.0
    overlapping = c <= 0.0
    # At a subnormal or zero offset the dot product above underflows to 0;
    # for such overlapping pairs decide with the scale-robust line of action
    # (which also gives coincident centres their deterministic normal).
    unsure = np.flatnonzero(overlapping & (half_b == 0.0))
    if unsure.size:
        ua, ub, when = a[unsure], b[unsure], start[unsure]
        raw = (position[ua] + velocity[ua] * (when - local_time[ua])[:, None]
               - position[ub] - velocity[ub] * (when - local_time[ub])[:, None])
        relative = velocity[ua] - velocity[ub]
        normal, _ = line_of_action(raw, relative)
        approaching[unsure] = np.einsum('ij,ij->i', normal, relative) < 0.0
    hit = approaching & (overlapping | (disc >= 0.0))
    # A pair closing at a subnormal speed (a collapsing cluster at rest)
    # overflows to an impact time of inf: never, which is right.
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        # c / (-b + sqrt(disc)) is the smaller root without cancellation.
        delay = np.where(overlapping, 0.0, c / (-half_b + np.sqrt(np.maximum(disc, 0.0))))
    return np.where(hit, start + delay, np.inf)


def wall_impact_times(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                      local_time: np.ndarray, walls: Walls, dimensions: int) -> np.ndarray:
    """Return (n, 2 * dimensions) impact times with each wall, inf for none.

    Columns are (low x, high x, low y, high y, ...); a particle already past
    a wall and moving further out impacts at once.
    """
    times = np.full((position.shape[0], 2 * dimensions), np.inf)
    # A subnormal speed overflows the time to inf (never), which is right.
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        for axis in range(dimensions):
            p, v = position[:, axis], velocity[:, axis]
            gap_low = p - (walls.low[axis] + radius)
            gap_high = (walls.high[axis] - radius) - p
            low = np.where(v < 0.0, np.maximum(gap_low, 0.0) / -v, np.inf)
            high = np.where(v > 0.0, np.maximum(gap_high, 0.0) / v, np.inf)
            times[:, 2 * axis] = local_time + low
            times[:, 2 * axis + 1] = local_time + high
    return times


class _Escapes:
    """Candidate pairs for particles an impact sent out of their swept ball.

    The broadphase covers each particle's path inside the ball around its
    mid-step position with radius |v| dt / 2. An impact can speed a
    particle up so that the rest of its path leaves that ball; such a
    particle is queried again, for the rest of its path, against every
    particle's ball (and against the other escaped particles directly).
    """

    def __init__(self, centre: np.ndarray, half: np.ndarray, radius: np.ndarray,
                 n: int) -> None:
        """Keep every particle's swept ball; the tree is built on first need."""
        self.centre, self.half, self.radius = centre, half, radius
        self.escaped = np.zeros(n, dtype=bool)
        self.mid = np.zeros((n, 3))
        self.own = np.zeros(n)
        self.tree = None
        self.known: Optional[np.ndarray] = None
        self.n = n

    def new_pairs(self, x: np.ndarray, v: np.ndarray, local_time: np.ndarray, dt: float,
                  changed: np.ndarray, a: np.ndarray, b: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Return candidate pairs (i < j) not in (a, b) for newly escaped particles."""
        moved = np.flatnonzero(changed & ~self.escaped)
        if not moved.size:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        rest = (dt - local_time[moved])[:, None]
        end = x[moved] + v[moved] * rest
        limit = self.half[moved] * (1.0 + 1e-12)
        # The rest of the path is a segment: inside the ball iff both ends are.
        inside = (np.linalg.norm(x[moved] - self.centre[moved], axis=1) <= limit) & \
            (np.linalg.norm(end - self.centre[moved], axis=1) <= limit)
        fresh = moved[~inside]
        if not fresh.size:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        from scipy.spatial import cKDTree
        if self.tree is None:
            self.tree = cKDTree(self.centre)
        reach = self.radius + self.half
        rest = (dt - local_time[fresh])[:, None]
        mid = x[fresh] + v[fresh] * (0.5 * rest)
        own = self.radius[fresh] + np.linalg.norm(v[fresh], axis=1) * (0.5 * rest[:, 0])
        hits = self.tree.query_ball_point(mid, own + float(reach.max()))
        counts = np.fromiter((len(h) for h in hits), dtype=np.int64, count=len(hits))
        i = np.repeat(fresh, counts)
        j = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]) if counts.sum() \
            else np.zeros(0, dtype=np.int64)
        near = np.linalg.norm(np.repeat(mid, counts, axis=0) - self.centre[j], axis=1) <= \
            np.repeat(own, counts) + reach[j]
        i, j = i[near], j[near]
        # Escaped particles left their balls too: pair them with each other
        # when the balls of the rest of their paths meet.
        self.escaped[fresh] = True
        self.mid[fresh], self.own[fresh] = mid, own
        others = np.flatnonzero(self.escaped)
        gap = np.linalg.norm(mid[:, None, :] - self.mid[others][None, :, :], axis=2)
        close_f, close_o = np.nonzero(gap <= own[:, None] + self.own[others][None, :])
        i = np.concatenate([i, fresh[close_f]])
        j = np.concatenate([j, others[close_o]])
        keep = i != j
        lo, hi = np.minimum(i[keep], j[keep]), np.maximum(i[keep], j[keep])
        key = np.unique(lo * self.n + hi)
        if self.known is None:
            self.known = np.sort(a * self.n + b)
        pos = np.searchsorted(self.known, key)
        new = (pos >= self.known.size) | \
            (self.known[np.minimum(pos, self.known.size - 1)] != key)
        key, pos = key[new], pos[new]
        self.known = np.insert(self.known, pos, key)
        return key // self.n, key % self.n


class SweptContactStage(Stage):
    """Move particles through the step, stopping at each impact in time order."""

    name = 'swept_contacts'

    def __init__(self, restitution: float, walls: Optional[Walls], ordering: str,
                 rounds: int, requery: bool = False) -> None:
        """Keep the restitution, the box, the ordering, the round budget, requery."""
        self.requery = requery
        # Verlet list over k-d tree searches, widened by each particle's path.
        self._pairs = BroadphaseStage()
        self.restitution = restitution
        self.walls = walls
        self.ordering = ordering
        self.rounds = rounds

    def run(self, ctx: StepContext) -> None:
        """Advance positions to the end of the step, applying impacts on the way."""
        s, dt = ctx.state, ctx.dt
        n = len(s)
        x, v, dynamic = s.position, s.velocity, s.dynamic
        speed = np.sqrt(np.einsum('ij,ij->i', v, v))
        # The mid-step ball (centre, r + |v| dt / 2) holds a particle's whole
        # path; requery uses it to notice paths an impact sends elsewhere.
        centre, half = x + v * (0.5 * dt), speed * (0.5 * dt)
        # Every pair that can touch in the step has |p_i - p_j| <= r_i + r_j +
        # (|v_i| + |v_j|) dt at the step start; the Verlet list returns exactly
        # those (and more), searching afresh only when particles moved far.
        pair_i, pair_j = self._pairs.find(x, s.radius, v, s.inv_mass, dt, extra=speed * dt)
        ctx.pair_i, ctx.pair_j = pair_i, pair_j
        escapes = _Escapes(centre, half, s.radius, n) if self.requery else None
        movable = dynamic[pair_i] | dynamic[pair_j]
        a, b = pair_i[movable], pair_j[movable]
        local_time = np.zeros(n)
        pair_time = np.full(a.size, np.inf)
        wall_time = np.full((n, 2 * ctx.dimensions), np.inf)
        first_wall = np.full(n, np.inf)
        changed = np.ones(n, dtype=bool)
        for _ in range(self.rounds):
            redo = np.flatnonzero(changed[a] | changed[b])
            if redo.size:
                pair_time[redo] = pair_impact_times(x, v, s.radius, local_time,
                                                    a[redo], b[redo])
            if self.walls is not None:
                moved = np.flatnonzero(changed & dynamic)
                wall_time[moved] = wall_impact_times(x[moved], v[moved], s.radius[moved],
                                                     local_time[moved], self.walls,
                                                     ctx.dimensions)
                first_wall[moved] = wall_time[moved].min(axis=1)
            changed[:] = False
            pending = np.flatnonzero(pair_time <= dt)
            walls_due = first_wall <= dt
            if not pending.size and not walls_due.any():
                break
            chosen, earliest = self._choose_pairs(a[pending], b[pending], pair_time[pending],
                                                  dynamic, first_wall, n)
            pairs = pending[chosen]
            wall_hits = np.flatnonzero(walls_due & (first_wall <= earliest))
            self._resolve_pairs(ctx, a[pairs], b[pairs], pair_time[pairs], local_time, changed)
            if wall_hits.size:
                self._resolve_walls(ctx, wall_hits, wall_time[wall_hits], local_time, changed)
            if escapes is None:
                continue
            extra_a, extra_b = escapes.new_pairs(x, v, local_time, dt, changed, a, b)
            if extra_a.size:
                a, b = np.concatenate([a, extra_a]), np.concatenate([b, extra_b])
                pair_time = np.concatenate([pair_time, np.full(extra_a.size, np.inf)])
        x[dynamic] += v[dynamic] * (dt - local_time[dynamic])[:, None]

    def _choose_pairs(self, a: np.ndarray, b: np.ndarray, time: np.ndarray,
                      dynamic: np.ndarray, first_wall: np.ndarray, n: int
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Return (mask of pairs to resolve now, earliest pair time per particle)."""
        earliest = np.full(n, np.inf)
        np.minimum.at(earliest, a, time)
        np.minimum.at(earliest, b, time)
        # A wall impact at the same instant or earlier goes first.
        before_walls = (time < first_wall[a]) & (time < first_wall[b])
        if self.ordering == 'batched':
            first_a = time == earliest[a]
            first_b = time == earliest[b]
        else:
            order = np.lexsort((np.arange(time.size), time))
            rank = np.empty(time.size, dtype=np.int64)
            rank[order] = np.arange(time.size)
            first_rank = np.full(n, time.size, dtype=np.int64)
            np.minimum.at(first_rank, a, rank)
            np.minimum.at(first_rank, b, rank)
            first_a = first_rank[a] == rank
            first_b = first_rank[b] == rank
        # A static particle never changes, so it never has to wait its turn.
        chosen = (first_a | ~dynamic[a]) & (first_b | ~dynamic[b]) & before_walls
        return chosen, earliest

    def _resolve_pairs(self, ctx: StepContext, a: np.ndarray, b: np.ndarray, time: np.ndarray,
                       local_time: np.ndarray, changed: np.ndarray) -> None:
        """Move the pairs to their impact time and apply the impulses."""
        if not a.size:
            return
        s = ctx.state
        x, v, dynamic = s.position, s.velocity, s.dynamic
        for side in (a, b):
            mover = side[dynamic[side]]
            when = time[dynamic[side]]
            x[mover] += v[mover] * (when - local_time[mover])[:, None]
            local_time[mover] = when
        normal, _ = line_of_action(x[a] - x[b], v[a] - v[b])
        scale = None
        if self.ordering == 'batched':
            # Simultaneous impacts on one particle share it out (see batched_impulses).
            scale = shared_scale(a, b, np.ones(a.size, dtype=bool), dynamic, len(s))
        e = pair_coefficient(s.restitution, a, b, self.restitution)
        result = apply_pair_impulses(v, s.inv_mass, a, b, normal, e, scale=scale)
        hit = result.hit
        if scale is None:
            ctx.book('restitution', result.removed[hit], a[hit], b[hit])
        else:
            ctx.book('restitution', result.removed_at, result.particles)
        record_pairs(ctx.impacts, ctx.time + time[hit], x, s.radius, a[hit], b[hit],
                     normal[hit], result.magnitude[hit], 0.0, result.approach[hit])
        ctx.stats.collisions += int(hit.sum())
        changed[a] = True
        changed[b] = True

    def _resolve_walls(self, ctx: StepContext, index: np.ndarray, times: np.ndarray,
                       local_time: np.ndarray, changed: np.ndarray) -> None:
        """Move particles to their wall impact and reflect them by the contact law."""
        s = ctx.state
        when = times.min(axis=1)
        s.position[index] += s.velocity[index] * (when - local_time[index])[:, None]
        local_time[index] = when
        at_wall = times == when[:, None]
        for axis in range(ctx.dimensions):
            for column, plane, inward in ((2 * axis, self.walls.low[axis], 1.0),
                                          (2 * axis + 1, self.walls.high[axis], -1.0)):
                hit = index[at_wall[:, column] & (inward * s.velocity[index, axis] < 0.0)]
                if not hit.size:
                    continue
                e = wall_coefficient(s.restitution, hit, self.walls.restitution)
                _, magnitude, approach, removed = apply_wall_impulses(
                    s.velocity, s.inv_mass, hit, axis, inward, e)
                ctx.book('walls', removed, hit)
                ctx.stats.wall_collisions += int(hit.size)
                record_walls(ctx.impacts, ctx.time + local_time[hit], s.position, hit, axis,
                             float(plane), inward, magnitude, 0.0, approach)
        changed[index] = True

    def describe(self) -> str:
        """Say what the stage does."""
        return (f'swept broadphase (Verlet list, reach r + |v| dt), impacts at their time '
                f'of impact, {self.ordering} in time order, e = {self.restitution:g}, '
                f'up to {self.rounds} rounds{", requery escaped paths" if self.requery else ""}, '
                'then drift to the step end')
