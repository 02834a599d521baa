"""A Gymnasium environment over a MuJoCo scene: one rigid body on one actuated hinge or ball joint.

The observation is the model state of ``DESIGN.md``, ``x = (q, ω)``: the body's orientation
quaternion ``(w, x, y, z)`` and its body-frame angular velocity. The physics is built with
:func:`envs.scenes.build_model`, so every effect the scene does not declare is switched off.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.errors import SceneError, UsageError
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.core.space import S3, ConfigurationSpace
from fvin_mpc.core.state import as_float_array, unit_quaternion

from .scenes import (
    IMPULSE_HOLD_S,
    IMPULSE_HOLD_TOLERANCE,
    MIN_CONTROL_PERIOD,
    ScenePhysics,
    SceneSpec,
    build_model,
    resolve_scene,
    scale_mass,
)

#: The value of each effect that :class:`MujocoBodyEnv` leaves to a subclass when it is off.
_EFFECTS_OFF = {"gyro_noise_std": 0.0, "encoder_bits": None, "impulse_delta_omega": 0.0}

#: Largest initial |ω| (rad/s) of ``reset(options={"random": True})`` unless ``"max_omega"`` is given
#: (Pendulum-v1 draws θ̇ from [−1, 1]).
DEFAULT_RANDOM_MAX_OMEGA = 1.0
#: Rotation (rad) per control period at a scene's speed scale, for a scene that declares no period:
#: the ``pendulum`` scene's ``h·ω_s = 0.05 s × √60 rad/s`` (the controllers were tuned there), so a
#: new scene is sampled as finely *in its own time* — a slow body gets a longer period, not a finer
#: timestep's hundreds of steps per horizon.
STEP_ANGLE = 0.05 * math.sqrt(60.0)
#: Weights of the quadratic cost (Pendulum-v1's): angle², |ω|², |u|².
COST_WEIGHTS = (1.0, 0.1, 0.001)

# What an MJCF's scales must allow (:meth:`RigidBodyEnv._check_scales`; the crafts' alike in
# envs.quadrotor_env). A body's speed scale is the faster of ω_s (the speed that carries it over its
# energy span, :attr:`RigidBodyEnv.speed_scale`) and the motor's ω_u = √(2π τ_max / J_max) (the speed its
# largest torque gives it from rest over half a turn): the speeds its task and its data reach.
#: The most a MuJoCo timestep may turn the body at its speed scale (rad). Data reach 1.2× the speed
#: scale (the excitation's 1.4× energy span); at 0.5 rad per step they turn at most 0.6 rad per step, so
#: even a period of one timestep stays inside the variational step's solvable region h|ω| ≲ 1
#: (DESIGN.md) and RK4's error per step (∝ (hω)⁵) stays below 1e-3. The families drawn over the ranges
#: a user brings reach 0.3; a 1 s step on the pendulum is 7.7, a 1e-9 kg rod under a 2 N·m motor 1e3.
MAX_STEP_ANGLE = 0.5
#: The most a control period (the model's step) may turn the body at its speed scale (rad): the
#: variational step's solvable region h|ω| ≲ 1 (DESIGN.md; singular at π/2). Past it unrolled Newton
#: returns silently wrong numbers. The default periods give 0.39 (``STEP_ANGLE``), the families ≤ 0.65.
MAX_PERIOD_ANGLE = 1.0
#: The weakest motor, as a share of the peak gravity torque, that can swing the body up: pumping gains
#: about 2τ/τ_g rad of amplitude per half swing (fvin_mpc.swingup.default_duration), so below 0.05 the
#: swing-up takes more than 16 natural periods and any damping may eat the gain; the families draw
#: 0.15–1.5, the weak pendulum of docs/custom_scene.md is 0.2. A 1e30 kg rod under 2 N·m is 4e-31.
MIN_MOTOR_SHARE = 0.05

_JOINT_TYPES = {int(mujoco.mjtJoint.mjJNT_HINGE): "hinge", int(mujoco.mjtJoint.mjJNT_BALL): "ball"}
_RESET_OPTIONS = frozenset({"qpos", "qvel", "random", "max_omega"})


def geodesic_angle(q: np.ndarray, p: np.ndarray) -> float:
    """Rotation angle in ``[0, π]`` between unit quaternions ``q`` and ``p``; sign invariant."""
    d = abs(float(np.dot(q, p)))
    # 2·atan2(√(1−d²), d) is accurate near 0 and π, unlike 2·acos(d) near 0.
    return 2.0 * math.atan2(math.sqrt(max(0.0, 1.0 - d * d)), d)


class MujocoBodyEnv(gymnasium.Env):
    """What the MuJoCo envs share (:class:`RigidBodyEnv`, :class:`envs.quadrotor_env.QuadrotorEnv`):
    the scene's model built with exactly its declared physics, the control period as a whole number
    of MuJoCo steps, the actuators as the action space, the accessors, stepping a whole or partial
    period, rendering and closing. A subclass sets ``_body_name``, ``_body_id``, ``_goal`` and its
    observation space, and aims the camera (:meth:`_aim_camera`)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}
    #: The declarable effects on the observation or the state that this env simulates beyond what
    #: every MuJoCo env does (noise on all entries, delay, mass); declaring another is refused.
    simulated_effects: frozenset[str] = frozenset()

    def __init__(self, scene: str | Path | SceneSpec, physics: ScenePhysics | None, control_period: float | None,
                 render_mode: str | None, width: int, height: int) -> None:
        spec = resolve_scene(scene)
        if spec.space is not self.space:
            raise ValueError(f"scene {spec.name!r} is on {spec.space.description}; {type(self).__name__} observes "
                             f"{self.space.description}")
        self.scene_spec: SceneSpec = spec
        self._model, self._physics = build_model(spec.xml_path, physics if physics is not None else spec.physics)
        unsimulated = [name for name, off in _EFFECTS_OFF.items()
                       if getattr(self._physics, name) != off and name not in self.simulated_effects]
        if unsimulated:
            raise SceneError(f"{type(self).__name__} does not simulate {unsimulated}; declare them off")
        self._data = mujoco.MjData(self._model)
        model = self._model
        # The plant as built, restored at each reset: a declared mass change alters the model in place.
        self._built_masses = (model.body_mass.copy(), model.body_inertia.copy(), model.body_ipos.copy(),
                              model.body_sameframe.copy(), model.body_simple.copy())
        self._mass_change_pending = self._physics.mass_change is not None
        self._built_gears = model.actuator_gear.copy()
        self._actuator_change_pending = self._physics.actuator_change is not None
        if self._physics.actuator_change is not None and not self._physics.actuator_change[1] < model.nu:
            raise SceneError(f"actuator_change names actuator {self._physics.actuator_change[1]}; the scene has "
                             f"{model.nu}")
        timestep = float(model.opt.timestep)
        # The commanded torques in flight, oldest first, one per MuJoCo timestep of actuation delay.
        self._delay_line = np.zeros((math.ceil(self._physics.actuation_delay_s / timestep - 1e-9), model.nu))

        #: Whether the period was chosen by the caller or the scene; if not, a subclass that knows the
        #: scene's time scale may choose it (:meth:`_set_control_period`).
        self._control_period_given = control_period is not None or spec.control_period is not None
        if control_period is None:
            control_period = spec.control_period or timestep * _min_frames(timestep)
        self._set_control_period(float(control_period))

        limited = self._physics.actuator_limits & model.actuator_ctrllimited.astype(bool)
        low = np.where(limited, model.actuator_ctrlrange[:, 0], -np.inf)
        high = np.where(limited, model.actuator_ctrlrange[:, 1], np.inf)
        self.action_space = spaces.Box(low=low, high=high, dtype=np.float64)

        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        self.render_mode = render_mode
        self._width, self._height = int(width), int(height)
        self._renderer: mujoco.Renderer | None = None
        self._camera: mujoco.MjvCamera | None = None

    def _set_control_period(self, control_period: float) -> None:
        self._frame_skip = _frame_skip(control_period, float(self._model.opt.timestep))
        self._dt = self._frame_skip * float(self._model.opt.timestep)
        self.metadata = {**type(self).metadata, "render_fps": round(1.0 / self._dt)}

    # ------------------------------------------------------------------ accessors
    @property
    def model(self) -> mujoco.MjModel:
        return self._model

    @property
    def data(self) -> mujoco.MjData:
        return self._data

    @property
    def physics(self) -> ScenePhysics:
        """The physics declaration actually simulated."""
        return self._physics

    @property
    def body_name(self) -> str:
        return self._body_name

    @property
    def dt(self) -> float:
        """Control period (s): ``frame_skip`` MuJoCo timesteps."""
        return self._dt

    @property
    def frame_skip(self) -> int:
        return self._frame_skip

    @property
    def goal(self) -> np.ndarray:
        """Goal orientation, unit quaternion (w, x, y, z), shape ``(4,)``."""
        return self._goal.copy()

    @property
    def torque_low(self) -> np.ndarray:
        return self.action_space.low.copy()

    @property
    def torque_high(self) -> np.ndarray:
        return self.action_space.high.copy()

    # ------------------------------------------------------------------ stepping, rendering
    def _advance(self, action: Any, substeps: int | None) -> np.ndarray:
        """Apply ``action`` (clipped to the action space; returned) for one control period
        (``frame_skip`` MuJoCo sub-steps) or for ``substeps`` of them."""
        u = as_float_array(action, (self._model.nu,), "action")
        u = np.clip(u, self.action_space.low, self.action_space.high)
        if substeps is not None and not 1 <= substeps <= self._frame_skip:
            raise ValueError(f"substeps must be in [1, {self._frame_skip}], got {substeps}")
        self._change_mass_when_due()
        self._before_advance()
        for _ in range(self._frame_skip if substeps is None else substeps):
            if len(self._delay_line):
                self._data.ctrl[:] = self._delay_line[0]
                self._delay_line = np.vstack([self._delay_line[1:], u])
            else:
                self._data.ctrl[:] = u
            mujoco.mj_step(self._model, self._data)
        # mj_step leaves positions/velocities-derived quantities (xpos, xquat, cvel, energy) at the
        # state *before* the last substep; bring them up to date.
        mujoco.mj_forward(self._model, self._data)
        return u

    def _change_mass_when_due(self) -> None:
        # Between (partial) periods, never inside a MuJoCo step: the model's constants change at once.
        change = self._physics.mass_change
        if self._mass_change_pending and self._data.time >= change[0] - 1e-9:
            if len(change) == 3:
                self._model.body_ipos[1:] += np.asarray(change[2])
                # MuJoCo's shortcuts for a body whose inertial frame is its own frame no longer hold.
                self._model.body_sameframe[1:] = 0
                self._model.body_simple[1:] = 0
            scale_mass(self._model, change[1])  # recomputes what MuJoCo derives, the shifted centres too
            self._mass_change_pending = False
        actuator = self._physics.actuator_change
        if self._actuator_change_pending and self._data.time >= actuator[0] - 1e-9:
            self._model.actuator_gear[actuator[1]] *= actuator[2]
            self._actuator_change_pending = False

    @property
    def mass_changed(self) -> bool:
        """Whether this episode's declared mass change (``physics.mass_change``) has come."""
        return self._physics.mass_change is not None and not self._mass_change_pending

    def _before_advance(self) -> None:
        """Whatever a subclass's declared effects do to the state at the start of a (partial) period."""

    def _aim_camera(self, camera: mujoco.MjvCamera) -> None:
        """Point the free camera (MuJoCo's default one on entry) at the task."""
        raise NotImplementedError

    def render(self):
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called without a render_mode; create the env with render_mode='rgb_array'"
            )
            return None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self._model, height=self._height, width=self._width)
            self._camera = mujoco.MjvCamera()
            mujoco.mjv_defaultFreeCamera(self._model, self._camera)
            self._aim_camera(self._camera)
        self._renderer.update_scene(self._data, camera=self._camera)
        return self._renderer.render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def _reset_options(self, seed: int | None, options: dict[str, Any] | None, known: frozenset[str]) -> dict[str, Any]:
        """``reset``'s start: gymnasium's seeding, then ``options`` (a copy) checked against the ``known`` names."""
        super().reset(seed=seed)
        options = {} if options is None else dict(options)
        unknown = set(options) - known
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; expected some of {sorted(known)}")
        return options

    def _reset_to(self, qpos: Any, qvel: Any) -> tuple[np.ndarray, dict[str, Any]]:
        """``reset``'s end: MuJoCo's data reset to the joint state ``qpos``, ``qvel``; its observation
        and info. Validated before the simulation is touched, so a bad option leaves it as it was."""
        qpos = as_float_array(qpos, (self._model.nq,), "qpos")
        qvel = as_float_array(qvel, (self._model.nv,), "qvel")
        if self.mass_changed:
            (self._model.body_mass[:], self._model.body_inertia[:], self._model.body_ipos[:],
             self._model.body_sameframe[:], self._model.body_simple[:]) = self._built_masses
            mujoco.mj_setConst(self._model, self._data)
        self._mass_change_pending = self._physics.mass_change is not None
        self._model.actuator_gear[:] = self._built_gears
        self._actuator_change_pending = self._physics.actuator_change is not None
        mujoco.mj_resetData(self._model, self._data)
        self._delay_line[:] = 0.0
        self.set_state(qpos, qvel)
        return self._observation(), self._info()


