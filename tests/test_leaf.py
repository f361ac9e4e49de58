"""Leaf separating-plane potential: derivatives, the paper's properties, hard cases, bad input."""

import numpy as np
import pytest
import warp as wp
from helpers import edge_edge, leaf_fd_errors, parallel_faces, random_separated_pair, vertex_face

import warpcontact as wc
from warpcontact.kernels import leaf as leaf_kernels


def evaluate(A, B, **kw):
    return wc.triangle_pair_potential(np.asarray(A)[None], np.asarray(B)[None], **kw)


# --- derivatives against finite differences -------------------------------------------


@pytest.mark.parametrize("offset", [0.5, 1.0, 2.5, 10.0])
def test_random_pairs_match_finite_differences(offset):
    rng = np.random.default_rng(int(offset * 10))
    for _ in range(4):
        A, B = random_separated_pair(rng, offset=offset)
        grad_err, hess_err = leaf_fd_errors(A, B, h=1e-6)
        assert grad_err < 1e-6
        assert hess_err < 1e-6


@pytest.mark.parametrize(
    "make, gap",
    [(parallel_faces, 1e-2), (vertex_face, 1e-2), (edge_edge, 1e-2), (parallel_faces, 1e-4), (edge_edge, 1e-4)],
)
def test_near_contact_matches_finite_differences(make, gap):
    A, B = make(gap)
    grad_err, hess_err = leaf_fd_errors(A, B, h=gap * 1e-4)
    assert grad_err < 1e-5
    assert hess_err < 1e-5


@pytest.mark.parametrize("size", [1e-4, 1e3])
def test_tiny_and_huge_triangles_match_finite_differences(size):
    A, B = vertex_face(0.05 * size, size=size)
    grad_err, hess_err = leaf_fd_errors(A, B, h=size * 1e-6)
    assert grad_err < 1e-5
    assert hess_err < 1e-5


def test_triangles_too_small_for_float64_contact_geometry_are_refused():
    """Found by a probe: a vertex 0.1 of their size above a face read as CONTACT (+inf) once
    the triangles were 1e-82 m across (fourth powers of length underflowed); at 1e-79 m they
    were reported unsolved. Now both are refused by size, and a pair collapsed to one point
    stays valid."""
    from warpcontact import triangle_pair_potential

    for scale in (1e-79, 1e-82, 1e-120):
        A, B = vertex_face(0.1)
        with pytest.raises(ValueError, match=r"A and B: pair 1 spans \S+ m, below the 1e-75 m that float64 contact geometry resolves"):
            triangle_pair_potential(np.stack([A, A * scale]), np.stack([B, B * scale]))
    A, B = vertex_face(0.1)
    assert triangle_pair_potential((A * 1e-70)[None], (B * 1e-70)[None]).status[0] != 1  # not read as touching


def test_sliver_matches_finite_differences():
    A = np.array([[0.0, 0.0, 0.1], [1.0, 0.0, 0.1], [0.5, 1e-3, 0.1]])
    B = np.array([[0.2, -0.5, 0.0], [0.4, 0.5, 0.0], [0.3, 0.0, -0.7]])
    grad_err, hess_err = leaf_fd_errors(A, B, h=1e-7)
    assert grad_err < 1e-5
    assert hess_err < 1e-5


_TRIANGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _vertex_face_apart(distance):
    A, B = vertex_face(0.0)
    return A, B - [0.0, 0.0, distance]


@pytest.mark.parametrize(
    "A, B, h",
    [
        pytest.param(_TRIANGLE, _TRIANGLE + [1.5, 1.5, 0.0], 1e-6, id="coplanar"),
        pytest.param(_TRIANGLE, np.array([[0.5 + 7.07e-5, 0.5 + 7.07e-5, 0.0], [1.5, 0.6, 0.0], [0.6, 1.5, 0.0]]), 1e-9, id="coplanar-gap-1e-4"),
        pytest.param(*_vertex_face_apart(1e3), 1e-3, id="distance-1e3"),
        pytest.param(*_vertex_face_apart(1e6), 1.0, id="distance-1e6"),
        pytest.param(np.array([[0.0, 0.0, 0.01], [1.0, 0.0, 0.01], [0.5, 1e-6, 0.01]]), np.array([[0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.5 + 1e-6, 0.0, 0.0]]), 1e-9, id="sliver-1e6"),
    ],
)
def test_hard_configurations_match_finite_differences(A, B, h):
    """Coplanar triangles (apart and 1e-4 apart in their plane), triangles 1e3 and 1e6 of their
    size apart, and slivers of aspect 1e6 crossing each other's line 1 cm apart: the leaf's
    gradient and Hessian against central differences (measured errors at most 4e-7)."""
    grad_err, hess_err = leaf_fd_errors(A, B, h)
    assert grad_err < 5e-6
    assert hess_err < 5e-6


