"""The parameter estimator on a free body (R³ × S³, fvin_mpc.control.adaptation) against oracles: the closed-form
quadrotor made heavier through its own parameters, the learned quadrotor's scaled blocks, and MuJoCo's craft
picking up a payload it is not told about."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fvin_mpc.control.adaptation import (
    FREE_BODY_MIN_EFFECT,
    AdaptiveRTI,
    ParameterEstimator,
    TransitionWindow,
    default_free,
    free_body_vector,
    nominal_estimate,
    rti_parameters,
)
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.flight import quadrotor_model
from fvin_mpc.control.model_export import CompileCount, from_closed_form
from fvin_mpc.core import s3
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.core.space import R3S3
from fvin_mpc.envs.quadrotor_env import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene
from fvin_mpc.studies.flight_report import make_controller


@pytest.fixture(scope="module")
def env():
    environment = QuadrotorEnv("quadrotor")
    yield environment
    environment.close()


def payload_env(at: float, scale: float, shift=None) -> QuadrotorEnv:
    change = (at, scale) if shift is None else (at, scale, shift)
    physics = dataclasses.replace(resolve_scene("quadrotor").physics, mass_change=change)
    return QuadrotorEnv("quadrotor", physics=physics)


def estimate(mass: float = 1.0, inertia: float = 1.0, gains=(1.0, 1.0, 1.0, 1.0)) -> dict[str, float]:
    return {"mass": mass, "inertia": inertia, **{f"gain{i}": g for i, g in enumerate(gains)}}


def test_the_closed_forms_vector_steps_like_the_heavier_craft(env):
    """``mass`` 1.5 and ``inertia`` 1.3 through the run-time parameters step exactly like the closed form built
    with 0.75 kg and 1.5 · 1.3 J (the mass scales the inertia too: uniformly denser), gravity unchanged; the rotors'
    gains go to the gain scale."""
    model = quadrotor_model(env, true_model=True)
    craft = env.unwrapped.space.closed_form(env.unwrapped.model, env.unwrapped.body_name)
    heavier = dataclasses.replace(craft, mass=1.5 * craft.mass,
                                  inertia=tuple(tuple(1.5 * 1.3 * v for v in row) for row in craft.inertia))
    oracle = from_closed_form(R3S3, heavier, model.step_size, model.newton_iters)
    vector = rti_parameters(model, estimate(1.5, 1.3))
    assert vector[model.model_parameters.slice("gravity")] == pytest.approx([craft.gravity])
    rng = np.random.default_rng(0)
    for _ in range(3):
        x = env.unwrapped.goal_state + np.concatenate([rng.normal(0, 0.1, 3), np.zeros(4), rng.normal(0, 1.0, 6)])
        q = rng.normal(size=4)
        x[3:7] = q / np.linalg.norm(q)
        u = rng.uniform(0.5, 2.0, 4)
        expected = np.asarray(oracle.step(x, u)[0], dtype=float).ravel()
        stepped = np.asarray(model.parametric_step(x, u, vector)[0], dtype=float).ravel()
        assert np.max(np.abs(stepped - expected)) < 1e-12
    gains = rti_parameters(model, estimate(gains=(0.7, 1.0, 1.1, 1.0)))
    assert gains[model.model_parameters.slice("gain_scale")] == pytest.approx([0.7, 1.0, 1.1, 1.0])
    assert rti_parameters(model, nominal_estimate(model)) == pytest.approx(model.model_parameters.defaults)


def test_the_learned_crafts_blocks_scale_its_mass_matrix_potential_and_inertia(env):
    """The learned model's Cholesky factors take the square root: ``M`` and ``J`` scale by the estimate up to
    their parametrizations' ``ε`` (``J`` by mass × inertia); the potential's uniform field and its network's output
    layer scale with the mass; the step at the nominal estimate is the exported step."""
    model = quadrotor_model(env)
    parameters = model.model_parameters
    own = parameters.defaults
    vector = np.array(free_body_vector(model, [1.5, 1.3, 1.0, 1.0, 1.0, 1.0]), dtype=float)

    def block(values, name):
        return values[parameters.slice(name)]

    for name, scale in (("mass_cholesky", 1.5), ("inertia_cholesky", 1.5 * 1.3)):
        before = np.array(s3.symmetric_from_cholesky(tuple(block(own, name))), dtype=float)
        after = np.array(s3.symmetric_from_cholesky(tuple(block(vector, name))), dtype=float)
        assert np.allclose(after, scale * before, rtol=1e-12)
    assert block(vector, "potential_linear") == pytest.approx(1.5 * block(own, "potential_linear"), rel=1e-14)
    output = next(b.name for b in parameters.blocks if b.name.startswith("potential_w"))
    assert block(vector, output) == pytest.approx(1.5 * block(own, output), rel=1e-14)
    x, u = env.unwrapped.goal_state, env.unwrapped.hover_thrust
    nominal = np.asarray(model.parametric_step(x, u, rti_parameters(model, nominal_estimate(model)))[0]).ravel()
    assert np.max(np.abs(nominal - np.asarray(model.step(x, u)[0]).ravel())) < 1e-12


def test_the_estimate_converges_on_the_models_own_step(env):
    """Transitions of the closed form with mass 1.5 and inertia 1.3 under random thrusts: fitting both finds
    them to 1e-6, every kept step lowering the window's error; by default only the mass is free."""
    model = quadrotor_model(env, true_model=True)
    assert default_free(model) == ("mass",)
    truth = rti_parameters(model, estimate(1.5, 1.3))
    rng = np.random.default_rng(1)
    window, x = TransitionWindow(30), env.unwrapped.goal_state.copy()
    for _ in range(30):
        u = env.unwrapped.hover_thrust * 1.5 + rng.uniform(-0.3, 0.3, 4)
        x_next = np.asarray(model.parametric_step(x, u, truth)[0], dtype=float).ravel()
        window.add(x, u, x_next)
        x = x_next
    estimator = ParameterEstimator(model, free=("mass", "inertia"))
    for _ in range(20):
        update = estimator.update(window)
        if update.accepted:
            assert update.error_after < update.error_before
    assert estimator.parameters["mass"] == pytest.approx(1.5, abs=1e-6)
    assert estimator.parameters["inertia"] == pytest.approx(1.3, abs=1e-6)
    with pytest.raises(ValueError, match="damping"):
        ParameterEstimator(model, free=("mass", "damping"))


