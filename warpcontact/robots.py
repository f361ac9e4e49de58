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

from ._validate import is_real
from .articulation import JOINT_AXES
from .builder import finite_vector
from .rotation import quat_from_rotation_vector, quat_rotate

__all__ = ["AntSpec", "actuated_coordinates", "add_ant", "ant_description", "ant_standing_height"]


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


def ant_description(*, position=(0.0, 0.0), yaw: float = 0.0, ground_height: float = 0.0, spec: AntSpec = AntSpec(), name: str = "ant"):
    """The ant's links and joints standing at ``position`` (x, y) with its feet 1 mm above
    ``ground_height``, facing ``yaw`` (rad).

    Returns (links, joints): links are dicts (name, extents (m), pose (7,)); joints are dicts
    (name, kind, parent, child (link names; parent None for the world), anchor (world point
    at these poses), axis (world), dofs, limits, kp, kd) in ``ModelBuilder.add_joint`` terms.
    """
    # A bad name or spec failed in the middle of add_ant, its bodies already in the builder.
    if not (isinstance(name, str) and name):
        raise ValueError(f"name: expected a non-empty string to prefix the ant's links and joints, got {name!r}")
    if not isinstance(spec, AntSpec):
        raise ValueError(f"{name}: spec must be an AntSpec, got {type(spec).__name__}")
    s = spec
    where = finite_vector(position, 2)
    if where is None:  # a 3-vector's z was dropped, a scalar failed in indexing
        raise ValueError(f"{name}: position must be 2 finite numbers (x, y; the feet stand at ground_height), got {position!r}")
    for label, value in (("yaw", yaw), ("ground_height", ground_height)):
        if not (is_real(value) and np.isfinite(value)):
            raise ValueError(f"{name}: {label} must be a finite number, got {value!r}")
    origin = np.array([where[0], where[1], ground_height + ant_standing_height(s)])
    turn = quat_from_rotation_vector(np.array([0.0, 0.0, yaw]))

    def place(local_centre, heading=0.0):
        rot = quat_from_rotation_vector(np.array([0.0, 0.0, yaw + heading]))
        return np.array([*(origin + quat_rotate(turn, local_centre)), *rot])

    torso = f"{name}_torso"
    links = [{"name": torso, "extents": tuple(s.torso_size), "pose": place((0.0, 0.0, 0.0))}]
    joints = [{"name": f"{name}_base", "kind": "base", "parent": None, "child": torso, "dofs": ("x", "y", "z", "rz")}]
    hip_radius = np.hypot(s.torso_size[0], s.torso_size[1]) / 2.0 + s.hip_offset
    w = s.leg_width
    for leg, angle in enumerate(np.pi / 4 + np.pi / 2 * np.arange(4)):
        direction = np.array([np.cos(angle), np.sin(angle), 0.0])
        side = quat_rotate(turn, np.array([-np.sin(angle), np.cos(angle), 0.0]))
        hip = hip_radius * direction
        knee = hip + (2 * s.gap + s.upper_length) * direction
        upper, lower = f"{name}_upper{leg}", f"{name}_lower{leg}"
        links.append({"name": upper, "extents": (s.upper_length, w, w), "pose": place(hip + (s.gap + s.upper_length / 2) * direction, angle)})
        links.append({"name": lower, "extents": (w, w, s.lower_length), "pose": place(knee - np.array([0.0, 0.0, s.gap + s.lower_length / 2]), angle)})
        joints.append(
            {"name": f"{name}_hip{leg}", "kind": "universal", "parent": torso, "child": upper, "anchor": origin + quat_rotate(turn, hip), "axis": np.array([[0.0, 0.0, 1.0], side]), "limits": s.hip_limits, "kp": s.hip_kp, "kd": s.hip_kd}
        )
        joints.append(
            {"name": f"{name}_knee{leg}", "kind": "revolute", "parent": upper, "child": lower, "anchor": origin + quat_rotate(turn, knee), "axis": side, "limits": [s.knee_limits], "kp": s.knee_kp, "kd": s.knee_kd}
        )
    return links, joints


def actuated_coordinates(joints) -> list[str]:
    """Names of the actuated joint coordinates (every coordinate of a joint with gains)."""
    return [f"{j['name']}:{k}" for j in joints if j.get("kp") for k in range(JOINT_AXES.get(j["kind"], 0))]


def add_ant(builder, *, position=(0.0, 0.0), yaw: float = 0.0, ground_height: float = 0.0, spec: AntSpec = AntSpec(), name: str = "ant") -> dict:
    """Add the ant (see ``ant_description``) to a ``ModelBuilder``, standing at ``position``
    (x, y; m) with its feet 1 mm above ``ground_height`` (m), facing ``yaw`` (rad); ``spec``
    sizes it and ``name`` prefixes its links and joints.

    Returns a dict with ``bodies`` (short name -> body index), ``joints`` (short name ->
    joint index) and ``actuated`` (the 12 leg coordinate names: per leg hip swing, hip lift,
    knee).
    """
    gravity = np.asarray(builder.gravity, dtype=np.float64)
    if gravity.any() and not (gravity[2] < 0.0 and np.allclose(gravity[:2], 0.0, atol=1e-9 * abs(gravity[2]))):
        # Built Z-up in a Y-up builder, the ant stood in its floor, and only "bodies intersect"
        # was said.
        raise ValueError(f"add_ant builds the ant Z-up (its base moves in x, y, z and turns about z); this builder's gravity is {gravity.tolist()}, not along -z")
    links, joints = ant_description(position=position, yaw=yaw, ground_height=ground_height, spec=spec, name=name)
    index = {}
    for link in links:
        index[link["name"]] = builder.add_box(link["extents"], density=spec.density, pose=link["pose"], name=link["name"])
    joint_index = {}
    for j in joints:
        options = {k: j[k] for k in ("anchor", "axis", "dofs", "limits", "kp", "kd") if k in j}
        parent = index[j["parent"]] if j["parent"] is not None else None
        joint_index[j["name"][len(name) + 1 :]] = builder.add_joint(j["kind"], child=index[j["child"]], parent=parent, name=j["name"], **options)
    bodies = {k[len(name) + 1 :]: v for k, v in index.items()}
    return {"bodies": bodies, "joints": joint_index, "actuated": actuated_coordinates(joints)}
