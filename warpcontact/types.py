"""Model / State / Control of the rigid-body simulator (in the manner of NVIDIA Newton).

- ``Model``: what does not change during a simulation: bodies (meshes in the body frame,
  whose origin is the centre of mass), masses, second moments, static flags, PD gains,
  gravity, contact stiffness, friction, and the contact model.
- ``State``: body poses at the current and the previous time step (the paper's
  (x^t, x^{t-1})) and the joint coordinates of articulations at both; velocities are
  (pose - previous pose) / dt.
- ``Control``: PD target poses of actuated bodies, PD targets of joint coordinates and
  target relative rotations of ball joints.

Poses are Warp transforms (px, py, pz, qx, qy, qz, qw) of each body's centre-of-mass frame,
in metres. Arrays that users optimise are allocated with ``requires_grad=True``.
"""

import threading
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ._validate import check_time_step, checked_flag
from ._runtime import paused_tape
from .articulation import ArticulationModel
from .contact import ContactModel
from .kernels import state as state_kernels

__all__ = ["Model", "State", "Control", "set_body_velocity"]


@dataclass
class State:
    """Body poses now and one step earlier, (nbodies,) ``wp.transformd`` each, and joint
    coordinates now and one step earlier, (ncoordinates,) float64 each (rad or m).

    The velocities are the two poses' difference over the time step, which the State does
    not store: a step of another dt than the last scales them (``set_body_velocity``).
    ``joint_q_prev`` is the step's record of the previous coordinates: written, not read
    (joint velocities come from ``body_q_prev``)."""

    body_q: wp.array
    body_q_prev: wp.array
    joint_q: wp.array = None
    joint_q_prev: wp.array = None


@dataclass
class Control:
    """PD target poses, (nbodies,) ``wp.transformd``, used for bodies with non-zero gains;
    PD targets of joint coordinates, (ncoordinates,) float64 (rad or m); PD target relative
    rotations of ball joints, (nball,) ``wp.quatd`` unit quaternions (x, y, z, w) of the
    child's joint frame in the parent's joint frame, in ``articulation.ball_joint_names``
    order (see ``ArticulationModel.ball_rotations``). A missing target holds the joint where
    the step starts (damping only)."""

    body_target: wp.array
    joint_target: wp.array = None
    ball_target: wp.array = None