def test_hessian_is_symmetric_and_translation_invariant():
    A, B = vertex_face(0.1)
    res = evaluate(A, B)
    H = res.hessian[0]
    assert np.abs(H - H.T).max() <= 1e-12 * np.abs(H).max()
    # Moving both triangles together changes nothing: grad sums to zero, H kills translations.
    g = res.grad[0].reshape(6, 3)
    assert np.abs(g.sum(axis=0)).max() <= 1e-12 * np.abs(g).max()
    shift = np.tile(np.eye(3), (6, 1))
    assert np.abs(H @ shift).max() <= 1e-9 * np.abs(H).max()


def test_far_from_origin_equals_near_origin():
    A, B = edge_edge(1e-3)
    near = evaluate(A, B)
    offset = np.array([1e5, -2e5, 3e5])
    far = evaluate(A + offset, B + offset)
    assert far.ok[0]
    # Adding the offset rounds the input by ~eps * 3e5 = 7e-11, i.e. ~1e-7 of the 1e-3 gap;
    # the comparison can be no tighter than that.
    np.testing.assert_allclose(far.value, near.value, rtol=1e-6)
    np.testing.assert_allclose(far.grad, near.grad, rtol=1e-5, atol=1e-6 * np.abs(near.grad).max())


# --- centred limit -----------------------------------------------------------------------


@pytest.mark.parametrize("distance", [1e-6, 1e-3, 0.1, 1.0, 10.0, 1e3, 1e6])
def test_collapsed_triangles_reproduce_centred_potential(distance):
    rng = np.random.default_rng(7)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    ca = rng.normal(size=3)
    A = np.repeat(ca[None], 3, axis=0)
    B = np.repeat((ca - distance * direction)[None], 3, axis=0)
    res = evaluate(A, B)
    distance = np.linalg.norm(A[0] - B[0])  # as represented after rounding
    direction = (A[0] - B[0]) / distance
    value, first, _ = wc.centered_potential(np.array([distance]), derivatives=True)
    assert res.ok[0]
    np.testing.assert_allclose(res.value[0], value[0], rtol=1e-12)
    # Each of the three collapsed vertices carries a third of dP_c/dr along the centre line.
    g = res.grad[0]
    np.testing.assert_allclose(g[0].sum(axis=0), first[0] * direction, rtol=1e-9)
    np.testing.assert_allclose(g[1].sum(axis=0), -first[0] * direction, rtol=1e-9)


def test_centred_potential_and_blend_derivatives():
    r = np.geomspace(1e-6, 1e6, 41)
    v, d1, d2 = wc.centered_potential(r, derivatives=True)
    np.testing.assert_allclose(v, 12 * (1 + r**-0.5) ** 2, rtol=1e-14)
    h = r * 1e-6
    vp, d1p, _ = wc.centered_potential(r + h, derivatives=True)
    vm, d1m, _ = wc.centered_potential(r - h, derivatives=True)
    np.testing.assert_allclose(d1, (vp - vm) / (2 * h), rtol=1e-7)
    np.testing.assert_allclose(d2, (d1p - d1m) / (2 * h), rtol=1e-7)
    assert np.isinf(wc.centered_potential(np.array([0.0]))[0])
    assert np.all(d1 < 0) and np.all(d2 > 0)

    s = np.linspace(-0.5, 1.5, 201)
    p, p1, p2 = wc.quintic_blend(s, derivatives=True)
    assert p.min() == 0.0 and p.max() == 1.0 and np.all(np.diff(p) >= 0)
    inner = (s > 0.01) & (s < 0.99)
    hs = 1e-6
    pp, p1p, _ = wc.quintic_blend(s + hs, derivatives=True)
    pm, p1m, _ = wc.quintic_blend(s - hs, derivatives=True)
    np.testing.assert_allclose(p1[inner], ((pp - pm) / (2 * hs))[inner], atol=1e-8)
    np.testing.assert_allclose(p2[inner], ((p1p - p1m) / (2 * hs))[inner], atol=1e-7)
    # C2 at both ends: value, slope and curvature meet the constant pieces.
    ends = wc.quintic_blend(np.array([1e-9, 1 - 1e-9]), derivatives=True)
    assert np.abs(ends[1]).max() < 1e-15 and np.abs(ends[2]).max() < 1e-6


