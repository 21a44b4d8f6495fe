"""Object textures, backgrounds and occluders: built-in defaults that work offline, or user folders.

The names (built-in defaults, and how a user folder's files are named) are
:mod:`foldwise.assets`'s, which lists them without decoding anything; this module decodes the images
behind them. An occluder PNG with an alpha channel keeps its own shape; others get a random shape
at render time. An image OpenCV cannot read raises :class:`AssetError` naming the path.

Decoded images are cached per process: the same few hundred images are reused thousands of
times by a render worker. Photo backgrounds are cut from cached copies shrunk by powers of 1.25
(a bilinear warp of a crop that spans at most 1.25x the output), not resized from the full photo.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path

import numba
import numpy as np

from foldwise.asset_check import AssetError
from foldwise.assets import (
    BUILTIN_BACKGROUNDS,
    BUILTIN_OBJECTS,
    BUILTIN_OCCLUDERS,
    PROCEDURAL_BACKGROUNDS,
    PROCEDURAL_PREFIX,
    AssetNames,
    folder_files,
)


@dataclass(frozen=True)
class Asset:
    """One named image; ``load()`` returns it decoded (uint8 RGB, or RGBA for occluders with alpha)."""

    name: str
    loader: Callable[[], np.ndarray] = field(repr=False, compare=False)
    source: str = ""  # where it comes from, for messages: "skimage.data.brick" or a file path

    def load(self) -> np.ndarray:
        return self.loader()

    @property
    def procedural(self) -> bool:
        return self.name.startswith(PROCEDURAL_PREFIX)


def _to_uint8_rgb(image: np.ndarray, source: str, keep_alpha: bool = False) -> np.ndarray:
    """Any decoded image (grey, RGB, RGBA; bool, uint8, uint16, float) as uint8 RGB or RGBA."""
    if image.dtype == bool:
        image = image.astype(np.uint8) * 255
    elif image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    elif np.issubdtype(image.dtype, np.floating):
        image = np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise AssetError(f"{source}: unsupported pixel type {image.dtype}")
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise AssetError(f"{source}: expected a grey, RGB or RGBA image, got shape {image.shape}")
    if image.shape[2] == 4 and not keep_alpha:
        image = image[:, :, :3]
    if image.shape[0] < 2 or image.shape[1] < 2:
        raise AssetError(f"{source}: image of {image.shape[1]}x{image.shape[0]} pixels is too small")
    return np.ascontiguousarray(image)


@cache
def _skimage_image(name: str, keep_alpha: bool) -> np.ndarray:
    import skimage.data

    if name == "motorcycle_left":
        image = skimage.data.stereo_motorcycle()[0]
    else:
        image = getattr(skimage.data, name)()
    image = _to_uint8_rgb(np.asarray(image), f"skimage.data.{name}", keep_alpha=keep_alpha)
    image.setflags(write=False)
    return image


@lru_cache(maxsize=128)
def _file_image(path: str, keep_alpha: bool) -> np.ndarray:
    import cv2

    image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        # The asset check decodes with Pillow, which reads a few files OpenCV refuses (a PNG whose
        # IEND checksum is broken, TIFFs with damaged tags): what the check passed must render.
        image = _pillow_image(path)
    elif image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    image = _to_uint8_rgb(image, path, keep_alpha=keep_alpha)
    image.setflags(write=False)
    return image


def _pillow_image(path: str) -> np.ndarray:
    """RGB or RGBA pixels of a file OpenCV cannot decode, or AssetError."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            has_alpha = "A" in image.getbands() or "transparency" in image.info
            return np.asarray(image.convert("RGBA" if has_alpha else "RGB"))
    except Exception as error:  # a hostile file may raise anything from a decoder
        raise AssetError(f"cannot read image {path!r} ({type(error).__name__}: {error})") from None


def _procedural_placeholder() -> np.ndarray:
    raise AssetError("procedural backgrounds are generated per image: use AssetCatalog.background()")


