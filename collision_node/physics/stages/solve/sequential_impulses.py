"""Contact solve: impulses along the line of action, one colour at a time.

Sweeps the colour batches of the contact graph in order (Gauss-Seidel)
until no contact approaches or the iteration budget is spent. Each
impulse only changes the velocity component along N, exactly as the
lecture's velocity update.

Every impulse comes from the one contact law (``contact_law``); a scene
without effects (e = 1, no threshold) gets exactly the lecture's
impulses. What the solve adds to the law:

- restitution per pair by the combine rule (``contact_law.combine``), set to
  0 below the restitution threshold: an impulse gets e only if the pair
  closes faster than the threshold and either did so before the solve or
  touches a particle that an impact struck within it (``_thresholded``);
- particles touching a wall plane are solved in every sweep, one batch
  per plane, so piles rest on their floor;
- friction (``collision_node.friction``) right after a pair's normal
  impulse in the same colour batch, bounded by mu times that impulse, so
  pairs sharing a particle stay sequential;
- under gravity, shock passes finish resting contact (``_shock_pass``);
  they act only on contacts closing slower than the threshold and, like a
  floor, do not conserve momentum;
- the energy removed is booked per effect ('restitution', 'walls',
  'friction') by the law, from the impulses;
- with an impact log, each contact that received impulses is recorded
  once per solve: its summed normal and tangential impulse and the speed
  it closed at before the solve.

Resting contact is solved with accumulated impulses (kernel backend,
under a restitution threshold): each contact closing slower than the
threshold accumulates its normal impulse (clamped >= 0, target separating
speed 0) and its tangential one (inside the Coulomb cone of the
accumulated normal impulse); a contact that opens gets its resting impulse
taken back. The impulses are kept per contact in ``ContactCache`` (by
stable particle ids) and applied first in the next step where the contact
persists and is not a new impact (warm starting), so a resting pile needs
few sweeps. Impact impulses are the law's, unchanged and never cached.

Two backends apply the same law. ``kernel`` (the default) runs the whole
solve, its set-up included (wall contacts, orders, the warm start's cache
look-up and store), in one compiled call (``contact_kernels.solve_step``)
that visits contacts one at a time in the broadphase's sorted pair order, and
the shock passes' pairs from the ground up: the order Gauss-Seidel walks a
chain such as Newton's cradle from its low end in one sweep (the chain
batches this replaced reproduced exactly that order, one batch per link).
``numpy`` is the vectorised reference: one greedy colour of the contact
graph per call (``coloring``), pairs past the colour budget one at a time;
the kernel visiting in that colour order gives identical velocities and
bookings (``test/test_contact_kernels.py``). Dense clusters get friction
and the ordered solve like any other contact.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...law import coloring
from ...law.primitives import FRICTION, RESTITUTION, WALLS
from .contact_kernels import solve_step
from ...law.contact_law import (apply_impulses, apply_pair_friction, apply_pair_impulses,
                                apply_wall_friction, apply_wall_impulses, pair_coefficient,
                                record_pairs, record_walls, wall_coefficient)
from ...model.effects import Walls
from ...law.impulse import closing_speed
from ...step.pipeline import Contacts, Stage, StepContext
from ...model.tunables import (BACKENDS, RESIDUAL_FRACTION, SHOCK_PASSES, STRIKE_FACTOR, WALL_SLOP,
                               WALL_ULPS)

# Orders the kernel visits contacts in: 'pairs' (the broadphase's sorted
# (i, j) order, shock passes by height) or 'colours' (the reference's).
VISITS = ('pairs', 'colours')


# Empty and one-value arrays handed to the kernel where a scene has no such data.
_NO_ROWS = np.zeros(0, dtype=np.int64)
_NO_VALUES = np.zeros(0)
_ONE_ZERO = np.zeros(1)


def _per_pair(value) -> np.ndarray:
    """Return a pair coefficient as the kernel takes it: one value, or one per pair."""
    return np.ascontiguousarray(np.atleast_1d(np.asarray(value, dtype=float)))


def _per_particle(own: Optional[np.ndarray], n: int, default: float) -> np.ndarray:
    """Return a wall coefficient as the kernel takes it: one value, or one per particle."""
    if own is None:
        return np.array([float(default)])
    return np.ascontiguousarray(wall_coefficient(own, np.arange(n), default), dtype=float)


def solve_order(i: np.ndarray, j: np.ndarray, dynamic: np.ndarray) -> list[np.ndarray]:
    """Return the reference solve's batches: one per colour, then each overflow pair alone."""
    batches, overflow = coloring.color_pairs(i, j, dynamic, coloring.MAX_COLORS)
    return batches + [overflow[k:k + 1] for k in range(overflow.size)]


