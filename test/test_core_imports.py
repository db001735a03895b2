"""The core imports no ROS module (only node.py, viewer.py and bench_node.py may)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ROS_MODULES_ALLOWED_IN = {'collision_node.node', 'collision_node.viewer',
                          'collision_node.bench_node'}

PROBE = r'''
import importlib, json, pkgutil, sys
import collision_node
allowed = set(sys.argv[1].split(','))
names = sorted(m.name for m in pkgutil.walk_packages(collision_node.__path__, 'collision_node.'))
core = [n for n in names if n not in allowed]
for name in core:
    importlib.import_module(name)
from collision_node.simulate import main
main(['oblique_pair', '--quiet', '--steps', '5'])

def is_ros(module):
    top = module.split('.')[0]
    return (top in ('rclpy', 'ament_index_python') or top.startswith(('rcl', 'rosidl'))
            or top.endswith('_msgs') or top.endswith('_srvs'))

print(json.dumps({'core': core, 'ros': sorted(m for m in sys.modules if is_ros(m))}))
'''


def test_core_and_its_runner_import_no_ros_module():
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    done = subprocess.run([sys.executable, '-c', PROBE, ','.join(sorted(ROS_MODULES_ALLOWED_IN))],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.splitlines()[-1])
    # The probe really walked the core: the stages and the runner are in it.
    assert {'collision_node.scene', 'collision_node.stages.broadphase',
            'collision_node.simulate', 'collision_node.bench'} <= set(report['core'])
    assert report['ros'] == []


def test_the_probe_would_see_a_ros_module():
    # Guard against a probe that cannot fail: rclpy is installed and would be seen.
    done = subprocess.run([sys.executable, '-c', 'import rclpy, sys; '
                           'print(sorted(m for m in sys.modules if m.startswith("rcl")))'],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'rclpy' in done.stdout
