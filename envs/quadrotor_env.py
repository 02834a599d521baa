"""A Gymnasium environment over a MuJoCo free body with rotors: the ``quadrotor`` scene.

The observation is the 13-number state of ``docs/r3s3.md``, ``(x, q, v, ω)``: position and
velocity in the world frame, orientation quaternion ``(w, x, y, z)``, body-frame angular velocity.
The physics is built with :func:`envs.scenes.build_model`, so every effect the scene does not
declare is switched off (there is no floor and no contact: the craft can fall forever).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces

from fvin_mpc.core.errors import SceneError
from fvin_mpc.core.space import R3S3, ConfigurationSpace
from fvin_mpc.core.state import as_float_array, unit_quaternion

from .rigid_body_env import MAX_PERIOD_ANGLE, MAX_STEP_ANGLE, MujocoBodyEnv, geodesic_angle
from .scenes import ScenePhysics, SceneSpec, build_model, resolve_scene

#: Largest initial |ω| (rad/s) of a default reset: a tumbling craft (the recovery task of ``python -m fvin_mpc.fly``).
DEFAULT_RESET_MAX_OMEGA = 10.0
#: Weights of the quadratic cost: |x − x*|², angle², |v|², |ω|², |u − u_hover|².
COST_WEIGHTS = (1.0, 1.0, 0.1, 0.01, 0.01)

_RESET_OPTIONS = frozenset({"state", "qpos", "qvel", "hover", "max_omega", "max_speed", "max_offset"})

#: Where a free body's parts sit in its states (the free joint block of :data:`~fvin_mpc.core.space.R3S3`).
_FREE = R3S3.layout.free_body(by=__name__)


class QuadrotorEnv(MujocoBodyEnv):
    """Bring a free-flying rotor craft to hover at a point.

    ## Description

    One MuJoCo body on a free joint (six degrees of freedom) with rotors: actuator ``i`` pushes with
    thrust ``uᵢ`` (N) along the body z axis at its arm site and reacts with a yaw torque about body z
    (a site transmission with ``gear = (0, 0, 1, 0, 0, ±κ)``), under gravity along −z. The built-in
    scene ``quadrotor`` is a 0.5 kg craft with four rotors in an × layout (``envs/scenes/quadrotor.xml``,
    the parameters of :data:`fvin_mpc.core.quadrotor.QUADROTOR`). The task is to hover at the hover
    point (the body's position in the MJCF, ``(0, 0, 1)`` m) level and at rest; episodes start there in a
    random attitude — upside down included — tumbling at up to 10 rad/s.

    Only the effects the scene's :class:`~envs.scenes.ScenePhysics` declares are simulated (gravity
    and actuator limits for the built-in scene); no floor, no contact, no aerodynamic drag.

    ## Action Space

    ``ndarray`` of shape ``(nu,)``, float64: the rotor thrusts (N), bounded by the actuators'
    ``ctrlrange`` when the physics declares actuator limits (``quadrotor``: ``[0, 2.5]`` each, 10 N in
    all against a weight of 4.905 N: about 2 g). Actions outside the bounds are clipped; a wrong
    shape or a non-finite entry raises ``ValueError`` and sends nothing.

    ## Observation Space

    ``ndarray`` of shape ``(13,)``, float64:

    | Num   | Observation                                                   | Min  | Max |
    |-------|---------------------------------------------------------------|------|-----|
    | 0–2   | x, position of the centre of mass (``xipos``), world (m)       | -Inf | Inf |
    | 3–6   | q (w, x, y, z), orientation body → world (`xquat`)             | -1.0 | 1.0 |
    | 7–9   | v, velocity of the centre of mass, world frame (m/s)           | -Inf | Inf |
    | 10–12 | ω, angular velocity, body frame (rad/s), ``Ṙ = R[ω]×``          | -Inf | Inf |

    With the centre of mass at the body origin these are MuJoCo's free-joint coordinates: ``qvel[:3]``
    is the world-frame linear velocity of the body origin and ``qvel[3:]`` the body-frame angular
    velocity; otherwise ``x = xpos + R c``, ``v = qvel[:3] + R (ω × c)`` with ``c`` the centre of mass in
    the body frame (``body_ipos``; :meth:`joint_state` inverts it) (checked against
    ``mj_objectVelocity`` and finite differences in ``tests/test_quadrotor_env.py``). ``q`` and
    ``−q`` are the same rotation; MuJoCo's sign is left as is. With ``sensor_noise_std > 0`` Gaussian
    noise is added to all 13 entries and ``q`` renormalized; reward and ``info`` use the true state.

    ## Rewards

    *r = −(|x − x*|² + angle² + 0.1 |v|² + 0.01 |ω|² + 0.01 |u − u_hover|²)*, ``x*`` the hover
    point, *angle* the geodesic angle to the goal orientation (level), ``u_hover = m g / nu`` per rotor.

    ## Starting State

    At the hover point, at rest translationally, in an orientation uniform on S³ with an angular
    velocity uniform in the ball ``|ω| ≤ 10`` rad/s, drawn from the env's ``np_random``.
    ``reset(options=...)`` accepts:

    - ``{"state": (13,)}``: the observed state ``(x, q, v, ω)`` exactly (of the centre of mass).
    - ``{"qpos": (7,), "qvel": (6,)}``: the free joint's state exactly (position, quaternion
      (w, x, y, z) normalized here; world-frame v, body-frame ω). Either may be omitted (the hover
      point level / zero).
    - ``{"hover": True}``: level at rest at the hover point.
    - ``{"max_omega": w, "max_speed": s, "max_offset": d}``: the random start with ``|ω| ≤ w``
      (default 10 rad/s), a velocity uniform in ``|v| ≤ s`` (default 0) and a position uniform in the
      ball of radius ``d`` around the hover point (default 0).

    ## Episode End

    ``terminated`` is always ``False``; the registered id truncates after 250 steps (5 s).

    ## Info

    ``angle_from_goal`` (rad), ``position_error`` (m, ``|x − x*|``), ``time`` (s), ``energy``
    (MuJoCo's kinetic + gravitational energy, J).

    ## Arguments

    - ``scene``: ``"quadrotor"``, a path to an MJCF, or a :class:`~envs.scenes.SceneSpec`.
    - ``physics``, ``control_period``: as :class:`~envs.RigidBodyEnv` (default: the scene's; 20 ms
      for ``quadrotor``).
    - ``hover_point``: the goal position of the centre of mass (m); default where the MJCF puts it, level.
    - ``control_period``: default the scene's, or for an MJCF that names none
      :data:`CONTROL_PERIOD_SHARE` of the craft's attitude time scale (:func:`craft_control_period`).
    - ``render_mode``: ``None`` or ``"rgb_array"``; ``width``, ``height`` in pixels.

    Requirements on the MJCF (``ValueError`` otherwise): the observed body has exactly one joint, a
    free joint, which is the model's only degree of freedom; no actuator has internal state.

    ## Version History

    * v0: initial version (``fvin_mpc/Quadrotor-v0``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}
    #: The configuration space of the observations (:mod:`fvin_mpc.core.space`).
    space: ConfigurationSpace = R3S3

    def __init__(self, scene: str | Path | SceneSpec = "quadrotor", physics: ScenePhysics | None = None,
                 control_period: float | None = None, hover_point: Any = None, render_mode: str | None = None,
                 width: int = 480, height: int = 480) -> None:
        spec = resolve_scene(scene)
        if control_period is None and spec.control_period is None:
            control_period = craft_control_period(*build_model(spec.xml_path, physics or spec.physics),
                                                  _craft_body_name(spec))
        super().__init__(scene, physics, control_period, render_mode, width, height)
        spec, model = self.scene_spec, self._model
        self._body_name = _craft_body_name(spec, model)
        self._body_id, self._joint_id = _free_body(model, self._body_name)

        self._goal = unit_quaternion(spec.goal if spec.goal is not None else (1.0, 0.0, 0.0, 0.0), "goal")
        # self._com: the state's x is the centre of mass, where Newton–Euler separates translation from
        # rotation (the body origin of a description is wherever its author put it).
        qpos0 = np.asarray(model.qpos0, dtype=float)
        self._hover_point = (qpos0[:3] + _rotate(self._goal, self._com) if hover_point is None
                             else as_float_array(hover_point, (3,), "hover_point"))
        self._scales = craft_scales(model, self._physics, self._body_name)
        check_craft_scales(self._scales, self._physics, float(model.opt.timestep), self._dt, spec.name)
        self._hover_thrust = hover_control(model, self._body_id, self._goal, self._physics.gravity)

        obs_high = np.array([np.inf] * 3 + [1.0] * 4 + [np.inf] * 6)
        self.observation_space = spaces.Box(low=-obs_high, high=obs_high, dtype=np.float64)
        self._set_joint_state(*self._hover_joint_state())

    # ------------------------------------------------------------------ accessors (and MujocoBodyEnv's)
    @property
    def hover_point(self) -> np.ndarray:
        """Goal position (m), world frame."""
        return self._hover_point.copy()

    @property
    def _com(self) -> np.ndarray:
        """The centre of mass in the body frame, as the plant has it now (a declared payload moves it)."""
        return np.asarray(self._model.body_ipos[self._body_id], dtype=float).copy()

    @property
    def scales(self) -> CraftScales:
        """The craft's sizes (:class:`CraftScales`), read off the MJCF by MuJoCo."""
        return self._scales

    @property
    def goal_state(self) -> np.ndarray:
        """The 13-number hover state: at the hover point, level, at rest."""
        return np.concatenate([self._hover_point, self._goal, np.zeros(6)])

    @property
    def hover_thrust(self) -> np.ndarray:
        """The controls that hold the level craft at rest (:func:`hover_control`; ``m g / nu`` each for a
        symmetric craft), ``(nu,)``."""
        return self._hover_thrust.copy()

    def state(self) -> np.ndarray:
        """The noise-free state ``(x, q, v, ω)`` ``(13,)`` (see the class docstring)."""
        qvel = self._data.qvel
        q = self._data.xquat[self._body_id]
        velocity = qvel[:3] + _rotate(q, np.cross(qvel[3:6], self._com))
        return np.concatenate([self._data.xipos[self._body_id], q, velocity, qvel[3:6]])

    def joint_state(self, state: Any) -> tuple[np.ndarray, np.ndarray]:
        """The free joint's ``(qpos (7,), qvel (6,))`` of a state ``(x, q, v, ω)`` of the centre of mass."""
        state = as_float_array(state, (R3S3.state_dim,), "state")
        q = unit_quaternion(state[_FREE.quaternion], "state quaternion")
        offset = _rotate(q, self._com)
        velocity = state[_FREE.velocity] - _rotate(q, np.cross(state[_FREE.omega], self._com))
        return np.concatenate([state[_FREE.position] - offset, q]), np.concatenate([velocity, state[_FREE.omega]])

    def set_state(self, qpos: Any, qvel: Any) -> None:
        """Set the free joint's state exactly and run ``mj_forward``; the quaternion is normalized.
        ``ValueError`` on a wrong shape or a non-finite entry (the state is then left unchanged)."""
        qpos = as_float_array(qpos, (7,), "qpos")
        qvel = as_float_array(qvel, (6,), "qvel")
        self._set_joint_state(qpos, qvel)

    def _set_joint_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        qpos = np.concatenate([qpos[:3], unit_quaternion(qpos[3:], "free-joint quaternion")])
        self._data.qpos[:] = qpos
        self._data.qvel[:] = qvel
        mujoco.mj_forward(self._model, self._data)

    def _hover_joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self.joint_state(self.goal_state)

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        options = self._reset_options(seed, options, _RESET_OPTIONS)
        if "state" in options:
            if len(options) > 1:
                others = sorted(set(options) - {"state"})
                raise ValueError(f"reset options: 'state' is the whole start, not with {others}")
            return self._reset_to(*self.joint_state(options["state"]))
        exact = {"qpos", "qvel", "hover"} & set(options)
        random_bounds = {"max_omega", "max_speed", "max_offset"} & set(options)
        if exact and random_bounds:
            raise ValueError(
                f"reset options: {sorted(random_bounds)} apply to the random start only, not with {sorted(exact)}"
            )
        if options.get("hover", False):
            if "qpos" in options or "qvel" in options:
                raise ValueError("reset options: give either 'hover' or 'qpos'/'qvel', not both")
            qpos, qvel = self._hover_joint_state()
        elif "qpos" in options or "qvel" in options:
            hover_qpos, _ = self._hover_joint_state()
            qpos, qvel = options.get("qpos", hover_qpos), options.get("qvel", np.zeros(6))
        else:
            qpos, qvel = self._random_joint_state(float(options.get("max_omega", DEFAULT_RESET_MAX_OMEGA)),
                                                  float(options.get("max_speed", 0.0)),
                                                  float(options.get("max_offset", 0.0)))
        return self._reset_to(qpos, qvel)  # the free joint's (7,) and (6,)

    def step(self, action: Any, substeps: int | None = None):
        """One control period (``frame_skip`` MuJoCo sub-steps) under ``action``; ``substeps`` runs
        only that many sub-steps (a thrust that changes within a period, as a latency-aware closed
        loop delivers it: :func:`fvin_mpc.control.closed_loop.run_episode`)."""
        u = self._advance(action, substeps)
        info = self._info()
        state = self.state()
        w_x, w_angle, w_v, w_omega, w_u = COST_WEIGHTS
        du = u - self._hover_thrust
        reward = -(w_x * info["position_error"] ** 2 + w_angle * info["angle_from_goal"] ** 2
                   + w_v * float(state[_FREE.velocity] @ state[_FREE.velocity])
                   + w_omega * float(state[_FREE.omega] @ state[_FREE.omega])
                   + w_u * float(du @ du))
        return self._observation(), reward, False, False, info

    def _aim_camera(self, camera: mujoco.MjvCamera) -> None:
        camera.lookat[:] = self._hover_point
        camera.azimuth, camera.elevation, camera.distance = 60.0, -20.0, 2.0

    # ------------------------------------------------------------------ internals
    def _observation(self) -> np.ndarray:
        observation = self.state()
        noise_std = self._physics.sensor_noise_std
        if noise_std > 0.0:
            observation = observation + self.np_random.normal(0.0, noise_std, size=self.space.state_dim)
            observation[_FREE.quaternion] /= np.linalg.norm(observation[_FREE.quaternion])
        observation[_FREE.quaternion] = np.clip(observation[_FREE.quaternion], -1.0, 1.0)
        return observation

    def _info(self) -> dict[str, float]:
        return {
            "angle_from_goal": geodesic_angle(self._data.xquat[self._body_id], self._goal),
            "position_error": float(np.linalg.norm(self._data.xipos[self._body_id] - self._hover_point)),
            "time": float(self._data.time),
            "energy": float(self._data.energy.sum()),
        }

    def _random_joint_state(
        self, max_omega: float, max_speed: float, max_offset: float
    ) -> tuple[np.ndarray, np.ndarray]:
        for name, value in (("max_omega", max_omega), ("max_speed", max_speed), ("max_offset", max_offset)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"reset option {name} must be finite and >= 0, got {value!r}")
        rng = self.np_random
        quaternion = rng.normal(size=4)
        position = self._hover_point + uniform_in_ball(rng, max_offset)
        return self.joint_state(np.concatenate([position, quaternion / np.linalg.norm(quaternion),
                                                uniform_in_ball(rng, max_speed), uniform_in_ball(rng, max_omega)]))


@dataclass(frozen=True)
class CraftScales:
    """The sizes of a craft, read off its compiled MJCF through MuJoCo alone (no closed form): what
    data collection and the flight tasks scale with.

    Attributes:
        mass: kg (the body's subtree).
        arm: m, the largest distance from the centre of mass to a site that carries an actuator's force.
        thrust_to_weight: the largest total upward force the actuators give level, over the weight.
        attitude_time: s, ``1/√α`` with ``α`` the smaller of the roll and pitch angular accelerations
            that half the actuators' ranges give about the centre of mass (rad/s²).
        hover_control: ``(nu,)``, the controls that hold the craft level at rest (:func:`hover_control`).
        angular_control: the size of the controls (RMS over the three body axes of the norm of the
            least-squares controls, no thrust change) that turn the level craft at 1 rad/s²: what
            turning costs in control units, which a controller's control weight scales with.
        yaw_time: s, ``1/√α`` for the yaw axis alike: a rotor craft turns about its thrust axis only
            through the rotors' drag torques, 3–10× slower than it rolls, and a recovery from a
            tumble must wait for it.
        linear_control: the size of the least-squares controls that raise the level craft's vertical
            acceleration by 1 m/s², no torque: what a thrust-only actuator's weight scales with.
        moment_actuators: ``(nu,)`` bool, the actuators that put no force on the body (pure moments,
            as a wrench-actuated description's roll, pitch and yaw actuators).
    """

    mass: float
    arm: float
    thrust_to_weight: float
    attitude_time: float
    hover_control: np.ndarray
    angular_control: float
    yaw_time: float = math.inf
    linear_control: float = math.nan
    moment_actuators: tuple[bool, ...] = ()


#: The control period as a share of the attitude time scale: 0.3 gives the built-in craft's 20 ms
#: (its ``attitude_time`` is 69 ms), where a 10 rad/s tumble turns 0.2 rad per step.
CONTROL_PERIOD_SHARE = 0.3


def _rotate(q: Any, vector: Any) -> np.ndarray:
    """``R(q) vector`` for a unit quaternion ``(w, x, y, z)``."""
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.asarray(vector, dtype=float), np.asarray(q, dtype=float))
    return out


