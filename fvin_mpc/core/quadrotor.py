"""A closed-form free rigid body with rotors (a quadrotor) in R³ × S³ — the ground truth for the
combined step (:mod:`fvin_mpc.core.fvin_r3s3`), on components for every backend.

Physics (world z up, gravity ``−g e_z``; body frame at the centre of mass, which need not be the
origin of the MJCF's body: :func:`from_mujoco` measures the sites from it):

* actuator ``i`` at body site ``rᵢ`` pushes with ``aᵢ uᵢ`` (N), ``aᵢ`` its body-frame force per unit
  control — ``e_z`` for a rotor pushing along the body z axis (the default), a tilted axis for a
  tilted rotor, zero for a pure body-moment actuator: ``F_x = R(q) Σ aᵢ uᵢ`` (world frame);
* body torque ``τ = B u`` with column ``i`` of ``B`` equal to ``rᵢ × aᵢ + mᵢ``, ``mᵢ`` its pure
  torque per unit control — by default ``κ sᵢ e_z``, the yaw reaction of a rotor spinning in
  direction ``sᵢ = ±1``;
  the model's gain is ``g = 2 B`` (DESIGN.md, factor of two);
* ``U(x, q) = m g x_z + ½ k |x + R(q) a − b|²``: gravity, plus an optional tether — a spring of
  stiffness ``k`` from the body site ``a`` to the world anchor ``b`` (``k = 0``: a free quadrotor,
  ``U`` independent of ``q``). The tether is what couples ``x`` and ``q`` through ``U``.

Newton–Euler: ``m v̇ = −∇ₓU + F_x``, ``q̇ = ½ q ⊗ (0, ω)``,
``J ω̇ + ω × Jω = B u + a × Rᵀ(−k d)`` with ``d = x + R(q) a − b``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops

Matrix = tuple[tuple[float, ...], ...]
Vector = tuple[float, float, float]


@dataclass(frozen=True)
class Quadrotor:
    """Rotor craft parameters (SI units).

    Attributes:
        mass: ``m`` (kg); ``M = m I``.
        inertia: 3×3 body inertia about the centre of mass (kg·m²), ``J``.
        rotor_sites: body-frame positions ``rᵢ`` of the rotors (m), one per control.
        rotor_spins: ``sᵢ = ±1``, the sign of each rotor's yaw reaction.
        yaw_coefficient: ``κ`` (m): yaw torque per newton of thrust.
        gravity: ``g`` (m/s²), along −z.
        tether_stiffness: ``k`` (N/m); 0 for none.
        tether_site: ``a``, body frame (m).
        tether_anchor: ``b``, world frame (m).
        thrust_low, thrust_high: per-rotor thrust bounds (N); ``None``: unbounded.
        thrust_axes: ``aᵢ``, body-frame force per unit control; ``None``: ``e_z`` for every rotor.
        rotor_moments: ``mᵢ``, body-frame pure torque per unit control; ``None``: ``κ sᵢ e_z``.
        unmodelled: what the description simulates that this closed form leaves out (e.g. fluid drag),
            one phrase each; empty when it represents the description fully.
    """

    mass: float
    inertia: Matrix
    rotor_sites: tuple[Vector, ...]
    rotor_spins: tuple[float, ...]
    yaw_coefficient: float
    gravity: float = 9.81
    tether_stiffness: float = 0.0
    tether_site: Vector = (0.0, 0.0, 0.0)
    tether_anchor: Vector = (0.0, 0.0, 0.0)
    thrust_low: tuple[float, ...] | None = None
    thrust_high: tuple[float, ...] | None = None
    thrust_axes: tuple[Vector, ...] | None = None
    rotor_moments: tuple[Vector, ...] | None = None
    unmodelled: tuple[str, ...] = ()
    constant_inertia: bool = field(default=True, init=False)

    #: The fields that are model parameters of an export (fvin_mpc.core.model_parameters).
    PARAMETERS: ClassVar[tuple[str, ...]] = ("mass", "inertia", "gravity")

    def __post_init__(self) -> None:
        if len(self.rotor_sites) != len(self.rotor_spins):
            raise ValueError("one spin per rotor site")
        for bounds in (self.thrust_low, self.thrust_high, self.thrust_axes, self.rotor_moments):
            if bounds is not None and len(bounds) != len(self.rotor_sites):
                raise ValueError("one thrust bound, axis and moment per rotor site")

    @property
    def force_map(self) -> Matrix:
        """``A`` (3×m): body-frame force per unit control, the ``aᵢ`` as columns."""
        axes = self.thrust_axes or ((0.0, 0.0, 1.0),) * self.control_dim
        return tuple(tuple(float(a[i]) for a in axes) for i in range(3))

    @property
    def control_dim(self) -> int:
        return len(self.rotor_sites)

    @property
    def torque_map(self) -> Matrix:
        """``B`` (3×m): body torque about the centre of mass per unit control, ``rᵢ × aᵢ + mᵢ``."""
        axes = self.thrust_axes or ((0.0, 0.0, 1.0),) * self.control_dim
        moments = self.rotor_moments or tuple((0.0, 0.0, self.yaw_coefficient * s) for s in self.rotor_spins)
        columns = [s3.add(s3.cross(r, a), m) for r, a, m in zip(self.rotor_sites, axes, moments)]
        return tuple(tuple(float(c[i]) for c in columns) for i in range(3))

    @property
    def hover_thrust(self) -> float:
        """Per-rotor thrust that holds a symmetric untethered craft level at rest: ``m g / n``
        (:attr:`hover_controls` for any craft)."""
        return self.mass * self.gravity / self.control_dim

    @property
    def hover_controls(self) -> tuple[float, ...]:
        """The smallest controls (least squares) whose force and torque hold the untethered craft
        level at rest: ``A u = m g e_z``, ``B u = 0``."""
        import numpy as np

        wrench = np.vstack([np.array(self.force_map), np.array(self.torque_map)])
        wanted = np.array([0.0, 0.0, self.mass * self.gravity, 0.0, 0.0, 0.0])
        return tuple(float(u) for u in np.linalg.lstsq(wrench, wanted, rcond=None)[0])

    def terms(self, ops: Ops) -> "QuadrotorTerms":
        return QuadrotorTerms(self, ops)


class QuadrotorTerms:
    """:class:`Quadrotor` as :class:`~fvin_mpc.core.fvin_r3s3.CombinedTerms` on a backend."""

    constant_inertia = True

    def __init__(self, body: Quadrotor, ops: Ops) -> None:
        self.body, self.ops = body, ops
        self.control_dim = body.control_dim
        self._gain = tuple(tuple(2.0 * b for b in row) for row in body.torque_map)

    def mass_matrix(self) -> s3.Mat3:
        m = self.body.mass
        return ((m, 0.0, 0.0), (0.0, m, 0.0), (0.0, 0.0, m))

    def inertia(self, q: s3.Quat) -> s3.Mat3:
        zero = 0.0 * q[0]
        return tuple(tuple(entry + zero for entry in row) for row in self.body.inertia)  # type: ignore[return-value]

    def _tether(self, x: s3.Vec3, q: s3.Quat) -> s3.Vec3:
        """``d = x + R(q) a − b``, with ``R(q) a = (w² − v·v) a + 2 (v·a) v + 2 w v × a``."""
        a, b = self.body.tether_site, self.body.tether_anchor
        w, v = q[0], s3.imaginary(q)
        va, vxa = s3.dot(v, a), s3.cross(v, a)
        ww_vv = w * w - s3.dot(v, v)
        return tuple(x[i] + ww_vv * a[i] + 2.0 * va * v[i] + 2.0 * w * vxa[i] - b[i] for i in range(3))  # type: ignore[return-value]

    def potential(self, x: s3.Vec3, q: s3.Quat) -> Any:
        body = self.body
        u = body.mass * body.gravity * x[2] + 0.0 * q[0]
        if body.tether_stiffness:
            d = self._tether(x, q)
            u = u + 0.5 * body.tether_stiffness * s3.dot(d, d)
        return u

    def potential_gradient_x(self, x: s3.Vec3, q: s3.Quat) -> s3.Vec3:
        body = self.body
        zero = 0.0 * (x[0] + q[0])
        gravity = (zero, zero, body.mass * body.gravity + zero)
        if not body.tether_stiffness:
            return gravity  # type: ignore[return-value]
        return s3.add(gravity, s3.scale(body.tether_stiffness, self._tether(x, q)))  # type: ignore[return-value]

    def potential_gradient_q(self, x: s3.Vec3, q: s3.Quat) -> s3.Quat:
        """Euclidean ``∂U/∂q`` of the homogeneous ``R(q) a`` above (``U`` does not see ``|q|``'s
        extension off S³ in the step: only ``H(q)∇_qU``, its tangential part, enters)."""
        body = self.body
        zero = 0.0 * (x[0] + q[0])
        if not body.tether_stiffness:
            return (zero, zero, zero, zero)
        k, a = body.tether_stiffness, body.tether_site
        d = self._tether(x, q)
        w, v = q[0], s3.imaginary(q)
        ad, vd, va = s3.dot(a, d), s3.dot(v, d), s3.dot(v, a)
        axd = s3.cross(a, d)
        d_w = 2.0 * w * ad + 2.0 * s3.dot(d, s3.cross(v, a))
        d_v = tuple(-2.0 * ad * v[i] + 2.0 * vd * a[i] + 2.0 * va * d[i] + 2.0 * w * axd[i] for i in range(3))
        return (k * d_w, k * d_v[0], k * d_v[1], k * d_v[2])

    def translational_force(self, x: s3.Vec3, q: s3.Quat, u: tuple[Any, ...]) -> s3.Vec3:
        """``R(q) A u``; for rotors along body z, the third column of ``R(q)`` times the total thrust."""
        w, qx, qy, qz = q
        if self.body.thrust_axes is None:
            total = u[0]
            for u_i in u[1:]:
                total = total + u_i
            return (2.0 * (qx * qz + w * qy) * total, 2.0 * (qy * qz - w * qx) * total,
                    (w * w - qx * qx - qy * qy + qz * qz) * total)
        force_map = self.body.force_map
        body_force = []
        for row in force_map:
            entry = 0.0 * u[0]
            for a_i, u_i in zip(row, u):
                if a_i:
                    entry = entry + a_i * u_i
            body_force.append(entry)
        return s3.matvec(s3.rotation_matrix(q), body_force)  # type: ignore[return-value]

    def control_gain(self, x: s3.Vec3, q: s3.Quat) -> tuple[tuple[Any, ...], ...]:
        zero = 0.0 * q[0]
        return tuple(tuple(entry + zero for entry in row) for row in self._gain)


def x_configuration(mass: float, inertia: Matrix, arm: float, yaw_coefficient: float, **kwargs: Any) -> Quadrotor:
    """Four rotors in an ×: sites ``arm·(±1, ±1, 0)/√2``, spins alternating around the frame."""
    c = arm / math.sqrt(2.0)
    sites = ((c, c, 0.0), (-c, c, 0.0), (-c, -c, 0.0), (c, -c, 0.0))
    return Quadrotor(mass=mass, inertia=inertia, rotor_sites=sites, rotor_spins=(1.0, -1.0, 1.0, -1.0),
                     yaw_coefficient=yaw_coefficient, **kwargs)


#: A small quadrotor (≈ 0.5 kg, 0.17 m arms), slightly asymmetric inertia so a tumble is not trivial.
QUADROTOR = x_configuration(mass=0.5, inertia=((2.3e-3, 0.0, 0.0), (0.0, 2.9e-3, 0.0), (0.0, 0.0, 4.6e-3)),
                            arm=0.17, yaw_coefficient=0.016)


def from_mujoco(model: Any, body: str) -> Quadrotor:
    """The closed-form :class:`Quadrotor` of ``body`` in a compiled MuJoCo model (as
    :func:`fvin_mpc.core.rigid_body.from_mujoco` for pivoted bodies).

    Read off the model, not the scene file: mass; inertia about the centre of mass in the body frame
    (rotated from the principal frame ``body_iquat``); the centre of mass ``c`` (``body_ipos``), from
    which every site is measured; gravity (zero when the model's flags disable it); one control per
    actuator, each a site transmission on ``body`` (no ``refsite``) with a fixed gain ``k`` and no
    bias: its gear ``(f, t)`` in the site's frame gives the body-frame force ``aᵢ = k R_site f`` at the
    site ``rᵢ − c`` and the pure torque ``mᵢ = k R_site t`` — rotors along body z with a yaw gear,
    tilted rotors, a thrust site beside three body-moment actuators alike; the bounds (``ctrlrange``
    when limited and clamping is not disabled). What the model simulates beyond this — fluid drag
    (``density``, ``viscosity``, ``wind``) — is named in ``unmodelled``, not represented.

    Requirements (``ValueError`` otherwise): ``body`` has one free joint, the model's only degree of
    freedom; every actuator is as above.

    Args:
        model: a ``mujoco.MjModel``.
        body: the craft's body name.
    """
    import mujoco
    import numpy as np

    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        raise ValueError(f"no body named {body!r} in the model")
    free = int(mujoco.mjtJoint.mjJNT_FREE)
    if model.body_jntnum[body_id] != 1 or int(model.jnt_type[model.body_jntadr[body_id]]) != free or model.nv != 6:
        raise ValueError(f"body {body!r} must have one free joint, the model's only degree of freedom")
    centre = np.asarray(model.body_ipos[body_id], dtype=float)
    mass = float(model.body_subtreemass[body_id])
    frame = np.zeros(9)
    mujoco.mju_quat2Mat(frame, np.asarray(model.body_iquat[body_id], dtype=float))
    frame = frame.reshape(3, 3)
    inertia = frame @ np.diag(model.body_inertia[body_id]) @ frame.T
    gravity = np.asarray(model.opt.gravity, dtype=float)
    if gravity[0] != 0.0 or gravity[1] != 0.0:
        raise ValueError(f"gravity must point along −z, got {gravity}")
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_GRAVITY:
        gravity = np.zeros(3)
    sites, axes, moments = [], [], []
    for a in range(model.nu):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f"#{a}"
        site = int(model.actuator_trnid[a, 0])
        if (model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_SITE or model.site_bodyid[site] != body_id
                or model.actuator_trnid[a, 1] >= 0):
            raise ValueError(f"actuator {name!r} must act through a site of body {body!r} (no refsite)")
        plain = (model.actuator_dyntype[a] == mujoco.mjtDyn.mjDYN_NONE
                 and model.actuator_gaintype[a] == mujoco.mjtGain.mjGAIN_FIXED
                 and not np.any(model.actuator_biasprm[a])
                 and model.actuator_biastype[a] == mujoco.mjtBias.mjBIAS_NONE)
        if not plain:
            raise ValueError(f"actuator {name!r} must be a fixed gain (force = gain·ctrl, no bias, no dynamics)")
        site_frame = np.zeros(9)
        mujoco.mju_quat2Mat(site_frame, np.asarray(model.site_quat[site], dtype=float))
        site_frame = float(model.actuator_gainprm[a, 0]) * site_frame.reshape(3, 3)
        sites.append(tuple(float(c) for c in model.site_pos[site] - centre))
        axes.append(tuple(float(c) for c in site_frame @ model.actuator_gear[a, :3]))
        moments.append(tuple(float(c) for c in site_frame @ model.actuator_gear[a, 3:]))
    unmodelled = []
    if model.opt.density > 0.0 or model.opt.viscosity > 0.0 or np.any(model.opt.wind != 0.0):
        unmodelled.append(f"fluid drag (density {model.opt.density:g} kg/m³, viscosity {model.opt.viscosity:g} Pa·s, "
                          f"wind {tuple(float(w) for w in model.opt.wind)} m/s)")
    clamped = not model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL
    limited = clamped and bool(np.all(model.actuator_ctrllimited))
    as_tuple = lambda matrix: tuple(tuple(float(x) for x in row) for row in matrix)  # noqa: E731
    # the rotor description of the common case (every gear along body z with a yaw reaction of one κ)
    # keeps the closed form's rotor parameters; anything else is stated by its axes and moments
    yaw = [m[2] for m in moments]
    rotors = (all(np.allclose(a, (0.0, 0.0, 1.0), atol=1e-12) for a in axes)
              and all(abs(m[0]) < 1e-12 and abs(m[1]) < 1e-12 for m in moments)
              and np.ptp(np.abs(yaw)) <= 1e-12 * max(max(np.abs(yaw), default=0.0), 1.0))
    return Quadrotor(mass=mass, inertia=as_tuple(inertia), rotor_sites=tuple(sites),
                     rotor_spins=tuple(1.0 if y >= 0.0 else -1.0 for y in yaw),
                     yaw_coefficient=abs(float(yaw[0])) if rotors and yaw else 0.0, gravity=-float(gravity[2]),
                     thrust_low=tuple(float(v) for v in model.actuator_ctrlrange[:, 0]) if limited else None,
                     thrust_high=tuple(float(v) for v in model.actuator_ctrlrange[:, 1]) if limited else None,
                     thrust_axes=None if rotors else tuple(axes), rotor_moments=None if rotors else tuple(moments),
                     unmodelled=tuple(unmodelled))


@dataclass(frozen=True)
class GeometricController:
    """A stabilizing closed-form controller for a :class:`Quadrotor` (NumPy): position PD with gravity
    compensation and attitude tracking on SO(3) (Lee, Leok & McClamroch 2010), then the thrusts that
    give the commanded total thrust and body torque, clipped to the bounds. Used to collect data that
    cover the flight envelope without leaving it; not the MPC.

    Gains: ``position_gain`` and ``velocity_gain`` per kg (``k_x = m·position_gain``), the lateral
    acceleration demand capped at ``max_lateral_acceleration`` g, ``attitude_frequency``
    ``ω_R`` and ``attitude_damping`` ``ζ`` (``k_R = ω_R² J``, ``k_ω = 2ζω_R J``). The collective thrust is
    at least ``min_thrust_fraction`` of the weight, so that an upside-down craft keeps torque authority.
    """

    body: Quadrotor
    position_gain: float = 4.0
    velocity_gain: float = 3.0
    max_lateral_acceleration: float = 0.6
    attitude_frequency: float = 15.0
    attitude_damping: float = 1.0
    min_thrust_fraction: float = 1.0

    def allocation(self) -> Any:
        """``A`` (4×m): ``[thrust along body z; τ] = A u`` (for rotors along body z the first row is ones)."""
        import numpy as np

        return np.vstack([np.array(self.body.force_map)[2], np.array(self.body.torque_map)])

    def __call__(self, state: Any, target_position: Any, target_velocity: Any = (0.0, 0.0, 0.0),
                 target_yaw: float = 0.0) -> Any:
        """Thrusts ``(m,)`` for the state ``(x, q, v, ω)`` ``(13,)`` towards the target."""
        import numpy as np

        body = self.body
        m, inertia = body.mass, np.array(body.inertia)
        x, q, v, omega = state[:3], state[3:7], state[7:10], state[10:13]
        rotation = np.array(s3.rotation_matrix(tuple(q / np.linalg.norm(q))), dtype=float)
        acceleration = (-self.position_gain * (x - np.asarray(target_position))
                        - self.velocity_gain * (v - np.asarray(target_velocity)))
        # Height first: the lateral demand is capped so that a tilted craft never trades lift for it.
        lateral = np.linalg.norm(acceleration[:2])
        if lateral > self.max_lateral_acceleration * body.gravity:
            acceleration[:2] *= self.max_lateral_acceleration * body.gravity / lateral
        force = m * (acceleration + np.array([0.0, 0.0, body.gravity]))
        b3 = force / max(np.linalg.norm(force), 1e-9)
        heading = np.array([math.cos(target_yaw), math.sin(target_yaw), 0.0])
        b2 = np.cross(b3, heading)
        b2 = b2 / max(np.linalg.norm(b2), 1e-9)
        desired = np.column_stack([np.cross(b2, b3), b2, b3])
        error = desired.T @ rotation - rotation.T @ desired
        e_rotation = 0.5 * np.array([error[2, 1], error[0, 2], error[1, 0]])
        k_rotation = self.attitude_frequency**2 * inertia
        k_omega = 2.0 * self.attitude_damping * self.attitude_frequency * inertia
        torque = -k_rotation @ e_rotation - k_omega @ omega + np.cross(omega, inertia @ omega)
        thrust = max(float(force @ rotation[:, 2]), self.min_thrust_fraction * m * body.gravity)
        low = -np.inf if body.thrust_low is None else np.array(body.thrust_low)
        high = np.inf if body.thrust_high is None else np.array(body.thrust_high)
        # the least-squares inverse: square for four rotors, the smallest controls for more
        inverse = np.linalg.pinv(self.allocation())
        # Yaw authority is small (κ ≪ arm): the yaw torque is limited to what the rotors can give on
        # top of the thrust and the roll and pitch torques; if even those saturate, the thrust moves
        # towards mid-range, then roll and pitch are scaled down together (their direction kept) —
        # clipping thrusts instead would turn a righting torque into a yaw one.
        if np.all(np.isfinite(high)):
            thrust = min(thrust, 0.95 * float(np.sum(high)))
        middle = 0.5 * float(np.sum(low + high)) if np.all(np.isfinite(low + high)) else thrust
        candidates = [(rp, t) for rp in (1.0, 0.7, 0.5, 0.3, 0.15, 0.0)
                      for t in (thrust, 0.5 * (thrust + middle), middle)]
        # Then the collective thrust gives way before roll and pitch do (a craft that cannot turn cannot
        # recover: at full thrust on every rotor there is no torque left).
        for roll_pitch, collective in candidates:
            base = inverse @ np.array([collective, roll_pitch * torque[0], roll_pitch * torque[1], 0.0])
            per_yaw = inverse[:, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                bound_a, bound_b = (low - base) / per_yaw, (high - base) / per_yaw
            lowest = np.max(np.where(per_yaw != 0.0, np.minimum(bound_a, bound_b), -np.inf))
            highest = np.min(np.where(per_yaw != 0.0, np.maximum(bound_a, bound_b), np.inf))
            if lowest <= highest:
                u = base + per_yaw * float(np.clip(torque[2], lowest, highest))
                break
        else:
            u = base
        return np.clip(u, low, high)
