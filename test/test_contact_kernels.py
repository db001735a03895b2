"""The compiled contact solve applies exactly the vectorised law; the colouring is a colouring.

``contact_kernels`` writes the law of ``contact_law`` (and ``friction``)
one contact at a time. Here the vectorised law and the kernels run on the
same contacts and must give identical velocities, spins and bookings
(bit for bit where the operations are the same; energy totals summed in
another order to rounding), and the greedy colouring must put no two pairs
that share a dynamic particle in one colour, within its budget.
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys

import numpy as np
import pytest

from collision_node import World
from collision_node.physics.law import coloring
from collision_node.physics.law import primitives
from collision_node.physics.model.accuracy import PRESETS
from collision_node.physics.law.coloring import color_pairs
from oracles.contact_law import apply_pair_friction, apply_pair_impulses
from collision_node.physics.model.scene import load_scene
from collision_node.physics.model.accuracy import parse_accuracy
from collision_node.physics.stages.solve.batched_impulses import BatchedImpulseStage
from collision_node.physics.stages.solve.sequential_impulses import SequentialImpulseStage
from solve_reference import reference_of


def disjoint_pairs(rng: np.random.Generator, count: int):
    """Return random pairs sharing no particle (every third partner static)."""
    n = 2 * count
    velocity = rng.normal(size=(n, 3))
    angular = rng.normal(size=(n, 3))
    inv_mass = rng.uniform(0.2, 5.0, n)
    radius = rng.uniform(0.05, 0.2, n)
    perm = rng.permutation(n)
    i, j = perm[:count], perm[count:]
    inv_mass[j[::3]] = 0.0                               # static partners
    normal = rng.normal(size=(count, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    return velocity, angular, inv_mass, radius, i, j, normal


@pytest.mark.parametrize('planar', [False, True])
def test_kernel_law_equals_vectorised_law_on_one_colour(planar):
    rng = np.random.default_rng(7)
    velocity, angular, inv_mass, radius, i, j, normal = disjoint_pairs(rng, 200)
    e = rng.uniform(0.0, 1.0, i.size)
    mu = rng.uniform(0.0, 1.0, i.size)
    tolerance = 0.05
    v_ref, w_ref = velocity.copy(), angular.copy()
    result = apply_pair_impulses(v_ref, inv_mass, i, j, normal, e, tolerance)
    hit = result.hit
    assert 20 < hit.sum() < i.size              # both outcomes are exercised
    tangential, lost = apply_pair_friction(v_ref, w_ref, inv_mass, radius, i[hit], j[hit],
                                           normal[hit], result.magnitude[hit], mu[hit], planar)
    v_k, w_k = velocity.copy(), angular.copy()
    magnitude, removed = np.zeros(i.size), np.zeros(i.size)
    k_tangential, k_lost = [], []
    for k in range(i.size):
        magnitude[k], _, removed[k] = primitives.pair_impulse(
            v_k, inv_mass, i[k], j[k], *normal[k], e[k], tolerance)
    for k in np.flatnonzero(hit):
        t, loss = primitives.pair_friction(v_k, w_k, inv_mass, radius, i[k], j[k],
                                           *normal[k], magnitude[k], mu[k], planar)
        k_tangential.append(t)
        k_lost.append(loss)
    np.testing.assert_array_equal(v_k, v_ref)
    np.testing.assert_array_equal(w_k, w_ref)
    np.testing.assert_array_equal(magnitude, result.magnitude)
    np.testing.assert_array_equal(removed, result.removed)
    np.testing.assert_array_equal(k_tangential, tangential)
    np.testing.assert_array_equal(k_lost, lost)


def solver_of(world: World) -> SequentialImpulseStage:
    """Return the world's contact solve stage."""
    (stage,) = [s for s in world.pipeline.stages if isinstance(s, SequentialImpulseStage)]
    return stage


def touching_only(world: World) -> None:
    """Make the world's detection and solve take touching contacts only (no speculative)."""
    for stage in world.pipeline.stages:
        if hasattr(stage, 'speculative'):
            stage.speculative = False


def use_reference(world: World, kind: type = SequentialImpulseStage) -> None:
    """Replace the world's compiled ``kind`` stage with its numpy reference."""
    stages = world.pipeline.stages
    (at,) = [k for k, s in enumerate(stages) if isinstance(s, kind)]
    stages[at] = reference_of(stages[at])


def settled_pile(preset: str, steps: int) -> World:
    """Return the shipped 2-D pile (240 discs, e = 0.3, mu = 0.5) after ``steps`` steps."""
    world = World(load_scene('pile').with_accuracy(PRESETS[preset]))
    world.step(steps)
    return world


