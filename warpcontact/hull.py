"""Convex hulls of point sets (host side, numpy): outward-oriented triangles.

One home for the scenes' Fibonacci balls (points in convex position) and for USD colliders
authored with ``physics:approximation = "convexHull"``.
"""

from __future__ import annotations

import numpy as np

from ._validate import real_array

__all__ = ["convex_hull", "convex_hull_mesh"]

# A point closer than this fraction of the points' extent to a face's plane, on its outer
# side, counts as on the hull already (not in convex position).
_PLANE_TOLERANCE = 1e-12
# Where that hull fails its check, it is built again with these (all_on_hull excepted).
_PLANE_TOLERANCES = (_PLANE_TOLERANCE, 1e-10, 1e-8, 1e-6)
# The returned hull may miss a point by this fraction of the extent (rounding of the plane
# tests of sliver faces), or by this many plane tolerances where that is more; a larger
# miss, or a hull that is not closed, is refused.
_CHECK_TOLERANCE = 1e-9
_CHECK_MARGIN = 10.0
# Sets thinner than this fraction of their extent are refused as nearly flat: the check
# above cannot see errors in them (a 1 x 1 x 1.8e-11 slab came back with 6% more volume and
# points 0.9 of its thickness outside).
_FLAT_TOLERANCE = 1e-8


def convex_hull(points, *, all_on_hull: bool = False) -> np.ndarray:
    """Outward-oriented triangles (indices into ``points``) of the convex hull of ``points``.

    Incremental: from a tetrahedron (the first four points where they span one), each point
    in turn replaces the faces it sees with a fan from their horizon. Points inside the hull
    or on it (within 1e-12 of the points' extent) are left out, or with ``all_on_hull``
    (points meant to be in convex position) are an error. Each point is tested against every
    face, so the cost grows as points x hull faces (this 2-core CPU: 0.07 s for 642 points
    all on the hull, 0.5 s for 2,562, 6 s for 10,242; a 3,000-point cloud in a box, 0.1 s).

    Args:
        points: (N, 3) coordinates, N >= 4, finite.

    The result is checked: closed (every edge used once each way) and no point outside it by
    more than 1e-9 of the extent. Where that fails (points in one plane to within their own
    rounding, as float32 points or points 1e4 m from the origin are, let rounding decide which
    faces a point sees), the hull is built again counting points within 1e-10, 1e-8, then
    1e-6 of the extent of a face's plane on it, and checked to 10 times that (not with
    ``all_on_hull``). Points that nearly coincide (a copy of each point 1e-11
    away, an exporter's seam) can make the plane tests' rounding decide visibility, and such a
    hull came back open, with up to 200 times the volume and points outside it; it is refused
    now. The points are scaled by a power of two (exactly) to an extent of about 1, so sets of
    any size within float64's range give the same hull (a cube of 1e120 m came back a
    tetrahedron).

    Raises ValueError for fewer than 4 points, non-finite points, points that span no volume
    (collinear or coplanar) or almost none (thinner than 1e-8 of their extent), or a hull
    that fails its check.
    """
    given = points
    points = real_array(points)
    if points is None:  # text or ragged lists failed inside numpy, bools read as 0/1, complex numbers lost their imaginary parts
        raise ValueError(f"points: expected (N, 3) real numbers, not text, bools, complex numbers or ragged lists; got a {type(given).__name__} of such")
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError(f"points: expected (N, 3) with N >= 4, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points: not all finite")
    extent = float(np.ptp(points, axis=0).max())
    if not 0.0 < extent < np.inf:
        raise ValueError(f"points: they span {extent:g} m, which float64 differences of them cannot represent" if extent else "points: they all coincide")
    # Scaled by a power of two to an extent of about 1, exactly: squared lengths overflowed or
    # underflowed beyond ~1e80 and below ~1e-85 (a unit cube of 1e100 m read as flat).
    exponent = int(np.frexp(extent)[1])
    points, extent = np.ldexp(points, -exponent), float(np.ldexp(extent, -exponent))
    # On points in one plane to within their own rounding (float32 points, or points 1e4 m
    # from the origin) rounding decided which faces a point saw: hulls came back open, or
    # with sliver faces whose rounding-set planes had points "outside", and convexHull
    # colliders were refused (a turned, subdivided float32 box in 9 of 100 turns; a cylinder
    # 1e4 m out in every turn; a probe, stop 63). Such sets are built again with points near
    # a face's plane counted on it, and checked to that tolerance.
    seed = _seed_tetrahedron(points, _PLANE_TOLERANCE * extent, extent)
    failure = None
    for relative in (_PLANE_TOLERANCE,) if all_on_hull else _PLANE_TOLERANCES:
        faces = _incremental_hull(points, seed, relative * extent, all_on_hull)
        failure = _hull_failure(points, faces, max(_CHECK_TOLERANCE, _CHECK_MARGIN * relative))
        if failure is None:
            return faces
    raise ValueError(
        f"points: their convex hull could not be built reliably ({failure}, with points within {relative:g} of their extent of a face's "
        "plane counted on it): points that nearly coincide, or a set too large or small for float64 products; merge points that nearly "
        "coincide, or rescale them"
    )


