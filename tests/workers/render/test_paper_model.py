"""The paper model: random isometric bending of a sheet along non-crossing rulings.

The geometric checks recompute everything from the returned arrays (flat and bent vertices,
faces, rulings) rather than trusting the module's own bookkeeping.
"""

from __future__ import annotations

import math
from collections import Counter
from functools import cache

import numpy as np
import pytest

from workers.render.paper_model import (
    RulingLayoutError,
    SelfIntersection,
    SheetMesh,
    build_sheet,
    sample_sheet,
    write_obj,
)

A4 = (0.21, 0.297)
SEEDS = range(50)
RULING_COUNTS = (2, 3, 5, 8)


# -- independent geometry helpers -------------------------------------------------------------


def edges_of(faces: np.ndarray) -> np.ndarray:
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def triangle_angles(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) interior angle at each corner of each triangle."""
    tri = points[faces]
    angles = []
    for k in range(3):
        u = tri[:, (k + 1) % 3] - tri[:, k]
        v = tri[:, (k + 2) % 3] - tri[:, k]
        cos = np.einsum("ij,ij->i", u, v) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
        angles.append(np.arccos(np.clip(cos, -1.0, 1.0)))
    return np.stack(angles, axis=1)


def signed_flat_areas(flat: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = flat[faces]
    return 0.5 * (
        (t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (t[:, 1, 1] - t[:, 0, 1]) * (t[:, 2, 0] - t[:, 0, 0])
    )


def border_sides(points: np.ndarray, width: float, height: float, tol: float) -> np.ndarray:
    """(n, 4) bool: on the bottom, right, top, left side."""
    x, y = points[:, 0], points[:, 1]
    return np.stack([np.abs(y) <= tol, np.abs(x - width) <= tol, np.abs(y - height) <= tol, np.abs(x) <= tol], axis=1)


def orientation(a, b, c) -> float:
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])


def segments_cross(p0, p1, q0, q1):
    """Whether 2D segments share a point (touching counts); works on (2, n) arrays too."""
    o1, o2 = orientation(p0, p1, q0), orientation(p0, p1, q1)
    o3, o4 = orientation(q0, q1, p0), orientation(q0, q1, p1)
    return (o1 * o2 <= 0) & (o3 * o4 <= 0)


def segment_hits_triangle(p, q, a, b, c) -> np.ndarray:
    """Möller–Trumbore, vectorised over rows: does segment p->q meet triangle abc?"""
    d, e1, e2 = q - p, b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    usable = np.abs(det) > 1e-300
    inv = np.where(usable, 1.0 / np.where(usable, det, 1.0), 0.0)
    s = p - a
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return usable & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def region_polygon(faces: np.ndarray) -> list[int]:
    """The boundary of a triangulated disk (edges used once), counter-clockwise from its
    smallest vertex id."""
    edges = edges_of(faces)
    uses = Counter(map(frozenset, edges.tolist()))
    following = {int(a): int(b) for a, b in edges if uses[frozenset((a, b))] == 1}
    polygon = [min(following)]
    while following[polygon[-1]] != polygon[0]:
        polygon.append(following[polygon[-1]])
    assert len(polygon) == len(following), "a region's boundary is one loop"
    return polygon


def best_smallest_angle(corners: np.ndarray) -> float:
    """Brute force over every triangulation of a convex polygon (dynamic programming over its
    corner intervals): the largest smallest angle any of them reaches."""

    @cache
    def best(i: int, j: int) -> float:
        if j - i < 2:
            return math.inf
        return max(
            min(best(i, m), best(m, j), triangle_angles(corners, np.array([[i, m, j]])).min()) for m in range(i + 1, j)
        )

    return best(0, len(corners) - 1)


def count_crossing_triangles(mesh: SheetMesh) -> int:
    """Brute force: pairs of triangles from regions that share no vertex (regions that do
    share one meet along a ruling) where an edge of one pierces the other."""
    faces, regions = mesh.faces, mesh.face_regions
    neighbours = np.zeros((regions.max() + 1,) * 2, bool)
    regions_at_vertex = [set() for _ in range(len(mesh.vertices))]
    for face, region in zip(faces, regions):
        for vertex in face:
            regions_at_vertex[vertex].add(region)
    for around in regions_at_vertex:
        for r in around:
            neighbours[r, list(around)] = True
    tri = mesh.vertices[faces]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    boxes_meet = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=2)
    i, j = np.nonzero(np.triu(boxes_meet, 1))
    keep = ~neighbours[regions[i], regions[j]]
    first, second = tri[i[keep]], tri[j[keep]]
    hit = np.zeros(len(first), bool)
    for x, y in ((first, second), (second, first)):
        for k in range(3):
            hit |= segment_hits_triangle(x[:, k], x[:, (k + 1) % 3], y[:, 0], y[:, 1], y[:, 2])
    return int(hit.sum())


def assert_valid_sheet(mesh: SheetMesh) -> None:
    width, height = mesh.width, mesh.height
    scale = max(width, height)
    flat, vertices, faces = mesh.flat, mesh.vertices, mesh.faces
    assert flat.dtype == vertices.dtype == np.float64 and faces.dtype == np.int64
    assert flat.shape[1] == 2 and vertices.shape == (len(flat), 3) and faces.shape[1] == 3
    assert faces.min() >= 0 and faces.max() < len(flat)
    assert len(np.unique(faces)) == len(flat), "every vertex is used by a triangle"
    assert np.all(flat >= 0.0) and np.all(flat <= np.array([width, height]))
    np.testing.assert_allclose(mesh.uv, flat / np.array([width, height]), rtol=0, atol=1e-15)

    # Counter-clockwise, non-degenerate triangles that tile the flat sheet exactly.
    areas = signed_flat_areas(flat, faces)
    assert areas.min() > 0, "every triangle is counter-clockwise, none degenerate"
    assert math.isclose(areas.sum(), width * height, rel_tol=1e-12)
    tol = 1e-9 * scale
    on_border = np.any(border_sides(flat, width, height, tol), axis=1)
    minimal = bool(on_border.all())
    if minimal:
        # The minimal mesh: sheet corners and ruling ends only (a disk with every vertex on
        # its boundary has V - 2 triangles), each region triangulated with the largest
        # smallest angle any triangulation of its corners reaches: no needless sliver.
        assert len(flat) == 4 + 2 * len(mesh.fold_lines) and len(faces) == len(flat) - 2
        angles = triangle_angles(flat, faces).min(axis=1)
        for region in np.unique(mesh.face_regions):
            mine = mesh.face_regions == region
            polygon = region_polygon(faces[mine])
            assert len(polygon) == mine.sum() + 2, "a region's triangles use its corners only"
            # Every corner turns (no three collinear, so no flat triangle is even possible).
            sides = np.roll(flat[polygon], -1, axis=0) - flat[polygon]
            following = np.roll(sides, -1, axis=0)
            turns = (sides[:, 0] * following[:, 1] - sides[:, 1] * following[:, 0]) / (
                np.linalg.norm(sides, axis=1) * np.linalg.norm(following, axis=1)
            )
            assert turns.min() > 1e-6, "a region corner is not a real corner"
            best = best_smallest_angle(flat[polygon])
            assert angles[mine].min() >= best * (1 - 1e-9), "a region has a needlessly thin triangle"
    else:
        assert areas.min() > 0.02 * width * height / len(faces), "no sliver: every triangle has 2% of the mean area"

    # Isometry: edge lengths and triangle angles equal the flat sheet's.
    flat3 = np.column_stack([flat, np.zeros(len(flat))])
    edges = edges_of(faces)
    flat_lengths = np.linalg.norm(flat3[edges[:, 0]] - flat3[edges[:, 1]], axis=1)
    bent_lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    np.testing.assert_allclose(bent_lengths, flat_lengths, rtol=1e-9, atol=0)
    np.testing.assert_allclose(triangle_angles(vertices, faces), triangle_angles(flat3, faces), rtol=1e-9, atol=1e-12)

    # Watertight: every edge is shared by two triangles, except edges along the sheet border.
    keys, counts = np.unique(np.sort(edges, axis=1), axis=0, return_counts=True)
    assert counts.max() == 2, "an edge belongs to more than two triangles"
    open_edges = keys[counts == 1]
    sides0 = border_sides(flat[open_edges[:, 0]], width, height, tol)
    sides1 = border_sides(flat[open_edges[:, 1]], width, height, tol)
    assert np.all(np.any(sides0 & sides1, axis=1)), "an open edge is not along the sheet border"
    assert math.isclose(
        np.linalg.norm(flat[open_edges[:, 0]] - flat[open_edges[:, 1]], axis=1).sum(),
        2 * (width + height),
        rel_tol=1e-12,
    ), "the open edges are exactly the border"

    # The bent triangle angles around every vertex add up as on the flat sheet: 2π inside,
    # π on a side, π/2 at a sheet corner.
    n_sides = border_sides(flat, width, height, tol).sum(axis=1)
    expected = np.choose(n_sides, [2 * np.pi, np.pi, np.pi / 2])
    angle_sums = np.bincount(faces.ravel(), weights=triangle_angles(vertices, faces).ravel(), minlength=len(flat))
    np.testing.assert_allclose(angle_sums, expected, rtol=1e-9)
    assert np.sum(n_sides == 2) == 4, "the four sheet corners are vertices"

    # Rulings: both ends on the border, on two different sides, no two touching or crossing.
    lines = mesh.fold_lines
    assert len(lines) >= len(mesh.rulings)
    for p0, p1, _ in [*mesh.rulings, *lines]:
        ends = border_sides(np.array([p0, p1]), width, height, tol)
        assert ends[0].any() and ends[1].any(), "ruling end off the border"
        assert not np.any(ends[0] & ends[1]), "ruling with both ends on one side"
    if len(lines) > 1:
        p0, p1 = (np.array([line[k] for line in lines]) for k in (0, 1))
        i, j = np.triu_indices(len(lines), 1)
        assert not np.any(segments_cross(p0[i].T, p1[i].T, p0[j].T, p1[j].T)), "two rulings cross or touch"

    # Every fold line is one edge of the minimal mesh, shared by triangles of two regions.
    if minimal:
        for p0, p1, _ in lines:
            i, j = (int(np.argmin(np.linalg.norm(flat - np.asarray(p), axis=1))) for p in (p0, p1))
            np.testing.assert_allclose(flat[[i, j]], [p0, p1], rtol=0, atol=tol)
            along = np.flatnonzero(np.isin(faces, [i, j]).sum(axis=1) == 2)
            assert len(along) == 2 and mesh.face_regions[along[0]] != mesh.face_regions[along[1]]

    # No triangle straddles a ruling: its vertices are all on one side or on the line.
    for p0, p1, _ in lines:
        p0, p1 = np.asarray(p0), np.asarray(p1)
        direction = (p1 - p0) / np.linalg.norm(p1 - p0)
        side = (flat[:, 0] - p0[0]) * direction[1] - (flat[:, 1] - p0[1]) * direction[0]
        side = np.where(np.abs(side) <= tol, 0.0, np.sign(side))[faces]
        assert not np.any((side.max(axis=1) > 0) & (side.min(axis=1) < 0)), "a triangle crosses a ruling"

    # Rigid regions: one more than the rulings, each still a plane after bending.
    assert mesh.face_regions.shape == (len(faces),)
    assert np.array_equal(np.unique(mesh.face_regions), np.arange(len(lines) + 1))
    first_face = faces[np.unique(mesh.face_regions, return_index=True)[1]]  # one face per region
    a, b, c = (vertices[first_face[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    region = mesh.face_regions
    heights = np.einsum("fkj,fj->fk", vertices[faces] - a[region][:, None], normals[region])
    assert np.abs(heights).max() <= 1e-12 * scale, "a region is not planar after bending"

    # The region holding the sheet centre stays where the flat sheet was.
    centre_face = np.argmax(
        np.min(
            [
                orientation(flat[faces[:, k]].T, flat[faces[:, (k + 1) % 3]].T, (width / 2, height / 2))
                for k in range(3)
            ],
            axis=0,
        )
    )
    fixed = faces[centre_face]
    np.testing.assert_allclose(vertices[fixed, :2], flat[fixed] - [width / 2, height / 2], atol=1e-12)
    np.testing.assert_allclose(vertices[fixed, 2], 0.0, atol=1e-12)


def assert_same_surface(fine: SheetMesh, coarse: SheetMesh) -> None:
    """Both meshes are the same bent sheet: every vertex of ``fine`` sits, in 3D, where the
    ``coarse`` triangle holding its flat position puts it (regions are planar and rigid, so
    barycentric interpolation inside a triangle is exact)."""
    assert fine.rulings == coarse.rulings and fine.fold_lines == coarse.fold_lines
    tri = coarse.flat[coarse.faces]  # (F, 3, 2)
    twice_area = signed_flat_areas(coarse.flat, coarse.faces) * 2
    weights = (
        np.stack(
            [
                orientation(tri[:, (k + 1) % 3].T[:, None], tri[:, (k + 2) % 3].T[:, None], fine.flat.T[:, :, None])
                for k in range(3)
            ],
            axis=2,
        )
        / twice_area[None, :, None]
    )  # (V, F, 3) barycentric coordinates
    holding = np.argmax(weights.min(axis=2), axis=1)
    assert np.all(weights.min(axis=2).max(axis=1) > -1e-9), "a vertex lies outside the coarse sheet"
    chosen = weights[np.arange(len(fine.flat)), holding]
    predicted = np.einsum("vk,vkj->vj", chosen, coarse.vertices[coarse.faces[holding]])
    np.testing.assert_allclose(fine.vertices, predicted, rtol=0, atol=1e-12 * max(fine.width, fine.height))


# -- sampled sheets -------------------------------------------------------------------------


@pytest.mark.parametrize("n_rulings", RULING_COUNTS)
def test_sampled_sheets_are_isometric_and_well_meshed(n_rulings):
    rejected = []
    for seed in SEEDS:
        try:
            mesh = sample_sheet(n_rulings, np.random.default_rng(seed), *A4)
        except SelfIntersection as error:
            rejected.append(error.reason)
            continue
        assert len(mesh.rulings) == n_rulings and len(mesh.fold_lines) == 3 * n_rulings
        assert len(mesh.faces) == 2 * len(mesh.fold_lines) + 2, "minimal mesh: two triangles per fold line, plus two"
        assert_valid_sheet(mesh)
        # The sheet really bends: every guiding ruling has its angle, and something leaves z=0.
        assert all(math.radians(10) - 1e-12 <= abs(angle) <= math.radians(50) + 1e-12 for *_, angle in mesh.rulings)
        assert np.ptp(mesh.vertices[:, 2]) > 1e-3
        if seed % 10 == 0:  # the refined mesh of the same draw: the same sheet, more triangles
            fine = sample_sheet(n_rulings, np.random.default_rng(seed), *A4, max_edge=0.015)
            assert 200 <= len(fine.faces) <= 2500, "refined meshes stay modest"
            assert_valid_sheet(fine)
            assert_same_surface(fine, mesh)
    assert len(rejected) <= len(SEEDS) // 5, f"too many self-intersecting samples: {rejected}"


def test_same_generator_state_gives_the_same_sheet():
    first = sample_sheet(5, np.random.default_rng(123), *A4)
    second = sample_sheet(5, np.random.default_rng(123), *A4)
    other = sample_sheet(5, np.random.default_rng(124), *A4)
    for name in ("flat", "vertices", "faces", "uv"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    assert first.rulings == second.rulings
    assert first.rulings != other.rulings


def test_the_draws_are_pinned():
    # The layout's random draws and their order (module docstring) decide every rendered sheet:
    # these are the values of the array implementation the compiled one replaced.
    mesh = sample_sheet(3, np.random.default_rng(2018), *A4)
    assert mesh.rulings == [
        ((0.08240964512944982, 0.0), (0.0, 0.06823121036148194), -0.6044079225881946),
        ((0.21, 0.20710071645334474), (0.0, 0.1227809780804334), 0.35218417009072867),
        ((0.21, 0.2746665017093413), (0.1747085448156295, 0.297), 0.724122784863628),
    ]
    assert mesh.faces.tolist() == [
        [7, 5, 4],
        [7, 4, 6],
        [6, 8, 9],
        [6, 9, 7],
        [11, 9, 8],
        [11, 8, 1],
        [11, 1, 10],
        [10, 12, 13],
        [10, 13, 11],
        [12, 14, 15],
        [12, 15, 13],
        [17, 3, 15],
        [17, 15, 14],
        [17, 14, 16],
        [16, 18, 19],
        [16, 19, 17],
        [18, 20, 21],
        [18, 21, 19],
        [20, 2, 21],
        [5, 0, 4],
    ]


def test_default_options_are_made_once_and_never_mixed_with_given_ones():
    from workers.render import paper_model  # noqa: PLC0415 - the private option cache

    width, height = A4
    default = paper_model._options(width, height, {})
    assert paper_model._options(width, height, {}) is default, "one default per sheet size"
    assert paper_model._options(0.3, 0.2, {}).mesh_step != default.mesh_step, "defaults follow the sheet size"
    assert paper_model._options(width, height, {"smooth_steps": 1}).smooth_steps == 1
    assert paper_model._options(width, height, {"smooth_steps": 3}) == default
    assert paper_model._options(width, height, {}).smooth_steps == 3
    before = sample_sheet(3, np.random.default_rng(4), *A4)
    other = sample_sheet(3, np.random.default_rng(4), *A4, smooth_steps=1, max_edge=0.03, clearance=0.0)
    after = sample_sheet(3, np.random.default_rng(4), *A4)
    explicit = sample_sheet(3, np.random.default_rng(4), *A4, smooth_steps=3)
    assert len(other.fold_lines) == 3 and len(before.fold_lines) == len(after.fold_lines) == 9
    for mesh in (after, explicit):
        assert mesh.fold_lines == before.fold_lines
        for name in ("flat", "vertices", "faces", "uv", "face_regions"):
            np.testing.assert_array_equal(getattr(mesh, name), getattr(before, name))


def test_interpolated_rulings_share_their_guiding_angle():
    mesh = sample_sheet(3, np.random.default_rng(5), *A4, smooth_steps=4)
    assert len(mesh.fold_lines) == 12
    for guide, (*_, angle) in enumerate(mesh.rulings):
        shares = [a for *_, a in mesh.fold_lines[4 * guide : 4 * guide + 4]]
        np.testing.assert_allclose(shares, angle / 4)
    assert_valid_sheet(mesh)


def test_sharp_creases_and_other_sheet_shapes():
    for n, size, opts in [
        (8, (0.5, 0.12), {}),
        (5, (1.0, 1.0), {"smooth_steps": 1}),
        (8, (0.9, 0.6), {"smooth_steps": 5, "mesh_step": 0.04}),
        (1, (0.3, 0.2), {}),
        (5, (0.01, 0.007), {}),  # tolerances are relative: a 1 cm sheet ...
        (5, (100.0, 60.0), {}),  # ... and a 100 m one behave alike
    ]:
        mesh = sample_sheet(n, np.random.default_rng(11), *size, **opts)
        assert len(mesh.fold_lines) == n * opts.get("smooth_steps", 3)
        assert_valid_sheet(mesh)


def test_no_rulings_gives_the_flat_sheet():
    mesh = sample_sheet(0, np.random.default_rng(0), *A4)
    assert mesh.rulings == [] and mesh.fold_lines == []
    assert len(mesh.flat) == 4 and len(mesh.faces) == 2, "two triangles make the flat sheet"
    assert_valid_sheet(mesh)
    np.testing.assert_array_equal(mesh.vertices[:, 2], 0.0)
    np.testing.assert_allclose(mesh.vertices[:, :2], mesh.flat - np.array(A4) / 2)
    normals = np.cross(
        mesh.vertices[mesh.faces[:, 1]] - mesh.vertices[mesh.faces[:, 0]],
        mesh.vertices[mesh.faces[:, 2]] - mesh.vertices[mesh.faces[:, 0]],
    )
    assert np.all(normals[:, 2] > 0), "faces are counter-clockwise, normals towards +z"


def test_refined_mesh_is_the_same_sheet_with_short_edges():
    width, height = A4
    coarse = sample_sheet(5, np.random.default_rng(7), width, height)
    sizes = []
    for max_edge in (0.05, 0.02, 0.008):
        fine = sample_sheet(5, np.random.default_rng(7), width, height, max_edge=max_edge)
        assert_valid_sheet(fine)
        assert_same_surface(fine, coarse)
        # Border and rulings are cut into edges no longer than max_edge; grid points fill the
        # regions' insides (vertices off the border and off every ruling).
        edges = np.unique(np.sort(edges_of(fine.faces), axis=1), axis=0)
        lengths = np.linalg.norm(fine.flat[edges[:, 0]] - fine.flat[edges[:, 1]], axis=1)
        tol = 1e-9 * width
        on_line = [border_sides(fine.flat, width, height, tol)]  # (V, lines): on the border's sides, the rulings
        for p0, p1, _ in fine.fold_lines:
            p0, p1 = np.asarray(p0), np.asarray(p1)
            direction = (p1 - p0) / np.linalg.norm(p1 - p0)
            across = (fine.flat[:, 0] - p0[0]) * direction[1] - (fine.flat[:, 1] - p0[1]) * direction[0]
            on_line.append((np.abs(across) <= tol)[:, None])
        on_line = np.concatenate(on_line, axis=1)
        along_lines = np.any(on_line[edges[:, 0]] & on_line[edges[:, 1]], axis=1)
        assert lengths[along_lines].max() <= max_edge * (1 + 1e-9)
        on_line = on_line.any(axis=1)
        assert (~on_line).sum() > 0
        sizes.append(len(fine.faces))
    assert len(coarse.faces) < sizes[0] < sizes[1] < sizes[2]


def test_a_region_with_many_corners_gets_its_fattest_triangulation():
    width, height = A4
    # Four corner cuts leave an octagon in the middle (a tree of regions, not a chain); a
    # fan from any one corner of it would be thinner than the best triangulation.
    cuts = [
        ((0.03, 0.0), (0.0, 0.04), 0.4),
        ((0.21, 0.05), (0.17, 0.0), -0.5),
        ((0.16, 0.297), (0.21, 0.25), 0.6),
        ((0.0, 0.24), (0.05, 0.297), -0.3),
    ]
    mesh = build_sheet(width, height, cuts, smooth_steps=1)
    assert_valid_sheet(mesh)  # checks every region against the best of all its triangulations
    corners_per_region = np.bincount(mesh.face_regions) + 2
    assert sorted(corners_per_region.tolist()) == [3, 3, 3, 3, 8]
    octagon = np.argmax(corners_per_region)
    fans = []
    polygon = region_polygon(mesh.faces[mesh.face_regions == octagon])
    for apex in range(8):
        order = np.roll(polygon, -apex)
        fan = np.array([[order[0], order[j], order[j + 1]] for j in range(1, 7)])
        fans.append(triangle_angles(mesh.flat, fan).min())
    mine = triangle_angles(mesh.flat, mesh.faces[mesh.face_regions == octagon]).min()
    assert mine > max(fans) * 1.05
    assert_same_surface(build_sheet(width, height, cuts, smooth_steps=1, max_edge=0.02), mesh)


# -- given rulings --------------------------------------------------------------------------


def test_a_positive_angle_is_a_valley_fold_of_the_right_size():
    width, height = A4
    for angle in (0.7, -0.7):
        # A vertical crease right of the centre: the left part stays, the right part turns.
        mesh = build_sheet(width, height, [((0.15, 0.0), (0.15, height), angle)], smooth_steps=1)
        assert_valid_sheet(mesh)
        right = mesh.flat[:, 0] > 0.15 + 1e-9
        left = mesh.flat[:, 0] < 0.15 - 1e-9
        np.testing.assert_allclose(mesh.vertices[left, 2], 0.0, atol=1e-15)
        # The far edge (x = W) rises (valley) or drops (mountain) by its distance times sin(angle).
        far = np.isclose(mesh.flat[:, 0], width)
        np.testing.assert_allclose(mesh.vertices[far, 2], (width - 0.15) * math.sin(angle), rtol=1e-12)
        assert np.sign(mesh.vertices[right, 2]).tolist() == [np.sign(angle)] * int(right.sum())
        # Dihedral angle between the two sides' normals is the bending angle.
        tri = mesh.vertices[mesh.faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        turned = normals[right[mesh.faces].all(axis=1)]
        np.testing.assert_allclose(np.arccos(np.clip(turned @ [0, 0, 1], -1, 1)), abs(angle), rtol=1e-12)


def test_smooth_bend_spreads_the_angle_over_its_band():
    width, height = A4
    mesh = build_sheet(width, height, [((0.05, 0.0), (0.05, height), 1.2)], smooth_steps=4, bend_spacing=0.01)
    assert_valid_sheet(mesh)
    xs = sorted(p0[0] for p0, _, _ in mesh.fold_lines)
    np.testing.assert_allclose(xs, [0.035, 0.045, 0.055, 0.065], atol=1e-12)
    # The centre is right of the band: the part left of it turns by the whole angle.
    left_edge = np.isclose(mesh.flat[:, 0], 0.0)
    assert np.all(mesh.vertices[left_edge, 2] > 0)
    tri = mesh.vertices[mesh.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    outside = (mesh.flat[mesh.faces][:, :, 0] < 0.035 - 1e-9).all(axis=1)
    np.testing.assert_allclose(normals[outside] @ [0, 0, 1], math.cos(1.2), rtol=1e-12)


def test_a_bend_through_the_fixed_centre_still_folds_both_sides_the_same_way():
    width, height = A4
    # The centre lies inside the band of a smooth 60° bend (interpolated rulings 1 cm apart at
    # x = 0.096, 0.106, 0.116): the strip holding it stays put, the left part turns by one
    # share (20°), the right part by two (40°), both towards +z, and 60° apart in all.
    mesh = build_sheet(width, height, [((0.106, 0.0), (0.106, height), math.radians(60))], bend_spacing=0.01)
    assert_valid_sheet(mesh)
    tri = mesh.vertices[mesh.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    xs = mesh.flat[mesh.faces][:, :, 0]
    left, right = normals[(xs < 0.096 - 1e-9).all(axis=1)], normals[(xs > 0.116 + 1e-9).all(axis=1)]
    np.testing.assert_allclose(np.degrees(np.arccos(left @ [0, 0, 1])), 20.0, rtol=1e-9)
    np.testing.assert_allclose(np.degrees(np.arccos(right @ [0, 0, 1])), 40.0, rtol=1e-9)
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(left @ right.T, -1, 1))), 60.0, rtol=1e-9)
    for edge_x in (0.0, width):
        assert np.all(mesh.vertices[np.isclose(mesh.flat[:, 0], edge_x), 2] > 0)


def test_flaps_folded_through_each_other_are_a_self_intersection():
    width, height = A4
    # Two flaps, 0.4 W wide, folded up by 110° over a middle strip 0.2 W wide: in the x-z
    # cross-section the left flap runs from (0.4W, 0) to (0.537W, 0.376W) and the right one
    # from (0.6W, 0) to (0.463W, 0.376W), so they cross above x = 0.5 W. The bends along the
    # sheet add up to 220°, below the 270° curl limit: only the geometric test can see it.
    rulings = [
        ((0.4 * width, 0.0), (0.4 * width, height), math.radians(110)),
        ((0.6 * width, 0.0), (0.6 * width, height), math.radians(110)),
    ]
    with pytest.raises(SelfIntersection, match="pass through") as caught:
        build_sheet(width, height, rulings, smooth_steps=1)
    assert "regions" in caught.value.reason
    # Without the check the same sheet is built, and it is still an exact isometry.
    assert_valid_sheet(build_sheet(width, height, rulings, smooth_steps=1, check_self_intersection=False))
    # Folding the flaps to opposite sides (a Z) keeps them apart.
    apart = [rulings[0], (rulings[1][0], rulings[1][1], -rulings[1][2])]
    assert_valid_sheet(build_sheet(width, height, apart, smooth_steps=1))
    # Less folded (70°), the flaps lean outwards and never meet.
    assert_valid_sheet(
        build_sheet(width, height, [(p0, p1, math.radians(70)) for p0, p1, _ in rulings], smooth_steps=1)
    )


def test_layers_closer_than_the_clearance_count_as_touching():
    width, height = A4
    # A flap folded flat back (179°) over a strip tilted by 1°: it lies parallel to the fixed
    # region, 0.05 W * sin(1°) ~ 0.18 mm above it, without crossing it.
    rulings = [
        ((0.25 * width, 0.0), (0.25 * width, height), math.radians(179)),
        ((0.3 * width, 0.0), (0.3 * width, height), math.radians(1)),
    ]
    with pytest.raises(SelfIntersection, match="within 0.001"):
        build_sheet(width, height, rulings, smooth_steps=1, clearance=1e-3)
    assert_valid_sheet(build_sheet(width, height, rulings, smooth_steps=1, clearance=0.0))


def test_bends_adding_up_past_the_limit_are_rejected():
    width, height = A4
    rulings = [((x, 0.0), (x, height), math.radians(100)) for x in (0.05, 0.1, 0.16)]
    with pytest.raises(SelfIntersection, match="add up to 300 degrees"):
        build_sheet(width, height, rulings)
    # Alternating signs never curl: 100 - 100 + 100.
    alternating = [(p0, p1, a * s) for (p0, p1, a), s in zip(rulings, (1, -1, 1))]
    assert_valid_sheet(build_sheet(width, height, alternating))


def test_bends_add_up_along_paths_through_a_tree_of_regions():
    width, height = A4
    # Four corner flaps around an octagon: the path between two flaps crosses both their
    # rulings, so opposite flaps folded the same way (2 x 2.5 rad) curl past 270°; flaps folded
    # opposite ways cancel.
    cuts = [
        ((0.03, 0.0), (0.0, 0.04)),
        ((0.21, 0.05), (0.17, 0.0)),
        ((0.16, 0.297), (0.21, 0.25)),
        ((0.0, 0.24), (0.05, 0.297)),
    ]
    with pytest.raises(SelfIntersection, match="add up to 286 degrees"):
        build_sheet(width, height, [(p0, p1, a) for (p0, p1), a in zip(cuts, (2.5, -2.5, 2.5, -2.5))], smooth_steps=1)
    # The worst sum may be negative: flaps at -2.5 and -0.5 rad (3.0 rad, 172°) beat the largest
    # positive pair (2.5 + 0.3 rad).
    mixed = [(p0, p1, a) for (p0, p1), a in zip(cuts, (2.5, -2.5, -0.5, 0.3))]
    with pytest.raises(SelfIntersection, match="add up to 172 degrees"):
        build_sheet(width, height, mixed, smooth_steps=1, max_total_bend=2.9)
    assert_valid_sheet(build_sheet(width, height, mixed, smooth_steps=1))


def test_high_bending_angles_get_rejected_sometimes_and_never_pass_intersecting():
    # With up to 170° per ruling many samples curl through themselves: the ones that pass
    # must still be valid sheets; the others name their reason.
    outcomes = {"ok": 0, "rejected": 0}
    for seed in range(12):
        try:
            mesh = sample_sheet(3, np.random.default_rng(seed), *A4, min_angle=2.0, max_angle=2.9)
        except SelfIntersection as error:
            assert error.reason and str(error) == error.reason
            outcomes["rejected"] += 1
            continue
        outcomes["ok"] += 1
        assert_valid_sheet(mesh)
    assert outcomes["rejected"] >= 3


def test_self_intersection_verdicts_agree_with_brute_force():
    # Sharp creases of 85°-160° with the curl limit lifted: the geometric test alone decides,
    # and a brute-force Möller–Trumbore check over all triangle pairs must agree with it.
    options = dict(min_angle=1.5, max_angle=2.8, max_total_bend=20.0, clearance=0.0, smooth_steps=1)
    verdicts = []
    for seed in range(10):
        try:
            mesh = sample_sheet(5, np.random.default_rng(seed), *A4, **options)
            verdicts.append("accepted")
            assert count_crossing_triangles(mesh) == 0
        except SelfIntersection as error:
            assert "pass through" in error.reason
            verdicts.append("rejected")
            unchecked = sample_sheet(5, np.random.default_rng(seed), *A4, check_self_intersection=False, **options)
            assert count_crossing_triangles(unchecked) > 0
    assert {"accepted", "rejected"} <= set(verdicts)


# -- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "rulings, message",
    [
        ([((0.05, 0.0), (0.15, 0.0), 0.5)], "both ends on the bottom"),
        ([((0.05, 0.0), (0.15, 0.297), 0.5), ((0.15, 0.0), (0.05, 0.297), 0.5)], "cross"),
        ([((0.05, 0.1), (0.15, 0.297), 0.5)], "not on the sheet border"),
        ([((0.05, -0.1), (0.15, 0.297), 0.5)], "outside"),
        ([((0.0, 0.0), (0.21, 0.297), 0.5)], "corner"),
        ([((0.05, 0.0), (0.05, 0.297), 0.5), ((0.052, 0.0), (0.052, 0.297), 0.5)], "apart"),
        ([((0.05, 0.0), (0.05, 0.297), math.pi)], "below pi"),
        ([((0.05, 0.0), (0.05, 0.297))], "must be \\(p0, p1, angle\\)"),
        ([((0.05, 0.0), (0.05, 0.297), "steep")], "must be a number"),
    ],
)
def test_bad_rulings_are_named(rulings, message):
    with pytest.raises(RulingLayoutError, match=message):
        build_sheet(*A4, rulings, smooth_steps=1)


def test_bad_arguments_are_clear_errors():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="n_rulings"):
        sample_sheet(-1, rng, *A4)
    with pytest.raises(TypeError, match="n_rulings"):
        sample_sheet(2.5, rng, *A4)
    with pytest.raises(TypeError, match="Generator"):
        sample_sheet(2, 7, *A4)
    with pytest.raises(ValueError, match="width"):
        sample_sheet(2, rng, 0.0, 0.3)
    with pytest.raises(ValueError, match="height"):
        sample_sheet(2, rng, 0.2, float("nan"))
    with pytest.raises(TypeError, match="unknown paper model option.*wiggle"):
        sample_sheet(2, rng, *A4, wiggle=3)
    with pytest.raises(ValueError, match="smooth_steps"):
        sample_sheet(2, rng, *A4, smooth_steps=0)
    for max_edge, error in ((0.0, ValueError), (-0.01, ValueError), (float("inf"), ValueError), ("fine", TypeError)):
        with pytest.raises(error, match="max_edge"):
            sample_sheet(2, rng, *A4, max_edge=max_edge)
    with pytest.raises(ValueError, match="max_edge 1e-05 .* over 1000000 vertices"):
        sample_sheet(2, rng, *A4, max_edge=1e-5)
    with pytest.raises(ValueError, match="max_angle"):
        sample_sheet(2, rng, *A4, max_angle=4.0)
    with pytest.raises(ValueError, match="do not fit"):
        sample_sheet(40, rng, *A4)
    # Strips required wider than the ruling spacing the sampler can give: no layout ever passes.
    with pytest.raises(ValueError, match="no valid layout of 5 rulings in 5 tries; last problem: two rulings"):
        sample_sheet(5, rng, *A4, smooth_steps=1, min_strip=0.05, max_tries=5)


# -- OBJ ------------------------------------------------------------------------------------


def read_obj(path):
    vertices, uvs, faces = [], [], []
    for line in path.read_text().splitlines():
        kind, *fields = line.split() or [""]
        if kind == "v":
            vertices.append([float(f) for f in fields])
        elif kind == "vt":
            uvs.append([float(f) for f in fields])
        elif kind == "f":
            corners = [f.split("/") for f in fields]
            assert all(v == t for v, t in corners), "v and vt indices agree"
            faces.append([int(v) - 1 for v, _ in corners])
    return np.array(vertices), np.array(uvs), np.array(faces)


def test_obj_round_trips(tmp_path):
    mesh = sample_sheet(5, np.random.default_rng(3), *A4)
    path = tmp_path / "sheet.obj"
    write_obj(mesh, path)
    vertices, uvs, faces = read_obj(path)
    assert len(vertices) == len(uvs) == len(mesh.vertices)
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    np.testing.assert_allclose(vertices, mesh.vertices, rtol=0, atol=1e-12)
    np.testing.assert_allclose(uvs, mesh.uv, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(faces, mesh.faces)
    write_obj(mesh, str(tmp_path / "as_string.obj"))
    assert (tmp_path / "as_string.obj").read_text() == path.read_text()


def test_the_papers_canonical_sheet_of_2_rulings_and_3_regions_is_reachable():
    # render.smooth_steps: 1 (or the condition table's canonical smooth_steps) gives the paper's
    # sharp creases: 2 guiding rulings cut the sheet into 3 planar regions; the default
    # interpolates 3 rulings per guide, smooth bends of 7 regions.
    paper = sample_sheet(2, np.random.default_rng(7), *A4, smooth_steps=1)
    smooth = sample_sheet(2, np.random.default_rng(7), *A4)
    assert len(paper.fold_lines) == 2 and len(np.unique(paper.face_regions)) == 3
    assert len(smooth.fold_lines) == 6 and len(np.unique(smooth.face_regions)) == 7