class WallContacts:
    """Particles touching one wall plane, solved as one batch in each sweep."""

    def __init__(self, axis: int, plane: float, inward: float, index: np.ndarray,
                 restitution, friction, threshold: float, impact: Optional[np.ndarray],
                 record: bool) -> None:
        """Keep the plane, touching particles, their e and mu, the threshold and impacts."""
        self.axis, self.plane, self.inward, self.index = axis, plane, inward, index
        self.restitution, self.friction = restitution, friction
        self.threshold, self.impact = threshold, impact
        self.hit = np.zeros(index.size, dtype=bool)
        # Summed impulses and the approach speed before the solve, for the log.
        self.normal_impulse = self.tangential = self.approach = None
        if record:
            self.normal_impulse = np.zeros(index.size)
            self.tangential = np.zeros(index.size)

    def solve(self, ctx: StepContext, tolerance: float, planar: bool,
              struck: Optional[np.ndarray] = None) -> bool:
        """Reflect particles approaching the plane, v_n -> -e v_n; book losses.

        With a restitution threshold e is the wall's only for a particle
        approaching faster than it that arrived so (an impact) or was
        ``struck`` in this solve, as for pairs; a fast bounce marks it
        struck. Returns whether any particle approached.
        """
        state, index = ctx.state, self.index
        if self.normal_impulse is not None and self.approach is None:
            self.approach = -self.inward * state.velocity[index, self.axis]
        e = self.restitution
        if struck is not None:
            u = self.inward * state.velocity[index, self.axis]
            e = np.where((-u >= self.threshold) & (self.impact | struck[index]), e, 0.0)
        approaching, magnitude, approach, removed = apply_wall_impulses(
            state.velocity, state.inv_mass, index, self.axis, self.inward, e, tolerance)
        if not approaching.any():
            return False
        if struck is not None:
            struck[index[approaching & (e > 0.0)
                         & (approach >= STRIKE_FACTOR * self.threshold)]] = True
        self.hit |= approaching
        hit = index[approaching]
        ctx.book('walls', removed[approaching], hit)
        if self.normal_impulse is not None:
            self.normal_impulse += magnitude
        if self.friction is not None:
            normal = np.zeros((hit.size, 3))
            normal[:, self.axis] = self.inward
            mu = self.friction[approaching] if np.ndim(self.friction) else self.friction
            tangential, lost = apply_wall_friction(
                state.velocity, state.angular_velocity, state.inv_mass, state.radius,
                hit, normal, magnitude[approaching], mu, planar)
            ctx.book('friction', lost, hit)
            if self.tangential is not None:
                self.tangential[approaching] += tangential
        return True

    def record(self, ctx: StepContext) -> None:
        """Record each particle the plane pushed in this solve (nothing without a log)."""
        if self.normal_impulse is None:
            return
        pushed = self.normal_impulse > 0.0
        record_walls(ctx.impacts, ctx.time, ctx.state.position, self.index[pushed], self.axis,
                     self.plane, self.inward, self.normal_impulse[pushed],
                     self.tangential[pushed], np.maximum(self.approach[pushed], 0.0))


