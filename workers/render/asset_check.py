"""User asset folders checked once, before any work: by `foldwise run` and `POST /experiments`.

Reads each image's header with Pillow first, so it is safe on hostile files: a PNG whose
header claims 100,000 × 100,000 pixels is refused by its size instead of taking gigabytes to
decode. Only then is the file decoded, once: a whole header over corrupt or truncated data
(which Pillow's structural check passes for JPEG, BMP and TIFF) failed every θ that drew it.
Imports neither numba, OpenCV nor torch (the API calls it).
"""

from __future__ import annotations

from pathlib import Path

# What each accepted file name says its content is, as Pillow names the formats (MPO: the
# multi-picture JPEG some cameras write, a JPEG to every decoder).
SUFFIX_FORMATS = {
    ".png": {"PNG"},
    ".jpg": {"JPEG", "MPO"},
    ".jpeg": {"JPEG", "MPO"},
    ".bmp": {"BMP"},
    ".tif": {"TIFF"},
    ".tiff": {"TIFF"},
    ".webp": {"WEBP"},
}
IMAGE_SUFFIXES = tuple(SUFFIX_FORMATS)
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


def check_image_file(path: Path, what: str) -> tuple[int, int]:
    """(width, height) of an image file; AssetError if it is not an image of the format its name
    says, its size is out of bounds, or its pixels do not decode."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            width, height = image.size
            content = image.format
            image.verify()  # structure and checksums (PNG CRCs), without decoding the pixels
    except Image.DecompressionBombError:
        width = height = None
        content = None
    except Exception as error:  # UnidentifiedImageError, OSError, SyntaxError; a hostile file may raise anything
        raise AssetError(f"assets.{what}: {str(path)!r} is not a readable image ({type(error).__name__}: {error})") from None
    expected = SUFFIX_FORMATS[path.suffix.lower()]
    if content is not None and content not in expected:
        # The renderer decodes with OpenCV, which reads no GIF and trusts no name: a file that is
        # not what its name says is a mistake to fix here, not a θ that fails later.
        raise AssetError(f"assets.{what}: {str(path)!r} holds a {content} image, not {'/'.join(sorted(expected))} as its name says")
    if width is None or width * height > MAX_PIXELS:
        raise AssetError(f"assets.{what}: {str(path)!r} is larger than {MAX_PIXELS:,} pixels")
    if min(width, height) < MIN_SIDE[what]:
        raise AssetError(
            f"assets.{what}: {str(path)!r} is {width}x{height} pixels; {what} need at least {MIN_SIDE[what]} on each side"
        )
    try:
        with Image.open(path) as image:  # verify() leaves the image unusable: open it again
            image.load()
    except Exception as error:  # a hostile file may raise anything from a decoder
        raise AssetError(f"assets.{what}: {str(path)!r} does not decode ({type(error).__name__}: {error})") from None
    return width, height


def _user_folders(config):
    """(kind, folder) for each asset folder an ``AssetsConfig`` names (None: the built-in defaults)."""
    for what in ("objects", "backgrounds", "occluders"):
        folder = None if config is None else getattr(config, what)
        if folder is not None:
            yield what, folder


def check_asset_roots(config, roots: list[Path], uploads: Path | None = None) -> None:
    """AssetError unless every user folder of ``config`` lies under one of ``roots`` or in
    ``uploads`` (the store's uploaded folders, checked on arrival), links resolved."""
    for what, folder in _user_folders(config):
        real = Path(folder).expanduser().resolve()
        if uploads is not None and uploads in real.parents:
            continue
        upload_hint = f"; or upload the images with POST /assets/{what}" if uploads is not None else ""
        if not roots:
            raise AssetError(
                f"assets.{what}: this server takes asset folders only under FOLDWISE_ASSET_ROOTS, which is not set{upload_hint}"
            )
        if not any(real == root or root in real.parents for root in roots):
            allowed = ", ".join(str(root) for root in roots)
            raise AssetError(f"assets.{what}: {str(folder)!r} is outside the asset roots of this server ({allowed}){upload_hint}")


def check_class_names(files: list[Path]) -> None:
    """AssetError naming both files when two object images would name the same class (the
    class of an object image is its file name without the extension: workers/render/assets.py)."""
    first_with: dict[str, Path] = {}
    for path in files:
        if path.stem in first_with:
            raise AssetError(
                f"assets.objects: {str(first_with[path.stem])!r} and {str(path)!r} both name the class "
                f"{path.stem!r}: rename one"
            )
        first_with[path.stem] = path


def validate_assets(config) -> None:
    """Check every user folder of an ``AssetsConfig`` (None, or a default folder: nothing to check)."""
    for what, folder in _user_folders(config):
        files = image_files(folder, what)
        if what == "objects":
            check_class_names(files)
        for path in files:
            check_image_file(path, what)
