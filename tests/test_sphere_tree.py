"""Layered bounding-sphere hierarchy: definition (def:BSH), layout, determinism, input checks.

Every property is recomputed independently from the mesh by walking the stored tree, so a
wrong centre, radius, split or index in build_sphere_tree makes a test fail.
"""

import math

import numpy as np
import pytest
import trimesh

from warpcontact.sphere_tree import SphereTree, build_sphere_tree

ARRAY_FIELDS = ("centers", "radii", "left", "right", "parent", "triangle", "depth", "vertex_count", "triangle_count")


def _random_soup(seed: int = 7, num_triangles: int = 157) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(3 * num_triangles + 20, 3)) * [3.0, 1.0, 0.5]
    faces = rng.integers(0, vertices.shape[0], size=(num_triangles, 3))
    return vertices, faces


def _with_degenerate_faces() -> tuple[np.ndarray, np.ndarray]:
    """A box plus zero-area faces: repeated indices, a point, and collinear vertices."""
    box = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    vertices = np.vstack([box.vertices, [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]]])
    nv = box.vertices.shape[0]
    extra = np.array([[0, 0, 1], [2, 2, 2], [nv, nv + 1, nv + 2], [nv + 1, nv, nv + 1], [3, 5, 3]])
    return vertices, np.vstack([box.faces, extra])


def _meshes():
    cases = {}
    for subdivisions in range(4):
        sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
        cases[f"icosphere{subdivisions}"] = (sphere.vertices, sphere.faces)
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    cases["box"] = (box.vertices, box.faces)
    cases["soup"] = _random_soup()
    cases["degenerate"] = _with_degenerate_faces()
    cases["single"] = (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), np.array([[0, 1, 2]]))
    cases["two"] = (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]]), np.array([[0, 1, 2], [1, 2, 3]]))
    return cases


MESHES = _meshes()


@pytest.fixture(scope="module", params=sorted(MESHES))
def built(request):
    vertices, faces = MESHES[request.param]
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    return vertices, faces, build_sphere_tree(vertices, faces, name=request.param)


def _subtree_triangles(tree: SphereTree, node: int) -> list[int]:
    stack, found = [node], []
    while stack:
        n = stack.pop()
        if tree.left[n] < 0:
            found.append(int(tree.triangle[n]))
        else:
            stack.extend((int(tree.right[n]), int(tree.left[n])))
    return found


def _distance(a, b) -> float:
    dx, dy, dz = (float(a[k]) - float(b[k]) for k in range(3))
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def _centroid_order_key(centroids, axis, triangle):
    return (centroids[triangle, axis], triangle)


def test_shapes_dtypes_and_counts(built):
    vertices, faces, tree = built
    num_triangles = faces.shape[0]
    assert tree.num_triangles == num_triangles
    assert tree.num_nodes == 2 * num_triangles - 1
    assert tree.centers.shape == (tree.num_nodes, 3) and tree.centers.dtype == np.float64
    assert tree.radii.dtype == np.float64
    for field in ("radii", "left", "right", "parent", "triangle", "depth", "vertex_count", "triangle_count"):
        assert getattr(tree, field).shape == (tree.num_nodes,), field
    for field in ("left", "right", "parent", "triangle", "depth", "vertex_count", "triangle_count"):
        assert getattr(tree, field).dtype == np.int32, field
    assert np.all(np.isfinite(tree.centers)) and np.all(np.isfinite(tree.radii)) and np.all(tree.radii >= 0)


def test_each_face_in_exactly_one_leaf(built):
    _, faces, tree = built
    is_leaf = tree.left < 0
    assert np.array_equal(is_leaf, tree.right < 0)
    assert np.array_equal(is_leaf, tree.triangle >= 0)
    assert np.array_equal(np.sort(tree.triangle[is_leaf]), np.arange(faces.shape[0]))


def test_preorder_and_links(built):
    _, _, tree = built
    assert tree.parent[0] == -1
    assert np.all(tree.parent[1:] >= 0)
    order, stack = [], [0]
    while stack:
        node = stack.pop()
        order.append(node)
        if tree.left[node] >= 0:
            stack.extend((int(tree.right[node]), int(tree.left[node])))
    assert order == list(range(tree.num_nodes))
    for node in np.flatnonzero(tree.left >= 0):
        left, right = tree.left[node], tree.right[node]
        assert node < left < right
        assert left == node + 1
        assert tree.parent[left] == node and tree.parent[right] == node
        assert tree.depth[left] == tree.depth[node] + 1 == tree.depth[right]
    assert tree.depth[0] == 0


def test_balanced_depth_bound(built):
    _, faces, tree = built
    num_triangles = faces.shape[0]
    assert tree.max_depth <= math.ceil(math.log2(num_triangles)) + 1
    for node in range(tree.num_nodes):
        assert tree.triangle_count[node] == len(_subtree_triangles(tree, node))
    for node in np.flatnonzero(tree.left >= 0):
        left_count = len(_subtree_triangles(tree, tree.left[node]))
        right_count = len(_subtree_triangles(tree, tree.right[node]))
        assert abs(left_count - right_count) <= 1


