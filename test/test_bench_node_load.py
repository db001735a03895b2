"""The node-load benchmark's inputs (the benchmark itself is run, not tested)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from rclpy.serialization import deserialize_message
from std_msgs.msg import String

from collision_node import bench
from collision_node.bench import node_load
from collision_node.physics import parse_scene_text
from collision_node.physics.model.scene import parse_spawn
from collision_node.physics.model.validation import SceneError

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros


def test_registered_as_a_subcommand():
    assert bench.SUBCOMMANDS['node-load'] == 'collision_node.bench.node_load'


def test_flood_spawns_fit_the_box_without_overlap():
    positions = node_load.lattice_positions(10_001)
    gaps = np.diff(np.unique(positions[:, 0]))
    assert np.allclose(gaps, node_load.LATTICE) and len(np.unique(positions, axis=0)) == 10_001
    assert node_load.LATTICE >= 4 * node_load.SPAWN_RADIUS
    side = node_load.box_side(node_load.box_scene_text(10_001))
    assert positions.max() + node_load.SPAWN_RADIUS < side
    request = json.loads(node_load.spawn_text(positions[5], 'f5'))
    assert request['request_id'] == 'f5' and request['radius'] == node_load.SPAWN_RADIUS
    assert 'request_id' not in json.loads(node_load.spawn_text(positions[5], None))


def test_scenes_load():
    assert len(parse_scene_text(node_load.box_scene_text(100), 'box').initial) == 0
    gas = parse_scene_text(node_load.gas_scene_text(2000), 'gas')
    assert len(gas.initial) == 2000


def test_stall_request_is_rejected_at_its_last_entry():
    with pytest.raises(SceneError, match=r'particles\[499\]\.radius'):
        parse_spawn(node_load.stall_request(500), 3, 0)


def test_alias_bomb_is_a_billion_laughs():
    data = yaml.safe_load(node_load.alias_bomb('position'))
    inner = data['position']
    for _ in range(8):
        assert len(inner) == 9 and inner[0] is inner[8]      # shared, not copied
        inner = inner[0]
    assert inner == ['lol'] * 9


def test_every_garbage_kind_makes_a_message():
    import random
    rng = random.Random(1)
    kinds = node_load.garbage_kinds()
    assert len({name for name, _ in kinds}) == len(kinds) == 10
    for name, make in kinds:
        message = make(0, rng)
        if isinstance(message, bytes):
            # A well-formed String message whose data is not UTF-8 (rclpy replaces it).
            length = int.from_bytes(message[4:8], 'little')
            with pytest.raises(UnicodeDecodeError):
                message[8:8 + length - 1].decode('utf-8')
            assert '\ufffd' in deserialize_message(message, String).data
        else:
            assert isinstance(message, str)


def test_without_and_floor_are_checked_before_anything_starts(capsys):
    everything = ['--parts', 'b', '--without', ' ']     # every kind's name has a space
    assert all(' ' in name for name, _ in node_load.garbage_kinds())
    assert node_load.main(everything) == 2
    assert '--without leaves no garbage kind' in capsys.readouterr().err
    assert node_load.main(['--parts', 'ab', '--floor']) == 2
    assert '--floor runs part b only' in capsys.readouterr().err


def test_the_stepped_world_is_the_issues_gas():
    scene = parse_scene_text(node_load.table_gas_text(2000), 'gas')
    assert len(scene.initial) == 2000 and scene.dimensions == 2
    assert set(scene.initial.radius.tolist()) == {0.0008}
    assert scene.effects.walls is not None


def test_latency_summary_and_parts_are_checked(capsys):
    assert node_load.milliseconds([0.001, 0.002, 0.003]) == '2.0 / 2.8 / 3.0 ms'
    assert node_load.milliseconds([]) == '-'
    assert node_load.main(['--parts', 'eg']) == 2
    assert "--parts takes letters of abcdef, got 'eg'" in capsys.readouterr().err
    assert node_load.main(['--parts', 'e', '--burst', '0']) == 2
    assert '--burst must be >= 1' in capsys.readouterr().err
