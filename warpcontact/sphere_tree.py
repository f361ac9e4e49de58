"""Layered bounding-sphere hierarchy (BSH) of a rigid-body mesh (Definition def:BSH).

The tree is built once, in the body frame, and moves rigidly with the body; it is never
rebuilt. It is a binary tree with one triangle per leaf. A node's centre is the mean of the
unique vertices under it, a leaf's radius reaches its triangle's farthest vertex, and an
internal node's radius is the smallest one about its centre that encloses both children's
spheres ("layered": spheres enclose spheres, not just the geometry).

Construction is top-down and breadth-first: at every level, all nodes that still hold more
than one triangle split at the median triangle centroid along the longest axis of their
centroid bounding box, in one vectorised sort over the whole level. The tree is therefore
balanced (leaves differ in depth by at most one) and the build costs O(T log^2 T) for T
triangles: ceil(log2 T) levels, each an O(T log T) sort plus an O(T log T) unique-vertex pass.
"""

from dataclasses import dataclass

import numpy as np

from ._validate import check_coordinates, extent_problem, real_dtype

__all__ = ["SphereTree", "build_sphere_tree", "tree_of_validated_mesh", "validated_mesh", "welded_face_indices"]


@dataclass(frozen=True)
class SphereTree:
    """Layered bounding-sphere hierarchy of one mesh, in the body frame (float64, metres).

    Arrays have one row per node, M = 2 T - 1 nodes for T triangles, pre-order (root 0,
    parent index < child index; a left subtree is stored whole before its right sibling).

    Attributes:
        centers: (M, 3) float64 node centre, the mean of the unique vertices under the node (m).
        radii: (M,) float64 node radius (m).
        left: (M,) int32 left child, -1 at leaves.
        right: (M,) int32 right child, -1 at leaves.
        parent: (M,) int32 parent, -1 at the root.
        triangle: (M,) int32 face index at leaves, -1 at internal nodes.
        depth: (M,) int32 depth, root 0.
        vertex_count: (M,) int32 number of unique vertex positions under the node.
        triangle_count: (M,) int32 number of triangles (leaves) under the node.
    """

    centers: np.ndarray
    radii: np.ndarray
    left: np.ndarray
    right: np.ndarray
    parent: np.ndarray
    triangle: np.ndarray
    depth: np.ndarray
    vertex_count: np.ndarray
    triangle_count: np.ndarray

    @property
    def num_nodes(self) -> int:
        """Number of nodes M = 2 T - 1."""
        return int(self.radii.shape[0])

    @property
    def num_triangles(self) -> int:
        """Number of triangles T (= number of leaves)."""
        return (self.num_nodes + 1) // 2

    @property
    def max_depth(self) -> int:
        """Depth of the deepest leaf (0 for a single-triangle mesh)."""
        return int(self.depth.max())


def build_sphere_tree(vertices, faces, *, name: str = "mesh") -> SphereTree:
    """Build the layered bounding-sphere hierarchy of a triangle mesh.

    Args:
        vertices: (nv, 3) vertex positions in the body frame (m); any real dtype, computed in
            float64. Vertices no face uses are allowed and ignored.
        faces: (nf, 3) vertex indices per triangle, nf >= 1; integer-valued (a float array of
            whole numbers is accepted). Zero-area faces, including ones that repeat a vertex
            index, are allowed: they act as the segment or point they are.
        name: mesh name used in error messages.

    Returns:
        The tree, with ``2 nf - 1`` nodes in pre-order. Deterministic: the same input gives
        bit-identical arrays.

    Raises:
        ValueError: naming the mesh and the problem, for non-numeric input, wrong shapes,
            non-finite vertices, non-integer or out-of-range face indices, or no faces.
    """
    return tree_of_validated_mesh(*validated_mesh(vertices, faces, name))


