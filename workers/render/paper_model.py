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
ends too near a corner or strips narrower than ``min_strip`` are redrawn.

Self-intersection (``SelfIntersection``, the caller resamples): a sheet whose bends add up
past ``max_total_bend`` (270°) between two regions curls into itself; otherwise every two
regions that do not share a ruling are tested as the planar convex polygons they are (exact,
cheap, done before meshing), counting layers closer than ``clearance`` as touching.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from os import PathLike
from typing import Any, Sequence

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
    """Perimeter coordinate ``s`` in [0, 2(W+H)), counter-clockwise from the corner (0, 0)."""

    def __init__(self, width: float, height: float):
        self.width = width
        self.height = height
        self.length = 2.0 * (width + height)
        self.corners = np.array([0.0, width, width + height, 2.0 * width + height])
        self.breaks = np.append(self.corners, self.length)  # side k is [breaks[k], breaks[k + 1]]
        self.corner_points = np.array([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]])
        self._corner_x = np.array([0.0, width, width, 0.0, 0.0])  # at each break, back to (0, 0)
        self._corner_y = np.array([0.0, 0.0, height, height, 0.0])

    def points(self, s: np.ndarray) -> np.ndarray:
        """(n, 2) flat points at perimeter positions ``s`` (any real numbers, taken modulo)."""
        s = np.asarray(s, np.float64).ravel() % self.length
        out = np.empty((len(s), 2))
        # x and y are piecewise linear in s between the corners; the clamp keeps round-off
        # from pushing a border point off the sheet (uv stays in [0, 1]).
        out[:, 0] = np.interp(s, self.breaks, self._corner_x)
        out[:, 1] = np.interp(s, self.breaks, self._corner_y)
        return np.minimum(np.maximum(out, 0.0, out=out), (self.width, self.height), out=out)

    def point(self, s: float) -> Point:
        x, y = self.points(np.array([s]))[0].tolist()
        return (x, y)

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
        raise ValueError(
            f"need 0 <= min_angle <= max_angle < pi, got min_angle={min_angle!r}, max_angle={max_angle!r}"
        )
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


@dataclass(frozen=True)
class _Chords:
    """Every fold line, as arrays: perimeter positions of both ends (all p0 ends, then all p1
    ends), their flat points, and the angles."""

    ends: np.ndarray  # (2n,) perimeter positions
    end_points: np.ndarray  # (2n, 2)
    angle: np.ndarray  # (n,) radians

    def __len__(self) -> int:
        return len(self.angle)

    @property
    def s0(self) -> np.ndarray:
        return self.ends[: len(self.angle)]

    @property
    def s1(self) -> np.ndarray:
        return self.ends[len(self.angle) :]

    @property
    def p0(self) -> np.ndarray:
        return self.end_points[: len(self.angle)]

    @property
    def p1(self) -> np.ndarray:
        return self.end_points[len(self.angle) :]

    def as_rulings(self) -> list[Ruling]:
        return _rulings(self.end_points, self.angle)


def _rulings(end_points: np.ndarray, angle: np.ndarray) -> list[Ruling]:
    """Rulings ((x0, y0), (x1, y1), angle) in plain floats; ``end_points``: all p0 then all p1."""
    n = len(angle)
    ends = [tuple(point) for point in end_points.tolist()]
    return list(zip(ends[:n], ends[n:], angle.tolist()))


def _expand(border: _Border, guides: np.ndarray, options: _Options) -> _Chords:
    """Interpolated rulings: each guiding ruling (s0, s1, angle) becomes a nested family
    (s0 + o, s1 - o) of ``smooth_steps`` rulings sharing its angle equally."""
    m = options.smooth_steps
    offsets = (np.arange(m) - (m - 1) / 2.0) * options.bend_spacing
    n = len(guides) * m
    ends = np.empty(2 * n)
    ends[:n] = (guides[:, :1] + offsets).ravel()
    ends[n:] = (guides[:, 1:2] - offsets).ravel()
    ends %= border.length
    return _Chords(ends, border.points(ends), np.repeat(guides[:, 2] / m, m))


