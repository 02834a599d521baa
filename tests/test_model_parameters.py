"""Model parameters as run-time inputs (:mod:`fvin_mpc.core.model_parameters`,
:attr:`~fvin_mpc.control.model_export.ExportedModel.parametric_step`): with the model's own values the
parametrized step is the constant one; a changed value changes the step exactly as rebuilding the model
with it does (the same terms code, on symbols); the gain scale multiplies each control's effect."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fvin_mpc.control import model_export as export
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.core.quadrotor import x_configuration
from fvin_mpc.core.rigid_body import PENDULUM, PENDULUM_DAMPED
from fvin_mpc.core.space import R3S3, S3


def random_states(model, count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    layout = model.space.layout
    states = []
    for _ in range(count):
        x = rng.normal(size=layout.state_dim)
        x[layout.attitude("test").quaternion] /= np.linalg.norm(x[layout.attitude("test").quaternion])
        x[layout.attitude("test").omega] *= 2.0
        states.append(x)
    return states


def step(function, *arguments) -> np.ndarray:
    return np.asarray(function(*arguments)[0], dtype=float).ravel()


CRAFT = x_configuration(mass=0.5, inertia=((2e-3, 0, 0), (0, 2e-3, 0), (0, 0, 4e-3)), arm=0.1,
                        yaw_coefficient=0.01)


def closed_form_models():
    return {"pendulum": export.from_rigid_body(PENDULUM, 0.05),
            "damped": export.from_rigid_body(PENDULUM_DAMPED, 0.05),
            "quadrotor": export.from_quadrotor(CRAFT, 0.02)}


@pytest.fixture(scope="module")
def models():
    return {**closed_form_models(),
            "learned": export.from_checkpoint("pendulum_sign-invariant"),
            "learned-damped": export.from_checkpoint("pendulum_damped_sign-invariant"),
            "learned-quadrotor": export.from_checkpoint("quadrotor_fixed-inertia")}


def test_the_parameter_vectors_name_what_each_model_has(models):
    assert models["pendulum"].model_parameters.names[:2] == ("gain_scale[0]", "inertia[0,0]")
    assert "mass_gravity" in models["pendulum"].model_parameters.names
    assert "damping" not in models["pendulum"].model_parameters.names  # no damping: no term to scale
    assert "damping" in models["damped"].model_parameters.names
    assert [b.name for b in models["quadrotor"].model_parameters.blocks] == ["gain_scale", "mass", "inertia",
                                                                              "gravity"]
    learned = [b.name for b in models["learned-damped"].model_parameters.blocks]
    assert learned == ["gain_scale", "dissipation_cholesky", "potential_w2"]
    quadrotor = [b.name for b in models["learned-quadrotor"].model_parameters.blocks]
    assert quadrotor == ["gain_scale", "inertia_cholesky", "mass_cholesky", "potential_linear", "potential_w2"]
    assert models["learned-quadrotor"].model_parameters.block(
        models["learned-quadrotor"].model_parameters.defaults, "gain_scale") == [1.0] * 4


@pytest.mark.parametrize("name", ["pendulum", "damped", "quadrotor", "learned", "learned-damped",
                                  "learned-quadrotor"])
def test_with_the_model_own_values_the_parametrized_step_is_the_constant_one(models, name):
    model = models[name]
    defaults = model.model_parameters.defaults
    rng = np.random.default_rng(1)
    for x in random_states(model, 20):
        u = rng.normal(size=model.control_dim)
        np.testing.assert_allclose(step(model.parametric_step, x, u, defaults), step(model.step, x, u),
                                   rtol=0.0, atol=1e-14)
        assert float(model.parametric_energy(x, defaults)) == pytest.approx(model.energy(x), rel=1e-13, abs=1e-13)


@pytest.mark.parametrize("name", ["pendulum", "quadrotor", "learned-quadrotor"])
def test_a_gain_scale_multiplies_each_control_effect(models, name):
    model = models[name]
    rng = np.random.default_rng(2)
    scale = rng.uniform(0.3, 1.7, size=model.control_dim)
    p = model.model_parameters.values(gain_scale=scale)
    for x in random_states(model, 10, seed=3):
        u = rng.normal(size=model.control_dim)
        np.testing.assert_allclose(step(model.parametric_step, x, u, p), step(model.step, x, scale * u),
                                   rtol=0.0, atol=1e-14)


def test_a_changed_physical_value_steps_as_the_model_rebuilt_with_it(models):
    """The parametrized terms are the terms code on symbols: changing a value is rebuilding with it."""
    cases = [("damped", dataclasses.replace(PENDULUM_DAMPED, damping=0.4, mass_gravity=7.0), 0.05, S3,
              {"damping": 0.4, "mass_gravity": 7.0}),
             ("quadrotor", dataclasses.replace(CRAFT, mass=0.8, gravity=9.0), 0.02, R3S3,
              {"mass": 0.8, "gravity": 9.0})]
    for name, body, h, space, blocks in cases:
        model = models[name]
        rebuilt = export.from_closed_form(space, body, h)
        p = model.model_parameters.values(**blocks)
        for x in random_states(model, 10, seed=4):
            u = np.full(model.control_dim, 0.3)
            changed = step(model.parametric_step, x, u, p)
            np.testing.assert_allclose(changed, step(rebuilt.step, x, u), rtol=0.0, atol=1e-13)
            assert np.max(np.abs(changed - step(model.step, x, u))) > 1e-6  # it did change the step


def test_a_changed_learned_weight_steps_as_the_checkpoint_with_it(models):
    model = models["learned-damped"]
    checkpoint = load_checkpoint("pendulum_damped_sign-invariant")
    weights = dict(checkpoint.weights)
    weights["dissipation_cholesky"] = np.asarray(weights["dissipation_cholesky"]) * 2.0
    weights["potential_w2"] = np.asarray(weights["potential_w2"]) * 0.9
    rebuilt = export.from_checkpoint(dataclasses.replace(checkpoint, weights=weights))
    parameters = model.model_parameters
    p = parameters.values(dissipation_cholesky=weights["dissipation_cholesky"], potential_w2=weights["potential_w2"])
    for x in random_states(model, 10, seed=5):
        u = np.array([0.4])
        np.testing.assert_allclose(step(model.parametric_step, x, u, p), step(rebuilt.step, x, u),
                                   rtol=0.0, atol=1e-13)


def test_wrong_parameter_values_are_refused_with_the_reason(models):
    parameters = models["pendulum"].model_parameters
    with pytest.raises(ValueError, match="has 1 entries, got 2"):
        parameters.values(gain_scale=[1.0, 2.0])
    with pytest.raises(KeyError, match="no parameter block 'mass'"):
        parameters.values(mass=1.0)
    with pytest.raises(ValueError, match="non-finite"):
        parameters.values(mass_gravity=np.nan)
    with pytest.raises(ValueError, match=f"need {parameters.size} finite values"):
        parameters.values(np.ones(3))


def test_a_low_rank_output_layer_correction_steps_as_the_checkpoint_with_it():
    """``low_rank=2`` adds a zero ``out × 2`` block per network output layer but the potential's (a parameter
    whole already): at zero the step is the exported one; with ``C`` it is the checkpoint whose layer is
    ``W + C Σ_2 V_2ᵀ`` (the layer's own two strongest directions); ``C = α U_2`` scales those directions by
    ``1 + α``. A negative rank is refused."""
    from fvin_mpc.core.model_parameters import learned_parameters, low_rank_basis

    checkpoint = load_checkpoint("quadrotor_fixed-inertia")
    model = export.from_checkpoint(checkpoint, low_rank=2)
    blocks = {b.name: b.default for b in model.model_parameters.blocks}
    assert {name: value.shape for name, value in blocks.items() if name.startswith("lowrank_")} == {
        "lowrank_force_w2": (12, 2), "lowrank_gain_w2": (12, 2)}
    assert not any(np.any(value) for name, value in blocks.items() if name.startswith("lowrank_"))
    rng = np.random.default_rng(6)
    correction = {name: rng.normal(0.0, 0.3, (12, 2)) for name in ("lowrank_force_w2", "lowrank_gain_w2")}
    weights = dict(checkpoint.weights)
    for name, c in correction.items():
        layer = name.removeprefix("lowrank_")
        weights[layer] = np.asarray(weights[layer]) + c @ low_rank_basis(weights[layer], 2)
    rebuilt = export.from_checkpoint(dataclasses.replace(checkpoint, weights=weights))
    p = model.model_parameters.values(**correction)
    for x in random_states(model, 6, seed=7):
        u = np.full(4, 1.2)
        np.testing.assert_allclose(step(model.parametric_step, x, u, model.model_parameters.defaults),
                                   step(model.step, x, u), rtol=0.0, atol=1e-13)
        changed = step(model.parametric_step, x, u, p)
        np.testing.assert_allclose(changed, step(rebuilt.step, x, u), rtol=0.0, atol=1e-12)
        assert np.max(np.abs(changed - step(model.step, x, u))) > 1e-4
    layer = np.asarray(checkpoint.weights["gain_w2"])
    left, singular, right = np.linalg.svd(layer)
    scaled = layer + (0.5 * left[:, :2]) @ low_rank_basis(layer, 2)
    np.testing.assert_allclose(np.linalg.svd(scaled, compute_uv=False)[:2], 1.5 * singular[:2], rtol=1e-12)
    with pytest.raises(ValueError, match="rank is >= 0"):
        learned_parameters(checkpoint.weights, checkpoint.config, low_rank=-1)