def test_the_min_effect_is_the_learned_crafts_own_error_in_hover(env):
    """:data:`FREE_BODY_MIN_EFFECT` is the learned quadrotor's one-step error in hover on MuJoCo (within 2×), and
    a hovering craft excites its mass far above it."""
    model = quadrotor_model(env)
    base = env.unwrapped
    estimator = ParameterEstimator(model)
    rng = np.random.default_rng(0)
    window = TransitionWindow(40)
    x, _ = env.reset(seed=0, options={"hover": True})
    for _ in range(40):
        u = base.hover_thrust * (1.0 + rng.uniform(-0.02, 0.02, 4))
        x_next, *_ = env.step(u)
        window.add(x, u, x_next)
        x = x_next
    residual = np.sqrt(estimator.prediction_error(window) * 12)  # the norm of a transition's 12 entries, RMS
    assert 0.5 * FREE_BODY_MIN_EFFECT < residual < 2.0 * FREE_BODY_MIN_EFFECT
    update = estimator.update(window)
    assert update.fitted == ("mass",)


def test_a_payload_moves_the_centre_of_mass_the_state_follows_and_reset_undoes_it():
    """``mass_change=(t, 1.5, shift)``: from ``t`` the craft is 1.5× as heavy and its centre of mass ``shift``
    off (the observed position with it); the observed velocity is the centre's; reset restores the craft."""
    plant = payload_env(0.1, 1.5, (0.0, 0.0, -0.02))
    model = plant.unwrapped.model
    body = plant.unwrapped.body_name
    built_mass = float(model.body(body).mass[0])
    built_centre = model.body(body).ipos.copy()
    x, _ = plant.reset(seed=0, options={"hover": True})
    for _ in range(10):
        x, *_ = plant.step(plant.unwrapped.hover_thrust)
    assert float(model.body(body).mass[0]) == pytest.approx(1.5 * built_mass)
    assert model.body(body).ipos == pytest.approx(built_centre + [0.0, 0.0, -0.02])
    data = plant.unwrapped._data
    assert x[:3] == pytest.approx(data.xipos[model.body(body).id])
    h, before = plant.unwrapped.dt, x
    after, *_ = plant.step(plant.unwrapped.hover_thrust)
    assert (after[:3] - before[:3]) / h == pytest.approx(0.5 * (after[7:10] + before[7:10]), abs=2e-3)
    plant.reset(seed=0, options={"hover": True})
    assert float(model.body(body).mass[0]) == pytest.approx(built_mass)
    assert model.body(body).ipos == pytest.approx(built_centre)
    with pytest.raises(ValueError, match="mass_change"):
        dataclasses.replace(plant.unwrapped.physics, mass_change=(1.0, 1.5, (0.0, 0.02)))
    plant.close()