class ContactCache:
    """Accumulated resting impulses of the last solve, keyed by stable particle ids.

    Pairs are keyed by (lower id, higher id), wall contacts by (id, plane:
    axis * 2 + 1 for a plane facing +axis); tangential impulses are stored as
    the impulse on the lower id. Ids never change or get reused (``World``:
    a spawn takes new ids, a delete leaves a gap), so a contact between
    particles that survive a delete or spawn finds its entry, and one with a
    deleted particle is simply never looked up again. A world reset builds a
    new pipeline and with it an empty cache.
    """

    # Keys are lower * stride + higher in int64: ids up to 2**31 are safe.
    MAX_ID = 2 ** 31 - 1

    def __init__(self) -> None:
        """Start empty."""
        self.clear()

    def clear(self) -> None:
        """Forget every contact."""
        none = np.zeros(0, dtype=np.int64)
        self.adopt(none, np.zeros(0), np.zeros((0, 3)), none, np.zeros(0), np.zeros((0, 3)))

    def adopt(self, key: np.ndarray, normal: np.ndarray, tangential: np.ndarray,
              wall_key: np.ndarray, wall_normal: np.ndarray,
              wall_tangential: np.ndarray) -> None:
        """Hold the contacts a compiled solve kept (``contact_kernels.solve_step``).

        Pair keys (``_pair_keys``) and wall keys (id * 8 + plane code) come
        sorted ascending, each with its normal and tangential impulse.
        """
        self.key, self.normal, self.tangential = key, normal, tangential
        stride = self.MAX_ID + 1
        self.lo, self.hi = key // stride, key % stride
        self.wall_key, self.wall_normal, self.wall_tangential = (wall_key, wall_normal,
                                                                 wall_tangential)

    def __len__(self) -> int:
        """Return the number of contacts held (pairs and wall contacts)."""
        return int(self.lo.size + self.wall_key.size)

    @classmethod
    def _pair_keys(cls, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return lo * (cls.MAX_ID + 1) + hi

    def lookup(self, ids: np.ndarray, i: np.ndarray, j: np.ndarray, w_index: np.ndarray,
               w_code: np.ndarray) -> tuple:
        """Return the cached (normal, tangential) impulses of pairs and wall contacts.

        Contacts not in the cache get zeros; tangential impulses come back as
        the impulse on i.
        """
        m, k = i.size, w_index.size
        acc, acc_t = np.zeros(m), np.zeros((m, 3))
        w_acc, w_acc_t = np.zeros(k), np.zeros((k, 3))
        if ids.size and int(ids.max()) > self.MAX_ID:
            self.clear()
        if self.lo.size and m:
            a, b = ids[i], ids[j]
            swapped = a > b
            found, where = _find(self._pair_keys(self.lo, self.hi),
                                 self._pair_keys(np.minimum(a, b), np.maximum(a, b)))
            acc[found] = self.normal[where]
            sign = np.where(swapped[found], -1.0, 1.0)
            acc_t[found] = self.tangential[where] * sign[:, None]
        if self.wall_key.size and k:
            found, where = _find(self.wall_key, ids[w_index] * 8 + w_code)
            w_acc[found] = self.wall_normal[where]
            w_acc_t[found] = self.wall_tangential[where]
        return acc, acc_t, w_acc, w_acc_t

    def store(self, ids: np.ndarray, i: np.ndarray, j: np.ndarray, acc: np.ndarray,
              acc_t: np.ndarray, w_index: np.ndarray, w_code: np.ndarray, w_acc: np.ndarray,
              w_acc_t: np.ndarray) -> None:
        """Keep this solve's contacts that hold a resting impulse (replacing the last)."""
        if ids.size and int(ids.max()) > self.MAX_ID:
            self.clear()
            return
        keep = acc > 0.0
        a, b = ids[i[keep]], ids[j[keep]]
        key = self._pair_keys(np.minimum(a, b), np.maximum(a, b))
        tangential = acc_t[keep] * np.where(a > b, -1.0, 1.0)[:, None]
        wall_keep = w_acc > 0.0
        wall_key = ids[w_index[wall_keep]] * 8 + w_code[wall_keep]
        # Sorted by key, as the compiled solve keeps them.
        order, wall_order = np.argsort(key, kind='stable'), np.argsort(wall_key, kind='stable')
        self.adopt(key[order], acc[keep][order], tangential[order], wall_key[wall_order],
                   w_acc[wall_keep][wall_order], w_acc_t[wall_keep][wall_order])


def _find(table: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (positions of ``keys`` found in ``table``, their rows in ``table``)."""
    order = np.argsort(table, kind='stable')
    sorted_table = table[order]
    at = np.minimum(np.searchsorted(sorted_table, keys), sorted_table.size - 1)
    found = np.flatnonzero(sorted_table[at] == keys)
    return found, order[at[found]]


class SequentialImpulseStage(Stage):
    """Resolve approaching contacts with restitution, colour by colour."""

    name = 'contact_impulses'

    def __init__(self, restitution: float, iterations: int,
                 friction: Optional[float] = None, walls: Optional[Walls] = None,
                 gravity: Optional[np.ndarray] = None, backend: str = 'kernel',
                 visit: str = 'pairs') -> None:
        """Keep the particle-particle restitution, the sweep budget, friction mu and walls.

        With walls, particles touching a wall plane are solved together with
        the pairs in every sweep, so a pile rests on its floor.

        The restitution threshold comes from the step's effects
        (``Effects.threshold(dt)``), since its default depends on dt.
        """
        self.restitution = restitution
        self.iterations = iterations
        self.friction = friction
        self.walls = walls
        self.gravity = gravity
        if backend not in BACKENDS or visit not in VISITS:
            raise ValueError(f'backend must be one of {BACKENDS} and visit one of {VISITS}, '
                             f'got {backend!r}, {visit!r}')
        self.backend, self.visit = backend, visit
        # Accumulated resting impulses, warm-started from the previous step
        # where contacts persist (kernel backend, under a restitution threshold).
        self.warm_start = True
        self.cache = ContactCache()
        # The wall planes as the kernel takes them, built on first use.
        self._plane_arrays: Optional[tuple] = None
        # Sweeps run, summed over the solves, and in the last solve (kernel).
        self.sweeps = self.solves = self.last_sweeps = 0

    def run(self, ctx: StepContext) -> None:
        """Apply the law's impulses in place, count the contacts hit, book and record them."""
        contacts = ctx.contacts if ctx.contacts is not None else Contacts.empty()
        if self.walls is None and len(contacts) == 0:
            return
        state = ctx.state
        threshold = ctx.effects.threshold(ctx.dt)
        i, j, normal = contacts.i, contacts.j, contacts.normal
        restitution = pair_coefficient(state.restitution, i, j, self.restitution)
        mu = None
        if self.friction is not None:
            mu = pair_coefficient(state.friction, i, j, self.friction)
        mu_per_pair = np.ndim(mu) > 0
        planar = ctx.dimensions == 2
        shock = self.gravity is not None and threshold > 0.0
        tolerance = RESIDUAL_FRACTION * threshold
        # The restitution threshold (Box2D's idea: slow contacts are resting,
        # so e = 0) is judged per impulse on two things. A pair closing
        # faster than the threshold before the solve is an impact. An
        # impulse with e > 0 marks both particles 'struck'; a pair closing
        # faster than the threshold at its impulse gets its e if it is an
        # impact or touches a struck particle (struck by an impulse on a pair
        # closing at STRIKE_FACTOR times the threshold). So the shock of an impact
        # travels through resting contacts with their e, as in the
        # sequential impact model (a ball dropped at e = 1 on a resting
        # column leaves at its impact speed, whatever the column's height),
        # while the sweeps' own back-and-forth in a resting pile, which no
        # impact caused, stays inelastic and the pile does not bounce.
        # Every impulse uses (1 + e) on the current closing speed, which
        # never adds energy.
        if self.backend == 'kernel':
            self._run_kernel(ctx, restitution, mu, threshold, tolerance, planar, shock)
            return
        # The reference states the law without accumulated impulses.
        self.cache.clear()
        struck = impact = None
        if threshold > 0.0:
            struck = np.zeros(len(state), dtype=bool)
            impact = -closing_speed(state.velocity, i, j, normal) >= threshold
        per_pair = np.ndim(restitution) > 0
        batches = solve_order(i, j, state.dynamic)
        record = ctx.impacts is not None
        walls = self._wall_contacts(ctx, threshold, record)
        hit = np.zeros(len(contacts), dtype=bool)
        if record:
            approach0 = -closing_speed(state.velocity, i, j, normal)
            summed_normal = np.zeros(len(contacts))
            summed_tangential = np.zeros(len(contacts))
        for _ in range(self.iterations):
            applied = False
            for batch in batches:
                bi, bj, bn = i[batch], j[batch], normal[batch]
                e = restitution[batch] if per_pair else restitution
                if struck is not None:
                    e = self._thresholded(state, bi, bj, bn, e, threshold, impact[batch], struck)
                result = apply_pair_impulses(state.velocity, state.inv_mass, bi, bj, bn, e,
                                             tolerance)
                mask = result.hit
                if not mask.any():
                    continue
                if struck is not None:
                    # A static particle never moves, so it passes no shock on.
                    bouncing = mask & (e > 0.0) & (result.approach >= STRIKE_FACTOR * threshold)
                    struck[bi[bouncing & state.dynamic[bi]]] = True
                    struck[bj[bouncing & state.dynamic[bj]]] = True
                hit[batch[mask]] = True
                applied = True
                ctx.book('restitution', result.removed[mask], bi[mask], bj[mask])
                if record:
                    summed_normal[batch] += result.magnitude
                if mu is not None:
                    tangential, lost = apply_pair_friction(
                        state.velocity, state.angular_velocity, state.inv_mass, state.radius,
                        bi[mask], bj[mask], bn[mask], result.magnitude[mask],
                        mu[batch][mask] if mu_per_pair else mu, planar)
                    ctx.book('friction', lost, bi[mask], bj[mask])
                    if record:
                        summed_tangential[batch[mask]] += tangential
            # Each plane is one batch: a particle touches a plane once.
            for wall in walls:
                applied = wall.solve(ctx, tolerance, planar, struck) or applied
            # One batch shares no dynamic particle, so after one sweep every
            # contact is resolved (vn' = -e vn >= 0) and a checking sweep
            # would find nothing: skip it.
            if not applied or (len(batches) == 1 and not walls):
                break
        if shock and len(contacts):
            # The sweeps stop at the tolerance, which leaves a stack sinking at up
            # to that speed and separation lifting it back every step (found by
            # the fuzzer: two balls resting on a floor kept -4.9e-6 m/s). The
            # shock passes finish resting contact exactly (tolerance 0).
            # Walls are the bottom of every pile: solve them first and after each pass.
            for wall in walls:
                wall.solve(ctx, 0.0, planar, struck)
            for _ in range(SHOCK_PASSES):
                pushed = self._shock_pass(ctx, i, j, normal, self.gravity, threshold, 0.0)
                for wall in walls:
                    wall.solve(ctx, 0.0, planar, struck)
                if pushed is None:
                    break
                if record:
                    summed_normal += pushed
        ctx.stats.collisions += int(hit.sum())
        ctx.stats.wall_collisions += int(sum(int(w.hit.sum()) for w in walls))
        if record:
            pushed = summed_normal > 0.0
            record_pairs(ctx.impacts, ctx.time, state.position, state.radius, i[pushed],
                         j[pushed], normal[pushed], summed_normal[pushed],
                         summed_tangential[pushed], np.maximum(approach0[pushed], 0.0))
            for wall in walls:
                wall.record(ctx)

    def _run_kernel(self, ctx: StepContext, restitution, mu, threshold: float,
                    tolerance: float, planar: bool, shock: bool) -> None:
        """Run the same solve in one compiled call (``contact_kernels.solve_step``).

        The kernel also does the set-up: the wall contacts, the visit and shock
        orders and the warm start's cache look-up and store, with the values
        the numpy set-up (``_wall_contacts``, ``_shock_order``,
        ``ContactCache``) gives.
        """
        state = ctx.state
        contacts = ctx.contacts if ctx.contacts is not None else Contacts.empty()
        i = np.ascontiguousarray(contacts.i, dtype=np.int64)
        j = np.ascontiguousarray(contacts.j, dtype=np.int64)
        normal = np.ascontiguousarray(contacts.normal, dtype=float)
        m, n = i.size, len(state)
        record = ctx.impacts is not None
        # The kernel works on contiguous float arrays; write back if copies were made.
        velocity = np.ascontiguousarray(state.velocity, dtype=float)
        spin = state.angular_velocity
        # Without spin (no friction) the kernel gets a scratch array it never reads.
        angular = (np.zeros((n, 3)) if spin is None
                   else np.ascontiguousarray(spin, dtype=float))
        friction = mu is not None
        planes = self._planes(ctx.dimensions)
        colours = self.visit == 'colours'
        order = shock_order = _NO_ROWS
        if colours:
            order = np.ascontiguousarray(self._visit_order(i, j, state.dynamic),
                                         dtype=np.int64)
        height = _NO_VALUES
        if shock and m:
            # As _shock_pass: heights relative to the first contact's particle.
            height = -((state.position - state.position[i[0]]) @ self.gravity)
            if colours:
                shock_order, _ = self._shock_order(state, i, j, self.gravity)
        w_rest, w_mu = _ONE_ZERO, _ONE_ZERO
        if self.walls is not None:
            w_rest = _per_particle(state.restitution, n, self.walls.restitution)
            if friction:
                w_mu = _per_particle(state.friction, n, self.friction)
        if record:
            approach0 = -closing_speed(velocity, i, j, normal)
        booked = ctx.losses if ctx.losses is not None else _NO_VALUES
        accumulate = self.warm_start and threshold > 0.0
        cache = self.cache
        (sweeps, totals, hit, summed_normal, summed_tangential, w_start, w_index, w_axis,
         w_inward, w_hit, w_normal, w_tangential, w_approach, *kept) = solve_step(
            velocity, angular, np.ascontiguousarray(state.position, dtype=float),
            np.ascontiguousarray(state.inv_mass, dtype=float),
            np.ascontiguousarray(state.radius, dtype=float),
            np.ascontiguousarray(state.ids, dtype=np.int64), i, j, normal,
            _per_pair(restitution), _per_pair(mu if friction else 0.0), colours, order,
            *planes, WALL_SLOP, w_rest, w_mu, threshold > 0.0, float(threshold),
            float(tolerance), STRIKE_FACTOR, int(self.iterations), friction, planar, shock,
            height, shock_order, SHOCK_PASSES, booked, accumulate, ContactCache.MAX_ID,
            cache.key, cache.normal, cache.tangential, cache.wall_key, cache.wall_normal,
            cache.wall_tangential)
        cache.adopt(*kept)
        self.sweeps += int(sweeps)
        self.solves += 1
        self.last_sweeps = int(sweeps)
        if velocity is not state.velocity:
            state.velocity[...] = velocity
        if spin is not None and angular is not spin:
            spin[...] = angular
        k = w_index.size
        effects = [(RESTITUTION, 'restitution')]
        if k:
            effects.append((WALLS, 'walls'))
        if friction:
            effects.append((FRICTION, 'friction'))
        for row, effect in effects:
            ctx.stats.add_dissipated(effect, float(totals[row]))
        ctx.stats.collisions += int(np.count_nonzero(hit))
        ctx.stats.wall_collisions += int(np.count_nonzero(w_hit))
        if record:
            pushed = summed_normal > 0.0
            record_pairs(ctx.impacts, ctx.time, state.position, state.radius, i[pushed],
                         j[pushed], normal[pushed], summed_normal[pushed],
                         summed_tangential[pushed], np.maximum(approach0[pushed], 0.0))
            planes = [] if self.walls is None else self.walls.planes(ctx.dimensions)
            for (axis, plane, inward), lo, hi in zip(planes, w_start[:-1], w_start[1:]):
                if hi == lo:
                    continue
                wall = WallContacts(axis, plane, inward, w_index[lo:hi], None, None,
                                    threshold, None, True)
                wall.normal_impulse = w_normal[lo:hi]
                wall.tangential = w_tangential[lo:hi]
                wall.approach = w_approach[lo:hi]
                wall.record(ctx)

    def _planes(self, dimensions: int) -> tuple:
        """Return the wall planes as arrays for the kernel: axis, plane, inward, ulps slop."""
        if self.walls is None:
            return _NO_ROWS, _NO_VALUES, _NO_VALUES, _NO_VALUES
        if self._plane_arrays is None or self._plane_arrays[0] != (self.walls, dimensions):
            planes = self.walls.planes(dimensions)
            axis = np.array([p[0] for p in planes], dtype=np.int64)
            plane = np.array([p[1] for p in planes], dtype=float)
            inward = np.array([p[2] for p in planes], dtype=float)
            # As _wall_contacts: WALL_ULPS float spacings at the plane's coordinate.
            ulps = WALL_ULPS * np.spacing(np.abs(plane))
            self._plane_arrays = ((self.walls, dimensions), (axis, plane, inward, ulps))
        return self._plane_arrays[1]

    @staticmethod
    def _thresholded(state, i: np.ndarray, j: np.ndarray, normal: np.ndarray, restitution,
                     threshold: float, impact: np.ndarray, struck: np.ndarray) -> np.ndarray:
        """Return e per pair: its own if closing past the threshold from an impact, else 0."""
        fast = -closing_speed(state.velocity, i, j, normal) >= threshold
        return np.where(fast & (impact | struck[i] | struck[j]), restitution, 0.0)

    def _wall_contacts(self, ctx: StepContext, threshold: float,
                       record: bool) -> list['WallContacts']:
        """Return the particles touching each wall plane, one entry per plane."""
        if self.walls is None:
            return []
        s = ctx.state
        out = []
        for axis, plane, inward in self.walls.planes(ctx.dimensions):
            gap = inward * (s.position[:, axis] - plane) - s.radius
            # Relative to the particle and to the float spacing where it is.
            slop = WALL_SLOP * s.radius + WALL_ULPS * np.spacing(abs(plane))
            index = np.flatnonzero(s.dynamic & (gap <= slop))
            if index.size == 0:
                continue
            e = wall_coefficient(s.restitution, index, self.walls.restitution)
            impact = None
            if threshold > 0.0:
                impact = -inward * s.velocity[index, axis] >= threshold
            mu = None
            if self.friction is not None:
                mu = wall_coefficient(s.friction, index, self.friction)
            out.append(WallContacts(axis, plane, inward, index, e, mu, threshold, impact,
                                    record))
        return out

    @staticmethod
    def _shock_pass(ctx: StepContext, i: np.ndarray, j: np.ndarray, normal: np.ndarray,
                    gravity: np.ndarray, threshold: float, tolerance: float
                    ) -> Optional[np.ndarray]:
        """Stop resting contacts from the ground up; return the impulse per contact.

        Shock propagation (Guendelman, Bridson and Fedkiw 2003): sweeps over a
        pile converge slowly because each inelastic impulse pushes the lower
        particle down again. Final passes, pairs ordered by the height of
        their lower particle along -g, treat the lower particle as immovable
        and stop the upper one's approach (e = 0): its velocity along the
        line of action becomes the lower one's, but never more than 0, so a
        lower particle moving up or sideways cannot lift it (a frozen
        particle would otherwise push with infinite mass and add energy);
        only the upper particle's kinetic energy changes, and it can only
        fall. It acts only on pairs still closing slower than the
        restitution threshold, i.e. resting contact the sweeps left
        unfinished; real impacts were solved by the sweeps. The energy is
        the work of the impulses (``contact_law.apply_impulses``), booked
        as 'restitution'. Returns None when no pair needed it.
        """
        state = ctx.state
        # Heights relative to the first contact's particle: the order is the
        # same, and the products keep their digits far from the origin.
        origin = state.position[i[0]]
        height = -((state.position - origin) @ gravity)
        i_lower = height[i] <= height[j]
        order = np.argsort(np.where(i_lower, height[i], height[j]), kind='stable')
        i, j, normal, i_lower = i[order], j[order], normal[order], i_lower[order]
        lower = np.where(i_lower, i, j)
        upper = np.where(i_lower, j, i)
        outward = np.where(i_lower[:, None], -normal, normal)    # lower -> upper
        batches = solve_order(i, j, state.dynamic)
        pushed = None
        dynamic = state.dynamic
        for batch in batches:
            up, n_out = upper[batch], outward[batch]
            u_upper = np.einsum('ij,ij->i', state.velocity[up], n_out)
            u_lower = np.einsum('ij,ij->i', state.velocity[lower[batch]], n_out)
            target = np.minimum(u_lower, 0.0)
            resting = ((u_upper < target - tolerance) & (u_lower - u_upper < threshold)
                       & dynamic[up])
            if not resting.any():
                continue
            magnitude = (target - u_upper)[resting] / state.inv_mass[up[resting]]
            particles, removed = apply_impulses(state.velocity, state.inv_mass, up[resting],
                                                magnitude[:, None] * n_out[resting])
            ctx.book('restitution', removed, particles)
            if pushed is None:
                pushed = np.zeros(i.size)
            pushed[order[batch[resting]]] += magnitude
        return pushed

    def _visit_order(self, i: np.ndarray, j: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
        """Return the order the kernel visits the pairs in (see ``visit``)."""
        if self.visit == 'pairs':
            return np.arange(i.size, dtype=np.int64)
        batches = solve_order(i, j, dynamic)
        return np.concatenate(batches) if batches else np.zeros(0, dtype=np.int64)

    def _shock_order(self, state, i: np.ndarray, j: np.ndarray, gravity: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Return the shock passes' pair order (ground up) and whether i is the lower one."""
        # As _shock_pass: heights relative to the first contact's particle.
        origin = state.position[i[0]]
        height = -((state.position - origin) @ gravity)
        i_lower = height[i] <= height[j]
        order = np.argsort(np.where(i_lower, height[i], height[j]), kind='stable')
        if self.visit == 'colours':
            order = order[np.concatenate(solve_order(i[order], j[order], state.dynamic))]
        return order.astype(np.int64), i_lower

    def describe(self) -> str:
        """Say what the stage does."""
        text = (f'impulse j = -(1+e) vn / (w1+w2) along N, e = {self.restitution:g}, '
                f'colour by colour, up to {self.iterations} sweeps')
        if self.walls is not None:
            text += '; wall contacts in every sweep'
        if self.friction is not None:
            text += (f'; Coulomb friction mu = {self.friction:g} with spin '
                     '(|J_t| <= mu j, I = 2/5 m r^2)')
        if self.gravity is not None:
            text += '; e = 0 below the restitution threshold; shock passes for resting contact'
        if self.warm_start and self.backend == 'kernel':
            text += ('; resting impulses accumulated (clamped) and warm-started from the '
                     'previous step')
        return text
