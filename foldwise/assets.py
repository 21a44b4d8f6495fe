"""Asset names: what θ may name as its object, background and occluder, without decoding an image.

The scheduler samples θ from these names and records the experiment's classes; the render worker
(:mod:`workers.render.assets`) decodes the images behind them. Both list a folder the same way, so
the names the scheduler draws are the names the worker finds.

Built-in defaults are photographs scikit-image ships (no download):

* objects (the detector's classes, in this order): astronaut, coffee, chelsea, rocket,
  motorcycle_left (``AssetsConfig.n_objects`` keeps the first n);
* backgrounds: brick, grass, gravel, hubble_deep_field, moon, immunohistochemistry, retina,
  cell, plus procedural ones (``procedural:noise``, ``procedural:gradient``,
  ``procedural:stripes``, ``procedural:checker``) drawn from θ's seed;
* occluders: coins, page, camera, text, clock, colorwheel, and logo (which has its own alpha).

A user folder (``AssetsConfig.objects`` / ``backgrounds`` / ``occluders``) replaces the
corresponding defaults: every image file in it, searched recursively, is one asset. Objects are
named by the file stem (the class name), backgrounds and occluders by their path relative to the
folder. Two files of one name are an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

PROCEDURAL_PREFIX = "procedural:"
PROCEDURAL_BACKGROUNDS = ("noise", "gradient", "stripes", "checker")

BUILTIN_OBJECTS = ("astronaut", "coffee", "chelsea", "rocket", "motorcycle_left")
BUILTIN_BACKGROUNDS = (
    "brick",
    "grass",
    "gravel",
    "hubble_deep_field",
    "moon",
    "immunohistochemistry",
    "retina",
    "cell",
)
BUILTIN_OCCLUDERS = ("coins", "page", "camera", "text", "clock", "colorwheel", "logo")


@dataclass(frozen=True)
class AssetNames:
    """The names θ may carry (the images behind them live with the render worker)."""

    objects: tuple[str, ...]
    backgrounds: tuple[str, ...]
    occluders: tuple[str, ...]

    def __post_init__(self) -> None:
        for what in ("objects", "backgrounds", "occluders"):
            if not getattr(self, what):
                raise ValueError(f"AssetNames.{what} is empty: θ needs at least one")

    @property
    def classes(self) -> list[str]:
        """The detector's classes: the objects' names, in order."""
        return list(self.objects)


def folder_files(folder: Path, what: str, name_by_stem: bool) -> list[tuple[str, Path]]:
    """(name, path) of each image of a user folder, in path order; no image is opened.

    Raises ``AssetError`` (:mod:`foldwise.asset_check`) for a missing folder, a folder without
    images, or two files of one name."""
    from foldwise.asset_check import AssetError, image_files

    folder = Path(folder).expanduser()
    files = [
        (path.stem if name_by_stem else path.relative_to(folder).as_posix(), path) for path in image_files(folder, what)
    ]
    names = [name for name, _ in files]
    if len(set(names)) != len(names):
        duplicates = sorted({n for n in names if names.count(n) > 1})
        raise AssetError(f"assets.{what}: several images share the name(s) {duplicates} in {str(folder)!r}")
    return files


def folder_names(folder: Path, what: str, name_by_stem: bool) -> list[str]:
    """The asset names of a user folder (see :func:`folder_files`)."""
    return [name for name, _ in folder_files(folder, what, name_by_stem)]


def builtin_backgrounds() -> tuple[str, ...]:
    """The built-in backgrounds: scikit-image photographs, then the procedural patterns."""
    return BUILTIN_BACKGROUNDS + tuple(PROCEDURAL_PREFIX + kind for kind in PROCEDURAL_BACKGROUNDS)


def asset_names(config=None) -> AssetNames:
    """The names of an ``AssetsConfig``'s assets (None: the built-in defaults), cached per folder."""
    if config is None:
        return _asset_names(None, None, None, len(BUILTIN_OBJECTS))
    return _asset_names(
        *(
            None if folder is None else str(Path(folder).expanduser().resolve())
            for folder in (config.objects, config.backgrounds, config.occluders)
        ),
        config.n_objects,
    )


@lru_cache(maxsize=16)
def _asset_names(objects: str | None, backgrounds: str | None, occluders: str | None, n_objects: int) -> AssetNames:
    return AssetNames(
        objects=tuple(BUILTIN_OBJECTS[:n_objects] if objects is None else folder_names(Path(objects), "objects", True)),
        backgrounds=builtin_backgrounds()
        if backgrounds is None
        else tuple(folder_names(Path(backgrounds), "backgrounds", False)),
        occluders=BUILTIN_OCCLUDERS if occluders is None else tuple(folder_names(Path(occluders), "occluders", False)),
    )
