"""Bad input is a 4xx naming the problem, never a 500, and it records nothing.

Run against SQLite (always) and PostgreSQL (where one listens on loopback), since the two
databases fail differently on the same input: PostgreSQL refuses NUL in text and ids past its
32-bit INTEGER with errors, where SQLite stores or finds nothing.
"""

from __future__ import annotations

import os
import shutil
import socket

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from db.migrate import upgrade
from db.models import Experiment
from db.session import get_sessionmaker, reset_engines
from foldwise.settings import get_settings
from services.api.app import create_app

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def _closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path, monkeypatch):
    # A copy of a database migrated once per session (a migration per test cost ~0.15 s of each
    # of these tests); upgrade() finds the copy at head.
    if request.param == "sqlite":
        shutil.copy(request.getfixturevalue("migrated_sqlite_template"), tmp_path / "api.db")
        url = f"sqlite:///{tmp_path / 'api.db'}"
    else:
        url = request.getfixturevalue("migrated_postgres_url")
    upgrade(url)
    monkeypatch.setenv("FOLDWISE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("FOLDWISE_DATABASE_URL", url)
    monkeypatch.setenv("FOLDWISE_BROKER_URL", f"redis://127.0.0.1:{_closed_port()}/0")
    monkeypatch.setenv("FOLDWISE_API_TOKEN", TOKEN)
    monkeypatch.setenv("FOLDWISE_ASSET_ROOTS", os.pathsep.join(["/nonexistent", str(tmp_path / "assets")]))
    get_settings.cache_clear()
    reset_engines()
    yield url
    reset_engines()
    get_settings.cache_clear()


@pytest.fixture
def client(database_url) -> TestClient:
    return TestClient(create_app(broker_timeout_s=0.3, ping_timeout_s=0.2))


def _experiments(url: str) -> int:
    with get_sessionmaker(url)() as session:
        return session.scalar(select(func.count()).select_from(Experiment))


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("get", "/experiments/{id}"),
        ("get", "/experiments/{id}/stages"),
        ("get", "/experiments/{id}/history"),
        ("get", "/experiments/{id}/config"),
        ("get", "/models/{id}"),
        ("post", "/experiments/{id}/cancel"),
    ],
)
@pytest.mark.parametrize("bad_id", [2**31 - 1, 2**31, 2**63, 0])
def test_an_id_that_names_no_row_is_404(client, method, path, bad_id):
    response = getattr(client, method)(path.format(id=bad_id), headers=AUTH)
    assert response.status_code == 404, response.text
    assert "does not exist" in response.json()["detail"]


@pytest.mark.parametrize(
    ("body", "status", "named"),
    [
        ({"name": "nul\x00here"}, 422, "name: control character '\\x00'"),
        ({"name": "bell\x07"}, 422, "name: control character"),
        ({"name": "x", "assets": {"objects": "/srv/a\x00b"}}, 422, "assets.objects: control character"),
        ({"name": "x", "active_learning": {"m": True}}, 422, "active_learning.m: expected a number, got a boolean"),
        (
            {"name": "x", "active_learning": {"m": 10**9}},
            422,
            "active_learning.m: Input should be less than or equal to 100000",
        ),
        ({"name": "x", "active_learning": {"t": 10**9}}, 422, "active_learning.t"),
        ({"name": "x", "active_learning": {"max_increments": 10**9}}, 422, "active_learning.max_increments"),
        ({"name": "x", "test_set": {"per_stage": 10**9}}, 422, "test_set.per_stage"),
        ({"name": "x", "seed": 2**63}, 422, "seed"),
        ({"name": "x", "render": {"image_size": 10**6}}, 422, "render.image_size"),
        ({"name": "x", "evaluation": {"batch_size": 10**9}}, 422, "evaluation.batch_size"),
        (
            {"name": "x", "curriculum": {"mixed": {"active_learning": {"m": False}}}},
            422,
            "curriculum.mixed.active_learning.m",
        ),
        # An asset folder the server does not have: it was a 201, then a scheduler error on every pass.
        (
            {"name": "x", "assets": {"backgrounds": "/nonexistent/foldwise"}},
            422,
            "assets.backgrounds: folder '/nonexistent/foldwise' does not exist",
        ),
    ],
)
def test_a_bad_config_is_422_naming_the_key_and_records_nothing(client, database_url, body, status, named):
    response = client.post("/experiments", json=body, headers=AUTH)
    assert response.status_code == status, response.text
    assert named in response.json()["detail"]
    assert _experiments(database_url) == 0


