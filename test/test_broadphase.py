"""The broadphase never misses a contact: its Verlet list against brute force."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from collision_node import World, parse_scene
from collision_node.physics.stages.detection import grid_kernels
from collision_node.physics.step.pipeline import Stage, StepContext
from collision_node.physics.stages.detection import broadphase as broadphase_module
from collision_node.physics.stages.detection.broadphase import BroadphaseStage, candidate_pairs


def brute_force_overlaps(position: np.ndarray, radius: np.ndarray) -> set:
    """Return every pair (i < j) with |p_i - p_j| < r_i + r_j, by checking all of them."""
    i, j = np.triu_indices(position.shape[0], k=1)
    distance = np.linalg.norm(position[i] - position[j], axis=1)
    hit = distance < radius[i] + radius[j]
    return set(zip(i[hit].tolist(), j[hit].tolist()))


class CheckCandidates(Stage):
    """Assert, right after the broadphase, that its pairs hold every overlap."""

    name = 'check_candidates'

    def __init__(self) -> None:
        """Count the overlaps seen, so the test knows it checked something."""
        self.overlaps_seen = 0

    def run(self, ctx: StepContext) -> None:
        """Compare the candidate pairs with brute force."""
        i, j = ctx.pair_i, ctx.pair_j
        assert np.all(i < j)
        keys = i * len(ctx.state) + j
        assert np.all(np.diff(keys) > 0), 'pairs must be sorted by (i, j), without repeats'
        overlaps = brute_force_overlaps(ctx.state.position, ctx.state.radius)
        missing = overlaps - set(zip(i.tolist(), j.tolist()))
        assert not missing, f'broadphase missed {sorted(missing)[:5]}'
        self.overlaps_seen += len(overlaps)


@pytest.mark.parametrize('seed, all_pairs_up_to', [(1, 48), (2, 0)])
def test_verlet_list_with_fast_movers_misses_no_contact(monkeypatch, seed, all_pairs_up_to):
    # all_pairs_up_to = 0 makes movers meet each other through a search, not all pairs.
    monkeypatch.setattr(broadphase_module, 'ALL_PAIRS_UP_TO', all_pairs_up_to)
    rng = np.random.default_rng(seed)
    count = 300
    # A crowded box; a few particles 20x faster than the rest (movers), a few
    # large ones (queried on their own) and a few static ones.
    speeds = np.where(rng.random(count) < 0.01, 20.0, 1.0)
    direction = rng.normal(size=(count, 3))
    velocity = direction / np.linalg.norm(direction, axis=1)[:, None] * speeds[:, None]
    radius = np.where(rng.random(count) < 0.01, 0.4, rng.uniform(0.04, 0.06, count))
    static = rng.random(count) < 0.02
    velocity[static] = 0.0
    particles = [{'position': rng.uniform(-1.5, 1.5, 3).tolist(),
                  'velocity': velocity[k].tolist(), 'radius': float(radius[k]),
                  'mass': float('inf') if static[k] else 1.0} for k in range(count)]
    # Preset fast: the discrete pipeline, whose broadphase keeps the Verlet list.
    world = World(parse_scene({'dt': 0.005, 'particles': particles, 'accuracy': 'fast',
                               'effects': {'walls': {'min': [-2, -2, -2], 'max': [2, 2, 2]}}},
                              'verlet'))
    at = [isinstance(stage, BroadphaseStage) for stage in world.pipeline.stages].index(True)
    broadphase = world.pipeline.stages[at]
    check = CheckCandidates()
    world.pipeline.stages.insert(at + 1, check)
    energy = world.kinetic_energy()
    world.step(150)
    # Every path of the stage ran: full searches, list reuse and mover patches.
    assert 1 < broadphase.searches < 150 and broadphase.mover_updates > 0
    assert check.overlaps_seen > 100
    assert world.kinetic_energy() == pytest.approx(energy, rel=1e-12)


def test_spawn_invalidates_the_list(world_from):
    world = world_from(generate=[{'kind': 'gas', 'count': 100, 'radius': 0.05, 'mass': 1,
                                  'speed': 0.1, 'seed': 4,
                                  'region': {'min': [0, 0, 0], 'max': [2, 2, 2]}}])
    check = CheckCandidates()
    world.pipeline.stages.insert(2, check)
    world.step(3)
    # A particle spawned on top of particle 0 must be a candidate at once.
    p0 = world.state.position[0].tolist()
    world.spawn_text(f'{{position: {p0}, radius: 0.05, mass: 1}}')
    world.step(1)
    assert check.overlaps_seen >= 1


def test_candidate_pairs_with_large_particles_match_brute_force():
    rng = np.random.default_rng(5)
    position = rng.uniform(-1, 1, (400, 3))
    radius = rng.uniform(0.01, 0.03, 400)
    radius[:4] = [0.5, 0.3, 1e-3, 0.8]
    i, j = candidate_pairs(position, radius)
    assert brute_force_overlaps(position, radius) <= set(zip(i.tolist(), j.tolist()))
    assert np.all(i < j) and np.all(np.diff(i * 400 + j) > 0)


def near_pairs(position: np.ndarray, reach: np.ndarray) -> set:
    """Return every pair (i < j) with |p_i - p_j| <= reach_i + reach_j, by brute force."""
    i, j = np.triu_indices(position.shape[0], k=1)
    distance = np.linalg.norm(position[i] - position[j], axis=1)
    hit = distance <= reach[i] + reach[j]
    return set(zip(i[hit].tolist(), j[hit].tolist()))


def mixed_sizes(rng, count: int, dimensions: int, large_share: float, factor: float,
                fraction: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Return positions and radii: ``large_share`` of them ``factor`` times larger.

    The box is sized for the given volume (area) fraction, so that many
    pairs touch and the brute-force comparison checks something.
    """
    radius = rng.uniform(0.9, 1.1, count) * 0.05
    radius[rng.random(count) < large_share] *= factor
    unit = np.pi if dimensions == 2 else 4.0 / 3.0 * np.pi
    side = (float(np.sum(unit * radius ** dimensions)) / fraction) ** (1.0 / dimensions)
    return rng.uniform(0.0, side, (count, dimensions)), radius


