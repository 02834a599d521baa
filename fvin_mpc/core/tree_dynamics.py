"""The closed-form dynamics of a kinematic tree read off a MuJoCo model, written once for every backend.

A :class:`KinematicTree` holds a MuJoCo model's bodies, joints (hinge, slide, ball, free) and actuators as
numbers; its methods give, at a state ``(qpos, qvel)`` on components (:mod:`fvin_mpc.core.backend`:
arrays ``(*batch,)`` in NumPy and torch, scalars in CasADi), the terms of ``M(q) q̈ + bias = passive + Bᵀu``
in MuJoCo's own coordinates (``../shared/DESIGN.md``, "Mechanisms: trees of joints"):

* :meth:`~KinematicTree.mass_matrix` — ``M(q)``, armature on the diagonal: MuJoCo's ``mj_fullM``;
* :meth:`~KinematicTree.bias_force` — ``C(q, ν)ν + g(q)``: ``qfrc_bias``;
* :meth:`~KinematicTree.passive_force` — ``−Dν − K(q − q_spring)`` (springs on hinges and slides):
  ``qfrc_passive``;
* :meth:`~KinematicTree.actuator_moment` — ``B(q)``, ``nu × nv``, gear and transmission (joint, jointinparent,
  site): ``actuator_moment`` (dense); the generalized actuation is ``Bᵀ(gain ⊙ u)`` (:meth:`~KinematicTree.gains`);
* :meth:`~KinematicTree.potential_energy`, :meth:`~KinematicTree.kinetic_energy` — ``energy[0]``, ``energy[1]``.

The recursion is MuJoCo's own, so that the conventions need no conversion: forward kinematics body by body
as ``mj_kinematics`` (a hinge or slide angle from its ``qpos0``, a ball's or free joint's quaternion
normalized, a free joint's position absolute), each degree of freedom's motion axis as ``cdof`` (a ball's
and a free joint's rotation axes the body's own, so its ``qvel`` is the body-frame rate; a free joint's
translation in the world), the composite-rigid-body algorithm for ``M`` and Newton–Euler at zero
acceleration for the bias — every spatial quantity at the world origin, gravity as the base's
acceleration. Rotations are 3×3 matrices of components (:mod:`fvin_mpc.core.s3`); a quaternion ``q``
enters as ``R(q)/|q|²``, the rotation of ``q/|q|`` without a square root.

:func:`refusals` lists what a model has that these terms leave out (tendons, equality constraints,
contacts, dry friction, fluid forces, gravity compensation, actuators with dynamics or bias, transmissions
other than joint and site, ...); :meth:`KinematicTree.from_mujoco` refuses such a model in one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import mujoco
import numpy as np

from fvin_mpc.core import s3
from fvin_mpc.core.backend import Ops, get_ops
from fvin_mpc.core.errors import SceneError

NP = get_ops("numpy")

Vec3 = tuple[Any, Any, Any]
Mat3 = tuple[Vec3, Vec3, Vec3]
#: A spatial motion or force at the world origin: (angular part, linear part) — ``(ω, v_O)`` for a motion
#: (``v_O`` the velocity of the body point at the origin), ``(moment about the origin, force)`` for a force.
Spatial = tuple[Vec3, Vec3]

_JOINT_KINDS = {int(mujoco.mjtJoint.mjJNT_FREE): "free", int(mujoco.mjtJoint.mjJNT_BALL): "ball",
                int(mujoco.mjtJoint.mjJNT_SLIDE): "slide", int(mujoco.mjtJoint.mjJNT_HINGE): "hinge"}
_TRANSMISSIONS = {int(mujoco.mjtTrn.mjTRN_JOINT): "joint", int(mujoco.mjtTrn.mjTRN_JOINTINPARENT): "jointinparent",
                  int(mujoco.mjtTrn.mjTRN_SITE): "site"}
_ZERO: Vec3 = (0.0, 0.0, 0.0)
_IDENTITY: Mat3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


# ----------------------------------------------------------------------------- the model as numbers
@dataclass(frozen=True)
class TreeJoint:
    """One joint: its kind (``"hinge"``, ``"slide"``, ``"ball"``, ``"free"``), body, ``qpos``/``qvel``
    addresses, axis and anchor in the body frame, the ``qpos0`` its angle or travel counts from, and its
    spring (stiffness and ``qpos_spring``; hinge and slide only)."""

    kind: str
    label: str
    body: int
    qpos: int
    dof: int
    axis: Vec3
    anchor: Vec3
    reference: float
    stiffness: float
    spring_reference: float

    @property
    def dof_count(self) -> int:
        return {"free": 6, "ball": 3}.get(self.kind, 1)


@dataclass(frozen=True)
class TreeBody:
    """One body: its parent (``-1`` for the world, body 0), pose in the parent at ``qpos0``, mass, centre of
    mass and inertia about it (body frame), and its joints (indices into :attr:`KinematicTree.joints`)."""

    label: str
    parent: int
    position: Vec3
    rotation: Mat3
    mass: float
    center_of_mass: Vec3
    inertia: Mat3
    joints: tuple[int, ...]


@dataclass(frozen=True)
class TreeActuator:
    """One actuator's transmission: ``"joint"`` or ``"jointinparent"`` (``joint``) or ``"site"`` (the site's
    ``body``, position and rotation in it), its ``gear`` (6 entries), and the gain its force is per unit of
    control (force = gain·u: a motor's is 1)."""

    label: str
    transmission: str
    gear: tuple[float, ...]
    gain: float
    joint: int = -1
    body: int = 0
    site_position: Vec3 = _ZERO
    site_rotation: Mat3 = _IDENTITY


@dataclass(frozen=True)
class TreeTerms:
    """The terms at one state, on components: ``mass`` (``nv`` rows of ``nv``), ``bias``, ``passive``
    (``nv`` each) and ``moment`` (``nu`` rows of ``nv``)."""

    mass: tuple[tuple[Any, ...], ...]
    bias: tuple[Any, ...]
    passive: tuple[Any, ...]
    moment: tuple[tuple[Any, ...], ...]


@dataclass(frozen=True)
class TreePose:
    """Forward kinematics at one ``qpos``: every body's rotation and origin in the world, every degree of
    freedom's motion axis at the world origin, and each body's dofs in the groups the velocity recursion
    takes them (a group's axes move with the velocity before it, MuJoCo's ``cdof_dot``)."""

    rotations: list[Mat3]
    origins: list[Vec3]
    axes: list[Spatial]
    groups: list[list[list[int]]]


def _vec(values: Sequence[float]) -> Vec3:
    return tuple(float(v) for v in values)  # type: ignore[return-value]


def _mat(values: np.ndarray) -> Mat3:
    return tuple(tuple(float(v) for v in row) for row in np.asarray(values).reshape(3, 3))  # type: ignore[return-value]


def _quaternion_matrix(quat: Sequence[float]) -> Mat3:
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, np.asarray(quat, dtype=float) / np.linalg.norm(quat))
    return _mat(matrix)


