"""foldwise.documents: YAML read strictly and cheaply, whatever the document."""

from __future__ import annotations

import time

import pytest

from foldwise.documents import MAX_ALIASES, MAX_NODES, DocumentError, check_nesting, load_yaml


def test_a_merge_key_is_refused_naming_where_it_is():
    with pytest.raises(DocumentError, match=r"YAML merge keys \(<<\) are not accepted.*\(line 2, column 5\)"):
        load_yaml("base: &base {a: 1}\nb: {<<: *base, c: 2}\n")


def test_the_merge_key_bomb_is_refused_in_milliseconds():
    lines = ["b0: &b0 {k0: 1}"] + [f"b{n}: &b{n} {{<<: [*b{n - 1}, *b{n - 1}], k{n}: 1}}" for n in range(1, 40)]
    started = time.perf_counter()
    with pytest.raises(DocumentError, match="merge keys"):
        load_yaml("\n".join(lines))
    assert time.perf_counter() - started < 0.5


def test_aliases_are_bounded_in_number_and_in_what_they_expand_to():
    assert load_yaml("a: &a [1, 2]\nb: *a\n") == {"a": [1, 2], "b": [1, 2]}
    with pytest.raises(DocumentError, match=f"more than {MAX_ALIASES} aliases"):
        load_yaml("a: &a 1\n" + "".join(f"b{i}: *a\n" for i in range(MAX_ALIASES + 1)))
    laughs = "a: &a [1,1,1,1,1,1,1,1,1,1]\n" + "".join(
        f"{c}: &{c} [" + ",".join([f"*{p}"] * 10) + "]\n" for p, c in zip("abcde", "bcdef")
    )
    with pytest.raises(DocumentError, match=f"more than {MAX_NODES:,} values"):
        load_yaml(laughs)


def test_a_huge_document_stops_at_the_bound_without_reading_the_rest():
    document = "[" + ", ".join(["1"] * 400_000) + "]"
    started = time.perf_counter()
    with pytest.raises(DocumentError, match=rf"more than {MAX_NODES:,} values \(line 1, column"):
        load_yaml(document)
    assert time.perf_counter() - started < 3.0  # the whole document would take tens of seconds


def test_check_nesting_counts_json_data_and_shared_structures():
    check_nesting({"a": [1] * (MAX_NODES // 2)})
    with pytest.raises(DocumentError, match="values"):
        check_nesting({"a": [1] * (MAX_NODES + 1)})
    shared = [1] * 100
    with pytest.raises(DocumentError, match="values"):
        check_nesting([shared] * 100)  # 100 objects in memory, 10,000 values to whoever walks it