@dataclass
class Model:
    """Simulation model; build it with ``ModelBuilder``.

    Attributes (device arrays, one entry per body unless stated):
        body_names: list of names.
        body_mass: (nbodies,) float64 mass (kg), requires_grad.
        body_unit_second_moment: (nbodies,) mat33d second moment per unit mass,
            sum m_v X X^T / m about the centre of mass (m^2), so changing a mass scales
            the whole mass distribution.
        body_dynamic: (nbodies,) int32, 0 for static bodies.
        body_kp_linear / body_kd_linear: (nbodies,) vec3d per-axis PD gains (N/m, N s/m).
        body_kp_angular / body_kd_angular: (nbodies,) float64 orientation PD gains
            (N m/rad, N m s/rad).
        body_radius: numpy (nbodies,) farthest vertex from the centre of mass (m).
        body_center_of_mass: numpy (nbodies, 3) each body frame's origin in its mesh frame (m):
            the centre of mass (a static body's: the mean of its vertices).
        body_meshes: list of (V, F) in the body frame.
        gravity: (3,) m/s^2.
        contact_stiffness: (1,) float64 mu, requires_grad.
        friction: (1,) float64 friction coefficient lambda, requires_grad when > 0 (0 disables
            friction; set requires_grad for d/d lambda at 0, one friction setup a taped step).
        friction_smoothing: slip speed v_eps (m/s) below which friction is smoothed; the
            friction force reaches lambda N once slip speeds exceed a few v_eps.
        contact: the ``ContactModel`` over all bodies.
        initial_q: numpy (nbodies, 7) initial poses.
        articulation: the ``ArticulationModel``: joints, reduced coordinates, joint gains and
            limits (every dynamic body without a joint is a free body).
    """

    body_names: list
    body_mass: wp.array
    body_unit_second_moment: wp.array
    body_dynamic: wp.array
    body_kp_linear: wp.array
    body_kd_linear: wp.array
    body_kp_angular: wp.array
    body_kd_angular: wp.array
    body_radius: np.ndarray
    body_center_of_mass: np.ndarray
    body_meshes: list
    gravity: np.ndarray
    contact_stiffness: wp.array
    friction: wp.array
    friction_smoothing: float
    contact: ContactModel
    initial_q: np.ndarray
    articulation: ArticulationModel
    device: object = field(default=None)
    # Held by a step: the contact model keeps its last evaluation (term lists, separating
    # planes) for the step's later calls, so two threads stepping one model read each other's.
    step_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)

    @property
    def num_bodies(self) -> int:
        return len(self.body_names)

    @property
    def static(self) -> np.ndarray:
        return self.body_dynamic.numpy() == 0

    @property
    def num_joint_coordinates(self) -> int:
        return self.articulation.num_coordinates

    def _coordinates(self, requires_grad: bool, values: np.ndarray | None = None) -> wp.array:
        values = self.articulation.initial_coordinates if values is None else values
        return wp.array(values, dtype=wp.float64, device=self.device, requires_grad=requires_grad)

    def state(self, *, requires_grad: bool = True) -> State:
        """A state at the initial poses, at rest."""
        requires_grad = checked_flag(requires_grad, "requires_grad")
        return State(
            body_q=wp.array(self.initial_q, dtype=wp.transformd, device=self.device, requires_grad=requires_grad),
            body_q_prev=wp.array(self.initial_q, dtype=wp.transformd, device=self.device, requires_grad=requires_grad),
            joint_q=self._coordinates(requires_grad),
            joint_q_prev=self._coordinates(requires_grad),
        )

    def control(self, *, requires_grad: bool = True) -> Control:
        """A control whose PD targets are the initial poses, the joints' default targets (their
        ``target``, else the initial coordinates) and the initial ball-joint rotations."""
        requires_grad = checked_flag(requires_grad, "requires_grad")
        return Control(
            body_target=wp.array(self.initial_q, dtype=wp.transformd, device=self.device, requires_grad=requires_grad),
            joint_target=self._coordinates(requires_grad, self.articulation.default_targets),
            ball_target=wp.array(self.articulation.initial_ball_rotations, dtype=wp.quatd, device=self.device, requires_grad=requires_grad),
        )


def shares_memory(a, b) -> bool:
    """Whether two arrays overlap in memory (anything else, or an empty array, shares none)."""

    def extent(array):
        return (array.ptr, array.ptr + array.capacity) if isinstance(array, wp.array) and array.ptr and array.capacity else None

    first, second = extent(a), extent(b)
    return first is not None and second is not None and first[0] < second[1] and second[0] < first[1]


