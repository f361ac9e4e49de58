"""IPC baseline contact model (Li et al. 2020) through the IPC Toolkit (``ipctk``, CPU).

The IPC barrier on point-triangle and edge-edge distances d < dhat, summed over the candidate
pairs of different bodies; ipctk (1.6) evaluates it on squared distances, b = -(d^2 -
dhat^2)^2 log(d^2 / dhat^2) (measured: 1.994e-8 per pair at d = 3 mm, dhat = 1 cm; the IPC
paper's form on d would give 5.9e-5). Its support is local: beyond
``dhat`` the potential and its gradient are exactly zero (the vanishing-gradient baseline of
the paper), and it is only once differentiable where the closest features switch.

``IpcContactModel`` has the interface the solver uses (``evaluate``, ``advancement_limit``,
``advancement_frame``, ``friction_frame``, ``friction_terms``, ``friction_adjoint``,
``body_pairs``, names and static flags), so ``ModelBuilder(contact_mode="ipc")`` swaps it in
for the separating-plane model. Choices: one collision mesh of all bodies, with a native
vertex-patch filter so a body's own triangles never pair; line-search steps bounded by
ipctk's continuous collision detection, which follows straight vertex paths, along chords of
the arcs a step turns the vertices on (pieces whose bulge from the arc stays below
``ARC_BULGE`` x dhat), times the same safety fraction as the plane bound.

Friction is IPC's own lagged friction (Li et al. 2020, section 5) through ipctk, with the
model's coefficient lambda and smoothing v_eps: for each point-triangle / edge-edge
collision active at q^t (within dhat), the lagged normal force is the barrier's force
magnitude mu |b'(d)| (ipctk's ``BarrierPotential`` with stiffness mu), the tangent basis and
closest-point coordinates are those at q^t, and the slip is the closest points' relative
displacement over the step, u = x - x^t; D = lambda N f0(|T^T u|) with IPC's C2 mollifier f0
(eps = v_eps dt, saturating at lambda N like the separating-plane models' sqrt law; the two
differ only below eps). Beyond dhat there is no collision and no friction. The backward is
exact: ipctk's ``force_jacobian`` with respect to the lagged positions differentiates N, the
basis and the closest points by x^t.
"""

from __future__ import annotations

import numpy as np

from dataclasses import dataclass

from .articulation import connected_labels
from .contact import ContactEvaluation, LaggedFriction, check_friction_arguments, check_own, checked_adjoint_arguments, checked_bodies, contact_body_pairs, hessian_slots
from .rotation import cross, quat_from_rotation_vector, quat_to_matrix, skew
from ._validate import check_barrier_support, checked_flag, validated_poses, validated_step

# A step's arc is checked in chord pieces whose bulge stays below this fraction of dhat.
ARC_BULGE = 1e-3
MAX_ARC_PIECES = 64
# Interval splits of one continuous collision query (Tight-Inclusion CCD), past which it
# returns its conservative time of impact: ipctk's default (1e7) let a query between faces
# ~1e-16 m apart (a box sunk through a soft barrier) split for minutes and take 12 GB. Some
# ordinary queries reach it too, and their shorter steps move trajectories in the last
# digits (a ball 2 mm above the ground at stiffness 1e3: 2.8e-9 m).
CCD_MAX_ITERATIONS = 100_000
# Below this fraction of dhat the least distance is taken per body pair (``_pair_separations``),
# where the solver's check of pressed pairs needs it; above it every pair gets the global one.
PAIR_DISTANCE_FRACTION = 1e-3

__all__ = ["IpcContactModel", "toolkit_problem"]


