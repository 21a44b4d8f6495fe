"""User asset folders checked once, before any work: by `foldwise run` and `POST /experiments`.

Reads image headers with Pillow and never decodes pixels, so it is cheap for thousands of
files and safe on hostile ones: a PNG whose header claims 100,000 × 100,000 pixels is refused
by its size instead of taking gigabytes to decode. Imports neither numba, OpenCV nor torch (the
API calls it).
"""

from __future__ import annotations

from pathlib import Path

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
# Below these sides an asset cannot be drawn (a 1x1 background or occluder made every θ that
# drew it fail, silently); above MAX_PIXELS it is refused rather than decoded.
MIN_SIDE = {"objects": 16, "backgrounds": 16, "occluders": 8}
MAX_PIXELS = 64_000_000


class AssetError(ValueError):
    """An asset folder or image that cannot be used; the message names the path."""


def image_files(folder: Path, what: str) -> list[Path]:
    """The images under ``folder`` (recursively), or AssetError if it is missing or holds none."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        what_it_is = "is not a folder" if folder.exists() else "does not exist"
        raise AssetError(f"assets.{what}: folder {str(folder)!r} {what_it_is}")
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise AssetError(f"assets.{what}: folder {str(folder)!r} holds no images ({' '.join(IMAGE_SUFFIXES)})")
    return files


def check_image_header(path: Path, what: str) -> tuple[int, int]:
    """(width, height) from the file's header; AssetError if it is not an image or its size is out of bounds."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            width, height = image.size
            image.verify()  # structure and checksums (PNG CRCs), without decoding the pixels
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise AssetError(f"assets.{what}: {str(path)!r} is not a readable image ({type(error).__name__}: {error})") from None
    except Image.DecompressionBombError:
        width = height = None
    if width is None or width * height > MAX_PIXELS:
        raise AssetError(f"assets.{what}: {str(path)!r} is larger than {MAX_PIXELS:,} pixels")
    if min(width, height) < MIN_SIDE[what]:
        raise AssetError(
            f"assets.{what}: {str(path)!r} is {width}x{height} pixels; {what} need at least {MIN_SIDE[what]} on each side"
        )
    return width, height


def _user_folders(config):
    """(kind, folder) for each asset folder an ``AssetsConfig`` names (None: the built-in defaults)."""
    for what in ("objects", "backgrounds", "occluders"):
        folder = None if config is None else getattr(config, what)
        if folder is not None:
            yield what, folder


def check_asset_roots(config, roots: list[Path]) -> None:
    """AssetError unless every user folder of ``config`` lies under one of ``roots`` (links resolved)."""
    for what, folder in _user_folders(config):
        if not roots:
            raise AssetError(
                f"assets.{what}: this server takes asset folders only under FOLDWISE_ASSET_ROOTS, which is not set"
            )
        real = Path(folder).expanduser().resolve()
        if not any(real == root or root in real.parents for root in roots):
            allowed = ", ".join(str(root) for root in roots)
            raise AssetError(f"assets.{what}: {str(folder)!r} is outside the asset roots of this server ({allowed})")


def validate_assets(config) -> None:
    """Check every user folder of an ``AssetsConfig`` (None, or a default folder: nothing to check)."""
    for what, folder in _user_folders(config):
        for path in image_files(folder, what):
            check_image_header(path, what)
