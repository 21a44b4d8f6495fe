"""User asset folders checked once, before any work: by `foldwise run` and `POST /experiments`.

Reads each image's header with Pillow first, so it is safe on hostile files: a PNG whose
header claims 100,000 × 100,000 pixels is refused by its size instead of taking gigabytes to
decode. Only then is the file decoded, once: a whole header over corrupt or truncated data
(which Pillow's structural check passes for JPEG, BMP and TIFF) failed every θ that drew it.
Imports neither numba, OpenCV nor torch (the API calls it).
"""

from __future__ import annotations

import os
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
MIN_SIDE = {"objects": 16, "backgrounds": 16, "occluders": 8, "lookalikes": 16}
MAX_PIXELS = 64_000_000


# Linux's PATH_MAX and NAME_MAX: past them every file call fails with ENAMETOOLONG.
MAX_PATH_CHARS = 4096
MAX_NAME_BYTES = 255


class AssetError(ValueError):
    """An asset folder or image that cannot be used; the message names the path."""


def _shown(text: str, limit: int = 80) -> str:
    return repr(text if len(text) <= limit else text[: limit - 1] + "…")


def asset_path(folder: Path | str, what: str, key: str | None = None) -> Path:
    """The asset folder a config names, ``~`` expanded: the one check of an asset path before
    any file call, so that a path the system cannot take is an AssetError naming the problem
    (an unknown ``~user``, a path or a name too long, a loop of symbolic links), not an
    exception from deep inside pathlib. Messages start with ``key`` (default ``assets.{what}``)."""
    key = key or f"assets.{what}"
    text = str(folder)
    if len(text) > MAX_PATH_CHARS:
        raise AssetError(f"{key}: a path of {len(text):,} characters; at most {MAX_PATH_CHARS} are allowed")
    path = Path(text)
    if text.startswith("~"):
        try:
            path = path.expanduser()
        except RuntimeError:  # pathlib's word for "no such user"
            user = text[1:].split(os.sep, 1)[0]
            raise AssetError(
                f"{key}: {_shown(text)}: there is no user {user!r} on this server to expand ~{user}"
            ) from None
        if len(str(path)) > MAX_PATH_CHARS:
            raise AssetError(
                f"{key}: {_shown(text)} is {len(str(path)):,} characters once ~ is expanded; at most {MAX_PATH_CHARS}"
            )
    for part in path.parts:
        if len(os.fsencode(part)) > MAX_NAME_BYTES:
            raise AssetError(
                f"{key}: {_shown(text)}: the name {_shown(part, 40)} is {len(os.fsencode(part)):,} bytes; "
                f"at most {MAX_NAME_BYTES} are allowed"
            )
    try:
        path.resolve()
    except RuntimeError:  # pathlib's word for ELOOP
        raise AssetError(f"{key}: {_shown(text)} is a loop of symbolic links") from None
    except OSError as error:
        raise AssetError(f"{key}: {_shown(text)} cannot be resolved ({error.strerror or error})") from None
    return path


def image_files(folder: Path, what: str) -> list[Path]:
    """The images under ``folder`` (recursively), or AssetError if it is missing or holds none."""
    folder = asset_path(folder, what)
    try:
        if not folder.is_dir():
            what_it_is = "is not a folder" if folder.exists() else "does not exist"
            raise AssetError(f"assets.{what}: folder {str(folder)!r} {what_it_is}")
        files = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    except OSError as error:  # unreadable (permissions), or a name the system refuses deeper down
        raise AssetError(f"assets.{what}: folder {str(folder)!r} cannot be read ({error.strerror or error})") from None
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
        raise AssetError(
            f"assets.{what}: {str(path)!r} is not a readable image ({type(error).__name__}: {error})"
        ) from None
    expected = SUFFIX_FORMATS[path.suffix.lower()]
    if content is not None and content not in expected:
        # The renderer decodes with OpenCV, which reads no GIF and trusts no name: a file that is
        # not what its name says is a mistake to fix here, not a θ that fails later.
        raise AssetError(
            f"assets.{what}: {str(path)!r} holds a {content} image, not {'/'.join(sorted(expected))} as its name says"
        )
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
    for what in ("objects", "backgrounds", "occluders", "lookalikes"):
        folder = None if config is None else getattr(config, what)
        if folder is not None:
            yield what, folder


def check_asset_roots(config, roots: list[Path], uploads: Path | None = None) -> None:
    """AssetError unless every user folder of ``config`` lies under one of ``roots`` or in
    ``uploads`` (the store's uploaded folders, checked on arrival), links resolved."""
    for what, folder in _user_folders(config):
        real = asset_path(folder, what).resolve()
        if uploads is not None and uploads in real.parents:
            continue
        upload_hint = f"; or upload the images with POST /assets/{what}" if uploads is not None else ""
        if not roots:
            raise AssetError(
                f"assets.{what}: this server takes asset folders only under FOLDWISE_ASSET_ROOTS, which is not set{upload_hint}"
            )
        if not any(real == root or root in real.parents for root in roots):
            allowed = ", ".join(str(root) for root in roots)
            raise AssetError(
                f"assets.{what}: {str(folder)!r} is outside the asset roots of this server ({allowed}){upload_hint}"
            )


def check_class_names(files: list[Path], what: str = "objects") -> None:
    """AssetError naming both files when two object (or lookalike) images would take the same
    name (an object image's class is its file name without the extension: workers/render/assets.py)."""
    first_with: dict[str, Path] = {}
    for path in files:
        if path.stem in first_with:
            named = "the class" if what == "objects" else "the lookalike"
            raise AssetError(
                f"assets.{what}: {str(first_with[path.stem])!r} and {str(path)!r} both name {named} "
                f"{path.stem!r}: rename one"
            )
        first_with[path.stem] = path


def validate_assets(config) -> None:
    """Check every user folder of an ``AssetsConfig`` (None, or a default folder: nothing to check)."""
    for what, folder in _user_folders(config):
        files = image_files(folder, what)
        if what in ("objects", "lookalikes"):
            check_class_names(files, what)
        for path in files:
            check_image_file(path, what)


def check_photographs(test_set, roots: list[Path] | None = None) -> Path | None:
    """The folder (or COCO file) ``test_set.photographs`` names, checked as a path before anything
    is recorded; with ``roots`` (a server's FOLDWISE_ASSET_ROOTS) it must lie under one of them.
    Reading it as a dataset is the train worker's (``workers.train.data.load_dataset``)."""
    folder = getattr(test_set, "photographs", None)
    if folder is None:
        return None
    key = "test_set.photographs"
    path = asset_path(folder, "photographs", key)
    if not path.exists():
        raise AssetError(f"{key}: {_shown(str(folder))} does not exist")
    if roots is not None:
        real = path.resolve()
        if not any(real == root or root in real.parents for root in roots):
            allowed = ", ".join(str(root) for root in roots) or "none: FOLDWISE_ASSET_ROOTS is not set"
            raise AssetError(f"{key}: {_shown(str(folder))} is outside the asset roots of this server ({allowed})")
    return path
