"""The state after a run is bit-identical for 1, 2 and 4 threads (Box2D's test_determinism).

Every shipped scene at every stepped preset (and batched ordering), a 3-D
pour large enough that the parallel loops run (falling spheres, walls,
resting contact, friction, sleeping), the same pour with its rows kept in
cell order (``stages/ordering``) and a 3-D gas of 20,000 are stepped in
one child process whose numba pool holds 4 threads (``NUMBA_NUM_THREADS``,
which must be set before numba starts), once per thread count; the child
prints a digest of each final state. The default count of the rest of the
suite is every core; ``test_outcome_digest`` pins the same scenes' outcomes
of the single-thread kernels.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from collision_node import World
from collision_node.bench.throughput import gas_scene
from collision_node.physics.model.scene import parse_scene, shipped_scene_names
from collision_node.physics.step import threads
from collision_node.physics.model.validation import SceneError
from collision_node.scenarios import pour3d

from test_outcome_digest import scene_for, world_digest

STEPPED = ('fast', 'balanced', 'accurate', 'batched')
THREAD_COUNTS = (1, 2, 4)
# Steps per case: enough for impacts in every scene, short enough for three runs each.
STEPS = {'gas_10k': 6, 'billiards_break': 120}
DEFAULT_STEPS = 60
POUR_COUNT = 6000
POUR_STEPS = 40
GAS_COUNT = 20_000
GAS_STEPS = 5
# The label mark of a case whose rows are kept in cell order however few they are.
ORDERED = ' in cell order'


def cases() -> list:
    """Return (label, scene factory, steps) for every case the child runs."""
    out = []
    for name in sorted(shipped_scene_names()):
        for preset in STEPPED:
            out.append((f'{name}/{preset}', lambda n=name, p=preset: scene_for(n, p),
                        STEPS.get(name, DEFAULT_STEPS)))
    for preset in ('fast', 'balanced', 'accurate'):
        out.append((f'pour3d_{POUR_COUNT}/{preset}',
                    lambda p=preset: pour3d(POUR_COUNT, accuracy=p), POUR_STEPS))
        out.append((f'gas_{GAS_COUNT}/{preset}',
                    lambda p=preset: parse_scene(dict(gas_scene(GAS_COUNT, fraction=0.1),
                                                      accuracy=p), 'gas'), GAS_STEPS))
        # The same pour with its rows kept in cell order (as a world of
        # SPATIAL_ORDER_MIN_PARTICLES does): renumbered at each full search.
        out.append((f'pour3d_{POUR_COUNT}{ORDERED}/{preset}',
                    lambda p=preset: pour3d(POUR_COUNT, accuracy=p), POUR_STEPS))
    return out


def child_digests() -> dict:
    """Step every case at every thread count; return {label: {threads: digest}} (the child)."""
    result = {}
    for label, make, steps in cases():
        scene = make()
        if scene is None:
            continue
        result[label] = {}
        for count in THREAD_COUNTS:
            world = World(scene, threads=count)
            if ORDERED in label:
                world.pipeline.spatial_order.min_particles = 2
            world.step(steps)
            result[label][count] = world_digest(world)
    return result


@pytest.fixture(scope='module')
def digests() -> dict:
    """Run the child once with a pool of 4 threads; return its digests."""
    env = dict(os.environ, NUMBA_NUM_THREADS=str(max(THREAD_COUNTS)))
    here = Path(__file__).resolve().parent
    env['PYTHONPATH'] = os.pathsep.join([str(here.parent), str(here),
                                         env.get('PYTHONPATH', '')])
    done = subprocess.run([sys.executable, str(Path(__file__).resolve())], env=env,
                          capture_output=True, text=True, timeout=1500)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize('label', [label for label, _, _ in cases()])
def test_state_is_the_same_for_every_thread_count(digests, label):
    if label not in digests:
        # A preset the scene refuses (exact-only effects): nothing to compare.
        assert scene_for(*label.split('/')) is None
        return
    by_count = digests[label]
    assert sorted(by_count) == [str(count) for count in THREAD_COUNTS]
    assert len(set(by_count.values())) == 1, by_count


def test_a_count_over_the_pool_is_refused_with_the_pool_size():
    with pytest.raises(SceneError, match=f'at most {threads.available()}'):
        threads.resolve(threads.available() + 1)
    for bad in (-1, 2.0, True, '2'):
        with pytest.raises(SceneError, match='must be an integer'):
            threads.resolve(bad)
    assert threads.resolve(0) == threads.available()


if __name__ == '__main__':
    print(json.dumps(child_digests()))