def test_centred_potential_rejects_negative_and_nan():
    with pytest.raises(ValueError, match="r"):
        wc.centered_potential(np.array([-1.0]))
    with pytest.raises(ValueError, match="NaN"):
        wc.centered_potential(np.array([np.nan]))


def test_centred_potential_refuses_distances_whose_derivatives_overflow():
    # A finite value beside an infinite second derivative came back for r = 1e-150.
    tiny = np.array([1e-3, 1e-150])
    with pytest.raises(ValueError, match=r"r: 1e-150 m \(flat index 1\) is too small"):
        wc.centered_potential(tiny, derivatives=True)
    assert np.all(np.isfinite(wc.centered_potential(tiny)))  # the value alone is finite
    v, d1, d2 = wc.centered_potential(np.array([1e-100, 0.0]), derivatives=True)
    assert np.all(np.isfinite([v[0], d1[0], d2[0]])) and np.isinf(v[1]) and d1[1] == d2[1] == 0.0


# --- Property A: barrier ---------------------------------------------------------------------


@pytest.mark.parametrize("make", [parallel_faces, vertex_face, edge_edge])
def test_value_grows_without_bound_as_gap_closes(make):
    gaps = np.geomspace(1e-1, 1e-9, 9)
    values = []
    for gap in gaps:
        res = evaluate(*make(gap))
        assert res.ok[0], f"gap {gap}: status {res.status[0]}"
        assert np.isfinite(res.grad).all() and np.isfinite(res.hessian).all()
        values.append(res.value[0])
    values = np.array(values)
    assert np.all(np.diff(values) > 0)
    # Barrier rate: at least ~1/gap (the closest vertex alone contributes 1/(|n| gap)).
    assert np.all(values * gaps > 0.9)


def test_contact_configurations_are_infinite():
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    cases = {
        "shared vertex": (tri, np.array([[0.0, 0.0, 0.0], [-1.0, 0.0, 0.3], [0.0, -1.0, 0.5]])),
        "vertex on face": (tri, np.array([[0.2, 0.2, 0.0], [0.5, 0.5, 1.0], [0.1, 0.6, 1.0]])),
        "edge on edge": (tri, np.array([[0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, -1.0]])),
        "edge through face": (tri, np.array([[0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [2.0, 2.0, 0.7]])),
        "coplanar overlap": (tri, tri * 0.8 + np.array([0.1, 0.1, 0.0])),
        "identical": (tri, tri.copy()),
    }
    for name, (A, B) in cases.items():
        res = evaluate(A, B)
        assert np.isposinf(res.value[0]), name
        assert res.status[0] == wc.LeafStatus.CONTACT, name
        assert not res.ok[0], name
        assert np.isfinite(res.grad).all() and np.isfinite(res.hessian).all(), name


def test_coplanar_disjoint_triangles_are_finite():
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    res = evaluate(tri, tri + np.array([1.5, 1.5, 0.0]))
    assert res.ok[0] and np.isfinite(res.value[0])
    assert abs(res.plane[0, 2]) < 1e-12  # the separating plane is vertical


def test_coplanar_triangles_a_hair_apart_are_not_contact():
    """Found by a probe: coplanar triangles with a vertex 1.4e-8 of their size from the other's
    edge, turned off the world axes, came back as CONTACT (+inf) in 15 of 100 random turns
    (half of them at 1.4e-9): where rounding tilts the closest points' plane, no face normal
    or edge cross product separates a coplanar pair; an in-plane edge normal does. Until the
    plane search ran in a frame along the start normal, 30 of 100 were NOT CONVERGED at 1e-8
    and 98 at 1e-9; now every one is solved."""
    A = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    rng = np.random.default_rng(1)
    for gap in (1e-8, 1e-9):
        B = np.array([[0.5 + gap, 0.5 + gap, 0.0], [1.5, 0.5, 0.0], [0.5, 1.5, 0.0]])
        turns = [_random_rotation(rng) for _ in range(100)]
        res = wc.triangle_pair_potential(np.stack([A @ R.T for R in turns]), np.stack([B @ R.T for R in turns]))
        assert (res.status == wc.LeafStatus.OK).all(), (gap, res.status)
        assert np.isfinite(res.value).all(), gap


def _random_rotation(rng):
    from warpcontact.rotation import quat_to_matrix

    q = rng.normal(size=4)
    return quat_to_matrix(q / np.linalg.norm(q))


def _coplanar_parallel_edges(gap):
    """A's bottom edge ``gap`` above B's top edge, both along x, overlapping over 0.8 m."""
    A = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.4, 0.8, 0.5]]) + np.array([0.0, 0.0, gap])
    B = np.array([[0.2, 0.0, 0.0], [1.3, 0.0, 0.0], [0.6, -0.7, -0.6]])
    return A, B


