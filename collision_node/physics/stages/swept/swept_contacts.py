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

Effects (every declared one, so every stepped preset runs the same
effects). Under gravity a dynamic particle's path is the parabola
x0 + v t + g t^2 / 2 and a static one does not move (``paths.py``): two
dynamic particles still close on a straight line (the quadratic above,
after both are brought to a common time on their parabolas), a wall plane
is reached at the root of a quadratic (``paths.entering_time``), a static
particle at the first root of a quartic (``paths.parabola_sphere_time``).
With drag, particles move between impacts by drag's closed form
(``drag.drag_step``, its work booked as 'drag'), while impact times are
solved on the drag-free path from the particle's current state: drag only
slows a path, so the Verlet allowance |v| dt + |g| dt^2 / 2 still bounds
every particle's travel, and the impulse is applied at the positions the
drag paths reached (a gap or overlap of order k/m |v| dt^2, which the
step-end solve and separation take). At each impact the contact law
applies the normal impulse with the combined e, Coulomb friction bounded
by mu times that impulse (``contact_law.apply_pair_friction`` /
``apply_wall_friction``, with spin) and the restitution threshold.

Only impacts that close at least as fast as the restitution threshold are
taken here (``Effects.threshold(dt)``: the declared value, 2 |g| dt by
default under gravity, 0 otherwise); slower contacts are resting contact
(a pile, a stack, a ball come to rest on the floor), which the plan hands
to the step-end stages after this one: walls, narrowphase, the sequential
solve with its threshold, shock passes and friction, and separation.
Taking them here would be Zeno's loop of ever smaller bounces.

The rounds run compiled (``swept_kernels.sweep``, the same formulas in the
same order) for sequential ordering without drag or requery; the numpy
rounds below are the reference the kernel is tested against and still run
drag, requery and batched ordering.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...law.contact_law import (apply_pair_friction, apply_pair_impulses, apply_wall_friction,
                                apply_wall_impulses, pair_coefficient, record_pairs, record_walls,
                                thresholded, wall_coefficient)
from ...model.effects import Drag, Walls
from ...law.paths import entering_time, parabola_sphere_time
from ...law.primitives import EFFECTS as KERNEL_EFFECTS
from .swept_kernels import in_contact, sweep, workspace
from ...step.pipeline import Stage, StepContext
from ..solve.batched_impulses import shared_scale
from ..detection.broadphase import BroadphaseStage
from ..motion.drag import advance_with_drag
from ..detection.narrowphase import line_of_action
from ...model.tunables import STRIKE_FACTOR, TOUCH_SLOP


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


