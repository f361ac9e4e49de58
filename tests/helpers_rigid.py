"""Rigid-coordinate test utilities: meshes, poses and finite differences in (dp, dtheta)."""

import numpy as np
import trimesh


def icosphere(subdivisions=0, radius=0.5):
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(s.vertices, dtype=np.float64), np.asarray(s.faces)


def box(extents=(1.0, 0.6, 0.4)):
    b = trimesh.creation.box(extents=extents)
    return np.asarray(b.vertices, dtype=np.float64), np.asarray(b.faces)


def quat(axis, angle):
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([np.sin(angle / 2) * axis, [np.cos(angle / 2)]])


def quat_mul(q, r):
    x1, y1, z1, w1 = q
    x2, y2, z2, w2 = r
    return np.array(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ]
    )


def perturbed(poses, body, coordinate, h):
    """Poses moved by h along one rigid coordinate (dp, then dtheta about world axes)."""
    out = poses.copy()
    if coordinate < 3:
        out[body, coordinate] += h
    else:
        axis = np.zeros(3)
        axis[coordinate - 3] = 1.0
        out[body, 3:] = quat_mul(quat(axis, h), poses[body, 3:])
    return out


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def fd_check(model, poses, h=1e-6):
    """Relative errors of grad vs FD of the value, and of the Hessian vs FD of the gradient.

    The gradient at a rotated pose is taken about that pose, so FD of it differs from the
    Hessian by the exponential map's bracket: J = H - 1/2 [g_theta]x on each body's
    (theta, theta) block; the comparison adds that back.
    """
    base = model.evaluate(poses)
    assert base.ok
    n = model.num_bodies
    fd_grad = np.zeros(6 * n)
    fd_jac = np.zeros((6 * n, 6 * n))
    for b in range(n):
        if model.static[b]:
            continue
        for c in range(6):
            plus = model.evaluate(perturbed(poses, b, c, h))
            minus = model.evaluate(perturbed(poses, b, c, -h))
            fd_grad[6 * b + c] = (plus.value - minus.value) / (2 * h)
            fd_jac[:, 6 * b + c] = (plus.grad - minus.grad).reshape(-1) / (2 * h)
    for b in range(n):
        rot = slice(6 * b + 3, 6 * b + 6)
        fd_jac[rot, rot] += 0.5 * skew(base.grad[b, 3:])
    grad = base.grad.reshape(-1)
    grad_err = np.abs(fd_grad - grad).max() / np.abs(grad).max()
    # The Hessian holds the non-static bodies only.
    rows = np.flatnonzero(np.repeat(~np.asarray(model.static, dtype=bool), 6))
    assert np.all(fd_jac[np.ix_(rows, np.setdiff1d(np.arange(6 * n), rows))] == 0)
    fd_jac = fd_jac[np.ix_(rows, rows)]
    hess_err = np.abs(fd_jac - base.hessian).max() / np.abs(base.hessian).max()
    return base, grad_err, hess_err


def identity_poses(positions):
    poses = np.zeros((len(positions), 7))
    poses[:, :3] = positions
    poses[:, 6] = 1.0
    return poses


def ball_into_wall(**builder_options):
    """x of a 0.5 m ball launched at 1 m/s into a static wall (face at x = 0.6), 15 steps of
    0.02 s in zero gravity; every step's poses are checked to be contact-free."""
    import warp as wp

    import warpcontact as wc

    b = wc.ModelBuilder(gravity=(0.0, 0.0, 0.0), **builder_options)
    b.add_box((0.1, 2.0, 2.0), static=True, name="wall", pose=(0.65, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    b.add_sphere(0.5, subdivisions=1, density=100.0, name="ball", pose=(0.0, 0.1, 0.05, 0.0, 0.0, 0.0, 1.0))
    model = b.finalize()
    solver = wc.ImplicitSolver(model)
    states = [model.state(requires_grad=False)]
    wc.set_body_velocity(states[0], wp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=wp.vec3d), wp.zeros(2, dtype=wp.vec3d), 0.02)
    for _ in range(15):
        nxt = model.state(requires_grad=False)
        solver.step(states[-1], nxt, None, 0.02)
        states.append(nxt)
        assert model.contact.evaluate(nxt.body_q.numpy()).ok
    return np.array([s.body_q.numpy()[1, 0] for s in states])
