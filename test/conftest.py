"""Shared test helpers: build worlds from inline scene mappings."""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, settings

from collision_node import World, parse_scene

# Hypothesis profiles: ``fast`` (the default, what .ci/run uses) is
# derandomized so CI is reproducible; ``deep`` is the long search, run as
#   HYPOTHESIS_PROFILE=deep python -m pytest test/test_hard_cases.py test/test_fuzz.py
# and it also lengthens the hard cases that have a long form (docs/stability.md).
settings.register_profile('fast', max_examples=100, deadline=None, derandomize=True,
                          database=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile('deep', max_examples=3000, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
HYPOTHESIS_PROFILE = os.environ.get('HYPOTHESIS_PROFILE', 'fast')
settings.load_profile(HYPOTHESIS_PROFILE)


def make_world(**scene) -> World:
    """Return a world for an inline scene mapping (keys as in a scene file)."""
    return World(parse_scene(scene, 'test-scene'))


@pytest.fixture
def world_from():
    """Give tests the ``make_world`` helper."""
    return make_world


@pytest.fixture
def deep_profile() -> bool:
    """Say whether the long forms of the hard cases should run (HYPOTHESIS_PROFILE=deep)."""
    return HYPOTHESIS_PROFILE == 'deep'
