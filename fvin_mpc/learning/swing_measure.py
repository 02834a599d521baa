"""A model measure that predicts control: the energy a swing at full torque gains, plant against model.

A swing-up ends with a climb under a saturated motor: whether the body arrives upright depends on
the energy the motor puts in against gravity and the damping takes out over that climb. The
rollout loss weighs every transition of the data alike and barely sees it (on the weak, damped point
pendulum of docs/excitation.md, training longer lowered the validation loss and made the learned damping
worse; the MPC of a model whose last climb ends 1° from upright, where the plant's ends 15° short, never
swings the body up).

:func:`swing_probe` rolls the plant (MuJoCo) once from hanging at speeds of 0.6–1.3 ``ω_s`` (the
speed that carries the body over the energy span ``ΔE``; both directions on a hinge, directions
across the horizontal plane on a ball joint) with every actuator at its bound in the direction of
motion, until the body's tilt from upright (the centre of mass's direction) first stops
decreasing: the swing's apex (or, over the top, the sample nearest upright).
:func:`swing_apex_error` rolls a model through the same
policy from the same states (the policy reads the model's own state) and compares, per start, the
**true** mechanical energy (the closed-form body of the MJCF: a fixed yardstick for every model)
of the model's state and the plant's at the plant's apex step, in units of ``ΔE``:
``swing_energy_error`` is the mean absolute difference (``…_max`` the largest). The apex angles of
both are reported beside it (``plant_apex_deg``, ``model_apex_deg``, their mean absolute
difference ``swing_apex_error_deg``): easier to read, but sampled once per control period, so a
swing that passes over the top has an apex anywhere in ``[0, h·|ω|/2]``.
It needs only a batched step, so the closed-form model (:func:`closed_form_step`) is measured the
same way as a learned one (:func:`torch_model_step`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.learning.excitation import SwingPhysics

#: Start speeds from hanging, in units of the scene's speed scale ``ω_s``.
START_SPEEDS = (0.6, 0.8, 0.9, 1.0, 1.1, 1.3)
#: Longest swing rolled, in natural periods ``2π/ω_s``.
MAX_PERIODS = 1.5
#: At most this many steps per swing (a fine timestep on a slow body would otherwise take thousands).
MAX_STEPS = 400

#: ``step(q (S, 4), ω (S, 3), u (S, m)) → (q, ω)``, NumPy in and out.
BatchStep = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class SwingProbe:
    """The plant's swings, computed once per scene and control period.

    Attributes:
        q0, omega0: the start states ``(S, 4)``, ``(S, 3)`` (hanging, body-frame ω).
        plant_apex: the plant's apex angle from the goal per start (rad).
        goal: the goal orientation (4,).
        directions, low, high, speed: the pump policy (:class:`~fvin_mpc.learning.excitation.SwingPhysics`).
        max_steps: the longest swing rolled.
        step_size: the control period (s).
        plant_steps: the step of each start's apex.
        plant_energy: the true energy above hanging at it, in units of the energy span.
        physics: the scene's :class:`~fvin_mpc.learning.excitation.SwingPhysics` (the true energy).
    """

    q0: np.ndarray
    omega0: np.ndarray
    plant_apex: np.ndarray
    goal: np.ndarray
    directions: np.ndarray
    low: np.ndarray
    high: np.ndarray
    speed: float
    max_steps: int
    step_size: float
    plant_steps: np.ndarray
    plant_energy: np.ndarray
    physics: Any

    def energies(self, q: np.ndarray, omega: np.ndarray) -> np.ndarray:
        """The true energy above hanging of the rows of ``q (S, 4)``, ``ω (S, 3)``, in units of the span."""
        physics = self.physics
        values = [physics.potential(a) - physics.rest_energy + 0.5 * b @ physics.inertia(a) @ b
                  if np.all(np.isfinite(a)) and np.all(np.isfinite(b)) else np.inf for a, b in zip(q, omega)]
        return np.array(values) / physics.scales.energy_span

    def controls(self, omega: np.ndarray) -> np.ndarray:
        """Every actuator at its bound in the direction of motion, per row of ``omega (S, 3)``, the
        spin about the centre of mass's axis left out: an actuator along that axis (its direction
        less than half off it) is idle, the others follow the motion across it (where a row does
        not move along an actuator, its upper bound). A spin a swing-up does not need would make
        the swing chaotic (a ball joint's light axis), and the measure meaningless."""
        axis = self.physics.center_of_mass / np.linalg.norm(self.physics.center_of_mass)
        across = self.directions - np.outer(self.directions @ axis, axis)
        idle = np.linalg.norm(across, axis=1) < 0.5 * np.linalg.norm(self.directions, axis=1)
        along = np.asarray(omega) @ across.T
        pushed = np.where(along >= 0.0, self.high, self.low)
        return np.where(idle, np.clip(0.0, self.low, self.high), pushed)


def rotation_matrices(q: np.ndarray) -> np.ndarray:
    """``(S, 3, 3)`` rotation matrices of the unit quaternions (w, x, y, z) ``q (S, 4)``."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    matrices = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return np.moveaxis(matrices, (0, 1), (-2, -1))


def tilts(q: np.ndarray, goal: np.ndarray, center_of_mass: np.ndarray) -> np.ndarray:
    """Angles ``(S,)`` between the centre of mass's direction at the rows of ``q (S, 4)`` and at
    ``goal``: how far from upright, whatever the spin about the vertical (which a ball joint's
    actuators may change and which no swing-up needs)."""
    c = np.asarray(center_of_mass, dtype=float)
    c = c / np.linalg.norm(c)
    up = rotation_matrices(goal[None])[0] @ c
    cosine = np.clip((rotation_matrices(q) @ c) @ up, -1.0, 1.0)
    return np.arccos(cosine)


def swing_probe(scene: str, body: str | None = None, control_period: float | None = None,
                speeds: tuple[float, ...] = START_SPEEDS) -> SwingProbe:
    """The plant's swings from hanging at ``speeds·ω_s`` under full torque along the motion."""
    env = RigidBodyEnv(scene=scene, body=body, control_period=control_period)
    try:
        physics = SwingPhysics(env)
        base = env.unwrapped
        scales = physics.scales
        quaternion, rate = physics.attitude.quaternion, physics.attitude.omega
        axis = base.joint_axis
        if axis is not None:
            qvels = [np.array([sign * c * scales.speed]) for c in speeds for sign in (1.0, -1.0)]
        else:
            # Directions across the plane perpendicular to gravity at hanging (body frame), spread
            # by the golden angle so that any number of starts covers it.
            observation, _ = env.reset()
            down = _body_frame_down(observation[quaternion], np.asarray(base.model.opt.gravity, dtype=float))
            first = np.cross(down, [1.0, 0.0, 0.0] if abs(down[0]) < 0.9 else [0.0, 1.0, 0.0])
            first /= np.linalg.norm(first)
            second = np.cross(down, first)
            qvels = []
            for k, c in enumerate(speeds * 2):
                angle = k * math.pi * (3.0 - math.sqrt(5.0))
                direction = math.cos(angle) * first + math.sin(angle) * second
                inertia = physics.inertia(observation[quaternion])
                # The speed whose kinetic energy equals c²·(energy at ω_s about the stiffest axis).
                kinetic = c * c * scales.energy_span
                qvels.append(direction * math.sqrt(2.0 * kinetic / float(direction @ inertia @ direction)))
        max_steps = min(MAX_STEPS, max(2, math.ceil(MAX_PERIODS * scales.natural_period / scales.step_size)))
        goal = np.asarray(base.goal, dtype=float)
        policy = SwingProbe(np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), goal, physics.directions, physics.low,
                            physics.high, scales.speed, max_steps, scales.step_size, np.zeros(0, dtype=int),
                            np.zeros(0), physics)
        q0, omega0, apexes, steps, energies = [], [], [], [], []
        for qvel in qvels:
            observation, _ = env.reset(options={"qpos": base.rest_qpos, "qvel": qvel})
            q0.append(observation[quaternion])
            omega0.append(observation[rate])

            def plant_step(q: np.ndarray, omega: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                state = env.step(u[0])[0]
                return state[None, quaternion], state[None, rate]

            qs, omegas = _rollout(plant_step, policy, observation[None, quaternion], observation[None, rate])
            step, apex = _apex(tilts(qs[:, 0], goal, physics.center_of_mass))
            apexes.append(apex)
            steps.append(step)
            energies.append(policy.energies(qs[step], omegas[step])[0])
        return SwingProbe(np.array(q0), np.array(omega0), np.array(apexes), goal, physics.directions, physics.low,
                          physics.high, scales.speed, max_steps, scales.step_size, np.array(steps),
                          np.array(energies), physics)
    finally:
        env.close()


def _body_frame_down(q: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """The direction of gravity in the frame of a body at orientation ``q`` (w, x, y, z)."""
    return rotation_matrices(q[None])[0].T @ (gravity / np.linalg.norm(gravity))


def _rollout(step: BatchStep, probe: SwingProbe, q: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(q (K+1, S, 4), ω (K+1, S, 3))`` under the pump policy, ``K = max_steps``; a row that
    diverges (non-finite) stays non-finite."""
    qs, omegas = [q], [omega]
    for _ in range(probe.max_steps):
        finite = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(omega), axis=1)
        q, omega = step(np.where(finite[:, None], q, probe.q0[:1] if len(probe.q0) else q),
                        np.where(finite[:, None], omega, 0.0), probe.controls(np.nan_to_num(omega)))
        q = np.where(finite[:, None], q, np.nan)
        omega = np.where(finite[:, None], omega, np.nan)
        qs.append(q)
        omegas.append(omega)
    return np.array(qs), np.array(omegas)


def _apex(angles: np.ndarray) -> tuple[int, float]:
    """``(step, angle)`` of a swing's apex: the last sample before the angle from the goal first
    stops decreasing (the last sample if it never does; ``π`` once the rollout is non-finite)."""
    angles = np.where(np.isfinite(angles), angles, math.pi)
    rising = np.flatnonzero(angles[1:] >= angles[:-1])
    step = int(rising[0]) if rising.size else len(angles) - 1
    return step, float(angles[step])


def swing_apex_error(step: BatchStep, probe: SwingProbe) -> dict[str, Any]:
    """How far a model's swings end from the plant's (module docstring).

    Returns: ``swing_energy_error`` (mean absolute difference of the true energy at the plant's
    apex step, in units of the energy span) and ``swing_energy_error_max``; ``swing_apex_error_deg``
    (mean absolute difference of the apex angles) and per start ``plant_apex_deg``,
    ``model_apex_deg``, ``plant_energy`` and ``model_energy``.
    """
    qs, omegas = _rollout(step, probe, probe.q0.copy(), probe.omega0.copy())
    rows = np.arange(len(probe.q0))
    energy = probe.energies(qs[probe.plant_steps, rows], omegas[probe.plant_steps, rows])
    energy_error = np.abs(energy - probe.plant_energy)
    model_apex = np.array([_apex(tilts(qs[:, i], probe.goal, probe.physics.center_of_mass))[1] for i in rows])
    difference = np.degrees(np.abs(model_apex - probe.plant_apex))
    return {"swing_energy_error": float(energy_error.mean()), "swing_energy_error_max": float(energy_error.max()),
            "swing_apex_error_deg": float(difference.mean()),
            "plant_apex_deg": np.round(np.degrees(probe.plant_apex), 3).tolist(),
            "model_apex_deg": np.round(np.degrees(model_apex), 3).tolist(),
            "plant_energy": np.round(probe.plant_energy, 5).tolist(), "model_energy": np.round(energy, 5).tolist()}


def torch_model_step(model: Any) -> BatchStep:
    """A :data:`BatchStep` of a torch model with ``step(q, ω, u) → TorchStep`` (no gradients)."""
    import torch

    from fvin_mpc.learning.model import DTYPE

    def step(q: np.ndarray, omega: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.no_grad():
            out = model.step(*(torch.as_tensor(a, dtype=DTYPE) for a in (q, omega, u)))
        return out.q.numpy(), out.omega.numpy()

    return step


def closed_form_step(scene: str, body: str | None = None, control_period: float | None = None,
                     newton_iters: int = 8) -> BatchStep:
    """A :data:`BatchStep` of the closed-form body read off the scene's MJCF (same integrator as the
    learned model: the forced variational step)."""
    env = RigidBodyEnv(scene=scene, body=body, control_period=control_period)
    rigid_body, step_size = from_mujoco(env.unwrapped.model, env.unwrapped.body_name), float(env.unwrapped.dt)
    env.close()
    return rigid_body_step(rigid_body, step_size, newton_iters)


def rigid_body_step(rigid_body: Any, step_size: float, newton_iters: int = 8) -> BatchStep:
    """A :data:`BatchStep` of a :class:`~fvin_mpc.core.rigid_body.PivotedRigidBody` (e.g. one with
    deliberately wrong damping) through the forced variational step."""
    ops = get_ops("numpy")
    terms = rigid_body.terms(ops)

    def step(q: np.ndarray, omega: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = fvin.fvin_step(tuple(q.T), tuple(omega.T), tuple(u.T), terms, step_size, newton_iters, ops)
        return np.stack(np.broadcast_arrays(*out.q), axis=-1), np.stack(np.broadcast_arrays(*out.omega), axis=-1)

    return step


def scene_swing_measure(model: Any, scene: str, body: str | None = None,
                        control_period: float | None = None) -> dict[str, Any]:
    """:func:`swing_apex_error` of a torch model on a scene (probe and rollouts in one call)."""
    return swing_apex_error(torch_model_step(model), swing_probe(scene, body, control_period))