@pytest.mark.parametrize('dimensions', [2, 3])
@pytest.mark.parametrize('large_share, factor', [(0.1, 5.0), (0.1, 10.0), (0.2, 10.0),
                                                 (0.45, 5.0), (0.45, 10.0)])
def test_candidate_pairs_of_mixed_sizes_equal_brute_force(dimensions, large_share, factor):
    rng = np.random.default_rng(int(100 * large_share + factor + 7 * dimensions))
    position, radius = mixed_sizes(rng, 700, dimensions, large_share, factor, fraction=0.3)
    # A margin on top of the radius, as the Verlet list and the swept contacts add.
    reach = radius * rng.uniform(1.0, 1.2, radius.size)
    i, j = candidate_pairs(position, reach)
    expected = near_pairs(position, reach)
    assert len(expected) > 200
    assert set(zip(i.tolist(), j.tolist())) == expected
    assert np.all(i < j) and np.all(np.diff(i * radius.size + j) > 0)


def test_size_classes_keep_reaches_within_a_factor_of_two():
    rng = np.random.default_rng(3)
    reach = np.exp(rng.uniform(np.log(1e-3), np.log(2.0), 1000))
    reach[:3] = [0.0, 1e-3, 2.0]
    classes = broadphase_module.size_classes(reach)
    assert np.array_equal(np.sort(np.concatenate(classes)), np.arange(1000))
    assert len(classes) == 11      # log2(2 / 1e-3) = 10.97: levels 0 to 10
    for members in classes:
        assert np.all(np.diff(members) > 0)
        positive = reach[members][reach[members] > 0]
        assert positive.max() < 2.0 * positive.min()
    # One size (a gas) is one class: a single tree, as before size classes.
    assert len(broadphase_module.size_classes(np.full(50, 0.05))) == 1