class SweptContactStage(Stage):
    """Move particles through the step, stopping at each impact in time order."""

    name = 'swept_contacts'

    def __init__(self, restitution: float, walls: Optional[Walls], ordering: str,
                 rounds: int, requery: bool = False, gravity: Optional[np.ndarray] = None,
                 drag: Optional[Drag] = None, friction: Optional[float] = None,
                 resting: bool = False) -> None:
        """Keep the restitution, the box, the ordering, the round budget, requery.

        ``gravity``, ``drag`` and ``friction`` are the scene's effects (None:
        not declared); the restitution threshold comes from the step's
        effects (``Effects.threshold(dt)``), since its default depends on dt.
        ``resting``: a contact solve follows that takes slower contacts.
        """
        self.resting = resting
        self.requery = requery
        # Verlet list over k-d tree searches, widened by each particle's path.
        self._pairs = BroadphaseStage()
        self.restitution = restitution
        self.walls = walls
        self.ordering = ordering
        self.rounds = rounds
        self.gravity = None if gravity is None else np.asarray(gravity, dtype=float)
        self.drag = drag
        self.friction = friction
        # False: always the numpy rounds (tests compare the two paths).
        self.compiled = True
        self._workspace = None

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
        """Advance positions to the end of the step, applying impacts on the way.

        The compiled step (``swept_kernels.sweep``) runs it when it covers
        the stage's settings (sequential ordering, no drag, no requery);
        otherwise, or with ``compiled`` False, the numpy rounds below.
        """
        if self.compiled and self.ordering == 'sequential' and self.drag is None \
                and not self.requery:
            self._run_compiled(ctx)
        else:
            self._run_numpy(ctx)

    def _travel(self, ctx: StepContext) -> np.ndarray:
        """Return how far each particle can travel in the step (the broadphase's allowance)."""
        s, dt = ctx.state, ctx.dt
        v = s.velocity
        travel = np.sqrt(np.einsum('ij,ij->i', v, v)) * dt
        if self.gravity is not None:
            sag = float(np.linalg.norm(self.gravity))
            travel = travel + np.where(s.dynamic, 0.5 * sag * dt * dt, 0.0)
        return travel

    def _run_compiled(self, ctx: StepContext) -> None:
        """Run the step in one compiled call (``swept_kernels.sweep``); book and record."""
        s, dt = ctx.state, ctx.dt
        n = len(s)
        dynamic = s.dynamic
        pair_i, pair_j = self._pairs.find(s.position, s.radius, s.velocity, s.inv_mass, dt,
                                          extra=self._travel(ctx))
        ctx.pair_i, ctx.pair_j = pair_i, pair_j
        movable = dynamic[pair_i] | dynamic[pair_j]
        a = np.ascontiguousarray(pair_i[movable], dtype=np.int64)
        b = np.ascontiguousarray(pair_j[movable], dtype=np.int64)
        min_speed = ctx.effects.threshold(dt)
        d = ctx.dimensions
        resting_pair = np.zeros(0, dtype=bool)
        resting_wall = np.zeros((0, 2 * d), dtype=bool)
        has_resting = self.gravity is not None
        if has_resting:
            resting_pair, walls_touch = self._in_contact(ctx, a, b)
            if walls_touch is not None:
                resting_wall = walls_touch
            else:
                resting_wall = np.zeros((n, 2 * d), dtype=bool)
        walls = self.walls
        low = np.full(3, -np.inf) if walls is None else np.asarray(walls.low, dtype=float)
        high = np.full(3, np.inf) if walls is None else np.asarray(walls.high, dtype=float)
        gravity = np.zeros(3) if self.gravity is None else self.gravity
        own_e = s.restitution if s.restitution is not None else np.zeros(0)
        own_mu = s.friction if s.friction is not None else np.zeros(0)
        spin = s.angular_velocity if s.angular_velocity is not None else np.zeros((n, 3))
        loss = np.zeros((len(KERNEL_EFFECTS), n))
        totals = np.zeros(len(KERNEL_EFFECTS))
        counts = np.zeros(4, dtype=np.int64)
        self._workspace = workspace(n, a.size, d, self._workspace)
        records, index = sweep(
            s.position, s.velocity, spin, s.inv_mass, s.radius, dynamic, a, b,
            own_e, s.restitution is not None, own_mu, s.friction is not None,
            float(self.restitution), float(1.0 if walls is None else walls.restitution),
            self.friction is not None, float(self.friction or 0.0), walls is not None,
            low, high, d, gravity, self.gravity is not None, resting_pair, resting_wall,
            has_resting, float(min_speed), STRIKE_FACTOR * min_speed, float(dt),
            int(self.rounds), d == 2, ctx.impacts is not None, loss, totals, counts,
            self._workspace)
        # The effects the numpy rounds book: restitution when a pair was resolved,
        # walls and friction when one hit.
        booked = (counts[3] > 0, counts[1] > 0,
                  self.friction is not None and counts[0] + counts[1] > 0)
        for row, effect in enumerate(KERNEL_EFFECTS):
            if not booked[row]:
                continue
            ctx.stats.add_dissipated(effect, float(totals[row]))
            if ctx.losses is not None:
                ctx.losses += loss[row]
        ctx.stats.collisions += int(counts[0])
        ctx.stats.wall_collisions += int(counts[1])
        if ctx.impacts is not None and len(index):
            ctx.impacts.record(ctx.time + records[:, 0], index[:, 0], index[:, 1],
                               records[:, 1:4], records[:, 4:7], records[:, 7], records[:, 8],
                               records[:, 9])

    def _run_numpy(self, ctx: StepContext) -> None:
        """Run the stage in numpy rounds: the reference the compiled step is tested against."""
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

    def _in_contact(self, ctx: StepContext, a: np.ndarray, b: np.ndarray
                    ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Return (pairs, particle-wall columns) touching at the step start.

        Under gravity these are resting contact (a pile, a stack, a ball on
        the floor): the step-end solve takes them with its threshold and
        shock passes. Taken here, a resting column at e = 1 kept the closing
        speeds its last solve left (a few thresholds) as a wave that never
        settled (test_hard_cases, case 7). Once any impact here changes one
        of their particles, they are taken here in time order (if they
        close at the threshold or faster): held, the changed particle ran
        through its supports for the rest of the step, compressing a
        settling pile (up to 2.5 cm per pair, 0.3 m summed in a step) that
        separation later lifted out beyond the losses of the step it did
        so, adding energy (the 200-disc pile at e = 0.3, test_effects: up
        to 0.13 J in 165 of 270 steps for seed 3). As in the solver, such a contact
        keeps its e only if an impact of at least STRIKE_FACTOR thresholds
        struck one of its particles, so the shock runs through a resting
        column with its e (the sequential impact model, case 13); otherwise
        it is resting contact, e = 0 (with e = 1 slower shocks kept a
        packed pile of 500 spreading sideways, case 7).
        """
        # Compiled (``swept_kernels.in_contact``): in numpy, the gathers and
        # temporaries cost 5 ms a step of the 10k-sphere pour.
        s = ctx.state
        d = ctx.dimensions
        pairs = np.empty(a.size, dtype=bool)
        walls = np.empty((len(s), 2 * d), dtype=bool)
        has_walls = self.walls is not None
        low = np.asarray(self.walls.low, dtype=float) if has_walls else np.zeros(3)
        high = np.asarray(self.walls.high, dtype=float) if has_walls else np.zeros(3)
        in_contact(s.position, s.radius, np.ascontiguousarray(a, dtype=np.int64),
                   np.ascontiguousarray(b, dtype=np.int64), TOUCH_SLOP, has_walls, low, high,
                   d, pairs, walls)
        return pairs, walls if has_walls else None

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
            moving = dynamic[side]
            self._advance(ctx, side[moving], time[moving], local_time)
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

    def describe(self) -> str:
        """Say what the stage does."""
        reach = 'r + |v| dt' if self.gravity is None else 'r + |v| dt + |g| dt^2/2'
        paths = 'straight paths'
        if self.gravity is not None:
            paths = 'parabolas under g (straight between falling particles)'
        text = (f'swept broadphase (Verlet list, reach {reach}), {paths}, impacts at their '
                f'time of impact, {self.ordering} in time order, e = {self.restitution:g}, '
                f'up to {self.rounds} rounds{", requery escaped paths" if self.requery else ""}')
        if self.friction is not None:
            text += f', Coulomb friction mu = {self.friction:g} at each impact'
        if self.resting:
            text += ', impacts slower than the restitution threshold left to the contact solve'
        if self.drag is not None:
            text += (f'; drag k1 = {self.drag.linear:g}, k2 = {self.drag.quadratic:g} moves '
                     'particles between impacts in closed form, impact times are solved on '
                     'the drag-free path (drag only shortens it: the allowance bounds it)')
        return text + ', then to the step end'