def _folder_assets(folder: Path, what: str, keep_alpha: bool, name_by_stem: bool) -> list[Asset]:
    import cv2

    assets = []
    for name, path in folder_files(folder, what, name_by_stem):
        # A header check is cheap enough for thousands of files and catches non-images early;
        # a file that still fails to decode raises AssetError when first used.
        if not cv2.haveImageReader(str(path)):
            raise AssetError(f"assets.{what}: cannot read image {str(path)!r} (not a format OpenCV can decode)")
        assets.append(Asset(name, (lambda p=str(path): _file_image(p, keep_alpha)), source=str(path)))
    return assets


def _builtin(names, keep_alpha: bool) -> list[Asset]:
    return [Asset(n, (lambda n=n: _skimage_image(n, keep_alpha)), source=f"skimage.data.{n}") for n in names]


class AssetCatalog:
    """Objects (the detector's classes), backgrounds and occluders, each a list of named images;
    and lookalikes where the config gives them (sheets of the objects' kind that are none of them)."""

    def __init__(
        self,
        objects: list[Asset],
        backgrounds: list[Asset],
        occluders: list[Asset],
        lookalikes: list[Asset] | None = None,
    ):
        for what, assets in (("objects", objects), ("backgrounds", backgrounds), ("occluders", occluders)):
            if not assets:
                raise AssetError(f"asset catalog: no {what}")
            names = [a.name for a in assets]
            if len(set(names)) != len(names):
                raise AssetError(f"asset catalog: duplicate {what} names")
        self.objects = list(objects)
        self.lookalikes = list(lookalikes or [])
        clash = sorted({a.name for a in self.lookalikes} & set(self.classes))
        if clash:
            raise AssetError(
                f"assets.lookalikes: {clash} share a name with an object; a lookalike is none of the objects"
            )
        self.backgrounds = list(backgrounds)
        self.occluders = list(occluders)
        # Photographs pre-shrunk by powers of PHOTO_LEVEL_STEP, per (name, level): a crop is
        # cut from the level where it spans size..1.25 x size pixels, so one cheap bilinear
        # resize finishes it (an INTER_AREA resize of the full crop costs 0.6-1.4 ms).
        self._shrunk: OrderedDict[tuple[str, int], np.ndarray] = OrderedDict()
        self._occluders: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        self._lock = threading.Lock()
        self._by_name = {
            "objects": {a.name: a for a in self.objects},
            "backgrounds": {a.name: a for a in self.backgrounds},
            "occluders": {a.name: a for a in self.occluders},
            "lookalikes": {a.name: a for a in self.lookalikes},
        }

    def __repr__(self) -> str:
        return (
            f"AssetCatalog({len(self.objects)} objects, {len(self.backgrounds)} backgrounds, "
            f"{len(self.occluders)} occluders)"
        )

    @property
    def classes(self) -> list[str]:
        return [a.name for a in self.objects]

    @property
    def names(self) -> AssetNames:
        """The names θ may carry."""
        return AssetNames(
            objects=tuple(self.classes),
            backgrounds=tuple(a.name for a in self.backgrounds),
            occluders=tuple(a.name for a in self.occluders),
        )

    @property
    def distractors(self) -> list[str]:
        """What clutter is printed with: every occluder and background photograph, and the
        procedural patterns ("occluders/…", "backgrounds/…"); never an object's texture."""
        return [f"occluders/{a.name}" for a in self.occluders] + [f"backgrounds/{a.name}" for a in self.backgrounds]

    @property
    def lookalike_sheets(self) -> list[str]:
        """The lookalikes as distractor names ("lookalikes/…"): every image shows one or two of
        them beside its targets (layers.py); empty where the config gives none."""
        return [f"lookalikes/{a.name}" for a in self.lookalikes]

    def lookalike_textures(self) -> dict[str, np.ndarray]:
        """Each lookalike's image by name: what a detector's texture check must not confirm."""
        return {a.name: a.load() for a in self.lookalikes}

    def distractor(self, name: str, rng: np.random.Generator, size: int = 256) -> np.ndarray:
        """(h, w, 3) uint8 RGB of distractor ``name`` (see ``distractors``): the photograph
        (read-only, cached), or a procedural pattern of ``size`` pixels drawn from ``rng``."""
        kind, _, asset_name = name.partition("/")
        if kind == "occluders":
            return self.occluder(asset_name)[0]
        if kind == "backgrounds":
            asset = self._get("backgrounds", asset_name)
            if asset.procedural:
                return procedural_background(asset_name[len(PROCEDURAL_PREFIX) :], size, rng)
            photo = asset.load()
            return photo if photo.shape[2] == 3 else np.ascontiguousarray(photo[:, :, :3])
        if kind == "lookalikes":
            return self._get("lookalikes", asset_name).load()
        raise AssetError(
            f"unknown distractor {name!r}: expected occluders/<name>, backgrounds/<name> or lookalikes/<name>"
        )

    def _get(self, kind: str, name: str) -> Asset:
        try:
            return self._by_name[kind][name]
        except KeyError:
            known = list(self._by_name[kind])
            shown = ", ".join(known[:10]) + (", ..." if len(known) > 10 else "")
            raise AssetError(f"unknown {kind[:-1]} {name!r}; this catalog has: {shown}") from None

    def label(self, object_name: str) -> int:
        """0-based class index of an object."""
        self._get("objects", object_name)
        return self.classes.index(object_name)

    def texture(self, object_name: str) -> np.ndarray:
        """(h, w, 3) uint8 RGB albedo of an object (read-only, cached)."""
        return self._get("objects", object_name).load()

    def textures(self, object_names) -> dict[str, np.ndarray]:
        """Each named object's texture (:meth:`texture`), by name: a detector's texture check reference."""
        return {name: self.texture(name) for name in object_names}

    def occluder(self, name: str) -> tuple[np.ndarray, np.ndarray | None]:
        """(rgb (h, w, 3) uint8, alpha (h, w) uint8 or None when the image has no alpha), both
        read-only and cached: the same arrays every call, so per-array caches downstream hit."""
        asset = self._get("occluders", name)
        with self._lock:
            split = self._occluders.get(name)
        if split is not None:
            return split
        image = asset.load()
        rgb, alpha = image, None
        if image.shape[2] == 4:
            rgb = np.ascontiguousarray(image[:, :, :3])
            if image[:, :, 3].min() < 255:
                alpha = np.ascontiguousarray(image[:, :, 3])
        for array in (rgb, alpha):
            if array is not None and array.flags.writeable and array.flags.owndata:
                array.setflags(write=False)
        split = (rgb, alpha)
        with self._lock:
            return self._occluders.setdefault(name, split)

    def background(self, name: str, size: int, rng: np.random.Generator) -> np.ndarray:
        """A (size, size, 3) uint8 RGB background: a random square crop of a photograph, or a
        procedural pattern, both drawn from ``rng`` (so θ's seed fixes it).

        The crop window is drawn exactly as :func:`random_crop` draws it on the full photograph;
        the resampling differs (bilinear from a cached pre-shrunk level, see _level_window, whose
        rounding moves the crop by under half an output pixel), so the two agree to within that
        and interpolation differences."""
        asset = self._get("backgrounds", name)
        if asset.procedural:
            return procedural_background(name[len(PROCEDURAL_PREFIX) :], size, rng)
        if size < 1:
            raise AssetError(f"background size must be >= 1 pixel, got {size}")
        photo = asset.load()
        if photo.shape[2] != 3:
            photo = np.ascontiguousarray(photo[:, :, :3])
        h, w = photo.shape[:2]
        y0, x0, side, mirror = _crop_window(h, w, rng)
        level = _level_for(side, size)
        source = photo if level == 0 else self._photo_level(asset, level)
        import cv2

        # Bilinear reads every source pixel at <= PHOTO_LEVEL_STEP x down, so it barely aliases.
        left, top, window_w, window_h = _level_window(photo.shape, source.shape, y0, x0, side)
        window = source[top : top + window_h, left : left + window_w]
        out = cv2.resize(
            window,
            None,
            fx=size / (side * source.shape[1] / w),
            fy=size / (side * source.shape[0] / h),
            interpolation=cv2.INTER_LINEAR,
        )
        if out.shape[:2] != (size, size):  # enlarging can round the output size: resize to it instead
            out = cv2.resize(window, (size, size), interpolation=cv2.INTER_LINEAR)
        return _flip(out) if mirror else out

    def _photo_level(self, asset: Asset, level: int) -> np.ndarray:
        """The photograph shrunk by PHOTO_LEVEL_STEP ** level with INTER_AREA, cached (LRU,
        at most MAX_CACHED_LEVELS arrays) per (name, level); independent of the output size."""
        import cv2

        key = (asset.name, level)
        with self._lock:
            image = self._shrunk.get(key)
            if image is not None:
                self._shrunk.move_to_end(key)
                return image
        photo = asset.load()
        h, w = photo.shape[:2]
        factor = PHOTO_LEVEL_STEP**-level
        image = cv2.resize(photo, (max(2, round(w * factor)), max(2, round(h * factor))), interpolation=cv2.INTER_AREA)
        image.setflags(write=False)
        with self._lock:
            self._shrunk[key] = image
            self._shrunk.move_to_end(key)
            while len(self._shrunk) > MAX_CACHED_LEVELS:
                self._shrunk.popitem(last=False)
        return image


