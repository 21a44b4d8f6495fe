"""Random isometric deformations of a rectangular sheet (Perriollat & Bartoli 2013).

A developable sheet bends only along straight *rulings*: segments with both ends on the
border, on two different sides, never crossing one another. The rulings cut the W×H
rectangle into convex regions; each region moves rigidly, by the product of the rotations
about the rulings on its path from the *reference* region (the one holding the sheet centre,
which stays fixed). Two regions that share a ruling apply the same transform to it, so the
bent surface is exactly isometric to the flat sheet -- provided the mesh has its vertices ON
the rulings and no triangle straddles one (a regular grid pushed through the region
transforms would shorten every edge crossing a fold).

The mesh. Every region is a convex polygon (the rectangle cut by non-crossing lines) that
stays planar, and both renderers shade per face with perspective-correct texture mapping, so
vertices inside a region add nothing to the image. By default (``max_edge=None``) the mesh is
therefore minimal and exact: its vertices are the four sheet corners and the ruling ends
(each one vertex, shared by the two regions that meet there, so the mesh is watertight), and
each region is triangulated from its corners alone, with the largest smallest angle possible.
A region's corners are strictly convex (a ruling end is never at a sheet corner and rulings
never touch), so no triangle has three collinear points. A sheet with ``n`` fold lines has
``2n + 4`` vertices and ``2n + 2`` triangles. ``max_edge`` asks for a refined mesh instead
(for displacement, say): border and rulings subdivided into edges no longer than it, and
grid points inside each region, Delaunay-triangulated region by region.

Conventions (see ``SheetMesh``): flat coordinates in metres in ``[0, W] x [0, H]`` (x right,
y up); the 3D sheet frame puts the flat point (x, y) at (x - W/2, y - H/2, 0) before
bending; faces are counter-clockwise in the flat frame, so normals point to +z. A positive
bending angle is a valley fold seen from +z: the sheet on both sides of the ruling turns
towards +z (with the reference region fixed, the far side lifts).

Guiding rulings: ``n`` of them (canonical 2, easy 3, medium 5, hard 8). A smooth bend rather
than a crease splits each guiding ruling into ``smooth_steps`` interpolated rulings whose end
points step along the border (a nested family, so they never cross), each carrying an equal
share of the guiding angle.

Sampling never produces crossing rulings by construction: two sheet corners split the border
into arcs A and B; the guiding rulings' ends are drawn as increasing positions along A and
along B and the i-th of A is paired with the i-th of B (nested chords never alternate along
the perimeter). Arcs A and B share no side, so both ends of a ruling are on different sides.
Every chain of non-crossing rulings arises this way for some pair of corners. Layouts with
ends too near a corner or strips narrower than ``min_strip`` are redrawn. Each layout draws,
in this order: the pair of corners (``rng.integers``), the arc positions on A and on B and
the angles (one ``rng.random(3n)``, scaled as ``rng.uniform`` would), then the angles' signs
(``rng.integers(0, 2, n)``).

Self-intersection (``SelfIntersection``, the caller resamples): a sheet whose bends add up
past ``max_total_bend`` (270°) between two regions curls into itself; otherwise every two
regions that do not share a ruling are tested as the planar convex polygons they are (exact,
cheap, done before meshing), counting layers closer than ``clearance`` as touching.

Cost. A sheet has few regions (one more than its fold lines), so array code would spend its
time on per-call overhead: the layout checks, the regions and their transforms, the
self-intersection tests and the minimal mesh run as compiled loops instead (numba, no
fastmath: the same draw gives the same bytes), a tenth of a millisecond or two per sheet.
They compile on the first call after the source changes (some seconds) and are cached on
disk after that.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from os import PathLike
from typing import Any

import numba
import numpy as np

Point = tuple[float, float]
Ruling = tuple[Point, Point, float]

# Relative outward bulge given to boundary points before Delaunay triangulation (refined mesh
# only): it makes collinear boundary points strictly convex, so Qhull keeps every one of them
# as a hull vertex and never builds a triangle from three points of one straight edge (its
# circumcircle, of radius ~600 edge lengths, always holds another point of the region).
_BULGE = 2e-4
# A refined mesh with more grid points than this is a mistake (max_edge far too small).
_MAX_GRID_POINTS = 1_000_000

_OPTION_NAMES = {
    "mesh_step",
    "max_edge",
    "smooth_steps",
    "bend_spacing",
    "min_gap",
    "corner_gap",
    "min_strip",
    "max_total_bend",
    "clearance",
    "check_self_intersection",
    "min_angle",
    "max_angle",
    "max_tries",
}


class SelfIntersection(ValueError):
    """The bent sheet passes through itself (or curls further than a sheet plausibly does).

    ``reason`` says why; the caller resamples the deformation and records it.
    """

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class RulingLayoutError(ValueError):
    """Rulings that cannot make a valid sheet (crossing, on one side, too close, ...)."""


@dataclass(frozen=True, eq=False)
class SheetMesh:
    """A bent sheet: the flat mesh and its isometric image.

    ``flat``: (V, 2) float64 vertex positions on the flat sheet, metres, in [0, W] x [0, H].
    ``vertices``: (V, 3) float64 deformed positions in the sheet frame (flat point (x, y)
    sits at (x - W/2, y - H/2, 0) before bending; the region holding the centre is fixed).
    ``faces``: (F, 3) int64, counter-clockwise in the flat frame (normals +z before bending),
    grouped region by region.
    ``uv``: (V, 2) = flat / (W, H). ``rulings``: the guiding rulings ``(p0, p1, angle)``
    (flat end points, bending angle in radians, positive = valley fold seen from +z).
    ``fold_lines``: every ruling the mesh actually folds along, same format: the
    ``smooth_steps`` interpolated rulings of each guiding ruling in turn, each with its share
    of the angle. ``face_regions``: (F,) index of the rigid region each face belongs to.
    """

    flat: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    width: float
    height: float
    rulings: list[Ruling]
    fold_lines: list[Ruling] = field(default_factory=list)
    face_regions: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


# -- the border as a closed curve -----------------------------------------------------------


class _Border:
    """Perimeter coordinate ``s`` in [0, 2(W+H)), counter-clockwise from the corner (0, 0).
    Read-only once made (shared: see ``_border``)."""

    def __init__(self, width: float, height: float):
        self.width = width
        self.height = height
        self.length = 2.0 * (width + height)
        self.corner_s = np.array([0.0, width, width + height, 2.0 * width + height])
        self.breaks = np.append(self.corner_s, self.length)  # side k is [breaks[k], breaks[k + 1]]
        self.corner_points = np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]])
        self.corner_x = np.array([0.0, width, width, 0.0, 0.0])  # at each break, back to (0, 0)
        self.corner_y = np.array([0.0, 0.0, height, height, 0.0])
        self.size = np.array([width, height])
        for array in (self.corner_s, self.breaks, self.corner_points, self.corner_x, self.corner_y, self.size):
            array.setflags(write=False)

    def position(self, point: Sequence[float], tol: float) -> float:
        """``s`` of a border point; RulingLayoutError when the point is off the border."""
        x, y = float(point[0]), float(point[1])
        w, h = self.width, self.height
        if not (-tol <= x <= w + tol and -tol <= y <= h + tol):
            raise RulingLayoutError(f"ruling end ({x:.6g}, {y:.6g}) lies outside the {w:g} x {h:g} sheet")
        distances = [abs(y), abs(x - w), abs(y - h), abs(x)]
        side = int(np.argmin(distances))
        if distances[side] > tol:
            raise RulingLayoutError(f"ruling end ({x:.6g}, {y:.6g}) is not on the sheet border")
        x, y = min(max(x, 0.0), w), min(max(y, 0.0), h)
        return [x, w + y, w + h + (w - x), 2 * w + h + (h - y)][side] % self.length


@lru_cache(maxsize=64)
def _border(width: float, height: float) -> _Border:
    """One _Border per sheet size: the pipeline draws many sheets of few sizes."""
    return _Border(width, height)


# -- options ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Options:
    mesh_step: float
    max_edge: float | None
    smooth_steps: int
    bend_spacing: float
    min_gap: float
    corner_gap: float
    min_strip: float
    max_total_bend: float
    clearance: float
    check_self_intersection: bool
    min_angle: float
    max_angle: float
    max_tries: int


def _positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


def _options(width: float, height: float, opts: dict) -> _Options:
    """The options in force: ``opts`` checked, the defaults filled in (those of a sheet size,
    when ``opts`` is empty, made once: _Options is immutable, so sharing it is safe)."""
    if not opts:
        return _default_options(width, height)
    return _parse_options(width, height, opts)


@lru_cache(maxsize=64)
def _default_options(width: float, height: float) -> _Options:
    return _parse_options(width, height, {})


def _parse_options(width: float, height: float, opts: dict) -> _Options:
    unknown = sorted(set(opts) - _OPTION_NAMES)
    if unknown:
        raise TypeError(
            f"unknown paper model option(s) {', '.join(unknown)}; known: {', '.join(sorted(_OPTION_NAMES))}"
        )

    def get(name: str, default: Any) -> Any:
        value = opts.get(name)
        return default if value is None else value

    default_step = min(math.sqrt(width * height) / 16.0, min(width, height) / 4.0)
    mesh_step = _positive("mesh_step", get("mesh_step", default_step))
    if mesh_step > min(width, height):
        raise ValueError(f"mesh_step {mesh_step:g} is larger than the sheet's short side {min(width, height):g}")
    max_edge = opts.get("max_edge")
    if max_edge is not None:
        max_edge = _positive("max_edge", max_edge)
        if (width / max_edge) * (height / max_edge) > _MAX_GRID_POINTS:
            raise ValueError(
                f"max_edge {max_edge:g} on a {width:g} x {height:g} sheet would make a mesh of over "
                f"{_MAX_GRID_POINTS} vertices"
            )
    smooth_steps = get("smooth_steps", 3)
    if isinstance(smooth_steps, bool) or not isinstance(smooth_steps, (int, np.integer)) or smooth_steps < 1:
        raise ValueError(f"smooth_steps must be an integer >= 1 (1 = sharp crease), got {smooth_steps!r}")
    min_angle = float(get("min_angle", math.radians(10.0)))
    max_angle = float(get("max_angle", math.radians(50.0)))
    if not (0.0 <= min_angle <= max_angle < math.pi):
        raise ValueError(f"need 0 <= min_angle <= max_angle < pi, got min_angle={min_angle!r}, max_angle={max_angle!r}")
    max_tries = get("max_tries", 200)
    if isinstance(max_tries, bool) or not isinstance(max_tries, (int, np.integer)) or max_tries < 1:
        raise ValueError(f"max_tries must be an integer >= 1, got {max_tries!r}")
    clearance = float(get("clearance", 2e-3 * max(width, height)))
    if not (math.isfinite(clearance) and clearance >= 0):
        raise ValueError(f"clearance must be a non-negative finite number, got {clearance!r}")
    options = _Options(
        mesh_step=mesh_step,
        max_edge=max_edge,
        smooth_steps=int(smooth_steps),
        bend_spacing=_positive("bend_spacing", get("bend_spacing", 0.75 * mesh_step)),
        min_gap=_positive("min_gap", get("min_gap", mesh_step)),
        corner_gap=_positive("corner_gap", get("corner_gap", 0.5 * mesh_step)),
        min_strip=_positive("min_strip", get("min_strip", 0.3 * mesh_step)),
        max_total_bend=_positive("max_total_bend", get("max_total_bend", 1.5 * math.pi)),
        clearance=clearance,
        check_self_intersection=bool(get("check_self_intersection", True)),
        min_angle=min_angle,
        max_angle=max_angle,
        max_tries=int(max_tries),
    )
    if options.smooth_steps > 1 and options.bend_spacing < options.min_strip:
        raise ValueError(
            f"bend_spacing {options.bend_spacing:g} is below min_strip {options.min_strip:g}: "
            "the interpolated rulings of one bend would always be too close"
        )
    return options


def _check_sheet_size(width: Any, height: Any) -> tuple[float, float]:
    return _positive("width", width), _positive("height", height)


# -- rulings ---------------------------------------------------------------------------------

# What _chords_and_problem found wrong with a layout (0: nothing).
_NEAR_CORNER, _ONE_SIDE, _ENDS_CLOSE, _CROSSING, _STRIP_NARROW = 1, 2, 3, 4, 5
_SIDE_NAMES = ("bottom", "right", "top", "left")


@dataclass(frozen=True)
class _Chords:
    """Every fold line, as arrays: perimeter positions of both ends (all p0 ends, then all p1
    ends), their flat points, and the angles."""

    ends: np.ndarray  # (2n,) perimeter positions
    end_points: np.ndarray  # (2n, 2)
    angle: np.ndarray  # (n,) radians

    def as_rulings(self) -> list[Ruling]:
        return _rulings(self.end_points, self.angle)


def _rulings(end_points: np.ndarray, angle: np.ndarray) -> list[Ruling]:
    """Rulings ((x0, y0), (x1, y1), angle) in plain floats; ``end_points``: all p0 then all p1."""
    n = len(angle)
    ends = list(map(tuple, end_points.tolist()))
    return list(zip(ends[:n], ends[n:], angle.tolist()))


@numba.njit(cache=True, nogil=True)
def _border_points(s, length, breaks, corner_x, corner_y, width, height):  # pragma: no cover - compiled
    """(n, 2) flat points at perimeter positions ``s`` (taken modulo ``length``): x and y are
    piecewise linear in s between the corners, computed as np.interp does (slope times offset
    plus the value at the break before), then clamped so that round-off never pushes a border
    point off the sheet (uv stays in [0, 1])."""
    out = np.empty((len(s), 2))
    for i in range(len(s)):
        at = s[i] % length
        if at >= breaks[4]:  # the modulo rounded up to the full length: back at (0, 0)
            x, y = corner_x[4], corner_y[4]
        else:
            side = 3
            while breaks[side] > at:
                side -= 1
            if breaks[side] == at:
                x, y = corner_x[side], corner_y[side]
            else:
                run = breaks[side + 1] - breaks[side]
                x = (corner_x[side + 1] - corner_x[side]) / run * (at - breaks[side]) + corner_x[side]
                y = (corner_y[side + 1] - corner_y[side]) / run * (at - breaks[side]) + corner_y[side]
        out[i, 0] = min(max(x, 0.0), width)
        out[i, 1] = min(max(y, 0.0), height)
    return out


@numba.njit(cache=True, nogil=True)
def _chords_and_problem(
    guides, steps, bend_spacing, length, breaks, corner_x, corner_y, width, height, corner_gap, min_strip
):  # pragma: no cover - compiled
    """The fold lines of guiding rulings ``(s0, s1, angle)`` and the first problem of their
    layout. Each guiding ruling becomes a nested family (s0 + o, s1 - o) of ``steps`` rulings
    sharing its angle equally (offsets o ``bend_spacing`` apart, centred on 0).

    Returns (ends (2n,), end points (2n, 2), angles (n,), guide end points (2 n_guides, 2),
    problem, where, value): problem 0 when the layout is valid, else the first of
    _NEAR_CORNER (``where``: the end), _ONE_SIDE (``where``: the side), _ENDS_CLOSE
    (``value``: the gap along the border), _CROSSING, _STRIP_NARROW (``value``: the
    distance), checked in that order.
    """
    n_guides = guides.shape[0]
    n = n_guides * steps
    ends = np.empty(2 * n)
    angle = np.empty(n)
    for g in range(n_guides):
        share = guides[g, 2] / steps
        for k in range(steps):
            offset = (k - (steps - 1) / 2.0) * bend_spacing
            ends[g * steps + k] = (guides[g, 0] + offset) % length
            ends[n + g * steps + k] = (guides[g, 1] - offset) % length
            angle[g * steps + k] = share
    points = _border_points(ends, length, breaks, corner_x, corner_y, width, height)
    guide_ends = np.empty(2 * n_guides)
    guide_ends[:n_guides] = guides[:, 0]
    guide_ends[n_guides:] = guides[:, 1]
    guide_points = _border_points(guide_ends, length, breaks, corner_x, corner_y, width, height)
    if n == 0:
        return ends, points, angle, guide_points, 0, 0, 0.0

    # Ends at corners (end k belongs to chord k % n), then chords with both ends on one side.
    side = np.empty(2 * n, np.int64)
    for k in range(2 * n):
        s = 0
        while s < 4 and breaks[s + 1] <= ends[k]:
            s += 1
        side[k] = s
        to_corner = 0.0 if s == 4 else min(ends[k] - breaks[s], breaks[s + 1] - ends[k])
        if to_corner < corner_gap:
            return ends, points, angle, guide_points, _NEAR_CORNER, k, 0.0
    for c in range(n):
        if side[c] == side[n + c]:
            return ends, points, angle, guide_points, _ONE_SIDE, side[c], 0.0
    if n < 2:
        return ends, points, angle, guide_points, 0, 0, 0.0

    # Around the border: the closest two ends of different rulings are neighbours (only ends of
    # one of those two rulings could lie between them, and they would be closer still).
    order = np.argsort(ends, kind="mergesort")
    for i in range(2 * n):
        following = order[(i + 1) % (2 * n)]
        if i + 1 < 2 * n:
            gap = ends[following] - ends[order[i]]
        else:
            gap = ends[following] + length - ends[order[i]]
        if order[i] % n != following % n and gap < min_strip:
            return ends, points, angle, guide_points, _ENDS_CLOSE, 0, gap
    # Two chords cross exactly when their ends alternate along the border: read around it,
    # non-crossing chords pair up like nested brackets.
    open_chords = np.empty(2 * n, np.int64)
    n_open = 0
    for i in range(2 * n):
        chord = order[i] % n
        if n_open and open_chords[n_open - 1] == chord:
            n_open -= 1
        else:
            open_chords[n_open] = chord
            n_open += 1
    if n_open:
        return ends, points, angle, guide_points, _CROSSING, 0, 0.0
    # Segments that do not cross are closest at an end of one of them: every end against
    # every other ruling.
    closest = np.inf
    for j in range(n):
        x0, y0 = points[j, 0], points[j, 1]
        dx, dy = points[n + j, 0] - x0, points[n + j, 1] - y0
        for k in range(2 * n):
            if k % n == j:
                continue
            ex, ey = points[k, 0] - x0, points[k, 1] - y0
            t = min(max((ex * dx + ey * dy) / (dx * dx + dy * dy), 0.0), 1.0)
            ex -= t * dx
            ey -= t * dy
            closest = min(closest, ex * ex + ey * ey)
    closest = math.sqrt(closest)
    if closest < min_strip:
        return ends, points, angle, guide_points, _STRIP_NARROW, 0, closest
    return ends, points, angle, guide_points, 0, 0, 0.0


def _chords(border: _Border, guides: np.ndarray, options: _Options) -> tuple[_Chords, list[Ruling], str | None]:
    """The fold lines of guiding rulings (n, 3) rows (s0, s1, angle), the guiding rulings as
    ``Ruling`` tuples, and what is wrong with the layout (None when it is valid: no end near a
    corner, no ruling with both ends on one side, no two ends of different rulings closer
    than ``min_strip`` along the border, no crossing, no strip narrower than ``min_strip``)."""
    return _checked(guides, *_chords_and_problem(guides, *_layout_arguments(border, options)), options)


def _layout_arguments(border: _Border, options: _Options) -> tuple:
    return (
        options.smooth_steps,
        options.bend_spacing,
        border.length,
        border.breaks,
        border.corner_x,
        border.corner_y,
        border.width,
        border.height,
        options.corner_gap,
        options.min_strip,
    )


def _checked(
    guides: np.ndarray,
    ends: np.ndarray,
    end_points: np.ndarray,
    angle: np.ndarray,
    guide_points: np.ndarray,
    problem: int,
    where: int,
    value: float,
    options: _Options,
) -> tuple[_Chords, list[Ruling], str | None]:
    """_chords' answer from _chords_and_problem's: the problem, if any, in words."""
    chords = _Chords(ends, end_points, angle)
    if problem == 0:
        return chords, _rulings(guide_points, guides[:, 2]), None
    if problem == _NEAR_CORNER:
        x, y = end_points[where].tolist()
        message = f"ruling end ({x:.4g}, {y:.4g}) is within {options.corner_gap:.3g} of a sheet corner"
    elif problem == _ONE_SIDE:
        message = f"a ruling has both ends on the {_SIDE_NAMES[where]} side"
    elif problem == _ENDS_CLOSE:
        message = f"two rulings have ends only {value:.3g} apart (min_strip {options.min_strip:.3g})"
    elif problem == _CROSSING:
        message = "two rulings cross inside the sheet"
    else:
        message = f"two rulings come within {value:.3g} of each other (min_strip {options.min_strip:.3g})"
    return chords, [], message


@lru_cache(maxsize=256)
def _arc_splits(
    width: float, height: float, n: int, keep_off: float, spacing: float
) -> tuple[tuple[float, tuple[float, tuple[float, ...]], tuple[float, tuple[float, ...]]], ...]:
    """Pairs of corners i < j that leave room for ``n`` guiding rulings on both arcs between
    them, as (corner i's position, (free length, inner corners) of arc A, same of arc B)."""
    length = 2.0 * (width + height)
    corners = [0.0, width, width + height, 2.0 * width + height]
    splits = []
    for i in range(4):
        for j in range(i + 1, 4):
            arc_a = corners[j] - corners[i]
            inner_a = tuple(c - corners[i] for c in corners[i + 1 : j])
            inner_b = tuple(sorted((corners[i] - c) % length for c in (*corners[:i], *corners[j + 1 :])))
            free_a = arc_a - 2 * keep_off * (1 + len(inner_a)) - (n - 1) * spacing
            free_b = length - arc_a - 2 * keep_off * (1 + len(inner_b)) - (n - 1) * spacing
            if min(free_a, free_b) > 0:
                splits.append((corners[i], (free_a, inner_a), (free_b, inner_b)))
    return tuple(splits)


@dataclass(frozen=True)
class _GuideSampler:
    """What drawing ``n`` guiding rulings needs besides the generator: the pairs of corners
    that leave room for them (_arc_splits), as rows (corner i's position, then free length
    and inner corners (NaN where fewer than two) of arc A, then the same of arc B), and the
    spacings."""

    splits: np.ndarray  # (k, 7)
    keep_off: float  # ruling centres (of interpolated families) from the corners
    spacing: float  # between neighbouring guiding rulings' centres


@lru_cache(maxsize=256)
def _guide_sampler(width: float, height: float, n: int, options: _Options) -> _GuideSampler | None:
    """The sampler of ``n`` guiding rulings on a sheet, or None when no pair of corners leaves
    room for them."""
    half_band = (options.smooth_steps - 1) / 2.0 * options.bend_spacing
    # Ruling ends (interpolated ones included) keep corner_gap from every corner: from the two
    # corners that bound the arcs, and from the corner in the middle of an arc (if any).
    keep_off = options.corner_gap + half_band
    spacing = 2.0 * half_band + options.min_gap
    splits = _arc_splits(width, height, n, keep_off, spacing)
    if not splits:
        return None
    rows = np.full((len(splits), 7), np.nan)
    for row, (start, (free_a, inner_a), (free_b, inner_b)) in zip(rows, splits):
        row[0], row[1], row[4] = start, free_a, free_b
        row[2 : 2 + len(inner_a)], row[5 : 5 + len(inner_b)] = inner_a, inner_b
    rows.setflags(write=False)
    return _GuideSampler(rows, keep_off, spacing)


@numba.njit(cache=True, nogil=True)
def _place_guides(split, unit, signs, keep_off, spacing, min_angle, angle_span, length):  # pragma: no cover - compiled
    """Guiding rulings as (n, 3) rows (s0, s1, angle) from one row of _GuideSampler.splits and
    the draws: ``unit``, 3n uniforms in [0, 1) (arc A, arc B, angles), ``signs``, n draws of
    0 or 1. On each arc: positions uniform among those at least ``spacing`` apart (sorted
    uniforms on the arc shortened by the gaps), opened up around the arc's inner corners. The
    i-th of A is paired with the i-th of B. The arithmetic is that of rng.uniform and
    np.sort, to the bit (free * sorted u is sorted free * u: scaling keeps the order)."""
    n = len(signs)
    guides = np.empty((n, 3))
    start = split[0]
    for arc in range(2):
        free = split[1 + 3 * arc]
        draws = np.sort(unit[arc * n : (arc + 1) * n])
        for i in range(n):
            position = keep_off + free * draws[i] + spacing * i
            for corner in split[2 + 3 * arc : 4 + 3 * arc]:
                if position >= corner - keep_off:  # False for NaN: no such corner
                    position += 2 * keep_off
            guides[i, arc] = (start + position) % length if arc == 0 else (start - position) % length
    for i in range(n):
        guides[i, 2] = (min_angle + angle_span * unit[2 * n + i]) * (signs[i] * 2.0 - 1.0)
    return guides


@numba.njit(cache=True, nogil=True)
def _sampled_chords_and_problem(
    split,
    unit,
    signs,
    keep_off,
    spacing,
    min_angle,
    angle_span,
    steps,
    bend_spacing,
    length,
    breaks,
    corner_x,
    corner_y,
    width,
    height,
    corner_gap,
    min_strip,
):  # pragma: no cover - compiled
    """_place_guides, then _chords_and_problem: (guides, then what that returns)."""
    guides = _place_guides(split, unit, signs, keep_off, spacing, min_angle, angle_span, length)
    ends, points, angle, guide_points, problem, where, value = _chords_and_problem(
        guides, steps, bend_spacing, length, breaks, corner_x, corner_y, width, height, corner_gap, min_strip
    )
    return guides, ends, points, angle, guide_points, problem, where, value


def _sample_chords(
    n: int, rng: np.random.Generator, border: _Border, sampler: _GuideSampler, options: _Options
) -> tuple[_Chords, list[Ruling], str | None]:
    """One random layout of ``n`` guiding rulings, as _chords answers. Draws, in order: the
    pair of corners, 3n uniforms (rng.uniform(low, high, n) is low + (high - low) *
    rng.random(n): the doubles of arc A, arc B and the angles in one call), the n signs
    (those rng.choice([-1, 1], n) would draw)."""
    split = sampler.splits[int(rng.integers(len(sampler.splits)))]
    unit = rng.random(3 * n)
    signs = rng.integers(0, 2, n)
    guides, *answer = _sampled_chords_and_problem(
        split,
        unit,
        signs,
        sampler.keep_off,
        sampler.spacing,
        options.min_angle,
        options.max_angle - options.min_angle,
        *_layout_arguments(border, options),
    )
    return _checked(guides, *answer, options)


# -- regions, transforms, self-intersection, minimal mesh (compiled) --------------------------
#
# The sheet has few regions (one more than its fold lines), so array code spends its time on
# per-call overhead; these loops run compiled instead (numba, no fastmath: the same input
# gives the same bytes). Sheet vertex ids: 0-3 the sheet corners (counter-clockwise from
# (0, 0)), then 4 + 2c and 5 + 2c the ends p0 and p1 of chord c. Regions' corners are stacked:
# region r's, counter-clockwise, are ids[start[r] : start[r] + counts[r]].

_CURLED, _CROSSED, _DEGENERATE = 1, 2, 3  # what _sheet_geometry found wrong (0: nothing)


@numba.njit(cache=True, nogil=True)
def _trace_regions(positions, n):  # pragma: no cover - compiled
    """Walk the border counter-clockwise (``positions``: perimeter position of every vertex
    id); at each ruling end, jump along the ruling to its other end and walk on: every closed
    walk is one region, traced counter-clockwise. Returns the stacked region corners (ids,
    counts, start), each region's rulings as it traverses them ((start id, end id) rows,
    region by region from first_crossing[r]) and, per chord, its two sides (region, start id,
    end id)."""
    n_vertices = 4 + 2 * n
    if n == 0:
        whole = np.arange(4)
        return (
            whole,
            np.full(1, 4),
            np.zeros(1, np.int64),
            np.zeros((0, 2), np.int64),
            np.zeros(1, np.int64),
            np.zeros((0, 2, 3), np.int64),
        )
    sorted_ids = np.argsort(positions, kind="mergesort")
    first_end = 0
    while sorted_ids[first_end] < 4:
        first_end += 1
    sequence = np.concatenate((sorted_ids[first_end:], sorted_ids[:first_end]))
    # For each end (by vertex id): the sheet corners after it along the border, and the next end.
    corners_after = np.zeros((n_vertices, 4), np.int64)
    n_after = np.zeros(n_vertices, np.int64)
    next_end = np.zeros(n_vertices, np.int64)
    current = sequence[0]
    for vertex in sequence[1:]:
        if vertex >= 4:
            next_end[current] = vertex
            current = vertex
        else:
            corners_after[current, n_after[current]] = vertex
            n_after[current] += 1
    next_end[current] = sequence[0]

    # A valid layout has n + 1 regions and 4n + 4 stacked corners (every end opens one step of
    # a walk, which lists it, the corners after it and the next end).
    visited = np.zeros(n_vertices, np.bool_)
    ids = np.empty(4 * n + 4, np.int64)
    counts = np.zeros(n + 1, np.int64)
    start = np.zeros(n + 1, np.int64)
    crossings = np.empty((2 * n, 2), np.int64)
    first_crossing = np.zeros(n + 1, np.int64)
    sides = np.empty((n, 2, 3), np.int64)
    n_sides = np.zeros(n, np.int64)
    n_ids, n_regions, n_crossings = 0, 0, 0
    for first in sequence:
        if first < 4 or visited[first]:
            continue
        region = n_regions
        n_regions += 1
        start[region] = n_ids
        first_crossing[region] = n_crossings
        current = first
        while True:
            visited[current] = True
            following = next_end[current]
            partner = following ^ 1  # the other end of the same ruling (ids 4 + 2c, 5 + 2c)
            ids[n_ids] = current
            n_ids += 1
            for k in range(n_after[current]):
                ids[n_ids] = corners_after[current, k]
                n_ids += 1
            ids[n_ids] = following
            n_ids += 1
            chord = (following - 4) >> 1
            crossings[n_crossings, 0], crossings[n_crossings, 1] = following, partner
            n_crossings += 1
            sides[chord, n_sides[chord], 0] = region
            sides[chord, n_sides[chord], 1] = following
            sides[chord, n_sides[chord], 2] = partner
            n_sides[chord] += 1
            current = partner
            if current == first:
                break
        counts[region] = n_ids - start[region]
    return ids, counts, start, crossings, first_crossing, sides


@numba.njit(cache=True, nogil=True)
def _sin2_smallest_angle(points, a, b, c):  # pragma: no cover - compiled
    """sin² of the smallest angle of the triangle of vertex ids a, b, c (0 when degenerate or
    clockwise). The smallest angle faces the shortest edge: sin = 2 area a_min / (a b c)."""
    x0, y0, x1, y1, x2, y2 = points[a, 0], points[a, 1], points[b, 0], points[b, 1], points[c, 0], points[c, 1]
    ax, ay, bx, by, cx, cy = x1 - x0, y1 - y0, x2 - x1, y2 - y1, x0 - x2, y0 - y2
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    twice_area = ax * by - ay * bx
    if not twice_area > 0.0:
        return 0.0
    return twice_area * twice_area * min(min(a2, b2), c2) / max(a2 * b2 * c2, 1e-300)


@numba.njit(cache=True, nogil=True)
def _minimal_faces(points, ids, counts, start):  # pragma: no cover - compiled
    """Every convex region triangulated from its corners alone, with the largest smallest
    angle possible. Up to five corners every triangulation is a fan: the fan from the corner
    whose worst triangle is best (the first such corner on a tie). More corners (rare): the
    Delaunay triangulation, which has the largest smallest angle of all triangulations: on
    each edge (i, j) of a pending piece it puts the corner m that sees the edge under the
    widest angle (its circle holds no other corner), giving triangle (i, m, j), then does the
    same on the two new edges. Returns (faces, region of each, ok), faces counter-clockwise,
    region by region; ok is False when a triangle is degenerate (which convex regions with
    strictly convex corners never give)."""
    n_regions = len(counts)
    n_faces = 0
    for r in range(n_regions):
        n_faces += counts[r] - 2
    faces = np.empty((n_faces, 3), np.int64)
    face_regions = np.empty(n_faces, np.int64)
    f = 0
    for r in range(n_regions):
        k = counts[r]
        corners = ids[start[r] : start[r] + k]
        if k <= 5:
            best_apex, best_quality = 0, -np.inf
            for apex in range(k):
                quality = np.inf
                for j in range(k - 2):
                    quality = min(
                        quality,
                        _sin2_smallest_angle(
                            points, corners[apex], corners[(apex + j + 1) % k], corners[(apex + j + 2) % k]
                        ),
                    )
                if quality > best_quality:
                    best_apex, best_quality = apex, quality
            if not best_quality > 0.0:
                return faces, face_regions, False
            for j in range(k - 2):
                faces[f, 0] = corners[best_apex]
                faces[f, 1] = corners[(best_apex + j + 1) % k]
                faces[f, 2] = corners[(best_apex + j + 2) % k]
                face_regions[f] = r
                f += 1
            continue
        pending = np.empty((k, 2), np.int64)  # a stack of corner intervals (i, j)
        pending[0, 0], pending[0, 1] = 0, k - 1
        n_pending = 1
        while n_pending:
            n_pending -= 1
            i, j = pending[n_pending, 0], pending[n_pending, 1]
            xi, yi = points[corners[i], 0], points[corners[i], 1]
            xj, yj = points[corners[j], 0], points[corners[j], 1]
            widest, best = 2.0, i + 1
            for m in range(i + 1, j):
                xm, ym = points[corners[m], 0], points[corners[m], 1]
                ux, uy, vx, vy = xi - xm, yi - ym, xj - xm, yj - ym
                cosine = (ux * vx + uy * vy) / math.sqrt((ux * ux + uy * uy) * (vx * vx + vy * vy))
                if cosine < widest:
                    widest, best = cosine, m
            faces[f, 0], faces[f, 1], faces[f, 2] = corners[i], corners[best], corners[j]
            face_regions[f] = r
            if not _sin2_smallest_angle(points, corners[i], corners[best], corners[j]) > 0.0:
                return faces, face_regions, False
            f += 1
            if best - i >= 2:
                pending[n_pending, 0], pending[n_pending, 1] = i, best
                n_pending += 1
            if j - best >= 2:
                pending[n_pending, 0], pending[n_pending, 1] = best, j
                n_pending += 1
    return faces, face_regions, True


@numba.njit(cache=True, nogil=True)
def _worst_bend(order, parent, angle_to_parent):  # pragma: no cover - compiled
    """The largest |sum of bending angles| over the rulings on the path between two regions
    of the region tree (``order``: breadth first from its root; ``angle_to_parent``: the
    angle of the ruling between a region and its parent). Children before parents, each
    region keeps the largest and smallest sums down a path from it; a path with its top at
    a region joins two of those (or one and the empty path)."""
    n_regions = len(order)
    down_max = np.zeros(n_regions)
    down_min = np.zeros(n_regions)
    worst = 0.0
    for q in range(n_regions - 1, 0, -1):
        child = order[q]
        top = parent[child]
        longest = angle_to_parent[child] + down_max[child]
        lowest = angle_to_parent[child] + down_min[child]
        worst = max(worst, down_max[top] + longest, -(down_min[top] + lowest))
        down_max[top] = max(down_max[top], longest)
        down_min[top] = min(down_min[top], lowest)
    return worst


@numba.njit(cache=True, nogil=True)
def _clip_to_slab(polygon, heights, clearance):  # pragma: no cover - compiled
    """The part of a convex polygon ((k, 3) corners, their heights above a plane) with
    |height| <= clearance (Sutherland-Hodgman against the two faces of the slab); with
    clearance 0, where it meets the plane. Returns (points, count)."""
    points, values, n = polygon.copy(), heights.copy(), len(heights)
    for sign in (1.0, -1.0):  # keep sign * height <= clearance
        kept_points = np.empty((2 * n + 1, 3))
        kept_values = np.empty(2 * n + 1)
        kept = 0
        for k in range(n):
            following = (k + 1) % n
            hp, hq = sign * values[k] - clearance, sign * values[following] - clearance
            if hp <= 0:
                kept_points[kept] = points[k]
                kept_values[kept] = values[k]
                kept += 1
            if (hp < 0 < hq) or (hq < 0 < hp):
                t = hp / (hp - hq)
                for axis in range(3):
                    a = points[k, axis]
                    kept_points[kept, axis] = a + t * (points[following, axis] - a)
                kept_values[kept] = sign * clearance  # exactly on the slab face, no round-off
                kept += 1
        points, values, n = kept_points, kept_values, kept
        if n == 0:
            break
    return points, n


@numba.njit(cache=True, nogil=True)
def _convex_sets_overlap(first, n_first, second, n_second):  # pragma: no cover - compiled
    """Separating-axis test for two convex 2D point sets given in boundary order (the first a
    polygon, the second a polygon, a segment or a point): overlapping unless the projections
    on the normal of some edge of either are apart; touching counts as overlapping."""
    for which in range(2 if n_second >= 2 else 1):
        shape, count = (first, n_first) if which == 0 else (second, n_second)
        for k in range(count):
            # The axis: the edge from corner k to the next, turned a quarter clockwise.
            ex = shape[(k + 1) % count, 0] - shape[k, 0]
            ey = shape[(k + 1) % count, 1] - shape[k, 1]
            if not ex * ex + ey * ey > 0:
                continue
            low_a, high_a, low_b, high_b = np.inf, -np.inf, np.inf, -np.inf
            for i in range(n_first):
                projection = first[i, 0] * ey - first[i, 1] * ex
                low_a, high_a = min(low_a, projection), max(high_a, projection)
            for i in range(n_second):
                projection = second[i, 0] * ey - second[i, 1] * ex
                low_b, high_b = min(low_b, projection), max(high_b, projection)
            if high_a < low_b or high_b < low_a:
                return False
    return True


@numba.njit(cache=True, nogil=True)
def _in_plane(corners, origin, rotation):  # pragma: no cover - compiled
    """(k, 2) coordinates of 3D points in the plane of a region (its first corner ``origin``
    and the first two columns of its rotation)."""
    out = np.empty((len(corners), 2))
    for i in range(len(corners)):
        for axis in range(2):
            out[i, axis] = (
                (corners[i, 0] - origin[0]) * rotation[0, axis]
                + (corners[i, 1] - origin[1]) * rotation[1, axis]
                + (corners[i, 2] - origin[2]) * rotation[2, axis]
            )
    return out


@numba.njit(cache=True, nogil=True)
def _heights(corners, origin, normal):  # pragma: no cover - compiled
    """Heights of 3D points above the plane through ``origin`` with unit ``normal``."""
    offset = normal[0] * origin[0] + normal[1] * origin[1] + normal[2] * origin[2]
    out = np.empty(len(corners))
    for i in range(len(corners)):
        out[i] = normal[0] * corners[i, 0] + normal[1] * corners[i, 1] + normal[2] * corners[i, 2] - offset
    return out


@numba.njit(cache=True, nogil=True)
def _wholly_beyond(corners, origin, normal, clearance):  # pragma: no cover - compiled
    """Whether 3D points all lie further than ``clearance`` on one side of the plane through
    ``origin`` with unit ``normal`` (the heights of _heights, without making the array)."""
    offset = normal[0] * origin[0] + normal[1] * origin[1] + normal[2] * origin[2]
    lowest, highest = np.inf, -np.inf
    for i in range(len(corners)):
        height = normal[0] * corners[i, 0] + normal[1] * corners[i, 1] + normal[2] * corners[i, 2] - offset
        lowest, highest = min(lowest, height), max(highest, height)
    return lowest > clearance or highest < -clearance


@numba.njit(cache=True, nogil=True)
def _self_intersection(corners, start, counts, rotations, adjacent, clearance):  # pragma: no cover - compiled
    """The first pair (a, b), a < b, of non-adjacent regions that pass through each other or
    come within ``clearance`` (measured across the plane of one of them), or (-1, -1).

    Regions are planar convex polygons (``corners``: bent corner positions, stacked). Regions
    sharing a ruling meet along it and bend by less than pi there, so only non-adjacent pairs
    can cross. Two cheap exact tests set most pairs apart: their bounding boxes grown by
    ``clearance`` miss each other, or one polygon lies wholly beyond ``clearance`` on one side
    of the other's plane. For the rest, the slice of b near a's plane is compared with a
    inside that plane. Exact for crossings, coplanar overlaps included.
    """
    n_regions = len(counts)
    low = np.empty((n_regions, 3))
    high = np.empty((n_regions, 3))
    for r in range(n_regions):
        for axis in range(3):
            values = corners[start[r] : start[r] + counts[r], axis]
            low[r, axis] = values.min() - clearance
            high[r, axis] = values.max() + clearance
    for a in range(n_regions):
        corners_a = corners[start[a] : start[a] + counts[a]]
        for b in range(a + 1, n_regions):
            if adjacent[a, b]:
                continue
            apart = False
            for axis in range(3):
                if not (low[a, axis] <= high[b, axis] and low[b, axis] <= high[a, axis]):
                    apart = True
            if apart:
                continue
            corners_b = corners[start[b] : start[b] + counts[b]]
            if _wholly_beyond(corners_b, corners_a[0], rotations[a, :, 2], clearance) or _wholly_beyond(
                corners_a, corners_b[0], rotations[b, :, 2], clearance
            ):
                continue
            piece, n_piece = _clip_to_slab(corners_b, _heights(corners_b, corners_a[0], rotations[a, :, 2]), clearance)
            if n_piece == 0:
                continue
            if _convex_sets_overlap(
                _in_plane(corners_a, corners_a[0], rotations[a]),
                len(corners_a),
                _in_plane(piece[:n_piece], corners_a[0], rotations[a]),
                n_piece,
            ):
                return a, b
    return -1, -1


@numba.njit(cache=True, nogil=True)
def _regions_and_frames(ends, end_points, angle, corner_s, corner_points, width, height):  # pragma: no cover - compiled
    """The regions of a valid layout of chords (``ends``: perimeter positions, all p0 then all
    p1; ``end_points`` the same as flat points; ``angle`` per chord) and their rigid
    transforms. Returns (flat (4 + 2n, 2), bent vertices, ids, counts, start, adjacent
    (R, R) bool, breadth-first order from the reference region, parent of each region,
    angle of the ruling to the parent, rotations (R, 3, 3), translations (R, 3))."""
    n = len(angle)
    n_vertices = 4 + 2 * n
    points = np.empty((n_vertices, 2))
    positions = np.empty(n_vertices)
    points[:4] = corner_points
    positions[:4] = corner_s
    for c in range(n):
        points[4 + 2 * c] = end_points[c]
        points[5 + 2 * c] = end_points[n + c]
        positions[4 + 2 * c], positions[5 + 2 * c] = ends[c], ends[n + c]
    ids, counts, start, crossings, first_crossing, sides = _trace_regions(positions, n)
    n_regions = len(counts)

    # Region graph (a tree): each ruling borders exactly two regions. Neighbours of each
    # region (region, chord, start id, end id of the ruling as the neighbour traverses it),
    # in chord order.
    neighbour_start = np.zeros(n_regions + 1, np.int64)
    for c in range(n):
        neighbour_start[sides[c, 0, 0] + 1] += 1
        neighbour_start[sides[c, 1, 0] + 1] += 1
    for r in range(n_regions):
        neighbour_start[r + 1] += neighbour_start[r]
    filled = neighbour_start[:-1].copy()
    neighbour_region = np.empty(2 * n, np.int64)
    neighbour_chord = np.empty(2 * n, np.int64)
    neighbour_ends = np.empty((2 * n, 2), np.int64)
    adjacent = np.zeros((n_regions, n_regions), np.bool_)
    for c in range(n):
        for side in range(2):
            r, other = sides[c, side, 0], sides[c, 1 - side, 0]
            e = filled[r]
            filled[r] += 1
            neighbour_region[e], neighbour_chord[e] = other, c
            neighbour_ends[e, 0], neighbour_ends[e, 1] = sides[c, 1 - side, 1], sides[c, 1 - side, 2]
            adjacent[r, other] = True

    # Reference region: the one holding the sheet centre (the first, if it is on a ruling).
    # A region lies left of the rulings it traverses: how far the centre is outside it is the
    # largest distance of the centre to the right of them.
    reference = 0
    if n:
        least = np.inf
        for r in range(n_regions):
            outside = -np.inf
            stop = first_crossing[r + 1] if r + 1 < n_regions else len(crossings)
            for k in range(first_crossing[r], stop):
                sx, sy = points[crossings[k, 0], 0], points[crossings[k, 0], 1]
                ax, ay = points[crossings[k, 1], 0] - sx, points[crossings[k, 1], 1] - sy
                cx, cy = width / 2.0 - sx, height / 2.0 - sy
                outside = max(outside, (ay * cx - ax * cy) / np.hypot(ax, ay))
            if outside < least:
                least, reference = outside, r

    # Breadth first from the reference region; every region's transform is its parent's
    # composed with the rotation about the ruling between them. The child traverses that
    # ruling start -> end with itself on the left, so a rotation by +angle about that
    # direction lifts it towards +z (valley fold). Points are centred: flat (x, y) sits at
    # (x - W/2, y - H/2, 0) before bending.
    centred = np.empty((n_vertices, 2))
    for v in range(n_vertices):
        centred[v, 0], centred[v, 1] = points[v, 0] - width / 2.0, points[v, 1] - height / 2.0
    rotations = np.zeros((n_regions, 3, 3))
    translations = np.zeros((n_regions, 3))
    rotations[reference, 0, 0] = rotations[reference, 1, 1] = rotations[reference, 2, 2] = 1.0
    # Each vertex moves with a region holding it: a sheet corner with its region, a ruling end
    # with the neighbour nearest the reference (both agree there, up to round-off).
    owner = np.zeros(n_vertices, np.int64)
    for r in range(n_regions):
        for i in range(start[r], start[r] + counts[r]):
            owner[ids[i]] = r
    order = np.empty(n_regions, np.int64)
    parent_of = np.zeros(n_regions, np.int64)
    angle_to_parent = np.zeros(n_regions)
    placed = np.zeros(n_regions, np.bool_)
    order[0] = reference
    placed[reference] = True
    n_placed = 1
    local = np.empty((3, 3))
    for q in range(n_regions):
        if q >= n_placed:
            break
        parent = order[q]
        for e in range(neighbour_start[parent], neighbour_start[parent + 1]):
            child = neighbour_region[e]
            if placed[child]:
                continue
            placed[child] = True
            parent_of[child], angle_to_parent[child] = parent, angle[neighbour_chord[e]]
            order[n_placed] = child
            n_placed += 1
            a, b = neighbour_ends[e, 0], neighbour_ends[e, 1]
            owner[a] = owner[b] = parent
            # Rodrigues with the horizontal unit axis (ux, uy, 0) through the point a.
            ax, ay = centred[a, 0], centred[a, 1]
            ux, uy = centred[b, 0] - ax, centred[b, 1] - ay
            length = np.hypot(ux, uy)
            ux, uy = ux / length, uy / length
            sin, cos = np.sin(angle_to_parent[child]), np.cos(angle_to_parent[child])
            versine = 1.0 - cos
            local[0, 0], local[0, 1], local[0, 2] = cos + ux * ux * versine, ux * uy * versine, uy * sin
            local[1, 0], local[1, 1], local[1, 2] = ux * uy * versine, cos + uy * uy * versine, -ux * sin
            local[2, 0], local[2, 1], local[2, 2] = -uy * sin, ux * sin, cos
            # The line stays put: the local translation is a - R a (a has z = 0).
            shift_x = ax - local[0, 0] * ax - local[0, 1] * ay
            shift_y = ay - local[1, 0] * ax - local[1, 1] * ay
            shift_z = 0.0 - local[2, 0] * ax - local[2, 1] * ay
            for i in range(3):
                p0, p1, p2 = rotations[parent, i, 0], rotations[parent, i, 1], rotations[parent, i, 2]
                for j in range(3):
                    rotations[child, i, j] = p0 * local[0, j] + p1 * local[1, j] + p2 * local[2, j]
                translations[child, i] = p0 * shift_x + p1 * shift_y + p2 * shift_z + translations[parent, i]
    vertices = np.empty((n_vertices, 3))
    for v in range(n_vertices):
        r = owner[v]
        x, y = centred[v, 0], centred[v, 1]
        for i in range(3):
            vertices[v, i] = rotations[r, i, 0] * x + rotations[r, i, 1] * y + translations[r, i]
    return (points, vertices, ids, counts, start, adjacent, order, parent_of, angle_to_parent, rotations, translations)


@numba.njit(cache=True, nogil=True)
def _sheet_geometry(
    ends, end_points, angle, corner_s, corner_points, width, height, check, max_total_bend, clearance, minimal
):  # pragma: no cover - compiled
    """_regions_and_frames, the self-intersection checks, then (``minimal``) the minimal mesh.
    Returns (problem, worst bend, region a, region b, flat (4 + 2n, 2), bent vertices, faces,
    face regions); problem is 0, _CURLED (worst bend past ``max_total_bend``), _CROSSED
    (regions a and b pass through each other) or _DEGENERATE (a triangle of the minimal
    mesh); faces are empty unless ``minimal`` and problem is 0."""
    n = len(angle)
    points, vertices, ids, counts, start, adjacent, order, parent_of, angle_to_parent, rotations, _ = (
        _regions_and_frames(ends, end_points, angle, corner_s, corner_points, width, height)
    )
    problem, worst, first, second = 0, 0.0, -1, -1
    if check and n:
        # Bends adding up along a path: a sheet curled past max_total_bend is rejected.
        worst = _worst_bend(order, parent_of, angle_to_parent)
        if worst > max_total_bend + 1e-12:
            problem = _CURLED
        else:
            # Regions are rigid planar polygons: check them before spending time on the mesh.
            bent_corners = np.empty((len(ids), 3))
            for i in range(len(ids)):
                bent_corners[i] = vertices[ids[i]]
            first, second = _self_intersection(bent_corners, start, counts, rotations, adjacent, clearance)
            if first >= 0:
                problem = _CROSSED
    faces, face_regions = np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    if minimal and problem == 0:
        faces, face_regions, ok = _minimal_faces(points, ids, counts, start)
        if not ok:
            problem = _DEGENERATE
    return problem, worst, first, second, points, vertices, faces, face_regions


@numba.njit(cache=True, nogil=True)
def _sheet_frames(ends, end_points, angle, corner_s, corner_points, width, height):  # pragma: no cover - compiled
    """What the refined mesh needs of _regions_and_frames: (ids, counts, start, order,
    rotations, translations)."""
    _, _, ids, counts, start, _, order, _, _, rotations, translations = _regions_and_frames(
        ends, end_points, angle, corner_s, corner_points, width, height
    )
    return ids, counts, start, order, rotations, translations


# -- refined mesh --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    """The sheet cut by its rulings, for the refined mesh: flat vertex positions (ids as in
    _sheet_geometry) and the stacked region corners."""

    points: np.ndarray  # (4 + 2n, 2) flat vertex positions
    ids: np.ndarray  # stacked region corners, counter-clockwise per region
    counts: np.ndarray  # corners per region
    start: np.ndarray  # where each region's corners begin in ids

    @property
    def polygons(self) -> list[np.ndarray]:
        return [self.ids[s : s + k] for s, k in zip(self.start.tolist(), self.counts.tolist())]


@dataclass(frozen=True)
class _RegionEdges:
    """The corners (sheet corners and ruling ends) and edges of every region, stacked."""

    start: np.ndarray  # index of each region's first corner
    region: np.ndarray  # region of each corner
    points: np.ndarray  # (n, 2) corner positions, counter-clockwise per region
    vectors: np.ndarray  # (n, 2) edge from each corner to the next one of its region
    lengths: np.ndarray
    normals: np.ndarray  # (n, 2) unit, outward
    offsets: np.ndarray  # normals . points

    @classmethod
    def of(cls, layout: _Layout) -> _RegionEdges:
        region = np.repeat(np.arange(len(layout.counts)), layout.counts)
        following = np.arange(1, len(region) + 1)
        following[layout.start + layout.counts - 1] = layout.start  # each region's last corner
        corner_points = layout.points[layout.ids]
        vectors = corner_points[following] - corner_points
        lengths = np.sqrt(np.einsum("ij,ij->i", vectors, vectors))
        normals = vectors[:, ::-1] * (1.0, -1.0) / lengths[:, None]
        offsets = np.einsum("ij,ij->i", normals, corner_points)
        return cls(layout.start, region, corner_points, vectors, lengths, normals, offsets)

    def depth(self, query: np.ndarray) -> np.ndarray:
        """(n, regions): how far outside each region each point lies (negative: inside)."""
        return np.maximum.reduceat(query @ self.normals.T - self.offsets, self.start, axis=1)

    def areas(self) -> np.ndarray:
        following = self.points + self.vectors
        cross = self.points[:, 0] * following[:, 1] - self.points[:, 1] * following[:, 0]
        return 0.5 * np.bincount(self.region, weights=cross, minlength=len(self.start))


def _subdivide(a: np.ndarray, b: np.ndarray, step: float) -> np.ndarray:
    """Points strictly between a and b at spacing at most ``step``."""
    n = max(1, math.ceil(float(np.linalg.norm(b - a)) / step - 1e-9))
    t = np.arange(1, n)[:, None] / n
    return a + t * (b - a)


def _refined_mesh(
    layout: _Layout, width: float, height: float, max_edge: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every region triangulated from its subdivided boundary plus the grid points well inside
    it (Delaunay). Points on a ruling are made once and shared by both regions. Returns the
    flat vertices (layout points first), faces (ccw) and the region of each face."""
    from scipy.spatial import Delaunay  # noqa: PLC0415 - scipy comes with scikit-image (render extra)

    edges = _RegionEdges.of(layout)
    points = layout.points
    blocks = [points]
    n_points = len(points)
    on_edge: dict[tuple[int, int], np.ndarray] = {}
    chains, chain_edges = [], []
    for r, polygon in enumerate(layout.polygons):
        chain, chain_edge = [], []
        k = len(polygon)
        for i in range(k):
            u, v = int(polygon[i]), int(polygon[(i + 1) % k])
            key = (min(u, v), max(u, v))
            inner = on_edge.get(key)
            if inner is None:
                new = _subdivide(points[key[0]], points[key[1]], max_edge)
                inner = np.arange(n_points, n_points + len(new))
                n_points += len(new)
                blocks.append(new)
                on_edge[key] = inner
            along = [u, *(inner if u < v else inner[::-1]).tolist()]
            chain += along
            chain_edge += [edges.start[r] + i] * len(along)
        chains.append(np.array(chain))
        chain_edges.append(np.array(chain_edge))
    boundary = np.concatenate(blocks)

    # Grid points at least `margin` inside a region belong to it (to one region at most).
    nx = max(1, round(width / max_edge))
    ny = max(1, round(height / max_edge))
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) * width / nx, (np.arange(ny) + 0.5) * height / ny)
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    depth = edges.depth(grid)
    grid_region = np.where(np.any(depth <= -0.35 * max_edge, axis=1), np.argmin(depth, axis=1), -1)

    # Bulge the boundary points of every straight edge outward (see _BULGE).
    chain_all, edge = np.concatenate(chains), np.concatenate(chain_edges)
    lengths = edges.lengths[edge]
    t = np.einsum("ij,ij->i", boundary[chain_all] - edges.points[edge], edges.vectors[edge]) / lengths**2
    bulged = boundary[chain_all] + edges.normals[edge] * (_BULGE * lengths * 4.0 * t * (1.0 - t))[:, None]

    faces, face_regions, interiors = [], [], []
    chain_stop = np.cumsum([len(c) for c in chains])
    n_interior = 0
    for r, chain in enumerate(chains):
        interior = grid[grid_region == r]
        triangulation = Delaunay(np.vstack([bulged[chain_stop[r] - len(chain) : chain_stop[r]], interior]))
        if len(triangulation.coplanar):
            raise RuntimeError("paper model: Delaunay dropped boundary points of a region (please report)")
        ids = np.concatenate([chain, len(boundary) + n_interior + np.arange(len(interior))])
        faces.append(ids[triangulation.simplices])
        face_regions.append(np.full(len(triangulation.simplices), r))
        interiors.append(interior)
        n_interior += len(interior)
    flat = np.concatenate([boundary, *interiors])
    faces_arr = np.concatenate(faces).astype(np.int64)
    face_regions_arr = np.concatenate(face_regions).astype(np.int64)

    # Counter-clockwise in the true (unbulged) flat frame; no sliver; regions exactly tiled.
    tri = flat[faces_arr]
    areas = 0.5 * (
        (tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
        - (tri[:, 1, 1] - tri[:, 0, 1]) * (tri[:, 2, 0] - tri[:, 0, 0])
    )
    faces_arr[areas < 0] = faces_arr[areas < 0][:, [0, 2, 1]]
    covered = np.bincount(face_regions_arr, weights=np.abs(areas), minlength=len(layout.counts))
    if np.min(np.abs(areas)) <= 1e-9 * max_edge**2 or not np.allclose(covered, edges.areas(), rtol=1e-9, atol=0):
        raise RuntimeError("paper model: degenerate triangulation of a region (please report)")
    return flat, faces_arr, face_regions_arr


# -- public API ------------------------------------------------------------------------------


def _assemble(
    width: float, height: float, border: _Border, chords: _Chords, guides: list[Ruling], options: _Options
) -> SheetMesh:
    """Regions, their rigid transforms, the self-intersection checks, then the mesh."""
    minimal = options.max_edge is None
    sheet = (chords.ends, chords.end_points, chords.angle, border.corner_s, border.corner_points, width, height)
    problem, worst, first, second, points, vertices, faces, face_regions = _sheet_geometry(
        *sheet, options.check_self_intersection, options.max_total_bend, options.clearance, minimal
    )
    if problem == _CURLED:
        raise SelfIntersection(
            f"bends add up to {math.degrees(worst):.0f} degrees between two regions "
            f"(limit {math.degrees(options.max_total_bend):.0f}): the sheet would curl into itself"
        )
    if problem == _CROSSED:
        raise SelfIntersection(
            f"regions {first} and {second} of the bent sheet pass through each other "
            f"(or come within {options.clearance:.3g} m)"
        )
    if problem == _DEGENERATE:
        raise RuntimeError("paper model: degenerate triangle in a region (please report)")

    if minimal:
        flat = points
    else:
        ids, counts, start, order, rotations, translations = _sheet_frames(*sheet)
        layout = _Layout(points, ids, counts, start)
        flat, faces, face_regions = _refined_mesh(layout, width, height, options.max_edge)
        # The new points move with a region holding them, on a ruling with the one nearest
        # the reference (the earliest in breadth-first order), as the layout's vertices do.
        n_regions = len(counts)
        rank = np.empty(n_regions, np.int64)
        rank[order] = np.arange(n_regions)
        owner_rank = np.full(len(flat), n_regions)
        np.minimum.at(owner_rank, faces.ravel(), np.repeat(rank[face_regions], 3))
        new = np.arange(len(points), len(flat))
        new_owner = order[owner_rank[new]]
        new_flat3 = np.zeros((len(new), 3))
        new_flat3[:, :2] = flat[new] - (width / 2.0, height / 2.0)
        new_vertices = (rotations[new_owner] @ new_flat3[:, :, None])[:, :, 0] + translations[new_owner]
        vertices = np.concatenate([vertices, new_vertices])

    return SheetMesh(
        flat=flat,
        vertices=vertices,
        faces=faces,
        uv=flat / border.size,
        width=width,
        height=height,
        rulings=guides,
        fold_lines=chords.as_rulings(),
        face_regions=face_regions,
    )


def build_sheet(
    width: float, height: float, rulings: Sequence[tuple[Sequence[float], Sequence[float], float]], **opts
) -> SheetMesh:
    """A bent sheet from given guiding rulings ``(p0, p1, angle)`` (flat end points on the
    border, radians, positive = valley fold seen from +z).

    Options (all keyword, lengths in metres): ``max_edge`` (None, the default: the minimal
    exact mesh, sheet corners and ruling ends only; a length: a refined mesh, border and
    rulings subdivided into edges at most that long and grid points at that spacing inside
    every region), ``mesh_step`` (the layout's length scale, from which the spacings below
    default; default sqrt(W H)/16, at most min(W, H)/4), ``smooth_steps`` (interpolated
    rulings per guiding ruling, default 3; 1 is a sharp crease), ``bend_spacing`` (border
    distance between them, default 0.75 mesh_step), ``corner_gap`` (ruling ends kept this far
    from corners, default 0.5 mesh_step), ``min_strip`` (least distance between rulings,
    default 0.3 mesh_step), ``max_total_bend`` (radians, default 3π/2), ``clearance``
    (non-neighbouring regions closer than this count as touching, default 0.002 max(W, H)),
    ``check_self_intersection`` (default True; False skips both the curl limit and the
    geometric test).

    Raises RulingLayoutError (a ValueError) for rulings that cannot make a sheet and
    SelfIntersection when the bent sheet passes through itself.
    """
    width, height = _check_sheet_size(width, height)
    options = _options(width, height, opts)
    border = _border(width, height)
    tol = 1e-9 * max(width, height)
    guides = []
    for index, ruling in enumerate(rulings):
        try:
            p0, p1, angle = ruling
        except (TypeError, ValueError):
            raise RulingLayoutError(f"ruling {index} must be (p0, p1, angle), got {ruling!r}") from None
        try:
            angle = float(angle)
        except (TypeError, ValueError):
            raise RulingLayoutError(f"ruling {index}: bending angle must be a number, got {angle!r}") from None
        if not math.isfinite(angle) or abs(angle) >= math.pi:
            raise RulingLayoutError(f"ruling {index}: bending angle {angle!r} must be finite and below pi in magnitude")
        guides.append((border.position(p0, tol), border.position(p1, tol), angle))
    chords, guide_rulings, problem = _chords(border, np.array(guides, np.float64).reshape(-1, 3), options)
    if problem is not None:
        raise RulingLayoutError(problem)
    return _assemble(width, height, border, chords, guide_rulings, options)


def sample_sheet(n_rulings: int, rng: np.random.Generator, width: float, height: float, **opts) -> SheetMesh:
    """A randomly bent W×H sheet with ``n_rulings`` guiding rulings (0 gives the flat sheet).

    Bending angles are uniform in [min_angle, max_angle] (default 10°–50°) with a random sign.
    Deterministic for the same ``rng`` state. Raises SelfIntersection (with ``.reason``) when
    the sampled sheet passes through itself: the caller resamples. Options as in
    ``build_sheet``, plus ``min_gap`` (border distance between the interpolated families of
    two guiding rulings, default mesh_step), ``min_angle``/``max_angle`` and ``max_tries``
    (layouts drawn before giving up on the geometric constraints, default 200).
    """
    if isinstance(n_rulings, bool) or not isinstance(n_rulings, (int, np.integer)):
        raise TypeError(f"n_rulings must be an integer, got {n_rulings!r}")
    if n_rulings < 0:
        raise ValueError(f"n_rulings must be >= 0, got {n_rulings}")
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator (numpy.random.default_rng(seed)), got {type(rng).__name__}"
        )
    width, height = _check_sheet_size(width, height)
    options = _options(width, height, opts)
    border = _border(width, height)
    if n_rulings == 0:
        chords, _, _ = _chords(border, np.zeros((0, 3)), options)
        return _assemble(width, height, border, chords, [], options)
    sampler = _guide_sampler(width, height, int(n_rulings), options)
    if sampler is None:
        border_per_ruling = (options.smooth_steps - 1) * options.bend_spacing + options.min_gap
        raise ValueError(
            f"{n_rulings} guiding rulings do not fit on a {width:g} x {height:g} sheet with mesh_step "
            f"{options.mesh_step:g} (each needs about {border_per_ruling:.3g} of border on both ends): "
            "use fewer rulings, fewer smooth_steps or a smaller mesh_step"
        )
    last_problem = None
    for _ in range(options.max_tries):
        chords, guide_rulings, problem = _sample_chords(int(n_rulings), rng, border, sampler, options)
        if problem is not None:
            last_problem = problem
            continue
        return _assemble(width, height, border, chords, guide_rulings, options)
    raise ValueError(
        f"no valid layout of {n_rulings} rulings in {options.max_tries} tries; last problem: {last_problem}"
    )


def write_obj(mesh: SheetMesh, path: str | PathLike) -> None:
    """Wavefront OBJ of the bent sheet: ``v`` (sheet frame), ``vt`` (uv), ``f v/vt`` (1-based)."""
    lines = [
        "# foldwise paper model: isometrically bent sheet",
        f"# width {mesh.width:.9g} m, height {mesh.height:.9g} m, {len(mesh.rulings)} guiding rulings",
        "o sheet",
    ]
    lines += [f"v {x:.12g} {y:.12g} {z:.12g}" for x, y, z in mesh.vertices]
    lines += [f"vt {u:.12g} {v:.12g}" for u, v in mesh.uv]
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in (mesh.faces + 1)]
    with open(path, "w", encoding="ascii") as handle:
        handle.write("\n".join(lines) + "\n")
