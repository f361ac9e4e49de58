"""Reusable articulated robots built from simple meshes.

``add_ant`` builds the paper's Ant-Push robot (appendix "Experimental Details"): a base with
3 translations and 1 rotation (yaw), four upper legs on 2-DOF hips and four lower legs on
knee hinges, 16 degrees of freedom of which the 12 leg coordinates are actuated. The paper
calls the hips ball joints, but its count (16 DOFs, 12 actuated) only adds up with the
hip's twist locked, so each hip is a universal joint: a vertical swing axis fixed in the
base and a lift axis fixed in the upper leg.

Links are boxes (12 triangles each), so the ant costs little in the contact model. Between
every joint's two links there is a small gap; by default the contact model also skips
each joint's parent-child pair (``ModelBuilder(articulation_contact=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rotation import quat_from_rotation_vector

__all__ = ["AntSpec", "ant_standing_height", "add_ant"]


@dataclass(frozen=True)
class AntSpec:
    """Dimensions (m), density (kg/m^3), gains and limits of the ant.

    The torso is a box ``torso_size``; legs are square boxes of side ``leg_width``. The hip
    sits ``hip_offset`` beyond the torso corner along the diagonal; the upper leg starts
    ``gap`` from the hip and is ``upper_length`` long (horizontal at rest); the knee sits
    ``gap`` beyond it; the lower leg hangs ``gap`` below the knee and is ``lower_length``
    long (vertical at rest).
    """

    torso_size: tuple = (0.5, 0.5, 0.15)
    leg_width: float = 0.06
    upper_length: float = 0.3
    lower_length: float = 0.3
    hip_offset: float = 0.02
    gap: float = 0.02
    density: float = 500.0
    hip_kp: float = 500.0
    hip_kd: float = 5.0
    knee_kp: float = 300.0
    knee_kd: float = 3.0
    hip_limits: tuple = ((-0.7, 0.7), (-0.7, 0.7))  # swing, lift (rad)
    knee_limits: tuple = (-0.8, 0.8)  # rad


def ant_standing_height(spec: AntSpec = AntSpec(), *, clearance: float = 1e-3) -> float:
    """Height (m) of the hips (and the torso's centre) with the feet ``clearance`` above z = 0."""
    return spec.gap + spec.lower_length + clearance


def add_ant(builder, *, position=(0.0, 0.0), yaw: float = 0.0, ground_height: float = 0.0, spec: AntSpec = AntSpec(), name: str = "ant") -> dict:
    """Add the ant to ``builder`` standing at ``position`` (x, y) with its feet 1 mm above
    ``ground_height``, facing ``yaw`` (rad).

    Returns a dict with ``bodies`` (name -> body index), ``joints`` (name -> joint index) and
    ``actuated`` (the 12 leg coordinate names, in the order hips (swing, lift) then knee,
    leg by leg).
    """
    s = spec
    height = ground_height + ant_standing_height(s)
    origin = np.array([position[0], position[1], height])

    def place(local_centre, local_rotation_z=0.0):
        rot = quat_from_rotation_vector(np.array([0.0, 0.0, yaw + local_rotation_z]))
        c = np.asarray(local_centre, dtype=np.float64)
        world = origin + _rotate_z(c, yaw)
        return (*world, *rot)

    bodies, joints, actuated = {}, {}, []
    torso = builder.add_box(s.torso_size, density=s.density, pose=place((0.0, 0.0, 0.0)), name=f"{name}_torso")
    bodies["torso"] = torso
    joints["base"] = builder.add_joint("base", child=torso, dofs=("x", "y", "z", "rz"), name=f"{name}_base")
    corner = np.hypot(s.torso_size[0], s.torso_size[1]) / 2.0
    hip_radius = corner + s.hip_offset
    w = s.leg_width
    for leg, angle in enumerate(np.pi / 4 + np.pi / 2 * np.arange(4)):
        direction = np.array([np.cos(angle), np.sin(angle), 0.0])
        side = np.array([-np.sin(angle), np.cos(angle), 0.0])
        hip = hip_radius * direction
        upper_centre = hip + (s.gap + s.upper_length / 2) * direction
        knee = hip + (2 * s.gap + s.upper_length) * direction
        lower_centre = knee - np.array([0.0, 0.0, s.gap + s.lower_length / 2])
        upper = builder.add_box((s.upper_length, w, w), density=s.density, pose=place(upper_centre, angle), name=f"{name}_upper{leg}")
        lower = builder.add_box((w, w, s.lower_length), density=s.density, pose=place(lower_centre, angle), name=f"{name}_lower{leg}")
        bodies[f"upper{leg}"], bodies[f"lower{leg}"] = upper, lower
        world_side = _rotate_z(side, yaw)
        joints[f"hip{leg}"] = builder.add_joint(
            "universal",
            child=upper,
            parent=torso,
            anchor=origin + _rotate_z(hip, yaw),
            axis=[(0.0, 0.0, 1.0), world_side],
            limits=s.hip_limits,
            kp=s.hip_kp,
            kd=s.hip_kd,
            name=f"{name}_hip{leg}",
        )
        joints[f"knee{leg}"] = builder.add_joint(
            "revolute",
            child=lower,
            parent=upper,
            anchor=origin + _rotate_z(knee, yaw),
            axis=world_side,
            limits=[s.knee_limits],
            kp=s.knee_kp,
            kd=s.knee_kd,
            name=f"{name}_knee{leg}",
        )
        actuated += [f"{name}_hip{leg}:0", f"{name}_hip{leg}:1", f"{name}_knee{leg}:0"]
    return {"bodies": bodies, "joints": joints, "actuated": actuated}


def _rotate_z(v, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    v = np.asarray(v, dtype=np.float64)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])