class RigidBodyEnv(MujocoBodyEnv):
    """Bring a rigid body on an actuated hinge or ball joint to a goal orientation.

    ## Description

    A MuJoCo scene (a built-in one from :data:`envs.scenes.SCENES` or any MJCF file) with one
    observed body, which hangs from the world on a single hinge or ball joint driven by one or
    more actuators. The built-in scenes are pendulums whose task is the swing-up: start hanging
    at rest, reach the upright orientation and stay there. ``pendulum`` has the physics of
    Gymnasium's Pendulum-v1 (``θ̈ = −15 sin θ + 3τ``, but θ = 0 *hanging*, see
    :mod:`envs.pendulum_v1` for the conversion); ``pendulum_damped`` adds joint damping 0.1;
    ``spherical_pendulum`` is a body with a cross bar on a ball joint with a motor per body axis.

    Only the effects the scene's :class:`~envs.scenes.ScenePhysics` declares are simulated
    (gravity, joint damping, dry friction, actuator limits, contact, sensor noise, and the plant
    perturbations a model does not know: gyro noise, encoder quantization, actuation delay, a scaled
    mass, a knock while holding); MuJoCo's other effects are switched off (:func:`envs.scenes.build_model`).

    ## Action Space

    ``ndarray`` of shape ``(nu,)``, float64: the actuators' controls (for the built-in scenes,
    torques in N·m). Bounded by the actuators' ``ctrlrange`` when the physics declares actuator
    limits, unbounded otherwise. Actions outside the bounds are clipped to them (MuJoCo would
    clamp them too); a wrong shape or a non-finite entry raises ``ValueError`` and sends nothing.

    | Scene                | Num | Action                     | Min  | Max |
    |----------------------|-----|----------------------------|------|-----|
    | `pendulum(_damped)`  | 0   | torque about the hinge (+y)| -2.0 | 2.0 |
    | `spherical_pendulum` | 0–2 | torque about body x, y, z  | -1.5 | 1.5 |

    ## Observation Space

    ``ndarray`` of shape ``(7,)``, float64: the body's world orientation and its angular velocity
    in the body frame (``Ṙ = R[ω]×``), i.e. the state ``x = (q, ω)`` of ``DESIGN.md``.

    | Num | Observation                                  | Min  | Max |
    |-----|----------------------------------------------|------|-----|
    | 0   | q_w, scalar part of the orientation (`xquat`) | -1.0 | 1.0 |
    | 1   | q_x                                          | -1.0 | 1.0 |
    | 2   | q_y                                          | -1.0 | 1.0 |
    | 3   | q_z                                          | -1.0 | 1.0 |
    | 4   | ω_x, body-frame angular velocity (rad/s)     | -Inf | Inf |
    | 5   | ω_y                                          | -Inf | Inf |
    | 6   | ω_z                                          | -Inf | Inf |

    The quaternion order is (w, x, y, z), MuJoCo's. ``q`` and ``−q`` are the same rotation; the
    sign MuJoCo reports is left as is. For the planar pendulum ``q = (cos θ/2, 0, sin θ/2, 0)``
    and ``ω = (0, θ̇, 0)``. If the physics declares ``sensor_noise_std > 0``, Gaussian noise of
    that standard deviation (from the env's ``np_random``) is added to all 7 entries and ``q`` is
    renormalized; reward and ``info`` use the noise-free state.

    ## Rewards

    In the style of Pendulum-v1:

    *r = -(angle² + 0.1 |ω|² + 0.001 |u|²)*

    where *angle* ∈ [0, π] is the sign-invariant geodesic angle between the body's orientation and
    the goal (``2 atan2(√(1−⟨q,g⟩²), |⟨q,g⟩|)``), ω the true body-frame angular velocity after the
    step and u the (clipped) action applied. The maximum reward is 0 (at the goal, at rest, u = 0).

    ## Starting State

    Hanging at rest: the scene's rest orientation (:attr:`rest`, the potential's minimum unless the
    scene declares it) with zero velocity — the hard start of the swing-up, whatever ``qpos0`` the
    MJCF was written with. ``reset(options=...)`` accepts:

    - ``{"qpos": ..., "qvel": ...}``: the joint state exactly (either may be omitted: the rest
      position / zero). Shapes ``(1,)``/``(1,)`` for a hinge (angle in rad, rate in rad/s), ``(4,)``/``(3,)``
      for a ball (quaternion (w, x, y, z), normalized here; body-frame angular velocity).
    - ``{"random": True, "max_omega": 1.0}``: an orientation uniform over the joint's range (hinge
      angle uniform in [−π, π), ball quaternion uniform on S³) and an angular velocity uniform in
      ``|ω| ≤ max_omega`` (an interval for a hinge, a ball for a ball joint), drawn from the env's
      ``np_random``. ``max_omega`` defaults to :data:`DEFAULT_RANDOM_MAX_OMEGA` = 1 rad/s.

    ## Episode End

    ``terminated`` is always ``False``. The registered ids truncate after 200 steps (10 s) through
    Gymnasium's ``TimeLimit``.

    ## Info

    ``angle_from_goal`` (rad, noise-free), ``time`` (simulated s), ``energy`` (MuJoCo's total
    mechanical energy ``data.energy.sum()``, J; potential energy counts only while gravity acts).

    ## Arguments

    - ``scene``: built-in scene name (``"pendulum"``, ``"pendulum_damped"``,
      ``"spherical_pendulum"``), a path to an MJCF file, or a :class:`~envs.scenes.SceneSpec`
      (:func:`~envs.scenes.resolve_scene`: a path to a built-in's file is that scene). Default ``"pendulum"``.
    - ``body``: the observed body. Default: the scene's; else the only body with a joint
      (``ValueError`` if there are several).
    - ``goal``: goal orientation quaternion (w, x, y, z), normalized here. Default: the scene's
      declared goal; else the maximum of the body's potential (upright, ``(0, 0, 1, 0)`` for the
      built-ins), read off the MJCF (``ValueError`` if there is none: no gravity, or the centre of
      mass on the pivot).
    - ``physics``: the :class:`~envs.scenes.ScenePhysics` to simulate. Default: the scene's; for an
      MJCF, :func:`~envs.scenes.infer_physics` (what the file would simulate).
    - ``control_period``: seconds per step, a whole multiple of the MJCF timestep. Default: the
      scene's (0.05 s for the built-ins); else one chosen from the scene's speed scale
      (:func:`scale_control_period`: the multiple of the timestep nearest to ``STEP_ANGLE / ω_s``,
      at least :data:`~envs.scenes.MIN_CONTROL_PERIOD`, 20 ms); for a body the closed form cannot
      read, the smallest multiple of the timestep that is at least 20 ms.
    - ``render_mode``: ``None`` or ``"rgb_array"`` (``MUJOCO_GL=egl`` headless); ``width``,
      ``height``: image size in pixels (at most the MJCF's offscreen buffer, 640×480 built in).

    Requirements on the MJCF (``ValueError`` otherwise): the body has exactly one joint, a hinge
    or a ball, and it is the model's only degree of freedom (so that ``(q, ω)`` is the whole
    state); every actuator drives that joint and has no internal state.

    ## Version History

    * v0: initial version (``fvin_mpc/Pendulum-v0``, ``fvin_mpc/PendulumDamped-v0``,
      ``fvin_mpc/SphericalPendulum-v0``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}
    #: The configuration space of the observations (:mod:`fvin_mpc.core.space`).
    space: ConfigurationSpace = S3
    simulated_effects = frozenset({"gyro_noise_std", "encoder_bits", "impulse_delta_omega"})

    def __init__(
        self,
        scene: str | Path = "pendulum",
        body: str | None = None,
        goal: Any = None,
        physics: ScenePhysics | None = None,
        control_period: float | None = None,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
    ) -> None:
        super().__init__(scene, physics, control_period, render_mode, width, height)
        spec, model = self.scene_spec, self._model

        body = body or spec.body or _only_jointed_body(model)
        self._body_id, self._joint_id = _validate_body_and_joint(model, body)
        self._body_name = body
        self._joint_type = _JOINT_TYPES[int(model.jnt_type[self._joint_id])]
        if self._physics.encoder_bits is not None and self._joint_type != "hinge":
            raise SceneError("encoder_bits quantizes a hinge angle; the scene's joint is a ball joint")
        #: The knock's state: ``None`` once it has come, else the time since when the body is held (or ``None``).
        self._knock_pending, self._held_since = self._physics.impulse_delta_omega > 0.0, None

        derived_goal, self._rest_qpos = self._task_from_potential()
        derived_goal = _canonical_sign(derived_goal)
        self._goal = unit_quaternion(goal if goal is not None else spec.goal if spec.goal is not None else derived_goal,
                                     "goal")
        if spec.rest is not None:
            self._rest_qpos = self._qpos_of_orientation(unit_quaternion(spec.rest, "rest"))
        self._set_joint_state(self._rest_qpos, np.zeros(model.nv))
        self._rest = self._data.xquat[self._body_id].copy()
        self._scales: tuple[float, float] | None = None
        if not self._control_period_given:
            try:
                self._set_control_period(scale_control_period(self.speed_scale, float(model.opt.timestep)))
            except ValueError:
                pass  # a body the closed form cannot read keeps the timestep rule (the scales say why when asked)
        self._check_scales()

        obs_high = np.array([1.0] * 4 + [np.inf] * 3)
        self.observation_space = spaces.Box(low=-obs_high, high=obs_high, dtype=np.float64)

    # ------------------------------------------------------------------ accessors
    @property
    def energy_span(self) -> float:
        """``|U(goal) − U(rest)|`` (J), read off the MJCF (the closed-form body of
        :func:`~fvin_mpc.core.rigid_body.from_mujoco`): the energy a swing-up must gain.

        Raises:
            ValueError: the body is one ``from_mujoco`` cannot read, or goal and rest have the same
                potential (nothing to swing up).
        """
        return self._energy_and_speed()[0]

    @property
    def speed_scale(self) -> float:
        """``ω_s = √(2·energy_span / J_max)`` (rad/s), ``J_max`` the largest principal inertia about
        the pivot: the speed that carries the body over the whole energy span — the scene's time
        scale, from which its default control period (:func:`scale_control_period`) and the
        controllers' settings are derived. Raises as :attr:`energy_span`."""
        return self._energy_and_speed()[1]

    def _energy_and_speed(self) -> tuple[float, float]:
        if self._scales is None:
            terms = from_mujoco(self._model, self._body_name).terms(get_ops("numpy"))
            span = abs(float(terms.potential(tuple(self._goal))) - float(terms.potential(tuple(self._rest))))
            if not span > 0.0:
                raise ValueError("the scene's goal and rest have the same potential energy: nothing to swing up")
            inertia = np.array(terms.inertia(tuple(self._rest)), dtype=float)
            self._scales = (span, math.sqrt(2.0 * span / float(np.linalg.eigvalsh(inertia).max())))
        return self._scales

    def _check_scales(self) -> None:
        """``SceneError`` for a body whose motor cannot move it (:data:`MIN_MOTOR_SHARE`), whose timestep does
        not resolve its speed scale (:data:`MAX_STEP_ANGLE`) or whose control period the model's step cannot
        take (:data:`MAX_PERIOD_ANGLE`). A body the closed form cannot read, or with nothing to swing up, is
        not judged here (its scales say why when a controller asks for them); an unbounded motor has no
        torque to judge (the commands refuse it: :func:`~fvin_mpc.envs.scenes.check_bounded_controls`)."""
        try:
            span, speed = self._energy_and_speed()
            axes = np.asarray(from_mujoco(self._model, self._body_name).actuator_axes, dtype=float)
        except ValueError:
            return
        name = self.scene_spec.name
        inertia = 2.0 * span / speed**2  # the largest principal inertia about the pivot (speed_scale)
        bounds = np.maximum(np.abs(self.action_space.low), np.abs(self.action_space.high))
        bounded = np.isfinite(bounds)
        fastest = speed
        if np.any(bounded):
            torque = float(np.max(bounds[bounded] * np.linalg.norm(axes[:, bounded], axis=0)))
            gravity_torque = span / 2.0
            if torque < MIN_MOTOR_SHARE * gravity_torque:
                mass = float(self._model.body_subtreemass[self._body_id])
                raise SceneError(
                    f"scene {name!r}: the motor cannot move the body: its largest torque {torque:.3g} N·m is "
                    f"{torque / gravity_torque:.3g} of the peak gravity torque {gravity_torque:.3g} N·m (a swing-up "
                    f"needs at least {MIN_MOTOR_SHARE:g}); check the body's mass ({mass:.3g} kg) and the actuators' "
                    "gear and ctrlrange")
            fastest = max(speed, math.sqrt(2.0 * math.pi * torque / inertia))
        timestep = float(self._model.opt.timestep)
        if timestep * fastest > MAX_STEP_ANGLE:
            raise SceneError(
                f"scene {name!r}: the timestep {timestep:g} s does not resolve the body's speed scale "
                f"{fastest:.3g} rad/s (it turns {timestep * fastest:.3g} rad per step, at most {MAX_STEP_ANGLE:g}): "
                f"use a timestep of at most {MAX_STEP_ANGLE / fastest:.2g} s, or check the body's mass and inertia "
                "and the actuators' gear")
        if self._dt * fastest > MAX_PERIOD_ANGLE:
            raise SceneError(
                f"scene {name!r}: a control period of {self._dt:g} s turns the body {self._dt * fastest:.3g} rad "
                f"per step at its speed scale {fastest:.3g} rad/s, past the {MAX_PERIOD_ANGLE:g} rad a model's step "
                f"can take: use a control period of at most {MAX_PERIOD_ANGLE / fastest:.2g} s")

    @property
    def joint_type(self) -> str:
        """``"hinge"`` or ``"ball"``."""
        return self._joint_type

    @property
    def joint_axis(self) -> np.ndarray | None:
        """A hinge's axis in the body frame (unit, ``(3,)``); ``None`` for a ball joint."""
        if self._joint_type != "hinge":
            return None
        axis = np.asarray(self._model.jnt_axis[self._joint_id], dtype=float)
        return axis / np.linalg.norm(axis)

    @property
    def rest(self) -> np.ndarray:
        """The potential's minimum (hanging), unit quaternion (w, x, y, z), shape ``(4,)``: where
        episodes start by default, and the energy reference of the controllers."""
        return self._rest.copy()

    @property
    def rest_qpos(self) -> np.ndarray:
        """The joint position of :attr:`rest`."""
        return self._rest_qpos.copy()

    @property
    def goal_qpos(self) -> np.ndarray:
        """The joint position of :attr:`goal` (a hinge: the angle about its axis nearest to it)."""
        return self._qpos_of_orientation(self._goal)

    def state(self) -> np.ndarray:
        """The noise-free state ``x = (q, ω)`` ``(7,)``: body orientation (w, x, y, z), body-frame ω."""
        velocity = np.zeros(6)
        # mjOBJ_XBODY: the body's own frame (xquat's); mjOBJ_BODY would give ω in its inertial frame (ximat),
        # which differs whenever the principal axes are not the body's axes (a composite, an off-axis rod).
        mujoco.mj_objectVelocity(self._model, self._data, mujoco.mjtObj.mjOBJ_XBODY, self._body_id, velocity, 1)
        return self.space.layout.join(self._data.xquat[self._body_id], velocity[:3])

    def set_state(self, qpos: Any, qvel: Any) -> None:
        """Set the joint state exactly (see the class docstring for shapes) and run ``mj_forward``.

        A ball joint's quaternion is normalized. ``ValueError`` on a wrong shape or a non-finite
        entry (the state is then left unchanged).
        """
        qpos = as_float_array(qpos, (self._model.nq,), "qpos")
        qvel = as_float_array(qvel, (self._model.nv,), "qvel")
        self._set_joint_state(qpos, qvel)

    def _set_joint_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        if self._joint_type == "ball":
            qpos = unit_quaternion(qpos, "ball-joint qpos")
        self._data.qpos[:] = qpos
        self._data.qvel[:] = qvel
        mujoco.mj_forward(self._model, self._data)

    # ------------------------------------------------------------------ task
    def _task_from_potential(self) -> tuple[np.ndarray, np.ndarray]:
        """``(goal orientation, rest qpos)``: the maximum and the minimum of the body's potential.

        A single rigid body under uniform gravity has ``U = −m g·c_world``, so on a hinge
        ``U(θ) = A cos θ + B sin θ + C`` exactly (four samples give ``A``, ``B``), and on a ball
        joint the extrema put the centre of mass straight above / below the pivot (the smallest
        rotation from the MJCF's ``qpos0`` that does so; about the axis nearest to world y when the
        centre of mass starts exactly below or above). Without gravity, or with the centre of mass
        on the pivot, there is no task to read off: the scene must declare ``goal`` and ``rest``.
        """
        model, data = self._model, self._data
        gravity = np.asarray(model.opt.gravity, dtype=float)
        # A body with child bodies (rigidly attached: the joint is the model's only dof) hangs by
        # its subtree's centre of mass; a single body's is its own (read as before, to the bit).
        composite = bool(np.any(model.body_parentid[self._body_id + 1:] == self._body_id))
        mass = float(model.body_subtreemass[self._body_id] if composite else model.body_mass[self._body_id])
        com = (lambda: data.subtree_com[self._body_id]) if composite else (lambda: data.xipos[self._body_id])
        if self._joint_type == "hinge":
            samples = []
            for angle in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi):
                self._set_joint_state(np.array([angle]), np.zeros(1))
                samples.append(-mass * float(gravity @ com()))
            a, b = 0.5 * (samples[0] - samples[2]), 0.5 * (samples[1] - samples[3])
            if math.hypot(a, b) < 1e-12:
                self._no_task()
            top = math.atan2(b, a)
            self._set_joint_state(np.array([top]), np.zeros(1))
            goal = data.xquat[self._body_id].copy()
            return goal, np.array([math.remainder(top + math.pi, 2 * math.pi)])
        self._set_joint_state(np.asarray(model.qpos0, dtype=float), np.zeros(3))
        reach = com() - data.xanchor[self._joint_id]
        if np.linalg.norm(gravity) == 0.0 or np.linalg.norm(reach) < 1e-12:
            self._no_task()
        down = gravity / np.linalg.norm(gravity)
        start = data.xquat[self._body_id].copy()
        goal = _rotate_towards(start, reach, -down)
        rest = _rotate_towards(start, reach, down)
        return goal, self._qpos_of_orientation(rest)

    def _no_task(self) -> None:
        raise SceneError(f"scene {self.scene_spec.name!r}: the potential has no maximum to read the task off "
                         "(no gravity, or the centre of mass on the pivot); declare goal and rest")

    def _qpos_of_orientation(self, orientation: np.ndarray) -> np.ndarray:
        """The joint position at which the body has ``orientation`` (a ball joint: exactly; a hinge:
        the angle about its axis nearest to it)."""
        parent = self._data.xquat[self._model.body_parentid[self._body_id]]
        local = _quaternion_product(
            _quaternion_conjugate(_quaternion_product(parent, self._model.body_quat[self._body_id])), orientation
        )
        if self._joint_type == "ball":
            return local / np.linalg.norm(local)
        axis = self._model.jnt_axis[self._joint_id]
        return np.array([2.0 * math.atan2(float(local[1:] @ axis), float(local[0]))])

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        options = self._reset_options(seed, options, _RESET_OPTIONS)
        if options.get("random", False):
            if "qpos" in options or "qvel" in options:
                raise ValueError("reset options: give either 'random' or 'qpos'/'qvel', not both")
            qpos, qvel = self._random_joint_state(float(options.get("max_omega", DEFAULT_RANDOM_MAX_OMEGA)))
        else:
            if "max_omega" in options:
                raise ValueError("reset option 'max_omega' only applies with 'random': True")
            qpos = options.get("qpos", self._rest_qpos)
            qvel = options.get("qvel", np.zeros(self._model.nv))
        self._knock_pending, self._held_since = self._physics.impulse_delta_omega > 0.0, None
        return self._reset_to(qpos, qvel)

    def step(self, action: Any, substeps: int | None = None):
        """One control period (``frame_skip`` MuJoCo sub-steps) under ``action``; ``substeps`` runs
        only that many sub-steps (a torque that changes within a period, as a latency-aware closed
        loop delivers it: :func:`fvin_mpc.control.closed_loop.run_episode`)."""
        u = self._advance(action, substeps)
        state, attitude = self.state(), self.space.layout.attitude(by=type(self).__name__)
        q, omega = state[attitude.quaternion], state[attitude.omega]
        angle = geodesic_angle(q, self._goal)
        if self._knock_pending:
            held = angle < IMPULSE_HOLD_TOLERANCE
            self._held_since = (self._held_since if self._held_since is not None else self._data.time) if held else None
        w_angle, w_omega, w_u = COST_WEIGHTS
        reward = -(w_angle * angle**2 + w_omega * float(omega @ omega) + w_u * float(u @ u))
        return self._observation(), reward, False, False, self._info(angle)

    def _before_advance(self) -> None:
        # The knock lands between periods (or partial periods), never inside a MuJoCo step.
        at = self._physics.impulse_at_s
        if at is not None:
            due = self._knock_pending and self._data.time >= at - 1e-9
        else:
            due = (self._knock_pending and self._held_since is not None
                   and self._data.time - self._held_since >= IMPULSE_HOLD_S - 1e-9)
        if not due:
            return
        delta = self._physics.impulse_delta_omega
        start = int(self._model.jnt_dofadr[self._joint_id])
        if self._joint_type == "hinge":
            self._data.qvel[start] += delta * (1.0 if self.np_random.uniform() < 0.5 else -1.0)
        else:  # a ball joint's qvel is the body-frame ω
            direction = self.np_random.normal(size=3)
            self._data.qvel[start:start + 3] += delta * direction / np.linalg.norm(direction)
        mujoco.mj_forward(self._model, self._data)
        self._knock_pending = False

    @property
    def knocked(self) -> bool:
        """Whether this episode's knock (``physics.impulse_delta_omega``) has come."""
        return self._physics.impulse_delta_omega > 0.0 and not self._knock_pending

    def _aim_camera(self, camera: mujoco.MjvCamera) -> None:
        camera.lookat[:] = self._data.xpos[self._body_id]
        camera.azimuth, camera.elevation = 90.0, -15.0
        camera.distance = 1.5 * float(self._model.stat.extent)

    # ------------------------------------------------------------------ internals
    def _observation(self) -> np.ndarray:
        observation, attitude = self.state(), self.space.layout.attitude(by=type(self).__name__)
        bits = self._physics.encoder_bits
        if bits is not None:
            angle = float(self._data.qpos[self._model.jnt_qposadr[self._joint_id]])
            error = round(angle / (2.0 * math.pi) * 2**bits) * (2.0 * math.pi) / 2**bits - angle
            # A hinge turns the body about its axis, fixed in the body frame: a body-frame rotation by the error.
            axis = self.joint_axis
            turn = np.concatenate([[math.cos(0.5 * error)], math.sin(0.5 * error) * axis])
            observation[attitude.quaternion] = _quaternion_product(observation[attitude.quaternion], turn)
        if self._physics.gyro_noise_std > 0.0:
            noise = self.np_random.normal(0.0, self._physics.gyro_noise_std, size=3)
            if self._physics.gyro_axes == "joint" and self._joint_type == "hinge":
                noise = float(noise @ self.joint_axis) * self.joint_axis
            observation[attitude.omega] += noise
        noise_std = self._physics.sensor_noise_std
        if noise_std > 0.0:
            observation = observation + self.np_random.normal(0.0, noise_std, size=self.space.state_dim)
            observation[attitude.quaternion] /= np.linalg.norm(observation[attitude.quaternion])
        # Guard the [-1, 1] bounds against a one-ulp excess from normalization.
        observation[attitude.quaternion] = np.clip(observation[attitude.quaternion], -1.0, 1.0)
        return observation

    def _info(self, angle: float | None = None) -> dict[str, float]:
        if angle is None:
            angle = geodesic_angle(self._data.xquat[self._body_id], self._goal)
        return {
            "angle_from_goal": angle,
            "time": float(self._data.time),
            "energy": float(self._data.energy.sum()),
        }

    def _random_joint_state(self, max_omega: float) -> tuple[np.ndarray, np.ndarray]:
        if not (math.isfinite(max_omega) and max_omega >= 0.0):
            raise ValueError(f"reset option max_omega must be finite and >= 0, got {max_omega!r}")
        rng = self.np_random
        if self._joint_type == "hinge":
            return rng.uniform(-np.pi, np.pi, size=1), rng.uniform(-max_omega, max_omega, size=1)
        quaternion = rng.normal(size=4)
        direction = rng.normal(size=3)
        radius = max_omega * rng.uniform() ** (1.0 / 3.0)  # uniform in the ball |ω| ≤ max_omega
        return quaternion / np.linalg.norm(quaternion), direction / np.linalg.norm(direction) * radius


