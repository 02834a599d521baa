"""Free-body data from the MJCF alone: short random-excitation bursts from random states.

Nothing here models the craft. A stabilizing pilot (:func:`fvin_mpc.learning.collection.collect_quadrotor`)
needs the closed form to represent the craft, so a craft it cannot represent could not even be recorded
and the learned model could only learn what the package already models. Instead each burst starts in a
random state — attitude uniform on S³ (upside down included) or near level, tumbling, moving — and is
driven by random piecewise-constant controls around the hover controls MuJoCo itself reports
(:func:`fvin_mpc.envs.quadrotor_env.hover_control`). The simulator has no floor, and a burst is short,
so the craft never leaves the envelope by more than a burst's fall.

Sizes come from the craft (:class:`~fvin_mpc.envs.quadrotor_env.CraftScales`): positions within a few
arm lengths of the hover point, speeds up to what a tenth of a second of its thrust gives.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fvin_mpc.core import s3
from fvin_mpc.core.data import Trajectories
from fvin_mpc.core.space import R3S3
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv, uniform_in_ball

#: ``metadata["collector"]`` of free-body data from random-excitation bursts.
EXCITATION = "random-excitation"


def collect_excitation(scene: Any = "quadrotor", trajectories: int = 750, steps: int = 20, seed: int = 0,
                       max_omega: float = 10.0, level_fraction: float = 0.5, hold_steps: int = 2,
                       progress: bool = True) -> Trajectories:
    """``trajectories`` seeded bursts of ``steps`` control periods in a free-body scene.

    A burst starts at the hover point plus a position uniform in a ball of three arm lengths, with a
    velocity uniform in the ball of ``0.1 s × (thrust-to-weight − 1) g``; its attitude is uniform on S³
    with ``|ω| ≤ max_omega`` (uniform in the ball) or, for ``level_fraction`` of the bursts, within
    0.5 rad of level with ``|ω| ≤ max_omega / 5`` (the hover the tasks end in). Every ``hold_steps``
    periods each actuator's control is drawn uniformly in ``hover ± a·(range/2)`` and clipped to its
    range, ``a`` uniform in [0, 1] per burst (gentle to violent).

    Returns :class:`~fvin_mpc.core.data.Trajectories` on R³ × S³ (``state (N, steps+1, 13)``, ``u (N, steps, nu)``).
    """
    from tqdm.auto import tqdm

    if trajectories < 1 or steps < 1 or hold_steps < 1:
        raise ValueError("trajectories, steps and hold_steps must be >= 1")
    env = QuadrotorEnv(scene=scene)
    scales = env.scales
    rng = np.random.default_rng(seed)
    hover = env.hover_thrust
    low, high = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    # unbounded actuators: excite within the hover controls' own size
    spread = np.where(np.isfinite(high - low), 0.5 * (high - low), np.maximum(np.abs(hover), 1e-3))
    gravity = float(np.linalg.norm(env.model.opt.gravity))
    max_speed = 0.1 * max(scales.thrust_to_weight - 1.0, 0.5) * gravity
    radius = 3.0 * scales.arm
    free = R3S3.layout.free_body(by="a free body's data")
    states = np.empty((trajectories, steps + 1, R3S3.state_dim))
    controls = np.empty((trajectories, steps, hover.size))
    near_level = 0
    for i in tqdm(range(trajectories), desc=f"excite {env.scene_spec.name}", disable=not progress):
        if rng.uniform() < level_fraction:
            near_level += 1
            axis = rng.normal(size=3)
            angle = rng.uniform(0.0, 0.5)
            attitude = np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis / np.linalg.norm(axis)])
            omega = uniform_in_ball(rng, max_omega / 5.0)
        else:
            attitude = rng.normal(size=4)
            attitude /= np.linalg.norm(attitude)
            omega = uniform_in_ball(rng, max_omega)
        start = np.concatenate([env.hover_point + uniform_in_ball(rng, radius), attitude,
                                uniform_in_ball(rng, max_speed), omega])
        observation = env.reset(options={"state": start})[0]
        amplitude = rng.uniform()
        states[i, 0] = observation
        for k in range(steps):
            if k % hold_steps == 0:
                u = np.clip(hover + amplitude * spread * rng.uniform(-1.0, 1.0, size=hover.size), low, high)
            observation = env.step(u)[0]
            states[i, k + 1], controls[i, k] = observation, u
    speeds = np.linalg.norm(states[..., free.omega], axis=-1)
    tilts = np.degrees(np.arccos(np.clip([[s3.rotation_matrix(tuple(q))[2][2] for q in trajectory]
                                          for trajectory in states[..., free.quaternion]], -1.0, 1.0)))
    metadata = {
        "scene": str(scene), "body": env.body_name, "control_period": float(env.dt), "seed": seed,
        "trajectories": trajectories, "steps": steps, "transitions": trajectories * steps, "collector": EXCITATION,
        "max_omega": max_omega, "level_fraction": level_fraction, "near_level_bursts": near_level,
        "hold_steps": hold_steps, "start_radius_m": radius, "start_speed_mps": max_speed,
        "coverage": {
            "max_abs_omega": float(speeds.max()), "median_abs_omega": float(np.median(speeds)),
            "max_speed": float(np.linalg.norm(states[..., free.velocity], axis=-1).max()),
            "max_distance": float(np.linalg.norm(states[..., free.position] - env.hover_point, axis=-1).max()),
            "upside_down_share": float((tilts > 90.0).mean()), "max_tilt_deg": float(tilts.max()),
            "saturated_share": float(((controls <= low + 1e-12) | (controls >= high - 1e-12)).mean()),
        },
    }
    env.close()
    return Trajectories(states, controls, {**metadata, "configuration_space": env.space.name})
