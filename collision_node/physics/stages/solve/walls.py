"""Walls: axis-aligned planes (a box, or single planes such as a floor).

A particle found past a plane at the end of a step, moving into it, is
taken back to the instant it touched the plane, reflected there by the
contact law (v_n -> -e v_n with the combined e, 0 below the restitution
threshold) and moved on for the rest
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

The stage runs it compiled (``wall_kernels.wall_pass``): one pass over
the particles; ``test/test_wall_kernels.py`` checks it against the
vectorised statement of the law, plane after plane (positions,
velocities, spins, bookings and impact records bit for bit).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from ...law.primitives import Bodies
from ...model.effects import Walls
from ...model.impacts import WALL
from ...model.tunables import SPECULATIVE_MARGIN, WALL_SLOP, WALL_ULPS
from ...step.pipeline import Stage, StepContext
from ...step.threads import parallel
from .wall_kernels import (APPROACH, BACK, FRICTION_LOSS, NORMAL_IMPULSE, PARTICLE, POINT,
                           TANGENTIAL, wall_pass, WallCoefficients, WallMotion, WallPlanes,
                           WALLS_LOSS)

_NONE = np.zeros(0)
_NO_SPIN = np.zeros((0, 3))


def wall_planes(planes: list) -> WallPlanes:
    """Return (axis, value, inward) triples as the kernels take them."""
    value = np.array([plane for _, plane, _ in planes], dtype=float)
    return WallPlanes(np.array([axis for axis, _, _ in planes], dtype=np.int64), value,
                      np.array([inward for _, _, inward in planes], dtype=float),
                      WALL_ULPS * np.spacing(np.abs(value)))


def near_wall_distance(threshold: float, dt: float) -> tuple[float, float]:
    """Return (slop, ahead) of ``StepContext.near_walls``: the widest wall contact the solve takes.

    A particle touches a plane in the contact solve within slop r + the
    plane's ulps + ahead (m), with slop WALL_SLOP, plus SPECULATIVE_MARGIN and
    ahead = threshold dt for speculative contacts (a restitution threshold
    set); these are the largest of those terms, computed as the solve computes them.
    """
    return (WALL_SLOP + SPECULATIVE_MARGIN,
            float(threshold * dt) if threshold > 0.0 else 0.0)


class WallStage(Stage):
    """Reflect particles that reach a wall plane at their time of impact."""

    name = 'walls'

    def __init__(self, walls: Walls, friction: Optional[float] = None) -> None:
        """Keep the planes and the Coulomb coefficient at walls (None: no friction)."""
        self.walls = walls
        self.friction = friction
        self._planes: dict = {}  # per dimensions: (tuple(WallPlanes), [(axis, value, inward)])
        # (dt, effects, gravity array, restitution threshold) of the last step.
        self._per_dt: tuple = (None, None, None, 0.0)

    def run(self, ctx: StepContext) -> None:
        """Reflect and clamp in place; count wall impacts, book lost energy."""
        planes = self._planes.get(ctx.dimensions)
        if planes is None:
            found = self.walls.planes(ctx.dimensions)
            planes = (tuple(wall_planes(found)), found)
            self._planes[ctx.dimensions] = planes
        s = ctx.state
        gravity = ctx.effects.gravity
        friction = self.friction is not None
        if ctx.dt != self._per_dt[0] or ctx.effects is not self._per_dt[1]:
            # The gravity vector and the threshold, computed once per dt.
            self._per_dt = (ctx.dt, ctx.effects, np.zeros(3) if gravity is None
                            else np.asarray(gravity, dtype=float),
                            ctx.effects.threshold(ctx.dt))
        bodies = Bodies(s.velocity, _NO_SPIN if s.angular_velocity is None or not friction
                        else s.angular_velocity, s.inv_mass, s.radius)
        coefficients = WallCoefficients(
            _NONE if s.restitution is None else s.restitution, float(self.walls.restitution),
            _NONE if s.friction is None or not friction else s.friction,
            float(self.friction) if friction else 0.0)
        threshold = float(self._per_dt[3])
        motion = WallMotion(friction, gravity is not None, self._per_dt[2], float(ctx.dt),
                            threshold, ctx.dimensions == 2, *near_wall_distance(threshold,
                                                                                ctx.dt))
        # The records as plain tuples: the compiled dispatcher types those fast.
        floats, ints, group_start, near = wall_pass(tuple(bodies), s.position, planes[0],
                                                    tuple(coefficients), tuple(motion),
                                                    parallel(ctx.threads, len(s)))
        ctx.near_walls = near
        if not ints.shape[0]:
            return
        # Book and record plane by plane, as the vectorised law does: the same
        # arrays in the same order give the same totals to the last bit.
        starts = group_start.tolist()
        for k, (axis, plane, inward) in enumerate(planes[1]):
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