# ---------------------------------------------------------------------- helpers
def _only_jointed_body(model: mujoco.MjModel) -> str:
    jointed = [b for b in range(model.nbody) if model.body_jntnum[b] > 0]
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in jointed]
    if len(jointed) != 1:
        raise SceneError(
            f"the MJCF has {len(jointed)} bodies with joints ({names}); pass body=... to choose the observed one"
        )
    if names[0] is None:
        raise SceneError("the only body with a joint has no name; name it in the MJCF")
    return names[0]


def _validate_body_and_joint(model: mujoco.MjModel, body: str) -> tuple[int, int]:
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, model.nbody)]
        raise SceneError(f"no body named {body!r} in the MJCF; bodies: {names}")
    if model.body_jntnum[body_id] != 1:
        raise SceneError(
            f"body {body!r} must have exactly one joint (a hinge or a ball), it has {model.body_jntnum[body_id]}"
        )
    joint_id = int(model.body_jntadr[body_id])
    joint_type = int(model.jnt_type[joint_id])
    if joint_type not in _JOINT_TYPES:
        raise SceneError(
            f"body {body!r}: its joint must be a hinge or a ball, got {mujoco.mjtJoint(joint_type).name}"
        )
    if model.nv != (1 if joint_type == int(mujoco.mjtJoint.mjJNT_HINGE) else 3):
        raise SceneError(
            f"the body's joint must be the model's only degree of freedom (so that (q, ω) is the whole state); "
            f"the model has nv={model.nv}"
        )
    if model.nu == 0:
        raise SceneError(f"body {body!r}: its joint is not actuated (the MJCF has no actuators)")
    for a in range(model.nu):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f"#{a}"
        if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT or model.actuator_trnid[a, 0] != joint_id:
            raise SceneError(f"actuator {name!r} must drive the joint of body {body!r} directly")
        if model.actuator_gainprm[a, 0] != 1.0:  # from_mujoco reads a torque as gear × control
            raise SceneError(f"actuator {name!r} has gain {model.actuator_gainprm[a, 0]:g}: the package reads a "
                             "motor's torque as gear × control; fold the gain into the gear")
    if model.na > 0:
        raise SceneError(
            "actuators with internal state (dyntype != none) are not supported: (q, ω) would not be the whole state"
        )
    return body_id, joint_id


