"""The swept stage's numpy rounds: the reference ``swept_kernels.sweep`` is tested against.

The same step as the compiled stage, vectorised over pairs (one numpy pass
per round) with the vectorised contact law (``law/contact_law.py``,
``law/paths.py``, ``motion/drag.advance_with_drag``). ``ReferenceSweptStage``
takes the place of a world's ``SweptContactStage`` (``use_reference``);
``pair_impact_times`` also serves the event-mode reference.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from oracles.contact_law import (apply_pair_friction, apply_pair_impulses,
                                 apply_wall_friction, apply_wall_impulses,
                                 pair_coefficient, record_pairs,
                                 record_walls, thresholded, wall_coefficient)
from oracles.paths import entering_time, parabola_sphere_time
from collision_node.physics.model.effects import Walls
from collision_node.physics.stages.detection.narrowphase import line_of_action
from collision_node.physics.stages.motion.drag import advance_with_drag
from collision_node.physics.stages.solve.batched_impulses import shared_scale
from collision_node.physics.stages.swept.swept_contacts import SweptContactStage
from collision_node.physics.step.pipeline import StepContext
from collision_node.physics.model.tunables import STRIKE_FACTOR


def _on_path(position: np.ndarray, velocity: np.ndarray, fall: Optional[np.ndarray],
             tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (position, velocity) after ``tau`` on the drag-free path.

    ``fall`` is each particle's acceleration (g for dynamic, 0 for static
    particles), None without gravity.
    """
    if fall is None:
        return position + velocity * tau[:, None], velocity
    t = tau[:, None]
    return position + velocity * t + 0.5 * fall * t * t, velocity + fall * t


def pair_impact_times(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                      local_time: np.ndarray, a: np.ndarray, b: np.ndarray,
                      gravity: Optional[np.ndarray] = None,
                      dynamic: Optional[np.ndarray] = None, min_speed: float = 0.0,
                      horizon: float = np.inf) -> np.ndarray:
    """Return the time of impact of pairs (a, b) on the step clock, inf for none.

    Both particles are brought to the later of their local clocks (on their
    parabolas under ``gravity``; ``dynamic`` says who falls); an approaching
    pair that already overlaps impacts at once. Pairs of a falling and a
    static particle (curved relative paths) are solved up to ``horizon``.
    With ``min_speed`` > 0, an impact closing slower than it is no impact
    here (inf): resting contact, left to the step-end solve.
    """
    start = np.maximum(local_time[a], local_time[b])
    reach = radius[a] + radius[b]
    fall_a = fall_b = None
    if gravity is not None:
        fall_a = gravity * dynamic[a, None]
        fall_b = gravity * dynamic[b, None]
    pa, va = _on_path(position[a], velocity[a], fall_a, start - local_time[a])
    pb, vb = _on_path(position[b], velocity[b], fall_b, start - local_time[b])
    offset = (pa - pb) / reach[:, None]
    closing = (va - vb) / reach[:, None]
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
        normal, _ = line_of_action(pa[unsure] - pb[unsure], va[unsure] - vb[unsure])
        approaching[unsure] = np.einsum('ij,ij->i', normal, va[unsure] - vb[unsure]) < 0.0
    hit = approaching & (overlapping | (disc >= 0.0))
    # A pair closing at a subnormal speed (a collapsing cluster at rest)
    # overflows to an impact time of inf: never, which is right.
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        # c / (-b + sqrt(disc)) is the smaller root without cancellation.
        delay = np.where(overlapping, 0.0, c / (-half_b + np.sqrt(np.maximum(disc, 0.0))))
    delay = np.where(hit, delay, np.inf)
    accel = None
    if gravity is not None:
        accel = (fall_a - fall_b) / reach[:, None]
        curved = np.flatnonzero(np.any(accel != 0.0, axis=1))
        if curved.size:
            delay[curved] = parabola_sphere_time(offset[curved], closing[curved],
                                                 accel[curved], horizon - start[curved])
    if min_speed > 0.0:
        due = np.flatnonzero(np.isfinite(delay))
        s = delay[due, None]
        rel_v = closing[due] if accel is None else closing[due] + accel[due] * s
        rel_x = offset[due] + closing[due] * s
        if accel is not None:
            rel_x = rel_x + 0.5 * accel[due] * s * s
        normal, _ = line_of_action(rel_x, rel_v)
        approach = -np.einsum('ij,ij->i', normal, rel_v) * reach[due]
        delay[due[approach < min_speed]] = np.inf
    return start + delay