def set_body_velocity(state: State, linear_velocity: wp.array, angular_velocity: wp.array, dt: float, *, body_names=None):
    """Set ``state.body_q_prev`` so that the state moves with the given velocities.

    A State holds velocities only as its two poses one step apart, so they mean these
    velocities for steps of ``dt`` alone: stepped with another dt they scale by dt / that dt
    (1 m/s set for 0.04 s steps moves at 4 m/s in 0.01 s steps). To change dt mid-run, set
    the velocities again for the new dt. Two poses tell turns apart only below half a turn a
    step, so |angular velocity| * dt must stay below pi (ValueError naming the body: by
    ``body_names``, e.g. ``model.body_names``, where given, else by index). A jointed body's
    velocities should be a motion its joints allow: the step keeps only the part they allow,
    weighted by the bodies' inertia, as an impulse would (a rod hinged at its end and given 2
    rad/s about its centre, no linear velocity, turns at 0.5 rad/s about the hinge), and says
    nothing: two poses a step apart cannot tell a disallowed velocity from an allowed one's
    second-order arc.

    Args:
        linear_velocity: (nbodies,) vec3d centre-of-mass velocities (m/s).
        angular_velocity: (nbodies,) vec3d angular velocities about world axes (rad/s).
        dt: the time step the state will be advanced with (s).
        body_names: the bodies' names for the errors (``model.body_names``); None names
            them by index.

    Recorded on an active ``wp.Tape``, so gradients reach the velocity arrays.
    """
    if not isinstance(state, State):
        raise ValueError(f"state: expected a State (model.state()), got {type(state).__name__}")
    for label in ("body_q", "body_q_prev"):
        poses = getattr(state, label)
        if not isinstance(poses, wp.array) or poses.dtype != wp.transformd or poses.ndim != 1:
            raise ValueError(f"state.{label}: expected a wp.array of wp.transformd, one per body (use model.state())")
    n = state.body_q.shape[0]
    if shares_memory(state.body_q_prev, state.body_q):
        # The kernel wrote the previous poses over the current ones: the body moved back by
        # a step and stayed at rest, silently.
        raise ValueError("state.body_q_prev: is the same array as state.body_q; a state needs two pose arrays (use model.state())")
    for label, arr in (("linear_velocity", linear_velocity), ("angular_velocity", angular_velocity)):
        if not isinstance(arr, wp.array) or arr.shape != (n,) or arr.dtype != wp.vec3d:
            raise ValueError(f"{label}: expected a wp.array of {n} vec3d")
    check_time_step(dt)
    if body_names is not None and (isinstance(body_names, str) or not isinstance(body_names, (list, tuple, np.ndarray)) or len(body_names) != n or not all(isinstance(name, str) for name in body_names)):
        raise ValueError(f"body_names: expected {n} names (str), one per body (model.body_names), got {body_names!r}")

    def body(b):
        return f"body {b}" if body_names is None else f"body {str(body_names[b])!r} (index {b})"

    # A turn of pi or more a step reads back as a shorter one the other way: 100 rad/s at
    # dt 0.04 s simulated as -57 rad/s.
    with np.errstate(invalid="ignore", over="ignore"):
        turn = np.linalg.norm(angular_velocity.numpy(), axis=1) * dt
    # A non-finite velocity is named below, once the previous pose it gives is read back.
    fast = np.flatnonzero(np.isfinite(turn) & (turn >= np.pi))
    if fast.size:
        b = fast[0]
        raise ValueError(
            f"angular_velocity: {body(b)} turns {turn[b]:.4g} rad in one step of {dt:g} s ({turn[b] / dt:.4g} rad/s); a state's two "
            f"poses can only represent turns below pi a step, so reduce dt below {np.pi / (turn[b] / dt):.3g} s"
        )
    inputs = [state.body_q, linear_velocity, angular_velocity, float(dt)]
    # Checked in a scratch array off the tape first: refused after writing the state, a call
    # left its non-finite poses in body_q_prev and its launch on an active wp.Tape, whose
    # backward then made the start poses' gradient NaN.
    with paused_tape():
        previous = wp.empty_like(state.body_q_prev, requires_grad=False)
        wp.launch(state_kernels.previous_pose_from_velocity_kernel, dim=n, inputs=inputs, outputs=[previous], device=state.body_q.device)
    # One read back per call (once per rollout): a NaN or overflowing velocity would reach
    # the solver only as a non-finite state_in.body_q_prev, blaming no velocity.
    bad = np.flatnonzero(~np.isfinite(previous.numpy()).all(axis=1))
    if bad.size:
        raise ValueError(
            f"linear_velocity, angular_velocity: {body(bad[0])}: its velocities give a non-finite previous pose "
            f"(linear {linear_velocity.numpy()[bad[0]].tolist()} m/s, angular {angular_velocity.numpy()[bad[0]].tolist()} rad/s)"
        )
    wp.launch(state_kernels.previous_pose_from_velocity_kernel, dim=n, inputs=inputs, outputs=[state.body_q_prev], device=state.body_q.device)