@pytest.mark.parametrize(
    "make, gaps",
    [(_coplanar_parallel_edges, (1e-5, 1e-7)), (parallel_faces, (1e-5, 1e-7, 1e-9)), (vertex_face, (1e-5, 1e-7, 1e-9)), (edge_edge, (1e-5, 1e-7, 1e-9))],
)
def test_turned_near_contact_hessian_is_the_turned_axis_aligned_one(make, gaps):
    """Found by a probe: the plane search ran in world axes, where a turned near-contact
    pair mixes the plane Hessian's stiff directions (tilts and offset, held by the near
    gaps) with its soft ones, and the 4x4 solve lost their digits: at 1e-7 m, coplanar
    parallel edges' Hessians were off by a median 5e-3 (2.4e-2 at most), edge-edge pairs'
    by 1.4e-5; at 1e-9 m, 16 of 60 vertex-face pairs were unsolved. Against the
    axis-aligned pair's Hessian turned with them they now differ by what rounding the turned
    vertices moves it (measured at most 6e-9 at 1e-7 m, 6e-7 at 1e-9 m). This checks that
    the Hessian turns with the pair; the finite-difference tests above check its value."""
    rng = np.random.default_rng(0)
    for gap in gaps:
        A, B = make(gap)
        aligned = evaluate(A, B).hessian[0]
        turns = [_random_rotation(rng) for _ in range(30)]
        res = wc.triangle_pair_potential(np.stack([A @ R.T for R in turns]), np.stack([B @ R.T for R in turns]))
        assert res.ok.all(), (gap, res.status)
        for R, hessian in zip(turns, res.hessian):
            turn = np.kron(np.eye(6), R)
            expected = turn @ aligned @ turn.T
            assert np.abs(hessian - expected).max() < (5e-8 if gap >= 1e-7 else 5e-6) * np.abs(expected).max(), gap


# --- Property B: smoothness where closest features switch ---------------------------------


def test_hessian_continuous_where_closest_feature_switches():
    """A point sliding past B's edge: the closest feature switches vertex-face -> vertex-edge.

    The squared point-triangle distance (IPC's building block) has a Hessian that jumps
    there; the leaf potential's Hessian must not.
    """
    B = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])
    base = np.array([[0.0, 0.0, 0.2], [0.3, 0.1, 1.2], [-0.2, 0.4, 1.1]])

    def hessians(ts):
        A = np.repeat(base[None], len(ts), axis=0)
        A[:, 0, 1] += ts  # slide the lowest vertex across the edge y = -1
        res = wc.triangle_pair_potential(A, np.repeat(B[None], len(ts), axis=0))
        assert res.ok.all()
        return res.hessian

    switch = -1.0  # the vertex crosses y = -1 at t = -1
    for step in (1e-3, 1e-4):
        H = hessians(np.array([switch - step, switch + step]))
        jump = np.abs(H[1] - H[0]).max() / np.abs(H[0]).max()
        assert jump < 50 * step, f"Hessian jumps by {jump} across the switch at step {step}"

    def point_triangle_distance_sq(p):
        # Distance to the triangle B (in the plane z = 0) from p, by projection and edge clamping.
        q = p[:2]
        inside = q[1] >= -1 and (q[1] + 1) <= 2 * (1 - abs(q[0])) + 1e-300
        if inside:
            return p[2] ** 2
        a, b = B[0, :2], B[1, :2]
        t = np.clip(np.dot(q - a, b - a) / np.dot(b - a, b - a), 0, 1)
        return np.sum((q - (a + t * (b - a))) ** 2) + p[2] ** 2

    def distance_hessian_yy(y, h=1e-5):
        p = np.array([0.0, y, 0.2])
        f = lambda dy: point_triangle_distance_sq(p + np.array([0.0, dy, 0.0]))  # noqa: E731
        return (f(h) - 2 * f(0.0) + f(-h)) / h**2

    ipc_jump = abs(distance_hessian_yy(switch - 1e-3) - distance_hessian_yy(switch + 1e-3))
    assert ipc_jump > 1.0  # 2 outside the face, 0 inside: a jump the leaf potential lacks


# --- Property C: non-prehensile and non-vanishing ---------------------------------------------


