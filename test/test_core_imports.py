"""The layout keeps the architecture.

The physics imports no ROS module and nothing outside itself, and no module
of the package is part of an import circle.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / 'collision_node'

PROBE = r'''
import importlib, json, pkgutil, sys
import collision_node.physics as physics
names = sorted(m.name for m in pkgutil.walk_packages(physics.__path__, 'collision_node.physics.'))
for name in names:
    importlib.import_module(name)
from collision_node.simulate import main
main(['oblique_pair', '--quiet', '--steps', '5'])

def is_ros(module):
    top = module.split('.')[0]
    return (top in ('rclpy', 'ament_index_python') or top.startswith(('rcl', 'rosidl'))
            or top.endswith('_msgs') or top.endswith('_srvs'))

print(json.dumps({'physics': names, 'ros': sorted(m for m in sys.modules if is_ros(m)),
                  'package': sorted(m for m in sys.modules if m.startswith('collision_node'))}))
'''


def module_name(path: Path) -> str:
    """Return the dotted module name of a file under the package."""
    parts = list(path.relative_to(ROOT).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def package_imports(path: Path, modules: set[str]) -> set[str]:
    """Return the package modules a file imports, at any depth (functions included)."""
    name = module_name(path)
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[:len(base) - node.level + 1]
                stem = '.'.join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ''
            # ``from . import x`` names a submodule or a name of the package itself.
            subs = [f'{stem}.{alias.name}' for alias in node.names]
            targets = [s for s in subs if s in modules]
            if len(targets) < len(subs):
                targets.append(stem)
        else:
            continue
        found.update(t for t in targets if t.startswith('collision_node'))
    return found


def import_graph() -> dict[str, set[str]]:
    """Return module -> package modules it imports, for every module of the package."""
    files = {module_name(p): p for p in PACKAGE.rglob('*.py')}
    return {name: {t for t in package_imports(path, set(files)) if t in files and t != name}
            for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Return the import circles of ``graph`` (strongly connected parts of two or more)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in graph[node]:
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            part = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                part.append(top)
                if top == node:
                    break
            if len(part) > 1:
                found.append(sorted(part))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def parents(name: str) -> set[str]:
    """Return the packages above a module (importing it imports them)."""
    parts = name.split('.')
    return {'.'.join(parts[:k]) for k in range(1, len(parts))}


def test_physics_and_its_runner_import_no_ros_module():
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    done = subprocess.run([sys.executable, '-c', PROBE], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.splitlines()[-1])
    # The probe really walked the physics: the stages, the plan and the world are in it.
    assert {'collision_node.physics.model.scene', 'collision_node.physics.step.plan',
            'collision_node.physics.stages.detection.broadphase',
            'collision_node.physics.step.world'} <= set(report['physics'])
    assert report['ros'] == []
    # Nor did the physics or the runner pull in the ROS front ends or the benchmarks.
    assert not [m for m in report['package']
                if m.startswith(('collision_node.ros', 'collision_node.bench'))]


def test_physics_imports_nothing_outside_itself():
    graph = import_graph()
    physics = {name for name in graph if name.startswith('collision_node.physics')}
    assert len(physics) > 20
    outside = {(name, target) for name in physics for target in graph[name]
               if not target.startswith('collision_node.physics')
               and target not in parents('collision_node.physics.x')}
    assert outside == set()


def test_no_import_circle_in_the_package():
    graph = import_graph()
    assert 'collision_node.physics.step.plan' in graph['collision_node.physics.step.world']
    assert cycles(graph) == []


def test_the_circle_check_would_see_a_circle():
    # Guard against a check that cannot fail.
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]
    graph = import_graph()
    pipeline, plan = 'collision_node.physics.step.pipeline', 'collision_node.physics.step.plan'
    graph[pipeline].add(plan)
    assert [pipeline, plan] in [[m for m in part if m in (pipeline, plan)]
                                for part in cycles(graph)]


def test_the_probe_would_see_a_ros_module():
    # Guard against a probe that cannot fail: rclpy is installed and would be seen.
    done = subprocess.run([sys.executable, '-c', 'import rclpy, sys; '
                           'print(sorted(m for m in sys.modules if m.startswith("rcl")))'],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'rclpy' in done.stdout


def test_no_two_modules_share_a_name():
    names: dict[str, list[str]] = {}
    for path in PACKAGE.rglob('*.py'):
        if path.name not in ('__init__.py', '__main__.py'):
            names.setdefault(path.stem, []).append(str(path.relative_to(ROOT)))
    assert {stem: paths for stem, paths in names.items() if len(paths) > 1} == {}
    assert 'world' in names and 'broadphase' in names


def test_no_folder_holds_more_than_fifteen_modules():
    folders = {path.parent for path in PACKAGE.rglob('*.py')}
    crowded = {str(folder.relative_to(ROOT)): count for folder in folders
               if (count := len([p for p in folder.glob('*.py')
                                 if p.name != '__init__.py'])) > 15}
    assert crowded == {}
    assert len(folders) > 10


def module_constants(path: Path) -> set[str]:
    """Return the public UPPER_CASE names a module assigns at its top level."""
    names = set()
    for node in ast.parse(path.read_text()).body:
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) else [])
        for target in targets:
            for leaf in ast.walk(target):
                if isinstance(leaf, ast.Name) and leaf.id.isupper() and leaf.id[0] != '_':
                    names.add(leaf.id)
    return names


def test_no_physics_constant_is_defined_in_two_modules():
    owners: dict[str, list[str]] = {}
    for path in (PACKAGE / 'physics').rglob('*.py'):
        for name in module_constants(path):
            owners.setdefault(name, []).append(str(path.relative_to(ROOT)))
    assert 'STRIKE_FACTOR' in owners and 'SPIN_FACTOR' in owners
    assert {name: paths for name, paths in owners.items() if len(paths) > 1} == {}


def parameter_count(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Return how many parameters a function takes (self and cls not counted)."""
    args = function.args
    count = len(args.posonlyargs) + len(args.args) + len(args.kwonlyargs)
    count += (args.vararg is not None) + (args.kwarg is not None)
    return count - (1 if args.args and args.args[0].arg in ('self', 'cls') else 0)


def test_no_function_takes_more_than_twelve_parameters():
    crowded = []
    for path in PACKAGE.rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) \
                    and parameter_count(node) > 12:
                crowded.append(f'{path.relative_to(ROOT)}:{node.name}')
    assert crowded == []
    assert parameter_count(ast.parse('def f(self, a, *b, c, **d): pass').body[0]) == 4