def assert_same_run(reference: World, kernel: World, steps: int) -> None:
    """Step both worlds and assert identical states, counters, losses and impacts."""
    reference.record_impacts(True)
    kernel.record_impacts(True)
    for _ in range(steps):
        reference.step()
        kernel.step()
        np.testing.assert_array_equal(kernel.state.velocity, reference.state.velocity)
        np.testing.assert_array_equal(kernel.state.position, reference.state.position)
        np.testing.assert_array_equal(kernel.state.angular_velocity,
                                      reference.state.angular_velocity)
    assert kernel.stats.collisions == reference.stats.collisions > 0
    assert kernel.stats.wall_collisions == reference.stats.wall_collisions > 0
    assert kernel.stats.dissipated.keys() == reference.stats.dissipated.keys()
    for effect, value in reference.stats.dissipated.items():
        assert kernel.stats.dissipated[effect] == pytest.approx(value, rel=1e-9, abs=1e-15)
    ref_impacts, k_impacts = reference.take_impacts(), kernel.take_impacts()
    assert ref_impacts.size > 0
    assert ref_impacts.dtype == k_impacts.dtype and ref_impacts.shape == k_impacts.shape
    for name in ref_impacts.dtype.names:
        np.testing.assert_allclose(k_impacts[name], ref_impacts[name], rtol=1e-12, atol=1e-15,
                                   err_msg=name)


@pytest.mark.parametrize('preset', ['fast', 'balanced'])
def test_kernel_solve_equals_vectorised_reference_on_a_pile(preset):
    base = settled_pile(preset, 150)
    reference, kernel = copy.deepcopy(base), copy.deepcopy(base)
    use_reference(reference)
    solver_of(kernel).visit = 'colours'
    # The reference states the law without accumulated impulses (warm starting
    # is the kernel's) and on touching contacts (speculative ones are the
    # kernel's, test_speculative_contacts.py): compare the law itself.
    solver_of(kernel).warm_start = False
    for world in (reference, kernel):
        touching_only(world)
    assert len(base.state) == 240
    assert_same_run(reference, kernel, 10)


def test_overflow_pairs_are_solved_one_by_one_with_friction(monkeypatch):
    # Two colours only: most pile contacts overflow and are visited one at a time.
    monkeypatch.setattr(coloring, 'MAX_COLORS', 2)
    base = settled_pile('fast', 150)
    reference, kernel = copy.deepcopy(base), copy.deepcopy(base)
    use_reference(reference)
    solver_of(kernel).visit = 'colours'
    # The reference states the law without accumulated impulses (warm starting
    # is the kernel's) and on touching contacts (speculative ones are the
    # kernel's, test_speculative_contacts.py): compare the law itself.
    solver_of(kernel).warm_start = False
    for world in (reference, kernel):
        touching_only(world)
    assert_same_run(reference, kernel, 5)
    assert reference.stats.dissipated['friction'] > base.stats.dissipated['friction']


def test_greedy_colouring_of_a_chain_and_a_lattice():
    # A chain of 1,000 contacts takes 2 colours (the chain batches took 256 and a leftover).
    n = 1001
    i, j = np.arange(n - 1), np.arange(1, n)
    batches, overflow = color_pairs(i, j, np.ones(n, dtype=bool))
    assert len(batches) == 2 and overflow.size == 0
    # A 30 x 30 hexagonal lattice: 6 neighbours each, at most 7 greedy colours.
    side = 30
    index = np.arange(side * side).reshape(side, side)
    links = [(index[:, :-1], index[:, 1:]), (index[:-1, :], index[1:, :]),
             (index[:-1, 1:], index[1:, :-1])]
    i = np.concatenate([a.ravel() for a, _ in links])
    j = np.concatenate([b.ravel() for _, b in links])
    dynamic = np.ones(side * side, dtype=bool)
    dynamic[:side] = False                          # a static bottom row never conflicts
    batches, overflow = color_pairs(i, j, dynamic)
    assert overflow.size == 0 and 3 <= len(batches) <= 7
    placed = np.sort(np.concatenate(batches))
    np.testing.assert_array_equal(placed, np.arange(i.size))
    for batch in batches:
        ends = np.concatenate([i[batch], j[batch]])
        ends = ends[dynamic[ends]]
        assert np.unique(ends).size == ends.size     # no shared dynamic particle
    # Past the budget: the pairs that found no colour are overflow, in pair order.
    batches, overflow = color_pairs(i, j, dynamic, max_colors=2)
    assert len(batches) == 2 and overflow.size > 0
    assert np.all(np.diff(overflow) > 0)
    with pytest.raises(ValueError, match='max_colors'):
        color_pairs(i, j, dynamic, max_colors=65)


def test_stage_refuses_an_unknown_visit_order():
    with pytest.raises(ValueError, match='visit'):
        SequentialImpulseStage(1.0, 8, visit='random')


