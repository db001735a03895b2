"""colcon builds the package; every executable resolves as ``ros2 run`` resolves it.

``ros2 run PKG EXE`` looks up the package prefix in the ament index
(``ament_index_python.get_package_prefix``, searching AMENT_PREFIX_PATH)
and runs the executable file ``<prefix>/lib/PKG/EXE``. This test builds a
copy of the package in a temporary workspace with colcon, puts the install
prefix on AMENT_PREFIX_PATH as ``source install/setup.bash`` would, resolves
every console script declared in setup.py that way, and runs ``simulate``
on a shipped scene from the installed share/ directory.
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from ament_index_python.packages import get_package_prefix

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = 'collision_node'
NOT_SOURCES = ('.git', '.venv', 'build', 'install', 'log', '__pycache__', '.hypothesis',
               '.pytest_cache', '*.egg-info', 'bench_out')


def declared_console_scripts() -> list[str]:
    """Return the executable names of setup.py's console_scripts, read from its source."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entry_points = ast.literal_eval(node.value)
            return [line.split('=')[0].strip() for line in entry_points['console_scripts']]
    raise AssertionError('setup.py declares no entry_points')


def colcon_build(workspace: Path) -> Path:
    """Build a copy of the package in ``workspace``; return the package's install prefix."""
    shutil.copytree(ROOT, workspace / 'src' / PACKAGE,
                    ignore=shutil.ignore_patterns(*NOT_SOURCES))
    colcon = shutil.which('colcon') or str(Path(sys.executable).with_name('colcon'))
    done = subprocess.run(
        [colcon, '--log-base', str(workspace / 'log'), 'build',
         '--base-paths', str(workspace / 'src'),
         '--build-base', str(workspace / 'build'),
         '--install-base', str(workspace / 'install'),
         '--event-handlers', 'console_direct-', 'console_start_end-'],
        cwd=workspace, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    return workspace / 'install' / PACKAGE


def installed_environment(prefix: Path) -> dict:
    """Return the environment ``source install/setup.bash`` gives, sources out of reach."""
    site = prefix / 'lib' / f'python{sys.version_info[0]}.{sys.version_info[1]}' / 'site-packages'
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        [str(prefix)] + [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
                         if p])
    env['PYTHONPATH'] = str(site)   # the installed package, not the source tree
    return env


def test_colcon_build_then_ros2_run_resolution(tmp_path, monkeypatch):
    prefix = colcon_build(tmp_path / 'ws')
    env = installed_environment(prefix)
    monkeypatch.setenv('AMENT_PREFIX_PATH', env['AMENT_PREFIX_PATH'])
    # ros2 run's lookup: package prefix from the ament index, then lib/<package>/<exe>.
    assert Path(get_package_prefix(PACKAGE)).resolve() == prefix.resolve()
    executables = declared_console_scripts()
    assert 'simulate' in executables
    for name in executables:
        path = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / name
        assert path.is_file(), f'{name}: not installed at {path}'
        assert os.access(path, os.X_OK), f'{name}: {path} is not executable'
        assert path.read_text().startswith('#!'), f'{name}: no interpreter line'

    # The installed package is what runs, and shipped scenes come from share/.
    run_dir = tmp_path / 'elsewhere'
    run_dir.mkdir()
    probe = subprocess.run(
        [sys.executable, '-c', 'import collision_node, collision_node.physics.scene as s; '
         'print(collision_node.__file__); print(s.resolve_scene_path("cradle"))'],
        cwd=run_dir, env=env, capture_output=True, text=True, timeout=60)
    module_file, scene_file = probe.stdout.split()
    assert Path(module_file).is_relative_to(prefix), probe.stdout + probe.stderr
    assert Path(scene_file) == prefix / 'share' / PACKAGE / 'scenes' / 'cradle.yaml'

    simulate = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / 'simulate'
    out = tmp_path / 'cradle.json'
    done = subprocess.run([str(simulate), 'cradle', '--out', str(out)], cwd=run_dir, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith('cradle: 5 particles, 1000 steps')
    velocities = np.array([p['velocity'] for p in json.loads(out.read_text())['particles']])
    np.testing.assert_allclose(velocities[4], [1.0, 0, 0], atol=1e-15)

    # A bad scene through the installed executable: exit 2, one line.
    done = subprocess.run([str(simulate), 'no_such_scene'], cwd=run_dir, env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert 'cradle' in done.stderr   # the shipped scenes it lists come from share/