def test_adaptation_in_the_loop_finds_the_payload_without_recompiling():
    """The closed-form craft hovering under the RTI (uncompiled: the test's speed) picks up half its mass again
    at 0.6 s, unannounced: the estimate stays at 1 before and is within 2 % of 1.5 a second after, the RTI's
    parameters carry it, and nothing is compiled during the flight."""
    plant = payload_env(0.6, 1.5)
    controller = AdaptiveRTI(make_controller(plant, "closed-form", compile="none"))
    compiles = CompileCount.calls
    run_episode(plant, controller, 1.6, {"hover": True}, seed=0, latency="none")
    assert CompileCount.calls == compiles
    history = {round(t, 3): entry["mass"] for t, entry, *_ in controller.history}
    assert abs(history[0.58] - 1.0) < 0.02
    assert controller.parameters["mass"] == pytest.approx(1.5, rel=0.02)
    expected = rti_parameters(controller.model, controller.parameters)
    assert controller.controller.parameters == pytest.approx(expected)
    plant.close()


def test_a_worn_rotor_delivers_its_share_from_its_time_and_reset_restores_it():
    """``actuator_change=(t, 0, 0.7)``: from ``t`` rotor 0 pushes with 0.7 of its command (the level craft's
    actuator force along z is the others' thrust plus 0.7 of its own); reset restores it; a rotor the craft
    does not have is refused."""
    from fvin_mpc.core.errors import SceneError

    physics = dataclasses.replace(resolve_scene("quadrotor").physics, actuator_change=(0.1, 0, 0.7))
    plant = QuadrotorEnv("quadrotor", physics=physics)
    data, u = plant.unwrapped._data, np.array([1.0, 1.2, 1.4, 1.6])
    body = plant.unwrapped.model.body(plant.unwrapped.body_name).id

    def thrust() -> float:  # the actuators' force along the body's z axis
        return float(data.xmat[body].reshape(3, 3)[:, 2] @ data.qfrc_actuator[:3])

    plant.reset(seed=0, options={"hover": True})
    plant.step(u)
    assert thrust() == pytest.approx(u.sum(), rel=1e-9)
    for _ in range(5):
        plant.step(u)
    assert thrust() == pytest.approx(u.sum() - 0.3 * u[0], rel=1e-9)
    plant.reset(seed=0, options={"hover": True})
    plant.step(u)
    assert thrust() == pytest.approx(u.sum(), rel=1e-9)
    plant.close()
    with pytest.raises(SceneError, match="actuator 7"):
        QuadrotorEnv("quadrotor", physics=dataclasses.replace(physics, actuator_change=(0.1, 7, 0.7)))
    with pytest.raises(ValueError, match="actuator_change"):
        dataclasses.replace(physics, actuator_change=(0.1, 0, -1.0))


