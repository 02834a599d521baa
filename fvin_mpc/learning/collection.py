"""Collect trajectories from a scene: ``python -m fvin_mpc.collect``.

Free-body scenes (``quadrotor``) are flown by a perturbed stabilizing controller instead
(:func:`collect_quadrotor`); what follows is the pivoted scenes' collection.

Initial states are drawn uniformly (angle(s) over the whole circle/sphere, angular
velocity up to ``--max-omega``), controls are either constant over a trajectory (as in
the paper's experiments) or random piecewise constant (a new level every
``--hold-steps`` control periods), drawn uniformly inside the actuators' range. Half
of the trajectories use each mode. Everything is seeded.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fvin_mpc.core import s3
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.quadrotor import GeometricController, from_mujoco
from fvin_mpc.core.space import R3S3
from fvin_mpc.envs import QuadrotorEnv, RigidBodyEnv
from fvin_mpc.envs.quadrotor_env import uniform_in_ball


def _joint_kind(env: Any) -> str:
    """``"hinge"`` or ``"ball"``: the env's single joint, the only kinds the collector samples."""
    model = env.unwrapped.model
    if model.nq == 1 and model.nv == 1:
        return "hinge"
    if model.nq == 4 and model.nv == 3:
        return "ball"
    raise ValueError(f"expected one hinge (nq=nv=1) or ball joint (nq=4, nv=3), got nq={model.nq}, nv={model.nv}")


def hinge_axis_record(env: Any) -> list[float] | None:
    """The env's hinge axis for a data file's metadata (a list; ``None`` for a ball joint): a model of
    the data steps on it (:func:`fvin_mpc.learning.space_training.default_model_config`)."""
    axis = env.unwrapped.joint_axis
    return None if axis is None else [float(v) for v in axis]


def random_joint_state(env: Any, rng: np.random.Generator, max_omega: float) -> tuple[np.ndarray, np.ndarray]:
    """A uniformly random ``(qpos, qvel)`` for the env's single hinge or ball joint."""
    if _joint_kind(env) == "hinge":
        return rng.uniform(-np.pi, np.pi, size=1), rng.uniform(-max_omega, max_omega, size=1)
    quaternion = rng.normal(size=4)
    quaternion /= np.linalg.norm(quaternion)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return quaternion, direction * max_omega * rng.uniform() ** (1 / 3)


def near_goal_joint_state(env: Any, rng: np.random.Generator, max_angle: float,
                          max_omega: float) -> tuple[np.ndarray, np.ndarray]:
    """A random ``(qpos, qvel)`` within ``max_angle`` rad of the env's goal, each ``|ω_i| ≤ max_omega``."""
    goal = np.asarray(env.unwrapped.goal_qpos, dtype=np.float64)
    if _joint_kind(env) == "hinge":
        return np.array([goal[0] + rng.uniform(-max_angle, max_angle)]), rng.uniform(-max_omega, max_omega, size=1)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    half = 0.5 * rng.uniform(0.0, max_angle)
    offset = np.concatenate([[np.cos(half)], np.sin(half) * axis])
    return np.asarray(s3.multiply(tuple(goal), tuple(offset)), dtype=np.float64), \
        rng.uniform(-max_omega, max_omega, size=3)