def test_leaf_sphere_is_centroid_and_farthest_vertex(built):
    vertices, faces, tree = built
    for node in np.flatnonzero(tree.left < 0):
        face = faces[tree.triangle[node]]
        unique = np.unique(face)
        centroid = vertices[unique].mean(axis=0)
        np.testing.assert_allclose(tree.centers[node], centroid, rtol=0, atol=1e-13 * (1 + np.abs(centroid).max()))
        assert tree.vertex_count[node] == unique.size
        expected_radius = max(_distance(vertices[i], tree.centers[node]) for i in face)
        assert tree.radii[node] == pytest.approx(expected_radius, rel=1e-14, abs=1e-15)


def test_internal_sphere_matches_definition(built):
    vertices, faces, tree = built
    scale = 1.0 + np.abs(vertices).max()
    for node in np.flatnonzero(tree.left >= 0):
        unique = np.unique(faces[_subtree_triangles(tree, node)])
        assert tree.vertex_count[node] == unique.size
        np.testing.assert_allclose(tree.centers[node], vertices[unique].mean(axis=0), rtol=0, atol=1e-13 * scale)

        center, radius = tree.centers[node], tree.radii[node]
        reaches = [_distance(center, tree.centers[c]) + tree.radii[c] for c in (tree.left[node], tree.right[node])]
        assert radius == max(reaches)  # the enclosing formula, evaluated in the same order
        assert all(reach <= radius for reach in reaches)
        farthest_vertex = np.sqrt(((vertices[unique] - center) ** 2).sum(axis=1)).max()
        assert farthest_vertex <= radius * (1 + 1e-12) + 1e-15


def test_split_is_median_along_longest_centroid_axis(built):
    vertices, faces, tree = built
    centroids = np.stack([vertices[np.unique(face)].mean(axis=0) for face in faces])
    for node in np.flatnonzero(tree.left >= 0):
        left_triangles = _subtree_triangles(tree, tree.left[node])
        right_triangles = _subtree_triangles(tree, tree.right[node])
        assert len(left_triangles) == (len(left_triangles) + len(right_triangles) + 1) // 2
        box = centroids[left_triangles + right_triangles]
        axis = int(np.argmax(box.max(axis=0) - box.min(axis=0)))
        last_left = max(_centroid_order_key(centroids, axis, t) for t in left_triangles)
        first_right = min(_centroid_order_key(centroids, axis, t) for t in right_triangles)
        assert last_left < first_right


def test_single_triangle_is_one_leaf():
    vertices, faces = MESHES["single"]
    tree = build_sphere_tree(vertices, faces)
    assert tree.num_nodes == 1 and tree.max_depth == 0
    assert tree.left[0] == tree.right[0] == tree.parent[0] == -1 and tree.triangle[0] == 0
    np.testing.assert_array_equal(tree.centers[0], vertices.mean(axis=0))


def test_degenerate_leaf_uses_unique_vertices():
    vertices = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [9.0, 9.0, 9.0]])
    tree = build_sphere_tree(vertices, np.array([[0, 0, 1]]))
    np.testing.assert_array_equal(tree.centers[0], [1.5, 0.0, 0.0])
    assert tree.radii[0] == 1.5 and tree.vertex_count[0] == 2


def test_unused_vertices_do_not_move_centres():
    vertices = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [100.0, 100.0, 100.0]])
    tree = build_sphere_tree(vertices, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(tree.centers[0], [2.0 / 3.0, 2.0 / 3.0, 0.0], rtol=0, atol=1e-15)


def test_deterministic_and_independent_of_input_copies():
    vertices, faces = _random_soup(seed=3, num_triangles=600)
    first = build_sphere_tree(vertices, faces)
    again = build_sphere_tree(vertices, faces)
    from_copy = build_sphere_tree(vertices.copy(), faces.copy())
    from_float32_faces = build_sphere_tree(vertices, faces.astype(np.float32))
    for other in (again, from_copy, from_float32_faces):
        for field in ARRAY_FIELDS:
            a, b = getattr(first, field), getattr(other, field)
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), field


def test_coincident_centroids_break_ties_by_triangle_index():
    # Every triangle has the same centroid, so only the index tie-break orders them.
    base = np.array([[1.0, 0.0, 0.0], [-0.5, 0.8, 0.0], [-0.5, -0.8, 0.0]])
    vertices = np.vstack([base * (k + 1) for k in range(6)])
    faces = np.arange(18).reshape(6, 3)[::-1].copy()
    tree = build_sphere_tree(vertices, faces)
    leaves_in_storage_order = tree.triangle[tree.left < 0]
    np.testing.assert_array_equal(leaves_in_storage_order, np.arange(6))


def test_tree_is_frozen():
    vertices, faces = MESHES["two"]
    tree = build_sphere_tree(vertices, faces)
    with pytest.raises(AttributeError):
        tree.radii = np.zeros(3)


