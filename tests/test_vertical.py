"""Networks of the body-frame vertical: a ball-jointed body's terms cannot tell a turn of the world about
the vertical (what the two-motor ball scenes need), checked against the rotation matrix, finite differences and
the whole step."""

from __future__ import annotations

import numpy as np
import pytest

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, body_vertical, body_vertical_gradient, init_weights

NP = get_ops("numpy")
RNG = np.random.default_rng(11)
VERTICAL = (0.3, -0.2, 1.0)


def _quaternion():
    q = RNG.normal(size=4)
    return tuple(q / np.linalg.norm(q))


def _turned_about(vertical, angle, q):
    v = np.asarray(vertical) / np.linalg.norm(vertical)
    return s3.multiply((np.cos(angle / 2), *(np.sin(angle / 2) * v)), q)


def test_the_body_vertical_is_r_transpose_v_and_its_gradient_the_chain_rule():
    config = ModelConfig(vertical=VERTICAL)
    v = np.array(config.vertical)
    for _ in range(5):
        q = _quaternion()
        assert np.allclose(body_vertical(q, v), np.array(s3.rotation_matrix(q)).T @ v, atol=1e-14)
        g = RNG.normal(size=3)
        gradient = np.array(body_vertical_gradient(q, v, tuple(g)))
        steps = 1e-6 * np.eye(4)
        numeric = [(g @ np.array(body_vertical(tuple(q + e), v)) - g @ np.array(body_vertical(tuple(q - e), v))) / 2e-6
                   for e in steps]
        np.testing.assert_allclose(gradient, numeric, atol=1e-8)
        assert np.allclose(body_vertical(tuple(-np.array(q)), v), body_vertical(q, v))  # even in the sign


def test_the_terms_and_the_step_cannot_tell_a_turn_about_the_vertical():
    config = ModelConfig(control_dim=2, dissipation=True, vertical=VERTICAL, step_size=0.05)
    weights = init_weights(config, seed=3)
    terms = LearnedTerms(weights, config, NP)
    q, omega, u = _quaternion(), tuple(RNG.normal(size=3)), (0.4, -0.7)
    turned = _turned_about(config.vertical, 1.1, q)
    assert float(terms.potential(turned)) == pytest.approx(float(terms.potential(q)), abs=1e-13)
    np.testing.assert_allclose(np.array(terms.inertia(turned)), np.array(terms.inertia(q)), atol=1e-13)
    np.testing.assert_allclose(np.array(terms.control_gain(turned)), np.array(terms.control_gain(q)), atol=1e-13)
    # The step commutes with the turn: ω is in the body frame (unchanged), q turns with the world.
    here = fvin.fvin_step(q, omega, u, terms, 0.05, 3, NP)
    there = fvin.fvin_step(turned, omega, u, terms, 0.05, 3, NP)
    expected = _turned_about(config.vertical, 1.1, here.q)
    assert abs(abs(float(np.dot(there.q, expected))) - 1.0) < 1e-12
    np.testing.assert_allclose(there.omega, here.omega, atol=1e-12)
    # A network of q (the default) can tell: the turn changes its potential.
    plain = ModelConfig(control_dim=2)
    plain_terms = LearnedTerms(init_weights(plain, seed=3), plain, NP)
    assert abs(float(plain_terms.potential(turned)) - float(plain_terms.potential(q))) > 1e-6


def test_the_vertical_is_stored_unit_and_a_checkpoint_without_it_still_loads(tmp_path):
    config = ModelConfig(control_dim=2, vertical=(0.0, 0.0, 2.0))
    assert config.vertical == (0.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="vertical"):
        ModelConfig(vertical=(0.0, 0.0, 0.0))
    stem = save_checkpoint(tmp_path / "m", config, init_weights(config, seed=0), scene="test")
    assert load_checkpoint(stem).config.vertical == (0.0, 0.0, 1.0)
    old = ModelConfig.from_dict({k: v for k, v in ModelConfig(control_dim=2).to_dict().items() if k != "vertical"})
    assert old.vertical is None  # checkpoints written before the field load as networks of q


def test_train_gives_a_ball_scene_its_vertical_and_a_hinge_none(tmp_path):
    from fvin_mpc.envs.families import write_family
    from fvin_mpc.learning.excitation import collect_swings
    from fvin_mpc.learning.space_training import default_model_config

    ball, = write_family("ball", [9003], tmp_path)
    hinge, = write_family("hinge", [9002], tmp_path)
    ball_config = default_model_config(collect_swings(str(ball), trajectories=10, steps=5, progress=False))
    assert ball_config.vertical == pytest.approx((0.0, 0.0, 1.0)) and ball_config.hinge_axis is None
    hinge_config = default_model_config(collect_swings(str(hinge), trajectories=10, steps=5, progress=False))
    assert hinge_config.vertical is None and hinge_config.hinge_axis is not None
