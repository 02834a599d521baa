"""A Gymnasium environment over a MuJoCo free body with rotors: the ``quadrotor`` scene.

The observation is the 13-number state of ``docs/r3s3.md``, ``(x, q, v, ω)``: position and
velocity in the world frame, orientation quaternion ``(w, x, y, z)``, body-frame angular velocity.
The physics is built with :func:`envs.scenes.build_model`, so every effect the scene does not
declare is switched off (there is no floor and no contact: the craft can fall forever).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces

from fvin_mpc.core.space import R3S3, ConfigurationSpace
from fvin_mpc.core.state import as_float_array, unit_quaternion

from .rigid_body_env import MujocoBodyEnv, geodesic_angle
from .scenes import ScenePhysics, SceneSpec

#: Largest initial |ω| (rad/s) of a default reset: a tumbling craft (the recovery task of ``python -m fvin_mpc.fly``).
DEFAULT_RESET_MAX_OMEGA = 10.0
#: Weights of the quadratic cost: |x − x*|², angle², |v|², |ω|², |u − u_hover|².
COST_WEIGHTS = (1.0, 1.0, 0.1, 0.01, 0.01)

_RESET_OPTIONS = frozenset({"qpos", "qvel", "hover", "max_omega", "max_speed", "max_offset"})


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
    | 0–2   | x, position of the body origin (the centre of mass), world (m) | -Inf | Inf |
    | 3–6   | q (w, x, y, z), orientation body → world (`xquat`)             | -1.0 | 1.0 |
    | 7–9   | v, linear velocity, world frame (m/s)                          | -Inf | Inf |
    | 10–12 | ω, angular velocity, body frame (rad/s), ``Ṙ = R[ω]×``          | -Inf | Inf |

    These are MuJoCo's free-joint coordinates: ``qvel[:3]`` is the world-frame linear velocity of
    the body origin and ``qvel[3:]`` the body-frame angular velocity (checked against
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
    - ``hover_point``: the goal position (m); default the body's position in the MJCF.
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
        super().__init__(scene, physics, control_period, render_mode, width, height)
        spec, model = self.scene_spec, self._model
        self._body_name = spec.body or "quadrotor"
        self._body_id, self._joint_id = _free_body(model, self._body_name)

        qpos0 = np.asarray(model.qpos0, dtype=float)
        self._hover_point = (qpos0[:3].copy() if hover_point is None
                             else as_float_array(hover_point, (3,), "hover_point"))
        self._goal = unit_quaternion(spec.goal if spec.goal is not None else (1.0, 0.0, 0.0, 0.0), "goal")
        weight = -float(model.body_subtreemass[self._body_id]) * float(model.opt.gravity[2])
        if not self._physics.gravity:
            weight = 0.0
        self._hover_thrust = np.full(model.nu, weight / max(model.nu, 1))

        obs_high = np.array([np.inf] * 3 + [1.0] * 4 + [np.inf] * 6)
        self.observation_space = spaces.Box(low=-obs_high, high=obs_high, dtype=np.float64)
        self._set_joint_state(*self._hover_joint_state())

    # ------------------------------------------------------------------ accessors (and MujocoBodyEnv's)
    @property
    def hover_point(self) -> np.ndarray:
        """Goal position (m), world frame."""
        return self._hover_point.copy()

    @property
    def goal_state(self) -> np.ndarray:
        """The 13-number hover state: at the hover point, level, at rest."""
        return np.concatenate([self._hover_point, self._goal, np.zeros(6)])

    @property
    def hover_thrust(self) -> np.ndarray:
        """Per-rotor thrust that holds the level craft at rest, ``m g / nu`` each (N), ``(nu,)``."""
        return self._hover_thrust.copy()

    def state(self) -> np.ndarray:
        """The noise-free state ``(x, q, v, ω)`` ``(13,)`` (see the class docstring)."""
        qvel = self._data.qvel
        return np.concatenate([self._data.xpos[self._body_id], self._data.xquat[self._body_id], qvel[:3], qvel[3:6]])

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
        return np.concatenate([self._hover_point, self._goal]), np.zeros(6)

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        options = self._reset_options(seed, options, _RESET_OPTIONS)
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
                   + w_v * float(state[7:10] @ state[7:10]) + w_omega * float(state[10:] @ state[10:])
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
            observation[3:7] /= np.linalg.norm(observation[3:7])
        observation[3:7] = np.clip(observation[3:7], -1.0, 1.0)
        return observation

    def _info(self) -> dict[str, float]:
        return {
            "angle_from_goal": geodesic_angle(self._data.xquat[self._body_id], self._goal),
            "position_error": float(np.linalg.norm(self._data.xpos[self._body_id] - self._hover_point)),
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
        qpos = np.concatenate([position, quaternion / np.linalg.norm(quaternion)])
        return qpos, np.concatenate([uniform_in_ball(rng, max_speed), uniform_in_ball(rng, max_omega)])


def uniform_in_ball(rng: np.random.Generator, radius: float) -> np.ndarray:
    """A point uniform in the ball ``|p| ≤ radius`` of R³."""
    direction = rng.normal(size=3)
    return direction / np.linalg.norm(direction) * radius * rng.uniform() ** (1.0 / 3.0)


def _free_body(model: mujoco.MjModel, body: str) -> tuple[int, int]:
    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, model.nbody)]
        raise ValueError(f"no body named {body!r} in the MJCF; bodies: {names}")
    if model.body_jntnum[body_id] != 1 or int(model.jnt_type[model.body_jntadr[body_id]]) != int(
        mujoco.mjtJoint.mjJNT_FREE
    ):
        raise ValueError(f"body {body!r} must have exactly one joint, a free joint")
    if model.nv != 6 or model.body_parentid[body_id] != 0:
        raise ValueError(f"the free joint of body {body!r} (a child of the world) must be the model's only "
                         f"degree of freedom; the model has nv={model.nv}")
    if model.nu == 0:
        raise ValueError("the MJCF has no actuators")
    if model.na > 0:
        raise ValueError("actuators with internal state (dyntype != none) are not supported")
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