def _craft_body_name(spec: SceneSpec, model: mujoco.MjModel | None = None) -> str:
    """The scene's observed body: the declared one, else the body of the MJCF's free joint."""
    if spec.body:
        return spec.body
    if model is None:
        model = mujoco.MjModel.from_xml_path(str(spec.xml_path))
    free = np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if free.size == 1:
        return mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.jnt_bodyid[free[0]])) or "quadrotor"
    return "quadrotor"


def actuator_wrenches(model: mujoco.MjModel, body_id: int, attitude: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per unit control, the world-frame force ``(3, nu)`` and the body-frame torque about the centre of
    mass ``(3, nu)`` each actuator puts on the free body at ``attitude``, at rest — by MuJoCo itself
    (``qfrc_actuator`` per control, less that at zero control), whatever its transmission and gear."""
    data = mujoco.MjData(model)
    data.qpos[_FREE.position] = 0.0  # the free joint's qpos: its block's position
    data.qpos[_FREE.quaternion] = attitude
    saved = int(model.opt.disableflags)
    # a unit control may lie outside a small ctrlrange: the column is a rate, not a feasible control
    model.opt.disableflags = saved | int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL)
    try:
        columns = []
        for control in np.vstack([np.zeros(model.nu), np.eye(model.nu)]):
            data.ctrl[:] = control
            mujoco.mj_forward(model, data)
            columns.append(data.qfrc_actuator[:6].copy())
    finally:
        model.opt.disableflags = saved
    generalized = (np.array(columns[1:]) - columns[0]).T
    force = generalized[:3]
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, np.asarray(attitude, dtype=float))
    body_force = rotation.reshape(3, 3).T @ force
    # the free joint's rotational forces are torques about the body origin; move them to the centre of mass
    torque = generalized[3:] - np.cross(np.asarray(model.body_ipos[body_id], dtype=float), body_force.T).T
    return force, torque


def hover_control(model: mujoco.MjModel, body_id: int, attitude: Any, gravity: bool = True) -> np.ndarray:
    """The controls whose force and torque come closest (least squares, within ``ctrlrange``; the
    smallest such) to holding the body still at ``attitude``: ``qfrc_actuator(u) = `` the weight, at rest,
    by MuJoCo — so a centre of mass off the rotors' centre gets unequal thrusts. Zeros without gravity.
    When no controls within the bounds hold it (a craft whose hover is infeasible) the residual stays."""
    from scipy.optimize import lsq_linear

    if not gravity or model.nu == 0:
        return np.zeros(model.nu)
    force, torque = actuator_wrenches(model, body_id, attitude)
    weight = float(model.body_subtreemass[body_id]) * -np.asarray(model.opt.gravity, dtype=float)
    matrix, wanted = np.vstack([force, torque]), np.concatenate([weight, np.zeros(3)])
    control = np.linalg.lstsq(matrix, wanted, rcond=None)[0]
    limited = model.actuator_ctrllimited.astype(bool) & ~(int(model.opt.disableflags)
                                                          & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL))
    low = np.where(limited, model.actuator_ctrlrange[:, 0], -np.inf)
    high = np.where(limited, model.actuator_ctrlrange[:, 1], np.inf)
    if np.all((control >= low) & (control <= high)):
        return control
    # rows scaled by the force and torque sizes, so that newtons and newton-metres weigh alike
    scale = np.maximum(np.abs(matrix).max(axis=1, keepdims=True), 1e-12)
    return lsq_linear(matrix / scale, wanted / scale[:, 0], bounds=(low, high)).x


#: The directions a free flyer's controls must move independently, in :func:`require_full_actuation`'s words.
_DIRECTIONS = ("the collective thrust", "the torque about body x", "the torque about body y", "the torque about body z")


def require_full_actuation(force: np.ndarray, torque: np.ndarray) -> None:
    """Refuse a craft whose controls cannot set its collective thrust and three body torques independently
    (the rank of ``[force_z; torque]`` per unit control below 4): no controller holds every attitude.
    Menagerie's ``skydio_x2`` before its pull request #220 is one — its adjacent rotors share a spin, so
    roll and yaw come from one combination of the four thrusts.

    Raises:
        SceneError: naming the directions that move together.
    """
    allocation = np.vstack([force[2], torque])
    scale = np.maximum(np.abs(allocation).max(axis=1, keepdims=True), 1e-300)
    allocation = allocation / scale
    rank = int(np.linalg.matrix_rank(allocation, tol=1e-9))
    if rank == 4:
        return
    tied = [name for k, name in enumerate(_DIRECTIONS)
            if np.linalg.matrix_rank(np.delete(allocation, k, axis=0), tol=1e-9) == rank]
    raise SceneError(f"the actuators set only {rank} of the 4 independent directions a free flyer needs: "
                     f"{' and '.join(tied)} move together (out of the family fly supports)")


def craft_scales(model: mujoco.MjModel, physics: ScenePhysics, body: str) -> CraftScales:
    """:class:`CraftScales` of ``body`` in a model built with ``physics``.

    Raises:
        SceneError: the actuators cannot set thrust and torques independently (:func:`require_full_actuation`).
    """
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    level = np.array([1.0, 0.0, 0.0, 0.0])
    force, torque = actuator_wrenches(model, body_id, level)
    require_full_actuation(force, torque)
    hover = hover_control(model, body_id, level, physics.gravity)
    limited = physics.actuator_limits & model.actuator_ctrllimited.astype(bool)
    low = np.where(limited, model.actuator_ctrlrange[:, 0], np.minimum(0.0, 2.0 * hover))
    high = np.where(limited, model.actuator_ctrlrange[:, 1], np.maximum(0.0, 2.0 * hover))
    mass = float(model.body_subtreemass[body_id])
    weight = mass * float(np.linalg.norm(model.opt.gravity)) or 1.0
    lift = float(np.sum(np.maximum(force[2] * low, force[2] * high)))
    frame = np.zeros(9)
    mujoco.mju_quat2Mat(frame, np.asarray(model.body_iquat[body_id], dtype=float))
    frame = frame.reshape(3, 3)
    inertia = frame @ np.diag(model.body_inertia[body_id]) @ frame.T
    authority = np.abs(torque) @ (0.5 * (high - low))
    alpha = float(np.min(authority[:2] / np.diag(inertia)[:2]))
    yaw_alpha = float(authority[2] / inertia[2, 2])
    sites = [int(model.actuator_trnid[a, 0]) for a in range(model.nu)
             if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_SITE and np.linalg.norm(force[:, a]) > 0.0]
    com = np.asarray(model.body_ipos[body_id], dtype=float)
    arm = max((float(np.linalg.norm(model.site_pos[s] - com)) for s in sites), default=0.0)
    if arm == 0.0:  # one thrust site at the centre of mass and body moments: the size of its inertia
        arm = math.sqrt(float(np.max(np.diag(inertia))) / mass)
    allocation = np.linalg.pinv(np.vstack([force[2], torque]))  # [thrust along z; body torque] = (force_z; B) u
    per_axis = [np.linalg.norm(allocation @ np.concatenate([[0.0], inertia[:, k]])) for k in range(3)]
    return CraftScales(mass=mass, arm=arm, thrust_to_weight=lift / weight,
                       attitude_time=1.0 / math.sqrt(alpha) if alpha > 0.0 else math.inf, hover_control=hover,
                       angular_control=float(np.sqrt(np.mean(np.square(per_axis)))),
                       yaw_time=1.0 / math.sqrt(yaw_alpha) if yaw_alpha > 0.0 else math.inf,
                       linear_control=float(np.linalg.norm(allocation @ np.array([mass, 0.0, 0.0, 0.0]))),
                       moment_actuators=tuple(bool(np.linalg.norm(force[:, a]) == 0.0) for a in range(model.nu)))


#: The least thrust-to-weight a craft may have: at hover its actuators spend 1/(thrust-to-weight) of their
#: upward range on the weight, and what is left is all they have to turn it (differential thrust) and to
#: climb; at 1.2 a sixth remains. Below 1 it cannot lift itself at all. The flyer family draws 1.5–4, the
#: built-in quadrotor has 2.04.
MIN_THRUST_TO_WEIGHT = 1.2


def check_craft_scales(scales: CraftScales, physics: ScenePhysics, timestep: float, period: float, name: str) -> None:
    """``SceneError`` for a craft that cannot hover (:data:`MIN_THRUST_TO_WEIGHT`), or whose timestep or
    control period does not resolve its rates: the faster of ``1/attitude_time`` and the tumble a
    recovery starts from (:data:`DEFAULT_RESET_MAX_OMEGA`), with the pivoted bodies' bounds
    (:data:`~envs.rigid_body_env.MAX_STEP_ANGLE` per timestep, :data:`~envs.rigid_body_env.MAX_PERIOD_ANGLE`
    per period: the same reasons)."""
    if physics.gravity and scales.thrust_to_weight < MIN_THRUST_TO_WEIGHT:
        raise SceneError(
            f"scene {name!r}: the craft cannot hover: its actuators lift {scales.thrust_to_weight:.3g} times its "
            f"weight ({scales.mass:.3g} kg), and it needs at least {MIN_THRUST_TO_WEIGHT:g} to hold its attitude "
            "while it hovers; raise the thrust bounds (ctrlrange) or the gear, or check the mass")
    rate = max(1.0 / scales.attitude_time, DEFAULT_RESET_MAX_OMEGA)
    if timestep * rate > MAX_STEP_ANGLE:
        raise SceneError(
            f"scene {name!r}: the timestep {timestep:g} s does not resolve the craft's rates of {rate:.3g} rad/s (it "
            f"turns {timestep * rate:.3g} rad per step, at most {MAX_STEP_ANGLE:g}): use a timestep of at most "
            f"{MAX_STEP_ANGLE / rate:.2g} s, or check the mass and inertia and the actuators' gear")
    if period * rate > MAX_PERIOD_ANGLE:
        raise SceneError(
            f"scene {name!r}: a control period of {period:g} s turns the craft {period * rate:.3g} rad per step at "
            f"{rate:.3g} rad/s, past the {MAX_PERIOD_ANGLE:g} rad a model's step can take: use a control period of at "
            f"most {MAX_PERIOD_ANGLE / rate:.2g} s")


def craft_control_period(model: mujoco.MjModel, physics: ScenePhysics, body: str) -> float:
    """The control period of a craft whose scene names none: :data:`CONTROL_PERIOD_SHARE` of its attitude
    time scale, down to a whole number of MJCF timesteps (at least one); the pivoted scenes' 20 ms
    default when the actuators give no bounded torque to measure it by."""
    timestep = float(model.opt.timestep)
    scales = craft_scales(model, physics, body)
    if not math.isfinite(scales.attitude_time):
        return timestep * math.ceil(0.02 / timestep - 1e-9)
    return round(timestep * max(1, math.floor(CONTROL_PERIOD_SHARE * scales.attitude_time / timestep + 1e-9)), 12)


def uniform_in_ball(rng: np.random.Generator, radius: float) -> np.ndarray:
    """A point uniform in the ball ``|p| ≤ radius`` of R³."""
    direction = rng.normal(size=3)
    return direction / np.linalg.norm(direction) * radius * rng.uniform() ** (1.0 / 3.0)


def _free_body(model: mujoco.MjModel, body: str) -> tuple[int, int]:
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, model.nbody)]
        raise SceneError(f"no body named {body!r} in the MJCF; bodies: {names}")
    if model.body_jntnum[body_id] != 1 or int(model.jnt_type[model.body_jntadr[body_id]]) != int(
        mujoco.mjtJoint.mjJNT_FREE
    ):
        raise SceneError(f"body {body!r} must have exactly one joint, a free joint")
    if model.nv != 6 or model.body_parentid[body_id] != 0:
        raise SceneError(f"the free joint of body {body!r} (a child of the world) must be the model's only "
                         f"degree of freedom; the model has nv={model.nv}")
    if model.nu == 0:
        raise SceneError("the MJCF has no actuators")
    if model.na > 0:
        raise SceneError("actuators with internal state (dyntype != none) are not supported")
    return body_id, int(model.body_jntadr[body_id])


# ---------------------------------------------------------------------- registration
#: Registered ids: ``gymnasium.make(id)`` after ``import fvin_mpc.envs``.
ENV_IDS = {"fvin_mpc/Quadrotor-v0": "quadrotor"}
MAX_EPISODE_STEPS = 250


def register_envs() -> None:
    """Register the free-body scenes with Gymnasium (idempotent): see :data:`ENV_IDS`."""
    for env_id, scene in ENV_IDS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(id=env_id, entry_point="fvin_mpc.envs.quadrotor_env:QuadrotorEnv",
                           kwargs={"scene": scene}, max_episode_steps=MAX_EPISODE_STEPS)