PHOTO_LEVEL_STEP = 1.25
MAX_CACHED_LEVELS = 256  # a 1411-pixel photo's levels down to 128 pixels: ~11 arrays, ~10 MB in all


def _level_for(side: int, size: int) -> int:
    """The coarsest level at which a crop of ``side`` photo pixels still spans >= ``size`` pixels
    (level 0: the photo itself)."""
    return max(0, math.floor(math.log(side / size) / math.log(PHOTO_LEVEL_STEP))) if side > size else 0


def _level_window(photo_shape, level_shape, y0: int, x0: int, side: int) -> tuple[int, int, int, int]:
    """(left, top, width, height) in level pixels of the photo's crop window (y0, x0, side).

    cv2.resize of it by the exact scale (fx = size / (side x level scale)) samples output pixel
    centre u + 0.5 at left + (u + 0.5) * step - 0.5, as the full-resolution crop does from
    x0 x level scale: only the origin is rounded to a whole level pixel, so the crop moves by
    under half an output pixel and keeps its scale. That lets OpenCV's resize do the work,
    ~3x cheaper than a warpAffine keeping the origin's fraction."""
    scale_y, scale_x = level_shape[0] / photo_shape[0], level_shape[1] / photo_shape[1]
    width, height = min(round(side * scale_x), level_shape[1]), min(round(side * scale_y), level_shape[0])
    left = min(max(round(x0 * scale_x), 0), level_shape[1] - width)
    top = min(max(round(y0 * scale_y), 0), level_shape[0] - height)
    return left, top, width, height