@pytest.mark.parametrize('scene', ['elastic_break', 'gas_10k'])
def test_compiled_batched_solve_equals_vectorised_reference(scene):
    # Batched ordering on a break (balls struck from several sides in one
    # sweep) and the dense gas: states, bookings and impacts bit for bit.
    # (Under 'fast': the ccd presets take batched ordering in the swept stage.)
    accuracy = parse_accuracy({'preset': 'fast', 'ordering': 'batched'}, 'test')
    base = World(load_scene(scene).with_accuracy(accuracy))
    reference, kernel = copy.deepcopy(base), copy.deepcopy(base)
    use_reference(reference, BatchedImpulseStage)
    reference.record_impacts(True)
    kernel.record_impacts(True)
    shared = 0
    for _ in range(6 if scene == 'gas_10k' else 150):
        reference.step()
        kernel.step()
        np.testing.assert_array_equal(kernel.state.velocity, reference.state.velocity)
        np.testing.assert_array_equal(kernel.state.position, reference.state.position)
        impacts = reference.take_impacts()
        taken = kernel.take_impacts()
        assert taken.dtype == impacts.dtype and taken.shape == impacts.shape
        for name in impacts.dtype.names:
            np.testing.assert_array_equal(taken[name], impacts[name], err_msg=name)
        ends = np.concatenate([impacts['i'], impacts['j']])
        shared += int(np.any(np.bincount(ends) > 1)) if ends.size else 0
    assert kernel.stats.collisions == reference.stats.collisions > 0
    assert kernel.stats.dissipated == reference.stats.dissipated
    assert shared > 0                    # some particle took impulses from two contacts


def test_the_compile_shares_hold_every_kernel_module_once():
    from collision_node.physics.step import kernels as k
    placed = list(k.SHARED) + [module for share in k.SHARES for module in share]
    assert sorted(m.__name__ for m in placed) == sorted(m.__name__ for m in k.MODULES)
    assert len(k.SHARES) == 2


def test_first_start_says_it_compiles_and_a_cached_start_says_nothing(tmp_path):
    # Two processes whatever the machine: the helper's share must land in the cache.
    code = ('import sys\nfrom collision_node.physics.step import kernels as k\n'
            'took = k.prepare(lambda text: print(text, file=sys.stderr), processes=2)\n'
            'print(took)\n')
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / 'numba'))
    # The bound only guards against a hang: a cold compile of every kernel takes minutes
    # on a busy 2-core machine (the compile time is measured by scripts/setup, not here).
    first = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                           text=True, timeout=1800)
    assert first.returncode == 0, first.stderr
    assert 'compiling the contact kernels' in first.stderr
    assert 'in 2 processes' in first.stderr and 'failed' not in first.stderr
    assert 'contact kernels compiled in' in first.stderr
    second = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                            text=True, timeout=300)
    assert second.returncode == 0 and second.stderr == ''
    assert float(second.stdout) < float(first.stdout)


def test_the_cache_folder_follows_every_physics_source(tmp_path):
    # numba checks a cached kernel against its own file only; a kernel calling
    # the law in another module must not load stale code when that module changes.
    import shutil
    from collision_node.physics.step import numba_cache as k
    copy = tmp_path / 'physics'
    shutil.copytree(k.PHYSICS_ROOT, copy, ignore=shutil.ignore_patterns('__pycache__'))
    before = k.sources_digest(str(copy))
    assert before == k.sources_digest(k.PHYSICS_ROOT)
    assert os.path.basename(k.CACHE_DIR) == f'numba-{before}'
    law = copy / 'law' / 'primitives.py'
    law.write_text(law.read_text() + '\n# changed\n')
    assert k.sources_digest(str(copy)) != before


def test_every_kernel_module_is_prepared_up_front():
    """Each physics module that compiles kernels has them prepared by ``kernels.prepare``.

    One left out would compile on its first use instead (a first step that
    takes seconds, without the 'compiling' message; the setup script would
    not compile it either). Helpers that only other kernels call are
    compiled with them, so a module counts when any of its kernels is listed.
    """
    import importlib
    import pkgutil

    from collision_node import physics
    from collision_node.physics.step import kernels as k
    from numba.core.registry import CPUDispatcher
    prepared = {kernel.py_func.__module__ for kernel in k.all_kernels()}
    compiled = set()
    for info in pkgutil.walk_packages(physics.__path__, 'collision_node.physics.'):
        module = importlib.import_module(info.name)
        if any(isinstance(value, CPUDispatcher) and value.py_func.__module__ == info.name
               for value in vars(module).values()):
            compiled.add(info.name)
    assert 'collision_node.physics.stages.events.resting_kernels' in compiled
    assert compiled == prepared
