"""The contact solve's stages stated with the vectorised numpy law: the kernels' oracles.

``SequentialReference``, ``WallReference`` and ``BatchedReference`` run
the law of ``contact_law`` (and ``friction``) over sets of contacts that
share no dynamic particle, one greedy colour of the contact graph per
numpy call, plane after plane at the walls. The compiled stages must give
identical velocities, spins and bookings on the same contacts (the
sequential one visiting in colour order, without warm starting: the
reference states the law without accumulated impulses). ``lookup`` and
``store`` are the warm-start cache's set-up in numpy.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from oracles.contact_law import (apply_pair_friction, apply_pair_impulses, apply_wall_friction,
                                 apply_wall_impulses, pair_coefficient,
                                 reflect_on_plane, wall_coefficient)
from oracles.impulse import closing_speed
from collision_node.physics.model.impacts import record_pairs, record_walls
from collision_node.physics.model.tunables import (RESIDUAL_FRACTION, STRIKE_FACTOR,
                                                   WALL_SLOP, WALL_ULPS)
from collision_node.physics.stages.solve.batched_impulses import (BatchedImpulseStage,
                                                                  shared_scale)
from collision_node.physics.stages.solve.contact_kernels import MAX_CACHED_ID, WarmStartCache
from collision_node.physics.stages.solve.sequential_impulses import (SequentialImpulseStage,
                                                                     solve_order)
from collision_node.physics.stages.solve.walls import WallStage
from collision_node.physics.step.pipeline import Contacts, StepContext


def reference_of(stage):
    """Return the numpy reference of a compiled solve or walls stage (same settings)."""
    if isinstance(stage, SequentialImpulseStage):
        return SequentialReference(stage.restitution, stage.iterations, stage.friction,
                                   stage.walls, stage.gravity)
    if isinstance(stage, WallStage):
        return WallReference(stage.walls, stage.friction)
    if isinstance(stage, BatchedImpulseStage):
        return BatchedReference(stage.restitution, stage.iterations)
    raise TypeError(f'no reference for {type(stage).__name__}')


class ReferenceWallContacts:
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

        Returns whether any particle approached.
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


def reference_wall_contacts(stage: SequentialImpulseStage, state, dimensions: int,
                            threshold: float, record: bool) -> list[ReferenceWallContacts]:
    """Return the particles touching each wall plane, one entry per plane touched."""
    if stage.walls is None:
        return []
    out = []
    for axis, plane, inward in stage.walls.planes(dimensions):
        gap = inward * (state.position[:, axis] - plane) - state.radius
        # Relative to the particle and to the float spacing where it is.
        slop = WALL_SLOP * state.radius + WALL_ULPS * np.spacing(abs(plane))
        index = np.flatnonzero(state.dynamic & (gap <= slop))
        if index.size == 0:
            continue
        e = wall_coefficient(state.restitution, index, stage.walls.restitution)
        impact = None
        if threshold > 0.0:
            impact = -inward * state.velocity[index, axis] >= threshold
        mu = None
        if stage.friction is not None:
            mu = wall_coefficient(state.friction, index, stage.friction)
        out.append(ReferenceWallContacts(axis, plane, inward, index, e, mu, threshold, impact,
                                         record))
    return out


class SequentialReference(SequentialImpulseStage):
    """The sequential solve with numpy, colour by colour, without accumulated impulses."""

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
        tolerance = RESIDUAL_FRACTION * threshold
        struck = impact = None
        if threshold > 0.0:
            struck = np.zeros(len(state), dtype=bool)
            impact = -closing_speed(state.velocity, i, j, normal) >= threshold
        per_pair = np.ndim(restitution) > 0
        batches = solve_order(i, j, state.dynamic)
        record = ctx.impacts is not None
        walls = reference_wall_contacts(self, state, ctx.dimensions, threshold, record)
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
                    fast = -closing_speed(state.velocity, bi, bj, bn) >= threshold
                    e = np.where(fast & (impact[batch] | struck[bi] | struck[bj]), e, 0.0)
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
            # contact is resolved: skip the checking sweep.
            if not applied or (len(batches) == 1 and not walls):
                break
        ctx.stats.collisions += int(hit.sum())
        ctx.stats.wall_collisions += int(sum(int(w.hit.sum()) for w in walls))
        if record:
            pushed = summed_normal > 0.0
            record_pairs(ctx.impacts, ctx.time, state.position, state.radius, i[pushed],
                         j[pushed], normal[pushed], summed_normal[pushed],
                         summed_tangential[pushed], np.maximum(approach0[pushed], 0.0))
            for wall in walls:
                wall.record(ctx)


class WallReference(WallStage):
    """The walls stage with numpy, plane after plane."""

    def run(self, ctx: StepContext) -> None:
        """Reflect and clamp in place; count wall impacts, book lost energy."""
        s = ctx.state
        dyn = s.dynamic
        gravity = ctx.effects.gravity
        threshold = ctx.effects.threshold(ctx.dt)
        for axis, plane, inward in self.walls.planes(ctx.dimensions):
            p, v = s.position[:, axis], s.velocity[:, axis]
            gap = inward * (p - plane) - s.radius
            inside_wall = dyn & (gap < 0.0)
            if not np.any(inside_wall):
                continue
            index = np.flatnonzero(inside_wall)
            u1 = inward * v[index]
            hit_local = u1 < 0.0
            hit = index[hit_local]
            g_n = 0.0 if gravity is None else inward * float(gravity[axis])
            rest = index[~hit_local]
            if rest.size:
                # Put back inside without an impact: the lift's energy, a negative loss.
                ctx.book('walls', -g_n * gap[rest] / s.inv_mass[rest], rest)
                p[rest] = plane + inward * s.radius[rest]
            if not hit.size:
                continue
            ctx.stats.wall_collisions += int(hit.size)
            e = wall_coefficient(s.restitution, hit, self.walls.restitution)
            out = reflect_on_plane(gap[hit], u1[hit_local], g_n, ctx.dt, e, threshold)
            mass = 1.0 / s.inv_mass[hit]
            normal_impulse = mass * (out['velocity'] - u1[hit_local])
            v[hit] = inward * out['velocity']
            p[hit] = plane + inward * (out['gap'] + s.radius[hit])
            ctx.book('walls', mass * (out['impact_loss_per_mass']
                                      + out['settle_loss_per_mass']), hit)
            tangential = 0.0
            if self.friction is not None:
                normal = np.zeros((hit.size, 3))
                normal[:, axis] = inward
                mu = wall_coefficient(s.friction, hit, self.friction)
                tangential, removed = apply_wall_friction(
                    s.velocity, s.angular_velocity, s.inv_mass, s.radius, hit, normal,
                    normal_impulse, mu, ctx.dimensions == 2)
                ctx.book('friction', removed, hit)
            record_walls(ctx.impacts, ctx.time + ctx.dt - out['back'], s.position, hit, axis,
                         plane, inward, normal_impulse, tangential, out['impact'])


class BatchedReference(BatchedImpulseStage):
    """The batched solve with numpy: every sweep's impulses at once, shared by degree."""

    def run(self, ctx: StepContext) -> None:
        """Apply the law's impulses in place, count the contacts hit, book and record them."""
        contacts = ctx.contacts
        if contacts is None or len(contacts) == 0:
            return
        state = ctx.state
        i, j, normal = contacts.i, contacts.j, contacts.normal
        restitution = pair_coefficient(state.restitution, i, j, self.restitution)
        record = ctx.impacts is not None
        if record:
            approach0 = -closing_speed(state.velocity, i, j, normal)
            summed = np.zeros(len(contacts))
        hit = np.zeros(len(contacts), dtype=bool)
        for _ in range(self.iterations):
            approaching = closing_speed(state.velocity, i, j, normal) < 0.0
            if not approaching.any():
                break
            scale = shared_scale(i, j, approaching, state.dynamic, len(state))
            result = apply_pair_impulses(state.velocity, state.inv_mass, i, j, normal,
                                         restitution, scale=scale)
            ctx.book('restitution', result.removed_at, result.particles)
            if record:
                summed += result.magnitude
            hit |= approaching
        ctx.stats.collisions += int(hit.sum())
        if record:
            record_pairs(ctx.impacts, ctx.time, state.position, state.radius, i[hit], j[hit],
                         normal[hit], summed[hit], 0.0, np.maximum(approach0[hit], 0.0))