def _assert_forces_in_cone(A, B, res):
    n = res.plane[0, :3]
    forces = -res.grad[0]
    gaps_a = A @ n + res.plane[0, 3]
    gaps_b = -(B @ n + res.plane[0, 3])
    assert np.all(gaps_a > 0) and np.all(gaps_b > 0)
    # The paper's witness points: weighted averages of each triangle's vertices.
    wa, wb = 1 / gaps_a**2, 1 / gaps_b**2
    a = (wa[:, None] * A).sum(0) / wa.sum()
    b = (wb[:, None] * B).sum(0) / wb.sum()
    ab = a - b
    assert np.linalg.norm(np.cross(n, ab)) <= 1e-8 * np.linalg.norm(n) * np.linalg.norm(ab)
    assert np.dot(n, ab) > 0
    for f in forces[0]:
        assert np.linalg.norm(f) > 0
        assert np.linalg.norm(np.cross(f, ab)) <= 1e-8 * np.linalg.norm(f) * np.linalg.norm(ab)
        assert np.dot(f, ab) > 0
    for f in forces[1]:
        assert np.linalg.norm(f) > 0
        assert np.dot(f, -ab) > 0


def test_forces_lie_in_separation_cone():
    rng = np.random.default_rng(3)
    configs = [random_separated_pair(rng, offset=o) for o in (0.5, 1.0, 3.0, 10.0)]
    configs += [parallel_faces(1e-6), vertex_face(1e-3), edge_edge(1e-5)]
    for A, B in configs:
        res = evaluate(A, B)
        assert res.ok[0]
        _assert_forces_in_cone(A, B, res)


@pytest.mark.parametrize("distance", [1e3, 1e6, 1e9])
def test_force_does_not_vanish_at_huge_distance(distance):
    A, B = vertex_face(distance)
    res = evaluate(A, B)
    assert res.ok[0]
    assert res.value[0] > 12.0
    # Net force on A pushes it away from B (+z) and is non-zero, ~ 6 r^-3/2 for the centres.
    net = -res.grad[0, 0].sum(axis=0)
    assert net[2] > 0
    assert net[2] > 0.5 * 6 * distance**-1.5
    _assert_forces_in_cone(A, B, res)


@pytest.mark.parametrize("distance", [1e26, 1e28, 1e40])
def test_pairs_beyond_the_plane_searchs_reach_are_reported_not_converged(distance):
    """Past ~1e29 m the barrier's 1/g vanishes against the plane term's 12 in float64: pairs
    converged to planes tilted up to 80 degrees from the separation (status OK), or read as
    contact at 1e40 m (+inf, disjoint triangles). Beyond 1e27 m they are not converged."""
    A, _ = vertex_face(0.0)
    u = np.array([0.0, 1.0, 1.0]) / np.sqrt(2.0)
    res = evaluate(A, np.zeros((3, 3)) + u * distance)
    if distance < 1e27:
        net = -res.grad[0, 1].sum(axis=0)
        assert res.ok[0] and net @ u == pytest.approx(np.linalg.norm(net), rel=1e-12)
    else:
        assert res.status[0] == wc.LeafStatus.NOT_CONVERGED and not np.isfinite(res.value[0])


@pytest.mark.parametrize("distance", [1e15, 1e16, 1e20, 1e24])
@pytest.mark.parametrize("far", ["triangle", "segment"])
def test_a_far_vertex_in_the_plane_of_a_triangle_is_not_read_as_touching_it(distance, far):
    """A vertex in the plane of the other triangle ~1e16 of its size away (beyond it) made
    the closest-point search's inside-the-face test read rounding noise as inside (every
    b_k - q rounded to one vector): distance 0, status CONTACT, value +inf, for disjoint
    triangles (a probe, stop 62; ``ContactModel(mode="brute")`` reported two 1 m cubes 1e16
    m apart as touching). Two point-like triangles that far apart have 12 (1 + r^-1/2)^2."""
    A = np.array([[0.5, -0.5, -0.5], [-0.5, -0.5, 0.5], [-0.5, -0.5, -0.5]])  # in the plane y = -0.5
    c = distance * np.array([0.6, 0.0, 0.8])
    third = c + [4.0, 0.5, 4.0] if far == "triangle" else c + [0.0, -0.5, 0.0]
    B = np.array([c + [0.0, -0.5, 0.0], c + [0.0, 0.5, 0.0], third])  # its first vertex in A's plane
    res = evaluate(A, B)
    assert res.status[0] == wc.LeafStatus.OK
    assert res.value[0] == pytest.approx(12.0 * (1.0 + distance**-0.5) ** 2, rel=1e-12)