def scale_control_period(speed_scale: float, timestep: float) -> float:
    """The control period of a scene that declares none: the whole multiple of ``timestep`` nearest
    to :data:`STEP_ANGLE` ``/ speed_scale``, and at least :data:`~envs.scenes.MIN_CONTROL_PERIOD`.

    One rule for every consumer: ``collect`` records at the env's period, ``train`` learns a model
    of that step, and the controllers plan on it, so a model step never follows a fine simulator
    timestep (a 4 ms timestep would otherwise give a slow body horizons of hundreds of steps).
    """
    frames = max(_min_frames(timestep), round(STEP_ANGLE / speed_scale / timestep))
    return frames * timestep


def _min_frames(timestep: float) -> int:
    return max(1, math.ceil(MIN_CONTROL_PERIOD / timestep - 1e-9))


def _frame_skip(control_period: float, timestep: float) -> int:
    if not (math.isfinite(control_period) and control_period > 0.0):
        raise UsageError(f"control_period must be finite and > 0, got {control_period!r}")
    frame_skip = round(control_period / timestep)
    if frame_skip < 1 or abs(frame_skip * timestep - control_period) > 1e-9 * control_period:
        raise UsageError(
            f"control_period {control_period} s must be a whole multiple of the MJCF timestep {timestep} s"
        )
    return int(frame_skip)


