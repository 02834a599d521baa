"""Closed-form rigid bodies hanging from a fixed pivot — the ground truth the learned
model is compared with, and the ``--true-model`` the MPC can run on.

Same :class:`~fvin_mpc.fvin.RigidBodyTerms` interface as the learned model, written on
components, so every backend (NumPy, torch, CasADi) evaluates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from . import s3
from .backend import Ops

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
    """:class:`PivotedRigidBody` evaluated with a backend's :class:`~fvin_mpc.backend.Ops`."""

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