def _pair_keys(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return lo * (MAX_CACHED_ID + 1) + hi


def _find(table: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (positions of ``keys`` found in ``table``, their rows in ``table``)."""
    order = np.argsort(table, kind='stable')
    sorted_table = table[order]
    at = np.minimum(np.searchsorted(sorted_table, keys), sorted_table.size - 1)
    found = np.flatnonzero(sorted_table[at] == keys)
    return found, order[at[found]]


def lookup(cache, ids: np.ndarray, i: np.ndarray, j: np.ndarray, w_index: np.ndarray,
           w_code: np.ndarray) -> tuple:
    """Return a ``ContactCache``'s (normal, tangential) impulses of pairs and wall contacts.

    Contacts not in the cache get zeros; tangential impulses come back as
    the impulse on i. ``w_code``: axis * 2 + (inward > 0) per wall contact.
    """
    m, k = i.size, w_index.size
    acc, acc_t = np.zeros(m), np.zeros((m, 3))
    w_acc, w_acc_t = np.zeros(k), np.zeros((k, 3))
    if ids.size and int(ids.max()) > MAX_CACHED_ID:
        return acc, acc_t, w_acc, w_acc_t
    if cache.lo.size and m:
        a, b = ids[i], ids[j]
        swapped = a > b
        found, where = _find(_pair_keys(cache.lo, cache.hi),
                             _pair_keys(np.minimum(a, b), np.maximum(a, b)))
        acc[found] = cache.normal[where]
        sign = np.where(swapped[found], -1.0, 1.0)
        acc_t[found] = cache.tangential[where] * sign[:, None]
    if cache.wall_key.size and k:
        found, where = _find(cache.wall_key, ids[w_index] * 8 + w_code)
        w_acc[found] = cache.wall_normal[where]
        w_acc_t[found] = cache.wall_tangential[where]
    return acc, acc_t, w_acc, w_acc_t


def store(ids: np.ndarray, i: np.ndarray, j: np.ndarray, acc: np.ndarray, acc_t: np.ndarray,
          w_index: np.ndarray, w_code: np.ndarray, w_acc: np.ndarray,
          w_acc_t: np.ndarray) -> WarmStartCache:
    """Return the cache of the contacts that hold a resting impulse, sorted by key."""
    keep = acc > 0.0
    a, b = ids[i[keep]], ids[j[keep]]
    key = _pair_keys(np.minimum(a, b), np.maximum(a, b))
    tangential = acc_t[keep] * np.where(a > b, -1.0, 1.0)[:, None]
    wall_keep = w_acc > 0.0
    wall_key = ids[w_index[wall_keep]] * 8 + w_code[wall_keep]
    order, wall_order = np.argsort(key, kind='stable'), np.argsort(wall_key, kind='stable')
    return WarmStartCache(key[order], acc[keep][order], tangential[order], wall_key[wall_order],
                          w_acc[wall_keep][wall_order], w_acc_t[wall_keep][wall_order])
