"""Write the generated parts of docs/ from the code, or check that they are current.

    python docs/generate.py          # rewrite docs/configuration.md, docs/rest-api.md and the
                                     # results table of docs/benchmarks.md
    python docs/generate.py --check  # exit 1, naming the stale files, if any differs

* docs/configuration.md: every key of an experiment config, from the pydantic schema in
  foldwise/config.py (type, range, default; the description is the field's own, or the comment
  above it in the source).
* docs/rest-api.md: every route of the REST API, from the FastAPI app's OpenAPI document.
* docs/benchmarks.md, between its GENERATED markers: one row per bench/results/*.json.

The output depends only on the code and the result files (sorted keys, no timestamps), so a
second run writes the same bytes. tests/test_docs.py runs the check.
"""

from __future__ import annotations

import argparse
import ast
import io
import json
import sys
import tokenize
import types
import typing
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CONFIG_SOURCE = ROOT / "foldwise" / "config.py"
RESULTS = ROOT / "bench" / "results"
BEGIN = "<!-- BEGIN GENERATED: python docs/generate.py -->"
END = "<!-- END GENERATED -->"

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _cell(text: Any) -> str:
    """Text fit for one Markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|")


# --- configuration ---------------------------------------------------------------------------


def _source_comments(path: Path) -> dict[tuple[str, str], str]:
    """(class, field) -> the comment lines right above the field, or on its line, in ``path``."""
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    inline: dict[int, str] = {}
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT and lines[token.start[0] - 1][: token.start[1]].strip():
            inline[token.start[0]] = token.string.lstrip("#").strip()
    comments: dict[tuple[str, str], str] = {}
    for node in ast.parse(source).body:
        if not isinstance(node, ast.ClassDef):
            continue
        for item in node.body:
            if not (isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)):
                continue
            above = []
            number = item.lineno - 2
            while number >= 0 and lines[number].strip().startswith("#"):
                above.insert(0, lines[number].strip().lstrip("#").strip())
                number -= 1
            if item.end_lineno in inline:
                above.append(inline[item.end_lineno])
            if above:
                comments[(node.name, item.target.id)] = " ".join(above)
    return comments


def _type_name(annotation: Any) -> str:
    """A reader's name for a field's type: `int`, `"a" | "b"`, `[int, int]`, `list of str`."""
    from pydantic import BaseModel

    origin, arguments = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_name(arguments[0])
    if origin is typing.Literal:
        return " \\| ".join(json.dumps(value) for value in arguments)
    if origin in (typing.Union, types.UnionType):
        names = [_type_name(argument) for argument in arguments if argument is not type(None)]
        return " \\| ".join(names) + (" \\| null" if type(None) in arguments else "")
    if origin is tuple:
        return "[" + ", ".join(_type_name(argument) for argument in arguments) + "]"
    if origin is list:
        return f"list of {_type_name(arguments[0])}"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "section"
    if isinstance(annotation, type):
        return {"Path": "path", "NoneType": "null"}.get(annotation.__name__, annotation.__name__)
    return str(annotation)


def _bounds(metadata: list[Any], text: bool = False) -> list[str]:
    words = []
    for item in metadata:
        for attribute, symbol in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")):
            value = getattr(item, attribute, None)
            if value is not None:
                words.append(f"{symbol} {value:,}" if isinstance(value, int) else f"{symbol} {value:g}")
        if getattr(item, "min_length", None) is not None:
            unit = "character" if text else "item"
            words.append(f"at least {item.min_length} {unit}{'s' if item.min_length != 1 else ''}")
        if getattr(item, "max_length", None) is not None:
            words.append(f"at most {item.max_length:,} characters")
    return words


def _element_bounds(annotation: Any) -> list[str]:
    """Bounds on the elements of a tuple or list of Annotated numbers."""
    words: list[str] = []
    for argument in typing.get_args(annotation):
        if typing.get_origin(argument) is typing.Annotated:
            words = [f"each {word}" for word in _bounds(list(typing.get_args(argument)[1:]))]
    return words


def _default(field: Any) -> str:
    from pydantic import BaseModel
    from pydantic_core import PydanticUndefined

    if field.default_factory is not None:
        value = field.default_factory()
    elif field.default is PydanticUndefined:
        return "required"
    else:
        value = field.default
    if isinstance(value, BaseModel):
        return "–"
    if isinstance(value, tuple):
        value = list(value)
    return f"`{json.dumps(value)}`"


def _sections(model: type, prefix: str) -> list[tuple[str, type]]:
    """(dotted prefix, model) of ``model`` and every section nested in it, depth first."""
    from pydantic import BaseModel

    found = [(prefix, model)]
    for name, field in model.model_fields.items():
        for candidate in (field.annotation, *typing.get_args(field.annotation)):
            if isinstance(candidate, type) and issubclass(candidate, BaseModel):
                found += _sections(candidate, f"{prefix}.{name}" if prefix else name)
    return found


def configuration_reference() -> str:
    from foldwise.config import ExperimentConfig

    comments = _source_comments(CONFIG_SOURCE)
    out = [
        "# Configuration reference",
        "",
        "<!-- Generated by `python docs/generate.py` from foldwise/config.py; edit the schema, not this file. -->",
        "",
        "An experiment is one YAML file (`configs/*.yaml`). Every section forbids unknown keys, and a bad",
        'value fails before any work starts, naming its dotted key. Numbers are strict (`"50"`, `50.0`',
        "and `true` are not counts), YAML is read as YAML 1.2 (`1e-3` is a float, `no` is text), and a",
        "key given twice is an error. The user guide (docs/user-guide.md) shows the configs that ship;",
        "the values `configs/quick.yaml` uses were chosen by the studies in bench/README.md.",
        "",
    ]
    for prefix, model in _sections(ExperimentConfig, ""):
        title = prefix or "top level"
        out += [f"## `{title}`", ""]
        doc = (model.__doc__ or "").strip()
        if doc and model is not ExperimentConfig and not doc.startswith("!!!"):
            out += [" ".join(doc.split("\n\n")[0].split()), ""]
        out += ["| key | type | range | default | description |", "|---|---|---|---|---|"]
        for name, field in model.model_fields.items():
            key = f"{prefix}.{name}" if prefix else name
            bounds = _bounds(field.metadata, text=field.annotation is str) + _element_bounds(field.annotation)
            description = comments.get((model.__name__, name)) or field.description or ""
            if _type_name(field.annotation).startswith("section"):
                description = f"{description} The `{key}` section below.".strip()
            out.append(
                f"| `{key}` | {_type_name(field.annotation)} | {_cell(', '.join(bounds)) or '–'} | "
                f"{_cell(_default(field))} | {_cell(description)} |"
            )
        out.append("")
    return "\n".join(out)


# --- REST API --------------------------------------------------------------------------------

METHODS = ("get", "post", "put", "patch", "delete")


def _schema_name(schema: dict[str, Any]) -> str:
    if "$ref" in schema:
        return schema["$ref"].rsplit("/", 1)[-1]
    if "anyOf" in schema:
        return " \\| ".join(_schema_name(option) for option in schema["anyOf"])
    if schema.get("type") == "array":
        return f"array of {_schema_name(schema.get('items', {}))}"
    if "enum" in schema:
        return " \\| ".join(json.dumps(value) for value in schema["enum"])
    return schema.get("type", "any")


def rest_reference(document: dict[str, Any] | None = None) -> str:
    if document is None:
        from services.api.app import create_app

        document = create_app().openapi()
    out = [
        "# REST API reference",
        "",
        "<!-- Generated by `python docs/generate.py` from the FastAPI app's OpenAPI document"
        " (services/api/app.py); edit the routes, not this file. -->",
        "",
        "`foldwise api` serves these routes (and the interactive OpenAPI page at `/docs`). Reads need no",
        "token; a route marked **token** needs `Authorization: Bearer $FOLDWISE_API_TOKEN`. Errors answer",
        '`{"detail": ...}`. The user guide (docs/user-guide.md) shows them in use.',
        "",
        "| method | path | summary | token |",
        "|---|---|---|---|",
    ]
    routes = [
        (path, method, document["paths"][path][method])
        for path in sorted(document["paths"])
        for method in METHODS
        if method in document["paths"][path]
    ]
    for path, method, operation in routes:
        token = "token" if operation.get("security") else ""
        out.append(f"| {method.upper()} | `{path}` | {_cell(operation.get('summary', ''))} | {token} |")
    out.append("")
    for path, method, operation in routes:
        out += [f"## {method.upper()} `{path}`", ""]
        if operation.get("security"):
            out += ["Needs the token.", ""]
        if operation.get("description"):
            out += [operation["description"].strip(), ""]
        parameters = operation.get("parameters", [])
        if parameters:
            out += ["| parameter | in | type | required | default | description |", "|---|---|---|---|---|---|"]
            for parameter in parameters:
                schema = parameter.get("schema", {})
                default = f"`{json.dumps(schema['default'])}`" if "default" in schema else ""
                bounds = ", ".join(
                    f"{symbol} {schema[key]}"
                    for key, symbol in (
                        ("minimum", "≥"),
                        ("exclusiveMinimum", ">"),
                        ("maximum", "≤"),
                        ("exclusiveMaximum", "<"),
                    )
                    if key in schema
                )
                kind = _schema_name(schema) + (f" ({bounds})" if bounds else "")
                out.append(
                    f"| `{parameter['name']}` | {parameter['in']} | {kind} | "
                    f"{'yes' if parameter.get('required') else 'no'} | {_cell(default)} | "
                    f"{_cell(parameter.get('description', ''))} |"
                )
            out.append("")
        body = operation.get("requestBody")
        if body:
            kinds = ", ".join(
                f"`{media}`" + (f" ({_schema_name(spec['schema'])})" if spec.get("schema") else "")
                for media, spec in sorted(body.get("content", {}).items())
            )
            out += [f"Body{' (required)' if body.get('required') else ''}: {kinds}.", ""]
        out += ["| status | meaning | content |", "|---|---|---|"]
        for code, response in sorted(operation.get("responses", {}).items()):
            content = ", ".join(
                f"`{media}`" + (f" ({_schema_name(spec['schema'])})" if spec.get("schema") else "")
                for media, spec in sorted(response.get("content", {}).items())
            )
            out.append(f"| {code} | {_cell(response.get('description', ''))} | {content} |")
        out.append("")
    return "\n".join(out)


# --- benchmark results -----------------------------------------------------------------------


def _find(report: dict[str, Any], *keys: str) -> Any:
    """The first of ``keys`` present at the report's top level or in its ``machine``."""
    for where in (report, report.get("machine") or {}):
        for key in keys:
            if where.get(key) not in (None, ""):
                return where[key]
    return None