DEEP = 10_000


@pytest.mark.parametrize(
    ("content_type", "body", "named"),
    [
        (
            "application/json",
            '{"name": "x", "active_learning": {"m": "50"}}',
            "active_learning.m: expected a number, got the text '50'",
        ),
        (
            "application/json",
            '{"name": "x", "active_learning": {"m": 50.0}}',
            "active_learning.m: expected a whole number, got 50.0",
        ),
        ("application/json", '{"name": "x", "name": "y"}', "duplicate key 'name'"),
        ("application/json", '{"name": "x", "a": ' + "[" * DEEP + "]" * DEEP + "}", "nested deeper than 32 levels"),
        (
            "application/json",
            '{"name": "x", "a": ' + '{"b": ' * DEEP + "1" + "}" * DEEP + "}",
            "nested deeper than 32 levels",
        ),
        ("application/json", '{"name": "x", "a": ' + "[" * 500 + "]" * 500 + "}", "nested deeper than 32 levels"),
        ("application/yaml", "name: x\na: " + "[" * DEEP + "]" * DEEP, "nested deeper than 32 levels (line 2"),
        ("application/yaml", "name: x\na: " + "{b: " * DEEP + "1" + "}" * DEEP, "nested deeper than 32 levels (line 2"),
        ("application/yaml", "name: x\nactive_learning:\n  m: 5\n  m: 6\n", "duplicate key 'm' (line 4, column 3)"),
        ("application/yaml", "name: x\nactive_learning: {m: '50'}\n", "active_learning.m: expected a number"),
        (
            "application/yaml",
            "name: x\ncurriculum: &c {conditions: [*c]}\n",
            "refers to the mapping or list that contains it",
        ),
        # Half a UTF-16 pair: no file system takes it (the asset-root check raised: 500).
        (
            "application/json",
            '{"name": "x", "assets": {"objects": "/srv/\\ud800"}}',
            "assets.objects: text is not valid Unicode (lone surrogate '\\ud800')",
        ),
        ("application/json", '{"name": "\\udfff"}', "name: "),
        # pydantic took !!binary bytes as text: a NUL name, 201 on SQLite and a 500 on PostgreSQL.
        ("application/yaml", "name: !!binary AA==\n", "!!binary data has no place in a config (line 1, column 7)"),
        (
            "application/yaml",
            "name: x\nseed: " + "1" * 5000 + "\n",
            "a whole number of 5,000 characters (line 2, column 7)",
        ),
    ],
    ids=lambda value: value[:40] if isinstance(value, str) else value,
)
def test_a_bad_document_is_422_on_one_line_and_records_nothing(client, database_url, content_type, body, named):
    response = client.post("/experiments", content=body.encode(), headers={**AUTH, "Content-Type": content_type})
    assert response.status_code == 422, response.text[:300]
    assert named in response.json()["detail"]
    assert _experiments(database_url) == 0


def test_yaml_floats_without_a_dot_are_floats(client):
    body = "name: small steps\ndetector: {learning_rate: 1e-3, weight_decay: 5e-4}\n"
    created = client.post("/experiments", content=body, headers={**AUTH, "Content-Type": "application/yaml"})
    assert created.status_code == 201, created.text
    detector = client.get(f"/experiments/{created.json()['id']}/config").json()["detector"]
    assert (detector["learning_rate"], detector["weight_decay"]) == (0.001, 0.0005)


def test_bad_posts_leave_the_database_usable(client, database_url):
    # On PostgreSQL a NUL reaching the INSERT aborted the transaction with a 500.
    for name in ("a\x00", "line\nbreak", "tab\there"):
        assert client.post("/experiments", json={"name": name}, headers=AUTH).status_code == 422, repr(name)
    created = client.post("/experiments", json={"name": "plain name"}, headers=AUTH)
    assert created.status_code == 201
    assert client.get(f"/experiments/{created.json()['id']}").json()["name"] == "plain name"
    assert _experiments(database_url) == 1


def _folder_of_pngs(folder, side=32):
    import cv2
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / "a.png"), np.full((side, side, 3), 128, np.uint8))
    return folder


