"""Small dense linear algebra for device code, generic over the float type.

The 4x4 plane Hessian of the leaf problem spans many orders of magnitude near contact
(barrier curvature ~ 1/gap^3 next to O(1) entries), so every solve here first applies a
symmetric Jacobi scaling before the Cholesky factorisation; `wp.inverse` (cofactors) is
not used for that reason. The functions take and return matrices and vectors of one float
type (``mat44d``/``vec4d`` or ``mat44f``/``vec4f``): the leaf's plane search runs in
either precision (``kernels/leaf.py``).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["spd4_inverse", "spd4_solve"]


@wp.func
def _spd4_scaled_cholesky(h: Any):
    """Cholesky factor of S H S with S = diag(h_ii^-1/2); returns (L, s, ok)."""
    zero = h.dtype(0.0)
    s = wp.vector(length=4, dtype=h.dtype)
    l = wp.matrix(shape=(4, 4), dtype=h.dtype)
    for i in range(4):
        if h[i, i] <= zero:
            return l, s, False
        s[i] = h.dtype(1.0) / wp.sqrt(h[i, i])
    for j in range(4):
        acc = h[j, j] * s[j] * s[j]
        for k in range(j):
            acc -= l[j, k] * l[j, k]
        if acc <= zero:
            return l, s, False
        ljj = wp.sqrt(acc)
        l[j, j] = ljj
        for i in range(j + 1, 4):
            acc = h[i, j] * s[i] * s[j]
            for k in range(j):
                acc -= l[i, k] * l[j, k]
            l[i, j] = acc / ljj
    return l, s, True


@wp.func
def _cholesky4_solve(l: Any, b: Any):
    y = wp.vector(length=4, dtype=l.dtype)
    for i in range(4):
        acc = b[i]
        for k in range(i):
            acc -= l[i, k] * y[k]
        y[i] = acc / l[i, i]
    x = wp.vector(length=4, dtype=l.dtype)
    for ii in range(4):
        i = 3 - ii
        acc = y[i]
        for k in range(i + 1, 4):
            acc -= l[k, i] * x[k]
        x[i] = acc / l[i, i]
    return x


@wp.func
def spd4_solve(h: Any, b: Any):
    """Solve H x = b for symmetric positive definite H; returns (x, ok)."""
    l, s, ok = _spd4_scaled_cholesky(h)
    if not ok:
        return wp.vector(length=4, dtype=h.dtype), False
    bs = wp.vector(b[0] * s[0], b[1] * s[1], b[2] * s[2], b[3] * s[3])
    xs = _cholesky4_solve(l, bs)
    return wp.vector(xs[0] * s[0], xs[1] * s[1], xs[2] * s[2], xs[3] * s[3]), True


@wp.func
def spd4_inverse(h: Any):
    """Inverse of a symmetric positive definite 4x4 matrix; returns (H^-1, ok)."""
    l, s, ok = _spd4_scaled_cholesky(h)
    inv = wp.matrix(shape=(4, 4), dtype=h.dtype)
    if not ok:
        return inv, False
    for j in range(4):
        e = wp.vector(length=4, dtype=h.dtype)
        e[j] = s[j]
        col = _cholesky4_solve(l, e)
        for i in range(4):
            inv[i, j] = col[i] * s[i]
    return inv, True