def _guide_rulings(border: _Border, guides: np.ndarray) -> list[Ruling]:
    return _rulings(border.points(np.concatenate([guides[:, 0], guides[:, 1]])), guides[:, 2])


def _validate_layout(border: _Border, chords: _Chords, options: _Options) -> None:
    """RulingLayoutError naming the first problem: ends at corners or on one side, ends nearly
    shared, crossing rulings, strips narrower than ``min_strip``."""
    n = len(chords)
    if n == 0:
        return
    ends = chords.ends  # end k belongs to chord k % n
    side = np.searchsorted(border.breaks, ends, side="right") - 1
    to_corner = np.minimum(ends - border.breaks[side], border.breaks[side + 1] - ends)
    if to_corner.min() < options.corner_gap:
        x, y = border.point(ends[np.argmax(to_corner < options.corner_gap)])
        raise RulingLayoutError(f"ruling end ({x:.4g}, {y:.4g}) is within {options.corner_gap:.3g} of a sheet corner")
    same_side = side[:n] == side[n:]
    if same_side.any():
        names = ["bottom", "right", "top", "left"]
        raise RulingLayoutError(f"a ruling has both ends on the {names[side[np.argmax(same_side)]]} side")
    if n < 2:
        return
    # Around the border: the closest two ends of different rulings are neighbours (only ends of
    # one of those two rulings could lie between them, and they would be closer still).
    order = np.argsort(ends, kind="stable")
    around = ends[order]
    gaps = np.concatenate([around[1:], around[:1] + border.length]) - around
    chord_around = order % n
    different = chord_around != np.concatenate([chord_around[1:], chord_around[:1]])
    too_close = different & (gaps < options.min_strip)
    if too_close.any():
        raise RulingLayoutError(
            f"two rulings have ends only {gaps[np.argmax(too_close)]:.3g} apart (min_strip {options.min_strip:.3g})"
        )
    # Two chords cross exactly when their ends alternate along the border: read around it,
    # non-crossing chords pair up like nested brackets.
    open_chords: list[int] = []
    for chord in chord_around.tolist():
        if open_chords and open_chords[-1] == chord:
            open_chords.pop()
        else:
            open_chords.append(chord)
    if open_chords:
        raise RulingLayoutError("two rulings cross inside the sheet")
    # Segments that do not cross are closest at an end of one of them: (2n, n) squared
    # distances from every end to every ruling.
    points = chords.end_points
    x0, y0 = points[:n, 0], points[:n, 1]
    dx, dy = points[n:, 0] - x0, points[n:, 1] - y0
    ex = points[:, :1] - x0  # from each ruling's p0 to every end
    ey = points[:, 1:] - y0
    t = np.minimum(np.maximum((ex * dx + ey * dy) / (dx * dx + dy * dy), 0.0), 1.0)
    ex -= t * dx
    ey -= t * dy
    squared = ex * ex + ey * ey
    from_ends = np.minimum(squared[:n], squared[n:])  # [i, j]: ends of ruling i to ruling j
    np.fill_diagonal(from_ends, np.inf)
    closest = float(np.sqrt(np.min(from_ends)))
    if closest < options.min_strip:
        raise RulingLayoutError(
            f"two rulings come within {closest:.3g} of each other (min_strip {options.min_strip:.3g})"
        )


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