def _headline(report: dict[str, Any]) -> str:
    """The figures a result exists for, in one cell (a report's own ``headline`` where it writes one)."""
    if isinstance(report.get("headline"), str):
        return report["headline"]
    if report.get("benchmark") == "faults":
        faults = report.get("faults", {})
        parts = [f"{name} {fault['seconds_to_recovery']:.1f} s" for name, fault in sorted(faults.items())]
        duplicates = sum(fault.get("duplicates", 0) for fault in faults.values())
        verdict = "all within" if report.get("all_met") else "not all within"
        return (
            f"seconds from the fault to the lost work running again: {', '.join(parts)} "
            f"({verdict} the {report.get('goal_s', 0):g} s goal; {duplicates} tasks done twice)"
        )
    scalars = [
        f"{key} {value:g}" if isinstance(value, float) else f"{key} {value}"
        for key, value in sorted(report.items())
        if isinstance(value, (int, float, bool)) and key not in ("wall_seconds",)
    ]
    return "; ".join(scalars[:6]) or "see the file"


def benchmark_table(results: Path = RESULTS) -> str:
    out = [
        "| result | figures | date | commit | CPU | cores |",
        "|---|---|---|---|---|---|",
    ]
    missing_any = False
    for path in sorted(results.glob("*.json")):
        report = json.loads(path.read_text(encoding="utf-8"))
        cells = []
        for keys in (
            ("date", "measured_at"),
            ("commit", "git_commit"),
            ("cpu", "cpu_model"),
            ("cores", "cpus_allowed", "cpus"),
        ):
            value = _find(report, *keys)
            missing_any |= value is None
            cells.append("*missing*" if value is None else _cell(value))
        link = f"../{path.relative_to(ROOT).as_posix()}" if path.is_relative_to(ROOT) else path.name
        out.append(f"| [`{path.name}`]({link}) | {_cell(_headline(report))} | " + " | ".join(cells) + " |")
    if len(out) == 2:
        out.append("| (no result files) | | | | | |")
    if missing_any:
        out += ["", "*missing*: the result file does not record it; run the benchmark again to have it recorded."]
    return "\n".join(out)


