"""The closed-form quadrotor read off the MJCF (:func:`fvin_mpc.core.quadrotor.from_mujoco`) and its
R³ × S³ step against MuJoCo as the plant: second order in the step size over short horizons."""

from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np
import pytest

from fvin_mpc.core import fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.quadrotor import QUADROTOR, from_mujoco
from fvin_mpc.envs import FREE_BODY_SCENES, QuadrotorEnv, RigidBodyEnv

NP = get_ops("numpy")


def test_the_mjcf_is_the_reference_craft():
    body = from_mujoco(QuadrotorEnv().model, "quadrotor")
    assert body.mass == QUADROTOR.mass and body.gravity == QUADROTOR.gravity
    np.testing.assert_array_equal(body.inertia, QUADROTOR.inertia)
    np.testing.assert_allclose(body.rotor_sites, QUADROTOR.rotor_sites, atol=1e-7)  # √2 to 7 digits in the MJCF
    assert body.rotor_spins == QUADROTOR.rotor_spins and body.yaw_coefficient == QUADROTOR.yaw_coefficient
    assert body.thrust_low == (0.0,) * 4 and body.thrust_high == (2.5,) * 4


def test_what_from_mujoco_reads_follows_the_model():
    model = QuadrotorEnv(physics=replace(FREE_BODY_SCENES["quadrotor"].physics, gravity=False,
                                         actuator_limits=False)).model
    body = from_mujoco(model, "quadrotor")
    assert body.gravity == 0.0 and body.thrust_low is None
    model.body_iquat[1] = [np.cos(0.2), 0.0, 0.0, np.sin(0.2)]  # principal axes turned 0.4 rad about z
    inertia = np.array(from_mujoco(model, "quadrotor").inertia)
    np.testing.assert_allclose(np.linalg.eigvalsh(inertia), [2.3e-3, 2.9e-3, 4.6e-3], rtol=1e-12)
    assert abs(inertia[0, 1]) > 1e-5
    # unequal yaw gears and a gear with a lateral force: read as axes and moments, not refused
    model.actuator_gear[1, 5], model.actuator_gear[2, 0] = 0.02, 0.1
    body = from_mujoco(model, "quadrotor")
    np.testing.assert_allclose(np.array(body.force_map)[:, 2], [0.1, 0.0, 1.0])
    np.testing.assert_allclose(np.array(body.torque_map)[:, 1], [0.1202082, 0.1202082, 0.02])
    site = model.site_pos[model.actuator_trnid[2, 0]]
    np.testing.assert_allclose(np.array(body.torque_map)[:, 2], np.cross(site, [0.1, 0.0, 1.0]) + [0, 0, 0.016])
    model.actuator_biastype[0], model.actuator_biasprm[0, 1] = mujoco.mjtBias.mjBIAS_AFFINE, -1.0
    with pytest.raises(ValueError, match="fixed gain"):
        from_mujoco(model, "quadrotor")
    with pytest.raises(ValueError, match="free joint"):
        from_mujoco(RigidBodyEnv("spherical_pendulum").model, "pendulum")
    with pytest.raises(ValueError, match="no body"):
        from_mujoco(model, "drone")


def _horizon_error(h: float, seed: int, horizon: float = 0.2) -> float:
    """Largest error of the closed-form step (K = 6) against MuJoCo (RK4 at 2 ms) over ``horizon``,
    from a tumbling, moving start under constant unequal thrusts: max over steps and entries
    (m, sign-invariant |Δq|, m/s, rad/s)."""
    env = QuadrotorEnv(control_period=h)
    terms = from_mujoco(env.model, "quadrotor").terms(NP)
    state = env.reset(seed=seed, options={"max_omega": 10.0, "max_speed": 2.0})[0]
    u = np.random.default_rng(seed).uniform(0.3, 2.3, size=4)
    model_state, error = state.copy(), 0.0
    for _ in range(int(round(horizon / h))):
        state = env.step(u)[0]
        model_state, residual = fvin_r3s3.step_state(model_state, u, terms, h, 6, NP)
        assert residual < 1e-9
        dq = min(np.linalg.norm(model_state[3:7] - state[3:7]), np.linalg.norm(model_state[3:7] + state[3:7]))
        error = max(error, float(np.abs(model_state[:3] - state[:3]).max()), dq,
                    float(np.abs(model_state[7:] - state[7:]).max()))
    return error


@pytest.mark.parametrize("seed", range(4))
def test_the_closed_form_step_matches_mujoco_to_second_order(seed):
    """Halving h (20 → 10 ms) divides the error over 0.2 s by 4 (measured log₂ ratios 2.01–2.08);
    MuJoCo's own RK4 error at 2 ms is far below (≈1e-9)."""
    coarse, fine = _horizon_error(0.02, seed), _horizon_error(0.01, seed)
    assert 1.85 < np.log2(coarse / fine) < 2.15
    assert coarse < 0.5  # rad/s at |ω| ≤ 10 after 10 steps of 20 ms: the integrator's error, not a model error
