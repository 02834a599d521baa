"""The parameter estimator (fvin_mpc.control.adaptation) against oracles: the closed-form pendulum whose
bob doubles, on the model's own step and on MuJoCo; rejected updates; physical bounds; the free scale."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from fvin_mpc.control.adaptation import (
    MINIMUM_SCALE,
    ParameterEstimator,
    ScaledTerms,
    TransitionWindow,
    nominal_parameters,
)
from fvin_mpc.control.model_export import CA, NP, from_rigid_body, from_terms
from fvin_mpc.control.scene import scene_env, scene_model
from fvin_mpc.core.rigid_body import PENDULUM
from fvin_mpc.core.space import S3
from fvin_mpc.envs import SCENES, RigidBodyEnv

H = 0.05


def pendulum_state(theta: float, rate: float) -> np.ndarray:
    return np.array([math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0, 0.0, rate, 0.0])


def scaled_model(mass: float, gain: float = 1.0, damping: float = 0.0):
    """The closed-form pendulum with the parameters applied: the oracle plant on the model's own step."""
    p = [mass, gain, damping]
    return from_terms(S3, ScaledTerms(PENDULUM.terms(CA), p), ScaledTerms(PENDULUM.terms(NP), p), H, 2, "oracle")


def fill(window: TransitionWindow, step, x: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` transitions of ``step(x, u) -> x_next`` under random torques in the motor's range."""
    for _ in range(count):
        u = rng.uniform(-2.0, 2.0, size=1)
        x_next = step(x, u)
        window.add(x, u, x_next)
        x = x_next
    return x


def test_the_estimate_converges_to_the_doubled_bob_on_the_models_own_step():
    plant = scaled_model(2.0)
    window = TransitionWindow(40)
    fill(window, lambda x, u: plant(x, u)[0], pendulum_state(2.0, 0.5), 40, np.random.default_rng(0))
    estimator = ParameterEstimator(from_rigid_body(PENDULUM, H))
    errors = [estimator.prediction_error(window)]
    for _ in range(15):
        update = estimator.update(window)
        if update.accepted:
            assert update.error_after < update.error_before  # every kept step lowers the window's error
        errors.append(estimator.prediction_error(window))
    assert estimator.parameters["mass"] == pytest.approx(2.0, abs=1e-6)
    assert estimator.parameters["damping"] == pytest.approx(0.0, abs=1e-6)
    assert estimator.parameters["gain0"] == 1.0  # pinned: the free scale
    assert np.all(np.diff(errors) <= 0.0) and errors[-1] < 1e-12 * errors[0]


def test_the_estimate_follows_a_change_it_is_not_told_about_on_mujoco():
    """The MuJoCo pendulum, then the same pendulum twice as heavy from the state it was in: the estimate
    sits near 1, then, once the sliding window holds only the heavy plant's transitions, near 2."""
    rng = np.random.default_rng(1)
    window = TransitionWindow(40)
    estimator = ParameterEstimator(from_rigid_body(PENDULUM, H))
    light = RigidBodyEnv("pendulum")
    heavy = RigidBodyEnv("pendulum", physics=replace(SCENES["pendulum"].physics, mass_scale=2.0))
    x, _ = light.reset(options={"qpos": [2.0], "qvel": [0.5]})

    def run(env, x, periods):
        for _ in range(periods):
            u = rng.uniform(-2.0, 2.0, size=1)
            x_next = env.step(u)[0]
            window.add(x, u, x_next)
            x = x_next
            estimator.update(window)
        return x

    x = run(light, x, 60)
    assert estimator.parameters["mass"] == pytest.approx(1.0, abs=0.02)
    heavy.reset(options={"qpos": light.data.qpos.copy(), "qvel": light.data.qvel.copy()})
    run(heavy, x, 60)
    # The model's step (h = 50 ms, K = 2) against MuJoCo's RK4 at 5 ms: a percent of bias at most.
    assert estimator.parameters["mass"] == pytest.approx(2.0, rel=0.02)


def test_an_update_that_worsens_the_window_is_rejected():
    plant = scaled_model(2.0)
    window = TransitionWindow(30)
    fill(window, lambda x, u: plant(x, u)[0], pendulum_state(1.0, -1.0), 30, np.random.default_rng(2))
    estimator = ParameterEstimator(from_rigid_body(PENDULUM, H))
    before, damping = estimator.parameters, estimator.damping
    update = estimator.consider(window, {"mass": 0.5})  # lighter, the wrong way from 1 to 2
    assert not update.accepted and update.candidate_error > update.error_before
    assert estimator.parameters == before and update.error_after == update.error_before
    assert estimator.damping > damping  # the next proposal is a shorter step
    assert estimator.consider(window, {"mass": 1.5}).accepted  # towards the truth: kept


def _fitted_to(plant, free: str, seed: int) -> tuple[ParameterEstimator, TransitionWindow]:
    """An estimator of ``free`` alone after 10 updates on 30 transitions of ``plant`` from a swing."""
    window = TransitionWindow(30)
    fill(window, lambda x, u: plant(x, u)[0], pendulum_state(1.0, 0.0), 30, np.random.default_rng(seed))
    estimator = ParameterEstimator(from_rigid_body(PENDULUM, H), free=(free,))
    for _ in range(10):
        estimator.update(window)
    return estimator, window


def test_parameters_stay_physical():
    # A motor wired backwards: the best unconstrained gain is −1, the estimate stops at the bound.
    estimator, _ = _fitted_to(scaled_model(1.0, gain=-1.0), "gain0", seed=3)
    assert estimator.parameters["gain0"] == pytest.approx(MINIMUM_SCALE)
    assert estimator.parameters["mass"] == 1.0
    # A plant that gains energy (negative damping): the model's added damping stops at 0 (it has none of its own).
    estimator, window = _fitted_to(scaled_model(1.0, damping=-0.05), "damping", seed=4)
    assert estimator.parameters["damping"] == pytest.approx(0.0, abs=1e-12)
    assert not estimator.consider(window, {"damping": -0.05}).accepted  # outside the bounds, however well it fits
    with pytest.raises(ValueError, match="bounds"):
        ParameterEstimator(from_rigid_body(PENDULUM, H), initial={"mass": -1.0})
    with pytest.raises(ValueError, match="unknown"):
        ParameterEstimator(from_rigid_body(PENDULUM, H), free=("length",))


def test_the_free_scale_one_factor_on_all_terms_moves_nothing():
    """Why one parameter must be pinned: mass, gains and damping times one factor give the same step."""
    base, scaled = scaled_model(1.0, 1.0, 0.1), scaled_model(3.0, 3.0, 0.3)
    x, u = pendulum_state(2.5, 1.5), np.array([0.7])
    np.testing.assert_allclose(scaled(x, u)[0], base(x, u)[0], rtol=0, atol=1e-12)
    assert nominal_parameters(1) == {"mass": 1.0, "gain0": 1.0, "damping": 0.0}


def test_a_window_without_excitation_moves_nothing():
    """Half a second near upright with next to no torque (it leaves 1 mrad only at 3.9/s): a mass change is
    invisible there; fitting anyway would chase the learned model's own one-step error (its drift at the
    goal) with absurd values."""
    env = scene_env("pendulum")
    model = scene_model(env)
    rng = np.random.default_rng(5)
    window = TransitionWindow(10)
    x, _ = env.reset(options={"qpos": env.unwrapped.goal_qpos + 1e-3})
    for _ in range(10):
        u = rng.uniform(-1e-3, 1e-3, size=1)
        x_next = env.step(u)[0]
        window.add(x, u, x_next)
        x = x_next
    gated = ParameterEstimator(model)
    # The learned model's own one-step error there: what MIN_EFFECT is set from.
    assert 1e-3 < math.sqrt(gated.prediction_error(window)) < 4e-3
    update = gated.update(window)
    assert update.fitted == () and not update.accepted and gated.parameters == nominal_parameters(1)
    ungated = ParameterEstimator(model, min_effect=0.0)
    for _ in range(10):
        ungated.update(window)
    moved = ungated.parameters
    assert abs(moved["mass"] - 1.0) > 0.5 or moved["damping"] > 1.0  # what the gate prevents
    assert not gated.consider(window, {"mass": 1.0 / MINIMUM_SCALE + 1.0}).accepted  # above the upper bound


def test_scaled_terms_keep_the_models_hinge():
    """A model that steps on a hinge (its terms carry a ``hinge_axis``) keeps it under the parameters."""

    class OnHinge:
        def __init__(self, terms):
            self.__dict__.update(terms.__dict__)
            self._terms = terms
            self.hinge_axis = (0.0, 1.0, 0.0)

        def __getattr__(self, name):
            return getattr(self._terms, name)

    hinge = OnHinge(PENDULUM.terms(NP))
    assert ScaledTerms(hinge, [2.0, 1.0, 0.0]).hinge_axis == (0.0, 1.0, 0.0)
    assert ScaledTerms(PENDULUM.terms(NP), [2.0, 1.0, 0.0]).hinge_axis is None


def test_adaptation_in_the_loop_finds_the_doubled_bob_without_recompiling():
    """The closed-form pendulum's RTI held upright; at 2 s the bob doubles and is knocked (2 rad/s), told
    nothing: the estimate, near 1 before, is within 5 % of 2 after, pushed to the RTI as gain_scale = 1/m,
    and no code is generated or compiled during the episode."""
    from fvin_mpc.control.adaptation import AdaptiveRTI, rti_parameters
    from fvin_mpc.control.closed_loop import run_episode
    from fvin_mpc.control.model_export import CompileCount
    from fvin_mpc.control.scene import scene_mpc, scene_mpc_settings

    physics = replace(SCENES["pendulum"].physics, mass_change=(2.0, 2.0), impulse_delta_omega=2.0, impulse_at_s=2.0)
    env = scene_env("pendulum", true_model=True, physics=physics)
    model = scene_model(env, true_model=True)
    adaptive = AdaptiveRTI(scene_mpc(env, model, scene_mpc_settings(env, solver="rti")))
    calls, runs = CompileCount.calls, CompileCount.compiler_runs
    episode, _ = run_episode(env, adaptive, 6.0, reset_options={"qpos": [math.pi], "qvel": [0.3]}, seed=0)
    assert (CompileCount.calls, CompileCount.compiler_runs) == (calls, runs)
    times = np.array([entry[0] for entry in adaptive.history])
    masses = np.array([entry[1]["mass"] for entry in adaptive.history])
    assert np.all(np.abs(masses[times < 2.0] - 1.0) < 0.05)
    assert masses[-1] == pytest.approx(2.0, rel=0.05)
    assert adaptive.controller.parameters[0] == pytest.approx(1.0 / masses[-1])  # gain_scale = gain / mass
    assert np.max(np.abs(episode.angle_from_goal[episode.time > 5.0])) < 0.05  # held again
    assert rti_parameters(model, {"mass": 2.0, "gain0": 1.0, "damping": 0.0})[0] == 0.5


def test_the_mass_as_a_gain_scale_steps_like_the_heavier_body():
    """The identity ``rti_parameters`` rests on: the damped closed form, mass 2, damping +0.05 as the
    estimator's terms and as the RTI's run-time parameters (gain_scale 1/2, damping (0.1 + 0.05)/2)."""
    from fvin_mpc.control.adaptation import rti_parameters
    from fvin_mpc.core.rigid_body import PENDULUM_DAMPED

    model = from_rigid_body(PENDULUM_DAMPED, H)
    estimate = {"mass": 2.0, "gain0": 0.8, "damping": 0.05}
    p = [estimate["mass"], estimate["gain0"], estimate["damping"]]
    heavier = from_terms(S3, ScaledTerms(PENDULUM_DAMPED.terms(CA), p), ScaledTerms(PENDULUM_DAMPED.terms(NP), p),
                         H, 2, "heavier")
    vector = rti_parameters(model, estimate)
    for x, u in ((pendulum_state(2.5, 1.0), [0.7]), (pendulum_state(-0.4, -3.0), [-1.5])):
        expected = np.asarray(heavier(x, u)[0], dtype=float).ravel()
        stepped = np.asarray(model.parametric_step(x, u, vector)[0], dtype=float).ravel()
        assert np.max(np.abs(stepped - expected)) < 1e-12


def test_the_mass_as_a_gain_scale_on_a_learned_dissipation():
    """The same identity through a learned model's ``dissipation_cholesky`` (the shipped damped pendulum):
    the run-time parameters from ``rti_parameters`` step like the estimator's scaled terms."""
    from fvin_mpc.control.adaptation import AdaptiveRTI, dissipation_block, rti_parameters

    env = scene_env("pendulum_damped")
    model = scene_model(env)
    assert dissipation_block(model) == "dissipation_cholesky"
    estimate = {"mass": 1.7, "gain0": 1.1, "damping": 0.03}
    p = [estimate["mass"], estimate["gain0"], estimate["damping"]]
    heavier = from_terms(S3, ScaledTerms(model.casadi_terms, p), ScaledTerms(model.numpy_terms, p),
                         model.step_size, model.newton_iters, "heavier")
    vector = rti_parameters(model, estimate)
    for x, u in ((pendulum_state(2.5, 1.0), [0.7]), (pendulum_state(-0.4, -3.0), [-1.5])):
        expected = np.asarray(heavier(x, u)[0], dtype=float).ravel()
        stepped = np.asarray(model.parametric_step(x, u, vector)[0], dtype=float).ravel()
        assert np.max(np.abs(stepped - expected)) < 1e-12
    undamped = scene_model(scene_env("pendulum"))
    with pytest.raises(ValueError, match="damping"):
        rti_parameters(undamped, {"mass": 1.0, "gain0": 1.0, "damping": 0.1})

    class Stub:  # only what AdaptiveRTI reads before a run
        model = undamped

        def set_parameters(self, values):
            pass

    with pytest.raises(ValueError, match="damping"):
        AdaptiveRTI(Stub(), free=("mass", "damping"))
