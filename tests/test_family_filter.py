"""The feasibility filter of the scene families (fvin_mpc/control/family_filter.py): its criterion, what a
two-actuator ball is judged on, and refusals."""

import numpy as np
import pytest

from fvin_mpc.control.family_filter import feasible, judge, judged_on, tilt_angles
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.envs.families import ball_scene, write_family


def test_judge_is_the_evaluation_criterion():
    t = np.arange(0.0, 10.0, 0.1)
    assert judge(t, np.where(t < 4.0, 3.0, 0.01))["swung_up"]
    assert judge(t, np.where(t < 4.0, 3.0, 0.01))["time_to_upright_s"] == pytest.approx(4.0)
    assert not judge(t, np.where(t < 4.0, 3.0, 0.08))["swung_up"]  # upright but not held within 0.05 rad
    assert not judge(t, np.where(t < 9.5, 0.01, 0.2))["swung_up"]  # fell at the end


def test_a_ball_with_two_actuators_is_judged_on_tilt(tmp_path):
    seeds = {ball_scene(seed)[1]["actuators"]: seed for seed in range(1000, 1030)}
    for actuators, expected in ((2, "tilt"), (3, "orientation")):
        (path,) = write_family("ball", [seeds[actuators]], tmp_path)
        env = RigidBodyEnv(str(path))
        assert judged_on(env) == expected
    # Tilt ignores the spin about the long axis: the goal spun about the centre of mass's direction.
    from fvin_mpc.core.rigid_body import from_mujoco
    from fvin_mpc.core.s3 import rotation_matrix

    c = np.array(from_mujoco(env.model, env.body_name).center_of_mass)
    up = np.array(rotation_matrix(tuple(env.goal))) @ c / np.linalg.norm(c)
    spin = np.concatenate([[np.cos(0.6)], np.sin(0.6) * up])  # 1.2 rad about the world direction of the com
    w1, v1, w2, v2 = spin[0], spin[1:], env.goal[0], env.goal[1:]
    spun = np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])
    np.testing.assert_allclose(tilt_angles(env, [env.goal, spun]), 0.0, atol=1e-7)


def test_a_scene_the_package_refuses_is_infeasible_with_the_reason(tmp_path):
    path = tmp_path / "free.xml"
    path.write_text(
        '<mujoco><worldbody><body name="b"><joint type="hinge" axis="0 0 1"/><geom size="0.1" pos="0.5 0 0" '
        'contype="0" conaffinity="0"/></body></worldbody><actuator><motor joint="0" ctrlrange="-1 1"/>'
        "</actuator></mujoco>".replace('joint="0"', 'joint="j"').replace('type="hinge"', 'name="j" type="hinge"')
    )
    ok, facts = feasible(path)
    assert not ok and "potential" in facts["error"]  # a vertical hinge: gravity does nothing about it


def test_the_filter_duration_is_the_swingup_commands_rule_with_the_gear_counted(tmp_path):
    from fvin_mpc.control.family_filter import swingup_duration
    from fvin_mpc.control.scene import scene_scales
    from fvin_mpc.swingup import MIN_DEFAULT_DURATION_S, default_duration

    weak = RigidBodyEnv("tests/data/weak_pendulum.xml")  # gear 1: the command's own number
    assert swingup_duration(weak) == pytest.approx(default_duration(scene_scales(weak)), rel=1e-12)
    (path,) = write_family("hinge", [1002], tmp_path)
    env = RigidBodyEnv(str(path))
    gear, bound = abs(env.model.actuator_gear[0, 0]), abs(env.model.actuator_ctrlrange[0]).max()
    assert gear != pytest.approx(1.0)  # the draw this test needs: a gear that changes the torque
    scales = scene_scales(env)
    assert (scales.control, scales.torque) == pytest.approx((bound, bound * gear), rel=1e-12)
    assert swingup_duration(env) == pytest.approx(default_duration(scales), rel=1e-12)
    assert MIN_DEFAULT_DURATION_S == 10.0