def test_the_effect_cost_charges_a_heavier_craft_what_it_charges_the_unchanged_one(env):
    """``control_cost="effect"`` (the default): the closed-form craft of mass 1.5 (its inertia with it) steps on
    ``1.5 u`` exactly as the unchanged craft on ``u`` (the step is homogeneous), and its stage residual on ``1.5 u``
    and the 1.5× goal thrust equals the unchanged craft's — the two control problems are one, in scaled controls, so
    the heavier craft plans the same motion. Charged in newtons (``"command"``) it pays ``1.5²`` for it. With the
    exported model's own parameters both costs are the same residual."""
    from fvin_mpc.control.flight import quadrotor_mpc_settings
    from fvin_mpc.control.problem import residual_functions

    model = quadrotor_model(env, true_model=True)
    parameters = model.model_parameters
    nominal, heavier = parameters.defaults, rti_parameters(model, estimate(1.5))
    np.testing.assert_allclose(np.ravel(parameters.control_effect(heavier)), np.full(4, 1 / 1.5), rtol=1e-14)
    worn = rti_parameters(model, estimate(1.5, gains=(0.7, 1.0, 1.0, 1.0)))
    np.testing.assert_allclose(np.ravel(parameters.control_effect(worn)), np.array([0.7, 1, 1, 1]) / 1.5, rtol=1e-14)
    learned = quadrotor_model(env)
    effect = learned.model_parameters.control_effect(rti_parameters(learned, estimate(1.5)))
    np.testing.assert_allclose(np.ravel(effect), np.full(4, 1 / 1.5), rtol=1e-12)

    rng = np.random.default_rng(3)
    x = env.unwrapped.goal_state + np.concatenate([rng.normal(0, 0.1, 3), np.zeros(4), rng.normal(0, 1.0, 6)])
    reference = env.unwrapped.goal_state
    u, u_goal = rng.uniform(0.5, 2.0, 4), np.full(4, 1.2)
    stepped = np.asarray(model.parametric_step(x, 1.5 * u, heavier)[0], dtype=float).ravel()
    unchanged = np.asarray(model.parametric_step(x, u, nominal)[0], dtype=float).ravel()
    assert np.max(np.abs(stepped - unchanged)) < 1e-12

    def stage(control_cost: str, controls, goal, p) -> np.ndarray:
        settings = quadrotor_mpc_settings(control_cost=control_cost)
        function, _ = residual_functions(R3S3.layout, settings, 4, 30.0, None, None, parameters.size,
                                         parameters.control_effect)
        return np.asarray(function(x, controls, reference, goal, p), dtype=float).ravel()

    np.testing.assert_allclose(stage("effect", 1.5 * u, 1.5 * u_goal, heavier), stage("effect", u, u_goal, nominal),
                               rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(stage("command", 1.5 * u, 1.5 * u_goal, heavier)[-4:],
                               1.5 * stage("command", u, u_goal, nominal)[-4:], rtol=1e-13)
    np.testing.assert_array_equal(stage("effect", u, u_goal, nominal), stage("command", u, u_goal, nominal))
    with pytest.raises(ValueError, match="control_cost"):
        quadrotor_mpc_settings(control_cost="newtons")


def test_a_worn_rotor_is_not_read_as_mass_by_the_mass_alone():
    """The closed-form craft hovering under the RTI (uncompiled) with rotor 0 at 70 % from 0.3 s: the mass alone
    is fitted on the translation's rows (``TRANSLATION_ROWS``), where the worn rotor shows as the thrust it lost
    (effective mass about 1.08); the rotation's rows carry its torque, which no mass explains — fitted there,
    with the mass scaling the inertia, the estimate ran to 2.7–3.6 and the craft fell. Here it stays within 1.0–1.2
    and the craft holds its point within 5 cm."""
    from fvin_mpc.control.adaptation import TRANSLATION_ROWS

    physics = dataclasses.replace(resolve_scene("quadrotor").physics, actuator_change=(0.3, 0, 0.7))
    plant = QuadrotorEnv("quadrotor", physics=physics)
    controller = AdaptiveRTI(make_controller(plant, "closed-form", compile="none"))
    assert controller.estimator.rows == TRANSLATION_ROWS
    episode, _ = run_episode(plant, controller, 2.0, {"hover": True}, seed=0, latency="none")
    masses = [entry["mass"] for _, entry, *_ in controller.history]
    assert 1.0 <= max(masses) <= 1.2 and 1.0 <= masses[-1] <= 1.2
    assert np.linalg.norm(episode.states[-1, :3] - plant.unwrapped.hover_point) < 0.05
    assert ParameterEstimator(controller.model, free=("mass", "inertia")).rows == tuple(range(12))
    plant.close()


def test_the_low_rank_corrections_are_fitted_where_the_mass_cannot_reach(env):
    """The learned craft exported with rank-1 output-layer corrections: the nominal estimate maps to the exported
    parameters, ``free=("lowrank",)`` names all 24 entries, unbounded; on transitions of the model with a known
    correction (the rotors' force layer's strongest direction 20 % weaker) the fit lowers the window's error by
    more than a hundredfold, every kept step lowering it."""
    from fvin_mpc.control.adaptation import expand_free, low_rank_names

    model = quadrotor_model(env, low_rank=1)
    names = low_rank_names(model)
    assert len(names) == 24 and names[0] == "lowrank_force_w2[0,0]"
    assert rti_parameters(model, nominal_estimate(model)) == pytest.approx(model.model_parameters.defaults)
    assert expand_free(model, ("mass", "lowrank_gain_w2")) == ("mass", *names[12:])
    force_layer = load_checkpoint(resolve_scene("quadrotor").default_checkpoint).weights["force_w2"]
    strongest = np.linalg.svd(force_layer)[0][:, 0]
    truth_estimate = {**nominal_estimate(model), **{f"lowrank_force_w2[{i},0]": -0.2 * strongest[i] for i in range(12)}}
    truth = rti_parameters(model, truth_estimate)
    rng = np.random.default_rng(2)
    window, x = TransitionWindow(40), env.unwrapped.goal_state.copy()
    for _ in range(40):
        u = env.unwrapped.hover_thrust + rng.uniform(-0.3, 0.3, 4)
        x_next = np.asarray(model.parametric_step(x, u, truth)[0], dtype=float).ravel()
        window.add(x, u, x_next)
        x = x_next
    estimator = ParameterEstimator(model, free=("lowrank",))
    before = estimator.prediction_error(window)
    for _ in range(10):
        update = estimator.update(window)
        if update.accepted:
            assert update.error_after < update.error_before
    assert estimator.prediction_error(window) < before / 100.0
    with pytest.raises(ValueError, match="no low-rank corrections"):
        ParameterEstimator(quadrotor_model(env), free=("lowrank",))

