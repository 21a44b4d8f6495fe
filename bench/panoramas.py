"""Photographs that no training path reads, for bench/wild.py's held-apart set: three of Blender's
studio-light panoramas, tone-mapped to JPEG.

foldwise's training backgrounds and occluders are scikit-image's photographs, and so are the
ground and clutter of wild.py's first two out-of-domain sets. Its third set covers them with
photographs the detector has never seen; three of them are panoramas of places that ship with
Blender (``bpy``'s ``datafiles/studiolights/world``, CC0, Greg Zaal / Poly Haven: see
data/panoramas/LICENSE.txt). They are HDR (OpenEXR); this module turns each into an 8-bit
photograph once, and the JPEGs are committed, so the set needs no OpenEXR reader:

    python bench/panoramas.py            # rewrite bench/data/panoramas/*.jpg

Each panorama's rows within 15% of a pole are dropped (the equirectangular projection stretches
them), and Reinhard's global operator (OpenCV's, gamma 2.2) maps the rest to 8 bits.
"""

from __future__ import annotations

import os
from pathlib import Path

FOLDER = Path(__file__).resolve().parent / "data" / "panoramas"
NAMES = ("night", "studio", "sunrise")
POLE_MARGIN = 0.15
JPEG_QUALITY = 92


def path(name: str) -> Path:
    """The committed JPEG of panorama ``name``."""
    if name not in NAMES:
        raise KeyError(f"unknown panorama {name!r}; known: {', '.join(NAMES)}")
    return FOLDER / f"{name}.jpg"


def studiolights_folder() -> Path:
    """bpy's folder of world panoramas (found without importing bpy)."""
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("bpy is not installed: its studio-light panoramas are the source")
    root = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(root.glob("*/datafiles/studiolights/world"))
    if not found:
        raise FileNotFoundError(f"no datafiles/studiolights/world under {root}")
    return found[-1]


def derive(out: Path = FOLDER, source: Path | None = None) -> list[Path]:
    """Write ``<name>.jpg`` for every panorama of NAMES into ``out``; returns the paths written."""
    # OpenCV reads EXR only when this is set before its first EXR read in the process.
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2
    import numpy as np

    source = source or studiolights_folder()
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in NAMES:
        hdr = cv2.imread(str(source / f"{name}.exr"), cv2.IMREAD_UNCHANGED)
        if hdr is None:
            raise FileNotFoundError(f"cannot read {source / f'{name}.exr'}")
        rows = hdr.shape[0]
        hdr = np.ascontiguousarray(hdr[round(rows * POLE_MARGIN) : round(rows * (1 - POLE_MARGIN)), :, :3])
        ldr = cv2.createTonemapReinhard(gamma=2.2, intensity=0.0, light_adapt=0.8, color_adapt=0.0).process(hdr)
        image = np.clip(np.nan_to_num(ldr) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        target = out / f"{name}.jpg"
        cv2.imwrite(str(target), image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        written.append(target)
    return written


if __name__ == "__main__":
    for written in derive():
        print(written)