def _sample_guides(n: int, rng: np.random.Generator, border: _Border, options: _Options) -> np.ndarray | None:
    """Guiding rulings as (n, 3) rows (s0, s1, angle) with nested ends on two arcs split by
    two corners, or None when no pair of corners leaves room for ``n`` rulings."""
    half_band = (options.smooth_steps - 1) / 2.0 * options.bend_spacing
    # Ruling ends (interpolated ones included) keep corner_gap from every corner: from the two
    # corners that bound the arcs, and from the corner in the middle of an arc (if any).
    keep_off = options.corner_gap + half_band
    spacing = 2.0 * half_band + options.min_gap  # between neighbouring guiding rulings' centres
    splits = _arc_splits(border.width, border.height, n, keep_off, spacing)
    if not splits:
        return None
    start, arc_a, arc_b = splits[int(rng.integers(len(splits)))]

    def increasing(free: float, inner_corners: tuple[float, ...]) -> np.ndarray:
        # Uniform among positions at least `spacing` apart (sorted uniforms on the arc shortened
        # by the gaps), then opened up around the arc's inner corners.
        positions = keep_off + np.sort(rng.uniform(0.0, free, n)) + spacing * np.arange(n)
        for corner in inner_corners:
            positions[positions >= corner - keep_off] += 2 * keep_off
        return positions

    along_a, along_b = increasing(*arc_a), increasing(*arc_b)
    guides = np.empty((n, 3))
    guides[:, 0] = (start + along_a) % border.length
    guides[:, 1] = (start - along_b) % border.length
    guides[:, 2] = rng.uniform(options.min_angle, options.max_angle, n)
    guides[:, 2] *= rng.integers(0, 2, n) * 2.0 - 1.0  # the sign rng.choice([-1, 1], n) would draw
    return guides


# -- regions ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    """The sheet cut by its rulings. Vertex ids: 0-3 the sheet corners (counter-clockwise from
    (0, 0)), then 4 + 2c and 5 + 2c the ends p0 and p1 of chord c. Regions' corners are
    stacked: region r's, counter-clockwise, are ``ids[start[r] : start[r] + counts[r]]``."""

    points: np.ndarray  # (4 + 2n, 2) flat vertex positions
    ids: np.ndarray  # stacked region corners
    corner_lists: list[list[int]]  # the same, region by region
    counts: np.ndarray  # corners per region
    start: np.ndarray  # where each region's corners begin in ids
    crossings: np.ndarray  # (2n, 2) (start id, end id): each region's rulings as it traverses them
    first_crossing: np.ndarray  # where each region's rows begin in crossings (stacked region by region)
    sides: list[list[tuple[int, int, int]]]  # per chord: its two (region, start id, end id)

    @property
    def polygons(self) -> list[np.ndarray]:
        return [np.array(corners) for corners in self.corner_lists]


def _trace_layout(border: _Border, chords: _Chords) -> _Layout:
    """Walk the border counter-clockwise; at each ruling end, jump along the ruling to its
    other end and walk on: every closed walk is one region, traced counter-clockwise."""
    n = len(chords)
    points = np.empty((4 + 2 * n, 2))
    points[:4], points[4::2], points[5::2] = border.corner_points, chords.p0, chords.p1
    if n == 0:
        whole = [0, 1, 2, 3]
        return _Layout(points, np.array(whole), [whole], np.array([4]), np.array([0]), np.zeros((0, 2), np.int64),
                       np.array([0]), [])
    positions = np.empty(4 + 2 * n)
    positions[:4], positions[4::2], positions[5::2] = border.corners, chords.s0, chords.s1
    sequence = np.argsort(positions, kind="stable").tolist()
    first_end = 0
    while sequence[first_end] < 4:
        first_end += 1
    sequence = sequence[first_end:] + sequence[:first_end]
    # For each end (by vertex id): the sheet corners after it along the border, and the next end.
    corners_after: list[list[int]] = [[] for _ in range(4 + 2 * n)]
    next_end = [0] * (4 + 2 * n)
    current = sequence[0]
    for vertex in sequence[1:]:
        if vertex >= 4:
            next_end[current] = current = vertex
        else:
            corners_after[current].append(vertex)
    next_end[current] = sequence[0]

    visited = [False] * (4 + 2 * n)
    corner_lists: list[list[int]] = []
    crossings: list[tuple[int, int]] = []
    first_crossing: list[int] = []
    sides: list[list[tuple[int, int, int]]] = [[] for _ in range(n)]
    for first in sequence:
        if first < 4 or visited[first]:
            continue
        region, corners = len(corner_lists), []
        first_crossing.append(len(crossings))
        current = first
        while True:
            visited[current] = True
            following = next_end[current]
            partner = following ^ 1  # the other end of the same ruling (ids 4 + 2c, 5 + 2c)
            corners += [current, *corners_after[current], following]
            chord = (following - 4) >> 1
            crossings.append((following, partner))
            sides[chord].append((region, following, partner))
            current = partner
            if current == first:
                break
        corner_lists.append(corners)
    counts = [len(corners) for corners in corner_lists]
    start = [0] * len(counts)
    for r in range(1, len(counts)):
        start[r] = start[r - 1] + counts[r - 1]
    return _Layout(
        points,
        np.array([vertex for corners in corner_lists for vertex in corners]),
        corner_lists,
        np.array(counts),
        np.array(start),
        np.array(crossings, np.int64),
        np.array(first_crossing),
        sides,
    )


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


