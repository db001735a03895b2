"""The lecture's formulas as written on the slides, for tests to compare against."""

from __future__ import annotations

import numpy as np


def lecture_update(m1, m2, v1, v2, normal):
    """Return the lecture's post-impact velocities (e = 1), written as on the slides."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a1, a2 = np.dot(v1, n), np.dot(v2, n)
    b1 = ((m1 - m2) * a1 + 2 * m2 * a2) / (m1 + m2)
    b2 = ((m2 - m1) * a2 + 2 * m1 * a1) / (m1 + m2)
    return v1 - a1 * n + b1 * n, v2 - a2 * n + b2 * n
