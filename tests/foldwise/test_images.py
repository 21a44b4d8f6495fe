import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from foldwise.images import MAX_PIXELS, ImageError, image_size, read_image

# EXIF Orientation value -> the numpy turn that shows the stored pixels as displayed.
DISPLAY = {
    1: lambda a: a,
    3: lambda a: np.rot90(a, 2),
    6: lambda a: np.rot90(a, -1),  # stored turned a quarter anticlockwise: shown turned clockwise
    8: lambda a: np.rot90(a, 1),
}


def _encode(array: np.ndarray, fmt: str = "PNG", orientation: int | None = None, **options) -> bytes:
    buffer = io.BytesIO()
    image = Image.fromarray(array)
    if orientation is not None:
        exif = Image.Exif()
        exif[0x0112] = orientation
        options["exif"] = exif.tobytes()
    image.save(buffer, fmt, **options)
    return buffer.getvalue()


def _png_header(width: int, height: int) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
    return b"\x89PNG\r\n\x1a\n" + header + chunk(b"IDAT", zlib.compress(b"\x00" * 16)) + chunk(b"IEND", b"")


def _marked(height: int = 30, width: int = 40) -> np.ndarray:
    array = np.zeros((height, width, 3), np.uint8)
    array[:5, :10] = (255, 0, 0)  # a red mark at the top left tells every turn apart
    return array


@pytest.mark.parametrize("orientation", sorted(DISPLAY))
def test_exif_orientation_is_applied_once(orientation, tmp_path):
    stored = _marked()
    path = tmp_path / "photo.png"
    path.write_bytes(_encode(stored, orientation=orientation))
    pixels, scale = read_image(path)
    assert scale == 1.0
    np.testing.assert_array_equal(pixels, DISPLAY[orientation](stored))
    assert image_size(path) == (pixels.shape[1], pixels.shape[0])


def test_bytes_and_paths_read_alike(tmp_path):
    data = _encode(_marked(), orientation=6)
    (tmp_path / "a.png").write_bytes(data)
    np.testing.assert_array_equal(read_image(data)[0], read_image(tmp_path / "a.png")[0])
    np.testing.assert_array_equal(read_image(str(tmp_path / "a.png"))[0], read_image(io.BytesIO(data))[0])


@pytest.mark.parametrize("fmt", ["JPEG", "PNG"])
def test_large_photo_is_shrunk_to_max_side(fmt):
    array = np.random.default_rng(0).integers(0, 255, (300, 400, 3), dtype=np.uint8)
    pixels, scale = read_image(_encode(array, fmt, orientation=6), max_side=100)
    assert pixels.shape == (100, 75, 3)  # portrait as displayed, longer side 100
    assert scale == pytest.approx(0.25)
    small, same = read_image(_encode(array, fmt), max_side=1000)
    assert small.shape == (300, 400, 3) and same == 1.0


@pytest.mark.parametrize(
    "mode, array",
    [
        ("L", np.full((4, 6), 200, np.uint8)),
        ("RGBA", np.dstack([np.full((4, 6, 3), 10, np.uint8), np.full((4, 6), 255, np.uint8)])),
        ("I;16", np.full((4, 6), 200 * 256, np.uint16)),
    ],
)
def test_any_mode_comes_out_rgb_uint8(mode, array):
    image = Image.fromarray(array)
    assert image.mode == mode
    buffer = io.BytesIO()
    image.save(buffer, "PNG")
    pixels, _ = read_image(buffer.getvalue())
    assert pixels.dtype == np.uint8 and pixels.shape == (4, 6, 3)
    assert int(pixels[0, 0, 0]) in (200, 10)


def test_not_an_image_is_named(tmp_path):
    path = tmp_path / "notes.jpg"
    path.write_text("not a picture")
    with pytest.raises(ImageError, match=r"notes\.jpg: not an image"):
        read_image(path)
    with pytest.raises(ImageError, match="not an image"):
        image_size(b"hello")
    with pytest.raises(ImageError, match="no such file"):
        image_size(tmp_path / "missing.png")
    with pytest.raises(ImageError, match="empty"):
        read_image(b"")


def test_truncated_image_is_named():
    data = _encode(np.random.default_rng(1).integers(0, 255, (200, 200, 3), dtype=np.uint8), "JPEG")
    with pytest.raises(ImageError, match="truncated"):
        image_size(data[:200])
    with pytest.raises(ImageError, match="truncated"):
        read_image(data[: len(data) // 2])


def test_too_many_pixels_is_refused_before_decoding():
    # A PNG header declaring 12000 x 12000 pixels, with no pixel data: decoding would fail,
    # so an error that names the pixel count shows that nothing was decoded.
    for side in (12_000, 20_000):  # over our limit; over PIL's own too
        bomb = _png_header(side, side)
        with pytest.raises(ImageError, match="pixels"):
            image_size(bomb)
        with pytest.raises(ImageError, match="pixels"):
            read_image(bomb)
    # Under PIL's own bomb limit but over ours: our limit alone refuses it.
    small = _encode(np.zeros((20, 30, 3), np.uint8))
    with pytest.raises(ImageError, match="30x20 = 600 pixels"):
        read_image(small, max_pixels=500)
    assert MAX_PIXELS >= 50_000_000


def test_max_side_must_be_positive():
    with pytest.raises(ValueError, match="max_side"):
        read_image(_encode(_marked()), max_side=0)
