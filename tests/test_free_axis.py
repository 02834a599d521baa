"""A goal that is a set: the turn about a free axis costs nothing (the two-motor ball scenes of the family)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from fvin_mpc.control.family_filter import judged_on, run_judged
from fvin_mpc.control.mpc import MPCSettings
from fvin_mpc.control.problem import DisturbanceEstimate, orientation_error
from fvin_mpc.control.scene import goal_symmetry_axis, scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core import s3
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.core.space import S3
from fvin_mpc.envs.families import write_family

RNG = np.random.default_rng(5)


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _turn(axis, angle):
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * _unit(axis)])


def _error(q, goal, kind, free_axis=None):
    return np.array(ca.evalf(orientation_error(ca.DM(q), ca.DM(goal), kind, free_axis))).ravel()


@pytest.mark.parametrize("kind", ["projector", "rotation-vector"])
def test_a_turn_about_the_free_axis_costs_nothing_and_a_tilt_costs_what_it_did(kind):
    goal, n = _unit(RNG.normal(size=4)), _unit(RNG.normal(size=3))
    for angle in (0.3, 2.0, -3.0):
        yawed = np.array(s3.multiply(tuple(goal), tuple(_turn(n, angle))))
        assert np.linalg.norm(_error(yawed, goal, kind, tuple(n))) < 1e-12
        assert np.linalg.norm(_error(-yawed, goal, kind, tuple(n))) < 1e-12  # either sign of the quaternion
        assert np.linalg.norm(_error(yawed, goal, kind)) > 0.1  # the whole orientation sees the turn
    tilt_axis = _unit(np.cross(n, RNG.normal(size=3)))
    tilted = np.array(s3.multiply(tuple(goal), tuple(_turn(tilt_axis, 0.4))))
    # A pure tilt keeps its whole cost: the same square as without the free axis.
    assert np.linalg.norm(_error(tilted, goal, kind, tuple(n))) == pytest.approx(
        np.linalg.norm(_error(tilted, goal, kind)), rel=1e-12)


def test_the_settings_refuse_an_axis_that_is_not_a_unit_vector():
    with pytest.raises(ValueError, match="free_axis"):
        MPCSettings(free_axis=(1.0, 1.0, 0.0))
    assert MPCSettings(free_axis=(0.0, 0.0, 1.0)).free_axis == (0.0, 0.0, 1.0)


def test_the_scene_defaults_free_the_centre_of_mass_direction_of_a_two_motor_ball_only(tmp_path):
    two, three = write_family("ball", [9002, 9006], tmp_path)  # 2 and 3 actuators
    (hinge,) = write_family("hinge", [9002], tmp_path)
    env = scene_env(str(two), true_model=True)
    axis = goal_symmetry_axis(env)
    center = from_mujoco(env.unwrapped.model, env.unwrapped.body_name).center_of_mass
    assert np.allclose(axis, _unit(center))
    assert scene_mpc_settings(env).free_axis == axis and judged_on(env) == "tilt"
    for other in (three, hinge):
        other_env = scene_env(str(other), true_model=True)
        assert goal_symmetry_axis(other_env) is None and scene_mpc_settings(other_env).free_axis is None
        assert judged_on(other_env) == "orientation"


def test_the_disturbance_estimate_counts_a_body_turned_about_the_free_axis_as_at_the_goal():
    n = _unit([0.2, -0.4, 1.0])
    goal = _unit(RNG.normal(size=4))
    low, high = -np.ones(2), np.ones(2)
    state = np.concatenate([s3.multiply(tuple(goal), tuple(_turn(n, 1.5))), 3.0 * n])  # turned and spinning about n
    for free_axis, moves in ((None, False), (tuple(n), True)):
        estimate = DisturbanceEstimate(S3.layout, 0.5, 0.5, 1.0, low, high, free_axis)
        estimate.predicted(state, np.ones((2, 3)))
        estimate.update(state + np.r_[np.zeros(4), 0.1, 0.0, 0.0], np.r_[goal, np.zeros(3)])
        assert bool(np.any(estimate.value != 0.0)) is moves


def test_a_two_motor_ball_that_held_off_upright_swings_up_with_the_free_axis(tmp_path):
    # Report member 9002 from a random start: charged for the turn about its long axis (which its
    # two motors cannot act on upright), the closed-form RTI held it 0.5 rad off upright.
    (scene,) = write_family("ball", [9002], tmp_path)
    env = scene_env(str(scene), true_model=True)
    model = scene_model(env, true_model=True)
    env.unwrapped.reset(seed=9002 * 1000 + 2, options={"random": True, "max_omega": 2.0})
    start = {"qpos": env.unwrapped.data.qpos.copy(), "qvel": env.unwrapped.data.qvel.copy()}
    held = {}
    for name, settings in (("free", scene_mpc_settings(env, solver="rti")),
                           ("whole", scene_mpc_settings(env, solver="rti"))):
        if name == "whole":
            settings = settings.updated(free_axis=None)
        _, metrics = run_judged(env, scene_mpc(env, model, settings), 8.0, start, seed=2)
        held[name] = (metrics["swung_up"], metrics["hold_error_rad"])
    assert held["free"][0] and held["free"][1] < 0.02
    assert not held["whole"][0] and held["whole"][1] > 0.2
