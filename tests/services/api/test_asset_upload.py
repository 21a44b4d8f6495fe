"""POST /assets/{kind}: one's own object images uploaded into the artifact store, content-hashed,
checked on arrival like any asset folder, and usable in a config without FOLDWISE_ASSET_ROOTS."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest

from foldwise import store
from tests.services.api.helpers import AUTH, experiment_count


def _png(side: int = 32, value: int = 128) -> bytes:
    ok, encoded = cv2.imencode(".png", np.full((side, side, 3), value, np.uint8))
    assert ok
    return encoded.tobytes()


def _gif() -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.new("RGB", (32, 32), (10, 20, 30)).save(buffer, format="GIF")
    return buffer.getvalue()


def _upload(client, kind: str, files: dict[str, bytes], headers=AUTH):
    return client.post(
        f"/assets/{kind}", files=[("files", (name, payload)) for name, payload in files.items()], headers=headers
    )


def _leftovers() -> list[str]:
    root = store.uploaded_assets_root()
    return sorted(p.name for p in root.iterdir()) if root.exists() else []


def test_an_uploaded_object_folder_is_kept_by_content_and_a_config_may_name_it(client, database_url, monkeypatch):
    monkeypatch.delenv("FOLDWISE_ASSET_ROOTS", raising=False)  # no folder of the server is allowed: only uploads
    files = {"poster.png": _png(value=90), "mug.png": _png(value=200)}
    first = _upload(client, "objects", files)
    assert first.status_code == 201, first.text
    body = first.json()
    folder = store.uploaded_assets_root() / f"objects-{body['sha256'][:16]}"
    assert body["folder"] == str(folder) and body["kind"] == "objects"
    assert [f["name"] for f in body["files"]] == ["mug.png", "poster.png"]
    assert (folder / "poster.png").read_bytes() == files["poster.png"]
    again = _upload(client, "objects", dict(reversed(files.items())))
    assert again.status_code == 201 and again.json()["folder"] == body["folder"]  # same content, same folder
    other = _upload(client, "objects", {"poster.png": _png(value=91), "mug.png": files["mug.png"]})
    assert other.json()["folder"] != body["folder"]
    assert _leftovers() == sorted([folder.name, other.json()["folder"].rsplit("/", 1)[1]])  # no staging folder left

    created = client.post("/experiments", json={"name": "mine", "assets": {"objects": body["folder"]}}, headers=AUTH)
    assert created.status_code == 201, created.text
    assert client.get(f"/experiments/{created.json()['id']}/config").json()["assets"]["objects"] == body["folder"]


@pytest.mark.parametrize(
    ("kind", "files", "code", "says"),
    [
        ("objects", {"poster.png": _gif()}, 422, "holds a GIF image, not PNG"),
        ("objects", {"poster.png": b"\x89PNG\r\n\x1a\n not really"}, 422, "'poster.png' is not a readable image"),
        ("backgrounds", {"tiny.png": _png(side=4)}, 422, "'tiny.png' is 4x4 pixels"),
        (
            "objects",
            {"mug.png": _png(), "mug.jpg": cv2.imencode(".jpg", np.zeros((32, 32, 3), np.uint8))[1].tobytes()},
            422,
            "both name the class 'mug'",
        ),
        ("objects", {"../escape.png": _png()}, 422, "no folders"),
        ("objects", {".hidden.png": _png()}, 422, "starting with a letter or digit"),
        ("objects", {"notes.txt": b"hello"}, 422, "not an image name"),
        ("objects", {"a\x01.png": _png()}, 422, "file name"),
        ("textures", {"a.png": _png()}, 422, "objects"),  # an unknown kind: the error lists the known ones
    ],
)
def test_a_bad_upload_is_a_4xx_that_names_the_file_and_keeps_nothing(client, database_url, kind, files, code, says):
    response = _upload(client, kind, files)
    assert response.status_code == code, response.text
    assert says in str(response.json()["detail"])
    assert "upload-" not in str(response.json()["detail"])  # the staging folder is not the client's business
    assert _leftovers() == []


def test_an_upload_needs_the_token_and_at_least_one_file(client, database_url):
    assert _upload(client, "objects", {"a.png": _png()}, headers={}).status_code == 401
    assert client.post("/assets/objects", headers=AUTH).status_code == 422
    assert _leftovers() == [] and experiment_count(database_url) == 0


def test_a_file_over_the_size_bound_is_a_413(client, database_url, monkeypatch):
    from services.api.routes import assets

    monkeypatch.setattr(assets, "MAX_FILE_BYTES", 1000)
    response = _upload(client, "backgrounds", {"big.png": _png(side=64) + b"\0" * 2000})
    assert response.status_code == 413 and "'big.png' is larger than" in response.json()["detail"]
    assert _leftovers() == []
