"""Closed-form free paths between impacts, and the times they reach a contact (numpy oracle).

The oracle of the compiled roots in ``law/primitives.py`` that the swept stage
and the event-driven mode use. Under uniform gravity a
dynamic particle moves on x(t) = x0 + v0 t + g t^2 / 2 and a static one
does not move, so:

- two dynamic particles share g: their relative path is a straight line
  and their impact time is the smaller root of a quadratic;
- a dynamic particle and a static one (or a wall plane) have a relative
  path that is a parabola: against a plane the gap is a quadratic in t
  (``entering_time``), against a static sphere the squared distance is a
  quartic (``parabola_sphere_time``).
"""

from __future__ import annotations

import numpy as np

# Bisection steps that finish a quartic root the eigenvalues did not give
# (2^-60 of the step: below rounding).
from collision_node.physics.model.tunables import BISECTIONS  # noqa: E402


def entering_time(gap: np.ndarray, rate: np.ndarray, curvature: np.ndarray) -> np.ndarray:
    """Return the first s >= 0 at which gap + rate s + curvature s^2 / 2 falls to 0.

    ``gap`` >= 0 is inside; a gap at or below zero that is closing (or not
    opening while pushed in) counts as now. inf where it never happens.
    """
    # An open side of the walls is a plane at infinity: its gap is inf and the
    # products below are NaN; a subnormal rate overflows a time to inf. Both
    # read as never, which is right.
    with np.errstate(invalid='ignore', over='ignore', divide='ignore'):
        disc = rate * rate - 2.0 * curvature * gap
        root = np.sqrt(np.maximum(disc, 0.0))
        closing = rate < 0.0
        curved = curvature != 0.0
        # The entering root has slope -sqrt(disc); take its cancellation-free form.
        quadratic = np.where(closing, 2.0 * gap / np.where(closing, root - rate, 1.0),
                             (-rate - root) / np.where(curved, curvature, 1.0))
        linear = np.where(closing, gap / np.where(closing, -rate, 1.0), np.inf)
    s = np.where(curved, np.where(disc >= 0.0, quadratic, np.inf), linear)
    s[~(s > 0.0)] = np.inf
    s[(gap <= 0.0) & (closing | ((rate == 0.0) & (curvature < 0.0)))] = 0.0
    return s


def _quartic(coefficients: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Evaluate quartics (rows of 5 coefficients, highest first) at ``s``."""
    out = coefficients[:, 0].copy()
    for k in range(1, 5):
        out = out * s + coefficients[:, k]
    return out


def parabola_sphere_time(offset: np.ndarray, velocity: np.ndarray, accel: np.ndarray,
                         horizon: np.ndarray) -> np.ndarray:
    """Return the first s in [0, horizon] with |offset + v s + a s^2 / 2| <= 1, inf for none.

    Lengths are in units of the contact distance r_i + r_j (so the sphere
    is the unit sphere) and ``accel`` is nonzero: the relative path of a
    falling particle and a static one. The squared distance less one is a
    quartic in s; its real roots are the eigenvalues of its companion
    matrix (all pairs at once), written in units of the horizon so the
    coefficients stay of order one, then polished by Newton steps. Where
    the path ends inside the sphere but no root was accepted, bisection
    finds the entry. An overlapping pair that is closing impacts at once.
    """
    m = offset.shape[0]
    out = np.full(m, np.inf)
    if not m:
        return out
    span = np.maximum(horizon, 0.0)
    o, c, k = offset, velocity * span[:, None], 0.5 * accel * (span * span)[:, None]
    dot = lambda p, q: np.einsum('ij,ij->i', p, q)  # noqa: E731
    coefficients = np.stack([dot(k, k), 2.0 * dot(c, k), dot(c, c) + 2.0 * dot(o, k),
                             2.0 * dot(o, c), dot(o, o) - 1.0], axis=1)
    inside = coefficients[:, 4] <= 0.0
    now = inside & ((coefficients[:, 3] < 0.0)
                    | ((coefficients[:, 3] == 0.0) & (dot(o, k) < 0.0)))
    out[now] = 0.0
    todo = np.flatnonzero(~inside & (span > 0.0) & (coefficients[:, 0] > 0.0))
    if not todo.size:
        return out
    q = coefficients[todo]
    companion = np.zeros((todo.size, 4, 4))
    companion[:, 0, :] = -q[:, 1:] / q[:, :1]
    companion[:, 1, 0] = companion[:, 2, 1] = companion[:, 3, 2] = 1.0
    with np.errstate(all='ignore'):
        roots = np.linalg.eigvals(companion)
        real = np.abs(roots.imag) <= 1e-6 * (1.0 + np.abs(roots.real))
        sigma = np.where(real, roots.real, np.inf)
        derivative = q[:, :4] * np.array([4.0, 3.0, 2.0, 1.0])
        for _ in range(3):
            value = np.stack([_quartic(q, sigma[:, r]) for r in range(4)], axis=1)
            slope = np.stack([((derivative[:, 0] * sigma[:, r] + derivative[:, 1])
                               * sigma[:, r] + derivative[:, 2]) * sigma[:, r]
                              + derivative[:, 3] for r in range(4)], axis=1)
            step = np.where(slope != 0.0, value / np.where(slope != 0.0, slope, 1.0), 0.0)
            sigma = np.where(np.isfinite(sigma), sigma - step, np.inf)
        sigma = np.where((sigma >= 0.0) & (sigma <= 1.0), sigma, np.inf)
    first = sigma.min(axis=1)
    # A root the eigenvalues missed (a close double root) while the path ends
    # inside: bisect between the start (outside) and the end (inside).
    missed = ~np.isfinite(first) & (_quartic(q, np.ones(todo.size)) <= 0.0)
    if missed.any():
        lo, hi = np.zeros(int(missed.sum())), np.ones(int(missed.sum()))
        qm = q[missed]
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            entered = _quartic(qm, mid) <= 0.0
            hi, lo = np.where(entered, mid, hi), np.where(entered, lo, mid)
        first[missed] = hi
    out[todo] = first * span[todo]
    return out
