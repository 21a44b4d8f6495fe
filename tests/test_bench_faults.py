"""bench/faults.py without its servers: it runs with compose.yaml's defaults, refuses a fault it
does not know, and reports a fault as met only when it recovered within the goal."""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import faults  # noqa: E402


def test_the_settings_are_compose_defaults_and_the_services_own():
    """What the bench runs with is what compose.yaml's ``${NAME:-default}`` says, and what the
    services assume when nothing is set (foldwise/settings.py), not the tests' short lease."""
    from foldwise.settings import Settings

    settings = faults.compose_settings()
    text = (ROOT / "compose.yaml").read_text()
    for name, value in settings.items():
        (default,) = re.findall(rf"{name}: \$\{{{name}:-([^}}]+)\}}", text)
        assert value == default, name
    defaults = Settings.model_fields
    assert float(settings["FOLDWISE_LEASE_S"]) == defaults["lease_s"].default
    assert float(settings["FOLDWISE_SCHEDULER_POLL_S"]) == defaults["scheduler_poll_s"].default
    assert float(settings["FOLDWISE_REQUEUE_AFTER_S"]) == defaults["requeue_after_s"].default


def test_faults_are_parsed_in_order_and_an_unknown_one_is_refused():
    assert faults.parse_faults("redis, render-worker") == ["render-worker", "redis"]
    assert faults.parse_faults("train-worker-mid-write,postgres,disk-full,scheduler") == [
        "scheduler",
        "postgres",
        "disk-full",
        "train-worker-mid-write",
    ]
    with pytest.raises(argparse.ArgumentTypeError, match="unknown fault worker"):
        faults.parse_faults("redis,worker")
    with pytest.raises(argparse.ArgumentTypeError):
        faults.parse_faults(",")
    with pytest.raises(SystemExit):
        faults.main(["--faults", "scheduler,disk"])


def test_a_fault_is_met_only_within_the_goal_and_all_met_needs_a_clean_audit():
    def result(seconds, problems=()):
        return faults.fault_result(
            seconds, recovered_when="claimed again", finished=True, resends=3, duplicates=0, problems=list(problems)
        )

    assert result(31.2)["met"] and result(60.0)["met"]
    assert not result(60.5)["met"] and not result(None)["met"]
    entry = result(31.234)
    assert {"seconds_to_recovery", "goal_s", "met", "resends", "finished", "duplicates"} <= entry.keys()
    assert entry["seconds_to_recovery"] == 31.23 and entry["goal_s"] == 60.0

    settings, machine = faults.compose_settings(), {"cpus_allowed": 2}
    assert faults.report({"redis": result(4.0), "scheduler": result(9.0)}, settings, machine)["all_met"]
    assert not faults.report({"redis": result(4.0), "scheduler": result(61.0)}, settings, machine)["all_met"]
    assert not faults.report({"redis": result(4.0, problems=["θ 7 sent 3 times"])}, settings, machine)["all_met"]
    assert not faults.report({}, settings, machine)["all_met"]
    document = faults.report({"redis": result(4.0)}, settings, machine)
    assert document["settings"] == settings and document["faults"]["redis"]["seconds_to_recovery"] == 4.0


def test_it_skips_saying_why_without_its_servers(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(faults, "missing_service", lambda: "PostgreSQL is not reachable on 127.0.0.1:5432")
    out = tmp_path / "faults.json"
    assert faults.main(["--out", str(out)]) == 0
    assert json.loads(out.read_text()) == {
        "benchmark": "faults",
        "skipped": True,
        "reason": "PostgreSQL is not reachable on 127.0.0.1:5432",
    }
    assert "skipped: PostgreSQL" in capsys.readouterr().err


def test_every_fault_is_a_harness_fault_the_tests_share():
    """Each name runs a function of tests/integration/fault_harness.py that takes the stack, the
    API client, the rows and the recovery timeout: the bench and the fault tests inject alike."""
    import inspect

    from tests.integration import fault_harness

    assert list(faults.FAULTS) == [
        "render-worker",
        "train-worker",
        "scheduler",
        "redis",
        "postgres",
        "disk-full",
        "train-worker-mid-write",
    ]
    for name, function in faults.FAULTS.items():
        parameters = inspect.signature(getattr(fault_harness, function)).parameters
        assert list(parameters)[:3] == ["stack", "api", "rows"], name
        assert "recovery_timeout_s" in parameters, name


def test_the_postgres_fault_says_why_when_it_cannot_start_a_server_of_its_own(monkeypatch, tmp_path, capsys):
    """The shared servers are there, PostgreSQL's server programs are not: that fault alone
    reports why (no server of the bench's own, no killing the shared one), and the run fails."""
    from tests.integration import fault_harness

    monkeypatch.setattr(faults, "missing_service", lambda: None)
    monkeypatch.setattr(faults, "machine_info", lambda: {"cpus_allowed": 2, "load_average_1min": 0.0})
    monkeypatch.setattr(fault_harness, "own_postgres_problem", lambda: "initdb is not installed")
    out = tmp_path / "faults.json"
    assert faults.main(["--faults", "postgres", "--out", str(out)]) == 1
    document = json.loads(out.read_text())
    assert list(document["faults"]) == ["postgres"] and not document["all_met"]
    (problem,) = document["faults"]["postgres"]["problems"]
    assert "cannot start a PostgreSQL server of the bench's own: initdb is not installed" in problem
    capsys.readouterr()
