"""YAML and JSON documents read strictly: what a config file or request body holds, or one
line saying what is wrong with it and where.

PyYAML's safe loader keeps the last of a key given twice without a word, reads YAML 1.1
(`1e-3` is text there, `no` is false, `010` is eight) and recurses once per level of nesting,
so 10,000 levels are a RecursionError. Its merge keys (``<<``) and aliases let a few lines
stand for billions of values (a "billion laughs"). :func:`load_yaml` reads YAML 1.2's core
schema, refuses repeated keys, binary data, merge keys, deep nesting and documents of more than
MAX_NODES values or MAX_ALIASES aliases (counted while composing, so a huge document stops
early); :func:`check_nesting` bounds the nesting and size of data from any source (a JSON body),
each alias counted as the values it stands for.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

# Levels of mappings and lists a document may nest (the deepest key of a config, curriculum.
# mixed.active_learning.m, is at 5): deeper is a mistake or an attack.
MAX_NESTING = 32
TOO_DEEP = f"nested deeper than {MAX_NESTING} levels"
# Values (mappings, lists, keys and scalars) a document may hold, aliases expanded: a config
# holds about a hundred. Pure-Python YAML reads ~15,000 a second here, so this bounds the cost
# of any document to a fraction of a second.
MAX_NODES = 5_000
TOO_LARGE = f"more than {MAX_NODES:,} values"
# Aliases (*name) a document may use; a config needs none.
MAX_ALIASES = 100
MERGE_TAG = "tag:yaml.org,2002:merge"


class DocumentError(ValueError):
    """A document that cannot be read; the message is one line, with the line and column where known."""


def _at(mark: yaml.Mark) -> str:
    return f"(line {mark.line + 1}, column {mark.column + 1})"


class _StrictLoader(yaml.SafeLoader):
    """The safe loader, YAML 1.2 core scalars (resolvers below), no repeated key, no
    ``!!binary``, no merge key; nesting, values and aliases bounded while composing (the
    composer recurses, and the scanner reads no further than the composer asks)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0
        self._aliases = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_NESTING:
                raise DocumentError(f"{TOO_DEEP} {_at(self.peek_event().start_mark)}")
            if self.check_event(yaml.AliasEvent):
                self._aliases += 1
                if self._aliases > MAX_ALIASES:
                    raise DocumentError(f"more than {MAX_ALIASES} aliases {_at(self.peek_event().start_mark)}")
            else:
                self._nodes += 1
                if self._nodes > MAX_NODES:
                    raise DocumentError(f"{TOO_LARGE} {_at(self.peek_event().start_mark)}")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def flatten_mapping(self, node: yaml.MappingNode) -> None:
        # A merge key copies the merged mappings into this one: each level of merges of merges
        # doubles the work, 23 lines took 21 s. A config has no use for it.
        for key_node, _ in node.value:
            if key_node.tag == MERGE_TAG:
                raise DocumentError(
                    f"YAML merge keys (<<) are not accepted: write the keys out {_at(key_node.start_mark)}"
                )
        super().flatten_mapping(node)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        self.flatten_mapping(node)
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                continue  # an unhashable key is the safe loader's error
            key = self.construct_object(key_node)
            if key in seen:
                raise DocumentError(f"duplicate key {key!r} {_at(key_node.start_mark)}")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)

    def construct_core_int(self, node: yaml.ScalarNode) -> int:
        text = self.construct_scalar(node)
        try:
            return int(text, 0) if text[:2] in ("0x", "0o") else int(text, 10)
        except ValueError:  # Python reads no integer of more than 4,300 digits from text
            raise DocumentError(f"a whole number of {len(text):,} characters {_at(node.start_mark)}") from None

    def construct_binary(self, node: yaml.ScalarNode) -> bytes:
        # pydantic would take the bytes as text, NUL and all (PostgreSQL refuses NUL in text).
        raise DocumentError(f"!!binary data has no place in a config {_at(node.start_mark)}")


_REPLACED_TAGS = {f"tag:yaml.org,2002:{name}" for name in ("bool", "int", "float", "timestamp")}
_StrictLoader.yaml_implicit_resolvers = {
    first: [(tag, pattern) for tag, pattern in resolvers if tag not in _REPLACED_TAGS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _name, _pattern, _first in (
    ("bool", r"true|True|TRUE|false|False|FALSE", "tTfF"),
    # Decimal (underscores between digits, as PyYAML read them), 0o octal, 0x hexadecimal.
    ("int", r"[-+]?[0-9]+(?:_[0-9]+)*|0o[0-7]+|0x[0-9a-fA-F]+", "-+0123456789"),
    (
        "float",
        r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)",
        "-+0123456789.",
    ),
):
    _StrictLoader.add_implicit_resolver(f"tag:yaml.org,2002:{_name}", re.compile(f"^(?:{_pattern})$"), list(_first))
_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_core_int)
_StrictLoader.add_constructor("tag:yaml.org,2002:binary", _StrictLoader.construct_binary)


def load_yaml(text: str) -> Any:
    """The data of one YAML document (JSON is YAML); DocumentError says what is wrong and where."""
    try:
        data = yaml.load(text, Loader=_StrictLoader)  # noqa: S506 (a SafeLoader)
    except yaml.MarkedYAMLError as error:
        where = f" {_at(error.problem_mark)}" if error.problem_mark else ""
        context = f"{error.context}: " if error.context else ""
        raise DocumentError(f"not YAML: {context}{error.problem}{where}") from None
    except yaml.YAMLError as error:
        raise DocumentError(f"not YAML: {' '.join(str(error).split())}") from None
    check_nesting(data)
    return data


def check_nesting(data: Any) -> None:
    """DocumentError if ``data`` nests dicts and lists deeper than MAX_NESTING or holds more
    than MAX_NODES values (a mapping's key and value count as two). Walked without recursion; a
    structure shared through YAML aliases is walked once but counted as often as it is used (a
    chain of aliases can nest deep and grow large on a few lines), and one that contains itself
    is an error."""
    heights: dict[int, int] = {}
    sizes: dict[int, int] = {}
    in_progress: set[int] = set()
    stack: list[Any] = [data]
    while stack:
        node = stack[-1]
        if id(node) in heights:
            stack.pop()
            continue
        if not isinstance(node, (dict, list, tuple)):
            heights[id(node)] = 0
            stack.pop()
            continue
        if len(node) > MAX_NODES:
            raise DocumentError(TOO_LARGE)  # before listing a huge list's children
        children = [
            c for c in (node.values() if isinstance(node, dict) else node) if isinstance(c, (dict, list, tuple))
        ]
        pending = [c for c in children if id(c) not in heights]
        if id(node) in in_progress or not pending:
            if any(id(c) in in_progress for c in pending):
                raise DocumentError("a YAML alias refers to the mapping or list that contains it")
            heights[id(node)] = 1 + max((heights[id(c)] for c in children), default=0)
            scalars = (2 * len(node) if isinstance(node, dict) else len(node)) - len(children)
            size = 1 + scalars + sum(sizes[id(c)] for c in children)
            if size > MAX_NODES:
                raise DocumentError(TOO_LARGE)
            sizes[id(node)] = size
            in_progress.discard(id(node))
            stack.pop()
        else:
            in_progress.add(id(node))
            stack.extend(pending)
    if heights[id(data)] > MAX_NESTING:
        raise DocumentError(TOO_DEEP)
