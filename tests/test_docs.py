"""The generated parts of docs/ match the code (docs/generate.py): a stale reference fails here."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _current(name: str) -> str:
    return (ROOT / "docs" / name).read_text(encoding="utf-8")


def test_configuration_reference_is_current() -> None:
    expected = _generator().configuration_reference() + "\n"
    assert _current("configuration.md") == expected, "docs/configuration.md is stale: run python docs/generate.py"


def test_rest_reference_is_current() -> None:
    """Regenerated from the app's OpenAPI now and compared, so a changed route fails here."""
    expected = _generator().rest_reference().rstrip("\n") + "\n"
    assert _current("rest-api.md") == expected, "docs/rest-api.md is stale: run python docs/generate.py"


def test_benchmark_table_is_current() -> None:
    generator = _generator()
    assert _current("benchmarks.md") == generator.benchmarks_page(_current("benchmarks.md")), (
        "docs/benchmarks.md's results table is stale: run python docs/generate.py"
    )


def test_configuration_reference_names_every_key() -> None:
    from foldwise.config import ExperimentConfig

    text = _current("configuration.md")
    for prefix, model in _generator()._sections(ExperimentConfig, ""):
        for name in model.model_fields:
            key = f"{prefix}.{name}" if prefix else name
            assert f"| `{key}` |" in text, key


def test_generation_is_deterministic() -> None:
    generator = _generator()
    assert generator.configuration_reference() == generator.configuration_reference()
    assert generator.rest_reference() == generator.rest_reference()


def test_benchmark_table_names_what_a_result_lacks(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_text(json.dumps({"benchmark": "x", "machine": {"cpu": "Some CPU", "cores": 2}}))
    (tmp_path / "b.json").write_text(
        json.dumps({"benchmark": "y", "date": "2026-01-02", "commit": "abc1234", "machine": {"cpu": "C", "cores": 4}})
    )
    table = _generator().benchmark_table(tmp_path)
    row_a, row_b = (line for line in table.splitlines() if line.startswith("| [`"))
    assert row_a.count("*missing*") == 2 and "Some CPU" in row_a
    assert "*missing*" not in row_b and "abc1234" in row_b and "2026-01-02" in row_b