# --- hard cases ------------------------------------------------------------------------------


def test_parallel_faces_at_tiny_gap():
    A, B = parallel_faces(1e-8)
    res = evaluate(A, B)
    assert res.ok[0]
    assert np.isfinite(res.grad).all() and np.isfinite(res.hessian).all()
    n = res.plane[0, :3]
    assert abs(n[0]) + abs(n[1]) < 1e-6 * abs(n[2])  # plane parallel to the faces
    assert res.iterations[0] < 50


@pytest.mark.parametrize("ground", [1.0, 12.0, 1e4])
def test_small_face_over_a_large_one_at_tiny_gaps(ground):
    """A face of 2 cm over a ground triangle of metres to kilometres: at gaps far below the
    triangles' size the closest points' direction, rounded, tilts the start plane across the
    large triangle's far vertices; the start falls back to the pair's separating axis."""
    small = np.array([[-0.01, 0.01, 0.0], [0.01, -0.01, 0.0], [-0.01, -0.01, 0.0]]) + [0.013, -0.007, 0.0]
    large = np.array([[-ground / 2, 0.35 * ground, 0.0], [ground / 2, -0.35 * ground, 0.0], [ground / 2, 0.35 * ground, 0.0]])
    scaled = []
    for gap in (1e-9, 3e-9, 1e-8, 3e-8, 1e-7):
        res = evaluate(small + [0.0, 0.0, gap], large)
        assert res.ok[0], (ground, gap, res.status[0])
        scaled.append(res.value[0] * gap)
    assert np.ptp(scaled) < 0.01 * np.min(scaled)  # P ~ 1/gap: the near vertices dominate
    if ground <= 12.0:  # beyond, a 1e-12 m step is a few ulps of the far vertices
        grad_err, hess_err = leaf_fd_errors(small + [0.0, 0.0, 1e-8], large, 1e-12)
        assert grad_err < 1e-6 and hess_err < 1e-6


@pytest.mark.parametrize("aspect", [1e3, 1e6])
def test_sliver_triangles(aspect):
    A = np.array([[0.0, 0.0, 0.01], [1.0, 0.0, 0.01], [0.5, 1.0 / aspect, 0.01]])
    B = np.array([[0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.5 + 1.0 / aspect, 0.0, 0.0]])
    res = evaluate(A, B)
    assert res.ok[0]
    assert np.isfinite(res.hessian).all()
    _assert_forces_in_cone(A, B, res)


def test_zero_area_triangles_act_as_segments_and_points():
    segment = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    point = np.array([[0.5, 0.0, 1.0]] * 3)
    res = evaluate(point, segment)
    assert res.ok[0] and np.isfinite(res.value[0])
    grad_err, hess_err = leaf_fd_errors(point, segment, h=1e-6)
    assert grad_err < 1e-6 and hess_err < 1e-6
    # A segment touching a point, or two crossing segments, is contact.
    assert np.isposinf(evaluate(np.array([[0.5, 0.0, 0.0]] * 3), segment).value[0])
    crossing = np.array([[0.5, -1.0, 0.0], [0.5, 1.0, 0.0], [0.5, 0.0, 0.0]])
    assert evaluate(crossing, segment).status[0] == wc.LeafStatus.CONTACT


def test_a_pair_whose_start_plane_rounding_loses_is_unsolved_without_nan():
    """A vertex 5.5e-17 m from a face (exact arithmetic), turned off the axes: the start
    plane's scale came out 1/0 - 1/0 and NaN was written as the value and the plane."""
    A = np.array([[0.3298709889692813, -0.06178526355210071, 0.09789984604497347], [0.9398965576189913, 0.32256537902070465, 0.7383242281131999], [0.3364213011026686, 0.02745987138678219, 1.3028863187079225]])
    B = np.array([[1.2901103071871201e-03, -1.5821473644789930e00, 1.2100153955026624e-01], [1.7139234029676438e00, 2.0916077916922016e-01, -4.7741498710202801e-01], [-2.7951514105705461e-01, 7.9843616052956157e-01, 4.2754760666597724e-01]])
    res = evaluate(A, B)
    assert res.status[0] == wc.LeafStatus.NOT_CONVERGED and not res.ok[0]
    assert np.isposinf(res.value[0])
    for values in (res.plane, res.grad, res.hessian):
        assert np.isfinite(values).all()


