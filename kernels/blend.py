"""Closed-form centred potential and the quintic blend (paper eqs. centered-potential, blending).

    P_c(r) = 12 (1 + r^-1/2)^2            (r = distance between cluster centres)
    Phi(s) = 6 s^5 - 15 s^4 + 10 s^3      (clamped to [0, 1]; C2 at both ends)
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["centered_potential", "quintic_blend", "shell_blend", "centered_potential_kernel", "quintic_blend_kernel"]


@wp.func
def centered_potential(r: wp.float64):
    """(P_c, dP_c/dr, d2P_c/dr2); +inf value and zero derivatives for r <= 0."""
    zero = wp.float64(0.0)
    if r <= zero:
        return wp.float64(wp.inf), zero, zero
    isr = wp.float64(1.0) / wp.sqrt(r)
    w = wp.float64(1.0) + isr
    value = wp.float64(12.0) * w * w
    first = wp.float64(-12.0) * isr * isr * isr * w
    second = wp.float64(18.0) * isr * isr * isr * isr * isr * w + wp.float64(6.0) / (r * r * r)
    return value, first, second


@wp.func
def quintic_blend(s: wp.float64):
    """(Phi, Phi', Phi'') with Phi clamped outside [0, 1]."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if s <= zero:
        return zero, zero, zero
    if s >= one:
        return one, zero, zero
    s2 = s * s
    value = s2 * s * (wp.float64(10.0) + s * (wp.float64(-15.0) + wp.float64(6.0) * s))
    first = wp.float64(30.0) * s2 * (one - s) * (one - s)
    second = wp.float64(60.0) * s * (one - s) * (one - wp.float64(2.0) * s)
    return value, first, second


@wp.func
def shell_blend(dist: wp.float64, d1: wp.float64, eps: wp.float64):
    """Phi of a node pair whose bounding spheres (radii summing to d1) have centres ``dist``
    apart, blended across the shell d1 <= dist <= (1 + eps) d1, and its first two
    derivatives in dist."""
    width = eps * d1
    phi, dphi, ddphi = quintic_blend((dist - d1) / width)
    return phi, dphi / width, ddphi / (width * width)


@wp.kernel
def centered_potential_kernel(
    # Data in:
    r_in: wp.array(dtype=wp.float64),
    # Data out:
    value_out: wp.array(dtype=wp.float64),
    first_out: wp.array(dtype=wp.float64),
    second_out: wp.array(dtype=wp.float64),
):
    tid = wp.tid()
    v, d1, d2 = centered_potential(r_in[tid])
    value_out[tid] = v
    first_out[tid] = d1
    second_out[tid] = d2


@wp.kernel
def quintic_blend_kernel(
    # Data in:
    s_in: wp.array(dtype=wp.float64),
    # Data out:
    value_out: wp.array(dtype=wp.float64),
    first_out: wp.array(dtype=wp.float64),
    second_out: wp.array(dtype=wp.float64),
):
    tid = wp.tid()
    v, d1, d2 = quintic_blend(s_in[tid])
    value_out[tid] = v
    first_out[tid] = d1
    second_out[tid] = d2
