"""YAML and JSON documents read strictly: what a config file or request body holds, or one
line saying what is wrong with it and where.

PyYAML's safe loader keeps the last of a key given twice without a word, reads YAML 1.1
(`1e-3` is text there, `no` is false, `010` is eight) and recurses once per level of nesting,
so 10,000 levels are a RecursionError. :func:`load_yaml` reads YAML 1.2's core schema, refuses
repeated keys, binary data and deep nesting; :func:`check_nesting` bounds the nesting of data
from any source (a JSON body), aliases included.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

# Levels of mappings and lists a document may nest (the deepest key of a config, curriculum.
# mixed.active_learning.m, is at 5): deeper is a mistake or an attack.
MAX_NESTING = 32
TOO_DEEP = f"nested deeper than {MAX_NESTING} levels"


class DocumentError(ValueError):
    """A document that cannot be read; the message is one line, with the line and column where known."""


def _at(mark: yaml.Mark) -> str:
    return f"(line {mark.line + 1}, column {mark.column + 1})"


class _StrictLoader(yaml.SafeLoader):
    """The safe loader, YAML 1.2 core scalars (resolvers below), no repeated key, no
    ``!!binary``, nesting bounded while composing (the composer recurses)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        self._depth += 1
        try:
            if self._depth > MAX_NESTING:
                raise DocumentError(f"{TOO_DEEP} {_at(self.peek_event().start_mark)}")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                continue  # an unhashable key is the safe loader's error; merged keys may be overridden
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
    ("float", r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)", "-+0123456789."),
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
    """DocumentError if ``data`` nests dicts and lists deeper than MAX_NESTING. Walked without
    recursion; a structure shared through YAML aliases is measured once (a chain of aliases can
    nest deep on shallow lines), and one that contains itself is an error."""
    heights: dict[int, int] = {}
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
        children = [c for c in (node.values() if isinstance(node, dict) else node) if isinstance(c, (dict, list, tuple))]
        pending = [c for c in children if id(c) not in heights]
        if id(node) in in_progress or not pending:
            if any(id(c) in in_progress for c in pending):
                raise DocumentError("a YAML alias refers to the mapping or list that contains it")
            heights[id(node)] = 1 + max((heights[id(c)] for c in children), default=0)
            in_progress.discard(id(node))
            stack.pop()
        else:
            in_progress.add(id(node))
            stack.extend(pending)
    if heights[id(data)] > MAX_NESTING:
        raise DocumentError(TOO_DEEP)