def test_large_mesh_builds():
    sphere = trimesh.creation.icosphere(subdivisions=5)
    tree = build_sphere_tree(sphere.vertices, sphere.faces, name="icosphere5")
    assert tree.num_triangles == 20480
    assert tree.max_depth <= math.ceil(math.log2(20480)) + 1
    assert np.array_equal(np.sort(tree.triangle[tree.left < 0]), np.arange(20480))
    assert tree.vertex_count[0] == sphere.vertices.shape[0]
    assert np.all(tree.radii[tree.left[tree.left >= 0]] <= tree.radii[tree.left >= 0])


GOOD_VERTICES = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
GOOD_FACES = np.array([[0, 1, 2], [0, 2, 3]])
NAN_VERTICES = GOOD_VERTICES.copy()
NAN_VERTICES[2, 1] = np.nan


@pytest.mark.parametrize(
    ("vertices", "faces", "message"),
    [
        (GOOD_VERTICES[:, :2], GOOD_FACES, "vertices must have shape"),
        (GOOD_VERTICES.ravel(), GOOD_FACES, "vertices must have shape"),
        (NAN_VERTICES, GOOD_FACES, "vertex 2 is not finite"),
        (np.where(NAN_VERTICES == NAN_VERTICES, NAN_VERTICES, np.inf), GOOD_FACES, "vertex 2 is not finite"),
        (GOOD_VERTICES, GOOD_FACES[:, :2], "faces must have shape"),
        (GOOD_VERTICES, GOOD_FACES.ravel(), "faces must have shape"),
        (GOOD_VERTICES, np.zeros((0, 3), dtype=np.int64), "has no faces"),
        (GOOD_VERTICES, np.array([[0, 1, 2], [0, 1.5, 3]]), "face 1 has non-integer"),
        (GOOD_VERTICES, np.array([[0, 1, 2], [0, np.nan, 3]]), "face 1 has non-integer"),
        (GOOD_VERTICES, np.array([[0, 1, 2], [0, 1, 4]]), "face 1 has vertex indices"),
        (GOOD_VERTICES, np.array([[0, -1, 2]]), "face 0 has vertex indices"),
        (GOOD_VERTICES, [["a", "b", "c"]], "faces must be real numbers"),
        ([["x", "y", "z"]], GOOD_FACES, "vertices must be real numbers"),
        (GOOD_VERTICES, np.ones((2, 3), dtype=bool), "faces must be real numbers"),
        (None, GOOD_FACES, "vertices must be real numbers"),
        ([[0.0, 0.0, 0.0], [1.0, 0.0]], GOOD_FACES, "vertices cannot be read"),
        # Squared distances underflowed: every leaf sphere of a 1e-170 m ball had radius 0;
        # below ~1e-77 m the leaf search's fourth powers did (disjoint triangles touched).
        (GOOD_VERTICES * 1e-160, GOOD_FACES, "m, below the 1e-75 m that float64 contact geometry resolves"),
        (GOOD_VERTICES * 1e-82, GOOD_FACES, "m, below the 1e-75 m that float64 contact geometry resolves"),
        # The faces' extent: a vertex no face uses, 1 m away, let such a mesh through.
        (np.vstack([GOOD_VERTICES * 1e-170, [[1.0, 0.0, 0.0]]]), GOOD_FACES, "spans 1e-170 m, below the 1e-75 m"),
    ],
)
def test_bad_input_names_mesh_and_problem(vertices, faces, message):
    with pytest.raises(ValueError, match="bad_mesh") as error:
        build_sphere_tree(vertices, faces, name="bad_mesh")
    assert message in str(error.value)


def test_unused_vertices_do_not_count_in_the_extent():
    """A body collapsed to one point is valid; an unused vertex 1e-80 m from it had it refused."""
    point = np.vstack([np.zeros((3, 3)), [[1e-80, 0.0, 0.0]]])
    tree = build_sphere_tree(point, np.array([[0, 1, 2]]))
    assert tree.radii.max() == 0.0


def test_copies_of_a_vertex_count_once():
    """Unique vertices are unique positions: the same sphere with each face's corners listed
    as copies of their own gave other centres and splits, and the hierarchy's contact value
    3 m from a box moved 11% (665.11 against 738.58; a probe, stop 65)."""
    import warpcontact as wc

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    welded = (np.asarray(sphere.vertices), np.asarray(sphere.faces))
    copies = (welded[0][welded[1]].reshape(-1, 3), np.arange(3 * len(welded[1])).reshape(-1, 3))
    a, b = build_sphere_tree(*welded), build_sphere_tree(*copies)
    for name in ("left", "right", "triangle", "vertex_count", "triangle_count"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    # The same vertices, summed in another order (their indices differ): equal to rounding.
    for name in ("centers", "radii"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0.0, atol=1e-15, err_msg=name)
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    poses = np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]])
    values = [wc.ContactModel([mesh, (box.vertices, box.faces)], static=[False, True]).evaluate(poses).value for mesh in (welded, copies)]
    assert values[0] == pytest.approx(values[1], rel=1e-12)