def wall_impact_times(position: np.ndarray, velocity: np.ndarray, radius: np.ndarray,
                      local_time: np.ndarray, walls: Walls, dimensions: int,
                      gravity: Optional[np.ndarray] = None,
                      min_speed: float = 0.0) -> np.ndarray:
    """Return (n, 2 * dimensions) impact times with each wall, inf for none.

    Columns are (low x, high x, low y, high y, ...); a particle already past
    a wall and moving further out impacts at once. Under ``gravity`` (the
    particles are dynamic) the path to a plane is a parabola; an impact
    closing slower than ``min_speed`` is resting contact, inf here.
    """
    if gravity is not None:
        # All planes at once: columns (low x, high x, ...), each a quadratic gap.
        d = dimensions
        p, v, g = position[:, :d], velocity[:, :d], np.asarray(gravity, float)[:d]
        gaps = np.empty((p.shape[0], 2 * d))
        rate = np.empty_like(gaps)
        gaps[:, 0::2] = p - (walls.low[:d] + radius[:, None])
        gaps[:, 1::2] = (walls.high[:d] - radius[:, None]) - p
        rate[:, 0::2], rate[:, 1::2] = v, -v
        curvature = np.empty(2 * d)
        curvature[0::2], curvature[1::2] = g, -g
        curvature = np.broadcast_to(curvature, gaps.shape)
        s = entering_time(gaps, rate, curvature)
        if min_speed > 0.0:
            speed = -(rate + curvature * np.where(np.isfinite(s), s, 0.0))
            s = np.where(speed >= min_speed, s, np.inf)
        return local_time[:, None] + s
    times = np.full((position.shape[0], 2 * dimensions), np.inf)
    # A subnormal speed overflows the time to inf (never), which is right.
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        for axis in range(dimensions):
            p, v = position[:, axis], velocity[:, axis]
            gap_low = p - (walls.low[axis] + radius)
            gap_high = (walls.high[axis] - radius) - p
            low = np.where(v < 0.0, np.maximum(gap_low, 0.0) / -v, np.inf)
            high = np.where(v > 0.0, np.maximum(gap_high, 0.0) / v, np.inf)
            if min_speed > 0.0:
                low = np.where(-v >= min_speed, low, np.inf)
                high = np.where(v >= min_speed, high, np.inf)
            times[:, 2 * axis] = local_time + low
            times[:, 2 * axis + 1] = local_time + high
    return times


