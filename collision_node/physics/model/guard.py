"""The one gate every text passes before it becomes data: size, depth, aliases.

Scene files, spawn requests (the node's spawn topic), ``--accuracy`` and the
node's ``accuracy`` parameter are all read by :func:`parse_text` (files by
:func:`read_text_file` first). It bounds the work a hostile or broken text
can cause before any parser sees it:

* size: at most ``MAX_TEXT_BYTES`` (1 MiB) of UTF-8, checked first;
* depth: at most ``MAX_DEPTH`` (32) nested lists or mappings, flow
  (``[`` ``{``) and block (indentation, ``- - -``) alike;
* aliases (``*name``) are refused, so a few hundred bytes cannot expand to
  gigabytes (the "billion laughs");
* numerals: a float that overflows becomes an :class:`OverflowedNumber`
  the validator rejects, and a numeral longer than 1000 characters is never
  converted (``int()`` of a long numeral is quadratic);
* duplicate keys in a mapping are refused (both parsers would keep the last
  one silently), naming the key, the mapping's path and the line.

JSON goes through the C parser (``json.loads``) after a depth scan of its
brackets outside strings, which is exact for JSON. Anything else goes
through libyaml: its event parser is iterative, and the tree is built from
its events here with an explicit stack that stops at the first alias or
at depth 33. (libyaml's own composer recurses in C and crashes the
interpreter on 100 000 nested ``[``; the pure-Python one is quadratic. A
text scan cannot tell YAML's quotes and compact sequences apart reliably
enough to stand guard, the event stream can and costs little.)

Every refusal is a :class:`SceneError` of one line that names the source
and the problem, quotes at most a short prefix of the text and never
carries an interpreter message.
"""

from __future__ import annotations

import gc
import json
import math
import re
from pathlib import Path
from typing import Any, Union

import yaml
from yaml.nodes import MappingNode, ScalarNode, SequenceNode

from .validation import MAX_INTEGER_DIGITS, OverflowedNumber, SceneError, one_line, quote

MAX_TEXT_BYTES = 1 << 20
MAX_DEPTH = 32

_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.DOTALL)
_BRACKET = re.compile(r'[\[\]{}]')
_SCI_FLOAT = re.compile(r'^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$')
# A key is quoted in a refusal only when it looks like a field name: any
# other text (a line of some other file) may be anything.
_KEY_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]{0,39}')


class _Refused(yaml.YAMLError):
    """Raised inside the loader; :func:`parse_text` turns it into the reason."""

    def __init__(self, reason: str, mark: Any) -> None:
        super().__init__(reason)
        self.reason, self.mark = reason, mark


class _DuplicateKey(ValueError):
    """A JSON object with a key twice; :func:`parse_text` reads the text again as YAML."""

    def __init__(self, key: Any) -> None:
        super().__init__('duplicate key')
        self.key = key


def _key_text(key: Any) -> str:
    """Name a key for a refusal: quoted if it is a field name, described otherwise."""
    if isinstance(key, str) and _KEY_NAME.fullmatch(key):
        return quote(key)
    return '(a key that is not a field name)'


def _path(stack: list[list[Any]]) -> str:
    """Return where the innermost open collection sits: ``particles[2].velocity``."""
    path = ''
    for parent, child in zip(stack, stack[1:] + [None]):
        if child is None:
            break
        node, pending = parent[0], parent[1]
        if isinstance(node, SequenceNode):
            path += f'[{len(node.value)}]'
        else:
            name = pending.value if isinstance(pending, ScalarNode) else None
            name = name if isinstance(name, str) and _KEY_NAME.fullmatch(name) else '?'
            path += f'.{name}' if path else name
    return path


