"""The allocator policy a stepping process sets (``step/memory.py``)."""

from __future__ import annotations

import ctypes
import platform

import pytest

from collision_node import World
from collision_node.physics.model.scene import load_scene
from collision_node.physics.step import memory


@pytest.mark.skipif(platform.libc_ver()[0] != 'glibc', reason='mallopt is glibc\'s')
def test_a_world_sets_the_allocator_thresholds_once_and_glibc_takes_them():
    World(load_scene('pile'))
    assert memory._applied
    # glibc accepted both values (mallopt returns 1); a second call does nothing.
    assert memory.keep_freed_memory() is True
    libc = ctypes.CDLL('libc.so.6')
    libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    # The largest value mallopt takes is a C int: the tunables never ask for more.
    assert min(memory.ALLOCATOR_TRIM_THRESHOLD, 2 ** 31 - 1) == memory.ALLOCATOR_TRIM_THRESHOLD
    assert libc.mallopt(memory._M_MMAP_THRESHOLD, memory.ALLOCATOR_MMAP_THRESHOLD) == 1
