"""Closed-form rigid bodies hanging from a fixed pivot — the ground truth the learned
model is compared with, and the ``--true-model`` the MPC can run on.

Same :class:`~fvin_mpc.core.fvin.RigidBodyTerms` interface as the learned model, written on
components, so every backend (NumPy, torch, CasADi) evaluates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops

Matrix = tuple[tuple[float, ...], ...]

#: Straight up: heights measured along world z (gravity along −z).
UP = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class PivotedRigidBody:
    """A rigid body on a fixed pivot under uniform gravity along −z.

    Attributes:
        inertia: 3×3 inertia about the pivot in the body frame (kg·m²); ``J`` of the model.
        center_of_mass: position of the centre of mass in the body frame (m).
        mass_gravity: ``m·g`` (N).
        actuator_axes: 3×m matrix; column ``j`` is the body-frame torque (N·m) per unit
            of control ``u_j``. The model's gain is twice it (``DESIGN.md``, factor of two).
        damping: viscous joint damping (N·m·s/rad), torque ``−damping·ω``.
        vertical: the world direction (unit) height is measured along: ``U = m g (R c − c)·vertical``.
            Straight up (``(0, 0, 1)``, gravity along −z) unless the body is a hinge whose axis is
            tilted from horizontal: :func:`from_mujoco` then takes the part of "up" perpendicular to
            the axis (and ``mass_gravity`` scaled by its length, ``center_of_mass`` the part
            perpendicular to the axis), which gives the same potential along the hinge's motion
            and a gravity torque along the axis only — what the hinge lets act.
        hinge_axis: a hinge's axis in the body frame (unit), on which the step stays
            (:func:`fvin_mpc.core.fvin.hinge_step`): a measured rate across the hinge — sensor noise
            the hinge cannot have — then moves nothing in a plan. ``None`` for a ball joint.
    """

    inertia: Matrix
    center_of_mass: tuple[float, float, float]
    mass_gravity: float
    actuator_axes: Matrix
    damping: float = 0.0
    constant_inertia: bool = field(default=True, init=False)
    vertical: tuple[float, float, float] = (0.0, 0.0, 1.0)
    hinge_axis: tuple[float, float, float] | None = None

    #: The fields that are model parameters of an export (fvin_mpc.core.model_parameters).
    PARAMETERS: ClassVar[tuple[str, ...]] = ("inertia", "center_of_mass", "mass_gravity", "damping")

    @property
    def control_dim(self) -> int:
        return len(self.actuator_axes[0])

    def terms(self, ops: Ops) -> "PivotedRigidBodyTerms":
        return PivotedRigidBodyTerms(self, ops)


class PivotedRigidBodyTerms:
    """:class:`PivotedRigidBody` evaluated with a backend's :class:`~fvin_mpc.core.backend.Ops`."""

    constant_inertia = True

    def __init__(self, body: PivotedRigidBody, ops: Ops) -> None:
        self.body = body
        self.ops = ops
        self.control_dim = body.control_dim
        self.hinge_axis = body.hinge_axis

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        zero = 0.0 * q[0]
        return tuple(tuple(entry + zero for entry in row) for row in self.body.inertia)  # type: ignore[return-value]

    def potential(self, q: s3.Quat) -> Any:
        """``U = m g (z_com(q) − z_com(identity))``: zero when hanging at rest (heights along
        :attr:`PivotedRigidBody.vertical`)."""
        c = self.body.center_of_mass
        if self.body.vertical != UP:
            r = s3.rotation_matrix(q)
            v = self.body.vertical
            height = sum(v[i] * s3.dot(r[i], c) for i in range(3) if v[i] != 0.0)
            return self.body.mass_gravity * (height - s3.dot(v, c))
        height = s3.dot(s3.rotation_matrix(q)[2], c)
        return self.body.mass_gravity * (height - c[2])

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        w, x, y, z = q
        cx, cy, cz = self.body.center_of_mass
        mg = self.body.mass_gravity
        if self.body.vertical != UP:
            # ∂/∂q of row i of R(q) (s3.rotation_matrix) times c, weighted by vertical_i.
            rows = (
                (w * cx - z * cy + y * cz, x * cx + y * cy + z * cz,
                 -y * cx + x * cy + w * cz, -z * cx - w * cy + x * cz),
                (z * cx + w * cy - x * cz, y * cx - x * cy - w * cz,
                 x * cx + y * cy + z * cz, w * cx - z * cy + y * cz),
                (-y * cx + x * cy + w * cz, z * cx + w * cy - x * cz,
                 -w * cx + z * cy - y * cz, x * cx + y * cy + z * cz),
            )
            v = self.body.vertical
            used = [i for i in range(3) if v[i] != 0.0]
            return tuple(mg * 2.0 * sum(v[i] * rows[i][k] for i in used) for k in range(4))  # type: ignore[return-value]
        return (
            mg * 2.0 * (-y * cx + x * cy + w * cz),
            mg * 2.0 * (z * cx + w * cy - x * cz),
            mg * 2.0 * (-w * cx + z * cy - y * cz),
            mg * 2.0 * (x * cx + y * cy + z * cz),
        )

    def control_gain(self, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        zero = 0.0 * q[0]
        return tuple(tuple(2.0 * entry + zero for entry in row) for row in self.body.actuator_axes)

    def dissipation(self, q: s3.Quat) -> s3.Mat3 | None:
        if isinstance(self.body.damping, (int, float)) and self.body.damping == 0.0:  # a symbol: a parameter
            return None
        zero = 0.0 * q[0]
        d = 2.0 * self.body.damping
        return ((d + zero, zero, zero), (zero, d + zero, zero), (zero, zero, d + zero))


#: Gymnasium's Pendulum-v1 physics as a rigid body: a uniform rod (m = 1 kg, l = 1 m,
#: g = 10 m/s²) about the y axis, ``θ̈ = −15 sin θ + 3τ``. Only rotation about y is
#: physical; ``J = I/3`` (isotropic) keeps the other axes well posed (``DESIGN.md``).
PENDULUM = PivotedRigidBody(
    inertia=((1 / 3, 0.0, 0.0), (0.0, 1 / 3, 0.0), (0.0, 0.0, 1 / 3)),
    center_of_mass=(0.0, 0.0, -0.5),
    mass_gravity=10.0,
    actuator_axes=((0.0,), (1.0,), (0.0,)),
)

#: The ``pendulum_damped`` scene: the same rod with joint damping 0.1 N·m·s/rad.
PENDULUM_DAMPED = PivotedRigidBody(
    inertia=PENDULUM.inertia,
    center_of_mass=PENDULUM.center_of_mass,
    mass_gravity=PENDULUM.mass_gravity,
    actuator_axes=PENDULUM.actuator_axes,
    damping=0.1,
)


def from_mujoco(model: Any, body: str) -> PivotedRigidBody:
    """The closed-form :class:`PivotedRigidBody` of ``body`` in a compiled MuJoCo model.

    Read off the model, not the scene files: the mass, centre of mass and inertia of the body's
    *subtree* (the body and every child body rigidly attached to it — a child with a joint of its
    own is refused), moved to the joint's anchor (parallel axes), the joint's ``armature`` (added
    to the inertia about the hinge axis, or to each axis of a ball joint, as MuJoCo adds it to the
    joint-space mass matrix), gravity, joint damping, and each actuator's torque axis (its
    ``gear``). For a hinge only the inertia about the hinge axis is physical; the body gets
    ``J = (I_axis + armature)·I`` (isotropic, as :data:`PENDULUM`) so the unactuated axes stay
    well posed, and, if the axis is tilted from horizontal or the centre of mass lies off the
    plane perpendicular to the axis, the potential keeps only what the hinge lets act
    (:attr:`PivotedRigidBody.vertical`). Body-frame quantities are in the body's frame (``xquat``,
    the state's orientation); the potential is zero at the identity orientation.

    A single body without armature (the built-in scenes) is read exactly as before: the same
    floating-point operations, so the same numbers to the bit.

    Args:
        model: a ``mujoco.MjModel``.
        body: the body's name.
    """
    import mujoco
    import numpy as np

    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        raise ValueError(f"no body named {body!r} in the model")
    joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] == body_id]
    hinge, ball = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_BALL)
    if len(joints) != 1 or int(model.jnt_type[joints[0]]) not in (hinge, ball):
        raise ValueError(f"body {body!r} must have exactly one hinge or ball joint")
    joint = joints[0]
    is_hinge = int(model.jnt_type[joint]) == hinge
    dof = int(model.jnt_dofadr[joint])
    joint_dofs = slice(dof, dof + (1 if is_hinge else 3))
    children = _subtree(model, body_id)[1:]
    jointed = [b for b in children if model.body_jntnum[b] > 0]
    if jointed:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in jointed]
        raise ValueError(f"body {body!r} has child bodies with joints of their own ({names}): a chain of jointed "
                         "bodies is not one rigid body")
    armature = np.asarray(model.dof_armature[joint_dofs], dtype=float)
    if children:
        mass, com, inertia = _subtree_inertia(model, body_id, joint)
    else:
        anchor = np.asarray(model.jnt_pos[joint], dtype=float)
        com = np.asarray(model.body_ipos[body_id], dtype=float) - anchor
        mass = float(model.body_mass[body_id])
        frame = np.zeros(9)
        mujoco.mju_quat2Mat(frame, np.asarray(model.body_iquat[body_id], dtype=float))
        frame = frame.reshape(3, 3)
        inertia = frame @ np.diag(model.body_inertia[body_id]) @ frame.T + mass * (
            com @ com * np.eye(3) - np.outer(com, com))
    actuators = [a for a in range(model.nu) if model.actuator_trnid[a, 0] == joint]
    gravity = np.asarray(model.opt.gravity, dtype=float)
    if gravity[0] != 0.0 or gravity[1] != 0.0:
        raise ValueError(f"gravity must point along −z, got {gravity}")
    vertical = UP
    if is_hinge:
        axis = np.asarray(model.jnt_axis[joint], dtype=float)
        inertia = float(axis @ inertia @ axis) * np.eye(3)
        if np.any(armature != 0.0):
            inertia = inertia + float(armature[0]) * np.eye(3)
        axes = np.array([model.actuator_gear[a, 0] * axis for a in actuators]).T
        damping = float(model.dof_damping[dof])
        along = float(com @ axis)
        world_axis = _world_hinge_axis(model, body_id, joint)
        if along != 0.0 or world_axis[2] != 0.0:
            # Keep what the hinge lets act: the centre of mass's part perpendicular to the axis, and
            # "up"'s part perpendicular to the (fixed) world axis. Along the hinge's motion this
            # changes U by a constant; the gravity torque it gives is along the axis.
            com = com - along * axis
            up = np.array(UP) - world_axis[2] * world_axis
            scale = float(np.linalg.norm(up))
            if scale < 1e-12:
                raise ValueError(f"body {body!r}'s hinge axis is vertical: gravity exerts no torque about it")
            gravity = gravity * scale
            vertical = tuple(float(v) for v in up / scale)
    else:
        axes = np.array([model.actuator_gear[a, :3] for a in actuators]).T
        dampings = np.asarray(model.dof_damping[dof : dof + 3], dtype=float)
        if np.ptp(dampings) > 0:
            raise ValueError("a ball joint with unequal damping per axis has no scalar damping")
        damping = float(dampings[0])
        if np.any(armature != 0.0):
            inertia = inertia + np.diag(armature)
    friction_on = not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS
    if friction_on and np.any(model.dof_frictionloss[joint_dofs] > 0):
        raise ValueError(f"body {body!r}'s joint has dry friction (frictionloss), which a PivotedRigidBody "
                         "cannot represent")
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY:
        gravity = np.zeros(3)
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_DAMPER:
        damping = 0.0
    as_tuple = lambda matrix: tuple(tuple(float(x) for x in row) for row in matrix)  # noqa: E731
    return PivotedRigidBody(inertia=as_tuple(inertia), center_of_mass=tuple(float(c) for c in com),
                            mass_gravity=-mass * float(gravity[2]), actuator_axes=as_tuple(axes), damping=damping,
                            vertical=vertical,
                            hinge_axis=tuple(float(a) for a in axis / np.linalg.norm(axis)) if is_hinge else None)


