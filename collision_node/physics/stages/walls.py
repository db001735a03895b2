"""Walls: axis-aligned planes (a box, or single planes such as a floor).

A particle found past a plane at the end of a step, moving into it, is
taken back to the instant it touched the plane, reflected there with
v_n -> -e v_n, and moved on for the rest of the step. With gravity the
path is the step's parabola (the drift plus gravity stages move particles
exactly along it), so the time of impact solves
q1 - u1 t + g_n t^2 / 2 = 0 backwards from the end of the step; with
e = 1 a ball bouncing on a floor keeps its apex height to rounding, and
with e < 1 the apex falls by exactly e^2 per bounce. Where that path is
not the particle's (it was pushed in by separation, or started inside)
the impact is taken at the end of the step: reflect and clamp.

A reflected particle that would be back inside the plane before the step
ends (a slow or inelastic impact under gravity) rests on it: v_n = 0,
placed on the plane. Impacts slower than the restitution threshold
(``Effects.threshold``) are perfectly inelastic. Per-particle restitution
combines with the walls' by the geometric mean (see ``effects``). With
friction declared, each impact also gets a Coulomb friction impulse
bounded by mu times its normal impulse, which spins the particle.

Energy: the change of kinetic plus potential energy of the particles a
plane touches is booked as 'walls' (restitution, resting contact and any
clamp), the friction part as 'friction'.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ..effects import Walls, combine
from ..energy import mechanical
from ..friction import apply_wall_friction
from ..step import Stage, StepContext


def reflect_on_plane(q1: np.ndarray, u1: np.ndarray, g_n: float, dt: float,
                     restitution, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (gap, normal velocity) at the end of the step after the impact.

    ``q1`` (< 0) is how far the particle is past the plane and ``u1`` (< 0)
    its velocity along the inward normal at the end of the step; ``g_n`` is
    gravity along that normal.
    """
    # Smallest t >= 0 with q1 - u1 t + g_n t^2 / 2 = 0, in the form without
    # cancellation (u1 - sqrt(D) adds two negative numbers).
    disc = u1 * u1 - 2.0 * g_n * q1
    real = disc >= 0.0
    denominator = u1 - np.sqrt(np.where(real, disc, 0.0))
    back = np.where(real & (denominator < 0.0),
                    2.0 * q1 / np.where(denominator < 0.0, denominator, -1.0), np.inf)
    on_path = back <= dt
    back = np.where(on_path, back, 0.0)
    impact = u1 - g_n * back
    e = np.where(-impact < threshold, 0.0, restitution) if threshold > 0.0 else restitution
    out = -e * impact
    gap = np.where(on_path, out * back + 0.5 * g_n * back * back, 0.0)
    velocity = out + g_n * back
    resting = gap < 0.0
    return np.where(resting, 0.0, gap), np.where(resting, 0.0, velocity)


class WallStage(Stage):
    """Reflect particles that reach a wall plane at their time of impact."""

    name = 'walls'

    def __init__(self, walls: Walls, friction: Optional[float] = None) -> None:
        """Keep the planes and the Coulomb coefficient at walls (None: no friction)."""
        self.walls = walls
        self.friction = friction

    def run(self, ctx: StepContext) -> None:
        """Reflect and clamp in place; count wall impacts, book lost energy."""
        s = ctx.state
        dyn = s.dynamic
        gravity = ctx.effects.gravity
        threshold = ctx.effects.threshold(ctx.dt)
        lost = lost_friction = 0.0
        for axis, plane, inward in self.walls.planes(ctx.dimensions):
            p, v = s.position[:, axis], s.velocity[:, axis]
            gap = inward * (p - plane) - s.radius
            inside_wall = dyn & (gap < 0.0)
            if not np.any(inside_wall):
                continue
            index = np.flatnonzero(inside_wall)
            before = mechanical(s, gravity, index)
            u1 = inward * v[index]
            hit_local = u1 < 0.0
            hit = index[hit_local]
            ctx.stats.wall_collisions += int(hit.size)
            if hit.size:
                g_n = 0.0 if gravity is None else inward * float(gravity[axis])
                own = None if s.restitution is None else s.restitution[hit]
                e = combine(own, None, self.walls.restitution)
                new_gap, new_u = reflect_on_plane(gap[hit], u1[hit_local], g_n, ctx.dt, e,
                                                  threshold)
                normal_impulse = (new_u - u1[hit_local]) / s.inv_mass[hit]
                v[hit] = inward * new_u
                p[hit] = plane + inward * (new_gap + s.radius[hit])
            # Position projection back inside for the rest: no velocity change.
            rest = index[~hit_local]
            p[rest] = plane + inward * s.radius[rest]
            after = mechanical(s, gravity, index)
            lost += before - after
            if self.friction is not None and hit.size:
                lost_friction += self._friction(ctx, hit, axis, inward, normal_impulse)
        ctx.stats.add_dissipated('walls', lost)
        if self.friction is not None:
            ctx.stats.add_dissipated('friction', lost_friction)

    def _friction(self, ctx: StepContext, hit: np.ndarray, axis: int, inward: float,
                  normal_impulse: np.ndarray) -> float:
        """Apply Coulomb friction at wall impacts of one plane; return energy removed."""
        s = ctx.state
        normal = np.zeros((hit.size, 3))
        normal[:, axis] = inward
        own = None if s.friction is None else s.friction[hit]
        mu = combine(own, None, self.friction)
        return apply_wall_friction(s.velocity, s.angular_velocity, s.inv_mass, s.radius, hit,
                                   normal, normal_impulse, mu, ctx.dimensions == 2)

    def describe(self) -> str:
        """Say what the stage does."""
        w = self.walls
        sides = ', '.join(f'{"xyz"[axis]} {"min" if inward > 0 else "max"} = {plane:g}'
                          for axis, plane, inward in w.planes(3))
        text = (f'planes {sides} m; impact at its time in the step, v_n -> '
                f'-{w.restitution:g} v_n (rest below the restitution threshold)')
        if self.friction is not None:
            text += f'; Coulomb friction mu = {self.friction:g} with spin'
        return text
