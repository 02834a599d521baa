"""The closed-form body read off an MJCF equals the hand-derived one, and refuses what it cannot model."""

import mujoco
import numpy as np
import pytest

from fvin_mpc.core.rigid_body import PENDULUM, PENDULUM_DAMPED, from_mujoco
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.envs.scenes import SCENE_DIR


@pytest.mark.parametrize("scene, expected", [("pendulum", PENDULUM), ("pendulum_damped", PENDULUM_DAMPED)])
def test_from_mujoco_matches_the_hand_derived_pendulum(scene, expected):
    env = RigidBodyEnv(scene)
    body = from_mujoco(env.model, env.body_name)
    # The MJCF writes 1/12 as 0.083333333333, hence 1e-12.
    np.testing.assert_allclose(body.inertia, expected.inertia, atol=1e-12)
    np.testing.assert_allclose(body.center_of_mass, expected.center_of_mass)
    assert body.mass_gravity == pytest.approx(expected.mass_gravity)
    np.testing.assert_array_equal(body.actuator_axes, expected.actuator_axes)
    assert body.damping == pytest.approx(expected.damping)


def test_spherical_pendulum_inertia_about_the_pivot_by_parallel_axes():
    env = RigidBodyEnv("spherical_pendulum")
    body = from_mujoco(env.model, env.body_name)
    mass, com = 0.9, np.array([0.0, 0.0, -0.666666666667])
    expected = np.diag([0.101, 0.117, 0.017]) + mass * (com @ com * np.eye(3) - np.outer(com, com))
    np.testing.assert_allclose(body.inertia, expected, atol=1e-12)
    np.testing.assert_array_equal(body.actuator_axes, np.eye(3))
    assert body.mass_gravity == pytest.approx(9.0)


def test_dry_friction_is_refused_unless_switched_off():
    xml = (SCENE_DIR / "pendulum.xml").read_text().replace('frictionloss="0"', 'frictionloss="0.5"')
    model = mujoco.MjModel.from_xml_string(xml)
    with pytest.raises(ValueError, match="dry friction"):
        from_mujoco(model, "pendulum")
    model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_FRICTIONLOSS)
    assert from_mujoco(model, "pendulum").damping == 0.0


def test_unknown_body_is_a_clear_error():
    with pytest.raises(ValueError, match="no body named"):
        from_mujoco(RigidBodyEnv("pendulum").model, "nope")
