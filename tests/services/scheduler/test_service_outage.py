"""The scheduler's loop outlives a database that restarts: a pass that cannot read the live
experiments is skipped, and the next one goes on."""

from __future__ import annotations

import logging

from sqlalchemy.exc import OperationalError

from services.scheduler import service


def test_a_pass_without_the_database_is_skipped_not_the_scheduler_s_end(monkeypatch, caplog):
    passes = []

    def database_restarting():
        passes.append("read")
        if len(passes) == 1:
            raise OperationalError("SELECT experiments.id", {}, Exception("the database system is starting up"))
        return [7]

    reconciled = []
    monkeypatch.setattr(service, "live_experiment_ids", database_restarting)
    monkeypatch.setattr(service, "reconcile_until_idle", lambda experiment_id, **_: reconciled.append(experiment_id))
    monkeypatch.setattr(service.signal, "signal", lambda *args: None)  # leave pytest's handlers alone
    with caplog.at_level(logging.WARNING, logger=service.__name__):
        service.serve(poll_s=0, once=True)  # the pass the outage hits
        service.serve(poll_s=0, once=True)  # the next one
    assert passes == ["read", "read"] and reconciled == [7]
    assert "cannot read the live experiments; retrying next pass" in caplog.text
    assert "starting up" in caplog.text