def test_mixed_sizes_stay_near_linear_in_pair_count():
    """45 % of the particles at 5x the radius: candidates stay a few per real contact.

    Pairing the large particles all-to-all (as the broadphase did) gave
    6.5 million candidates for 8,000 such particles; the Verlet list with
    its skin must stay within a small factor of the real contacts.
    """
    rng = np.random.default_rng(11)
    count = 4000
    position, radius = mixed_sizes(rng, count, 3, 0.45, 5.0)
    contacts = near_pairs(position, radius)
    i, j = candidate_pairs(position, radius)
    assert set(zip(i.tolist(), j.tolist())) == contacts and len(contacts) > 500
    stage = BroadphaseStage()
    velocity = rng.normal(size=(count, 3))
    i, j = stage.find(position, radius, velocity, np.ones(count), 0.01)
    assert stage.searches == 1
    assert contacts <= set(zip(i.tolist(), j.tolist()))
    assert i.size < 3 * len(contacts)
    # All-to-all pairing of the large ones alone would give ~ (0.45 n)^2 / 2 pairs.
    assert i.size < 0.01 * (0.45 * count) ** 2 / 2


def test_verlet_list_with_mixed_sizes_misses_no_contact():
    rng = np.random.default_rng(8)
    count = 400
    radius = np.where(rng.random(count) < 0.2, 0.3, 0.03)
    speeds = np.where(rng.random(count) < 0.01, 15.0, 1.0)
    direction = rng.normal(size=(count, 3))
    velocity = direction / np.linalg.norm(direction, axis=1)[:, None] * speeds[:, None]
    particles = [{'position': rng.uniform(-2.5, 2.5, 3).tolist(),
                  'velocity': velocity[k].tolist(), 'radius': float(radius[k]), 'mass': 1.0}
                 for k in range(count)]
    world = World(parse_scene({'dt': 0.005, 'particles': particles, 'accuracy': 'fast',
                               'effects': {'walls': {'min': [-3, -3, -3], 'max': [3, 3, 3]}}},
                              'mixed'))
    at = [isinstance(stage, BroadphaseStage) for stage in world.pipeline.stages].index(True)
    broadphase = world.pipeline.stages[at]
    check = CheckCandidates()
    world.pipeline.stages.insert(at + 1, check)
    energy = world.kinetic_energy()
    world.step(100)
    assert 1 < broadphase.searches < 100 and broadphase.mover_updates > 0
    assert check.overlaps_seen > 100
    assert world.kinetic_energy() == pytest.approx(energy, rel=1e-12)