def _quaternion_product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    result = np.zeros(4)
    mujoco.mju_mulQuat(result, np.asarray(p, dtype=float), np.asarray(q, dtype=float))
    return result


def _canonical_sign(q: np.ndarray) -> np.ndarray:
    """``q`` or ``−q`` (the same rotation), whichever has its first non-negligible component positive."""
    first = q[int(np.argmax(np.abs(q) > 1e-12))]
    return q if first > 0 else -q


def _quaternion_conjugate(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def _rotate_towards(orientation: np.ndarray, vector: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``orientation`` premultiplied by the smallest world rotation taking ``vector``'s direction to ``target``."""
    v, target = vector / np.linalg.norm(vector), target / np.linalg.norm(target)
    axis = np.cross(v, target)
    cos_angle = float(np.clip(v @ target, -1.0, 1.0))
    if np.linalg.norm(axis) < 1e-9:
        if cos_angle > 0:
            return orientation.copy()
        # Opposite directions: turn half a revolution about the axis ⟂ v nearest to world y.
        axis = np.array([0.0, 1.0, 0.0]) - v[1] * v
        if np.linalg.norm(axis) < 1e-9:
            axis = np.array([1.0, 0.0, 0.0]) - v[0] * v
    axis = axis / np.linalg.norm(axis)
    angle = math.atan2(float(np.linalg.norm(np.cross(v, target))), cos_angle)
    turn = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])
    return _quaternion_product(turn, orientation)


# ---------------------------------------------------------------------- registration
#: Registered ids: ``gymnasium.make(id)`` after ``import envs``.
ENV_IDS = {
    "fvin_mpc/Pendulum-v0": "pendulum",
    "fvin_mpc/PendulumDamped-v0": "pendulum_damped",
    "fvin_mpc/SphericalPendulum-v0": "spherical_pendulum",
}
MAX_EPISODE_STEPS = 200


def register_envs() -> None:
    """Register the built-in scenes with Gymnasium (idempotent): see :data:`ENV_IDS`."""
    for env_id, scene in ENV_IDS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="fvin_mpc.envs.rigid_body_env:RigidBodyEnv",
            kwargs={"scene": scene},
            max_episode_steps=MAX_EPISODE_STEPS,
        )
