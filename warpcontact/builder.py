"""ModelBuilder: bodies from trimesh meshes and primitives into a ``Model``."""

from dataclasses import dataclass

import numpy as np
import trimesh
import warp as wp

from ._runtime import resolve_device
from .contact import ContactModel
from .types import Model

__all__ = ["ModelBuilder"]


@dataclass
class _Body:
    name: str
    vertices: np.ndarray  # body frame, origin at the centre of mass
    faces: np.ndarray
    mass: float
    second_moment: np.ndarray
    pose: np.ndarray  # (7,) of the centre-of-mass frame
    static: bool
    kp_linear: np.ndarray
    kd_linear: np.ndarray
    kp_angular: float
    kd_angular: float


def _second_moment_from_inertia(inertia: np.ndarray) -> np.ndarray:
    """S = sum m X X^T from the inertia tensor J = tr(S) I - S."""
    return 0.5 * np.trace(inertia) * np.eye(3) - inertia


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    u = np.array([x, y, z])
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


class ModelBuilder:
    """Collects bodies, then ``finalize()`` builds a ``Model``.

    Args:
        gravity: (3,) gravitational acceleration (m/s^2).
        contact_stiffness: potential coefficient mu (the paper uses 1e-6 .. 5e-9).
        friction: friction coefficient; 0 disables friction (and all its work).
        friction_smoothing: slip speed (m/s) below which the friction law is smoothed.
        eps: blend margin of the hierarchical contact potential.
        contact_mode: ``"bsh"``, ``"brute"`` (the paper's model, hierarchical or exact),
            ``"ipc"`` (the IPC baseline through ipctk; CPU only, no friction) or ``"sdrs"``
            (the SDRS baseline: locally supported log barrier on separating planes; no
            friction).
        ipc_dhat: barrier support distance of the ``"ipc"`` baseline (m).
        sdrs_dhat: barrier support of the ``"sdrs"`` baseline on vertex-to-plane gaps (m);
            triangles interact below 2 sdrs_dhat.
    """

    def __init__(self, *, gravity=(0.0, 0.0, -9.81), contact_stiffness: float = 1e-6, friction: float = 0.0, friction_smoothing: float = 1e-4, eps: float = 0.5, contact_mode: str = "bsh", ipc_dhat: float = 1e-2, sdrs_dhat: float = 1e-2):
        gravity = np.asarray(gravity, dtype=np.float64)
        if gravity.shape != (3,) or not np.isfinite(gravity).all():
            raise ValueError(f"gravity: expected 3 finite numbers, got {gravity}")
        if not np.isfinite(contact_stiffness) or contact_stiffness <= 0:
            raise ValueError(f"contact_stiffness: must be positive and finite, got {contact_stiffness}")
        if not np.isfinite(friction) or friction < 0:
            raise ValueError(f"friction: must be >= 0 and finite, got {friction}")
        self.gravity = gravity
        self.contact_stiffness = float(contact_stiffness)
        if not np.isfinite(friction_smoothing) or friction_smoothing <= 0:
            raise ValueError(f"friction_smoothing: must be positive and finite, got {friction_smoothing}")
        self.friction = float(friction)
        self.friction_smoothing = float(friction_smoothing)
        if contact_mode in ("ipc", "sdrs") and friction > 0:
            raise ValueError(f"friction: the {contact_mode} baseline has no friction model here; use friction=0")
        self.eps = eps
        self.contact_mode = contact_mode
        self.ipc_dhat = ipc_dhat
        self.sdrs_dhat = sdrs_dhat
        self._bodies: list[_Body] = []

    def add_body(
        self,
        mesh,
        *,
        name: str | None = None,
        pose=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        density: float | None = None,
        mass: float | None = None,
        inertia=None,
        center_of_mass=None,
        static: bool = False,
        kp_linear=0.0,
        kd_linear=0.0,
        kp_angular: float = 0.0,
        kd_angular: float = 0.0,
    ) -> int:
        """Add a rigid body; returns its index.

        Args:
            mesh: ``trimesh.Trimesh`` or (vertices (nv, 3), faces (nf, 3)) in the mesh frame (m).
            pose: (7,) pose of the mesh frame (px, py, pz, qx, qy, qz, qw).
            density: kg/m^3; mass, centre of mass and inertia from the (watertight) mesh.
            mass, inertia, center_of_mass: given values instead of a density (kg, kg m^2
                about the centre of mass in the mesh frame's axes, m); inertia defaults to
                that of the mesh volume scaled to ``mass``.
            static: fixed in place; no degrees of freedom.
            kp_linear, kd_linear: PD gains per translation axis (scalar or 3 values).
            kp_angular, kd_angular: PD gains of the orientation.
        """
        name = name or f"body{len(self._bodies)}"
        if isinstance(mesh, trimesh.Trimesh):
            tm = mesh
        else:
            try:
                vertices, faces = mesh
                tm = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False)
            except Exception as exc:
                raise ValueError(f"body {name!r}: mesh must be a trimesh.Trimesh or (vertices, faces): {exc}") from None
        vertices = np.asarray(tm.vertices, dtype=np.float64)
        faces = np.asarray(tm.faces, dtype=np.int64)
        if len(faces) == 0:
            raise ValueError(f"body {name!r}: mesh has no faces")
        if not np.isfinite(vertices).all():
            raise ValueError(f"body {name!r}: mesh has non-finite vertices")
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (7,) or not np.isfinite(pose).all():
            raise ValueError(f"body {name!r}: pose must be 7 finite numbers (px, py, pz, qx, qy, qz, qw), got {pose}")
        qnorm = np.linalg.norm(pose[3:])
        if abs(qnorm - 1.0) > 1e-6:
            raise ValueError(f"body {name!r}: pose quaternion has norm {qnorm:.9g}, expected 1")
        pose[3:] /= qnorm

        if static:
            if density is not None or mass is not None:
                raise ValueError(f"body {name!r}: a static body takes no density or mass")
            com = vertices.mean(axis=0)
            body_mass, second_moment = 1.0, np.zeros((3, 3))
        elif density is not None:
            if mass is not None or inertia is not None:
                raise ValueError(f"body {name!r}: give either density or mass/inertia, not both")
            if not np.isfinite(density) or density <= 0:
                raise ValueError(f"body {name!r}: density must be positive, got {density}")
            if not tm.is_watertight or tm.volume <= 0:
                raise ValueError(f"body {name!r}: mass from density needs a closed, outward-oriented mesh; give mass and inertia instead")
            props = tm.mass_properties
            body_mass = float(props["volume"]) * density
            com = np.asarray(props["center_mass"], dtype=np.float64)
            second_moment = _second_moment_from_inertia(np.asarray(props["inertia"], dtype=np.float64) * density)
        elif mass is not None:
            if not np.isfinite(mass) or mass <= 0:
                raise ValueError(f"body {name!r}: mass must be positive, got {mass}")
            body_mass = float(mass)
            if inertia is None:
                if not tm.is_watertight or tm.volume <= 0:
                    raise ValueError(f"body {name!r}: inertia is needed for a mesh that is not closed")
                props = tm.mass_properties
                com = np.asarray(props["center_mass"], dtype=np.float64) if center_of_mass is None else np.asarray(center_of_mass, dtype=np.float64)
                scale = body_mass / float(props["mass"])
                inertia = np.asarray(props["inertia"], dtype=np.float64) * scale
            else:
                com = vertices.mean(axis=0) if center_of_mass is None else np.asarray(center_of_mass, dtype=np.float64)
            inertia = np.asarray(inertia, dtype=np.float64)
            if inertia.shape != (3, 3) or not np.allclose(inertia, inertia.T) or np.linalg.eigvalsh(inertia).min() <= 0:
                raise ValueError(f"body {name!r}: inertia must be a symmetric positive definite 3x3 matrix")
            second_moment = _second_moment_from_inertia(inertia)
            if np.linalg.eigvalsh(second_moment).min() < -1e-12 * np.trace(inertia):
                raise ValueError(f"body {name!r}: inertia violates the triangle inequality (not physical)")
        else:
            raise ValueError(f"body {name!r}: give a density or a mass (or mark it static)")

        kp_lin = np.broadcast_to(np.asarray(kp_linear, dtype=np.float64), (3,)).copy()
        kd_lin = np.broadcast_to(np.asarray(kd_linear, dtype=np.float64), (3,)).copy()
        for label, value in (("kp_linear", kp_lin), ("kd_linear", kd_lin), ("kp_angular", kp_angular), ("kd_angular", kd_angular)):
            if not np.all(np.isfinite(value)) or np.any(np.asarray(value) < 0):
                raise ValueError(f"body {name!r}: {label} must be >= 0 and finite, got {value}")
        if static and (kp_lin.any() or kd_lin.any() or kp_angular or kd_angular):
            raise ValueError(f"body {name!r}: a static body cannot be PD-actuated")

        # Body frame: origin at the centre of mass, axes of the mesh frame.
        com_pose = pose.copy()
        com_pose[:3] = pose[:3] + _quat_rotate(pose[3:], com)
        self._bodies.append(
            _Body(name, vertices - com, faces, body_mass, second_moment, com_pose, bool(static), kp_lin, kd_lin, float(kp_angular), float(kd_angular))
        )
        return len(self._bodies) - 1

    def add_box(self, extents, **kwargs) -> int:
        """Add a box with the given (x, y, z) extents (m), centred on its frame."""
        return self.add_body(trimesh.creation.box(extents=extents), **kwargs)

    def add_sphere(self, radius: float, *, subdivisions: int = 2, **kwargs) -> int:
        """Add an icosphere of the given radius (m)."""
        return self.add_body(trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius), **kwargs)

    def finalize(self, *, device="cpu") -> Model:
        if not self._bodies:
            raise ValueError("ModelBuilder: no bodies were added")
        dev = resolve_device(device)
        bodies = self._bodies
        names = [b.name for b in bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"ModelBuilder: body names must be unique, got {names}")
        meshes = [(b.vertices, b.faces) for b in bodies]
        static = [b.static for b in bodies]
        if self.contact_mode == "ipc":
            from .ipc import IpcContactModel

            contact = IpcContactModel(meshes, dhat=self.ipc_dhat, static=static, names=names, device=dev)
        else:
            contact = ContactModel(meshes, eps=self.eps, mode=self.contact_mode, dhat=self.sdrs_dhat, static=static, names=names, device=dev)
        with wp.ScopedDevice(dev):
            return Model(
                body_names=names,
                body_mass=wp.array([b.mass for b in bodies], dtype=wp.float64, requires_grad=True),
                body_unit_second_moment=wp.array(np.array([b.second_moment / b.mass for b in bodies]), dtype=wp.mat33d),
                body_dynamic=wp.array([0 if b.static else 1 for b in bodies], dtype=wp.int32),
                body_kp_linear=wp.array(np.array([b.kp_linear for b in bodies]), dtype=wp.vec3d),
                body_kd_linear=wp.array(np.array([b.kd_linear for b in bodies]), dtype=wp.vec3d),
                body_kp_angular=wp.array([b.kp_angular for b in bodies], dtype=wp.float64),
                body_kd_angular=wp.array([b.kd_angular for b in bodies], dtype=wp.float64),
                body_radius=np.array([np.linalg.norm(b.vertices, axis=1).max() for b in bodies]),
                body_meshes=[(b.vertices, b.faces) for b in bodies],
                gravity=self.gravity.copy(),
                contact_stiffness=wp.array([self.contact_stiffness], dtype=wp.float64, requires_grad=True),
                friction=wp.array([self.friction], dtype=wp.float64, requires_grad=True),
                friction_smoothing=self.friction_smoothing,
                contact=contact,
                initial_q=np.array([b.pose for b in bodies]),
                device=dev,
            )