def _local_transforms(a: np.ndarray, b: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(n, 4, 4) homogeneous rotations by ``angles`` about the lines through a[i] and b[i],
    points of the z = 0 plane (Rodrigues with a horizontal axis, entry by entry; positive =
    counter-clockwise looking from b towards a)."""
    ux, uy = (b[:, 0] - a[:, 0]), (b[:, 1] - a[:, 1])
    length = np.hypot(ux, uy)
    ux, uy = ux / length, uy / length
    sin, cos = np.sin(angles), np.cos(angles)
    versine = 1.0 - cos
    transforms = np.zeros((len(a), 4, 4))
    transforms[:, 0, 0] = cos + ux * ux * versine
    transforms[:, 0, 1] = transforms[:, 1, 0] = ux * uy * versine
    transforms[:, 0, 2], transforms[:, 2, 0] = uy * sin, -uy * sin
    transforms[:, 1, 1] = cos + uy * uy * versine
    transforms[:, 1, 2], transforms[:, 2, 1] = -ux * sin, ux * sin
    transforms[:, 2, 2] = cos
    transforms[:, 3, 3] = 1.0
    # The line stays put: translation a - R a (a has z = 0).
    ax, ay = a[:, 0], a[:, 1]
    transforms[:, :3, 3] = a - transforms[:, :3, 0] * ax[:, None] - transforms[:, :3, 1] * ay[:, None]
    return transforms


# -- meshes ----------------------------------------------------------------------------------


def _sin2_smallest_angle(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """sin² of the smallest angle of triangles with corner coordinates ``x``, ``y`` (..., 3)
    (0 when degenerate or clockwise). The smallest angle faces the shortest edge:
    sin = 2 area a_min / (a b c)."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    y0, y1, y2 = y[..., 0], y[..., 1], y[..., 2]
    ax, ay, bx, by, cx, cy = x1 - x0, y1 - y0, x2 - x1, y2 - y1, x0 - x2, y0 - y2
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    twice_area = ax * by - ay * bx
    sin2 = twice_area * twice_area * np.minimum(np.minimum(a2, b2), c2) / np.maximum(a2 * b2 * c2, 1e-300)
    return np.where(twice_area > 0.0, sin2, 0.0)


@lru_cache(maxsize=64)
def _fan_corners(most: int) -> np.ndarray:
    """(most, most - 2, 3) corner positions (a, a + j, a + j + 1), before the modulo by a
    region's corner count: fan from apex a, triangle j."""
    apex = np.arange(most)[:, None]
    step = np.arange(1, most - 1)[None]
    table = np.empty((most, most - 2, 3), np.int64)
    table[..., 0], table[..., 1], table[..., 2] = apex, apex + step, apex + step + 1
    table.setflags(write=False)
    return table


def _delaunay_polygon(corners: list[list[float]]) -> list[tuple[int, int, int]]:
    """The Delaunay triangulation of a strictly convex polygon (counter-clockwise corners),
    which has the largest smallest angle of all its triangulations: on each edge (i, j) it
    puts the corner that sees the edge under the widest angle (its circle holds no other
    corner), then does the same on the two new edges. Triangles (i, m, j), i < m < j, ccw."""
    triangles = []
    pending = [(0, len(corners) - 1)]
    while pending:
        i, j = pending.pop()
        (xi, yi), (xj, yj) = corners[i], corners[j]
        widest, best = 2.0, i + 1
        for m in range(i + 1, j):
            xm, ym = corners[m]
            ux, uy, vx, vy = xi - xm, yi - ym, xj - xm, yj - ym
            cosine = (ux * vx + uy * vy) / math.sqrt((ux * ux + uy * uy) * (vx * vx + vy * vy))
            if cosine < widest:
                widest, best = cosine, m
        triangles.append((i, best, j))
        pending += [(a, b) for a, b in ((i, best), (best, j)) if b - a >= 2]
    return triangles


def _minimal_mesh(layout: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """Every convex region triangulated from its corners alone, with the largest smallest
    angle possible. Up to five corners every triangulation is a fan, so the best fan is
    chosen, for all regions at once (padded to the largest corner count); regions with more
    corners (rare) get their Delaunay triangulation. Returns (faces, region of each), faces
    counter-clockwise, region by region."""
    counts = layout.counts
    n_regions, most = len(counts), int(counts.max())
    rows = np.arange(n_regions)
    padded = np.array([corners + corners[:1] * (most - len(corners)) for corners in layout.corner_lists])
    k = counts[:, None, None, None]
    triangles = padded[rows[:, None, None, None], _fan_corners(most) % k]  # (region, apex, j, 3)
    real = np.arange(most - 2) < counts[:, None] - 2  # (region, j): a k-gon's fan has k - 2 triangles
    sin2 = _sin2_smallest_angle(layout.points[:, 0][triangles], layout.points[:, 1][triangles])
    quality = np.where(real[:, None], sin2, np.inf).min(axis=2)
    quality[np.arange(most) >= counts[:, None]] = -np.inf  # apexes past the region's corners
    best = quality.argmax(axis=1)
    if not np.all(quality[rows, best] > 0.0):
        raise RuntimeError("paper model: degenerate triangle in a region (please report)")
    faces, face_regions = triangles[rows, best][real], np.repeat(rows, counts - 2)
    if most <= 5:
        return faces, face_regions
    large = np.flatnonzero(counts > 5)
    kept = counts[face_regions] <= 5
    extra = []
    for r in large.tolist():
        corners = layout.corner_lists[r]
        triangles = np.array(corners)[np.array(_delaunay_polygon(layout.points[corners].tolist()))]
        if not np.all(_sin2_smallest_angle(layout.points[triangles, 0], layout.points[triangles, 1]) > 0.0):
            raise RuntimeError("paper model: degenerate triangle in a region (please report)")
        extra.append(triangles)
    faces = np.concatenate([faces[kept], *extra])
    face_regions = np.concatenate([face_regions[kept], np.repeat(large, counts[large] - 2)])
    order = np.argsort(face_regions, kind="stable")
    return faces[order], face_regions[order]


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


# -- self-intersection ----------------------------------------------------------------------


def _clip_to_slab(polygon: list[list[float]], heights: list[float], clearance: float) -> np.ndarray:
    """The part of a convex polygon (corners as [x, y, z] lists, their heights above a plane)
    with |height| <= clearance (Sutherland-Hodgman against the two faces of the slab); with
    clearance 0, where it meets the plane. In plain floats: a handful of corners."""
    points, values = polygon, heights
    for sign in (1.0, -1.0):  # keep sign * height <= clearance
        kept_points, kept_values = [], []
        n = len(points)
        for k in range(n):
            p, q = points[k], points[(k + 1) % n]
            hp, hq = sign * values[k] - clearance, sign * values[(k + 1) % n] - clearance
            if hp <= 0:
                kept_points.append(p)
                kept_values.append(values[k])
            if (hp < 0 < hq) or (hq < 0 < hp):
                t = hp / (hp - hq)
                kept_points.append([a + t * (b - a) for a, b in zip(p, q)])
                kept_values.append(sign * clearance)  # exactly on the slab face, no round-off
        points, values = kept_points, kept_values
        if not points:
            break
    return np.array(points).reshape(-1, 3)


def _convex_sets_overlap(first: np.ndarray, second: np.ndarray) -> bool:
    """Separating-axis test for two convex 2D point sets given in boundary order (the first a
    polygon, the second a polygon, a segment or a point); touching counts as overlapping."""
    both = [first, second] if len(second) >= 2 else [first]
    edges = np.concatenate([np.append(points[1:], points[:1], axis=0) - points for points in both])
    axes = edges[np.einsum("ij,ij->i", edges, edges) > 0][:, ::-1] * (1.0, -1.0)
    a, b = first @ axes.T, second @ axes.T  # projections on every axis at once
    return not np.any((a.max(axis=0) < b.min(axis=0)) | (b.max(axis=0) < a.min(axis=0)))


@lru_cache(maxsize=64)
def _pairs_once(n: int) -> np.ndarray:
    """(n, n) bool, True above the diagonal: each unordered pair once, (a, b) with a < b."""
    mask = np.triu(np.ones((n, n), bool), k=1)
    mask.setflags(write=False)
    return mask


def _find_self_intersection(
    corners: np.ndarray, start: np.ndarray, rotations: np.ndarray, adjacent: np.ndarray, clearance: float
) -> tuple[int, int] | None:
    """The first pair of non-adjacent regions that pass through each other or come within
    ``clearance`` (measured across the plane of one of them), or None.

    Regions are planar convex polygons (``corners``: bent corner positions, stacked, region
    r's from ``start[r]``). Regions sharing a ruling meet along it and bend by less than pi there, so only
    non-adjacent pairs can cross. Two cheap exact tests, for all pairs at once, set most pairs
    apart: their bounding boxes grown by ``clearance`` miss each other, or one polygon lies
    wholly beyond ``clearance`` on one side of the other's plane. For the rest, the slice of
    one near the other's plane is compared with the other polygon inside that plane. Exact
    for crossings, coplanar overlaps included.
    """
    low = np.minimum.reduceat(corners, start, axis=0) - clearance
    high = np.maximum.reduceat(corners, start, axis=0) + clearance
    boxes_meet = ((low[:, None] <= high[None]) & (low[None] <= high[:, None])).all(axis=2)
    candidates = boxes_meet & ~adjacent & _pairs_once(len(start))
    if not candidates.any():
        return None
    normals = rotations[:, :, 2]
    origins = corners[start]
    # heights[r, k]: height of corner k above the plane of region r.
    heights = normals @ corners.T - (normals * origins).sum(axis=1)[:, None]
    above = np.maximum.reduceat(heights, start, axis=1)  # [a, b]: highest corner of b above a
    below = np.minimum.reduceat(heights, start, axis=1)
    beyond = (below > clearance) | (above < -clearance)  # [a, b]: b wholly off a's plane
    stop = np.concatenate([start[1:], [len(corners)]])
    for a, b in zip(*np.nonzero(candidates & ~beyond & ~beyond.T)):
        piece = _clip_to_slab(corners[start[b] : stop[b]].tolist(), heights[a, start[b] : stop[b]].tolist(), clearance)
        if not len(piece):
            continue
        basis = rotations[a][:, :2]
        if _convex_sets_overlap((corners[start[a] : stop[a]] - origins[a]) @ basis, (piece - origins[a]) @ basis):
            return int(a), int(b)
    return None


# -- public API ------------------------------------------------------------------------------


def _assemble(
    width: float, height: float, border: _Border, chords: _Chords, guides: list[Ruling], options: _Options
) -> SheetMesh:
    """Regions, their rigid transforms, the self-intersection checks, then the mesh."""
    layout = _trace_layout(border, chords)
    n_regions, n_chords = len(layout.counts), len(chords)

    # Region graph (a tree): each ruling borders exactly two regions.
    neighbours: list[list[tuple[int, int, int, int]]] = [[] for _ in range(n_regions)]
    first_side, second_side = [], []
    for chord_index, ((r0, s0, e0), (r1, s1, e1)) in enumerate(layout.sides):
        neighbours[r0].append((r1, chord_index, s1, e1))
        neighbours[r1].append((r0, chord_index, s0, e0))
        first_side.append(r0)
        second_side.append(r1)

    # Reference region: the one holding the sheet centre (the first, if it is on a ruling).
    # A region lies left of the rulings it traverses: how far the centre is outside it is the
    # largest distance of the centre to the right of them.
    reference = 0
    if n_chords:
        start, end = layout.points[layout.crossings[:, 0]], layout.points[layout.crossings[:, 1]]
        along, to_centre = end - start, (width / 2.0, height / 2.0) - start
        right = (along[:, 1] * to_centre[:, 0] - along[:, 0] * to_centre[:, 1]) / np.hypot(along[:, 0], along[:, 1])
        reference = int(np.argmin(np.maximum.reduceat(right, layout.first_crossing)))

    # Breadth first from the reference region: each region's parent and the ruling crossed to
    # reach it (traversed start -> end with the child on the left).
    parent = list(range(n_regions))
    via = [(0, 0, 0)] * n_regions  # (chord, start id, end id)
    depth = [0] * n_regions
    order = [reference]
    for r in order:  # grows while it is read: a breadth-first queue
        for child, chord_index, start, end in neighbours[r]:
            if child != reference and parent[child] == child:
                parent[child], via[child], depth[child] = r, (chord_index, start, end), depth[r] + 1
                order.append(child)

    # Every region's transform T_r = T_parent o Rot(ruling to the parent) and the rulings on
    # its path from the reference, composed by pointer jumping (log2(depth) batched rounds).
    # The child traverses its ruling start -> end with itself on the left, so a rotation by
    # +angle about that direction lifts it towards +z (valley fold).
    origin = np.array([width / 2.0, height / 2.0, 0.0])
    flat3 = np.zeros((len(layout.points), 3))
    flat3[:, :2] = layout.points - origin[:2]
    transforms = np.zeros((n_regions, 4, 4))
    transforms.reshape(n_regions, 16)[:, ::5] = 1.0  # identities
    on_path = np.zeros((n_regions, n_chords))
    # Each vertex moves with a region holding it: a sheet corner with its region, a ruling end
    # with the neighbour nearest the reference (both agree there, up to round-off).
    owner = np.zeros(len(layout.points), np.int64)
    owner[layout.ids] = np.repeat(np.arange(n_regions), layout.counts)
    if n_chords:
        children = np.array(order[1:])
        chord_index, start, end = np.array([via[c] for c in order[1:]]).T
        transforms[children] = _local_transforms(flat3[start], flat3[end], chords.angle[chord_index])
        on_path[children, chord_index] = 1.0
        owner[start] = owner[end] = np.array(parent)[children]
        jump = np.array(parent)
        for _ in range(max(depth).bit_length()):
            transforms = transforms[jump] @ transforms
            on_path += on_path[jump]
            jump = jump[jump]
    rotations, translations = transforms[:, :3, :3], transforms[:, :3, 3]
    moves = transforms[owner]  # flat3 has z = 0: x, y times the first two columns, plus the translation
    vertices = moves[:, :3, 0] * flat3[:, :1] + moves[:, :3, 1] * flat3[:, 1:2] + moves[:, :3, 3]

    if options.check_self_intersection and n_chords:
        # Bends adding up along a path: a sheet curled past max_total_bend is rejected. The
        # path between a and b holds the rulings on exactly one of their paths from the reference.
        to_reference = on_path @ chords.angle
        bends = to_reference[:, None] + to_reference[None] - 2.0 * ((on_path * chords.angle) @ on_path.T)
        worst = max(float(bends.max()), -float(bends.min()))
        if worst > options.max_total_bend + 1e-12:
            raise SelfIntersection(
                f"bends add up to {math.degrees(worst):.0f} degrees between two regions "
                f"(limit {math.degrees(options.max_total_bend):.0f}): the sheet would curl into itself"
            )
        # Regions are rigid planar polygons: check them before spending time on the mesh.
        adjacent = np.zeros((n_regions, n_regions), bool)
        adjacent[first_side, second_side] = adjacent[second_side, first_side] = True
        found = _find_self_intersection(vertices[layout.ids], layout.start, rotations, adjacent, options.clearance)
        if found is not None:
            raise SelfIntersection(
                f"regions {found[0]} and {found[1]} of the bent sheet pass through each other "
                f"(or come within {options.clearance:.3g} m)"
            )

    if options.max_edge is None:
        flat = layout.points
        faces, face_regions = _minimal_mesh(layout)
    else:
        flat, faces, face_regions = _refined_mesh(layout, width, height, options.max_edge)
        # The new points move with a region holding them, on a ruling with the one nearest
        # the reference, as above.
        rank = np.empty(n_regions, np.int64)
        rank[order] = np.arange(n_regions)
        owner_rank = np.full(len(flat), n_regions)
        np.minimum.at(owner_rank, faces.ravel(), np.repeat(rank[face_regions], 3))
        new = np.arange(len(layout.points), len(flat))
        new_owner = np.asarray(order)[owner_rank[new]]
        new_flat3 = np.zeros((len(new), 3))
        new_flat3[:, :2] = flat[new] - origin[:2]
        new_vertices = (rotations[new_owner] @ new_flat3[:, :, None])[:, :, 0] + translations[new_owner]
        vertices = np.concatenate([vertices, new_vertices])

    return SheetMesh(
        flat=flat,
        vertices=vertices,
        faces=faces,
        uv=flat / np.array([width, height]),
        width=float(width),
        height=float(height),
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
    border = _Border(width, height)
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
            raise RulingLayoutError(
                f"ruling {index}: bending angle {angle!r} must be finite and below pi in magnitude"
            )
        guides.append((border.position(p0, tol), border.position(p1, tol), angle))
    guides_arr = np.array(guides, np.float64).reshape(-1, 3)
    chords = _expand(border, guides_arr, options)
    _validate_layout(border, chords, options)
    return _assemble(width, height, border, chords, _guide_rulings(border, guides_arr), options)


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
    border = _Border(width, height)
    if n_rulings == 0:
        chords = _expand(border, np.zeros((0, 3)), options)
        return _assemble(width, height, border, chords, [], options)
    last_problem = None
    for _ in range(options.max_tries):
        guides = _sample_guides(int(n_rulings), rng, border, options)
        if guides is None:
            border_per_ruling = (options.smooth_steps - 1) * options.bend_spacing + options.min_gap
            raise ValueError(
                f"{n_rulings} guiding rulings do not fit on a {width:g} x {height:g} sheet with mesh_step "
                f"{options.mesh_step:g} (each needs about {border_per_ruling:.3g} of border on both ends): "
                "use fewer rulings, fewer smooth_steps or a smaller mesh_step"
            )
        chords = _expand(border, guides, options)
        try:
            _validate_layout(border, chords, options)
        except RulingLayoutError as problem:
            last_problem = problem
            continue
        return _assemble(width, height, border, chords, _guide_rulings(border, guides), options)
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