def control_sequence(rng: np.random.Generator, low: np.ndarray, high: np.ndarray, steps: int,
                     mode: str, hold_steps: int) -> np.ndarray:
    """``(steps, m)`` controls: one constant level, or a new level every ``hold_steps``."""
    if mode == "constant":
        return np.repeat(rng.uniform(low, high)[None], steps, axis=0)
    if mode == "piecewise":
        levels = rng.uniform(low, high, size=(-(-steps // hold_steps), low.size))
        return np.repeat(levels, hold_steps, axis=0)[:steps]
    raise ValueError(f"unknown control mode {mode!r}")


#: ``metadata["collector"]`` of speed-bounded data: a name of the method, not of the function that
#: implements it, so that moving code never invalidates a data file.
SPEED_BOUNDED = "speed-bounded"


def collect(scene: str = "pendulum", trajectories: int = 320, steps: int = 20, seed: int = 0,
            max_omega: float = 6.0, hold_steps: int = 4, body: str | None = None,
            progress: bool = True, control_period: float | None = None, max_speed: float | None = None,
            max_attempts_factor: int = 50, near_goal_trajectories: int = 0, near_goal_angle: float = 1.0,
            near_goal_omega: float = 2.0) -> Trajectories:
    """Roll out ``trajectories`` seeded episodes of ``steps`` control periods in the scene.

    Each trajectory starts from a uniformly random joint state (|ω| ≤ ``max_omega``) under one
    constant control (even index) or a new uniform level every ``hold_steps`` periods (odd index).

    Args:
        control_period: seconds per step, overriding the scene's (a whole multiple of the MJCF
            timestep), e.g. ``0.02`` for data of a model with step ``h = 0.02``.
        max_speed: keep only trajectories with ``max_i |ω_i| ≤ max_speed`` at every step; a rollout
            that exceeds it is discarded and a new one drawn for the same index (metadata: the
            acceptance rate, ``collector = "speed-bounded"``). For bodies whose light axis spins up
            past the step's solvability limit ``h|ω| ≈ 1`` (docs/spherical.md). ``None``: keep all.

        near_goal_trajectories: this many more trajectories (after the uniform ones) start within
            ``near_goal_angle`` rad of the scene's goal with every ``|ω_i| ≤ near_goal_omega`` — the
            states an MPC must predict well to catch and hold the body there, and which uniform
            sampling of S³ visits rarely (docs/spherical.md). Same controls, same speed bound.

    Raises:
        RuntimeError: fewer than one in ``max_attempts_factor`` rollouts is accepted.
    """
    from tqdm.auto import tqdm

    if max_speed is not None and not (math.isfinite(max_speed) and max_speed > 0):
        raise ValueError(f"max_speed must be finite and > 0, got {max_speed!r}")
    if near_goal_trajectories < 0 or not (0.0 < near_goal_angle <= math.pi and near_goal_omega >= 0.0):
        raise ValueError("near_goal_trajectories must be >= 0, near_goal_angle in (0, π], near_goal_omega >= 0; got "
                         f"{near_goal_trajectories}, {near_goal_angle}, {near_goal_omega}")
    uniform_trajectories, trajectories = trajectories, trajectories + near_goal_trajectories
    env = RigidBodyEnv(scene=scene, body=body, control_period=control_period)
    attitude = env.space.layout.attitude(by="collect_trajectories")
    rng = np.random.default_rng(seed)
    low, high = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    qs = np.empty((trajectories, steps + 1, 4))
    omegas = np.empty((trajectories, steps + 1, 3))
    us = np.empty((trajectories, steps, low.size))
    modes = []
    attempts = 0
    limit = np.inf if max_speed is None else max_speed
    description = f"collect {env.scene_spec.name}" + ("" if max_speed is None else f" (|ω_i| ≤ {max_speed:g})")
    for i in tqdm(range(trajectories), desc=description, disable=not progress):
        mode = "constant" if i % 2 == 0 else "piecewise"
        modes.append(mode)
        while True:
            attempts += 1
            if attempts > max_attempts_factor * trajectories:
                raise RuntimeError(f"acceptance too low: {i} of {trajectories} trajectories after {attempts} attempts")
            if i < uniform_trajectories:
                qpos, qvel = random_joint_state(env, rng, max_omega)
            else:
                qpos, qvel = near_goal_joint_state(env, rng, near_goal_angle, near_goal_omega)
            observation, _ = env.reset(seed=int(rng.integers(2**31)), options={"qpos": qpos, "qvel": qvel})
            controls = control_sequence(rng, low, high, steps, mode, hold_steps)
            qs[i, 0], omegas[i, 0] = observation[attitude.quaternion], observation[attitude.omega]
            accepted = bool(np.abs(observation[attitude.omega]).max() <= limit)
            for k in range(steps if accepted else 0):
                observation, *_ = env.step(controls[k])
                qs[i, k + 1], omegas[i, k + 1] = observation[attitude.quaternion], observation[attitude.omega]
                if np.abs(observation[attitude.omega]).max() > limit:
                    accepted = False
                    break
            if accepted:
                break
        us[i] = controls
    metadata = {
        "scene": str(scene), "body": env.unwrapped.body_name, "control_period": float(env.unwrapped.dt),
        "seed": seed, "trajectories": trajectories, "steps": steps, "transitions": trajectories * steps,
        "max_omega": max_omega, "hold_steps": hold_steps,
        "control_modes": {"constant": modes.count("constant"), "piecewise": modes.count("piecewise")},
        "hinge_axis": hinge_axis_record(env),
    }
    if near_goal_trajectories:
        metadata.update(near_goal_trajectories=near_goal_trajectories, near_goal_angle=near_goal_angle,
                        near_goal_omega=near_goal_omega)
    if max_speed is not None:
        metadata.update(max_speed=max_speed, attempts=attempts, acceptance_rate=trajectories / attempts,
                        collector=SPEED_BOUNDED)
    env.close()
    return Trajectories.from_parts(qs, omegas, us, metadata)


#: ``metadata["collector"]`` of free-body data flown by a perturbed stabilizing controller.
STABILIZED_FLIGHT = "stabilized-flight"


def collect_quadrotor(scene: str = "quadrotor", trajectories: int = 300, steps: int = 50, seed: int = 0,
                      max_omega: float = 10.0, tumbling_fraction: float = 0.5, waypoint_radius: float = 1.0,
                      waypoint_steps: int = 25, noise_fraction: float = 0.35, hold_steps: int = 2,
                      max_distance: float = 6.0, progress: bool = True) -> Trajectories:
    """Fly ``trajectories`` seeded episodes of ``steps`` control periods in a free-body scene.

    Each episode flies :class:`~fvin_mpc.core.quadrotor.GeometricController` (the closed-form craft
    read off the MJCF) towards waypoints drawn uniformly in the ball of ``waypoint_radius`` around the
    hover point (a new one every ``waypoint_steps`` periods), with every rotor's thrust perturbed by
    uniform noise of up to ``noise_fraction`` of the hover thrust times a per-episode level in
    [0, 1], held for ``hold_steps`` periods, then clipped to the bounds. A ``tumbling_fraction`` of
    the episodes starts in the env's recovery reset (attitude uniform on S³, ``|ω| ≤ max_omega``);
    the others start level-ish (``|ω| ≤ 1``, attitude within 0.5 rad) up to 0.5 m from the hover
    point, moving at up to 1 m/s. The controller's gains are scaled per episode by a factor in
    [0.6, 1.4] so that the data do not follow one closed loop. Episodes that get farther than
    ``max_distance`` from the hover point are flown again with fresh draws (metadata: the count).

    Returns :class:`~fvin_mpc.core.data.Trajectories` on R³ × S³ (``state (N, steps+1, 13)``, ``u (N, steps, 4)``).
    """
    from dataclasses import replace as _replace

    from tqdm.auto import tqdm

    env = QuadrotorEnv(scene=scene)
    body = from_mujoco(env.model, env.body_name)
    rng = np.random.default_rng(seed)
    low, high = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    hover = env.hover_point
    free = R3S3.layout.free_body(by="a free body's data")
    states = np.empty((trajectories, steps + 1, R3S3.state_dim))
    controls = np.empty((trajectories, steps, low.size))
    redrawn = tumbling = 0
    for i in tqdm(range(trajectories), desc=f"collect {env.scene_spec.name}", disable=not progress):
        while True:
            tumble = bool(rng.uniform() < tumbling_fraction)
            if tumble:
                observation = env.reset(seed=int(rng.integers(2**31)), options={"max_omega": max_omega})[0]
            else:
                axis = rng.normal(size=3)
                angle = rng.uniform(0.0, 0.5)
                turn = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis / np.linalg.norm(axis)])
                offset, velocity, omega = (uniform_in_ball(rng, r) for r in (0.5, 1.0, 1.0))
                observation = env.reset(options={"qpos": np.concatenate([hover + offset, turn]),
                                                 "qvel": np.concatenate([velocity, omega])})[0]
            gains = rng.uniform(0.6, 1.4)
            controller = _replace(GeometricController(body), position_gain=4.0 * gains, velocity_gain=3.0 * gains,
                                  attitude_frequency=15.0 * rng.uniform(0.7, 1.3))
            noise_level = noise_fraction * rng.uniform() * env.hover_thrust
            waypoint = hover
            states[i, 0] = observation
            noise = np.zeros(low.size)
            for k in range(steps):
                if k % waypoint_steps == 0:
                    waypoint = hover + uniform_in_ball(rng, waypoint_radius)
                if k % hold_steps == 0:
                    noise = rng.uniform(-1.0, 1.0, size=low.size) * noise_level
                u = np.clip(controller(observation, waypoint) + noise, low, high)
                observation = env.step(u)[0]
                states[i, k + 1], controls[i, k] = observation, u
            if np.linalg.norm(states[i, :, free.position] - hover, axis=1).max() <= max_distance:
                tumbling += tumble
                break
            redrawn += 1
    speeds = np.linalg.norm(states[..., free.omega], axis=-1)
    tilts = np.array([[np.degrees(math.acos(np.clip(s3.rotation_matrix(tuple(q))[2][2], -1.0, 1.0))) for q in traj]
                      for traj in states[..., free.quaternion]])
    metadata = {
        "scene": str(scene), "body": env.body_name, "control_period": float(env.dt), "seed": seed,
        "trajectories": trajectories, "steps": steps, "transitions": trajectories * steps,
        "collector": STABILIZED_FLIGHT, "tumbling_episodes": int(tumbling), "redrawn_episodes": int(redrawn),
        "max_omega": max_omega, "waypoint_radius": waypoint_radius, "waypoint_steps": waypoint_steps,
        "noise_fraction": noise_fraction, "hold_steps": hold_steps, "max_distance": max_distance,
        "coverage": {
            "max_abs_omega": float(speeds.max()), "median_abs_omega": float(np.median(speeds)),
            "max_speed": float(np.linalg.norm(states[..., free.velocity], axis=-1).max()),
            "max_distance": float(np.linalg.norm(states[..., free.position] - hover, axis=-1).max()),
            "upside_down_share": float((tilts > 90.0).mean()), "max_tilt_deg": float(tilts.max()),
            "saturated_share": float(((controls <= low + 1e-12) | (controls >= high - 1e-12)).mean()),
        },
    }
    env.close()
    return Trajectories(states, controls, {**metadata, "configuration_space": env.space.name})
