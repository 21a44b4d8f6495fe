"""Random isometric deformations of a rectangular sheet (Perriollat & Bartoli 2013).

A developable sheet bends only along straight *rulings*: segments with both ends on the
border, on two different sides, never crossing one another. The rulings cut the W×H
rectangle into convex regions; each region moves rigidly, by the product of the rotations
about the rulings on its path from the *reference* region (the one holding the sheet centre,
which stays fixed). Two regions that share a ruling apply the same transform to it, so the
bent surface is exactly isometric to the flat sheet -- provided the mesh has its vertices ON
the rulings and no triangle straddles one. That is why every region is triangulated on its
own (boundary vertices shared along rulings and border, interior points from a grid): a
regular grid pushed through the region transforms would shorten every edge crossing a fold.

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
from collections import deque
from dataclasses import dataclass, field
from os import PathLike
from typing import Any, Sequence

import numpy as np

Point = tuple[float, float]
Ruling = tuple[Point, Point, float]

# Relative outward bulge given to boundary points before Delaunay triangulation: it makes
# collinear boundary points strictly convex, so Qhull keeps every one of them as a hull vertex
# and never builds a triangle from three points of one straight edge (its circumcircle, of
# radius ~600 edge lengths, always holds another point of the region).
_BULGE = 2e-4

_OPTION_NAMES = {
    "mesh_step",
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
    ``faces``: (F, 3) int64, counter-clockwise in the flat frame (normals +z before bending).
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

    def point(self, s: float) -> Point:
        w, h = self.width, self.height
        s = s % self.length
        if s <= w:
            x, y = s, 0.0
        elif s <= w + h:
            x, y = w, s - w
        elif s <= 2 * w + h:
            x, y = w - (s - w - h), h
        else:
            x, y = 0.0, h - (s - 2 * w - h)
        # Round-off must not push a border point off the sheet (uv stays in [0, 1]).
        return (min(max(x, 0.0), w), min(max(y, 0.0), h))

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
class _Chord:
    s0: float  # perimeter positions of the two ends
    s1: float
    p0: np.ndarray  # flat end points
    p1: np.ndarray
    angle: float


def _expand(border: _Border, guides: list[tuple[float, float, float]], options: _Options) -> list[_Chord]:
    """Interpolated rulings: each guiding ruling (s0, s1, angle) becomes a nested family
    (s0 + o, s1 - o) of ``smooth_steps`` rulings sharing its angle equally."""
    m = options.smooth_steps
    offsets = (np.arange(m) - (m - 1) / 2.0) * options.bend_spacing
    chords = []
    for s0, s1, angle in guides:
        for offset in offsets:
            a, b = (s0 + offset) % border.length, (s1 - offset) % border.length
            chords.append(_Chord(a, b, np.array(border.point(a)), np.array(border.point(b)), angle / m))
    return chords


def _point_segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points[i] to segment (a[j], b[j]), as an (n, m) array."""
    ab = (b - a)[None]
    ap = points[:, None] - a[None]
    t = np.clip(np.sum(ap * ab, axis=2) / np.sum(ab * ab, axis=2), 0.0, 1.0)
    return np.linalg.norm(ap - t[..., None] * ab, axis=2)


