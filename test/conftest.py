"""Shared test helpers: build worlds from inline scene mappings."""

from __future__ import annotations

import pytest

from collision_node import World, parse_scene


def make_world(**scene) -> World:
    """Return a world for an inline scene mapping (keys as in a scene file)."""
    return World(parse_scene(scene, 'test-scene'))


@pytest.fixture
def world_from():
    """Give tests the ``make_world`` helper."""
    return make_world