def _subtree(model: Any, body_id: int) -> list[int]:
    """``body_id`` and every body below it (MuJoCo numbers a parent before its children)."""
    members = [body_id]
    for b in range(body_id + 1, model.nbody):
        if int(model.body_parentid[b]) in members:
            members.append(b)
    return members


def _kinematics(model: Any) -> Any:
    """MjData at ``qpos0`` with positions, orientations and subtree centres of mass computed."""
    import mujoco

    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    return data


def _world_hinge_axis(model: Any, body_id: int, joint: int) -> Any:
    """The hinge's axis in the world (fixed: the body hangs from the world), unit."""
    import numpy as np

    data = _kinematics(model)
    axis = np.asarray(data.xaxis[joint], dtype=float)
    return axis / np.linalg.norm(axis)


def _subtree_inertia(model: Any, body_id: int, joint: int) -> tuple[float, Any, Any]:
    """``(mass, centre of mass, inertia about the joint's anchor)`` of the subtree of ``body_id``, the last
    two in the body's frame: each body's principal inertia turned to the world by its inertial frame
    (``ximat``), moved to the anchor by parallel axes, summed, and turned into the body's frame."""
    import numpy as np

    data = _kinematics(model)
    anchor = np.asarray(data.xanchor[joint], dtype=float)
    frame = np.asarray(data.xmat[body_id], dtype=float).reshape(3, 3)
    world = np.zeros((3, 3))
    for b in _subtree(model, body_id):
        m = float(model.body_mass[b])
        orientation = np.asarray(data.ximat[b], dtype=float).reshape(3, 3)
        d = np.asarray(data.xipos[b], dtype=float) - anchor
        world += orientation @ np.diag(model.body_inertia[b]) @ orientation.T + m * (d @ d * np.eye(3) - np.outer(d, d))
    mass = float(model.body_subtreemass[body_id])
    com = frame.T @ (np.asarray(data.subtree_com[body_id], dtype=float) - anchor)
    return mass, com, frame.T @ world @ frame