def test_asset_folders_only_under_the_servers_roots(client, database_url, tmp_path):
    inside = _folder_of_pngs(tmp_path / "assets" / "backgrounds")
    outside = _folder_of_pngs(tmp_path / "elsewhere")
    escape = tmp_path / "assets" / "link"
    escape.symlink_to(outside, target_is_directory=True)
    for folder in (outside, escape):
        response = client.post("/experiments", json={"name": "x", "assets": {"backgrounds": str(folder)}}, headers=AUTH)
        assert response.status_code == 422 and "outside the asset roots of this server" in response.json()["detail"]
    assert _experiments(database_url) == 0
    created = client.post("/experiments", json={"name": "x", "assets": {"backgrounds": str(inside)}}, headers=AUTH)
    assert created.status_code == 201, created.text


def test_without_asset_roots_the_api_takes_no_asset_folder(database_url, monkeypatch, tmp_path):
    monkeypatch.delenv("FOLDWISE_ASSET_ROOTS")
    get_settings.cache_clear()
    client = TestClient(create_app(broker_timeout_s=0.3, ping_timeout_s=0.2))
    folder = _folder_of_pngs(tmp_path / "assets" / "backgrounds")
    response = client.post("/experiments", json={"name": "x", "assets": {"backgrounds": str(folder)}}, headers=AUTH)
    assert response.status_code == 422
    assert response.json()["detail"] == (
        "assets.backgrounds: this server takes asset folders only under FOLDWISE_ASSET_ROOTS, which is not set; "
        "or upload the images with POST /assets/backgrounds"
    )
    assert client.post("/experiments", json={"name": "defaults need no folder"}, headers=AUTH).status_code == 201


# --------------------------------------------------------------------------- the sweep
# Every route's numbers and names, each sent every kind of bad value: ?stage= and ?k= past
# 2**31 - 1 overflow PostgreSQL's integers, and past 2**63 - 1 SQLite's.

OUT_OF_RANGE = ["2147483648", "9223372036854775808", "99999999999999999999999", "-1", "0"]
NOT_INTEGERS = ["abc", "1.5", "1e3", "0x10", "%00", "1%00", "%0A", "nan"]
BAD_TEXT = ["%00", "a%00b", "%07", "%0A", "%7F", "", "x" * 201]

# Path ids: a whole number outside the ids' range names no row (404); anything else is 422.
ID_ROUTES = [
    ("get", "/experiments/{value}"),
    ("get", "/experiments/{value}/config"),
    ("get", "/experiments/{value}/stages"),
    ("get", "/experiments/{value}/history"),
    ("post", "/experiments/{value}/cancel"),
    ("get", "/experiments/{value}/images"),
    ("get", "/experiments/{value}/coco"),
    ("get", "/experiments/{value}/report.png"),
    ("get", "/experiments/{value}/figures/fig4.png"),
    ("get", "/experiments/{value}/learnability"),
    ("get", "/experiments/{value}/table2"),
    ("get", "/experiments/{experiment}/images/{value}.png"),
    ("get", "/models/{value}"),
    ("get", "/models/{value}/checkpoint"),
    ("post", "/models/{value}/detect"),
    ("get", "/?experiment={value}"),  # the dashboard: an id in a query, answered like one in a path
]

