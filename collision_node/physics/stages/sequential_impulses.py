"""Contact solve: impulses along the line of action, one colour at a time.

Sweeps the colour batches of the contact graph in order (Gauss-Seidel)
until no contact approaches or the iteration budget is spent. Each
impulse only changes the velocity component along N, exactly as the
lecture's velocity update.

A scene without effects (e = 1, no threshold) takes the lecture's path
unchanged. With e < 1 only, the energy removed is measured around the
solve. With per-particle restitution, a restitution threshold (gravity
sets one by default), friction or walls the general path runs:

- restitution per pair by the combine rule (``effects.combine``), set to
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
  'friction') from the exact per-contact formulas.

The dense-cluster fallback (pairs past ``MAX_BATCHES`` colours) is
frictionless.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..coloring import color_pairs
from ..effects import Walls, combine
from ..energy import kinetic_linear
from ..friction import apply_pair_friction, apply_wall_friction
from ..impulse import apply_normal_impulses, apply_normal_impulses_booked, closing_speed
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
# A particle within this fraction of (radius + |plane|) of a wall plane
# touches it (the walls stage places resting particles on the plane to
# rounding).
WALL_SLOP = 1.0e-9


class WallContacts:
    """Particles touching one wall plane, solved as one batch in each sweep."""

    def __init__(self, axis: int, inward: float, index: np.ndarray, restitution,
                 friction, threshold: float, impact: Optional[np.ndarray]) -> None:
        """Keep the plane, touching particles, their e and mu, the threshold and impacts."""
        self.axis, self.inward, self.index = axis, inward, index
        self.restitution, self.friction = restitution, friction
        self.threshold, self.impact = threshold, impact

    def solve(self, state, tolerance: float, planar: bool, lost: dict,
              struck: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """Reflect particles approaching the plane, v_n -> -e v_n; book losses.

        With a restitution threshold e is the wall's only for a particle
        approaching faster than it that arrived so (an impact) or was
        ``struck`` in this solve, as for pairs; a fast bounce marks it
        struck. Returns the mask of particles hit, or None when none
        approached.
        """
        index = self.index
        u = self.inward * state.velocity[index, self.axis]
        approaching = u < -tolerance
        if not approaching.any():
            return None
        e = self.restitution
        if struck is not None:
            e = np.where((-u >= self.threshold) & (self.impact | struck[index]), e, 0.0)
            struck[index[approaching & (e > 0.0) & (-u >= STRIKE_FACTOR * self.threshold)]] = True
        change = np.where(approaching, -(1.0 + e) * u, 0.0)
        state.velocity[index, self.axis] += self.inward * change
        w = state.inv_mass[index]
        impulse = change / w
        lost['walls'] += 0.5 * float(np.sum(impulse * -u * (1.0 - e)))
        if self.friction is not None:
            hit = index[approaching]
            normal = np.zeros((hit.size, 3))
            normal[:, self.axis] = self.inward
            mu = self.friction[approaching] if np.ndim(self.friction) else self.friction
            lost['friction'] += apply_wall_friction(
                state.velocity, state.angular_velocity, state.inv_mass, state.radius,
                hit, normal, impulse[approaching], mu, planar)
        return approaching


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
        """Apply impulses in place and count the contacts that received one."""
        contacts = ctx.contacts
        if self.walls is None and (contacts is None or len(contacts) == 0):
            return
        threshold = ctx.effects.threshold(ctx.dt)
        if threshold > 0.0 or self.friction is not None or self.walls is not None or \
                ctx.state.restitution is not None:
            self._run_dissipative(ctx, threshold)
            return
        state = ctx.state
        i, j, normal = contacts.i, contacts.j, contacts.normal
        batches, leftover = color_pairs(i, j, state.dynamic, MAX_BATCHES)
        leftover_scale = None
        if leftover.size:
            busiest = np.maximum(np.bincount(i[leftover], minlength=len(state)),
                                 np.bincount(j[leftover], minlength=len(state)))
            leftover_scale = 1.0 / np.maximum(busiest[i[leftover]], busiest[j[leftover]])
        track_energy = self.restitution < 1.0
        if track_energy:
            touched = np.unique(np.concatenate([i, j]))
            energy_before = self._energy(state, touched)
        hit = np.zeros(len(contacts), dtype=bool)
        for _ in range(self.iterations):
            applied = False
            for batch in batches:
                mask = apply_normal_impulses(state.velocity, state.inv_mass, i[batch],
                                             j[batch], normal[batch], self.restitution)
                if mask.any():
                    hit[batch[mask]] = True
                    applied = True
            if leftover.size:
                mask = apply_normal_impulses(state.velocity, state.inv_mass, i[leftover],
                                             j[leftover], normal[leftover], self.restitution,
                                             scale=leftover_scale)
                if mask.any():
                    hit[leftover[mask]] = True
                    applied = True
            # One batch shares no dynamic particle, so after one sweep every
            # contact is resolved (vn' = -e vn >= 0) and a checking sweep
            # would find nothing: skip it.
            if not applied or (len(batches) == 1 and not leftover.size):
                break
        ctx.stats.collisions += int(hit.sum())
        if track_energy:
            ctx.stats.add_dissipated('restitution',
                                     energy_before - self._energy(state, touched))

    def _run_dissipative(self, ctx: StepContext, threshold: float) -> None:
        """Solve with per-pair restitution, the threshold, friction and walls; book losses."""
        state = ctx.state
        contacts = ctx.contacts if ctx.contacts is not None else Contacts.empty()
        i, j, normal = contacts.i, contacts.j, contacts.normal
        own = state.restitution
        restitution = combine(None if own is None else own[i],
                              None if own is None else own[j], self.restitution)
        mu = None
        if self.friction is not None:
            own_mu = state.friction
            mu = combine(None if own_mu is None else own_mu[i],
                         None if own_mu is None else own_mu[j], self.friction)
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
        walls = self._wall_contacts(ctx, threshold)
        hit = np.zeros(len(contacts), dtype=bool)
        wall_hit = [np.zeros(len(w.index), dtype=bool) for w in walls]
        lost = {'restitution': 0.0, 'walls': 0.0, 'friction': 0.0}
        for _ in range(self.iterations):
            applied = False
            for batch in batches:
                bi, bj, bn = i[batch], j[batch], normal[batch]
                e = restitution[batch] if per_pair else restitution
                if struck is not None:
                    e = self._thresholded(state, bi, bj, bn, e, threshold, impact[batch], struck)
                mask, magnitude, removed = apply_normal_impulses_booked(
                    state.velocity, state.inv_mass, bi, bj, bn, e, tolerance)
                if not mask.any():
                    continue
                if struck is not None:
                    closing = magnitude * (state.inv_mass[bi] + state.inv_mass[bj]) / (1.0 + e)
                    bouncing = mask & (e > 0.0) & (closing >= STRIKE_FACTOR * threshold)
                    struck[bi[bouncing]] = struck[bj[bouncing]] = True
                hit[batch[mask]] = True
                applied = True
                lost['restitution'] += removed
                if mu is not None:
                    lost['friction'] += apply_pair_friction(
                        state.velocity, state.angular_velocity, state.inv_mass, state.radius,
                        bi[mask], bj[mask], bn[mask], magnitude[mask],
                        mu[batch][mask] if mu_per_pair else mu, planar)
            if leftover.size:
                touched = np.unique(np.concatenate([i[leftover], j[leftover]]))
                before = kinetic_linear(state, touched)
                e = restitution[leftover] if per_pair else restitution
                if struck is not None:
                    e = self._thresholded(state, i[leftover], j[leftover], normal[leftover], e,
                                          threshold, impact[leftover], struck)
                mask = apply_normal_impulses(state.velocity, state.inv_mass, i[leftover],
                                             j[leftover], normal[leftover], e,
                                             scale=self._leftover_scale(state, i, j, leftover))
                if mask.any():
                    hit[leftover[mask]] = True
                    applied = True
                    lost['restitution'] += before - kinetic_linear(state, touched)
            # Each plane is one batch: a particle touches a plane once.
            for wall, wall_mask in zip(walls, wall_hit):
                mask = wall.solve(state, tolerance, planar, lost, struck)
                if mask is not None:
                    wall_mask |= mask
                    applied = True
            if not applied:
                break
        if shock and len(contacts):
            # The sweeps stop at the tolerance, which leaves a stack sinking at up
            # to that speed and separation lifting it back every step (found by
            # the fuzzer: two balls resting on a floor kept -4.9e-6 m/s). The
            # shock passes finish resting contact exactly (tolerance 0).
            # Walls are the bottom of every pile: solve them first and after each pass.
            for wall in walls:
                wall.solve(state, 0.0, planar, lost, struck)
            for _ in range(SHOCK_PASSES):
                removed = self._shock_pass(state, i, j, normal, self.gravity, threshold, 0.0)
                for wall in walls:
                    wall.solve(state, 0.0, planar, lost, struck)
                if removed is None:
                    break
                lost['restitution'] += removed
        ctx.stats.collisions += int(hit.sum())
        ctx.stats.wall_collisions += int(sum(int(m.sum()) for m in wall_hit))
        for effect, energy in lost.items():
            if effect == 'restitution' or (effect == 'walls' and walls) or \
                    (effect == 'friction' and mu is not None):
                ctx.stats.add_dissipated(effect, energy)

    @staticmethod
    def _thresholded(state, i: np.ndarray, j: np.ndarray, normal: np.ndarray, restitution,
                     threshold: float, impact: np.ndarray, struck: np.ndarray) -> np.ndarray:
        """Return e per pair: its own if closing past the threshold from an impact, else 0."""
        fast = -closing_speed(state.velocity, i, j, normal) >= threshold
        return np.where(fast & (impact | struck[i] | struck[j]), restitution, 0.0)

    def _wall_contacts(self, ctx: StepContext, threshold: float) -> list['WallContacts']:
        """Return the particles touching each wall plane, one entry per plane."""
        if self.walls is None:
            return []
        s = ctx.state
        out = []
        for axis, plane, inward in self.walls.planes(ctx.dimensions):
            gap = inward * (s.position[:, axis] - plane) - s.radius
            slop = WALL_SLOP * (s.radius + abs(plane))
            index = np.flatnonzero(s.dynamic & (gap <= slop))
            if index.size == 0:
                continue
            own = None if s.restitution is None else s.restitution[index]
            e = combine(own, None, self.walls.restitution)
            impact = None
            if threshold > 0.0:
                impact = -inward * s.velocity[index, axis] >= threshold
            mu = None
            if self.friction is not None:
                own_mu = None if s.friction is None else s.friction[index]
                mu = combine(own_mu, None, self.friction)
            out.append(WallContacts(axis, inward, index, e, mu, threshold, impact))
        return out

    @staticmethod
    def _shock_pass(state, i: np.ndarray, j: np.ndarray, normal: np.ndarray,
                    gravity: np.ndarray, threshold: float, tolerance: float
                    ) -> Optional[float]:
        """Stop resting contacts from the ground up; return the energy removed.

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
        unfinished; real impacts were solved by the sweeps. Returns None
        when no pair needed it.
        """
        height = -(state.position @ gravity)
        i_lower = height[i] <= height[j]
        order = np.argsort(np.where(i_lower, height[i], height[j]), kind='stable')
        i, j, normal, i_lower = i[order], j[order], normal[order], i_lower[order]
        lower = np.where(i_lower, i, j)
        upper = np.where(i_lower, j, i)
        outward = np.where(i_lower[:, None], -normal, normal)    # lower -> upper
        batches, leftover = color_pairs(i, j, state.dynamic, MAX_BATCHES)
        if leftover.size:
            batches.append(leftover)
        removed = None
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
            moved = np.unique(up[resting])
            before = kinetic_linear(state, moved)
            np.add.at(state.velocity, up[resting],
                      (target - u_upper)[resting, None] * n_out[resting])
            removed = (removed or 0.0) + before - kinetic_linear(state, moved)
        return removed

    @staticmethod
    def _leftover_scale(state, i: np.ndarray, j: np.ndarray, leftover: np.ndarray
                        ) -> np.ndarray:
        """Share out the impulses of pairs past the colour budget (see MAX_BATCHES)."""
        busiest = np.maximum(np.bincount(i[leftover], minlength=len(state)),
                             np.bincount(j[leftover], minlength=len(state)))
        return 1.0 / np.maximum(busiest[i[leftover]], busiest[j[leftover]])

    @staticmethod
    def _energy(state, index: np.ndarray) -> float:
        """Linear kinetic energy of the particles in ``index``."""
        dyn = index[state.inv_mass[index] > 0.0]
        v = state.velocity[dyn]
        return 0.5 * float(np.sum(np.einsum('ij,ij->i', v, v) / state.inv_mass[dyn]))

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
