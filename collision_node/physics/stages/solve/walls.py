"""Walls: axis-aligned planes (a box, or single planes such as a floor).

A particle found past a plane at the end of a step, moving into it, is
taken back to the instant it touched the plane, reflected there by the
contact law (``contact_law.reflect_on_plane``: v_n -> -e v_n with the
combined e, 0 below the restitution threshold) and moved on for the rest
of the step. With gravity the path is the step's parabola (the drift plus
gravity stages move particles exactly along it); with e = 1 a ball
bouncing on a floor keeps its apex height to rounding, and with e < 1 the
apex falls by exactly e^2 per bounce. Where that path is not the
particle's (it was pushed in by separation, or started inside) the impact
is taken at the end of the step: reflect and clamp.

A reflected particle that would be back inside the plane before the step
ends (a slow or inelastic impact under gravity) rests on it: v_n = 0,
placed on the plane. With friction declared, each impact also gets a
Coulomb friction impulse bounded by mu times its normal impulse, which
spins the particle.

Energy, booked per particle from the law (relative to the plane, so exact
far from the origin): 'walls' gets the impact's (1 - e^2)/2 m v^2, the
rebound energy of a particle that comes to rest on the plane, and the
lift (a negative loss) of a particle put back onto the plane without an
impact on its path; 'friction' gets the friction impulse's work.

``run_vectorised`` states this law with numpy, plane after plane; the
stage runs it compiled (``wall_kernels.wall_pass``, backend 'kernel', the
default): one pass over the particles, identical positions, velocities,
spins, bookings and impact records (``test/test_wall_kernels.py``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...law.contact_law import (apply_wall_friction, record_walls, reflect_on_plane,
                                wall_coefficient)
from ...model.effects import Walls
from ...model.impacts import WALL
from ...step.pipeline import Stage, StepContext
from .wall_kernels import (APPROACH, BACK, FRICTION_LOSS, NORMAL_IMPULSE, PARTICLE, POINT,
                           TANGENTIAL, WALLS_LOSS, wall_pass)
from ...model.tunables import BACKENDS

_NONE = np.zeros(0)
_NO_SPIN = np.zeros((0, 3))


class WallStage(Stage):
    """Reflect particles that reach a wall plane at their time of impact."""

    name = 'walls'

    def __init__(self, walls: Walls, friction: Optional[float] = None,
                 backend: str = 'kernel') -> None:
        """Keep the planes and the Coulomb coefficient at walls (None: no friction).

        ``backend``: the compiled pass ('kernel') or the vectorised law ('numpy').
        """
        if backend not in BACKENDS:
            raise ValueError(f'backend must be one of {BACKENDS}, got {backend!r}')
        self.walls = walls
        self.friction = friction
        self.backend = backend
        self._planes: dict = {}        # per dimensions: (axis, value, inward) arrays
        # (dt, effects, gravity array, restitution threshold) of the last step.
        self._per_dt: tuple = (None, None, None, 0.0)

    def run(self, ctx: StepContext) -> None:
        """Reflect and clamp in place; count wall impacts, book lost energy."""
        if self.backend == 'numpy':
            self.run_vectorised(ctx)
            return
        planes = self._planes.get(ctx.dimensions)
        if planes is None:
            found = self.walls.planes(ctx.dimensions)
            planes = (np.array([axis for axis, _, _ in found], dtype=np.int64),
                      np.array([value for _, value, _ in found], dtype=float),
                      np.array([inward for _, _, inward in found], dtype=float), found)
            self._planes[ctx.dimensions] = planes
        s = ctx.state
        gravity = ctx.effects.gravity
        friction = self.friction is not None
        if ctx.dt != self._per_dt[0] or ctx.effects is not self._per_dt[1]:
            # The gravity vector and the threshold, computed once per dt.
            self._per_dt = (ctx.dt, ctx.effects, np.zeros(3) if gravity is None
                            else np.asarray(gravity, dtype=float),
                            ctx.effects.threshold(ctx.dt))
        floats, ints, group_start = wall_pass(
            s.position, s.velocity, _NO_SPIN if s.angular_velocity is None or not friction
            else s.angular_velocity, s.radius, s.inv_mass,
            _NONE if s.restitution is None else s.restitution, float(self.walls.restitution),
            _NONE if s.friction is None or not friction else s.friction,
            float(self.friction) if friction else 0.0, friction, planes[0], planes[1],
            planes[2], gravity is not None, self._per_dt[2], ctx.dt, self._per_dt[3],
            ctx.dimensions == 2)
        if not ints.shape[0]:
            return
        # Book and record plane by plane, as the vectorised law does: the same
        # arrays in the same order give the same totals to the last bit.
        starts = group_start.tolist()
        for k, (axis, plane, inward) in enumerate(planes[3]):
            low, middle, high = starts[2 * k], starts[2 * k + 1], starts[2 * k + 2]
            if low < middle:
                ctx.book('walls', np.ascontiguousarray(floats[low:middle, WALLS_LOSS]),
                         np.ascontiguousarray(ints[low:middle, PARTICLE]))
            if middle == high:
                continue
            hit = np.ascontiguousarray(ints[middle:high, PARTICLE])
            row = floats[middle:high]
            ctx.stats.wall_collisions += high - middle
            ctx.book('walls', np.ascontiguousarray(row[:, WALLS_LOSS]), hit)
            if friction:
                ctx.book('friction', np.ascontiguousarray(row[:, FRICTION_LOSS]), hit)
            if ctx.impacts is not None:
                normal = np.zeros((hit.size, 3))
                normal[:, axis] = inward
                ctx.impacts.record(ctx.time + ctx.dt - row[:, BACK], hit, WALL,
                                   row[:, POINT:POINT + 3], normal, row[:, NORMAL_IMPULSE],
                                   row[:, TANGENTIAL] if friction else 0.0, row[:, APPROACH])

    def run_vectorised(self, ctx: StepContext) -> None:
        """Apply the law with numpy, plane after plane (the compiled pass's reference)."""
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
                # Position projection back inside, no velocity change: the lift
                # from q < 0 (the depth past the plane) adds m g_n q of energy,
                # booked as a loss of -m g_n q (<= 0 for a floor, g_n < 0).
                ctx.book('walls', -g_n * gap[rest] / s.inv_mass[rest], rest)
                p[rest] = plane + inward * s.radius[rest]
            if not hit.size:
                continue
            ctx.stats.wall_collisions += int(hit.size)
            e = wall_coefficient(s.restitution, hit, self.walls.restitution)
            out = reflect_on_plane(gap[hit], u1[hit_local], g_n, ctx.dt, e, threshold)
            mass = 1.0 / s.inv_mass[hit]
            # What the plane delivered over the step (the impact, and the stop
            # of a particle that comes to rest): it bounds the friction.
            normal_impulse = mass * (out['velocity'] - u1[hit_local])
            v[hit] = inward * out['velocity']
            p[hit] = plane + inward * (out['gap'] + s.radius[hit])
            ctx.book('walls', mass * (out['impact_loss_per_mass']
                                      + out['settle_loss_per_mass']), hit)
            tangential = 0.0
            if self.friction is not None:
                tangential = self._friction(ctx, hit, axis, inward, normal_impulse)
            record_walls(ctx.impacts, ctx.time + ctx.dt - out['back'], s.position, hit, axis,
                         plane, inward, normal_impulse, tangential, out['impact'])

    def _friction(self, ctx: StepContext, hit: np.ndarray, axis: int, inward: float,
                  normal_impulse: np.ndarray) -> np.ndarray:
        """Apply Coulomb friction at wall impacts of one plane; return its impulses."""
        s = ctx.state
        normal = np.zeros((hit.size, 3))
        normal[:, axis] = inward
        mu = wall_coefficient(s.friction, hit, self.friction)
        tangential, removed = apply_wall_friction(s.velocity, s.angular_velocity, s.inv_mass,
                                                  s.radius, hit, normal, normal_impulse, mu,
                                                  ctx.dimensions == 2)
        ctx.book('friction', removed, hit)
        return tangential

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
