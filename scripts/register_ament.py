#!/usr/bin/env python3
"""Register an editable collision_node in an ament prefix as a colcon install would.

    python scripts/register_ament.py PREFIX [--python INTERPRETER]

``ros2 run collision_node EXE`` finds the package through the ament index
(``PREFIX/share/ament_index/resource_index/packages/collision_node``) and
runs ``PREFIX/lib/collision_node/EXE``; ``ros2 pkg`` and launch files read
``PREFIX/share/collision_node/package.xml``. A pip editable install writes
none of these (its console scripts land in ``PREFIX/bin``), so this script
adds them:

- the ament index marker (an empty file, as colcon writes it);
- ``share/collision_node/package.xml``, ``share/collision_node/scenes`` and
  ``share/collision_node/config`` as symlinks into the checkout (as ``colcon
  build --symlink-install``), so an edited scene, parameters file or manifest
  is what the prefix serves;
- one executable per ``console_scripts`` entry of setup.py in
  ``lib/collision_node/``, a launcher that imports the entry point, so it
  runs the checkout's code (the editable install puts the checkout on the
  interpreter's path; a PYTHONPATH, e.g. a git worktree, still wins).

Running it again rewrites the same files (idempotent); launchers it wrote
for entry points no longer declared are removed. Standard library only:
scripts/setup runs it with the venv's interpreter before anything else.
"""

from __future__ import annotations

import argparse
import ast
import os
import shutil
import sys
from pathlib import Path

PACKAGE = 'collision_node'
ROOT = Path(__file__).resolve().parent.parent
# First lines of every launcher this script writes; only such files are ever replaced or removed.
MARK = '# Written by scripts/register_ament.py'


def console_scripts(setup_py: Path) -> dict[str, str]:
    """Return setup.py's console_scripts as {name: 'module:function'}, read from its source."""
    tree = ast.parse(setup_py.read_text(encoding='utf-8'))
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entries = ast.literal_eval(node.value)['console_scripts']
            return {name.strip(): target.strip()
                    for name, target in (line.split('=', 1) for line in entries)}
    raise ValueError(f'{setup_py}: no entry_points')


def launcher(interpreter: str, target: str) -> str:
    """Return the text of an executable that calls ``module:function`` and exits with it."""
    module, function = target.split(':')
    return (f'#!{interpreter}\n'
            f'{MARK} (editable collision_node); runs {target}.\n'
            'import sys\n'
            f'from {module} import {function}\n'
            "if __name__ == '__main__':\n"
            f'    sys.exit({function}())\n')


def _replace_with_symlink(link: Path, target: Path) -> None:
    """Make ``link`` a symlink to ``target``, replacing a file, link or copied tree there."""
    if link.is_symlink() or link.is_file():
        link.unlink()
    elif link.is_dir():
        shutil.rmtree(link)
    link.symlink_to(target)


def _write_if_changed(path: Path, text: str, mode: int) -> None:
    """Write ``text`` to ``path`` (atomically) unless it already holds it; set ``mode``."""
    if not (path.is_file() and not path.is_symlink()
            and path.read_text(encoding='utf-8') == text):
        temporary = path.with_name(path.name + '.tmp')
        temporary.write_text(text, encoding='utf-8')
        temporary.replace(path)
    path.chmod(mode)


def register(prefix: Path, source: Path = ROOT, interpreter: str = sys.executable) -> list[Path]:
    """Register the package at ``source`` in ``prefix``; return the launchers written."""
    prefix = Path(prefix)
    index = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True, exist_ok=True)
    marker = index / PACKAGE
    _write_if_changed(marker, (source / 'resource' / PACKAGE).read_text(encoding='utf-8'),
                      0o644)

    share = prefix / 'share' / PACKAGE
    share.mkdir(parents=True, exist_ok=True)
    _replace_with_symlink(share / 'package.xml', source / 'package.xml')
    _replace_with_symlink(share / 'scenes', source / 'scenes')
    _replace_with_symlink(share / 'config', source / 'config')

    lib = prefix / 'lib' / PACKAGE
    lib.mkdir(parents=True, exist_ok=True)
    wanted = console_scripts(source / 'setup.py')
    for stale in lib.iterdir():
        if stale.name not in wanted and stale.is_file() and _written_here(stale):
            stale.unlink()
    written = []
    for name, target in wanted.items():
        path = lib / name
        if path.exists() and not _written_here(path):
            # A colcon or pip install owns this file: replace it (this registration wins).
            path.unlink()
        _write_if_changed(path, launcher(interpreter, target), 0o755)
        written.append(path)
    return written


def _written_here(path: Path) -> bool:
    """Tell whether ``path`` is a launcher this script wrote."""
    try:
        with open(path, encoding='utf-8') as file:
            file.readline()
            return file.readline().startswith(MARK)
    except (OSError, UnicodeDecodeError):
        return False


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments and register (silently); 0 on success, 2 on a bad prefix."""
    parser = argparse.ArgumentParser(prog='register_ament.py', description=__doc__.split('\n')[0])
    parser.add_argument('prefix', type=Path, help='the ament prefix, e.g. .venv')
    parser.add_argument('--python', default=sys.executable,
                        help='interpreter of the launchers (default: this one, unresolved)')
    args = parser.parse_args(argv)
    if not args.prefix.is_dir():
        parser.error(f'prefix {args.prefix} is not a directory')
    prefix = Path(os.path.abspath(args.prefix))
    register(prefix, ROOT, args.python)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