# Query and path parameters other than ids: every bad value is a 422 naming the parameter.
# (method, route, the parameter as FastAPI names it in the error, bad values)
PARAMETERS = [
    ("get", "/experiments/{experiment}/images?stage={value}", "stage", ["-1", *OUT_OF_RANGE[:3], *NOT_INTEGERS]),
    ("get", "/experiments/{experiment}/images?k={value}", "k", OUT_OF_RANGE + NOT_INTEGERS),
    ("get", "/experiments/{experiment}/images?stage=0&k={value}", "k", OUT_OF_RANGE + NOT_INTEGERS),
    ("get", "/experiments/{experiment}/images?stage={value}&k=1", "stage", ["-1", *OUT_OF_RANGE[:3], *NOT_INTEGERS]),
    ("get", "/experiments/{experiment}/images?limit={value}", "limit", ["1001", *OUT_OF_RANGE, *NOT_INTEGERS]),
    ("get", "/experiments/{experiment}/images?split={value}", "split", ["validation", "%00", "", "1"]),
    ("get", "/experiments/{experiment}/coco?split={value}", "split", ["validation", "%00", "", "1"]),
    ("get", "/experiments/{experiment}/report.{value}", "extension", ["pdf", "png%00", "png%0A"]),
    ("get", "/experiments/{experiment}/figures/{value}.png", "name", ["fig1", "fig4%00", "fig40"]),
    ("get", "/experiments/{experiment}/figures/fig4.{value}", "extension", ["gif", "svg%00"]),
    ("get", "/experiments?status={value}", "status", ["done", "%00", "", "1"]),
    ("get", "/experiments?study={value}", "study", BAD_TEXT),
    ("post", "/experiments?study={value}", "study", BAD_TEXT),
    ("post", "/models/1/detect?threshold={value}", "threshold", ["1.5", "-0.1", "nan", "inf", "abc", "%00", "1e9"]),
]
PNG_HEADER = b"\x89PNG\r\n\x1a\n" + b"\x00" * 16


@pytest.fixture
def sweep_client(database_url):
    """A client that answers a server error with its 500 (and body) instead of raising."""
    return TestClient(create_app(broker_timeout_s=0.3, ping_timeout_s=0.2), raise_server_exceptions=False)


def _send(client, method: str, path: str):
    if "/detect" in path:
        return client.post(path, content=PNG_HEADER, headers={**AUTH, "Content-Type": "image/png"})
    if method == "post" and path.startswith("/experiments?"):
        return client.post(path, json={"name": "in a study"}, headers=AUTH)
    return getattr(client, method)(path, headers=AUTH)


def _wrong(response, status: int, named: str) -> str | None:
    """Why ``response`` is not a clean ``status`` naming ``named`` (None when it is)."""
    if response.status_code != status:
        return f"{response.status_code} (want {status}): {response.text[:200]}"
    detail = response.json()["detail"]
    text = str(detail)
    if "Traceback" in text or named not in text:
        return f"{status} but the detail does not name {named!r}: {text[:200]}"
    return None


def _existing_experiment(client) -> int:
    created = client.post("/experiments", json={"name": "target"}, headers=AUTH)
    assert created.status_code == 201, created.text
    return created.json()["id"]


@pytest.mark.parametrize(("method", "route"), ID_ROUTES, ids=[f"{m} {r}" for m, r in ID_ROUTES])
def test_every_id_route_refuses_every_bad_id(sweep_client, method, route):
    experiment = _existing_experiment(sweep_client)
    wrong = {}
    for value in OUT_OF_RANGE:
        response = _send(sweep_client, method, route.format(experiment=experiment, value=value))
        wrong[value] = _wrong(response, 404, "does not exist")
    for value in NOT_INTEGERS:
        response = _send(sweep_client, method, route.format(experiment=experiment, value=value))
        wrong[value] = _wrong(response, 422, "integer")
    assert {value: why for value, why in wrong.items() if why} == {}


@pytest.mark.parametrize(
    ("method", "route", "parameter", "values"), PARAMETERS, ids=[f"{m} {r}" for m, r, _, _ in PARAMETERS]
)
def test_every_parameter_refuses_every_bad_value_naming_it(
    sweep_client, database_url, method, route, parameter, values
):
    experiment = _existing_experiment(sweep_client)
    wrong = {}
    for value in values:
        response = _send(sweep_client, method, route.format(experiment=experiment, value=value))
        wrong[value] = _wrong(response, 422, f"'{parameter}'")
    assert {value: why for value, why in wrong.items() if why} == {}
    assert _experiments(database_url) == 1  # only the target: a refused POST records nothing


def test_stage_and_k_at_the_column_limit_are_an_empty_page(sweep_client):
    # The largest value the columns hold is a valid filter that matches nothing, on both databases.
    experiment = _existing_experiment(sweep_client)
    response = sweep_client.get(f"/experiments/{experiment}/images?stage=2147483647&k=2147483647")
    assert response.status_code == 200, response.text
    assert response.json()["images"] == []