def test_iteration_cap_flags_pair_without_nan():
    A, B = vertex_face(1e-8)  # the closest-point start is far from this optimum
    res = evaluate(A, B, max_iterations=1)
    assert res.status[0] == wc.LeafStatus.NOT_CONVERGED
    assert not res.ok[0]
    assert np.isfinite(res.value[0])
    assert np.isfinite(res.grad).all() and np.isfinite(res.hessian).all()


def test_batch_of_mixed_pairs_and_float32_input():
    rng = np.random.default_rng(11)
    pairs = [random_separated_pair(rng) for _ in range(5)] + [parallel_faces(0.0)]
    A = np.array([p[0] for p in pairs])
    B = np.array([p[1] for p in pairs])
    res = wc.triangle_pair_potential(A, B)
    assert res.value.shape == (6,) and res.grad.shape == (6, 2, 3, 3) and res.hessian.shape == (6, 18, 18)
    assert res.plane.shape == (6, 4) and res.ok.dtype == bool
    assert res.ok[:5].all() and not res.ok[5]
    single = evaluate(A[2], B[2])
    np.testing.assert_array_equal(res.value[2], single.value[0])
    res32 = wc.triangle_pair_potential(A[:5].astype(np.float32), B[:5].astype(np.float32))
    np.testing.assert_allclose(res32.value, res.value[:5], rtol=1e-5)
    empty = wc.triangle_pair_potential(np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
    assert empty.value.shape == (0,)


# --- float32 plane searches ------------------------------------------------------------------


def _hard_pairs():
    rng = np.random.default_rng(5)
    pairs = [random_separated_pair(rng, offset=o) for o in (0.5, 2.5, 10.0)]
    pairs += [make(gap) for make in (parallel_faces, vertex_face, edge_edge) for gap in (1e-2, 1e-5, 1e-8)]
    pairs += [vertex_face(0.05 * size, size=size) for size in (1e-4, 1e3)]
    pairs += [(A + 1e6, B + 1e6) for A, B in [vertex_face(1e-3)]]  # far from the origin
    pairs += [(A, B + np.array([0.0, 0.0, -d])) for A, B in [vertex_face(0.0)] for d in (1e3, 1e6)]  # huge distances
    A = np.array([[0.0, 0.0, 0.01], [1.0, 0.0, 0.01], [0.5, 1e-6, 0.01]])
    B = np.array([[0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [0.5 + 1e-6, 0.0, 0.0]])
    pairs.append((A, B))  # slivers
    return np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])


def test_float32_search_matches_float64_on_hard_cases():
    """The float32 search is finished in float64, so values and derivatives meet float64's
    tolerances, also where float32 cannot resolve the gaps (1e-8 on unit triangles)."""
    A, B = _hard_pairs()
    ref = wc.triangle_pair_potential(A, B)
    res = wc.triangle_pair_potential(A, B, precision="float32")
    assert ref.ok.all() and res.ok.all()
    np.testing.assert_allclose(res.value, ref.value, rtol=1e-12)
    n = len(A)
    for got, want in ((res.grad.reshape(n, -1), ref.grad.reshape(n, -1)), (res.hessian.reshape(n, -1), ref.hessian.reshape(n, -1))):
        err = np.linalg.norm(got - want, axis=1) / np.linalg.norm(want, axis=1)
        assert err.max() < 1e-8
    assert (res.iterations >= 1).all()


def test_float32_search_keeps_contact_and_iteration_cap_status():
    A, B = parallel_faces(0.0)
    assert evaluate(A, B, precision="float32").status[0] == wc.LeafStatus.CONTACT
    A, B = vertex_face(1e-8)
    res = evaluate(A, B, precision="float32", max_iterations=1)
    assert res.status[0] == wc.LeafStatus.NOT_CONVERGED
    assert np.isfinite(res.value[0]) and np.isfinite(res.hessian).all()


def test_float32_search_refuses_sdrs_and_unknown_precisions():
    A, B = vertex_face(0.1)
    with pytest.raises(ValueError, match="contact mode 'sdrs' solves in float64"):
        evaluate(A, B, dhat=1e-2, precision="float32")
    with pytest.raises(ValueError, match=r"leaf precision: must be one of float64, float32, got 'float16'"):
        evaluate(A, B, precision="float16")