def tree_of_validated_mesh(positions: np.ndarray, face_indices: np.ndarray) -> SphereTree:
    """``build_sphere_tree`` of a mesh ``validated_mesh`` returned (float64 positions, int64
    faces), for callers that validated it already (a contact model checks its bodies first:
    validating again was a second pass over every mesh)."""
    num_triangles = face_indices.shape[0]
    num_nodes = 2 * num_triangles - 1

    every_face = np.arange(num_triangles)
    # Unique vertices are unique positions: a mesh whose faces each listed their own copies
    # of shared corners counted each corner once per face, which moved the centres and splits
    # (the hierarchy's value 11% off the welded mesh's 3 m away; a probe, stop 65).
    welded = welded_face_indices(positions, face_indices)
    # Leaf centres double as the split keys, so both follow the unique-vertex definition.
    triangle_centroids, triangle_vertex_counts = _unique_vertex_means(
        positions, welded, every_face, every_face, num_triangles
    )

    centers = np.empty((num_nodes, 3), dtype=np.float64)
    radii = np.empty(num_nodes, dtype=np.float64)
    left = np.full(num_nodes, -1, dtype=np.int32)
    right = np.full(num_nodes, -1, dtype=np.int32)
    parent = np.full(num_nodes, -1, dtype=np.int32)
    triangle = np.full(num_nodes, -1, dtype=np.int32)
    depth = np.empty(num_nodes, dtype=np.int32)
    vertex_count = np.empty(num_nodes, dtype=np.int32)
    triangle_count = np.empty(num_nodes, dtype=np.int32)

    # Each node owns a contiguous run of `triangle_order`; splitting only reorders inside runs.
    triangle_order = np.arange(num_triangles)
    level_node = np.zeros(1, dtype=np.int64)
    level_start = np.zeros(1, dtype=np.int64)
    level_size = np.full(1, num_triangles, dtype=np.int64)
    internal_nodes_by_level = []
    level_depth = 0
    while level_node.size:
        depth[level_node] = level_depth
        triangle_count[level_node] = level_size
        is_leaf = level_size == 1

        leaf_nodes = level_node[is_leaf]
        leaf_triangles = triangle_order[level_start[is_leaf]]
        triangle[leaf_nodes] = leaf_triangles
        centers[leaf_nodes] = triangle_centroids[leaf_triangles]
        vertex_count[leaf_nodes] = triangle_vertex_counts[leaf_triangles]
        radii[leaf_nodes] = _farthest_vertex_distance(
            positions[face_indices[leaf_triangles]], centers[leaf_nodes]
        )

        split_node = level_node[~is_leaf]
        split_start = level_start[~is_leaf]
        split_size = level_size[~is_leaf]
        if split_node.size == 0:
            break
        internal_nodes_by_level.append(split_node)

        segment_of_slot = np.repeat(np.arange(split_node.size), split_size)
        segment_offset = np.cumsum(split_size) - split_size
        slot = split_start[segment_of_slot] + (np.arange(segment_of_slot.size) - segment_offset[segment_of_slot])
        slot_triangle = triangle_order[slot]

        centers[split_node], counts = _unique_vertex_means(
            positions, welded, slot_triangle, segment_of_slot, split_node.size
        )
        vertex_count[split_node] = counts

        slot_centroid = triangle_centroids[slot_triangle]
        box_extent = np.maximum.reduceat(slot_centroid, segment_offset) - np.minimum.reduceat(
            slot_centroid, segment_offset
        )
        split_axis = np.argmax(box_extent, axis=1)
        split_key = slot_centroid[np.arange(slot.size), split_axis[segment_of_slot]]
        # The segment is the primary key, so every run stays in place; the triangle index
        # breaks coordinate ties so the order never depends on the sort's internals.
        within_segment_order = np.lexsort((slot_triangle, split_key, segment_of_slot))
        triangle_order[slot] = slot_triangle[within_segment_order]

        left_size = (split_size + 1) // 2
        left_node = split_node + 1
        # Pre-order: the left subtree's 2 * left_size - 1 nodes come before the right child.
        right_node = split_node + 2 * left_size
        left[split_node] = left_node
        right[split_node] = right_node
        parent[left_node] = split_node
        parent[right_node] = split_node

        # Interleaving keeps the next level in storage order of the runs, which the
        # segment-major sort above relies on.
        level_node = np.stack((left_node, right_node), axis=1).ravel()
        level_start = np.stack((split_start, split_start + left_size), axis=1).ravel()
        level_size = np.stack((left_size, split_size - left_size), axis=1).ravel()
        level_depth += 1

    # Children's spheres must be final before their parent's, so radii go bottom-up.
    for nodes in reversed(internal_nodes_by_level):
        reach_left = _distance(centers[nodes], centers[left[nodes]]) + radii[left[nodes]]
        reach_right = _distance(centers[nodes], centers[right[nodes]]) + radii[right[nodes]]
        radii[nodes] = np.maximum(reach_left, reach_right)

    return SphereTree(
        centers=centers,
        radii=radii,
        left=left,
        right=right,
        parent=parent,
        triangle=triangle,
        depth=depth,
        vertex_count=vertex_count,
        triangle_count=triangle_count,
    )


