"""The manual's colcon recipe builds the package; every executable resolves as ``ros2 run`` does.

``ros2 run PKG EXE`` looks up the package prefix in the ament index
(``ament_index_python.get_package_prefix``, searching AMENT_PREFIX_PATH)
and runs the executable file ``<prefix>/lib/PKG/EXE``. This test runs the
recipe of docs/install.md for the venv's colcon exactly as written (the repository
cloned into ``~/ws/src/``, ``colcon build``, ``. install/setup.sh``) with
HOME in a temporary directory, takes the environment the setup script
leaves, resolves every console script declared in setup.py that way and
runs ``simulate`` on a shipped scene from the installed share/ directory.
The clone holds the committed tree (CI runs in a fresh clone).
"""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ament_index_python.packages import get_package_prefix, get_package_share_directory

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = 'collision_node'
RECIPE_LEAD = 'runs exactly this block'
INSTALL_PAGE = 'docs/install.md'
ENV_MARK = '--- environment after the recipe ---\n'


def declared_console_scripts() -> list[str]:
    """Return the executable names of setup.py's console_scripts, read from its source."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entry_points = ast.literal_eval(node.value)
            return [line.split('=')[0].strip() for line in entry_points['console_scripts']]
    raise AssertionError('setup.py declares no entry_points')


def install_recipe() -> str:
    """Return the manual's colcon recipe for the venv (the bash block after RECIPE_LEAD)."""
    page = (ROOT / INSTALL_PAGE).read_text()
    found = re.search(re.escape(RECIPE_LEAD) + r'.*?```bash\n(.*?)```', page, re.DOTALL)
    assert found, f'{INSTALL_PAGE}: no bash block after "{RECIPE_LEAD}"'
    return found.group(1)


def run_recipe(home: Path) -> dict:
    """Run the recipe from the checkout with HOME = ``home``; return the environment it leaves."""
    script = 'set -eo pipefail\n' + install_recipe() + f"printf '\\n{ENV_MARK}'; env -0\n"
    env = {**os.environ, 'HOME': str(home)}
    done = subprocess.run(['bash', '-c', script], cwd=ROOT, env=env, capture_output=True,
                          timeout=300)
    assert done.returncode == 0, (done.stdout + done.stderr).decode(errors='replace')[-4000:]
    listing = done.stdout.decode().rsplit(ENV_MARK, 1)[1]
    return dict(item.split('=', 1) for item in listing.split('\0') if '=' in item)


def test_recipe_is_the_repository_in_src_and_builds_without_selection_or_bash():
    recipe = install_recipe()
    assert 'git clone "$PWD" ~/ws/src/collision_node' in recipe
    assert 'colcon build\n' in recipe and '. install/setup.sh' in recipe


def test_colcon_build_then_ros2_run_resolution(tmp_path, monkeypatch):
    env = run_recipe(tmp_path)
    prefix = tmp_path / 'ws' / 'install' / PACKAGE
    # install/setup.sh put the built prefix first on the ament path and its site-packages
    # on PYTHONPATH, ahead of the checkout.
    assert env['AMENT_PREFIX_PATH'].split(os.pathsep)[0] == str(prefix)
    site = prefix / 'lib' / f'python{sys.version_info[0]}.{sys.version_info[1]}' / 'site-packages'
    assert env['PYTHONPATH'].split(os.pathsep)[0] == str(site)
    monkeypatch.setenv('AMENT_PREFIX_PATH', env['AMENT_PREFIX_PATH'])
    # ros2 run's lookup: package prefix from the ament index, then lib/<package>/<exe>.
    assert Path(get_package_prefix(PACKAGE)).resolve() == prefix.resolve()
    share = Path(get_package_share_directory(PACKAGE))
    assert '<name>collision_node</name>' in (share / 'package.xml').read_text()
    # The parameters file is installed where --params-file $(ros2 pkg prefix ...) finds it.
    assert (share / 'config' / 'collision_node.yaml').read_text() == \
        (ROOT / 'config' / 'collision_node.yaml').read_text()
    executables = declared_console_scripts()
    assert sorted(executables) == ['collision_node', 'simulate', 'viewer']
    for name in executables:
        path = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / name
        assert path.is_file(), f'{name}: not installed at {path}'
        assert os.access(path, os.X_OK), f'{name}: {path} is not executable'
        assert path.read_text().startswith('#!'), f'{name}: no interpreter line'
    viewer = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / 'viewer'
    done = subprocess.run([str(viewer), '--help'], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.startswith('usage: viewer'), done.stderr

    # The installed package is what runs, and shipped scenes come from share/.
    run_dir = tmp_path / 'elsewhere'
    run_dir.mkdir()
    probe = subprocess.run(
        [sys.executable, '-c', 'import collision_node, collision_node.physics.model.scene as s; '
         'print(collision_node.__file__); print(s.resolve_scene_path("cradle"))'],
        cwd=run_dir, env=env, capture_output=True, text=True, timeout=60)
    module_file, scene_file = probe.stdout.split()
    assert Path(module_file).is_relative_to(prefix), probe.stdout + probe.stderr
    assert Path(scene_file) == prefix / 'share' / PACKAGE / 'scenes' / 'cradle.yaml'

    simulate = Path(get_package_prefix(PACKAGE)) / 'lib' / PACKAGE / 'simulate'
    out = tmp_path / 'cradle.json'
    # The installed copy is a new source path, so its first run compiles the numba
    # kernels (about a minute alone, several on a loaded 2-core machine) and says so.
    done = subprocess.run([str(simulate), 'cradle', '--out', str(out)], cwd=run_dir, env=env,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    assert 'compiling the contact kernels' in done.stderr
    assert done.stdout.startswith('cradle: 5 particles, 1000 steps')
    velocities = np.array([p['velocity'] for p in json.loads(out.read_text())['particles']])
    np.testing.assert_allclose(velocities[4], [1.0, 0, 0], atol=1e-15)

    # A bad scene through the installed executable: exit 2, one line.
    done = subprocess.run([str(simulate), 'no_such_scene'], cwd=run_dir, env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert 'cradle' in done.stderr   # the shipped scenes it lists come from share/
