"""Bad input is a 4xx naming the problem, never a 500, and it records nothing.

Run against SQLite (always) and PostgreSQL (where one listens on loopback), since the two
databases fail differently on the same input: PostgreSQL refuses NUL in text and ids past its
32-bit INTEGER with errors, where SQLite stores or finds nothing.
"""

from __future__ import annotations

import os
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
    url = f"sqlite:///{tmp_path / 'api.db'}" if request.param == "sqlite" else request.getfixturevalue("postgres_url")
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
        ({"name": "x", "active_learning": {"m": 10**9}}, 422, "active_learning.m: Input should be less than or equal to 100000"),
        ({"name": "x", "active_learning": {"t": 10**9}}, 422, "active_learning.t"),
        ({"name": "x", "active_learning": {"max_increments": 10**9}}, 422, "active_learning.max_increments"),
        ({"name": "x", "test_set": {"per_stage": 10**9}}, 422, "test_set.per_stage"),
        ({"name": "x", "seed": 2**63}, 422, "seed"),
        ({"name": "x", "render": {"image_size": 10**6}}, 422, "render.image_size"),
        ({"name": "x", "evaluation": {"batch_size": 10**9}}, 422, "evaluation.batch_size"),
        ({"name": "x", "curriculum": {"mixed": {"active_learning": {"m": False}}}}, 422, "curriculum.mixed.active_learning.m"),
        # An asset folder the server does not have: it was a 201, then a scheduler error on every pass.
        ({"name": "x", "assets": {"backgrounds": "/nonexistent/foldwise"}}, 422,
         "assets.backgrounds: folder '/nonexistent/foldwise' does not exist"),
    ],
)
def test_a_bad_config_is_422_naming_the_key_and_records_nothing(client, database_url, body, status, named):
    response = client.post("/experiments", json=body, headers=AUTH)
    assert response.status_code == status, response.text
    assert named in response.json()["detail"]
    assert _experiments(database_url) == 0


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
    assert response.json()["detail"] == "assets.backgrounds: this server takes asset folders only under FOLDWISE_ASSET_ROOTS, which is not set"
    assert client.post("/experiments", json={"name": "defaults need no folder"}, headers=AUTH).status_code == 201