def _distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance between rows of (..., 3) arrays, summed x, y, z in that order."""
    d = a - b
    return np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])


def _farthest_vertex_distance(triangle_vertices: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """(N,) largest distance from centers (N, 3) to the vertices of triangles (N, 3, 3)."""
    return _distance(triangle_vertices, centers[:, None, :]).max(axis=1)


def welded_face_indices(positions: np.ndarray, face_indices: np.ndarray) -> np.ndarray:
    """``face_indices`` with each vertex index replaced by the lowest index holding the same
    position (unchanged where no two vertices coincide; -0.0 and 0.0 coincide)."""
    _, first, row = np.unique(np.asarray(positions, dtype=np.float64), axis=0, return_index=True, return_inverse=True)
    return first[row.ravel()][np.asarray(face_indices)]


def _unique_vertex_means(
    positions: np.ndarray,
    face_indices: np.ndarray,
    member_faces: np.ndarray,
    member_group: np.ndarray,
    num_groups: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean position and count of the unique vertices of each group of faces.

    ``member_faces[k]`` belongs to group ``member_group[k]``; every group must be non-empty.
    Vertices are summed in increasing index order, so the result does not depend on the
    order of the members. Returns ((num_groups, 3) means, (num_groups,) counts).
    """
    num_vertices = positions.shape[0]
    group_vertex_key = np.repeat(member_group.astype(np.int64), 3) * num_vertices + face_indices[member_faces].ravel()
    # Sorted, then deduplicated: np.unique took its hashing path here, 19x slower (1.33 s
    # against 71 ms for 687k keys, numpy 2.4), for the same sorted keys.
    group_vertex_key = np.sort(group_vertex_key)
    first = np.ones(min(len(group_vertex_key), 1), dtype=bool)
    group_vertex_key = group_vertex_key[np.concatenate((first, group_vertex_key[1:] != group_vertex_key[:-1]))]
    group, vertex = np.divmod(group_vertex_key, num_vertices)
    counts = np.bincount(group, minlength=num_groups)
    sums = np.stack(
        [np.bincount(group, weights=positions[vertex, axis], minlength=num_groups) for axis in range(3)], axis=1
    )
    return sums / counts[:, None], counts


