"""User asset folders are checked before any work: each bad folder or file is one clear error."""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from foldwise.asset_check import MAX_PIXELS, AssetError, validate_assets
from foldwise.config import AssetsConfig

REPO_ROOT = Path(__file__).resolve().parents[2]


def _png(path: Path, width: int, height: int) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.random.default_rng(width * 7 + height).integers(0, 255, (height, width, 3), dtype=np.uint8)
    assert cv2.imwrite(str(path), image)
    return path


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_claiming(path: Path, width: int, height: int) -> Path:
    """A well-formed PNG header (valid CRCs) that claims width x height, with one row of data."""
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(b"\x00" * 64))
        + _chunk(b"IEND", b"")
    )
    return path


def _saved_as(path: Path, image_format: str, width: int = 32, height: int = 32) -> Path:
    """An image of ``image_format`` (Pillow's name) under whatever name ``path`` has."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.effect_noise((width, height), 60).convert("RGB").save(path, format=image_format)
    return path


def _truncated(path: Path) -> Path:
    path.write_bytes(path.read_bytes()[: path.stat().st_size * 6 // 10])
    return path


@pytest.fixture
def folders(tmp_path):
    objects = tmp_path / "objects"
    _png(objects / "poster.png", 64, 48)
    backgrounds = tmp_path / "backgrounds"
    _png(backgrounds / "wall.png", 40, 40)
    occluders = tmp_path / "occluders"
    _png(occluders / "leaf.png", 8, 8)
    return {"objects": objects, "backgrounds": backgrounds, "occluders": occluders}


def test_good_folders_and_the_defaults_pass(folders):
    validate_assets(None)
    validate_assets(AssetsConfig())
    validate_assets(AssetsConfig(**folders))


@pytest.mark.parametrize(
    ("what", "spoil", "message"),
    [
        ("objects", lambda d: d / "missing", "folder '{d}/missing' does not exist"),
        ("backgrounds", lambda d: _png(d / "x.png", 20, 20), "is not a folder"),
        ("occluders", lambda d: (d.mkdir(), d)[-1], "holds no images"),
        (
            "objects",
            lambda d: (d.mkdir(), (d / "notes.png").write_text("not an image"), d)[-1],
            "notes.png' is not a readable image",
        ),
        (
            "backgrounds",
            lambda d: (_png(d / "cut.png", 64, 64).write_bytes((d / "cut.png").read_bytes()[:90]), d)[-1],
            "cut.png' is not a readable image",
        ),
        (
            "backgrounds",
            lambda d: (_png(d / "dot.png", 1, 1), d)[-1],
            "dot.png' is 1x1 pixels; backgrounds need at least 16",
        ),
        (
            "occluders",
            lambda d: (_png(d / "speck.png", 7, 30), d)[-1],
            "speck.png' is 7x30 pixels; occluders need at least 8",
        ),
        (
            "objects",
            lambda d: (d.mkdir(), _png_claiming(d / "bomb.png", 100_000, 100_000), d)[-1],
            f"bomb.png' is larger than {MAX_PIXELS:,} pixels",
        ),
        # OpenCV, which renders, reads no GIF: a GIF named .png failed every θ that drew it.
        (
            "objects",
            lambda d: (_saved_as(d / "flag.png", "GIF"), d)[-1],
            "flag.png' holds a GIF image, not PNG as its name says",
        ),
        (
            "backgrounds",
            lambda d: (_png(d / "a.png", 32, 32), _saved_as(d / "photo.png", "JPEG"), d)[-1],
            "photo.png' holds a JPEG image, not PNG",
        ),
        ("occluders", lambda d: (_saved_as(d / "leaf.jpg", "PNG"), d)[-1], "leaf.jpg' holds a PNG image, not JPEG/MPO"),
        ("backgrounds", lambda d: (_saved_as(d / "scan.tif", "BMP"), d)[-1], "scan.tif' holds a BMP image, not TIFF"),
        # Pillow's structural check passes these (whole headers): their pixels do not decode.
        (
            "backgrounds",
            lambda d: (_truncated(_saved_as(d / "cut.jpg", "JPEG", 64, 64)), d)[-1],
            "cut.jpg' does not decode (OSError: image file is truncated",
        ),
        ("objects", lambda d: (_truncated(_saved_as(d / "cut.bmp", "BMP", 64, 64)), d)[-1], "cut.bmp' does not decode"),
        (
            "occluders",
            lambda d: (_truncated(_saved_as(d / "cut.tif", "TIFF", 64, 64)), d)[-1],
            "cut.tif' does not decode",
        ),
        (
            "objects",
            lambda d: (_png(d / "poster.png", 32, 32), _saved_as(d / "poster.jpg", "JPEG"), d)[-1],
            "'{d}/poster.jpg' and '{d}/poster.png' both name the class 'poster'",
        ),
        (
            "objects",
            lambda d: (_png(d / "a" / "mug.png", 32, 32), _png(d / "b" / "mug.png", 32, 32), d)[-1],
            "'{d}/a/mug.png' and '{d}/b/mug.png' both name the class 'mug'",
        ),
    ],
)
def test_each_bad_folder_or_file_is_named(tmp_path, folders, what, spoil, message):
    target = tmp_path / f"bad_{what}"
    folder = spoil(target)
    with pytest.raises(AssetError) as caught:
        validate_assets(AssetsConfig(**{**folders, what: folder}))
    assert str(caught.value).startswith(f"assets.{what}: ")
    assert message.format(d=target) in str(caught.value)


def test_a_png_claiming_ten_billion_pixels_is_refused_without_decoding(tmp_path):
    # It is 100 bytes; decoding it would allocate 30 GB. The check reads only its header.
    folder = tmp_path / "objects"
    folder.mkdir()
    _png_claiming(folder / "bomb.png", 100_000, 100_000)
    # VmHWM, the peak RSS of this process image (ru_maxrss would carry pytest's own over exec).
    script = (
        "import re; from foldwise.config import AssetsConfig;"
        "from foldwise.asset_check import validate_assets, AssetError\n"
        f"try: validate_assets(AssetsConfig(objects={str(folder)!r}))\n"
        "except AssetError: pass\n"
        "print(re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read()).group(1))"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, check=True)
    assert int(done.stdout) < 300_000  # KiB: the interpreter and Pillow, not the image


def test_foldwise_run_with_a_bad_asset_folder_is_one_line_and_records_nothing(tmp_path):
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["assets"] = {**config.get("assets", {}), "backgrounds": str(tmp_path / "nowhere")}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    env = {"FOLDWISE_DATA_DIR": str(tmp_path / "data"), "PATH": "/usr/bin:/bin", "COLUMNS": "200"}
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", str(path)], cwd=REPO_ROOT, capture_output=True, text=True, env=env
    )
    output = (done.stdout + done.stderr).strip()
    assert done.returncode == 2, output
    assert output == f"error: assets.backgrounds: folder '{tmp_path / 'nowhere'}' does not exist"
    assert not (tmp_path / "data").exists()  # no database, no images: nothing started


def test_every_accepted_format_under_its_own_name_passes(tmp_path):
    folder = tmp_path / "backgrounds"
    for name, image_format in [
        ("a.png", "PNG"),
        ("b.jpg", "JPEG"),
        ("c.JPEG", "JPEG"),
        ("d.bmp", "BMP"),
        ("e.tiff", "TIFF"),
        ("f.webp", "WEBP"),
    ]:
        _saved_as(folder / name, image_format)
    validate_assets(AssetsConfig(backgrounds=folder))


def test_a_file_the_check_passes_but_opencv_refuses_still_renders(tmp_path, folders):
    # A PNG whose IEND checksum is broken: Pillow decodes every pixel, OpenCV's libpng refuses it.
    from workers.render.assets import _file_image

    path = _png(folders["backgrounds"] / "wall.png", 40, 30)
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is None
    validate_assets(AssetsConfig(**folders))
    pixels = _file_image(str(path), False)
    intact = _png(tmp_path / "intact.png", 40, 30)  # the same pixels (seeded by the size)
    expected = cv2.cvtColor(cv2.imread(str(intact)), cv2.COLOR_BGR2RGB)
    assert pixels.shape == (30, 40, 3) and np.array_equal(pixels, expected)


def _loop(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "loop").symlink_to(folder / "loop")
    return folder / "loop"


@pytest.mark.parametrize(
    ("folder", "message"),
    [
        (
            lambda root: "~nosuchuser-foldwise",
            "there is no user 'nosuchuser-foldwise' on this server to expand ~nosuchuser-foldwise",
        ),
        (lambda root: "~nosuchuser-foldwise/objects", "no user 'nosuchuser-foldwise'"),
        (lambda root: str(root / (("d" * 200 + "/") * 25)), "a path of 5,"),
        (lambda root: str(root / ("n" * 256)), "is 256 bytes; at most 255 are allowed"),
        (lambda root: str(root / ("é" * 128)), "is 256 bytes; at most 255 are allowed"),
        (lambda root: str(_loop(root)), "is a loop of symbolic links"),
    ],
)
def test_an_asset_path_the_system_cannot_take_is_named(tmp_path, folder, message):
    from foldwise.asset_check import asset_path, check_asset_roots

    path = folder(tmp_path)
    for check in (
        lambda: validate_assets(AssetsConfig(objects=path)),
        lambda: check_asset_roots(AssetsConfig(objects=path), [tmp_path]),
        lambda: asset_path(path, "objects"),
    ):
        with pytest.raises(AssetError) as caught:
            check()
        assert str(caught.value).startswith("assets.objects: ") and message in str(caught.value)
        assert len(str(caught.value)) < 400  # a long path is shortened in the message


def test_a_path_under_the_limits_is_taken_as_it_is(tmp_path):
    from foldwise.asset_check import asset_path

    assert asset_path(tmp_path / ("n" * 255), "objects") == tmp_path / ("n" * 255)
    assert asset_path("~", "backgrounds") == Path.home()


def test_foldwise_run_names_an_unknown_user_in_one_line(tmp_path):
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["assets"] = {**config.get("assets", {}), "objects": "~nosuchuser-foldwise"}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    env = {"FOLDWISE_DATA_DIR": str(tmp_path / "data"), "PATH": "/usr/bin:/bin", "COLUMNS": "200"}
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", str(path)], cwd=REPO_ROOT, capture_output=True, text=True, env=env
    )
    output = (done.stdout + done.stderr).strip()
    assert done.returncode == 2, output
    assert output == (
        "error: assets.objects: '~nosuchuser-foldwise': there is no user 'nosuchuser-foldwise' on this server to "
        "expand ~nosuchuser-foldwise"
    )


@pytest.mark.parametrize(
    ("photographs", "message"),
    [
        ("nowhere", "test_set.photographs: '{tmp}/nowhere' does not exist"),
        ("not-a-dataset", "test_set.photographs: cannot read {tmp}/not-a-dataset: {tmp}/not-a-dataset: not a dataset"),
    ],
)
def test_foldwise_run_with_unreadable_photographs_is_one_line_and_records_nothing(tmp_path, photographs, message):
    (tmp_path / "not-a-dataset").mkdir()
    _png(tmp_path / "not-a-dataset" / "photo.png", 64, 48)
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["test_set"] = {**config.get("test_set", {}), "photographs": str(tmp_path / photographs)}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(config))
    env = {"FOLDWISE_DATA_DIR": str(tmp_path / "data"), "PATH": "/usr/bin:/bin", "COLUMNS": "400"}
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", "run", str(path)], cwd=REPO_ROOT, capture_output=True, text=True, env=env
    )
    output = (done.stdout + done.stderr).strip()
    assert done.returncode == 2, output
    assert output.startswith("error: " + message.format(tmp=tmp_path)), output
    assert not (tmp_path / "data").exists()


def test_photographs_outside_the_servers_roots_are_refused(tmp_path):
    from foldwise.asset_check import check_photographs
    from foldwise.config import TestSetConfig

    (tmp_path / "root").mkdir()
    (tmp_path / "elsewhere").mkdir()
    assert check_photographs(TestSetConfig()) is None
    inside = TestSetConfig(photographs=tmp_path / "root")
    assert check_photographs(inside, [tmp_path / "root"]) == tmp_path / "root"
    with pytest.raises(AssetError, match="test_set.photographs: .* is outside the asset roots of this server"):
        check_photographs(TestSetConfig(photographs=tmp_path / "elsewhere"), [tmp_path / "root"])
    with pytest.raises(AssetError, match="test_set.photographs: .*there is no user"):
        check_photographs(TestSetConfig(photographs="~nosuchuser-foldwise/photos"))