def _validate_layout(border: _Border, chords: list[_Chord], options: _Options) -> None:
    """RulingLayoutError naming the first problem: ends at corners or on one side, crossing
    rulings, ends nearly shared, strips narrower than ``min_strip``."""
    length = border.length
    s0 = np.array([c.s0 for c in chords])
    s1 = np.array([c.s1 for c in chords])
    ends = np.stack([s0, s1], axis=1).ravel()
    to_corner = np.abs(ends[:, None] - border.corners[None]) % length
    near = np.flatnonzero(np.minimum(to_corner, length - to_corner).min(axis=1) < options.corner_gap)
    if len(near):
        x, y = border.point(ends[near[0]])
        raise RulingLayoutError(f"ruling end ({x:.4g}, {y:.4g}) is within {options.corner_gap:.3g} of a sheet corner")
    side0, side1 = (np.searchsorted(border.corners, s % length, side="right") - 1 for s in (s0, s1))
    if np.any(side0 == side1):
        names = ["bottom", "right", "top", "left"]
        raise RulingLayoutError(f"a ruling has both ends on the {names[side0[side0 == side1][0]]} side")
    if len(chords) < 2:
        return
    p0 = np.array([c.p0 for c in chords])
    p1 = np.array([c.p1 for c in chords])
    pair = np.triu(np.ones((len(chords), len(chords)), bool), k=1)

    def cyclic(a, b):
        d = np.abs(a[:, None] - b[None]) % length
        return np.minimum(d, length - d)

    gaps = np.minimum.reduce([cyclic(s0, s0), cyclic(s0, s1), cyclic(s1, s0), cyclic(s1, s1)])
    bad = pair & (gaps < options.min_strip)
    if bad.any():
        gap = gaps[bad][0]
        raise RulingLayoutError(f"two rulings have ends only {gap:.3g} apart (min_strip {options.min_strip:.3g})")
    # Two chords cross exactly when their ends alternate along the border.
    span = ((s1 - s0) % length)[:, None]
    inside0 = (s0[None] - s0[:, None]) % length < span
    inside1 = (s1[None] - s0[:, None]) % length < span
    if np.any(pair & (inside0 != inside1)):
        raise RulingLayoutError("two rulings cross inside the sheet")
    # Segments that do not cross are closest at an end of one of them.
    distances = np.minimum.reduce(
        [
            _point_segment_distances(p0, p0, p1),
            _point_segment_distances(p1, p0, p1),
            _point_segment_distances(p0, p0, p1).T,
            _point_segment_distances(p1, p0, p1).T,
        ]
    )
    bad = pair & (distances < options.min_strip)
    if bad.any():
        raise RulingLayoutError(
            f"two rulings come within {distances[bad][0]:.3g} of each other (min_strip {options.min_strip:.3g})"
        )


def _sample_guides(
    n: int, rng: np.random.Generator, border: _Border, options: _Options
) -> list[tuple[float, float, float]] | None:
    """Guiding rulings as (s0, s1, angle) with nested ends on two arcs split by two corners,
    or None when no pair of corners leaves room for ``n`` rulings."""
    half_band = (options.smooth_steps - 1) / 2.0 * options.bend_spacing
    # Ruling ends (interpolated ones included) keep corner_gap from every corner: from the two
    # corners that bound the arcs, and from the corner in the middle of an arc (if any).
    keep_off = options.corner_gap + half_band
    spacing = 2.0 * half_band + options.min_gap  # between neighbouring guiding rulings' centres
    corners = border.corners
    splits = []
    for i in range(4):
        for j in range(i + 1, 4):
            arc_a = corners[j] - corners[i]
            inner_a = [c - corners[i] for c in corners[i + 1 : j]]
            arc_b = border.length - arc_a
            inner_b = sorted((corners[i] - c) % border.length for c in (*corners[:i], *corners[j + 1 :]))
            free_a = arc_a - 2 * keep_off * (1 + len(inner_a)) - (n - 1) * spacing
            free_b = arc_b - 2 * keep_off * (1 + len(inner_b)) - (n - 1) * spacing
            if min(free_a, free_b) > 0:
                splits.append((i, (free_a, inner_a), (free_b, inner_b)))
    if not splits:
        return None
    i, arc_a, arc_b = splits[int(rng.integers(len(splits)))]

    def increasing(free: float, inner_corners: list[float]) -> np.ndarray:
        # Uniform among positions at least `spacing` apart (sorted uniforms on the arc shortened
        # by the gaps), then opened up around the arc's inner corners.
        positions = keep_off + np.sort(rng.uniform(0.0, free, n)) + spacing * np.arange(n)
        for corner in inner_corners:
            positions[positions >= corner - keep_off] += 2 * keep_off
        return positions

    along_a, along_b = increasing(*arc_a), increasing(*arc_b)
    magnitudes = rng.uniform(options.min_angle, options.max_angle, n)
    signs = rng.choice([-1.0, 1.0], n)
    start = corners[i]
    return [
        ((start + a) % border.length, (start - b) % border.length, float(sign * magnitude))
        for a, b, sign, magnitude in zip(along_a, along_b, signs, magnitudes)
    ]