def scattered_set(rng, count: int, dimensions: int, scale: float, offset: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Return a mixed-size set (radii spread over three decades) at ``scale``, ``offset`` away.

    Positions are those of a dense box at ``scale`` shifted by ``offset``;
    a few huge particles (100x) and a few tiny ones (1/100x) join them.
    """
    position, radius = mixed_sizes(rng, count, dimensions, 0.15, 10.0, fraction=0.3)
    radius = radius.copy()
    radius[:4] *= 100.0
    radius[4:12] /= 100.0
    return offset + scale * position, scale * radius


@pytest.mark.parametrize('dimensions', [2, 3])
@pytest.mark.parametrize('scale, offset', [(1.0, 0.0), (1e-6, 0.0), (1.0, 1e9), (1e-6, 1.0),
                                           (1e3, -1e9)])
def test_grid_pairs_equal_brute_force_at_any_scale(dimensions, scale, offset):
    rng = np.random.default_rng(int(dimensions + 10 * np.log10(scale + 1) + 7))
    position, radius = scattered_set(rng, 600, dimensions, scale, offset)
    reach = radius * rng.uniform(1.0, 1.3, radius.size)
    i, j = candidate_pairs(position, reach)
    expected = near_pairs(position, reach)
    assert len(expected) > 300
    assert set(zip(i.tolist(), j.tolist())) == expected
    assert np.all(i < j) and np.all(np.diff(i * radius.size + j) > 0)


def test_grid_pairs_of_far_apart_clusters_equal_brute_force():
    # A cluster at the origin and one 1e9 m away, a particle of zero reach, two
    # coincident ones: the grid hashes its cells instead of spanning the gap.
    rng = np.random.default_rng(12)
    near, _ = mixed_sizes(rng, 300, 3, 0.1, 10.0, fraction=0.3)
    far = near[:200] + 1e9
    position = np.vstack([near, far, near[:1]])
    reach = np.concatenate([rng.uniform(0.04, 0.06, 300), rng.uniform(0.04, 0.06, 200),
                            [0.05]])
    reach[7] = 0.0
    i, j = candidate_pairs(position, reach)
    expected = near_pairs(position, reach)
    assert (0, 500) in expected and any(a >= 300 for a, _ in expected)
    assert set(zip(i.tolist(), j.tolist())) == expected
    assert np.all(np.diff(i * position.shape[0] + j) > 0)


def test_grid_handles_degenerate_sets():
    # Every particle at one point with zero reach: all pairs touch (distance 0).
    i, j = candidate_pairs(np.zeros((60, 3)), np.zeros(60))
    assert i.size == 60 * 59 // 2
    # Two particles: one pair or none.
    i, j = candidate_pairs(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), np.array([0.5, 0.5]))
    assert (i.tolist(), j.tolist()) == ([0], [1])
    i, j = candidate_pairs(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), np.array([0.4, 0.5]))
    assert i.size == 0


def test_mover_queries_equal_a_fresh_search():
    # The Verlet list patched with mover pairs holds every pair a fresh search finds
    # (and no pair beyond the listed ones and the movers' reach).
    rng = np.random.default_rng(21)
    count = 2000
    position, radius = mixed_sizes(rng, count, 3, 0.15, 10.0, fraction=0.2)
    velocity = rng.normal(size=(count, 3))
    stage = BroadphaseStage()
    stage.find(position, radius, velocity, np.ones(count), 0.01)
    moved = position.copy()
    movers = rng.choice(count, 30, replace=False)
    moved[movers] += rng.normal(scale=0.3, size=(30, 3))
    i, j = stage.find(moved, radius, velocity, np.ones(count), 0.01)
    assert stage.searches == 1 and stage.mover_updates == 1
    found = set(zip(i.tolist(), j.tolist()))
    assert near_pairs(moved, radius) <= found
    assert np.all(np.diff(i * count + j) > 0)


@pytest.mark.parametrize('dimensions', [2, 3])
@pytest.mark.parametrize('scale, offset', [(1.0, 0.0), (1e-6, 1.0), (1e3, -1e9)])
def test_one_size_gas_takes_the_neighbour_row_scan_and_equals_brute_force(
        dimensions, scale, offset):
    # One size class in a dense table (a gas): grid_pairs scans the five later
    # rows of neighbour cells. A lattice at spacing exactly reach_i + reach_j
    # (pairs on the limit, cells at the lattice's corners) and a random gas
    # with reaches varying by 30 % must give brute force's set, sorted.
    rng = np.random.default_rng(int(dimensions + 3 * np.log10(scale) + 50))
    side = 14 if dimensions == 3 else 40
    axes = np.meshgrid(*[np.arange(side, dtype=float)] * dimensions, indexing='ij')
    lattice = np.stack([a.ravel() for a in axes], axis=1)
    gas = rng.uniform(0.0, side, (lattice.shape[0], dimensions))
    for position, reach in ((offset + scale * lattice, np.full(lattice.shape[0], 0.5 * scale)),
                            (offset + scale * gas,
                             scale * rng.uniform(0.35, 0.45, lattice.shape[0]))):
        grid = grid_kernels.make_grid(position, reach, broadphase_module.size_classes(reach))
        assert grid.class_start.size == 2 and grid.dense[0]
        i, j = candidate_pairs(position, reach)
        # The exact test with its slack (pairs on the limit are kept).
        a, b = np.triu_indices(reach.size, k=1)
        offset_ab = position[a] - position[b]
        limit = reach[a] + reach[b]
        hit = np.einsum('ij,ij->i', offset_ab, offset_ab) <= limit * limit * (
            1.0 + broadphase_module.QUERY_SLACK)
        expected = set(zip(a[hit].tolist(), b[hit].tolist()))
        assert len(expected) > position.shape[0] // 2
        assert set(zip(i.tolist(), j.tolist())) == expected
        assert np.all(i < j) and np.all(np.diff(i * reach.size + j) > 0)


def _found_fields(found: grid_kernels.Found) -> tuple:
    """Return a ``Found`` as plain values, for comparing two searches."""
    return (found.pairs.first.tolist(), found.pairs.second.tolist(), found.complete,
            found.needed, found.estimated, found.tested)


@pytest.mark.parametrize('threads', [1, 2])
def test_shared_search_is_the_serial_one_on_a_gas_mixed_sizes_and_over_the_limit(threads):
    # grid_pairs_shared writes a dense gas's pairs block by block on the threads
    # and sorts them: the same Found as grid_pairs, for any thread count. A
    # mixed-size grid and a search over its pair limit (it gives up with the
    # same estimate) go to grid_pairs itself.
    rng = np.random.default_rng(19)
    count = 3 * 4096 + 77                       # several blocks, the last one short
    side = 31.0
    gas = rng.uniform(0.0, side, (count, 3))
    gas_reach = rng.uniform(0.4, 0.5, count)
    mixed_reach = gas_reach.copy()
    mixed_reach[::50] = 3.0
    limit = broadphase_module._limit()
    still = broadphase_module._still()
    previous = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        for reach, search_limit in ((gas_reach, limit), (mixed_reach, limit),
                                    (gas_reach, grid_kernels.SearchLimit(1000, 10 ** 9))):
            grid = grid_kernels.make_grid(gas, reach, broadphase_module.size_classes(reach))
            serial = grid_kernels.grid_pairs(reach, grid, search_limit, still)
            shared = grid_kernels.grid_pairs_shared(reach, grid, search_limit)
            assert _found_fields(shared) == _found_fields(serial)
        assert not shared.complete and shared.needed > 1000   # the last search gave up
        dense = grid_kernels.make_grid(gas, gas_reach, broadphase_module.size_classes(gas_reach))
        assert grid_kernels._one_dense_class(dense)
        found = grid_kernels.grid_pairs_shared(gas_reach, dense, limit)
        assert found.complete and found.pairs.first.size > count // 2
        i, j = found.pairs
        assert np.all(i < j) and np.all(np.diff(i * count + j) > 0)
        # Candidates past the limit's rows (its pairs plus one per item): the
        # blocks run in waves, and the pairs are still the serial search's.
        tight = grid_kernels.SearchLimit(found.pairs.first.size, 10 ** 9)
        assert grid_kernels._dense_candidates(dense, count) > 2 * (tight.max_pairs + count)
        waves = grid_kernels.grid_pairs_shared(gas_reach, dense, tight)
        assert _found_fields(waves) == _found_fields(found)
        over = grid_kernels.SearchLimit(found.pairs.first.size - 1, 10 ** 9)
        assert _found_fields(grid_kernels.grid_pairs_shared(gas_reach, dense, over)) == \
            _found_fields(grid_kernels.grid_pairs(gas_reach, dense, over, still))
    finally:
        numba.set_num_threads(previous)


@pytest.mark.parametrize('threads', [1, 2])
def test_shared_grid_and_movers_are_the_serial_ones(threads):
    # build_grid's shared loops (extents, cells, buckets, placing, in blocks)
    # and movers_shared give the serial grid and mover list to the last entry,
    # for a dense gas and for mixed sizes (hashed classes), at any thread count.
    rng = np.random.default_rng(23)
    count = 3 * 4096 + 77
    gas = rng.uniform(-7.0, 24.0, (count, 3))
    gas_reach = rng.uniform(0.4, 0.5, count)
    mixed_reach = gas_reach.copy()
    mixed_reach[::50] = 3.0
    mixed_reach[::97] = 0.05
    previous = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        for reach in (gas_reach, mixed_reach):
            classes = broadphase_module.size_classes(reach)
            serial = grid_kernels.make_grid(gas, reach, classes)
            shared = grid_kernels.make_grid(gas, reach, classes, True)
            for name, value in serial._asdict().items():
                np.testing.assert_array_equal(getattr(shared, name), value, err_msg=name)
        assert len(broadphase_module.size_classes(mixed_reach)) == 3
        built = gas + rng.normal(0.0, 0.05, gas.shape)
        extra = rng.uniform(0.0, 0.02, count)
        serial_movers = grid_kernels.movers(gas, built, extra, 0.1)
        assert 0 < serial_movers.size < count
        np.testing.assert_array_equal(grid_kernels.movers_shared(gas, built, extra, 0.1),
                                      serial_movers)
    finally:
        numba.set_num_threads(previous)
