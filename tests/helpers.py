"""Shared test utilities: finite differences, triangle configurations and interruptions."""

import numpy as np

import warpcontact as wc


def leaf_fd_errors(A, B, h, **options):
    """Relative errors of the analytic gradient and Hessian of one pair against central differences.

    The gradient is compared with differences of the value, the Hessian with differences of
    the analytic gradient; errors are max-abs, relative to the max-abs analytic entry.
    ``options`` go to ``triangle_pair_potential`` (e.g. ``dhat`` for the SDRS barrier).
    """
    x = np.concatenate([A, B]).reshape(18)
    X = np.repeat(x[None], 37, axis=0)
    for i in range(18):
        X[1 + 2 * i, i] += h
        X[2 + 2 * i, i] -= h
    res = wc.triangle_pair_potential(X[:, :9].reshape(-1, 3, 3), X[:, 9:].reshape(-1, 3, 3), **options)
    assert res.ok.all(), f"finite-difference stencil left the feasible set: status {res.status}"
    grad = res.grad[0].reshape(18)
    hess = res.hessian[0]
    fd_grad = (res.value[1::2] - res.value[2::2]) / (2 * h)
    G = res.grad.reshape(37, 18)
    fd_hess = (G[1::2] - G[2::2]) / (2 * h)
    grad_err = np.abs(fd_grad - grad).max() / np.abs(grad).max()
    hess_err = np.abs(fd_hess - hess).max() / np.abs(hess).max()
    return grad_err, hess_err


def random_separated_pair(rng, *, offset=2.5, size=1.0):
    """Random triangles of scale ``size`` with B offset along x by ``offset * size``; retried until disjoint."""
    while True:
        A = rng.normal(size=(3, 3)) * size
        B = rng.normal(size=(3, 3)) * size + np.array([offset * size, 0.0, 0.0])
        if wc.triangle_pair_potential(A[None], B[None], derivatives=False).ok[0]:
            return A, B


def parallel_faces(gap, size=1.0):
    """Two congruent, coplanar-offset (stacked) triangles separated by ``gap`` along z."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.9, 0.0]]) * size
    return tri + np.array([0.0, 0.0, gap]), tri.copy()


def vertex_face(gap, size=1.0):
    """A's lowest vertex hovering ``gap`` above the interior of B."""
    B = np.array([[-1.0, -1.0, 0.0], [1.5, -0.5, 0.0], [0.0, 1.2, 0.0]]) * size
    A = np.array([[0.1, 0.1, 0.0], [0.6, 0.3, 0.8], [-0.2, 0.5, 1.1]]) * size + np.array([0.0, 0.0, gap])
    return A, B


def edge_edge(gap, size=1.0):
    """Crossed edges: A's bottom edge along x, B's top edge along y, ``gap`` apart in z."""
    A = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.3, 1.0]]) * size + np.array([0.0, 0.0, gap])
    B = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.2, 0.0, -1.0]]) * size
    return A, B


def interrupt_call(monkeypatch, owner, name: str, n: int):
    """Make the ``n``-th call of method ``owner.name`` raise KeyboardInterrupt, as Ctrl-C there would."""
    real, calls = getattr(owner, name), []

    def interrupting(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(owner, name, interrupting)