def _incremental_hull(points: np.ndarray, seed: tuple[int, int, int, int], tolerance: float, all_on_hull: bool) -> np.ndarray:
    """Outward triangles of the hull of ``points`` (scaled to an extent of about 1), grown
    from the tetrahedron ``seed``, where a point within ``tolerance`` of a face's plane counts
    as on it; unchecked."""
    centre = points[list(seed)].mean(axis=0)
    a, b, c, d = seed
    faces = []
    for f in ((a, b, c), (a, c, d), (a, d, b), (b, d, c)):
        i, j, k = f
        normal = np.cross(points[j] - points[i], points[k] - points[i])
        faces.append(f if np.dot(normal, points[i] - centre) > 0 else (i, k, j))
    faces = np.array(faces, dtype=np.int64)
    # Per face: its first corner and its normal scaled to unit length over the tolerance, so
    # that a point sees the face where (p - corner) . scaled > 1.
    corner, scaled = _face_planes(points, faces, tolerance)
    rest = [p for p in range(len(points)) if p not in seed]
    for p in rest:
        visible = np.einsum("ij,ij->i", scaled, points[p] - corner) > 1.0
        if not visible.any():
            if all_on_hull:
                raise ValueError(f"point {p} is not in convex position")
            continue
        edges = {(int(f[e]), int(f[(e + 1) % 3])) for f in faces[visible] for e in range(3)}
        horizon = np.array([(u, v, p) for (u, v) in edges if (v, u) not in edges], dtype=np.int64).reshape(-1, 3)
        new_corner, new_scaled = _face_planes(points, horizon, tolerance)
        faces = np.concatenate([faces[~visible], horizon])
        corner = np.concatenate([corner[~visible], new_corner])
        scaled = np.concatenate([scaled[~visible], new_scaled])
    return faces


def _hull_failure(points: np.ndarray, faces: np.ndarray, tolerance: float) -> str | None:
    """None where ``faces`` close up with every edge used once in each direction and no
    point lies outside a face's plane by more than ``tolerance`` of the extent (tested on the
    points centred and scaled to unit extent); else what fails."""
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    directed = {tuple(e) for e in edges.tolist()}
    closed = len(directed) == len(edges) and all((v, u) in directed for u, v in directed)
    outside = np.inf
    if closed:
        low, high = points.min(axis=0), points.max(axis=0)
        unit = (points - 0.5 * (low + high)) / float((high - low).max())
        corner = unit[faces[:, 0]]
        normal = np.cross(unit[faces[:, 1]] - corner, unit[faces[:, 2]] - corner)
        with np.errstate(invalid="ignore", divide="ignore"):
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        offset = np.einsum("fi,fi->f", corner, normal)
        outside = -np.inf
        for start in range(0, len(unit), 256):  # points x faces in slices of bounded memory
            outside = max(outside, float(np.nan_to_num(unit[start : start + 256] @ normal.T - offset, nan=np.inf).max()))
    if not closed:
        return "it does not close up"
    if not outside <= tolerance:
        return f"a point lies {outside:.2g} of the extent outside it"
    return None