def benchmarks_page(current: str) -> str:
    """docs/benchmarks.md with the table between its markers replaced."""
    head, _, rest = current.partition(BEGIN)
    _, _, tail = rest.partition(END)
    if not rest:
        raise ValueError(f"docs/benchmarks.md has no {BEGIN!r} marker")
    return f"{head}{BEGIN}\n{benchmark_table()}\n{END}{tail}"


# --- the files -------------------------------------------------------------------------------


def generated() -> dict[Path, str]:
    """Each generated file's path and the text it must hold."""
    benchmarks = DOCS / "benchmarks.md"
    return {
        DOCS / "configuration.md": configuration_reference() + "\n",
        DOCS / "rest-api.md": rest_reference().rstrip("\n") + "\n",
        benchmarks: benchmarks_page(benchmarks.read_text(encoding="utf-8")),
    }


def stale() -> list[Path]:
    """The generated files whose text differs from what the code gives now."""
    return [path for path, text in generated().items() if not path.is_file() or path.read_text("utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a generated file is stale; write nothing")
    args = parser.parse_args(argv)
    if args.check:
        paths = stale()
        for path in paths:
            print(f"stale: {path.relative_to(ROOT)} (run: python docs/generate.py)", file=sys.stderr)
        return 1 if paths else 0
    for path, text in generated().items():
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