class GuardedLoader(yaml.CSafeLoader):
    """libyaml's safe loader with the guard's tree builder and number rules.

    PyYAML follows YAML 1.1, where an exponent needs a sign and a mantissa
    a dot, so ``mass: 1e3`` would be the string '1e3'. Scene authors write
    SCI notation as in YAML 1.2 and JSON; this resolver accepts it.
    """

    def get_single_node(self) -> Any:
        """Build the document's node tree from libyaml's events, iteratively.

        Replaces the recursive composer: refuses aliases and nesting deeper
        than ``MAX_DEPTH`` at the event that would pass the limit, and a
        scalar key a mapping already holds at that key.
        """
        self.get_event()                                  # StreamStart
        if self.check_event(yaml.StreamEndEvent):
            self.get_event()
            return None
        self.get_event()                                  # DocumentStart
        stack: list[list[Any]] = []                       # [node, pending key, keys seen]
        root = None
        while root is None:
            event = self.get_event()
            if isinstance(event, yaml.AliasEvent):
                raise _Refused('YAML aliases (*name) are not accepted', event.start_mark)
            if isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                node = stack.pop()[0]
                node.end_mark = event.end_mark
            elif isinstance(event, yaml.ScalarEvent):
                tag = event.tag
                if tag is None or tag == '!':
                    tag = self.resolve(ScalarNode, event.value, event.implicit)
                node = ScalarNode(tag, event.value, event.start_mark, event.end_mark,
                                  style=event.style)
            else:
                kind = SequenceNode if isinstance(event, yaml.SequenceStartEvent) \
                    else MappingNode
                if len(stack) >= MAX_DEPTH:
                    raise _Refused(f'nested deeper than {MAX_DEPTH} levels', event.start_mark)
                tag = event.tag
                if tag is None or tag == '!':
                    tag = self.resolve(kind, None, event.implicit)
                stack.append([kind(tag, [], event.start_mark, None,
                                   flow_style=event.flow_style), None,
                              set() if kind is MappingNode else None])
                continue
            if not stack:
                root = node
            elif isinstance(stack[-1][0], SequenceNode):
                stack[-1][0].value.append(node)
            elif stack[-1][1] is None:
                if isinstance(node, ScalarNode):
                    key = (node.tag, node.value)
                    if key in stack[-1][2]:
                        where = _path(stack)
                        raise _Refused(f'{where + ": " if where else ""}duplicate key '
                                       f'{_key_text(node.value)}', node.start_mark)
                    stack[-1][2].add(key)
                stack[-1][1] = node
            else:
                stack[-1][0].value.append((stack[-1][1], node))
                stack[-1][1] = None
        self.get_event()                                  # DocumentEnd
        if not self.check_event(yaml.StreamEndEvent):
            raise _Refused('expected a single document, found another',
                           self.peek_event().start_mark)
        self.get_event()
        return root


def _construct_float(loader: GuardedLoader, node: ScalarNode) -> float:
    """Read a float; a numeral that overflows to inf is not ``.inf``: mark it."""
    if len(node.value) > MAX_INTEGER_DIGITS:
        return OverflowedNumber(node.value)
    try:
        value = loader.construct_yaml_float(node)
    except ValueError:
        raise _Refused('a !!float value that is not a number', node.start_mark) from None
    if math.isinf(value) and 'inf' not in node.value.lower():
        return OverflowedNumber(node.value)
    return value


def _construct_int(loader: GuardedLoader, node: ScalarNode) -> Union[int, float]:
    """Read an integer; one too long to convert cheaply overflows a float anyway."""
    if len(node.value) > MAX_INTEGER_DIGITS:
        return OverflowedNumber(node.value)
    try:
        return loader.construct_yaml_int(node)
    except ValueError:
        raise _Refused('an !!int value that is not an integer', node.start_mark) from None


GuardedLoader.add_implicit_resolver('tag:yaml.org,2002:float', _SCI_FLOAT,
                                    list('-+0123456789.'))
GuardedLoader.add_constructor('tag:yaml.org,2002:float', _construct_float)
GuardedLoader.add_constructor('tag:yaml.org,2002:int', _construct_int)


def _json_float(text: str) -> float:
    value = float(text)
    return OverflowedNumber(text) if math.isinf(value) else value


def _json_int(text: str) -> Union[int, float]:
    return OverflowedNumber(text) if len(text) > MAX_INTEGER_DIGITS else int(text)


def _json_object(pairs: list[tuple[str, Any]]) -> dict:
    """Build a JSON object; a key given twice raises :class:`_DuplicateKey`."""
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise _DuplicateKey(key)
            seen.add(key)
    return out


def _json_depth(text: str) -> int:
    """Return the deepest bracket nesting outside JSON strings (exact for JSON)."""
    depth = deepest = 0
    for match in _BRACKET.finditer(_JSON_STRING.sub('""', text)):
        if match.group() in '[{':
            depth += 1
            deepest = max(deepest, depth)
            if deepest > MAX_DEPTH:
                break
        else:
            depth -= 1
    return deepest