# --- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "A, B, match",
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "shape"),
        (np.zeros((2, 3, 3)), np.zeros((3, 3, 3)), "pair counts differ"),
        (np.full((1, 3, 3), np.nan), np.zeros((1, 3, 3)), "non-finite"),
        (np.zeros((1, 3, 3)), np.full((1, 3, 3), np.inf), "non-finite"),
        ([["a", "b", "c"]] * 3, np.zeros((1, 3, 3)), "numeric"),
        ([[[0, 0, 0], [1, 0]]], np.zeros((1, 3, 3)), "A"),
    ],
)
def test_bad_input_raises_clear_error(A, B, match):
    with pytest.raises(ValueError, match=match):
        wc.triangle_pair_potential(A, B)


def test_bad_options_raise_clear_error():
    with pytest.raises(ValueError, match="max_iterations"):
        wc.triangle_pair_potential(np.zeros((1, 3, 3)), np.ones((1, 3, 3)), max_iterations=0)
    # Caps past int32 wrapped around (2**31: every pair NOT_CONVERGED at 0 iterations); 2.5
    # was truncated to 2 and True read as 1.
    for cap in (2**31, 2.5, True):
        with pytest.raises(ValueError, match=f"max_iterations: must be a whole number from 1 to 2147483647, got {cap!r}"):
            wc.triangle_pair_potential(np.zeros((1, 3, 3)), np.ones((1, 3, 3)), max_iterations=cap)
    # Coordinates whose squared distances overflow: the value was NaN at a scale of 1e155.
    with pytest.raises(ValueError, match=r"B: -1e\+155 at index \(0, 2, 2\)"):
        wc.triangle_pair_potential(np.ones((1, 3, 3)), np.array([[[0, 0, 0], [1, 0, 0], [0, 1, -1e155]]]))
    with pytest.raises(ValueError, match="device"):
        wc.triangle_pair_potential(np.zeros((1, 3, 3)), np.ones((1, 3, 3)), device="tpu:7")


# --- warm starts ------------------------------------------------------------------------------


@wp.kernel
def _solve_from_plane_kernel(
    a: wp.array(dtype=wp.mat33d),
    b: wp.array(dtype=wp.mat33d),
    plane: wp.array(dtype=wp.vec4d),
    value_out: wp.array(dtype=wp.float64),
    iterations_out: wp.array(dtype=wp.int32),
    status_out: wp.array(dtype=wp.int32),
    lpp_inv_out: wp.array(dtype=wp.mat44d),
):
    tid = wp.tid()
    sol = leaf_kernels.pair_solve_from_plane(a[tid], b[tid], plane[tid], wp.float64(0.0), 100)
    value_out[tid] = sol.value
    iterations_out[tid] = sol.iterations
    status_out[tid] = sol.status
    lpp_inv_out[tid] = sol.lpp_inv


def _solve_from_planes(A, B, planes):
    n = len(A)
    outs = [wp.zeros(n, dtype=wp.float64), wp.zeros(n, dtype=wp.int32), wp.zeros(n, dtype=wp.int32), wp.zeros(n, dtype=wp.mat44d)]
    wp.launch(
        _solve_from_plane_kernel,
        dim=n,
        inputs=[wp.array(A, dtype=wp.mat33d), wp.array(B, dtype=wp.mat33d), wp.array(planes, dtype=wp.vec4d)],
        outputs=outs,
    )
    return [o.numpy() for o in outs]


def test_solve_from_the_optimal_plane_needs_no_newton_step():
    """The friction adjoint re-solves each leaf from the plane the forward pass found: the
    solution must be the cold solve's, at once, and a plane that does not separate the
    triangles must fall back to the cold start."""
    rng = np.random.default_rng(7)
    pairs = [random_separated_pair(rng, offset=o) for o in (0.5, 1.0, 2.5, 10.0)] + [parallel_faces(1e-6), vertex_face(1e-4)]
    A = np.array([p[0] for p in pairs])
    B = np.array([p[1] for p in pairs])
    cold = wc.triangle_pair_potential(A, B)
    assert cold.ok.all()
    value, iterations, status, _ = _solve_from_planes(A, B, cold.plane)
    assert (status == 0).all() and (iterations <= 1).all()
    np.testing.assert_allclose(value, cold.value, rtol=1e-13)
    # A plane through A (separating nothing) and one with |n| >= 1: the cold start's results.
    bad = np.zeros_like(cold.plane)
    bad[:, 2] = 0.5
    bad[:, 3] = -0.5 * A[:, :, 2].mean(axis=1)
    for planes in (bad, cold.plane * 1e3):
        value, iterations, status, _ = _solve_from_planes(A, B, planes)
        assert (status == 0).all()
        np.testing.assert_allclose(value, cold.value, rtol=1e-12)
        np.testing.assert_array_equal(iterations, cold.iterations)