class _Escapes:
    """Candidate pairs for particles an impact sent out of their swept ball.

    The broadphase covers each particle's path inside the ball around its
    mid-step position with radius |v| dt / 2 (plus |g| dt^2 / 4 under
    gravity, around the chord's midpoint). An impact can speed a particle
    up so that the rest of its path leaves that ball; such a particle is
    queried again, for the rest of its path, against every particle's ball
    (and against the other escaped particles directly).
    """

    def __init__(self, centre: np.ndarray, half: np.ndarray, radius: np.ndarray,
                 n: int, gravity: Optional[np.ndarray] = None) -> None:
        """Keep every particle's swept ball; the tree is built on first need."""
        self.centre, self.half, self.radius = centre, half, radius
        self.gravity = gravity
        self.sag = 0.0 if gravity is None else float(np.linalg.norm(gravity))
        self.escaped = np.zeros(n, dtype=bool)
        self.mid = np.zeros((n, 3))
        self.own = np.zeros(n)
        self.tree = None
        self.known: Optional[np.ndarray] = None
        self.n = n

    def _rest_ball(self, x: np.ndarray, v: np.ndarray, rest: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Return (centre, radius) of a ball holding the rest of each path.

        Centre: the chord's midpoint x + v t / 2 + g t^2 / 4; every point
        of the parabola (or of a drag path, which only falls short of it)
        lies within |v| t / 2 + |g| t^2 / 4 of it.
        """
        t = rest[:, None]
        mid = x + v * (0.5 * t)
        own = np.linalg.norm(v, axis=1) * (0.5 * rest)
        if self.gravity is not None:
            mid = mid + self.gravity * (0.25 * t * t)
            own = own + self.sag * 0.25 * rest * rest
        return mid, own

    def new_pairs(self, x: np.ndarray, v: np.ndarray, local_time: np.ndarray, dt: float,
                  changed: np.ndarray, a: np.ndarray, b: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Return candidate pairs (i < j) not in (a, b) for newly escaped particles."""
        moved = np.flatnonzero(changed & ~self.escaped)
        if not moved.size:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        limit = self.half[moved] * (1.0 + 1e-12)
        if self.gravity is None:
            rest = (dt - local_time[moved])[:, None]
            end = x[moved] + v[moved] * rest
            # The rest of the path is a segment: inside the ball iff both ends are.
            inside = (np.linalg.norm(x[moved] - self.centre[moved], axis=1) <= limit) & \
                (np.linalg.norm(end - self.centre[moved], axis=1) <= limit)
        else:
            mid, own = self._rest_ball(x[moved], v[moved], dt - local_time[moved])
            inside = np.linalg.norm(mid - self.centre[moved], axis=1) + own <= limit
        fresh = moved[~inside]
        if not fresh.size:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        from scipy.spatial import cKDTree
        if self.tree is None:
            self.tree = cKDTree(self.centre)
        reach = self.radius + self.half
        mid, own = self._rest_ball(x[fresh], v[fresh], dt - local_time[fresh])
        own = own + self.radius[fresh]
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


class ReferenceSweptStage(SweptContactStage):
    """``SweptContactStage`` run in numpy rounds (the compiled stage's settings and pairs)."""

    def _advance(self, ctx: StepContext, index: np.ndarray, when: np.ndarray,
                 local_time: np.ndarray) -> None:
        """Move dynamic particles ``index`` (distinct) on their free paths to ``when``."""
        if not index.size:
            return
        s = ctx.state
        tau = when - local_time[index]
        local_time[index] = when
        if self.drag is not None:
            # Booked as the drag stage books it: the drag force's own work.
            advance_with_drag(ctx, index, self.drag, self.gravity, tau)
            return
        s.position[index], s.velocity[index] = _on_path(
            s.position[index], s.velocity[index],
            None if self.gravity is None else self.gravity[None, :], tau)

    def run(self, ctx: StepContext) -> None:
        """Run the stage in numpy rounds."""
        s, dt = ctx.state, ctx.dt
        n = len(s)
        x, v, dynamic = s.position, s.velocity, s.dynamic
        speed = np.sqrt(np.einsum('ij,ij->i', v, v))
        # The mid-step ball (centre, r + |v| dt / 2) holds a particle's whole
        # path; requery uses it to notice paths an impact sends elsewhere.
        # Under gravity the path is a parabola: its chord's midpoint and
        # |g| dt^2 / 4 more (see _Escapes); drag only shortens a path.
        centre, half = x + v * (0.5 * dt), speed * (0.5 * dt)
        travel = speed * dt
        if self.gravity is not None:
            sag = float(np.linalg.norm(self.gravity))
            centre = centre + np.where(dynamic[:, None], self.gravity * (0.25 * dt * dt), 0.0)
            half = half + np.where(dynamic, 0.25 * sag * dt * dt, 0.0)
            travel = travel + np.where(dynamic, 0.5 * sag * dt * dt, 0.0)
        # Every pair that can touch in the step has |p_i - p_j| <= r_i + r_j +
        # travel_i + travel_j at the step start (travel: |v| dt, plus
        # |g| dt^2 / 2 under gravity); the Verlet list returns exactly those
        # (and more), searching afresh only when particles moved far.
        pair_i, pair_j = self._pairs.find(x, s.radius, v, s.inv_mass, dt, extra=travel)
        ctx.pair_i, ctx.pair_j = pair_i, pair_j
        escapes = _Escapes(centre, half, s.radius, n, self.gravity) if self.requery else None
        movable = dynamic[pair_i] | dynamic[pair_j]
        a, b = pair_i[movable], pair_j[movable]
        # Impacts slower than the restitution threshold are resting contact,
        # solved after this stage (see the module docstring).
        min_speed = ctx.effects.threshold(dt)
        resting_pair = resting_wall = None
        # Particles an impact struck in this step, and those any impact
        # changed (see _in_contact).
        self._struck = np.zeros(n, dtype=bool)
        touched = self._touched = np.zeros(n, dtype=bool)
        self._strike_speed = STRIKE_FACTOR * min_speed
        if self.gravity is not None:
            resting_pair, resting_wall = self._in_contact(ctx, a, b)
        local_time = np.zeros(n)
        pair_time = np.full(a.size, np.inf)
        wall_time = np.full((n, 2 * ctx.dimensions), np.inf)
        first_wall = np.full(n, np.inf)
        changed = np.ones(n, dtype=bool)
        for _ in range(self.rounds):
            redo = np.flatnonzero(changed[a] | changed[b])
            if redo.size:
                pair_time[redo] = pair_impact_times(x, v, s.radius, local_time,
                                                    a[redo], b[redo], self.gravity, dynamic,
                                                    min_speed, dt)
                if resting_pair is not None:
                    held = resting_pair[redo] & ~(touched[a[redo]] | touched[b[redo]])
                    pair_time[redo[held]] = np.inf
            if self.walls is not None:
                moved = np.flatnonzero(changed & dynamic)
                wall_time[moved] = wall_impact_times(x[moved], v[moved], s.radius[moved],
                                                     local_time[moved], self.walls,
                                                     ctx.dimensions, self.gravity, min_speed)
                if resting_wall is not None:
                    held = resting_wall[moved] & ~touched[moved, None]
                    wall_time[moved] = np.where(held, np.inf, wall_time[moved])
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
            self._resolve_pairs(ctx, a[pairs], b[pairs], pair_time[pairs], local_time, changed,
                                min_speed, None if resting_pair is None else resting_pair[pairs])
            if wall_hits.size:
                self._resolve_walls(ctx, wall_hits, wall_time[wall_hits], local_time, changed,
                                    min_speed,
                                    None if resting_wall is None else resting_wall[wall_hits])
            if escapes is None:
                continue
            extra_a, extra_b = escapes.new_pairs(x, v, local_time, dt, changed, a, b)
            if extra_a.size:
                a, b = np.concatenate([a, extra_a]), np.concatenate([b, extra_b])
                pair_time = np.concatenate([pair_time, np.full(extra_a.size, np.inf)])
                if resting_pair is not None:
                    resting_pair = np.concatenate([resting_pair,
                                                   np.zeros(extra_a.size, dtype=bool)])
        movers = np.flatnonzero(dynamic)
        self._advance(ctx, movers, np.full(movers.size, dt), local_time)

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
                       local_time: np.ndarray, changed: np.ndarray,
                       min_speed: float = 0.0, resting: Optional[np.ndarray] = None) -> None:
        """Move the pairs to their impact time and apply the law's impulses.

        ``resting`` marks the pairs in contact at the step start: e = 0 for
        them unless a particle of theirs was struck (see ``_in_contact``).
        """
        if not a.size:
            return
        s = ctx.state
        x, v, dynamic = s.position, s.velocity, s.dynamic
        for side in (a, b):
            moving = np.flatnonzero(dynamic[side])
            # A particle in several impacts of a batch moves (and books drag) once.
            index, first = np.unique(side[moving], return_index=True)
            self._advance(ctx, index, time[moving][first], local_time)
        normal, _ = line_of_action(x[a] - x[b], v[a] - v[b])
        scale = None
        if self.ordering == 'batched':
            # Simultaneous impacts on one particle share it out (see batched_impulses).
            scale = shared_scale(a, b, np.ones(a.size, dtype=bool), dynamic, len(s))
        e = pair_coefficient(s.restitution, a, b, self.restitution)
        if min_speed > 0.0:
            approach = np.einsum('ij,ij->i', v[b] - v[a], normal)
            e = thresholded(e, approach, min_speed)
        if resting is not None:
            e = np.where(resting & ~(self._struck[a] | self._struck[b]), 0.0, e)
        result = apply_pair_impulses(v, s.inv_mass, a, b, normal, e, scale=scale)
        hit = result.hit
        if scale is None:
            ctx.book('restitution', result.removed[hit], a[hit], b[hit])
        else:
            ctx.book('restitution', result.removed_at, result.particles)
        tangential = 0.0
        if self.friction is not None and hit.any():
            # Coulomb friction bounded by mu times the impact's normal impulse
            # (sequential ordering only: one impact per particle at a time).
            mu = pair_coefficient(s.friction, a[hit], b[hit], self.friction)
            tangential = np.zeros(a.size)
            tangential[hit], lost = apply_pair_friction(
                v, s.angular_velocity, s.inv_mass, s.radius, a[hit], b[hit], normal[hit],
                result.magnitude[hit], mu, ctx.dimensions == 2)
            ctx.book('friction', lost, a[hit], b[hit])
            tangential = tangential[hit]
        record_pairs(ctx.impacts, ctx.time + time[hit], x, s.radius, a[hit], b[hit],
                     normal[hit], result.magnitude[hit], tangential, result.approach[hit])
        ctx.stats.collisions += int(hit.sum())
        strikes = hit & (np.asarray(e) > 0.0) & (result.approach >= self._strike_speed)
        self._struck[a[strikes]] = self._struck[b[strikes]] = True
        self._touched[a[hit]] = self._touched[b[hit]] = True
        changed[a] = True
        changed[b] = True

    def _resolve_walls(self, ctx: StepContext, index: np.ndarray, times: np.ndarray,
                       local_time: np.ndarray, changed: np.ndarray,
                       min_speed: float = 0.0, resting: Optional[np.ndarray] = None) -> None:
        """Move particles to their wall impact and reflect them by the contact law.

        ``resting`` (per particle and wall column) marks contact at the step
        start: e = 0 there unless the particle was struck (``_in_contact``).
        """
        s = ctx.state
        when = times.min(axis=1)
        self._advance(ctx, index, when, local_time)
        at_wall = times == when[:, None]
        for axis in range(ctx.dimensions):
            for column, plane, inward in ((2 * axis, self.walls.low[axis], 1.0),
                                          (2 * axis + 1, self.walls.high[axis], -1.0)):
                taken = at_wall[:, column] & (inward * s.velocity[index, axis] < 0.0)
                hit = index[taken]
                if not hit.size:
                    continue
                e = wall_coefficient(s.restitution, hit, self.walls.restitution)
                if min_speed > 0.0:
                    e = thresholded(e, -inward * s.velocity[hit, axis], min_speed)
                if resting is not None:
                    e = np.where(resting[taken, column] & ~self._struck[hit], 0.0, e)
                _, magnitude, approach, removed = apply_wall_impulses(
                    s.velocity, s.inv_mass, hit, axis, inward, e)
                ctx.book('walls', removed, hit)
                self._struck[hit[(np.asarray(e) > 0.0) & (approach >= self._strike_speed)]] = True
                self._touched[hit] = True
                tangential = 0.0
                if self.friction is not None:
                    normal = np.zeros((hit.size, 3))
                    normal[:, axis] = inward
                    mu = wall_coefficient(s.friction, hit, self.friction)
                    tangential, lost = apply_wall_friction(
                        s.velocity, s.angular_velocity, s.inv_mass, s.radius, hit, normal,
                        magnitude, mu, ctx.dimensions == 2)
                    ctx.book('friction', lost, hit)
                ctx.stats.wall_collisions += int(hit.size)
                record_walls(ctx.impacts, ctx.time + local_time[hit], s.position, hit, axis,
                             float(plane), inward, magnitude, tangential, approach)
        changed[index] = True


def use_reference(world) -> ReferenceSweptStage:
    """Put the numpy rounds in place of ``world``'s swept stage; return that stage."""
    stages = world.pipeline.stages
    place = [k for k, stage in enumerate(stages) if stage.name == 'swept_contacts']
    assert len(place) == 1, 'the world has no swept stage'
    reference = ReferenceSweptStage.__new__(ReferenceSweptStage)
    reference.__dict__.update(stages[place[0]].__dict__)
    stages[place[0]] = reference
    return reference
