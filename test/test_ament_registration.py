"""``ros2 run`` resolution of the editable install that scripts/setup registers.

``ros2 run PKG EXE`` (ros2run) asks the ament index for the package prefix
(``ament_index_python.get_package_prefix``, searching AMENT_PREFIX_PATH) and
executes ``<prefix>/lib/PKG/EXE``; ``ros2 pkg`` reads the share directory.
scripts/setup registers the checkout in the venv prefix with
scripts/register_ament.py; these tests run that script against a temporary
prefix, resolve every executable as ros2run does and run it, and check the
venv prefix itself (which scripts/setup registered before the tests run).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from ament_index_python.packages import (get_package_prefix, get_package_share_directory,
                                         PackageNotFoundError)
from std_msgs.msg import String

from node_harness import Probe, start, stop, STATUS_QOS, unique_domain_id

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = 'collision_node'
EXECUTABLES = ('collision_node', 'simulate', 'viewer')


def load_register_ament():
    """Import scripts/register_ament.py (a build-time script, not part of the package)."""
    spec = importlib.util.spec_from_file_location('register_ament',
                                                  ROOT / 'scripts' / 'register_ament.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


register_ament = load_register_ament()


def resolve(name: str) -> Path:
    """Return the executable ``ros2 run collision_node NAME`` would execute."""
    path = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / name
    assert path.is_file() and os.access(path, os.X_OK), f'{name}: no executable at {path}'
    return path


@pytest.fixture
def prefix(tmp_path, monkeypatch):
    """Return a temporary ament prefix holding the registered checkout, searched first."""
    prefix = tmp_path / 'prefix'
    prefix.mkdir()
    register_ament.register(prefix, ROOT, sys.executable)
    monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join(
        [str(prefix), os.environ.get('AMENT_PREFIX_PATH', sys.prefix)]))
    return prefix


def test_console_scripts_are_read_from_setup_py():
    assert register_ament.console_scripts(ROOT / 'setup.py') == {
        'collision_node': 'collision_node.ros.node:main',
        'viewer': 'collision_node.ros.viewer:main',
        'simulate': 'collision_node.simulate:main'}


def test_registration_is_what_ros2_run_and_ros2_pkg_look_up(prefix):
    assert Path(get_package_prefix(PACKAGE)) == prefix
    share = Path(get_package_share_directory(PACKAGE))
    assert share == prefix / 'share' / PACKAGE
    assert '<name>collision_node</name>' in (share / 'package.xml').read_text()
    assert (share / 'scenes' / 'oblique_pair.yaml').read_text() == \
        (ROOT / 'scenes' / 'oblique_pair.yaml').read_text()
    assert (share / 'config' / 'collision_node.yaml').read_text() == \
        (ROOT / 'config' / 'collision_node.yaml').read_text()
    for name in EXECUTABLES:
        text = resolve(name).read_text()
        assert text.startswith(f'#!{sys.executable}\n'), text


def test_executables_run_the_checkouts_code(prefix):
    simulate = resolve('simulate')
    # The launcher's interpreter, in this environment, imports the checkout under test.
    interpreter = simulate.read_text().splitlines()[0][2:]
    done = subprocess.run([interpreter, '-c', 'import collision_node; '
                           'print(collision_node.__file__)'],
                          cwd=prefix, capture_output=True, text=True, timeout=60)
    assert Path(done.stdout.strip()) == ROOT / 'collision_node' / '__init__.py', done.stderr
    done = subprocess.run([str(simulate), 'oblique_pair', '--steps', '5',
                           '--out', str(prefix / 'out.json')],
                          cwd=prefix, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith('oblique_pair: 2 particles, 5 steps'), done.stdout
    assert json.loads((prefix / 'out.json').read_text())['steps'] == 5


def test_resolved_node_executable_starts_and_reports_status(prefix):
    domain = unique_domain_id()
    node = start(str(resolve('collision_node')),
                 ['--ros-args', '-p', 'scene:=oblique_pair'], domain)
    probe = Probe(domain)
    try:
        statuses = probe.collect(String, 'status', STATUS_QOS)
        probe.wait_for(lambda: statuses or node.poll() is not None, 30.0)
        assert node.poll() is None, 'collision_node exited at start'
        status = json.loads(statuses[-1].data)
        assert (status['scene'], status['particles']) == ('oblique_pair', 2)
    finally:
        probe.close()
        code, _, err = stop(node)
    assert code == 0, err


def test_viewer_executable_answers_help(prefix):
    done = subprocess.run([str(resolve('viewer')), '--help'], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0 and done.stdout.startswith('usage: viewer'), done.stderr


def test_registration_is_idempotent_and_drops_only_its_own_stale_launchers(prefix):
    lib = prefix / 'lib' / PACKAGE
    before = {p.name: p.read_bytes() for p in lib.iterdir()}
    (lib / 'retired').write_text(register_ament.launcher(sys.executable, 'x.y:main'))
    (lib / 'someone_elses').write_text('#!/bin/sh\necho hi\n')
    (lib / 'viewer').unlink()
    (lib / 'viewer').write_text('#!/bin/sh\n# a copy a colcon build left here\n')
    register_ament.register(prefix, ROOT, sys.executable)
    register_ament.register(prefix, ROOT, sys.executable)
    after = {p.name: p.read_bytes() for p in lib.iterdir()}
    assert after == {**before, 'someone_elses': b'#!/bin/sh\necho hi\n'}
    assert (prefix / 'share' / PACKAGE / 'scenes').resolve() == ROOT / 'scenes'


def test_a_copied_share_tree_is_replaced_by_the_checkouts(prefix):
    scenes = prefix / 'share' / PACKAGE / 'scenes'
    scenes.unlink()
    scenes.mkdir()
    (scenes / 'old.yaml').write_text('particles: []\n')
    register_ament.register(prefix, ROOT, sys.executable)
    assert scenes.is_symlink() and not (scenes / 'old.yaml').exists()


def test_command_line_refuses_a_missing_prefix(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop_:
        register_ament.main([str(tmp_path / 'absent')])
    assert stop_.value.code == 2
    assert 'is not a directory' in capsys.readouterr().err


def test_the_venv_prefix_is_registered(monkeypatch):
    # scripts/setup registers the venv it creates; scripts/env.sh makes it the ament prefix.
    monkeypatch.setenv('AMENT_PREFIX_PATH', sys.prefix)
    try:
        found = Path(get_package_prefix(PACKAGE))
    except PackageNotFoundError:
        raise AssertionError(f'{PACKAGE} is not registered in {sys.prefix}: run scripts/setup')
    assert found == Path(sys.prefix)
    assert (Path(get_package_share_directory(PACKAGE)) / 'package.xml').is_file()
    for name in EXECUTABLES:
        resolve(name)
