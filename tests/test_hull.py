"""Convex hulls (warpcontact.hull): outward, closed, containing every point; degenerate inputs refused."""

import numpy as np
import pytest
import trimesh

from warpcontact.hull import convex_hull


def _check_hull(points, faces):
    mesh = trimesh.Trimesh(points, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    corner = points[faces[:, 0]]
    normal = np.cross(points[faces[:, 1]] - corner, points[faces[:, 2]] - corner)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    heights = np.einsum("fk,pfk->pf", normal, points[:, None, :] - corner[None])
    assert heights.max() <= 1e-9 * np.ptp(points, axis=0).max()  # every point inside or on every face
    return mesh


@pytest.mark.parametrize("seed", [0, 1])
def test_random_points_in_a_box(seed):
    points = np.random.default_rng(seed).uniform(-1.0, 1.0, (2000, 3))
    _check_hull(points, convex_hull(points))


@pytest.mark.parametrize(
    "mesh, volume",
    [
        (trimesh.creation.box(extents=(1.0, 2.0, 3.0)).subdivide().subdivide(), 6.0),  # coplanar points on every face
        (trimesh.creation.icosphere(subdivisions=2, radius=1e-6), None),  # tiny
        (trimesh.creation.box(extents=(1.0, 1.0, 1.0), transform=trimesh.transformations.translation_matrix((1e6, 0.0, 0.0))), 1.0),  # far from the origin
    ],
)
def test_meshes_whose_hull_is_known(mesh, volume):
    points = np.asarray(mesh.vertices, dtype=np.float64)
    hull = _check_hull(points, convex_hull(points))
    assert hull.volume == pytest.approx(mesh.volume if volume is None else volume, rel=1e-9)


def test_points_inside_are_left_out_or_refused_in_convex_position():
    cube = np.asarray(trimesh.creation.box(extents=(1.0, 1.0, 1.0)).vertices)
    points = np.vstack([cube, [[0.0, 0.0, 0.0], [0.1, 0.2, -0.3]]])
    assert set(np.unique(convex_hull(points))) == set(range(8))
    with pytest.raises(ValueError, match=r"point 8 is not in convex position"):
        convex_hull(points, all_on_hull=True)


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((3, 3)), r"expected \(N, 3\) with N >= 4"),
        (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]]), r"span no volume \(all on one line\)"),
        (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [2.0, 3.0, 0.0]]), r"span no volume \(all in one plane\)"),
        (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, np.nan]]), r"not all finite"),
    ],
)
def test_degenerate_points_are_refused(points, match):
    with pytest.raises(ValueError, match=match):
        convex_hull(points)


@pytest.mark.parametrize("distance", [1e-11, 1e-9, 1e-8, 1e-6])
def test_nearly_coinciding_points_give_a_right_hull_or_a_named_error(distance):
    # A copy of each point this close (an exporter's seam noise) left the hull open with up
    # to 200 times its volume, and points outside it, with no error.
    rng = np.random.default_rng(7)
    sphere = rng.standard_normal((150, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    points = np.vstack([sphere, sphere + distance * rng.standard_normal(sphere.shape)])[rng.permutation(300)]
    try:
        faces = convex_hull(points)
    except ValueError as exc:
        assert "could not be built reliably" in str(exc)
        return
    mesh = trimesh.Trimesh(points, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(trimesh.Trimesh(sphere, convex_hull(sphere), process=False).volume, rel=1e-5)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the overflow the check catches
def test_a_cube_too_large_for_float64_products_is_refused_not_misbuilt():
    # Squared lengths overflow: a cube of 1e120 m came back a tetrahedron, its corners outside.
    cube = np.asarray(trimesh.creation.box(extents=(1.0, 1.0, 1.0)).vertices)
    with pytest.raises(ValueError, match="could not be built reliably"):
        convex_hull(cube * 1e120)
    assert len(convex_hull(cube * 1e-9)) == len(convex_hull(cube * 1e9)) == 12
