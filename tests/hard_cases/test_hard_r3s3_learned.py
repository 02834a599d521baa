"""Hard cases of the combined R³ × S³ step with *learned* terms (random networks, every variant):
fast spins past the solvability limit, far translations where the tanh networks saturate, sign
flips, and near-singular solves (an inertia or a mass matrix close to singular). Always finite,
``|q_{k+1}| = 1``, the same rotation for ``±q`` in the sign-invariant variants. The closed-form
quadrotor's hard cases are in ``tests/test_r3s3.py``.
"""

import numpy as np
import strategies as S
from hypothesis import given, settings
from hypothesis import strategies as st

from fvin_mpc.core import fvin_r3s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks_r3s3 import LearnedCombinedTerms, R3S3Config, init_weights

NP = get_ops("numpy")
CONFIGS = {variant: R3S3Config(variant=variant, hidden_width=6, step_size=0.02, newton_iters=4)
           for variant in ("fixed-inertia", "sign-invariant", "plain")}


def learned_terms(variant: str, seed: int, inertia: float = 0.01, mass: float = 0.5) -> LearnedCombinedTerms:
    config = CONFIGS[variant]
    weights = init_weights(config, seed, mass=mass, inertia=inertia, gravity_force=5.0)
    rng = np.random.default_rng(seed)
    for name in weights:
        if name.endswith(f"_w{config.hidden_layers}") or name.endswith(f"_b{config.hidden_layers}"):
            weights[name] = weights[name] * 10.0 + rng.normal(scale=0.3, size=weights[name].shape)
    return LearnedCombinedTerms(weights, config, NP)


def run(terms: LearnedCombinedTerms, state: np.ndarray, u: np.ndarray, h: float, k: int) -> tuple[np.ndarray, float]:
    out, residual = fvin_r3s3.step_state(state, u, terms, h, k, NP)
    return out, float(residual)


@settings(max_examples=S.budget(40))
@given(variant=st.sampled_from(sorted(CONFIGS)), seed=S.SEEDS, q=S.unit_quaternions(), axis=S.unit_vectors(),
       spin=S.floats(0.0, 2.5), h=S.log_uniform(1e-3, 0.1), k=st.integers(1, 8), thrust=S.floats(0.0, 4.0))
@S.counted
def test_fast_spins_of_a_learned_model_stay_finite_and_unit(variant, seed, q, axis, spin, h, k, thrust):
    state = np.concatenate([[0.3, -0.2, 1.0], q, [0.5, 0.1, 2.0], (spin / h) * axis])
    out, residual = run(learned_terms(variant, seed % 1000), state, np.full(4, thrust), h, k)
    assert np.all(np.isfinite(out)) and np.isfinite(residual) and residual >= 0.0
    assert abs(np.linalg.norm(out[3:7]) - 1.0) < 1e-13


@settings(max_examples=S.budget(30))
@given(variant=st.sampled_from(sorted(CONFIGS)), seed=S.SEEDS, q=S.unit_quaternions(), direction=S.unit_vectors(),
       distance=S.log_uniform(1.0, 1e6), omega=S.vectors(3, -10.0, 10.0), thrust=S.floats(0.0, 4.0))
@S.counted
def test_far_translations_saturate_the_networks_without_harm(variant, seed, q, direction, distance, omega, thrust):
    """At ``|x|`` up to 1e6 the tanh units of ``U(x, q)`` saturate; the step stays finite and unit, and the
    displacement over one step stays what the velocity and forces give (no loss of ``x``'s digits
    beyond a few ulp)."""
    terms = learned_terms(variant, seed % 1000)
    state = np.concatenate([distance * direction, q, [0.5, 0.1, 2.0], omega])
    out, residual = run(terms, state, np.full(4, thrust), 0.02, 4)
    assert np.all(np.isfinite(out)) and np.isfinite(residual)
    assert abs(np.linalg.norm(out[3:7]) - 1.0) < 1e-13
    assert np.all(np.abs(out[:3] - state[:3]) < 1.0)  # 20 ms at a few m/s: no runaway


@settings(max_examples=S.budget(30))
@given(variant=st.sampled_from(["fixed-inertia", "sign-invariant"]), seed=S.SEEDS, q=S.unit_quaternions(),
       omega=S.vectors(3, -10.0, 10.0), thrust=S.floats(0.0, 3.0))
@S.counted
def test_a_sign_flip_gives_the_same_motion(variant, seed, q, omega, thrust):
    terms = learned_terms(variant, seed % 1000)
    state = np.concatenate([[0.1, 0.2, 0.9], q, [0.3, -0.4, 0.2], omega])
    flipped = state.copy()
    flipped[3:7] *= -1.0
    u = np.full(4, thrust) * [1.0, 1.1, 0.9, 1.05]
    a, _ = run(terms, state, u, 0.02, 4)
    b, _ = run(terms, flipped, u, 0.02, 4)
    keep = [0, 1, 2, 7, 8, 9, 10, 11, 12]
    assert np.all(np.abs(b[keep] - a[keep]) <= 1e-9 * (1.0 + np.abs(a[keep])))
    np.testing.assert_allclose(b[3:7], -a[3:7], rtol=0, atol=1e-12)


@settings(max_examples=S.budget(30))
@given(variant=st.sampled_from(sorted(CONFIGS)), seed=S.SEEDS, q=S.unit_quaternions(), omega=S.vectors(3, -10.0, 10.0),
       inertia=S.log_uniform(1e-9, 1e-3), mass=S.log_uniform(1e-9, 1e-2), thrust=S.floats(0.0, 4.0))
@S.counted
def test_near_singular_inertia_and_mass_stay_finite(variant, seed, q, omega, inertia, mass, thrust):
    """``J`` and ``M`` as small as 1e-9 (plus the Cholesky ε): the Newton solve is nearly singular and
    the translational kick huge, but the step is finite and ``|q| = 1``."""
    terms = learned_terms(variant, seed % 1000, inertia=inertia, mass=mass)
    state = np.concatenate([[0.0, 0.0, 1.0], q, [0.5, 0.1, 2.0], omega])
    out, residual = run(terms, state, np.full(4, thrust), 0.02, 6)
    assert np.all(np.isfinite(out)) and np.isfinite(residual)
    assert abs(np.linalg.norm(out[3:7]) - 1.0) < 1e-12