def validated_mesh(vertices, faces, name: str, *, face_name=None) -> tuple[np.ndarray, np.ndarray]:
    """Return (float64 (nv, 3) positions, int64 (nf, 3) face indices) or raise ValueError.
    ``face_name``: how a repeated face is named, a function of its index (default "face i";
    ``ModelBuilder.add_body``'s ``mesh_names``)."""
    positions = _mesh_array(vertices, name, "vertices")
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"mesh {name!r}: vertices must have shape (nv, 3), got {positions.shape}")
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    finite_vertex = np.isfinite(positions).all(axis=1)
    if not finite_vertex.all():
        bad = int(np.flatnonzero(~finite_vertex)[0])
        raise ValueError(f"mesh {name!r}: vertex {bad} is not finite: {positions[bad].tolist()}")
    check_coordinates(positions, f"mesh {name!r}: vertices")

    raw_faces = _mesh_array(faces, name, "faces")
    if raw_faces.ndim != 2 or raw_faces.shape[1] != 3:
        raise ValueError(f"mesh {name!r}: faces must have shape (nf, 3), got {raw_faces.shape}")
    if raw_faces.shape[0] == 0:
        raise ValueError(f"mesh {name!r}: has no faces")
    if not np.issubdtype(raw_faces.dtype, np.integer):
        whole = np.isfinite(raw_faces) & (raw_faces == np.round(raw_faces))
        if not whole.all():
            bad = int(np.flatnonzero(~whole.all(axis=1))[0])
            raise ValueError(f"mesh {name!r}: face {bad} has non-integer vertex indices {raw_faces[bad].tolist()}")
    out_of_range = (raw_faces < 0) | (raw_faces >= positions.shape[0])
    if out_of_range.any():
        bad = int(np.flatnonzero(out_of_range.any(axis=1))[0])
        raise ValueError(
            f"mesh {name!r}: face {bad} has vertex indices {raw_faces[bad].tolist()} "
            f"outside [0, {positions.shape[0]}) (the mesh has {positions.shape[0]} vertices)"
        )
    faces = np.ascontiguousarray(raw_faces, dtype=np.int64)
    _refuse_repeated_faces(positions, faces, name, face_name)
    # The faces' vertices only: an unused vertex 1 m away let a mesh 1e-170 m across through
    # (its tree's radii underflowed to 0), and one 1e-80 m from a point body refused it.
    used = positions[np.unique(faces)]
    problem = extent_problem(float(np.ptp(used, axis=0).max()))
    if problem is not None:
        raise ValueError(f"mesh {name!r}: {problem}")
    return positions, faces


def repeated_corner_sets(corners: np.ndarray) -> tuple[int, int, int] | None:
    """For polygons' corners (n, k, 3), the first two polygons with the same corner
    positions (in any order or winding) and how many repeat an earlier one; None if none."""
    if len(corners) < 2:
        return None
    order = np.lexsort((corners[..., 2], corners[..., 1], corners[..., 0]), axis=-1)
    keys = np.take_along_axis(corners, order[..., None], axis=1).reshape(len(corners), -1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    if counts.max() == 1:
        return None
    again = np.flatnonzero((keys == keys[first[np.argmax(counts > 1)]]).all(axis=1))
    return int(again[0]), int(again[1]), int((counts - 1).sum())


def _refuse_repeated_faces(positions: np.ndarray, faces: np.ndarray, name: str, face_name=None) -> None:
    """Refuse a triangle listed twice (the same three corners, by index or by position, in
    any order or winding): each copy is a leaf of the potential, so the mesh pushed twice as
    hard there (a box rested 0.89 mm over a ground of doubled faces instead of 0.63 mm)."""
    repeated = repeated_corner_sets(positions[faces])
    if repeated is not None:
        first, second, total = repeated
        pair = f"faces {first} and {second}" if face_name is None else f"{face_name(first)} and {face_name(second)}"
        raise ValueError(
            f"mesh {name!r}: {pair} are the same triangle ({total} repeated face(s) in all); "
            "each copy would push in the contact potential: remove the repeats (e.g. trimesh's update_faces(unique_faces()))"
        )


def _mesh_array(value, name: str, what: str) -> np.ndarray:
    """``value`` as a numpy array of a real, non-boolean dtype, or ValueError naming the mesh."""
    try:
        array = np.asarray(value)
    except Exception as exc:  # ragged nesting and the like
        raise ValueError(f"mesh {name!r}: {what} cannot be read as a numeric array ({exc})") from None
    if not real_dtype(array):
        raise ValueError(f"mesh {name!r}: {what} must be real numbers, got dtype {array.dtype}")
    return array