def check_size(text: str, source: str) -> None:
    """Refuse a text of more than ``MAX_TEXT_BYTES`` bytes of UTF-8."""
    # A character takes 1 to 4 bytes: count bytes only when it matters.
    if len(text) * 4 <= MAX_TEXT_BYTES:
        return
    size = len(text) if len(text) > MAX_TEXT_BYTES else \
        len(text.encode('utf-8', errors='surrogatepass'))
    if size > MAX_TEXT_BYTES:
        raise SceneError(f'{source}: text of {size} bytes (or more) is over the limit of '
                         f'{MAX_TEXT_BYTES} bytes (1 MiB)')


def read_text_file(path: Union[str, Path], source: str) -> str:
    """Read at most ``MAX_TEXT_BYTES`` (+1, to tell) of a file as UTF-8 text."""
    try:
        with open(path, 'rb') as handle:
            data = handle.read(MAX_TEXT_BYTES + 1)
    except OSError as error:
        raise SceneError(f'{source}: cannot read: {error.strerror}') from None
    if len(data) > MAX_TEXT_BYTES:
        raise SceneError(f'{source}: file is over the limit of {MAX_TEXT_BYTES} bytes '
                         '(1 MiB); not a scene file')
    try:
        return data.decode('utf-8')
    except UnicodeDecodeError as error:
        raise SceneError(f'{source}: cannot read: not UTF-8 text (byte {error.start}); '
                         'not a scene file') from None


def _where(mark: Any) -> str:
    if mark is None or getattr(mark, 'line', None) is None:
        return ''
    return f' (line {mark.line + 1}, column {mark.column + 1})'


def parse_text(text: str, source: str, kind: str = 'YAML or JSON') -> Any:
    """Parse a YAML or JSON text within the guard's limits; return plain data.

    ``kind`` names what was expected in a syntax error ('YAML', 'YAML or
    JSON'). Raises :class:`SceneError`, never a parser's exception.
    """
    if not isinstance(text, str):
        raise SceneError(f'{source}: expected text, got {type(text).__name__}')
    check_size(text, source)
    start = text.lstrip()[:1]
    if start in ('[', '{') and _json_depth(text) <= MAX_DEPTH or start in ('"', '-') or \
            start.isdigit():
        try:
            return json.loads(text, parse_float=_json_float, parse_int=_json_int,
                              parse_constant=str, object_pairs_hook=_json_object)
        except _DuplicateKey as duplicate:
            # The YAML reading finds the same key with its path and line;
            # should it not (JSON that libyaml reads otherwise), say what is known.
            _parse_yaml(text, source, kind)
            raise SceneError(f'{source}: duplicate key {_key_text(duplicate.key)}') from None
        except ValueError:
            pass                   # not JSON (JSONDecodeError is a ValueError): try YAML
    return _parse_yaml(text, source, kind)


def _parse_yaml(text: str, source: str, kind: str) -> Any:
    """Parse ``text`` with the guarded libyaml loader (see :func:`parse_text`)."""
    # The tree only grows while it is built, so the cyclic collector would
    # walk it again and again for nothing (2.5x the build time of a 1 MiB
    # scene); pause it for the build.
    collecting = gc.isenabled()
    gc.disable()
    try:
        return yaml.load(text, Loader=GuardedLoader)  # noqa: S506 (a CSafeLoader subclass)
    except _Refused as refused:
        raise SceneError(f'{source}: {refused.reason}{_where(refused.mark)}') from None
    except yaml.MarkedYAMLError as error:
        problem = one_line(error.problem or error.context or 'syntax error', 80)
        raise SceneError(f'{source}: not valid {kind}: {problem}'
                         f'{_where(error.problem_mark)}') from None
    except yaml.reader.ReaderError as error:
        raise SceneError(f'{source}: not valid {kind}: {one_line(error.reason, 80)} '
                         f'(character {error.position + 1})') from None
    except yaml.YAMLError:
        raise SceneError(f'{source}: not valid {kind}') from None
    except (ArithmeticError, ValueError, TypeError):
        # A value of a known tag that the constructor cannot build, such as
        # the date 2001-13-45: the interpreter's words would not help.
        raise SceneError(f'{source}: not valid {kind}: a tagged or dated value could not '
                         'be read') from None
    finally:
        if collecting:
            gc.enable()


__all__ = ['MAX_DEPTH', 'MAX_TEXT_BYTES', 'GuardedLoader', 'check_size', 'parse_text',
           'read_text_file']