def _face_planes(points: np.ndarray, faces: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Each face's first corner and its unit normal divided by ``tolerance``."""
    corner = points[faces[:, 0]]
    normal = np.cross(points[faces[:, 1]] - corner, points[faces[:, 2]] - corner)
    return corner, normal / (tolerance * np.linalg.norm(normal, axis=1, keepdims=True))


def convex_hull_mesh(points) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull of ``points`` as a mesh of the points it uses: (vertices, faces)."""
    used, faces = np.unique(convex_hull(points), return_inverse=True)
    points = real_array(points)
    return points[used], faces.reshape(-1, 3)


def _seed_tetrahedron(points: np.ndarray, tolerance: float, extent: float) -> tuple[int, int, int, int]:
    """Four extreme points, or the first four where they span a tetrahedron on a base that is
    no line; ValueError for points that span no volume, or almost none (_FLAT_TOLERANCE)."""
    first, second, third, heights = _extreme_triangle(points, tolerance)
    fourth = int(np.argmax(heights))
    if heights[fourth] <= tolerance:
        raise ValueError("points: they span no volume (all in one plane)")
    if heights[fourth] <= _FLAT_TOLERANCE * extent:
        raise ValueError(f"points: they span almost no volume (a thickness of {heights[fourth] / extent:.1e} of their extent, below {_FLAT_TOLERANCE:g}), where their hull is not reliable in float64")
    # A first three on one line gave a base whose normal was rounding noise, and a first four
    # in one plane a flat seed. "On" is to within the points' own rounding, which can exceed
    # ``tolerance``: four points of a cylinder's rim 1e4 m from the origin made a seed 1e-12
    # of the extent thick, turned either way by rounding (a probe, stop 63).
    thick = _FLAT_TOLERANCE * extent
    if np.linalg.norm(_off_line(points[:3], 0, 1)[2]) > thick and _tetrahedron_height(points, (0, 1, 2), 3) > thick:
        return 0, 1, 2, 3
    return first, second, third, fourth


def _off_line(points: np.ndarray, i: int, j: int) -> np.ndarray:
    """Each point's offset from the line through ``points[i]`` and ``points[j]``, across it
    (from ``points[i]`` where the two coincide)."""
    axis = points[j] - points[i]
    axis /= max(np.linalg.norm(axis), np.finfo(np.float64).tiny)
    offsets = points - points[i]
    return offsets - np.outer(offsets @ axis, axis)


def _extreme_triangle(points: np.ndarray, tolerance: float) -> tuple[int, int, int, np.ndarray]:
    """Three extreme points (the lowest in x, the farthest from it, the farthest from their
    line) and every point's height over their plane; ValueError for points on one line."""
    first = int(np.argmin(points[:, 0]))
    second = int(np.argmax(np.linalg.norm(points - points[first], axis=1)))
    off_line = _off_line(points, first, second)
    third = int(np.argmax(np.linalg.norm(off_line, axis=1)))
    if np.linalg.norm(off_line[third]) <= tolerance:
        raise ValueError("points: they span no volume (all on one line)")
    normal = np.cross(points[second] - points[first], points[third] - points[first])
    return first, second, third, np.abs((points - points[first]) @ (normal / np.linalg.norm(normal)))


def _tetrahedron_height(points: np.ndarray, base: tuple, apex: int) -> float:
    """Distance of ``points[apex]`` from the plane through the three ``base`` points (0 for
    a degenerate base)."""
    i, j, k = base
    normal = np.cross(points[j] - points[i], points[k] - points[i])
    length = np.linalg.norm(normal)
    return 0.0 if length == 0.0 else float(abs(np.dot(normal, points[apex] - points[i])) / length)
