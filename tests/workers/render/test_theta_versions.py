"""θ is a versioned record: a θ stored before version 2 still renders to the same bytes.

``data/theta_v1_renders.json`` holds 44 version-1 θ (canonical and every Table 3 condition at
every difficulty, 64 px) with the SHA-256 of the image, the box, the amodal box and the visible
fraction that the renderer of version 1 (commit 6d215e5) produced for them.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from foldwise.theta import THETA_VERSION, V1_DEFAULTS, Theta
from workers.render.pipeline import render_theta

CASES = json.loads((Path(__file__).parent / "data" / "theta_v1_renders.json").read_text())


def test_the_cases_cover_every_table_3_condition_at_every_difficulty():
    seen = {(c["theta"]["condition"], c["theta"]["difficulty"]) for c in CASES}
    assert {d for _, d in seen} == {"canonical", "easy", "medium", "hard"}
    assert {c for c, d in seen if d != "canonical"} == {"fb", "mb", "po", "de", "eo", "sc", "li"}
    assert all("version" not in c["theta"] or c["theta"]["version"] == 1 for c in CASES)


@pytest.mark.parametrize(
    "case", CASES, ids=[f"{c['theta']['condition']}-{c['theta']['difficulty']}-{i}" for i, c in enumerate(CASES)]
)
def test_a_version_1_theta_renders_to_the_same_bytes_and_boxes(case):
    result = render_theta(case["theta"])
    assert hashlib.sha256(result.image.tobytes()).hexdigest() == case["sha256"]
    assert result.box == case["box"] and result.amodal_box == case["amodal_box"]
    assert result.visible_fraction == case["visible_fraction"]


def test_reading_a_version_1_theta_fills_in_what_version_1_rendered_with():
    stored = CASES[0]["theta"]
    theta = Theta.parse(stored)
    assert theta.version == THETA_VERSION
    assert all(getattr(theta, name) == value for name, value in V1_DEFAULTS.items())
    assert all(getattr(theta, key) == value for key, value in stored.items() if key != "version")
    # Written back, it is a version-2 record that reads to the same θ.
    assert Theta.parse(theta.to_dict()) == theta


def test_an_unknown_version_or_a_bad_value_is_named():
    stored = dict(CASES[0]["theta"])
    with pytest.raises(ValueError, match="θ.version: 7 is not a θ version"):
        Theta.parse({**stored, "version": 7})
    with pytest.raises(ValueError, match="θ.scale"):
        Theta.parse({**stored, "scale": -1.0})
    with pytest.raises(ValueError, match="θ.image_size"):
        Theta.parse({**stored, "image_size": "128"})
    with pytest.raises(ValueError, match="θ.wobble: unknown key"):
        Theta.parse({**Theta.parse(stored).to_dict(), "wobble": 1})
    with pytest.raises(ValueError, match="θ.instances"):
        Theta.parse({**Theta.parse(stored).to_dict(), "instances": True})
