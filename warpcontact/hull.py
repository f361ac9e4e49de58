"""Convex hulls of point sets (host side, numpy): outward-oriented triangles.

One home for the scenes' Fibonacci balls (points in convex position) and for USD colliders
authored with ``physics:approximation = "convexHull"``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["convex_hull", "convex_hull_mesh"]

# A point closer than this fraction of the points' extent to a face's plane, on its outer
# side, counts as on the hull already (not in convex position). At 1e-12 a point 1e-11 from
# a hull vertex (an exporter's seam) saw faces by rounding noise, and the hull came out open
# with the wrong volume; the plane tests' rounding is ~1e-15 of the extent.
_PLANE_TOLERANCE = 1e-9
# Points closer than this fraction of the extent to an earlier point are left out with it:
# a face through two points d apart has a normal good to ~1e-16 / d, and planes of such
# slivers misjudged points by more than the tolerance (points 1e-8 apart broke the hull).
_MERGE_DISTANCE = 1e-6


def convex_hull(points, *, all_on_hull: bool = False) -> np.ndarray:
    """Outward-oriented triangles (indices into ``points``) of the convex hull of ``points``.

    Incremental: from a tetrahedron (the first four points where they span one), each point
    in turn replaces the faces it sees with a fan from their horizon. Points inside the hull
    or on it (within 1e-9 of the points' extent), and points within 1e-6 of it of an earlier
    point, are left out, or with ``all_on_hull``
    (points meant to be in convex position) are an error. Each point is tested against every
    face, so the cost grows as points x hull faces (this 2-core CPU: 0.07 s for 642 points
    all on the hull, 0.5 s for 2,562, 6 s for 10,242; a 3,000-point cloud in a box, 0.1 s).

    Args:
        points: (N, 3) coordinates, N >= 4, finite.

    The points are centred and scaled to unit extent first, so that no product overflows or
    underflows at any scale (a cube of 1e120 m came out a tetrahedron, one of 1e-120 m "in one
    plane"). The result is checked: closed, every edge used once each way, every point inside.

    Raises ValueError for fewer than 4 points, non-finite points, points that span no volume
    (collinear or coplanar, within 1e-9 of their extent), or a hull that fails its check.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise ValueError(f"points: expected (N, 3) with N >= 4, got shape {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points: not all finite")
    low, high = points.min(axis=0), points.max(axis=0)
    extent = float((high - low).max())
    if extent == 0.0:
        raise ValueError("points: they span no volume (all at one point)")
    points = (points - 0.5 * (low + high)) / extent
    kept = _first_of_near_duplicates(points, _MERGE_DISTANCE)
    if all_on_hull and not kept.all():
        raise ValueError(f"point {int(np.flatnonzero(~kept)[0])} is not in convex position (it nearly coincides with an earlier one)")
    index = np.flatnonzero(kept)
    faces = _incremental_hull(points[index], _PLANE_TOLERANCE, all_on_hull)
    _check_hull(points[index], faces, _PLANE_TOLERANCE)  # the merged points lie within 1e-6 of it
    return index[faces]


def _first_of_near_duplicates(points: np.ndarray, distance: float) -> np.ndarray:
    """(N,) True for each point farther than ``distance`` from every earlier point: a sweep
    along the axis of widest spread, comparing each point with those following it within
    ``distance`` along that axis."""
    axis = int(np.argmax(np.ptp(points, axis=0)))
    order = np.argsort(points[:, axis], kind="stable")
    ordered = points[order]
    kept = np.ones(len(points), dtype=bool)
    for step in range(1, len(points)):
        near = ordered[step:, axis] - ordered[:-step, axis] < distance
        if not near.any():
            break
        close = near & (np.linalg.norm(ordered[step:] - ordered[:-step], axis=1) < distance)
        first, second = order[:-step][close], order[step:][close]
        kept[np.maximum(first, second)] = False  # the later of the two in the input's order
    return kept


def _incremental_hull(points: np.ndarray, tolerance: float, all_on_hull: bool) -> np.ndarray:
    """``convex_hull``'s faces of ``points`` scaled to unit extent."""
    seed = _seed_tetrahedron(points, tolerance)
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


def _check_hull(points: np.ndarray, faces: np.ndarray, tolerance: float) -> None:
    """ValueError unless ``faces`` close up with every edge used once in each direction and
    every point lies inside every face's plane (within 10 ``tolerance``)."""
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    directed = {tuple(e) for e in edges.tolist()}
    closed = len(directed) == len(edges) and all((v, u) in directed for u, v in directed)
    outside = -np.inf
    if closed:
        corner, scaled = _face_planes(points, faces, tolerance)
        offset = np.einsum("fi,fi->f", corner, scaled)
        for start in range(0, len(points), 256):  # points x faces in slices of bounded memory
            outside = max(outside, float((points[start : start + 256] @ scaled.T - offset).max()))
    if not closed or outside > 10.0:
        raise ValueError(
            "points: their convex hull could not be built reliably (near-degenerate points: a sliver of a set, or "
            "points that nearly coincide); merge points closer than about 1e-9 of the set's extent"
        )


def _face_planes(points: np.ndarray, faces: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Each face's first corner and its unit normal divided by ``tolerance``."""
    corner = points[faces[:, 0]]
    normal = np.cross(points[faces[:, 1]] - corner, points[faces[:, 2]] - corner)
    return corner, normal / (tolerance * np.linalg.norm(normal, axis=1, keepdims=True))


def convex_hull_mesh(points) -> tuple[np.ndarray, np.ndarray]:
    """The convex hull of ``points`` as a mesh of the points it uses: (vertices, faces)."""
    points = np.asarray(points, dtype=np.float64)
    used, faces = np.unique(convex_hull(points), return_inverse=True)
    return points[used], faces.reshape(-1, 3)


def _seed_tetrahedron(points: np.ndarray, tolerance: float) -> tuple[int, int, int, int]:
    """The first four points where they span a tetrahedron, else four extreme points."""
    if _tetrahedron_height(points, (0, 1, 2), 3) > tolerance:
        return 0, 1, 2, 3
    first = int(np.argmin(points[:, 0]))
    second = int(np.argmax(np.linalg.norm(points - points[first], axis=1)))
    axis = points[second] - points[first]
    axis /= max(np.linalg.norm(axis), np.finfo(np.float64).tiny)
    offsets = points - points[first]
    off_line = offsets - np.outer(offsets @ axis, axis)
    third = int(np.argmax(np.linalg.norm(off_line, axis=1)))
    if np.linalg.norm(off_line[third]) <= tolerance:
        raise ValueError("points: they span no volume (all on one line)")
    heights = [_tetrahedron_height(points, (first, second, third), p) for p in range(len(points))]
    fourth = int(np.argmax(heights))
    if heights[fourth] <= tolerance:
        raise ValueError("points: they span no volume (all in one plane)")
    return first, second, third, fourth


def _tetrahedron_height(points: np.ndarray, base: tuple, apex: int) -> float:
    """Distance of ``points[apex]`` from the plane through the three ``base`` points (0 for
    a degenerate base)."""
    i, j, k = base
    normal = np.cross(points[j] - points[i], points[k] - points[i])
    length = np.linalg.norm(normal)
    return 0.0 if length == 0.0 else float(abs(np.dot(normal, points[apex] - points[i])) / length)
