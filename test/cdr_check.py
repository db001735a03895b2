"""Byte-for-byte comparison of hand-written CDR with rclpy's serializer."""

from __future__ import annotations

import numpy as np
from rclpy.serialization import serialize_message


def assert_same_cdr(mine: bytes, padding: list[tuple[int, int]], reference) -> None:
    """Assert ``mine`` equals rclpy's serialisation of ``reference`` on every data byte.

    rmw leaves alignment gaps uninitialised, so gap bytes may differ; every
    gap must be shorter than the widest alignment (8) and zero in ``mine``.
    """
    theirs = serialize_message(reference)
    assert len(mine) == len(theirs)
    gap = np.zeros(len(mine), dtype=bool)
    for offset, length in padding:
        assert 0 < length < 8
        gap[offset:offset + length] = True
    a = np.frombuffer(mine, dtype=np.uint8)
    b = np.frombuffer(theirs, dtype=np.uint8)
    assert not a[gap].any()
    differing = np.flatnonzero(a != b)
    assert gap[differing].all(), f'data bytes differ at offsets {differing[~gap[differing]]}'