def _disabled(model: mujoco.MjModel, flag: mujoco.mjtDisableBit) -> bool:
    return bool(model.opt.disableflags & int(flag))


def refusals(model: mujoco.MjModel) -> list[str]:
    """What ``model`` has that :class:`KinematicTree`'s terms leave out; empty if nothing.

    Joint limits are not among them: their forces are constraints, the MPC's state bounds (DESIGN)."""
    problems: list[str] = []
    counts = {"tendons": model.ntendon, "equality constraints": model.neq, "mocap bodies": model.nmocap,
              "flexible bodies (flex)": getattr(model, "nflex", 0), "plugins": getattr(model, "nplugin", 0)}
    problems += [f"{name} ({int(count)})" for name, count in counts.items() if count > 0]
    if model.njnt == 0:
        problems.append("no joint")
    contact_off = _disabled(model, mujoco.mjtDisableBit.mjDSBL_CONTACT) or \
        _disabled(model, mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    colliding = (model.geom_contype[:, None] & model.geom_conaffinity[None, :]) != 0
    if not contact_off and (model.npair > 0 or (model.ngeom > 1 and colliding[~np.eye(model.ngeom, dtype=bool)].any())):
        problems.append('contacts (disable them: <option><flag contact="disable"/></option>, or contype=conaffinity=0)')
    friction_off = _disabled(model, mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS) or \
        _disabled(model, mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    if not friction_off and np.any(model.dof_frictionloss > 0.0):
        problems.append("joint dry friction (frictionloss)")
    rotational = np.isin(model.jnt_type, [int(mujoco.mjtJoint.mjJNT_BALL), int(mujoco.mjtJoint.mjJNT_FREE)])
    if np.any(model.jnt_stiffness[rotational] != 0.0):
        problems.append("springs on ball or free joints (stiffness)")
    for field, what in (("jnt_stiffnesspoly", "polynomial springs (stiffnesspoly)"),
                        ("dof_dampingpoly", "polynomial damping (dampingpoly)"),
                        ("jnt_springyield", "yielding springs (springyield)"),
                        ("body_gravcomp", "gravity compensation (gravcomp)"),
                        ("actuator_armature", "actuator armature"), ("actuator_damping", "actuator damping"),
                        ("actuator_dampingpoly", "actuator damping"), ("actuator_delay", "actuator delay")):
        if np.any(np.asarray(getattr(model, field, 0.0)) != 0.0):
            problems.append(what)
    if model.opt.density != 0.0 or model.opt.viscosity != 0.0:
        problems.append("fluid forces (density, viscosity)")
    if model.na > 0 or np.any(model.actuator_dyntype != int(mujoco.mjtDyn.mjDYN_NONE)):
        problems.append("actuators with dynamics (dyntype, activation state)")
    if np.any(model.actuator_biastype != int(mujoco.mjtBias.mjBIAS_NONE)):
        problems.append("actuators with bias (position or velocity servos)")
    if np.any(model.actuator_gaintype != int(mujoco.mjtGain.mjGAIN_FIXED)):
        problems.append("actuators with a gain that is not fixed")
    if np.any(model.actuator_forcelimited):
        problems.append("actuators with a force range (forcelimited)")
    for actuator in range(model.nu):
        kind = int(model.actuator_trntype[actuator])
        if kind not in _TRANSMISSIONS:
            problems.append(f"actuator {actuator}: a transmission other than joint, jointinparent or site "
                            f"({mujoco.mjtTrn(kind).name})")
        elif kind == int(mujoco.mjtTrn.mjTRN_SITE) and int(model.actuator_trnid[actuator, 1]) != -1:
            problems.append(f"actuator {actuator}: a site transmission with a reference site (refsite)")
    return problems


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int, fallback: str) -> str:
    return mujoco.mj_id2name(model, kind, index) or f"{fallback} {index}"


@dataclass(frozen=True)
class KinematicTree:
    """A MuJoCo model's kinematic tree as numbers (:meth:`from_mujoco`); its methods are the closed form.

    Attributes:
        bodies: every body in MuJoCo's order (body 0 the world), parents before children.
        joints: every joint in MuJoCo's order (so ``qpos``, ``qvel`` are their entries in order).
        actuators: every actuator's transmission.
        gravity: the world's gravitational acceleration (zero where the model disables gravity).
        damping: per degree of freedom (zero where the model disables the damper).
        armature: per degree of freedom: added to ``M``'s diagonal.
        springs: whether springs act (the model does not disable them).
        nq, nv: sizes of ``qpos`` and ``qvel``.
    """

    bodies: tuple[TreeBody, ...]
    joints: tuple[TreeJoint, ...]
    actuators: tuple[TreeActuator, ...]
    gravity: Vec3
    damping: tuple[float, ...]
    armature: tuple[float, ...]
    springs: bool
    nq: int
    nv: int

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel) -> "KinematicTree":
        """The tree of ``model``.

        Raises:
            SceneError: ``model`` has what the closed form leaves out (:func:`refusals`), in one line.
        """
        problems = refusals(model)
        if problems:
            raise SceneError(f"the tree's closed form does not model: {'; '.join(problems)}")
        joints = tuple(TreeJoint(
            kind=_JOINT_KINDS[int(model.jnt_type[j])], label=_name(model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint"),
            body=int(model.jnt_bodyid[j]), qpos=int(model.jnt_qposadr[j]), dof=int(model.jnt_dofadr[j]),
            axis=_vec(model.jnt_axis[j]), anchor=_vec(model.jnt_pos[j]),
            reference=float(model.qpos0[model.jnt_qposadr[j]]), stiffness=float(model.jnt_stiffness[j]),
            spring_reference=float(model.qpos_spring[model.jnt_qposadr[j]])) for j in range(model.njnt))
        bodies = []
        for b in range(model.nbody):
            principal = _quaternion_matrix(model.body_iquat[b])
            inertia = np.asarray(principal) @ np.diag(model.body_inertia[b]) @ np.asarray(principal).T
            first, count = int(model.body_jntadr[b]), int(model.body_jntnum[b])
            bodies.append(TreeBody(
                label=_name(model, mujoco.mjtObj.mjOBJ_BODY, b, "body"),
                parent=int(model.body_parentid[b]) if b else -1,
                position=_vec(model.body_pos[b]), rotation=_quaternion_matrix(model.body_quat[b]),
                mass=float(model.body_mass[b]), center_of_mass=_vec(model.body_ipos[b]), inertia=_mat(inertia),
                joints=tuple(range(first, first + count)) if count > 0 else ()))
        actuators = []
        for a in range(model.nu):
            kind = _TRANSMISSIONS[int(model.actuator_trntype[a])]
            target = int(model.actuator_trnid[a, 0])
            common = dict(label=_name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator"), transmission=kind,
                          gear=tuple(float(g) for g in model.actuator_gear[a]),
                          gain=float(model.actuator_gainprm[a, 0]))
            if kind == "site":
                actuators.append(TreeActuator(**common, body=int(model.site_bodyid[target]),
                                              site_position=_vec(model.site_pos[target]),
                                              site_rotation=_quaternion_matrix(model.site_quat[target])))
            else:
                actuators.append(TreeActuator(**common, joint=target))
        gravity = (0.0, 0.0, 0.0) if _disabled(model, mujoco.mjtDisableBit.mjDSBL_GRAVITY) else _vec(model.opt.gravity)
        damper_off = _disabled(model, mujoco.mjtDisableBit.mjDSBL_DAMPER)
        return cls(bodies=tuple(bodies), joints=joints, actuators=tuple(actuators), gravity=gravity,
                   damping=tuple(0.0 if damper_off else float(d) for d in model.dof_damping),
                   armature=tuple(float(a) for a in model.dof_armature),
                   springs=not _disabled(model, mujoco.mjtDisableBit.mjDSBL_SPRING), nq=int(model.nq), nv=int(model.nv))

    # -------------------------------------------------------------- sizes and structure
    @property
    def nu(self) -> int:
        return len(self.actuators)

    def dof_bodies(self) -> tuple[int, ...]:
        """The body each degree of freedom moves (MuJoCo's ``dof_bodyid``)."""
        return tuple(joint.body for joint in self.joints for _ in range(joint.dof_count))

    def supports(self, body: int) -> frozenset[int]:
        """The body and its ancestors (the world included): the bodies whose dofs move it."""
        chain = []
        while body >= 0:
            chain.append(body)
            body = self.bodies[body].parent
        return frozenset(chain)

    # -------------------------------------------------------------- kinematics
    def pose(self, qpos: Sequence[Any], ops: Ops) -> TreePose:
        """Forward kinematics at ``qpos`` (what every term reads; pass it on to compute it once)."""
        rotations: list[Mat3] = [_IDENTITY]
        origins: list[Vec3] = [_ZERO]
        axes: list[Spatial] = []
        groups: list[list[list[int]]] = [[]]
        for b, body in enumerate(self.bodies[1:], start=1):
            rotation = s3.mattmat(rotations[body.parent], body.rotation)
            origin = s3.add(origins[body.parent], s3.matvec(rotations[body.parent], body.position))
            body_groups: list[list[int]] = []
            own_frame: list[tuple[list[int], Vec3]] = []  # ball and free rotations: the body's own axes
            for j in body.joints:
                joint = self.joints[j]
                first = joint.dof
                if joint.kind == "free":
                    origin = tuple(qpos[joint.qpos:joint.qpos + 3])  # type: ignore[assignment]
                    rotation = _unit_rotation(tuple(qpos[joint.qpos + 3:joint.qpos + 7]))
                    axes += [(_ZERO, unit) for unit in _IDENTITY]
                    axes += [(_ZERO, _ZERO)] * 3  # filled below from the body's rotation
                    body_groups += [[first, first + 1, first + 2], [first + 3, first + 4, first + 5]]
                    own_frame.append(([first + 3, first + 4, first + 5], origin))
                    continue
                axis = s3.matvec(rotation, joint.axis)
                anchor = s3.add(origin, s3.matvec(rotation, joint.anchor))
                if joint.kind == "slide":
                    origin = s3.add(origin, s3.scale(qpos[joint.qpos] - joint.reference, axis))
                    axes.append((_ZERO, axis))
                    body_groups.append([first])
                    continue
                if joint.kind == "hinge":
                    rotation = s3.mattmat(rotation, _axis_rotation(joint.axis, qpos[joint.qpos] - joint.reference, ops))
                    axes.append((axis, s3.cross(anchor, axis)))
                    body_groups.append([first])
                else:  # ball
                    rotation = s3.mattmat(rotation, _unit_rotation(tuple(qpos[joint.qpos:joint.qpos + 4])))
                    axes += [(_ZERO, _ZERO)] * 3
                    body_groups.append([first, first + 1, first + 2])
                    own_frame.append(([first, first + 1, first + 2], anchor))
                origin = s3.sub(anchor, s3.matvec(rotation, joint.anchor))
            for dofs, anchor in own_frame:  # MuJoCo's cdof: the columns of the body's rotation
                for i, dof in enumerate(dofs):
                    column = (rotation[0][i], rotation[1][i], rotation[2][i])
                    axes[dof] = (column, s3.cross(anchor, column))
            rotations.append(rotation)
            origins.append(origin)
            groups.append(body_groups)
        return TreePose(rotations, origins, axes, groups)

    def _inertias(self, pose: TreePose) -> list[tuple[Any, Vec3, Mat3]]:
        """Every body's ``(mass, centre of mass, inertia about it)`` in the world."""
        found = []
        for b, body in enumerate(self.bodies):
            rotation = pose.rotations[b]
            center = s3.add(pose.origins[b], s3.matvec(rotation, body.center_of_mass))
            inertia = s3.mattmat(s3.mattmat(rotation, body.inertia), _transpose(rotation))
            found.append((body.mass, center, inertia))
        return found

    # -------------------------------------------------------------- the terms
    def mass_matrix(self, qpos: Sequence[Any], ops: Ops, pose: TreePose | None = None) -> tuple[tuple[Any, ...], ...]:
        """``M(q)`` (``nv`` rows of ``nv`` components), armature included: MuJoCo's ``mj_fullM``, by the
        composite-rigid-body algorithm."""
        pose = pose or self.pose(qpos, ops)
        composite = []
        for mass, center, inertia in self._inertias(pose):
            offset = _matadd(_matscale(s3.dot(center, center), _IDENTITY), _matscale(-1.0, _outer(center, center)))
            composite.append([mass, s3.scale(mass, center), _matadd(inertia, _matscale(mass, offset))])
        for b in range(len(self.bodies) - 1, 0, -1):
            parent = composite[self.bodies[b].parent]
            mass, first_moment, inertia = composite[b]
            parent[0] = parent[0] + mass
            parent[1] = s3.add(parent[1], first_moment)
            parent[2] = _matadd(parent[2], inertia)
        dof_bodies = self.dof_bodies()
        rows: list[list[Any]] = [[0.0] * self.nv for _ in range(self.nv)]
        for column in range(self.nv):  # the composite of the column's body moving along its axis
            mass, first_moment, inertia = composite[dof_bodies[column]]
            angular, linear = pose.axes[column]
            momentum = (s3.add(s3.matvec(inertia, angular), s3.cross(first_moment, linear)),
                        s3.add(s3.scale(mass, linear), s3.cross(angular, first_moment)))
            supporting = self.supports(dof_bodies[column])
            for row in range(column + 1):
                if dof_bodies[row] in supporting:
                    rows[row][column] = rows[column][row] = _power(pose.axes[row], momentum)
            rows[column][column] = rows[column][column] + self.armature[column]
        return tuple(tuple(row) for row in rows)

    def bias_force(self, qpos: Sequence[Any], qvel: Sequence[Any], ops: Ops,
                   pose: TreePose | None = None) -> tuple[Any, ...]:
        """``C(q, ν)ν + g(q)`` (``nv`` components): MuJoCo's ``qfrc_bias``, by Newton–Euler at zero
        acceleration with gravity as the base's acceleration."""
        pose = pose or self.pose(qpos, ops)
        velocities: list[Spatial] = [(_ZERO, _ZERO)]
        accelerations: list[Spatial] = [(_ZERO, s3.scale(-1.0, self.gravity))]
        for b, body in enumerate(self.bodies[1:], start=1):
            velocity, acceleration = velocities[body.parent], accelerations[body.parent]
            for group in pose.groups[b]:
                for dof in group:
                    moving_axis = _cross_motion(velocity, pose.axes[dof])
                    acceleration = _spatial_add(acceleration, _spatial_scale(qvel[dof], moving_axis))
                for dof in group:
                    velocity = _spatial_add(velocity, _spatial_scale(qvel[dof], pose.axes[dof]))
            velocities.append(velocity)
            accelerations.append(acceleration)
        forces: list[Spatial] = []
        for b, (mass, center, inertia) in enumerate(self._inertias(pose)):
            momentum = _momentum(mass, center, inertia, velocities[b])
            forces.append(_spatial_add(_momentum(mass, center, inertia, accelerations[b]),
                                       _cross_force(velocities[b], momentum)))
        for b in range(len(self.bodies) - 1, 0, -1):
            parent = self.bodies[b].parent
            forces[parent] = _spatial_add(forces[parent], forces[b])
        dof_bodies = self.dof_bodies()
        return tuple(_power(pose.axes[k], forces[dof_bodies[k]]) for k in range(self.nv))

    def passive_force(self, qpos: Sequence[Any], qvel: Sequence[Any], ops: Ops) -> tuple[Any, ...]:
        """``−Dν − K(q − q_spring)`` (``nv`` components): MuJoCo's ``qfrc_passive`` (damping on every dof,
        springs on hinges and slides)."""
        force = [-self.damping[k] * qvel[k] for k in range(self.nv)]
        for joint in self.joints:
            if self.springs and joint.stiffness != 0.0:
                force[joint.dof] = force[joint.dof] - joint.stiffness * (qpos[joint.qpos] - joint.spring_reference)
        return tuple(force)

    def actuator_moment(self, qpos: Sequence[Any], ops: Ops,
                        pose: TreePose | None = None) -> tuple[tuple[Any, ...], ...]:
        """``B(q)`` (``nu`` rows of ``nv`` components), the generalized force per unit of each actuator's force:
        MuJoCo's ``actuator_moment`` (dense). A joint transmission's gear on the joint's dofs (a ball's in
        the child's frame, or with ``jointinparent`` in the parent's), a site's wrench ``(force, torque)``
        in the site's frame through the site's Jacobian."""
        rows = []
        for actuator in self.actuators:
            row: list[Any] = [0.0] * self.nv
            if actuator.transmission == "site":
                pose = pose or self.pose(qpos, ops)
                body_rotation = pose.rotations[actuator.body]
                rotation = s3.mattmat(body_rotation, actuator.site_rotation)
                point = s3.add(pose.origins[actuator.body], s3.matvec(body_rotation, actuator.site_position))
                force = s3.matvec(rotation, actuator.gear[:3])
                wrench = (s3.add(s3.matvec(rotation, actuator.gear[3:]), s3.cross(point, force)), force)
                supporting, dof_bodies = self.supports(actuator.body), self.dof_bodies()
                row = [_power(pose.axes[k], wrench) if dof_bodies[k] in supporting else 0.0 for k in range(self.nv)]
            else:
                joint = self.joints[actuator.joint]
                gear = list(actuator.gear[:joint.dof_count])
                if actuator.transmission == "jointinparent" and joint.kind in ("ball", "free"):
                    start = joint.qpos + (3 if joint.kind == "free" else 0)
                    rotated = s3.matvec(_transpose(_unit_rotation(tuple(qpos[start:start + 4]))), gear[-3:])
                    gear[-3:] = list(rotated)
                row[joint.dof:joint.dof + joint.dof_count] = gear
            rows.append(tuple(row))
        return tuple(rows)

    def gains(self) -> tuple[float, ...]:
        """Each actuator's force per unit of control: the generalized actuation is ``Bᵀ(gain ⊙ u)``."""
        return tuple(actuator.gain for actuator in self.actuators)

    def terms(self, qpos: Sequence[Any], qvel: Sequence[Any], ops: Ops) -> TreeTerms:
        """All four terms at one state, the kinematics computed once."""
        pose = self.pose(qpos, ops)
        return TreeTerms(self.mass_matrix(qpos, ops, pose), self.bias_force(qpos, qvel, ops, pose),
                         self.passive_force(qpos, qvel, ops), self.actuator_moment(qpos, ops, pose))

    def potential_energy(self, qpos: Sequence[Any], ops: Ops) -> Any:
        """Gravity's potential ``−Σ m g·c`` and the hinges' and slides' springs: MuJoCo's ``energy[0]``."""
        energy: Any = 0.0
        for mass, center, _ in self._inertias(self.pose(qpos, ops))[1:]:
            energy = energy - mass * s3.dot(self.gravity, center)
        for joint in self.joints:
            if self.springs and joint.stiffness != 0.0:
                stretch = qpos[joint.qpos] - joint.spring_reference
                energy = energy + 0.5 * joint.stiffness * stretch * stretch
        return energy

    def kinetic_energy(self, qpos: Sequence[Any], qvel: Sequence[Any], ops: Ops) -> Any:
        """``½ νᵀ M(q) ν`` (armature included, as MuJoCo's ``energy[1]``)."""
        mass = self.mass_matrix(qpos, ops)
        return 0.5 * s3.dot(qvel, s3.matvec(mass, qvel))

    # -------------------------------------------------------------- NumPy arrays
    def numpy_terms(self, qpos: Any, qvel: Any) -> dict[str, np.ndarray]:
        """:meth:`terms` of NumPy states ``qpos (…, nq)``, ``qvel (…, nv)`` as arrays: ``mass (…, nv, nv)``,
        ``bias``, ``passive (…, nv)``, ``moment (…, nu, nv)``."""
        qpos, qvel = np.asarray(qpos, dtype=float), np.asarray(qvel, dtype=float)
        batch = np.broadcast_shapes(qpos.shape[:-1], qvel.shape[:-1])
        terms = self.terms(NP.unstack(qpos), NP.unstack(qvel), NP)

        def array(nested: Any, shape: tuple[int, ...]) -> np.ndarray:
            flat = [entry for row in nested for entry in row] if len(shape) == 2 else list(nested)
            out = np.zeros((*batch, int(np.prod(shape))))
            for i, entry in enumerate(flat):
                out[..., i] = entry
            return out.reshape(*batch, *shape)

        return {"mass": array(terms.mass, (self.nv, self.nv)), "bias": array(terms.bias, (self.nv,)),
                "passive": array(terms.passive, (self.nv,)), "moment": array(terms.moment, (self.nu, self.nv))}


# ----------------------------------------------------------------------------- small algebra on components
def _transpose(m: Mat3) -> Mat3:
    return tuple(tuple(m[j][i] for j in range(3)) for i in range(3))  # type: ignore[return-value]


def _outer(a: Vec3, b: Vec3) -> Mat3:
    return tuple(tuple(a_i * b_j for b_j in b) for a_i in a)  # type: ignore[return-value]


def _matadd(a: Mat3, b: Mat3) -> Mat3:
    return tuple(s3.add(row_a, row_b) for row_a, row_b in zip(a, b))  # type: ignore[return-value]


def _matscale(s: Any, m: Mat3) -> Mat3:
    return tuple(s3.scale(s, row) for row in m)  # type: ignore[return-value]


def _unit_rotation(quat: tuple[Any, Any, Any, Any]) -> Mat3:
    """``R(q)/|q|²``: the rotation of ``q/|q|`` (MuJoCo normalizes a joint's quaternion)."""
    return _matscale(1.0 / s3.dot(quat, quat), s3.rotation_matrix(quat))


def _axis_rotation(axis: Vec3, angle: Any, ops: Ops) -> Mat3:
    """The rotation by ``angle`` about the unit ``axis`` (numbers): ``cos θ I + sin θ [a]× + (1 − cos θ) a aᵀ``."""
    c, s = ops.cos(angle), ops.sin(angle)
    skew = s3.skew(axis)
    return tuple(tuple((c if i == j else 0.0) + s * skew[i][j] + (1.0 - c) * (axis[i] * axis[j]) for j in range(3))
                 for i in range(3))  # type: ignore[return-value]


def _spatial_add(a: Spatial, b: Spatial) -> Spatial:
    return (s3.add(a[0], b[0]), s3.add(a[1], b[1]))


def _spatial_scale(s: Any, a: Spatial) -> Spatial:
    return (s3.scale(s, a[0]), s3.scale(s, a[1]))


def _cross_motion(v: Spatial, m: Spatial) -> Spatial:
    """``v ×ₘ m``: how the motion axis ``m``, fixed in a frame moving with ``v``, changes."""
    return (s3.cross(v[0], m[0]), s3.add(s3.cross(v[0], m[1]), s3.cross(v[1], m[0])))


def _cross_force(v: Spatial, f: Spatial) -> Spatial:
    """``v ×* f``: the rate of a momentum ``f`` carried with ``v``."""
    return (s3.add(s3.cross(v[0], f[0]), s3.cross(v[1], f[1])), s3.cross(v[0], f[1]))


def _power(motion: Spatial, force: Spatial) -> Any:
    """``mᵀf``: the power of ``force`` along the motion axis ``motion``."""
    return s3.dot(motion[0], force[0]) + s3.dot(motion[1], force[1])


def _momentum(mass: Any, center: Vec3, inertia: Mat3, motion: Spatial) -> Spatial:
    """A body's momentum at the world origin under ``motion``: ``P = m(v_O + ω × c)``, ``L = I_c ω + c × P``."""
    linear = s3.scale(mass, s3.add(motion[1], s3.cross(motion[0], center)))
    return (s3.add(s3.matvec(inertia, motion[0]), s3.cross(center, linear)), linear)
