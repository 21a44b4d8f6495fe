"""`make test` runs under pytest-xdist: tests go to a worker a module at a time, and every test of
tests/integration to one worker (they share one compose stack and hold Redis db 9 per session)."""

from __future__ import annotations

from pathlib import Path


def _root_conftest(pytestconfig):
    root = Path(__file__).resolve().parent / "conftest.py"
    return next(
        plugin for plugin in pytestconfig.pluginmanager.get_plugins() if getattr(plugin, "__file__", None) == str(root)
    )


def test_integration_tests_are_one_unit_and_every_other_module_its_own(pytestconfig):
    unit = _root_conftest(pytestconfig).xdist_unit
    assert (
        unit("tests/integration/test_distributed.py::test_a")
        == unit("tests/integration/test_faults.py::test_b[x::y]")
        == "tests/integration"
    )
    assert (
        unit("tests/workers/train/test_export.py::test_a[faster_rcnn]")
        == unit("tests/workers/train/test_export.py::test_b")
        == "tests/workers/train/test_export.py"
    )
    assert unit("tests/workers/train/test_training.py::test_a") != unit("tests/workers/train/test_export.py::test_a")
    assert (
        unit("tests/test_integration_notes.py::test_a") == "tests/test_integration_notes.py"
    )  # only the folder is one unit


def test_whole_runs_go_to_the_workers_first_then_the_units_of_most_tests(pytestconfig):
    weight = _root_conftest(pytestconfig).unit_weight
    units = {
        "tests/workers/train/test_evaluation.py": 60,
        "tests/test_bench_wild.py": 6,
        "tests/integration": 12,
        "tests/test_docs.py": 3,
    }
    order = sorted(units, key=lambda unit: weight(unit, units[unit]), reverse=True)
    assert order == [
        "tests/integration",
        "tests/test_bench_wild.py",
        "tests/workers/train/test_evaluation.py",
        "tests/test_docs.py",
    ]
