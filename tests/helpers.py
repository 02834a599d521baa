"""The tests' shared helpers: planar states, random rotations, synthetic trajectories.

One home for what the test modules used to copy: import from here (``tests/`` is on ``sys.path``
through ``conftest.py``). Hypothesis strategies live beside it in ``strategies.py``.
"""

import numpy as np

from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.data import Trajectories

NP = get_ops("numpy")


# ---------------------------------------------------------------------- planar states (hinge about +y)
def hinge_quaternion(theta: float) -> np.ndarray:
    """Rotation by θ about +y, ``(cos θ/2, 0, sin θ/2, 0)``: the pendulum scenes' orientation at hinge
    angle θ (θ = 0 hanging, θ = π upright)."""
    return np.array([np.cos(theta / 2), 0.0, np.sin(theta / 2), 0.0])


def hinge(theta: float, theta_dot: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Planar pendulum orientation and angular velocity: ``q (4,)``, ``ω = (0, θ̇, 0)``."""
    return hinge_quaternion(theta), np.array([0.0, theta_dot, 0.0])


def hinge_state(theta: float, theta_dot: float = 0.0) -> np.ndarray:
    """The planar pendulum's state ``x = (q, ω)`` ``(7,)`` (:mod:`fvin_mpc.core.state`)."""
    return np.concatenate(hinge(theta, theta_dot))


# ---------------------------------------------------------------------- random rotations
def random_unit_quaternions(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 4)`` unit quaternions, uniform on S³ (normalized Gaussians), seeded."""
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_states(n: int, seed: int, omega_scale: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """``(q (n, 4), ω (n, 3))``: uniform orientations and Gaussian angular velocities of scale ``omega_scale``."""
    return random_unit_quaternions(n, seed), omega_scale * np.random.default_rng(seed + 1).normal(size=(n, 3))


def assert_same_rotation(q: np.ndarray, p: np.ndarray, atol: float) -> None:
    """``q = ±p`` (q and −q are the same rotation)."""
    assert min(np.max(np.abs(q - p)), np.max(np.abs(q + p))) < atol, (q, p)


# ---------------------------------------------------------------------- synthetic data


def synthetic_hinge_data(body, trajectories=48, steps=10, seed=0):
    """Hinge-about-y trajectories of ``body`` integrated with 20 FVIN substeps per 0.05 s period
    (a finer integrator than the model being trained), random angles, rates and torques."""
    rng = np.random.default_rng(seed)
    terms = body.terms(NP)
    theta, omega0 = rng.uniform(-np.pi, np.pi, trajectories), rng.uniform(-5, 5, trajectories)
    u = rng.uniform(-2, 2, (trajectories, steps, 1))
    zero = 0 * theta
    q, omega = (np.cos(theta / 2), zero, np.sin(theta / 2), zero), (zero, omega0, zero)
    qs, omegas = [np.stack(q, -1)], [np.stack(omega, -1)]
    for k in range(steps):
        for _ in range(20):
            out = fvin.fvin_step(q, omega, (u[:, k, 0],), terms, 0.0025, 4, NP)
            q, omega = out.q, out.omega
        qs.append(np.stack(q, -1))
        omegas.append(np.stack(omega, -1))
    return Trajectories.from_parts(
        np.stack(qs, 1), np.stack(omegas, 1), u, {"control_period": 0.05, "scene": "synthetic"}
    )


def iterated_rti_plan(controller, x0: np.ndarray, iterations: int):
    """``controller``'s (a RealTimeMPC) plan after ``iterations`` SQP iterations from its ``"goal"``
    first guess with the measured state ``x0`` fixed: the real-time iteration run to convergence, to
    compare with IPOPT's solution of the same problem. Returns ``(plan, cost, largest gap)``."""
    from fvin_mpc.control.mpc import Plan

    guess = controller._first_guess(x0, "goal")
    plan = Plan(guess.states, guess.controls, None, None)
    for _ in range(iterations):
        plan = controller.iterate(plan, x0)
        assert plan is not None, "the QP gave no finite step"
    return (plan, *controller.plan_cost(plan))


def stage_models(scenes=("pendulum", "spherical_pendulum", "quadrotor")):
    """``(scene, true_model, model)`` for each of ``scenes``' learned (checkpoint) and closed-form models."""
    from fvin_mpc.control.flight import quadrotor_model
    from fvin_mpc.control.scene import scene_env, scene_model
    from fvin_mpc.envs import QuadrotorEnv
    from fvin_mpc.envs.scenes import resolve_scene

    for scene in scenes:
        for true_model in (False, True):
            if scene == "quadrotor":
                yield scene, true_model, quadrotor_model(QuadrotorEnv(resolve_scene(scene)), true_model=true_model)
            else:
                yield scene, true_model, scene_model(scene_env(scene, true_model=true_model), true_model=true_model)