def _crop_window(h: int, w: int, rng: np.random.Generator) -> tuple[int, int, int, bool]:
    """(top, left, side, mirror) of a random square crop, 40-100% of the shorter side."""
    side = max(2, round(min(h, w) * rng.uniform(0.4, 1.0)))
    y0 = int(rng.integers(0, h - side + 1))
    x0 = int(rng.integers(0, w - side + 1))
    mirror = bool(rng.random() < 0.5)
    return y0, x0, side, mirror


def _resize_square(image: np.ndarray, size: int, interpolation: str) -> np.ndarray:
    """``image`` (rows may be strided) resized to size x size; "area" or "linear" (OpenCV)."""
    import cv2

    if image.strides[1] != image.shape[2] * image.itemsize:  # OpenCV wants each row's pixels packed
        image = np.ascontiguousarray(image)
    flag = cv2.INTER_AREA if interpolation == "area" else cv2.INTER_LINEAR
    return cv2.resize(image, (size, size), interpolation=flag)


def _flip(image: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.flip(image, 1)


def _resize_crop(image: np.ndarray, y0: int, x0: int, side: int, size: int, mirror: bool) -> np.ndarray:
    crop = image[y0 : y0 + side, x0 : x0 + side, :3]
    out = _resize_square(crop, size, interpolation="area" if side > size else "linear")
    # Mirroring the small result gives the same bytes as resizing the mirrored crop (both
    # resamplers are symmetric), without copying the large crop backwards first.
    return _flip(out) if mirror else out


def random_crop(image: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """A random square crop (40-100% of the shorter side), maybe mirrored, resized to size x size
    straight from ``image`` (INTER_AREA when shrinking): the full-resolution reference path."""
    h, w = image.shape[:2]
    y0, x0, side, mirror = _crop_window(h, w, rng)
    return _resize_crop(image, y0, x0, side, size, mirror)


_PATTERN_CODES = {"gradient": 0, "stripes": 1, "checker": 2}


@numba.njit(cache=True, nogil=True)
def _two_colour_pattern(code, size, colours, cos_angle, sin_angle, period):
    """Gradient (code 0), stripes (1) or checker (2) as (size, size, 3) uint8 RGB in one pass.

    Every step is the float32 arithmetic, in the same order, of the NumPy formula it replaces:
    xs = arange(size, float32) / size; along = cos * xs + sin * ys; across = -sin * xs + cos * ys;
    gradient weight = (along - along.min()) / max(ptp(along), 1e-6); stripes: sin(2 pi along /
    period) > 0; checker: parity of floor(along / period) + floor(across / period); and each
    pixel clip(colour0 + (colour1 - colour0) * weight + 0.5, 0, 255) truncated to uint8."""
    n = np.float32(size)
    half, top = np.float32(0.5), np.float32(255.0)
    step = np.empty(3, np.float32)
    for k in range(3):
        step[k] = colours[1, k] - colours[0, k]
    # The two colours of stripes and checker: the gradient's formula at weight 0 and 1.
    two = np.empty((2, 3), np.uint8)
    for w in range(2):
        for k in range(3):
            value = colours[0, k] + step[k] * np.float32(w) + half
            two[w, k] = np.uint8(min(max(value, np.float32(0.0)), top))
    along_x = np.empty(size, np.float32)
    along_y = np.empty(size, np.float32)
    across_x = np.empty(size, np.float32)
    across_y = np.empty(size, np.float32)
    for i in range(size):
        t = np.float32(i) / n
        along_x[i] = cos_angle * t
        along_y[i] = sin_angle * t
        across_x[i] = -sin_angle * t
        across_y[i] = cos_angle * t
    # along is monotonic in each of along_x and along_y (float rounding is monotonic), so its
    # extremes are at corners: the sum of the extreme terms.
    low = along_x.min() + along_y.min()
    spread = along_x.max() + along_y.max() - low
    divisor = spread if spread > np.float32(1e-6) else np.float32(1e-6)
    two_pi = np.float32(2 * np.pi)
    turn = 1.0 / (2.0 * np.pi)
    zero = np.float32(0.0)
    out = np.empty((size, size, 3), np.uint8)
    weights = np.empty(size, np.float32)  # one row's gradient weights
    colour_of = np.empty(size, np.uint8)  # one row's colour index, 0 or 1
    # Each row: a loop over pixels without branches on ``code`` (so LLVM can vectorise it),
    # then a loop writing the RGB bytes.
    for y in range(size):
        row_y, across_row = along_y[y], across_y[y]
        if code == 0:
            for x in range(size):
                weights[x] = ((along_x[x] + row_y) - low) / divisor
            for x in range(size):
                for k in range(3):
                    value = colours[0, k] + step[k] * weights[x] + half
                    out[y, x, k] = np.uint8(min(max(value, zero), top))
            continue
        if code == 1:
            # sin(z) > 0 for z = 2 pi along / period (float32) iff z / (2 pi) has a fractional
            # part in (0, 1/2); taken in float64, exact but for a float32 z within ~1e-16
            # relative of a multiple of pi, where NumPy's float32 sin could not tell either.
            for x in range(size):
                turns = np.float64((two_pi * (along_x[x] + row_y)) / period) * turn
                fraction = turns - math.floor(turns)
                colour_of[x] = np.uint8(fraction > 0.0) & np.uint8(fraction < 0.5)
        else:
            for x in range(size):
                cells = math.floor((along_x[x] + row_y) / period) + math.floor((across_x[x] + across_row) / period)
                colour_of[x] = np.uint8(np.int32(cells) & 1)
        for x in range(size):
            c = colour_of[x]
            out[y, x, 0] = two[c, 0]
            out[y, x, 1] = two[c, 1]
            out[y, x, 2] = two[c, 2]
    return out


def procedural_background(kind: str, size: int, rng: np.random.Generator) -> np.ndarray:
    """Seeded synthetic backgrounds: smooth colour noise, a linear gradient, stripes, a checkerboard.

    The last three are one compiled pass (_two_colour_pattern), to the bytes of their NumPy formula."""
    import cv2

    colours = rng.uniform(0, 255, size=(2, 3))
    if kind == "noise":
        # Octaves of 4, 8, 16 and 32 cells (coarse blobs plus finer grain) with amplitudes
        # halving. They are summed on the cell grids, each partial sum enlarged 2x (cubic) to
        # the next, and the sum is enlarged to the image once, as uint8: a cubic enlargement
        # of 2x steps looks like one of the whole factor, and one uint8 resize of the image
        # costs ~1/15 of four float32 ones.
        total, amplitude, noise = 0.0, 1.0, None
        for cells in (4, 8, 16, 32):
            grid = rng.uniform(0, 255, size=(cells, cells, 3)).astype(np.float32)
            if noise is None:
                noise = grid
            else:
                noise = cv2.resize(noise, (cells, cells), interpolation=cv2.INTER_CUBIC)
                noise += np.float32(amplitude) * grid
            total += amplitude
            amplitude *= 0.5
        small = np.clip(noise / np.float32(total) + 0.5, 0, 255).astype(np.uint8)
        return cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)  # saturates like the clip
    elif kind in ("gradient", "stripes", "checker"):
        angle = rng.uniform(0, np.pi)
        period = 0.0
        if kind == "stripes":
            period = rng.uniform(0.05, 0.3)
        elif kind == "checker":
            period = rng.uniform(0.08, 0.3)
        return _two_colour_pattern(
            _PATTERN_CODES[kind],
            size,
            colours.astype(np.float32),
            np.float32(np.cos(angle)),
            np.float32(np.sin(angle)),
            np.float32(period),
        )
    else:
        raise AssetError(f"unknown procedural background {kind!r}; known: {', '.join(PROCEDURAL_BACKGROUNDS)}")


def _config_key(config) -> tuple:
    if config is None:
        return (None, None, None, 5, None)
    folder = lambda path: None if path is None else str(Path(path).expanduser().resolve())  # noqa: E731
    return (
        folder(config.objects),
        folder(config.backgrounds),
        folder(config.occluders),
        config.n_objects,
        folder(config.lookalikes),
    )


def load_assets(config=None) -> AssetCatalog:
    """The asset catalog of an ``AssetsConfig`` (None: the built-in defaults), cached per process."""
    return _load_assets_cached(_config_key(config))


@lru_cache(maxsize=16)
def _load_assets_cached(key: tuple) -> AssetCatalog:
    objects_dir, backgrounds_dir, occluders_dir, n_objects, lookalikes_dir = key
    if objects_dir is None:
        objects = _builtin(BUILTIN_OBJECTS[:n_objects], keep_alpha=False)
    else:
        objects = _folder_assets(Path(objects_dir), "objects", keep_alpha=False, name_by_stem=True)
        for asset in objects:  # few and essential: decode now so a broken texture fails before any work
            asset.load()
    if backgrounds_dir is None:
        backgrounds = _builtin(BUILTIN_BACKGROUNDS, keep_alpha=False) + [
            Asset(PROCEDURAL_PREFIX + kind, _procedural_placeholder, source="procedural")
            for kind in PROCEDURAL_BACKGROUNDS
        ]
    else:
        backgrounds = _folder_assets(Path(backgrounds_dir), "backgrounds", keep_alpha=False, name_by_stem=False)
    if occluders_dir is None:
        occluders = _builtin(BUILTIN_OCCLUDERS, keep_alpha=True)
    else:
        occluders = _folder_assets(Path(occluders_dir), "occluders", keep_alpha=True, name_by_stem=False)
    lookalikes = []
    if lookalikes_dir is not None:
        lookalikes = _folder_assets(Path(lookalikes_dir), "lookalikes", keep_alpha=False, name_by_stem=True)
        for asset in lookalikes:  # few, and drawn in every image: a broken one fails before any work
            asset.load()
    return AssetCatalog(objects, backgrounds, occluders, lookalikes)
