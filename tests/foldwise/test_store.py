"""foldwise.store: a file written atomically is whole or absent, and what a killed writer leaves
is recognised as an unfinished write of that file."""

from __future__ import annotations

import os

import pytest

from foldwise import store


def test_a_killed_writers_temporary_file_names_the_file_it_was_to_become(tmp_path, monkeypatch):
    target = tmp_path / "images" / "77.png"
    left_behind = []

    def killed(source, destination):  # the process dies before the rename: the file stays
        left_behind.append(os.path.basename(source))
        raise SystemExit

    monkeypatch.setattr(store.os, "replace", killed)
    monkeypatch.setattr(store.Path, "unlink", lambda self, missing_ok=False: None)
    with pytest.raises(SystemExit):
        store.atomic_write_bytes(target, b"png")
    (name,) = left_behind
    assert (target.parent / name).is_file() and not target.exists()
    assert store.unfinished_write_target(name) == "77.png"


@pytest.mark.parametrize("name", ["77.png", ".hidden", "x.tmp", ".tmp", "..tmp", ".77.tmp"])
def test_other_names_are_not_unfinished_writes(name):
    assert store.unfinished_write_target(name) is None


def test_a_finished_write_leaves_only_the_file(tmp_path):
    target = tmp_path / "7.png"
    store.atomic_write_bytes(target, b"abc")
    assert target.read_bytes() == b"abc" and os.listdir(tmp_path) == ["7.png"]
