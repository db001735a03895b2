"""How far the resting contacts hold each particle up (``contact_kernels.support_shift``).

Built from hand-made solve results: a particle whose resting impulse
carries its whole kick gets its sag back exactly, one carrying more gets
no more than its sag, a slope carries its sag along the normal only, and
a cluster touching no wall or static particle moves not at all.
"""

from __future__ import annotations

import numpy as np

from collision_node.physics.stages.solve.contact_kernels import (ContactImpulses,
                                                                 StepContacts, support_shift,
                                                                 WallContacts)

G, DT = 9.81, 1.0 / 60.0
FALL = (0.0, -G * DT, 0.0)
SAG = 0.5 * G * DT * DT
NO_ROWS = np.zeros(0, dtype=np.int64)


def impulses(resting, tangential=None) -> tuple:
    """Return a solve's ``ContactImpulses`` with these accumulated resting impulses."""
    resting = np.asarray(resting, dtype=float)
    m = resting.size
    return tuple(ContactImpulses(np.zeros(m, dtype=np.bool_), resting.copy(), np.zeros(m),
                                 np.zeros(m), np.zeros(m, dtype=np.bool_), resting,
                                 np.zeros(m),
                                 np.zeros((m, 3)) if tangential is None
                                 else np.asarray(tangential, dtype=float)))


def pair_contacts(first, second, normal) -> tuple:
    """Return the ``StepContacts`` record of these pairs (normals from second to first)."""
    return tuple(StepContacts(np.asarray(first, dtype=np.int64),
                              np.asarray(second, dtype=np.int64),
                              np.asarray(normal, dtype=float), NO_ROWS, np.zeros(0), NO_ROWS))


def no_walls() -> tuple:
    """Return ``WallContacts`` without a contact."""
    return tuple(WallContacts(np.zeros(1, dtype=np.int64), NO_ROWS, NO_ROWS, np.zeros(0),
                              np.zeros(0), np.zeros(0), np.zeros(0),
                              np.zeros(0, dtype=np.bool_)))


def shift(inv_mass, contacts, resting, tangential=None) -> np.ndarray:
    """Return ``support_shift`` for pair contacts only."""
    return support_shift(np.asarray(inv_mass, dtype=float), contacts,
                         impulses(resting, tangential), no_walls(), impulses([]), FALL, DT)


def test_a_ball_resting_on_a_static_one_gets_its_sag_back():
    # Ball 0 (2 kg) on static ball 1: a resting impulse of m g dt carries the whole kick.
    moved = shift([0.5, 0.0], pair_contacts([0], [1], [[0.0, 1.0, 0.0]]), [2.0 * G * DT])
    np.testing.assert_allclose(moved, [[0.0, SAG, 0.0], [0.0, 0.0, 0.0]], rtol=1e-15)


def test_a_resting_impulse_above_the_kick_lifts_no_more_than_the_sag():
    moved = shift([1.0, 0.0], pair_contacts([0], [1], [[0.0, 1.0, 0.0]]), [3.0 * G * DT])
    np.testing.assert_allclose(moved[0], [0.0, SAG, 0.0], rtol=1e-15)


def test_a_frictionless_slope_carries_the_sag_along_its_normal():
    normal = np.array([np.sin(0.5), np.cos(0.5), 0.0])
    carried = G * DT * np.cos(0.5)           # the kick's part along the normal
    moved = shift([1.0, 0.0], pair_contacts([0], [1], [normal]), [carried])
    np.testing.assert_allclose(moved[0], 0.5 * DT * carried * normal, rtol=1e-14)
    assert abs(np.dot(moved[0], [np.cos(0.5), -np.sin(0.5), 0.0])) < 1e-18


def test_a_falling_cluster_touching_no_support_moves_not_at_all():
    # Two dynamic balls pressed together: equal and opposite impulses, no wall, no static.
    moved = shift([1.0, 1.0], pair_contacts([0], [1], [[0.0, 1.0, 0.0]]), [G * DT])
    np.testing.assert_array_equal(moved, np.zeros((2, 3)))


def test_a_column_on_a_static_ball_is_held_up_ball_by_ball():
    # Balls 0 and 1 stacked on static ball 2: each carries its own kick, 1 also 0's weight.
    up = [[0.0, 1.0, 0.0]] * 2
    moved = shift([1.0, 1.0, 0.0], pair_contacts([0, 1], [1, 2], up), [G * DT, 2.0 * G * DT])
    np.testing.assert_allclose(moved[:2, 1], [SAG, SAG], rtol=1e-15)
    np.testing.assert_array_equal(moved[2], 0.0)
