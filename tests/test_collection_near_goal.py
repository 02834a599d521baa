"""Near-goal starts of the collector: where they start, that they are recorded, and bad input."""

import numpy as np
import pytest

from fvin_mpc.core import s3
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.learning.collection import collect, near_goal_joint_state


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(s3.geodesic_angles(a, b))


@pytest.mark.parametrize("scene", ["pendulum", "spherical_pendulum"])
def test_near_goal_states_start_within_the_angle_of_the_goal(scene):
    env = RigidBodyEnv(scene=scene)
    rng = np.random.default_rng(3)
    angles, speeds = [], []
    for _ in range(100):
        qpos, qvel = near_goal_joint_state(env, rng, 0.4, 1.5)
        env.reset(options={"qpos": qpos, "qvel": qvel})
        angles.append(_angle(env.state()[:4], env.goal))
        speeds.append(np.abs(qvel).max())
    assert max(angles) <= 0.4 + 1e-9
    assert max(angles) > 0.3  # the whole ball is used, not only its centre
    assert max(speeds) <= 1.5
    env.reset(options={"qpos": env.goal_qpos, "qvel": np.zeros(env.unwrapped.model.nv)})
    assert _angle(env.state()[:4], env.goal) < 1e-9


def test_collect_appends_near_goal_trajectories_and_records_them():
    data = collect("spherical_pendulum", trajectories=4, steps=3, seed=0, hold_steps=2, progress=False,
                   near_goal_trajectories=3, near_goal_angle=0.5, near_goal_omega=1.0)
    assert data.q.shape == (7, 4, 4) and data.metadata["transitions"] == 21
    assert data.metadata["near_goal_trajectories"] == 3
    env = RigidBodyEnv(scene="spherical_pendulum")
    assert all(_angle(q, env.goal) <= 0.5 + 1e-9 for q in data.q[4:, 0])
    assert all(np.abs(omega).max() <= 1.0 + 1e-9 for omega in data.omega[4:, 0])
    uniform = collect("spherical_pendulum", trajectories=4, steps=3, seed=0, hold_steps=2, progress=False)
    np.testing.assert_array_equal(uniform.q, data.q[:4])  # the uniform part is unchanged by the option


def test_collect_refuses_bad_near_goal_options():
    with pytest.raises(ValueError, match="near_goal"):
        collect("pendulum", trajectories=2, steps=2, progress=False, near_goal_trajectories=-1)
    with pytest.raises(ValueError, match="near_goal"):
        collect("pendulum", trajectories=2, steps=2, progress=False, near_goal_trajectories=1, near_goal_angle=0.0)