def test_a_misnamed_or_clashing_object_image_is_422_naming_the_files(client, database_url, tmp_path):
    from PIL import Image

    objects = tmp_path / "assets" / "objects"
    objects.mkdir(parents=True)
    Image.new("RGB", (32, 32), (9, 9, 9)).save(objects / "flag.png", format="GIF")
    response = client.post("/experiments", json={"name": "x", "assets": {"objects": str(objects)}}, headers=AUTH)
    assert response.status_code == 422
    assert (
        response.json()["detail"]
        == f"assets.objects: '{objects / 'flag.png'}' holds a GIF image, not PNG as its name says"
    )
    (objects / "flag.png").unlink()
    _folder_of_pngs(objects)
    Image.new("RGB", (32, 32), (9, 9, 9)).save(objects / "a.jpg", format="JPEG")
    response = client.post("/experiments", json={"name": "x", "assets": {"objects": str(objects)}}, headers=AUTH)
    assert response.status_code == 422
    assert f"'{objects / 'a.jpg'}' and '{objects / 'a.png'}' both name the class 'a'" in response.json()["detail"]
    assert _experiments(database_url) == 0


# Every number of the config schema, each sent every kind of bad value (as JSON, and the
# unbounded integers as YAML too, whose loader reads them itself).
BAD_NUMBERS = [2**31, 2**63, -(2**63) - 1, 10**400, 1e308, -1e308, "7", True, [], {}]


def _nested(key: str, value) -> dict:
    *sections, name = key.split(".")
    body: dict = {name: value}
    for section in reversed(sections):
        body = {section: body}
    return {"name": "x", **body}


def test_every_number_in_the_config_refuses_every_bad_value(client, database_url):
    from tests.foldwise.config_fields import NUMERIC_FIELDS

    wrong = {}
    for key in NUMERIC_FIELDS:
        values = [
            [v, v]
            if key.endswith(("conditions_per_image", "anchor_size_range"))
            else [v]
            if key.endswith("_sizes")
            else v
            for v in BAD_NUMBERS
        ]
        for value in values:
            response = client.post("/experiments", json=_nested(key, value), headers=AUTH)
            if response.status_code != 422 or key not in response.json()["detail"]:
                wrong[f"{key}={str(value)[:20]}"] = f"{response.status_code}: {response.text[:150]}"
    for yaml_body in ("name: x\nseed: " + "1" * 5000, "name: x\nactive_learning: {m: " + "9" * 30 + "}"):
        response = client.post("/experiments", content=yaml_body, headers={**AUTH, "Content-Type": "application/yaml"})
        if response.status_code != 422:
            wrong[yaml_body[:40]] = f"{response.status_code}: {response.text[:150]}"
    assert wrong == {}
    assert _experiments(database_url) == 0


READS_OF_AN_EXPERIMENT = [
    "/experiments/{id}", "/experiments/{id}/config", "/experiments/{id}/stages", "/experiments/{id}/history",
    "/experiments/{id}/images", "/experiments/{id}/images?split=test", "/experiments/{id}/coco?split=train",
    "/experiments/{id}/coco", "/experiments/{id}/report.png", "/experiments/{id}/report.csv", "/?experiment={id}",
    *[f"/experiments/{{id}}/figures/fig{n}.{extension}" for n in range(4, 9) for extension in ("png", "svg", "csv")],
]  # fmt: skip


def test_every_read_of_an_experiment_that_has_not_started_answers(sweep_client):
    # Fig. 4 of an experiment without stages was a matplotlib ValueError: a 500.
    experiment = _existing_experiment(sweep_client)
    answers = {route: sweep_client.get(route.format(id=experiment)).status_code for route in READS_OF_AN_EXPERIMENT}
    assert {route: code for route, code in answers.items() if code != 200} == {}


def test_an_imagenet_run_without_the_weights_is_a_422_naming_the_file_and_records_nothing(
    client, database_url, tmp_path, monkeypatch
):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    body = {"name": "imagenet", "detector": {"pretrained": "imagenet"}}
    refused = client.post("/experiments", json=body, headers=AUTH)
    assert refused.status_code == 422 and "mobilenet_v3_large-8738ca79.pth" in refused.json()["detail"]
    assert _experiments(database_url) == 0
    weights = tmp_path / "torch/hub/checkpoints/mobilenet_v3_large-8738ca79.pth"
    weights.parent.mkdir(parents=True)
    weights.write_bytes(b"")  # only its presence is checked here; the train worker reads it
    assert client.post("/experiments", json=body, headers=AUTH).status_code == 201
