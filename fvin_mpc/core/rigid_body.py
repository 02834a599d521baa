"""Closed-form rigid bodies hanging from a fixed pivot — the ground truth the learned
model is compared with, and the ``--true-model`` the MPC can run on.

Same :class:`~fvin_mpc.core.fvin.RigidBodyTerms` interface as the learned model, written on
components, so every backend (NumPy, torch, CasADi) evaluates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops

Matrix = tuple[tuple[float, ...], ...]


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
    """

    inertia: Matrix
    center_of_mass: tuple[float, float, float]
    mass_gravity: float
    actuator_axes: Matrix
    damping: float = 0.0
    constant_inertia: bool = field(default=True, init=False)

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

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        zero = 0.0 * q[0]
        return tuple(tuple(entry + zero for entry in row) for row in self.body.inertia)  # type: ignore[return-value]

    def potential(self, q: s3.Quat) -> Any:
        """``U = m g (z_com(q) − z_com(identity))``: zero when hanging at rest."""
        c = self.body.center_of_mass
        height = s3.dot(s3.rotation_matrix(q)[2], c)
        return self.body.mass_gravity * (height - c[2])

    def potential_gradient(self, q: s3.Quat) -> s3.Quat:
        w, x, y, z = q
        cx, cy, cz = self.body.center_of_mass
        mg = self.body.mass_gravity
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
        if self.body.damping == 0.0:
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

    Read off the model, not the scene files: mass, centre of mass and inertia (moved to the
    joint's anchor by the parallel-axis theorem), gravity, joint damping, and each actuator's
    torque axis (its ``gear``). For a hinge only the inertia about the hinge axis is physical;
    the body gets ``J = I_axis·I`` (isotropic, as :data:`PENDULUM`) so the unactuated axes stay
    well posed. Requires the body to hang from the world on one hinge or ball joint, with the
    world frame aligned to the body's rest orientation (true of the built-in scenes).

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
    anchor = np.asarray(model.jnt_pos[joint], dtype=float)
    com = np.asarray(model.body_ipos[body_id], dtype=float) - anchor
    mass = float(model.body_mass[body_id])
    frame = np.zeros(9)
    mujoco.mju_quat2Mat(frame, np.asarray(model.body_iquat[body_id], dtype=float))
    frame = frame.reshape(3, 3)
    inertia = frame @ np.diag(model.body_inertia[body_id]) @ frame.T + mass * (
        com @ com * np.eye(3) - np.outer(com, com)
    )
    dof = int(model.jnt_dofadr[joint])
    actuators = [a for a in range(model.nu) if model.actuator_trnid[a, 0] == joint]
    if int(model.jnt_type[joint]) == hinge:
        axis = np.asarray(model.jnt_axis[joint], dtype=float)
        inertia = float(axis @ inertia @ axis) * np.eye(3)
        axes = np.array([model.actuator_gear[a, 0] * axis for a in actuators]).T
        damping = float(model.dof_damping[dof])
    else:
        axes = np.array([model.actuator_gear[a, :3] for a in actuators]).T
        dampings = np.asarray(model.dof_damping[dof : dof + 3], dtype=float)
        if np.ptp(dampings) > 0:
            raise ValueError("a ball joint with unequal damping per axis has no scalar damping")
        damping = float(dampings[0])
    friction_on = not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS
    joint_dofs = slice(dof, dof + (1 if int(model.jnt_type[joint]) == hinge else 3))
    if friction_on and np.any(model.dof_frictionloss[joint_dofs] > 0):
        raise ValueError(
            f"body {body!r}'s joint has dry friction (frictionloss), which a PivotedRigidBody cannot represent"
        )
    gravity = np.asarray(model.opt.gravity, dtype=float)
    if gravity[0] != 0.0 or gravity[1] != 0.0:
        raise ValueError(f"gravity must point along −z, got {gravity}")
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY:
        gravity = np.zeros(3)
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_DAMPER:
        damping = 0.0
    as_tuple = lambda matrix: tuple(tuple(float(x) for x in row) for row in matrix)  # noqa: E731
    return PivotedRigidBody(inertia=as_tuple(inertia), center_of_mass=tuple(float(c) for c in com),
                            mass_gravity=-mass * float(gravity[2]), actuator_axes=as_tuple(axes), damping=damping)