def toolkit_problem() -> str | None:
    """Why the ipc baseline cannot run here (the IPC Toolkit, an optional extra, is not
    installed), or None."""
    try:
        import ipctk  # noqa: F401
        import scipy.sparse  # noqa: F401
    except ImportError as exc:
        # Ctrl-C inside an extension's initialisation surfaces as an ImportError ("initialization
        # failed"): it was reported as a missing IPC Toolkit, and the interrupt lost.
        if isinstance(exc.__cause__ or exc.__context__, KeyboardInterrupt):
            raise KeyboardInterrupt from exc
        return f"the ipc baseline needs the IPC Toolkit: pip install 'warpcontact[ipc]' ({exc})"
    return None


@dataclass(frozen=True)
class _IpcLaggedFriction:
    """ipctk's lagged friction data of one step (``LaggedFriction.data``)."""

    collisions: object  # ipctk.TangentialCollisions at q^t
    lagged_vertices: np.ndarray  # world vertices x^t
    normal_potential: object  # barrier with stiffness mu: the normal forces' source
    potential: object  # ipctk.FrictionPotential(eps)


class IpcContactModel:
    """IPC barrier between rigid bodies (numpy in and out, like ``ContactModel``).

    Args:
        meshes: list of (V, F) per body in the body frame.
        dhat: barrier support distance (m).
        static, names: as for ``ContactModel``.
        device: "cpu" (ipctk runs on the CPU only).
        exclude_pairs: (a, b) body index pairs without contact terms (jointed links).

    Raises:
        ValueError: without the IPC Toolkit (``pip install 'warpcontact[ipc]'``), on another
            device, or for bad meshes or a bad ``dhat``.
    """

    mode = "ipc"
    # ipctk's continuous collision detection admits friction-exact Newton directions where it
    # holds the plain ones back (the frames of ``ContactModel.crawl_skips_friction_model``'s
    # test took 2.6x as long with plain directions there), and each bound costs ~0.1 s.
    crawl_skips_friction_model = False

    def __init__(self, meshes, *, dhat: float = 1e-2, static=None, names=None, device="cpu", exclude_pairs=()):
        problem = toolkit_problem()
        if problem is not None:
            raise ValueError(problem)
        import ipctk
        import scipy.sparse as sp

        if str(device) != "cpu":
            raise ValueError(f"device: the ipc baseline runs on the CPU only (ipctk), got {device!r}")
        check_barrier_support(dhat)
        self._ipctk, self._sparse = ipctk, sp
        meshes, self.names, self.static = checked_bodies(meshes, names, static)
        self.num_bodies = len(meshes)
        self.dhat = float(dhat)
        self.body_pairs = contact_body_pairs(self.static, exclude_pairs)
        self._pair_index = {(int(a), int(b)): k for k, (a, b) in enumerate(self.body_pairs)}  # (a, b) -> row, for _pair_separations
        self.hessian_bodies, self._hessian_slot = hessian_slots(self.static)
        vertices, faces, body_of = [], [], []
        offset = 0
        for b, (V, F) in enumerate(meshes):
            vertices.append(V)
            faces.append(F + offset)
            body_of.append(np.full(len(V), b, dtype=np.int32))
            offset += len(V)
        self._local = np.concatenate(vertices)
        self._body_of = np.concatenate(body_of)
        F = np.concatenate(faces)
        self._mesh = ipctk.CollisionMesh(self._local, ipctk.edges(F), F)
        self._patch = self._patches(exclude_pairs)
        self._mesh.can_collide = ipctk.make_vertex_patches_filter(self._patch[self._body_of])
        self._potential = ipctk.BarrierPotential(self.dhat, 1.0)
        self._ccd = ipctk.TightInclusionCCD(max_iterations=CCD_MAX_ITERATIONS)
        self._world = self._local.copy()
        self._positions = np.zeros((self.num_bodies, 3))
        self._collisions = ipctk.NormalCollisions()
        # Whether evaluate has run: before it, the world vertices are the bodies' meshes all at
        # the origin (friction_frame found 0 pairs there and advancement_limit returned 0, silently).
        self._evaluated = False

    def _require_evaluation(self, what: str):
        """RuntimeError, as ``ContactModel``'s, when no ``evaluate`` has set the configuration."""
        if not self._evaluated:
            raise RuntimeError(f"{what}: uses the collisions and vertices of the last evaluate(poses), and the model holds none (call evaluate at the configuration the step starts from)")

    def _patches(self, exclude_pairs) -> np.ndarray:
        """Patch id per body: ipctk's filter only separates patches, so bodies joined by
        excluded pairs share one patch (all contact inside such a group is off). The groups of
        static bodies alone share one too, as static bodies have no contact terms between them
        in ``ContactModel`` (a pedestal standing on the floor made every step's barrier
        infinite; a probe, stop 65); a group that holds a dynamic body (a fixed robot base
        jointed to its first link) keeps its own, since that body's contact with the other
        static bodies would switch off with it."""
        labels = connected_labels(self.num_bodies, exclude_pairs).astype(np.int32)
        static_only = np.setdiff1d(labels[self.static], labels[~self.static])
        if len(static_only) > 1:
            labels[np.isin(labels, static_only)] = static_only[0]
        return labels

    def _world_vertices(self, poses: np.ndarray) -> np.ndarray:
        R = quat_to_matrix(poses[:, 3:])
        return np.einsum("vij,vj->vi", R[self._body_of], self._local) + poses[self._body_of, :3]

    def _validated_poses(self, poses) -> np.ndarray:
        """(nbodies, 7) float64 poses with unit quaternions, or ValueError naming the problem
        (the rules of ``ContactModel``: a quaternion off unit norm by more than
        QUATERNION_TOLERANCE is refused; a zero one gave a NaN gradient with value 0)."""
        return validated_poses(poses, self.names)

    def evaluate(self, poses, *, reuse: bool = False, friction: LaggedFriction | None = None) -> ContactEvaluation:
        """Barrier value, (nbodies, 6) gradient and Hessian in rigid coordinates (dp, dtheta).

        ``reuse`` and ``friction`` are accepted for ``ContactModel``'s signature and ignored:
        ipctk's collision set is rebuilt at every call, and ``friction_terms`` computes on the
        host, with nothing to wait for.
        """
        checked_flag(reuse, "reuse")
        poses = self._validated_poses(poses)
        ipctk = self._ipctk
        V = self._world_vertices(poses)
        self._world, self._positions = V, poses[:, :3].copy()
        self._evaluated = True
        n = self.num_bodies
        if ipctk.has_intersections(self._mesh, V):
            pairs = [(self.names[a], self.names[b]) for a, b in self.body_pairs if self._pair_intersects(V, a, b)]
            if not pairs:
                # Two static bodies ipctk's filter could not keep apart (_patches): unnamed before.
                static = np.flatnonzero(self.static)
                pairs = [(self.names[a], self.names[b]) for i, a in enumerate(static) for b in static[i + 1 :] if self._patch[a] != self._patch[b] and self._pair_intersects(V, a, b)]
            m = 6 * len(self.hessian_bodies)
            return ContactEvaluation(np.inf, np.zeros((n, 6)), np.zeros((m, m)), 0, 0, 0, pairs, [], 0.0, np.zeros(len(self.body_pairs)))
        value, g, H, collisions = self._vertex_terms(V)
        self._collisions = collisions
        grad, hess = self._rigid_terms(V, poses[:, :3], g, H)
        distance = collisions.compute_minimum_distance(self._mesh, V) ** 0.5 if len(collisions) else self.dhat
        separation = np.full(len(self.body_pairs), distance)
        if distance < PAIR_DISTANCE_FRACTION * self.dhat:
            separation = self._pair_separations(V, collisions)
        return ContactEvaluation(value, grad, hess, 0, 0, len(collisions), [], [], 0.0, separation)

    def _pair_separations(self, V: np.ndarray, collisions) -> np.ndarray:
        """Per body pair, the least distance of its active collisions, dhat for a pair without
        any (they are at least that far apart). One distance for every pair, the global least
        (static pairs' too), held every body's converged step to the closest pair's gap, so the
        solver's check of pressed pairs was off for ipc, and a box started 1e-12 m from
        another "converged" at its first step and stayed, pushed by 5e10 N (a probe, stop 58)."""
        separation = np.full(len(self.body_pairs), self.dhat)
        E, F = self._mesh.edges, self._mesh.faces
        for group in (collisions.vv_collisions, collisions.ev_collisions, collisions.ee_collisions, collisions.fv_collisions):
            for collision in group:
                ids = np.asarray(collision.vertex_ids(E, F))
                bodies = np.unique(self._body_of[ids[ids >= 0]])
                k = self._pair_index.get((int(bodies[0]), int(bodies[-1])))
                if k is not None:
                    separation[k] = min(separation[k], float(collision.compute_distance(collision.dof(V, E, F))) ** 0.5)
        return separation

    def _rigid_terms(self, V: np.ndarray, positions: np.ndarray, g: np.ndarray, H):
        """A vertex-coordinate gradient (nv, 3) and sparse Hessian in rigid coordinates
        (dp, dtheta) of the bodies at ``positions``: J = [I, -[r]x] per vertex, plus the
        exponential map's curvature; a zero gradient for static bodies, and a Hessian over
        the non-static bodies only (``hessian_bodies``)."""
        n = self.num_bodies
        r = V - positions[self._body_of]
        dynamic = ~self.static[self._body_of]
        grad = np.zeros((n, 6))
        np.add.at(grad, self._body_of, np.concatenate([g, cross(r, g)], axis=1))
        J = np.zeros((len(V), 3, 6))
        J[:, :, :3] = np.eye(3)
        J[:, :, 3:] = -skew(r)
        J[~dynamic] = 0.0
        shape = (len(V), 3, 6)
        slot = self._hessian_slot[self._body_of]
        m = len(self.hessian_bodies)
        rows = np.broadcast_to(3 * np.arange(len(V))[:, None, None] + np.arange(3)[None, :, None], shape)
        cols = np.broadcast_to(6 * slot[:, None, None] + np.arange(6)[None, None, :], shape)
        # Static vertices have no columns (and no entries: explicit zeros changed the sums).
        Jsp = self._sparse.csr_matrix((J[dynamic].reshape(-1), (rows[dynamic].reshape(-1), cols[dynamic].reshape(-1))), shape=(3 * len(V), 6 * m))
        # Row-major, as the rest of the solver's matrices (the layout changes BLAS rounding).
        hess = np.ascontiguousarray((Jsp.T @ (H @ Jsp)).toarray())
        curvature = 0.5 * (np.einsum("vi,vj->vij", g, r) + np.einsum("vi,vj->vij", r, g)) - np.einsum("vi,vi->v", g, r)[:, None, None] * np.eye(3)
        blocks = np.zeros((m, 3, 3))
        np.add.at(blocks, slot[dynamic], curvature[dynamic])
        for k in range(m):
            hess[6 * k + 3 : 6 * k + 6, 6 * k + 3 : 6 * k + 6] += blocks[k]
        grad[self.static] = 0.0
        return grad, hess

    def _vertex_terms(self, V: np.ndarray):
        """ipctk's own work at world vertices V: collision build, barrier value, gradient
        (nv, 3) and sparse Hessian (3 nv, 3 nv), and the collision set."""
        collisions = self._ipctk.NormalCollisions()
        collisions.build(self._mesh, V, self.dhat)
        value = float(self._potential(collisions, self._mesh, V))
        g = self._potential.gradient(collisions, self._mesh, V).reshape(-1, 3)
        H = self._potential.hessian(collisions, self._mesh, V)
        return value, g, H, collisions

    def vertex_terms(self, poses) -> tuple[float, int]:
        """Only ipctk's part of ``evaluate`` at ``poses`` (collision build + barrier value,
        gradient and Hessian in vertex coordinates, no intersection check or rigid
        projection), for timing it side by side with other models; returns (value, number
        of active collisions)."""
        value, _, _, collisions = self._vertex_terms(self._world_vertices(self._validated_poses(poses)))
        return value, len(collisions)

    def _pair_intersects(self, V, a, b) -> bool:
        keep = np.isin(self._body_of, [a, b])
        index = -np.ones(len(V), dtype=np.int64)
        index[keep] = np.arange(keep.sum())
        F = np.asarray(self._mesh.faces)
        F = F[keep[F].all(axis=1)]
        sub = self._ipctk.CollisionMesh(V[keep], self._ipctk.edges(index[F]), index[F])
        sub.can_collide = self._ipctk.make_vertex_patches_filter(self._body_of[keep])
        return bool(self._ipctk.has_intersections(sub, V[keep]))

    # --- friction -----------------------------------------------------------------------

    def friction_frame(self, mu: float, friction, slip_smoothing: float, *, coefficient: float | None = None) -> LaggedFriction:
        """IPC's lagged friction at the last evaluated configuration (a step's q^t): ipctk's
        tangential collisions of the collisions active there (module docstring);
        ``coefficient`` as ``ContactModel.friction_frame``'s."""
        coefficient = check_friction_arguments(mu, friction, slip_smoothing, coefficient)
        self._require_evaluation("friction_frame")
        ipctk = self._ipctk
        normal_potential = ipctk.BarrierPotential(self.dhat, float(mu))
        collisions = ipctk.TangentialCollisions()
        # The coefficient as checked (the array was read a second time here).
        collisions.build(self._mesh, self._world, self._collisions, normal_potential, coefficient)
        data = _IpcLaggedFriction(collisions, self._world.copy(), normal_potential, ipctk.FrictionPotential(float(slip_smoothing)))
        return LaggedFriction(pairs=len(collisions), mu=float(mu), friction=friction, slip_smoothing=float(slip_smoothing), data=data, model_id=id(self))

    def friction_terms(self, lagged: LaggedFriction, *, poses: np.ndarray | None = None):
        """Friction value, (6 nbodies,) gradient and dense Hessian over ``hessian_bodies`` in
        rigid coordinates at the last evaluated poses, or at ``poses`` (see
        ``ContactModel.friction_terms``)."""
        check_own(lagged, LaggedFriction, "lagged", self)
        data = lagged.data
        if poses is None:
            self._require_evaluation("friction_terms")
        else:
            # ContactModel's rules, the poses kept to the last bit (a NaN gave a NaN value, a row short an IndexError).
            poses = validated_poses(poses, self.names, normalize=False)
        if not lagged.pairs:
            m = 6 * len(self.hessian_bodies)
            return 0.0, np.zeros(6 * self.num_bodies), np.zeros((m, m))
        world, positions = (self._world, self._positions) if poses is None else (self._world_vertices(poses), poses[:, :3])
        slip = world - data.lagged_vertices
        value = float(data.potential(data.collisions, self._mesh, slip))
        g = data.potential.gradient(data.collisions, self._mesh, slip).reshape(-1, 3)
        H = data.potential.hessian(data.collisions, self._mesh, slip)
        grad, hess = self._rigid_terms(world, positions, g, H)
        return value, grad.reshape(-1), hess

    def friction_adjoint(self, lagged: LaggedFriction, q_next: np.ndarray, q_now: np.ndarray, multiplier: np.ndarray):
        """lambda^T d(grad_q D)/dy of the step's friction at its solution q_next, for y = q^t,
        the friction coefficient and mu (see ``ContactModel.friction_adjoint``).

        With F(x^t, u) ipctk's friction force (-dD/du) and u = x - x^t, grad_x D = -F and
        d(grad_x D)/dx^t = -dF/dx^t|_u + dF/du = -dF/dx^t|_u - d2D/du2.
        """
        check_own(lagged, LaggedFriction, "lagged", self)
        q_next, q_now, multiplier = checked_adjoint_arguments(q_next, q_now, multiplier, self.names)
        ipctk = self._ipctk
        data = lagged.data
        mesh = self._mesh
        V_next = self._world_vertices(q_next)
        V_now = data.lagged_vertices
        slip = V_next - V_now
        dynamic = ~self.static[self._body_of]
        r_next = V_next - q_next[self._body_of, :3]
        velocity = multiplier[self._body_of, :3] + cross(multiplier[self._body_of, 3:], r_next)
        velocity[~dynamic] = 0.0
        lagged_jacobian = data.potential.force_jacobian(
            data.collisions, mesh, V_now, np.zeros_like(V_now), slip, data.normal_potential, ipctk.TangentialPotential.LAGGED_DISPLACEMENTS
        )
        slip_hessian = data.potential.hessian(data.collisions, mesh, slip)
        w = velocity.reshape(-1)
        vertex_adjoint = (-(lagged_jacobian.T @ w) - slip_hessian.T @ w).reshape(-1, 3)
        vertex_adjoint[~dynamic] = 0.0
        r_now = V_now - q_now[self._body_of, :3]
        adj_q = np.zeros((self.num_bodies, 6))
        np.add.at(adj_q, self._body_of, np.concatenate([vertex_adjoint, cross(r_now, vertex_adjoint)], axis=1))
        contraction = float(w @ data.potential.gradient(data.collisions, mesh, slip))
        friction = float(lagged.friction.numpy()[0])
        return adj_q, contraction / friction, contraction / lagged.mu

    def advancement_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """World vertices and body positions of the last ``evaluate`` (see ContactModel)."""
        self._require_evaluation("advancement_frame")
        return self._world.copy(), self._positions.copy()

    def advancement_limit(self, step, *, fraction: float = 0.9, frame: tuple | None = None) -> float:
        """Largest alpha in (0, 1] with no collision along the step, from the last evaluated
        configuration or ``frame`` (ipctk CCD along chords of the bodies' arcs, times
        ``fraction`` when limiting)."""
        step = validated_step(step, self.names, self.static)
        if frame is None:
            self._require_evaluation("advancement_limit")
        world, positions = frame if frame is not None else (self._world, self._positions)
        offsets = world - positions[self._body_of]
        # ipctk's CCD follows straight vertex paths, and a step turns each body along an arc
        # that bulges from its chord by up to r theta^2 / 8: a rod spinning at 30 rad/s went
        # through a post inside that bulge. The arc is cut into pieces whose bulge is below
        # ARC_BULGE x dhat (at most MAX_ARC_PIECES), each checked on its chord.
        radius = np.zeros(self.num_bodies)
        np.maximum.at(radius, self._body_of, np.linalg.norm(offsets, axis=1))
        bulge = float(np.max(radius * np.sum(step[:, 3:] ** 2, axis=1))) / 8.0
        pieces = int(min(MAX_ARC_PIECES, max(1, np.ceil(np.sqrt(bulge / (ARC_BULGE * self.dhat))))))

        def vertices_at(s: float) -> np.ndarray:
            rotation = quat_to_matrix(quat_from_rotation_vector(s * step[:, 3:]))
            return np.einsum("vij,vj->vi", rotation[self._body_of], offsets) + (positions + s * step[:, :3])[self._body_of]

        start = world
        for piece in range(pieces):
            end = vertices_at((piece + 1) / pieces)
            alpha = float(self._ipctk.compute_collision_free_stepsize(self._mesh, start, end, narrow_phase_ccd=self._ccd))
            if alpha < 1.0:
                return fraction * (piece + alpha) / pieces
            start = end
        return 1.0
