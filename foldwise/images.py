"""Reading images from files or bytes: the one place foldwise decodes a picture.

Phone photographs store their pixels as the sensor read them and an EXIF Orientation tag
saying how to turn them for display; labelling tools, browsers and people see the turned
image, so box labels refer to it. ``read_image`` applies the orientation once, converts any
mode (grey, palette, RGBA, CMYK, 16-bit) to 8-bit RGB, and can shrink a very large photo
(12-50 Mpixel) while it decodes, returning the scale so that callers scale boxes with it.

The header is checked before any pixel is decoded: a file that is not an image, is cut
short, or declares more than ``MAX_PIXELS`` pixels (a decompression bomb: a few kilobytes
that decode to gigabytes) raises :class:`ImageError` naming the problem.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import BinaryIO

import numpy as np

# Larger than any phone or consumer camera (a 50-Mpixel photo is well inside), small enough
# that one decoded image (3 bytes a pixel) stays a few hundred megabytes.
MAX_PIXELS = 100_000_000

# EXIF Orientation values that turn the image by a quarter: width and height swap on display.
_SWAPPING_ORIENTATIONS = {5, 6, 7, 8}
_EXIF_ORIENTATION = 0x0112

Source = bytes | bytearray | memoryview | str | Path | BinaryIO


class ImageError(ValueError):
    """An image that cannot be read: the message names the file (where known) and the problem."""


def _describe(source: Source) -> str:
    if isinstance(source, (str, Path)):
        return str(source)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return f"image data ({len(source)} bytes)"
    return str(getattr(source, "name", "image data"))


def _open(source: Source, max_pixels: int):
    """The PIL image, header read only (PIL decodes lazily), checked against ``max_pixels``."""
    from PIL import Image, UnidentifiedImageError

    where = _describe(source)
    if isinstance(source, (bytes, bytearray, memoryview)):
        if len(source) == 0:
            raise ImageError(f"{where}: empty, not an image")
        stream: object = io.BytesIO(bytes(source))
    elif isinstance(source, (str, Path)):
        path = Path(source)
        if not path.is_file():
            raise ImageError(f"{where}: no such file")
        if path.stat().st_size == 0:
            raise ImageError(f"{where}: empty file, not an image")
        stream = path
    else:
        stream = source
    try:
        with warnings.catch_warnings():
            # PIL's own bomb limit warns (or raises) on its own figure; ours is checked below.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(stream)
    except Image.DecompressionBombError as error:
        raise ImageError(f"{where}: too many pixels ({error}); at most {max_pixels:,} are read") from None
    except UnidentifiedImageError:
        if _looks_like_image(stream):
            raise ImageError(f"{where}: truncated or damaged image header") from None
        raise ImageError(f"{where}: not an image (no format PIL reads recognises it)") from None
    except (OSError, SyntaxError, ValueError, EOFError) as error:
        raise ImageError(f"{where}: truncated or damaged image header ({error})") from None
    width, height = image.size
    if width < 1 or height < 1:
        raise ImageError(f"{where}: empty image ({width}x{height} pixels)")
    if width * height > max_pixels:
        raise ImageError(
            f"{where}: {width}x{height} = {width * height:,} pixels, more than the {max_pixels:,} read "
            "(a decompression bomb, or a photo to shrink before use)"
        )
    return image, where


_SIGNATURES = (b"\xff\xd8\xff", b"\x89PNG", b"GIF8", b"BM", b"II*\x00", b"MM\x00*", b"RIFF")


def _looks_like_image(stream) -> bool:
    """Whether the data starts as a common image format does (so a failure is damage, not a wrong file)."""
    try:
        if isinstance(stream, Path):
            with stream.open("rb") as handle:
                head = handle.read(8)
        else:
            stream.seek(0)
            head = stream.read(8)
    except (OSError, AttributeError):
        return False
    return any(head.startswith(signature) for signature in _SIGNATURES)


def _orientation(image) -> int:
    try:
        return int(image.getexif().get(_EXIF_ORIENTATION, 1) or 1)
    except Exception:  # a damaged EXIF block: the pixels as stored
        return 1


def image_size(source: Source, *, max_pixels: int = MAX_PIXELS) -> tuple[int, int]:
    """(width, height) of the image as displayed (EXIF orientation applied), from its header
    alone. ImageError when it is not an image, its header is cut short, or it holds more than
    ``max_pixels`` pixels."""
    image, _ = _open(source, max_pixels)
    with image:
        width, height = image.size
        if _orientation(image) in _SWAPPING_ORIENTATIONS:
            width, height = height, width
    return width, height


def read_image(
    source: Source, *, max_side: int | None = None, max_pixels: int = MAX_PIXELS
) -> tuple[np.ndarray, float]:
    """The image as displayed, as (H, W, 3) uint8 RGB, and the scale it was read at.

    The EXIF orientation is applied (boxes labelled on the displayed photo fit it). With
    ``max_side``, an image whose longer side exceeds it is shrunk (aspect kept) so that its
    longer side is ``max_side``; the scale is then ``max_side / longer side`` (multiply boxes
    of the full-size image by it), else 1.0. A JPEG is shrunk while it decodes (libjpeg's
    DCT scaling), so a 50-Mpixel photo never sits in memory at full size.
    """
    from PIL import Image, ImageOps

    if max_side is not None and max_side < 1:
        raise ValueError(f"max_side must be at least 1, got {max_side}")
    image, where = _open(source, max_pixels)
    with image:
        stored_w, stored_h = image.size
        full_w, full_h = (stored_h, stored_w) if _orientation(image) in _SWAPPING_ORIENTATIONS else (stored_w, stored_h)
        target = shrunk_size(full_w, full_h, max_side)
        scale = 1.0
        if target != (full_w, full_h):
            scale = max_side / max(stored_w, stored_h)
            # draft() picks the smallest DCT scale at least this large; the exact resize follows.
            image.draft(None, (int(np.ceil(stored_w * scale)), int(np.ceil(stored_h * scale))))
        try:
            image.load()
            upright = ImageOps.exif_transpose(image)
        except Image.DecompressionBombError as error:
            raise ImageError(f"{where}: too many pixels ({error})") from None
        except (OSError, SyntaxError, ValueError, EOFError) as error:
            raise ImageError(f"{where}: truncated or damaged image ({error})") from None
        rgb = _as_rgb(upright)
        if rgb.size != target:
            rgb = rgb.resize(target, Image.Resampling.LANCZOS, reducing_gap=3.0)
        return np.array(rgb, dtype=np.uint8), scale  # a writable copy (torch.from_numpy warns on read-only)


def shrunk_size(width: int, height: int, max_side: int | None) -> tuple[int, int]:
    """The (width, height) ``read_image`` gives an image of this displayed size with ``max_side``:
    unchanged when its longer side is at most ``max_side``. Boxes scale exactly by the ratio of
    the two sizes, axis by axis."""
    if max_side is None or max(width, height) <= max_side:
        return width, height
    scale = max_side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def _as_rgb(image):
    """Any PIL mode as 8-bit RGB; 16-bit grey keeps its high byte (PIL's own conversion clips)."""
    from PIL import Image

    if image.mode in ("I;16", "I;16L", "I;16B", "I;16N"):
        grey = (np.asarray(image).astype(np.uint32) >> 8).astype(np.uint8)
        return Image.fromarray(grey).convert("RGB")
    if image.mode in ("RGBA", "LA", "PA") or (image.mode == "P" and "transparency" in image.info):
        # Transparent pixels over white, as a viewer shows them, not over whatever colour they hold.
        rgba = image.convert("RGBA")
        background = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
        return Image.alpha_composite(background, rgba).convert("RGB")
    return image if image.mode == "RGB" else image.convert("RGB")
