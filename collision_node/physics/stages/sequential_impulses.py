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

The dense-cluster fallback (pairs past ``MAX_BATCHES`` colours) is
frictionless.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..coloring import color_pairs
from ..contact_law import (apply_impulses, apply_pair_friction, apply_pair_impulses,
                           apply_wall_friction, apply_wall_impulses, pair_coefficient,
                           record_pairs, record_walls, wall_coefficient)
from ..effects import Walls
from ..impulse import closing_speed
from ..step import Contacts, Stage, StepContext

# Past this many colours (only in very dense clusters, e.g. a thousand
# particles spawned on one point) the remaining pairs share their impulses
# out, each scaled by 1 / (contacts of its busiest particle): stable and
# never energy-adding, at the price of the order-dependent exactness that
# such a cluster does not have anyway.
MAX_BATCHES = 256


# Closing speeds below this fraction of the restitution threshold count as
# resolved, so sweeps over resting contact stop at rounding-level residues.
RESIDUAL_FRACTION = 1.0e-3
# An impulse marks its particles struck (see _run_dissipative) only if its
# pair closed at this many times the restitution threshold. Closing speeds
# also build up inside a resting stack whose sweeps did not converge in the
# budget (in a column of 20 under `fast`: up to 8.7 times the threshold);
# passing those on as shocks made the stack bounce and gain energy through
# separation (measured: at factor 1 or 2 a column of 20 at e = 1 kept 0.2 to
# 0.7 m/s and a 200-disc pile gained 4.4e-3 J in a step; at 10 neither).
# The price: an impact slower than 10 thresholds (0.8 m/s at 240 Hz under
# 9.81 m/s^2) onto resting balls is not passed on through them.
STRIKE_FACTOR = 10.0
# Passes of shock propagation at most (a particle resting on two others
# needs a few: stopping it against one support can make it approach the
# other).
SHOCK_PASSES = 8
# A particle within this fraction of its radius, plus WALL_ULPS floating-point
# spacings at the plane's coordinate, of a wall plane touches it (the walls
# stage places resting particles on the plane to rounding). Never a fraction
# of the coordinate itself: 1e-9 of a plane at x = 1e9 m was a slop of 1 m.
WALL_SLOP = 1.0e-9
WALL_ULPS = 4.0


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


class SequentialImpulseStage(Stage):
    """Resolve approaching contacts with restitution, colour by colour."""

    name = 'contact_impulses'

    def __init__(self, restitution: float, iterations: int,
                 friction: Optional[float] = None, walls: Optional[Walls] = None,
                 gravity: Optional[np.ndarray] = None) -> None:
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
        struck = impact = None
        if threshold > 0.0:
            struck = np.zeros(len(state), dtype=bool)
            impact = -closing_speed(state.velocity, i, j, normal) >= threshold
        per_pair = np.ndim(restitution) > 0
        batches, leftover = color_pairs(i, j, state.dynamic, MAX_BATCHES)
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
                    bouncing = mask & (e > 0.0) & (result.approach >= STRIKE_FACTOR * threshold)
                    struck[bi[bouncing]] = struck[bj[bouncing]] = True
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
            if leftover.size:
                li, lj, ln = i[leftover], j[leftover], normal[leftover]
                e = restitution[leftover] if per_pair else restitution
                if struck is not None:
                    e = self._thresholded(state, li, lj, ln, e, threshold, impact[leftover],
                                          struck)
                result = apply_pair_impulses(state.velocity, state.inv_mass, li, lj, ln, e,
                                             scale=self._leftover_scale(state, i, j, leftover))
                if result.hit.any():
                    hit[leftover[result.hit]] = True
                    applied = True
                    ctx.book('restitution', result.removed_at, result.particles)
                    if record:
                        summed_normal[leftover] += result.magnitude
            # Each plane is one batch: a particle touches a plane once.
            for wall in walls:
                applied = wall.solve(ctx, tolerance, planar, struck) or applied
            # One batch shares no dynamic particle, so after one sweep every
            # contact is resolved (vn' = -e vn >= 0) and a checking sweep
            # would find nothing: skip it.
            if not applied or (len(batches) == 1 and not leftover.size and not walls):
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
        batches, leftover = color_pairs(i, j, state.dynamic, MAX_BATCHES)
        if leftover.size:
            batches.append(leftover)
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

    @staticmethod
    def _leftover_scale(state, i: np.ndarray, j: np.ndarray, leftover: np.ndarray
                        ) -> np.ndarray:
        """Share out the impulses of pairs past the colour budget (see MAX_BATCHES)."""
        busiest = np.maximum(np.bincount(i[leftover], minlength=len(state)),
                             np.bincount(j[leftover], minlength=len(state)))
        return 1.0 / np.maximum(busiest[i[leftover]], busiest[j[leftover]])

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
        return text