# -- regions and mesh -------------------------------------------------------------------------


@dataclass
class _Region:
    chain: list[int]  # boundary vertex ids, counter-clockwise
    corner_ids: list[int]  # the polygon's corners (sheet corners and ruling ends), counter-clockwise
    crossings: list[tuple[int, int, int]]  # (chord index, vertex id at start, vertex id at end) as traversed


def _subdivide(a: np.ndarray, b: np.ndarray, step: float) -> np.ndarray:
    """Points strictly between a and b at spacing at most ``step``."""
    n = max(1, math.ceil(np.linalg.norm(b - a) / step - 1e-9))
    t = np.arange(1, n)[:, None] / n
    return a + t * (b - a)


class _MeshBuilder:
    """Vertices on the border and on every ruling (shared by the regions on both sides), and
    the regions traced as faces of the border-plus-rulings graph."""

    def __init__(self, border: _Border, chords: list[_Chord], options: _Options):
        self.border = border
        self.chords = chords
        self.options = options
        self.blocks: list[np.ndarray] = []
        self.corner_blocks: list[np.ndarray] = []
        self.count = 0

    def _add(self, points: np.ndarray, corner: bool) -> list[int]:
        block = np.asarray(points, np.float64).reshape(-1, 2)
        self.blocks.append(block)
        self.corner_blocks.append(np.full(len(block), corner))
        self.count += len(block)
        return list(range(self.count - len(block), self.count))

    @property
    def is_corner(self) -> np.ndarray:
        return np.concatenate(self.corner_blocks)

    def build(self) -> tuple[np.ndarray, list[_Region]]:
        border, chords, step = self.border, self.chords, self.options.mesh_step
        # Border: corners and ruling ends in perimeter order, subdivided between them.
        breaks = [(float(s), ("corner", k)) for k, s in enumerate(border.corners)]
        for c_index, c in enumerate(chords):
            breaks += [(c.s0, ("end", 2 * c_index)), (c.s1, ("end", 2 * c_index + 1))]
        breaks.sort(key=lambda item: item[0])
        end_vertex: dict[int, int] = {}
        border_ids: list[int] = []
        for k, (s, (kind, key)) in enumerate(breaks):
            if kind == "end":
                chord = chords[key // 2]
                point = chord.p0 if key % 2 == 0 else chord.p1
            else:
                point = np.array(border.point(s))
            (vertex,) = self._add(point, corner=True)
            border_ids.append(vertex)
            if kind == "end":
                end_vertex[key] = vertex
            s_next = breaks[(k + 1) % len(breaks)][0]
            if k + 1 == len(breaks):
                s_next += border.length
            next_point = np.array(border.point(s_next))
            # Subdivide along the border (one side between two breaks: corners are breaks).
            border_ids += self._add(_subdivide(point, next_point, step), corner=False)
        position_in_border = {v: i for i, v in enumerate(border_ids)}
        # Rulings: interior vertices, in the direction p0 -> p1.
        ruling_inner = []
        for chord in chords:
            ruling_inner.append(self._add(_subdivide(chord.p0, chord.p1, step), corner=False))

        regions = self._trace_regions(border_ids, position_in_border, end_vertex, ruling_inner)
        return np.concatenate(self.blocks), regions

    def _trace_regions(self, border_ids, position_in_border, end_vertex, ruling_inner) -> list[_Region]:
        """Walk the border counter-clockwise; at each ruling end, jump along the ruling to its
        other end and walk on: every closed walk is one region, traced counter-clockwise."""
        n_border = len(border_ids)
        is_corner = self.is_corner
        if not self.chords:
            chain = list(border_ids)
            return [_Region(chain, [v for v in chain if is_corner[v]], [])]
        ends = sorted(end_vertex, key=lambda e: position_in_border[end_vertex[e]])
        following = {e: ends[(i + 1) % len(ends)] for i, e in enumerate(ends)}
        visited: set[int] = set()
        regions = []
        for first in ends:
            if first in visited:
                continue
            chain: list[int] = []
            crossings = []
            current = first
            while True:
                visited.add(current)
                nxt = following[current]
                # Border arc from `current` to `nxt`, counter-clockwise (end excluded).
                i, j = position_in_border[end_vertex[current]], position_in_border[end_vertex[nxt]]
                span = (j - i) % n_border
                chain += [border_ids[(i + k) % n_border] for k in range(span)]
                # Then along the ruling from `nxt` to its other end (end excluded).
                chord_index, partner = nxt // 2, nxt ^ 1
                inner = ruling_inner[chord_index] if nxt % 2 == 0 else ruling_inner[chord_index][::-1]
                chain += [end_vertex[nxt]] + inner
                crossings.append((chord_index, end_vertex[nxt], end_vertex[partner]))
                current = partner
                if current == first:
                    break
            regions.append(_Region(chain, [v for v in chain if is_corner[v]], crossings))
        return regions


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
    def of(cls, regions: list[_Region], points: np.ndarray) -> _RegionEdges:
        counts = np.array([len(region.corner_ids) for region in regions])
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        region = np.repeat(np.arange(len(regions)), counts)
        following = start[region] + (np.arange(len(region)) - start[region] + 1) % counts[region]
        corner_points = points[np.concatenate([r.corner_ids for r in regions])]
        vectors = corner_points[following] - corner_points
        lengths = np.linalg.norm(vectors, axis=1)
        normals = np.stack([vectors[:, 1], -vectors[:, 0]], axis=1) / lengths[:, None]
        offsets = np.einsum("ij,ij->i", normals, corner_points)
        return cls(start, region, corner_points, vectors, lengths, normals, offsets)

    def depth(self, query: np.ndarray) -> np.ndarray:
        """(n, regions): how far outside each region each point lies (negative: inside)."""
        return np.maximum.reduceat(query @ self.normals.T - self.offsets, self.start, axis=1)

    def areas(self) -> np.ndarray:
        following = self.points + self.vectors
        cross = self.points[:, 0] * following[:, 1] - self.points[:, 1] * following[:, 0]
        return 0.5 * np.bincount(self.region, weights=cross, minlength=len(self.start))


def _triangulate_regions(
    regions: list[_Region],
    edges: _RegionEdges,
    points: np.ndarray,
    is_corner: np.ndarray,
    grid: np.ndarray,
    options: _Options,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate every convex region from its boundary chain plus the grid points well
    inside it. Returns faces (ids into ``points`` followed by the interior points, ccw), the
    region of each face, the interior points and the region of each."""
    from scipy.spatial import Delaunay  # noqa: PLC0415 - scipy comes with scikit-image (render extra)

    # Grid points at least `margin` inside a region belong to it (to one region at most).
    margin = 0.35 * options.mesh_step
    depth = edges.depth(grid)
    grid_region = np.where(np.any(depth <= -margin, axis=1), np.argmin(depth, axis=1), -1)

    # Bulge the boundary points of every straight edge outward (see _BULGE). Each chain starts
    # at a corner, so a chain point lies on the edge of the last corner at or before it.
    chains = [np.asarray(region.chain) for region in regions]
    chain_all = np.concatenate(chains)
    edge = np.cumsum(is_corner[chain_all]) - 1  # global edge index, since regions are stacked in order
    lengths = edges.lengths[edge]
    t = np.einsum("ij,ij->i", points[chain_all] - edges.points[edge], edges.vectors[edge]) / lengths**2
    bulged = points[chain_all] + edges.normals[edge] * (_BULGE * lengths * 4.0 * t * (1.0 - t))[:, None]

    faces, face_regions, interiors = [], [], []
    n_boundary = len(points)
    n_interior = 0
    chain_stop = np.cumsum([len(c) for c in chains])
    for r, chain in enumerate(chains):
        interior = grid[grid_region == r]
        triangulation = Delaunay(np.vstack([bulged[chain_stop[r] - len(chain) : chain_stop[r]], interior]))
        if len(triangulation.coplanar):
            raise RuntimeError("paper model: Delaunay dropped boundary points of a region (please report)")
        ids = np.concatenate([chain, n_boundary + n_interior + np.arange(len(interior))])
        faces.append(ids[triangulation.simplices])
        face_regions.append(np.full(len(triangulation.simplices), r))
        interiors.append(interior)
        n_interior += len(interior)
    faces_arr = np.concatenate(faces).astype(np.int64)
    face_regions_arr = np.concatenate(face_regions).astype(np.int64)
    interior_points = np.concatenate(interiors)
    interior_regions = np.repeat(np.arange(len(regions)), [len(i) for i in interiors])

    # Counter-clockwise in the true (unbulged) flat frame; no sliver; regions exactly tiled.
    tri = np.concatenate([points, interior_points])[faces_arr]
    areas = 0.5 * (
        (tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
        - (tri[:, 1, 1] - tri[:, 0, 1]) * (tri[:, 2, 0] - tri[:, 0, 0])
    )
    faces_arr[areas < 0] = faces_arr[areas < 0][:, [0, 2, 1]]
    covered = np.bincount(face_regions_arr, weights=np.abs(areas), minlength=len(regions))
    if np.min(np.abs(areas)) <= 1e-9 * options.mesh_step**2 or not np.allclose(covered, edges.areas(), rtol=1e-9, atol=0):
        raise RuntimeError("paper model: degenerate triangulation of a region (please report)")
    return faces_arr, face_regions_arr, interior_points, interior_regions


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` about the unit ``axis``."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


# -- self-intersection ----------------------------------------------------------------------


def _clip_to_slab(polygon: np.ndarray, heights: np.ndarray, clearance: float) -> np.ndarray:
    """The part of a convex polygon (n, 3) with |height| <= clearance (Sutherland-Hodgman
    against the two faces of the slab); with clearance 0, where it meets the plane."""
    points, values = list(polygon), list(heights)
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
                kept_points.append(p + t * (q - p))
                kept_values.append(sign * clearance)  # exactly on the slab face, no round-off
        points, values = kept_points, kept_values
        if not points:
            break
    return np.array(points).reshape(-1, 3)


def _convex_sets_overlap(first: np.ndarray, second: np.ndarray) -> bool:
    """Separating-axis test for two convex 2D point sets given in boundary order (the first a
    polygon, the second a polygon, a segment or a point); touching counts as overlapping."""
    axes = []
    for points in (first, second):
        if len(points) >= 2:
            edges = np.roll(points, -1, axis=0) - points
            edges = edges[np.linalg.norm(edges, axis=1) > 0]
            axes.append(np.stack([-edges[:, 1], edges[:, 0]], axis=1))
    for axis in np.concatenate(axes):
        a, b = first @ axis, second @ axis
        if a.max() < b.min() or b.max() < a.min():
            return False
    return True


def _find_self_intersection(
    corners: list[np.ndarray], rotations: list[np.ndarray], adjacent: np.ndarray, clearance: float
) -> tuple[int, int] | None:
    """The first pair of non-adjacent regions that pass through each other or come within
    ``clearance`` (measured across the plane of one of them), or None.

    Regions are planar convex polygons (``corners``: (n, 3) bent corner positions). Regions
    sharing a ruling meet along it and bend by less than pi there, so only non-adjacent pairs
    can cross. A pair is apart when one polygon lies wholly beyond ``clearance`` on one side of
    the other's plane; otherwise the slice of one near the other's plane is compared with the
    other polygon inside that plane. Exact for crossings, coplanar overlaps included.
    """
    n_regions = len(corners)
    normals = np.array([rotation[:, 2] for rotation in rotations])
    origins = np.array([c[0] for c in corners])
    owner = np.concatenate([np.full(len(c), r) for r, c in enumerate(corners)])
    stacked = np.concatenate(corners)
    # heights[r, k]: height of corner k above the plane of region r.
    heights = np.einsum("rj,rkj->rk", normals, stacked[None] - origins[:, None])
    above = np.full((n_regions, n_regions), -np.inf)
    below = np.full((n_regions, n_regions), np.inf)
    for r in range(n_regions):
        above[:, r] = heights[:, owner == r].max(axis=1)
        below[:, r] = heights[:, owner == r].min(axis=1)
    beyond = (below > clearance) | (above < -clearance)  # [a, b]: b wholly off a's plane
    for a in range(n_regions):
        for b in range(a + 1, n_regions):
            if adjacent[a, b] or beyond[a, b] or beyond[b, a]:
                continue
            piece = _clip_to_slab(corners[b], heights[a, owner == b], clearance)
            if not len(piece):
                continue
            basis = rotations[a][:, :2]
            if _convex_sets_overlap((corners[a] - origins[a]) @ basis, (piece - origins[a]) @ basis):
                return a, b
    return None


# -- public API ------------------------------------------------------------------------------


def _assemble(
    width: float, height: float, border: _Border, chords: list[_Chord], guides: list[Ruling], options: _Options
) -> SheetMesh:
    """Regions, their rigid transforms, the self-intersection checks, then the mesh."""
    builder = _MeshBuilder(border, chords, options)
    points, regions = builder.build()
    is_corner = builder.is_corner
    edges = _RegionEdges.of(regions, points)

    # Region graph: each ruling borders exactly two regions.
    sides: dict[int, list[tuple[int, int, int]]] = {}
    for r, region in enumerate(regions):
        for chord_index, start, end in region.crossings:
            sides.setdefault(chord_index, []).append((r, start, end))
    n_regions = len(regions)
    adjacent = np.zeros((n_regions, n_regions), bool)
    neighbours: list[list[tuple[int, int, int, int]]] = [[] for _ in regions]
    for chord_index, ((r0, s0, e0), (r1, s1, e1)) in sides.items():
        adjacent[r0, r1] = adjacent[r1, r0] = True
        neighbours[r0].append((r1, chord_index, s1, e1))
        neighbours[r1].append((r0, chord_index, s0, e0))

    # Reference region: the one holding the sheet centre (the deepest inside, if on a ruling).
    reference = int(np.argmin(edges.depth(np.array([[width / 2.0, height / 2.0]]))[0]))

    # Bends adding up along a path: a sheet curled past max_total_bend is rejected.
    bend_from = np.zeros((n_regions, n_regions))
    for source in range(n_regions):
        seen = {source}
        queue = deque([source])
        while queue:
            r = queue.popleft()
            for other, chord_index, _, _ in neighbours[r]:
                if other not in seen:
                    seen.add(other)
                    bend_from[source, other] = bend_from[source, r] + chords[chord_index].angle
                    queue.append(other)
    worst = float(np.max(np.abs(bend_from)))
    if options.check_self_intersection and worst > options.max_total_bend + 1e-12:
        raise SelfIntersection(
            f"bends add up to {math.degrees(worst):.0f} degrees between two regions "
            f"(limit {math.degrees(options.max_total_bend):.0f}): the sheet would curl into itself"
        )

    # Rigid transforms, breadth first from the reference region: T_child = T_parent o Rot(ruling).
    origin = np.array([width / 2.0, height / 2.0, 0.0])
    rotations = [np.eye(3)] * n_regions
    translations = [np.zeros(3)] * n_regions
    order = [reference]
    seen = {reference}
    queue = deque([reference])
    while queue:
        parent = queue.popleft()
        for child, chord_index, start, end in neighbours[parent]:
            if child in seen:
                continue
            seen.add(child)
            order.append(child)
            queue.append(child)
            # The child traverses the ruling start -> end with itself on the left, so a
            # rotation by +angle about that direction lifts it towards +z (valley fold).
            a = np.append(points[start], 0.0) - origin
            b = np.append(points[end], 0.0) - origin
            axis = (b - a) / np.linalg.norm(b - a)
            local = _rotation(axis, chords[chord_index].angle)
            rotations[child] = rotations[parent] @ local
            translations[child] = rotations[parent] @ (a - local @ a) + translations[parent]

    # Regions are rigid planar polygons: check them before spending time on the mesh.
    if options.check_self_intersection:
        corners = []
        for r, region in enumerate(regions):
            flat_corners = np.column_stack([points[region.corner_ids], np.zeros(len(region.corner_ids))]) - origin
            corners.append(flat_corners @ rotations[r].T + translations[r])
        found = _find_self_intersection(corners, rotations, adjacent, options.clearance)
        if found is not None:
            raise SelfIntersection(
                f"regions {found[0]} and {found[1]} of the bent sheet pass through each other "
                f"(or come within {options.clearance:.3g} m)"
            )

    # Triangulate each region; vertices on rulings are shared by both neighbours.
    nx = max(1, round(width / options.mesh_step))
    ny = max(1, round(height / options.mesh_step))
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) * width / nx, (np.arange(ny) + 0.5) * height / ny)
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    faces, face_regions, interior, interior_regions = _triangulate_regions(regions, edges, points, is_corner, grid, options)
    flat = np.concatenate([points, interior])

    # Each vertex moves with the region holding it; a vertex on a ruling with the neighbour
    # nearest the reference (both agree there, up to round-off).
    rank = np.empty(n_regions, np.int64)
    rank[order] = np.arange(n_regions)
    owner_rank = np.full(len(points), n_regions)
    for r, region in enumerate(regions):
        np.minimum.at(owner_rank, region.chain, rank[r])
    owner = np.concatenate([np.asarray(order)[owner_rank], interior_regions])
    flat3 = np.column_stack([flat, np.zeros(len(flat))]) - origin
    vertices = np.einsum("vij,vj->vi", np.array(rotations)[owner], flat3) + np.array(translations)[owner]

    fold_lines = [(tuple(map(float, c.p0)), tuple(map(float, c.p1)), float(c.angle)) for c in chords]
    return SheetMesh(
        flat=flat,
        vertices=vertices,
        faces=faces,
        uv=flat / np.array([width, height]),
        width=float(width),
        height=float(height),
        rulings=list(guides),
        fold_lines=fold_lines,
        face_regions=face_regions,
    )


def build_sheet(
    width: float, height: float, rulings: Sequence[tuple[Sequence[float], Sequence[float], float]], **opts
) -> SheetMesh:
    """A bent sheet from given guiding rulings ``(p0, p1, angle)`` (flat end points on the
    border, radians, positive = valley fold seen from +z).

    Options (all keyword, lengths in metres): ``mesh_step`` (target edge length, default
    sqrt(W H)/16, at most min(W, H)/4), ``smooth_steps`` (interpolated rulings per guiding
    ruling, default 3; 1 is a sharp crease), ``bend_spacing`` (border distance between
    them, default 0.75 mesh_step),
    ``corner_gap`` (ruling ends kept this far from corners, default 0.5 mesh_step),
    ``min_strip`` (least distance between rulings, default 0.3 mesh_step),
    ``max_total_bend`` (radians, default 3π/2), ``clearance`` (non-neighbouring regions
    closer than this count as touching, default 0.002 max(W, H)),
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
    chords = _expand(border, guides, options)
    _validate_layout(border, chords, options)
    guide_rulings = [(border.point(s0), border.point(s1), angle) for s0, s1, angle in guides]
    return _assemble(width, height, border, chords, guide_rulings, options)


def sample_sheet(n_rulings: int, rng: np.random.Generator, width: float, height: float, **opts) -> SheetMesh:
    """A randomly bent W×H sheet with ``n_rulings`` guiding rulings (0 gives the flat sheet).

    Bending angles are uniform in [min_angle, max_angle] (default 10°–50°) with a random sign.
    Deterministic for the same ``rng`` state. Raises SelfIntersection (with ``.reason``) when
    the sampled sheet passes through itself: the caller resamples. Other options as in
    ``build_sheet``, plus ``min_gap`` (border distance between the interpolated families of
    two guiding rulings, default mesh_step) and ``max_tries`` (layouts drawn before giving up
    on the geometric constraints, default 200).
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
        return _assemble(width, height, border, [], [], options)
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
        guide_rulings = [(border.point(s0), border.point(s1), angle) for s0, s1, angle in guides]
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
