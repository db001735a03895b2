"""The node refuses a scene file that is not a scene: exit 2, one line, nothing echoed."""

from __future__ import annotations

import subprocess

import pytest

from node_harness import executable, ros_env, unique_domain_id

SECRET = 'root:$6$saltsalt$0123456789abcdef:19000:0:99999:7:::'


@pytest.mark.parametrize('content, says', [
    ('[' * 5000, 'nested deeper than 32 levels (line 1, column 33)'),
    (SECRET + '\ndaemon:*:19000:0:99999:7:::\n', 'a key that is not a field name'),
    ('root:x:0:0:root:/root:/bin/bash\n', 'expected a mapping, got str'),
    (b'\x7fELF\x02\x01\x01\x00' + SECRET.encode() + b'\xff', 'not UTF-8 text'),
    ('particles: [{position: &p [0, 0, 0], radius: 1, mass: 1}, '
     '{position: *p, radius: 1, mass: 1}]\n', 'YAML aliases (*name) are not accepted'),
], ids=['deep', 'shadow', 'passwd', 'binary', 'alias'])
def test_scene_file_that_is_not_a_scene_stops_the_node_with_one_line(tmp_path, content, says):
    path = tmp_path / 'scene.yaml'
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    result = subprocess.run(
        [executable('collision_node'), '--ros-args', '-p', f'scene:={path}'],
        env=ros_env(unique_domain_id()), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert 'Traceback' not in result.stderr and len(result.stderr) < 1000
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and '[ERROR]' in lines[0], lines
    assert f'[collision_node]: {path}: ' in lines[0]
    reason = lines[0].split(f'{path}: ', 1)[1]
    assert says in reason
    for word in ('root', 'salt', '0123', 'daemon', 'ELF', '[['):
        assert word not in reason, reason
