"""The final state of every shipped scene at every preset it accepts, pinned by digest.

A refactor that changes no outcome keeps these digests: positions,
velocities, spins and the step statistics after a fixed number of steps,
hashed bit for bit. A change that must move floating-point operations
re-pins them in a commit of its own (``python test/test_outcome_digest.py``
prints the current table).
"""

from __future__ import annotations

import hashlib
import sys

import numpy as np
import pytest

from collision_node import load_scene, SceneError, World
from collision_node.physics.model.accuracy import parse_accuracy_text
from collision_node.physics.model.scene import shipped_scene_names

# The four presets, and batched ordering (the one setting no preset uses).
PRESETS = {'fast': 'fast', 'balanced': 'balanced', 'accurate': 'accurate', 'exact': 'exact',
           'batched': '{preset: balanced, ordering: batched}'}
# Steps per scene: enough for every scene to have impacts (the 10k gas is short).
STEPS = {'gas_10k': 8, 'billiards_break': 360, 'elastic_break': 240}
DEFAULT_STEPS = 120

PINNED = {
    ('billiards_break', 'fast'): 'c5acc58ee6f06a00843f',
    ('billiards_break', 'balanced'): 'e8d8807bf8b8477b1721',
    ('billiards_break', 'accurate'): 'fe9d3f67c4bf5d055b50',
    ('billiards_break', 'exact'): '648beaacab85f4de656a',
    ('billiards_break', 'batched'): '4b4f919593d1feeed10b',
    ('bouncing_balls', 'fast'): '176a1bd7cd947f19ddff',
    ('bouncing_balls', 'balanced'): '3bd1a82f3449d1c2d1dc',
    ('bouncing_balls', 'accurate'): 'e7a19c40247978270f22',
    ('bouncing_balls', 'exact'): '7d5e67e32be30dc57330',
    ('bouncing_balls', 'batched'): '3bd1a82f3449d1c2d1dc',
    ('bullet', 'fast'): '032bc712854282db6c91',
    ('bullet', 'balanced'): '032bc712854282db6c91',
    ('bullet', 'accurate'): '876da2d3a0212580a9e3',
    ('bullet', 'exact'): 'edbc56478f464811bcbd',
    ('bullet', 'batched'): '032bc712854282db6c91',
    ('cradle', 'fast'): '04eaa26eaae656d76688',
    ('cradle', 'balanced'): '04eaa26eaae656d76688',
    ('cradle', 'accurate'): '04eaa26eaae656d76688',
    ('cradle', 'exact'): '04eaa26eaae656d76688',
    ('cradle', 'batched'): '04eaa26eaae656d76688',
    ('elastic_break', 'fast'): '17fc2c80db01de9ffbbd',
    ('elastic_break', 'balanced'): '5c8592b64b26f94852f7',
    ('elastic_break', 'accurate'): '80b3b01e499a08f060db',
    ('elastic_break', 'exact'): '5150ca4d7e7dc3572ab8',
    ('elastic_break', 'batched'): '7328a472e1061f21025a',
    ('gas_10k', 'fast'): 'cc72873f152e78fb8d3a',
    ('gas_10k', 'balanced'): 'c38ac851819f3b609ce7',
    ('gas_10k', 'accurate'): '6c95c4637e742ae918dd',
    ('gas_10k', 'exact'): '24703022c069f40e2660',
    ('gas_10k', 'batched'): 'c38ac851819f3b609ce7',
    ('oblique_pair', 'fast'): '59aab38b8bdc1164f9c8',
    ('oblique_pair', 'balanced'): '59aab38b8bdc1164f9c8',
    ('oblique_pair', 'accurate'): '02e6f1cb3874679dc3f7',
    ('oblique_pair', 'exact'): '59aab38b8bdc1164f9c8',
    ('oblique_pair', 'batched'): '59aab38b8bdc1164f9c8',
    ('pile', 'fast'): 'e26d96e2778bf9b6f816',
    ('pile', 'balanced'): 'ffa58ba6b064007f0363',
    ('pile', 'accurate'): 'f59289ef8da0e56e6630',
    ('pile', 'exact'): None,
    ('pile', 'batched'): 'ffa58ba6b064007f0363',
    ('spin_billiards', 'fast'): '32dc053f546ae0b6acdb',
    ('spin_billiards', 'balanced'): '32dc053f546ae0b6acdb',
    ('spin_billiards', 'accurate'): 'e5fd9f6fc990744fb5ff',
    ('spin_billiards', 'exact'): None,
    ('spin_billiards', 'batched'): '32dc053f546ae0b6acdb',
}


def scene_for(name: str, preset: str):
    """Return the shipped scene ``name`` at ``preset``, or None where it refuses the preset."""
    scene = load_scene(name)
    try:
        return scene.with_accuracy(parse_accuracy_text(PRESETS[preset], scene.effects, 'preset'))
    except SceneError:
        return None


def outcome_digest(name: str, preset: str) -> str | None:
    """Return the digest of the state and stats after the scene's steps, or None if refused."""
    scene = scene_for(name, preset)
    if scene is None:
        return None
    world = World(scene)
    world.step(STEPS.get(name, DEFAULT_STEPS))
    return world_digest(world)


def world_digest(world: World) -> str:
    """Return the digest of a world's state (ids, positions, velocities, spins) and counts."""
    state = world.state
    digest = hashlib.sha256()
    for array in (state.ids, state.position, state.velocity, state.angular_velocity,
                  state.orientation):
        if array is not None:
            digest.update(np.ascontiguousarray(array).tobytes())
    digest.update(repr((world.steps, world.stats.collisions)).encode())
    return digest.hexdigest()[:20]


CASES = [(name, preset) for name in sorted(shipped_scene_names()) for preset in PRESETS]


@pytest.mark.parametrize('name,preset', CASES)
def test_outcome_is_pinned(name, preset):
    assert (name, preset) in PINNED, f'{name} at {preset} has no pinned digest'
    assert outcome_digest(name, preset) == PINNED[(name, preset)]


if __name__ == '__main__':
    for name, preset in CASES:
        print(f'    ({name!r}, {preset!r}): {outcome_digest(name, preset)!r},')
        sys.stdout.flush()
