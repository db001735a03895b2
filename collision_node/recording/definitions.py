"""Message definitions and type hashes of ROS 2 interfaces, read from their installed files.

A rosbag2 MCAP file carries each channel's full message definition as a
``ros2msg`` schema: the type's ``.msg`` text, then every type it depends on
(recursively, each once) after a line of 80 ``=`` and ``MSG: pkg/Name``.
:func:`message_definition` builds that text the way rosbag2's local
message definition source does (same dependency scan, same sorted order,
same separators) from ``share/<pkg>/msg/<Name>.msg`` of the ament prefixes;
:func:`type_hash` reads the ``RIHS01_`` hash that rosidl generated beside
it (``<Name>.json``). Nothing here imports ROS.
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from typing import Optional, Sequence

SEPARATOR = '=' * 80
# A type name as rosbag2 reads it: ``pkg/Name`` or ``pkg/msg/Name``.
TYPE_NAME = re.compile(r'^([a-zA-Z0-9_]+)/(?:msg/)?([a-zA-Z0-9_]+)$')
# The first word of a field line, with an optional array suffix (rosbag2's scan).
FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
PRIMITIVE_TYPES = frozenset(('bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8',
                             'int16', 'uint16', 'int32', 'uint32', 'int64', 'uint64',
                             'string'))
MAX_DEPTH = 50


class DefinitionError(LookupError):
    """A message definition or type hash that cannot be found or read."""


def ament_prefixes(environ: Optional[dict[str, str]] = None) -> list[Path]:
    """Return the prefixes to search: AMENT_PREFIX_PATH, then this interpreter's prefix.

    The interpreter's prefix is where the ROS 2 wheels install the
    interface packages, so a venv works without a sourced environment.
    """
    environ = os.environ if environ is None else environ
    paths = [p for p in environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes: list[Path] = []
    for path in [*paths, sys.prefix]:
        if Path(path) not in prefixes:
            prefixes.append(Path(path))
    return prefixes


def share_directory(package: str, prefixes: Sequence[Path]) -> Path:
    """Return ``share/<package>`` of the first prefix whose ament index lists the package."""
    for prefix in prefixes:
        if (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / package).is_file():
            return prefix / 'share' / package
    raise DefinitionError(f'package {package} is not installed in any ament prefix '
                          f'({os.pathsep.join(map(str, prefixes))})')


def _split(type_name: str) -> tuple[str, str]:
    """Return (package, name) of ``pkg/Name`` or ``pkg/msg/Name``."""
    match = TYPE_NAME.match(type_name)
    if match is None:
        raise DefinitionError(f'{type_name!r} is not a message type name (pkg/msg/Name)')
    return match.group(1), match.group(2)


def _interface_file(type_name: str, suffix: str, prefixes: Sequence[Path]) -> Path:
    """Return the installed ``share/<pkg>/msg/<Name><suffix>`` of a message type."""
    package, name = _split(type_name)
    path = share_directory(package, prefixes) / 'msg' / (name + suffix)
    if not path.is_file():
        raise DefinitionError(f'{type_name}: no {path}')
    return path


def dependencies(text: str, package: str) -> list[str]:
    """Return the non-primitive field types of a ``.msg`` text as sorted ``pkg/Name`` names."""
    found = set()
    for match in FIELD_TYPE.finditer(text):
        field_type = match.group(1)
        if field_type in PRIMITIVE_TYPES:
            continue
        found.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(found)


def message_definition(type_name: str, prefixes: Optional[Sequence[Path]] = None) -> str:
    """Return the full ``ros2msg`` definition of ``type_name`` as rosbag2 writes it."""
    prefixes = ament_prefixes() if prefixes is None else prefixes
    seen: set[str] = set()
    texts: dict[str, str] = {}

    def load(name: str) -> str:
        if name not in texts:
            texts[name] = _interface_file(name, '.msg', prefixes).read_text(encoding='utf-8')
        return texts[name]

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise DefinitionError(f'{type_name}: dependencies nested deeper than {MAX_DEPTH}')
        text = load(name)
        result = text
        for dependency in dependencies(text, _split(name)[0]):
            if dependency not in seen:
                seen.add(dependency)
                result += f'\n{SEPARATOR}\nMSG: {dependency}\n' + append(dependency, depth - 1)
        return result

    return append(type_name, MAX_DEPTH)


def type_hash(type_name: str, prefixes: Optional[Sequence[Path]] = None) -> str:
    """Return the ``RIHS01_...`` type description hash rosidl generated for ``type_name``."""
    prefixes = ament_prefixes() if prefixes is None else prefixes
    path = _interface_file(type_name, '.json', prefixes)
    package, name = _split(type_name)
    full_name = f'{package}/msg/{name}'
    try:
        hashes = json.loads(path.read_text(encoding='utf-8'))['type_hashes']
        return next(h['hash_string'] for h in hashes if h['type_name'] == full_name)
    except (ValueError, KeyError, TypeError, StopIteration):
        raise DefinitionError(f'{path}: no type hash of {full_name}') from None
