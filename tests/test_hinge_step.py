"""The S³ step on a hinge (:func:`fvin_mpc.core.fvin.hinge_step`): exact against the unconstrained step
where the two must agree, on the hinge for any terms, against MuJoCo for a 3-D body on an oblique hinge,
the same on every backend, and finite past its solvability limit."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import casadi as ca
import mujoco
import numpy as np
import pytest
import torch

from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms, ModelConfig, init_weights
from fvin_mpc.core.rigid_body import PivotedRigidBody, from_mujoco

NP = get_ops("numpy")

#: A rod tilted inside its body and a bob off its axes, on a hinge whose axis is none of the body's
#: axes and is tilted from horizontal: its inertia about the pivot is far from isotropic and has
#: products of inertia across the hinge.
OBLIQUE_HINGE = """
<mujoco>
  <option timestep="0.0005" integrator="RK4" gravity="0 0 -9.81"/>
  <worldbody>
    <body name="arm" quat="0.9 0.1 0.3 0.2">
      <joint name="hinge" type="hinge" axis="0.6 0.3 0.74" damping="0"/>
      <geom type="capsule" fromto="0 0 0 0.1 0.2 -0.6" size="0.03" mass="0.7"/>
      <geom type="sphere" pos="0.15 0.25 -0.6" size="0.06" mass="1.3"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="hinge" gear="1.5" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


@dataclass
class HingedTerms:
    """Terms of ``inner`` that step on ``hinge_axis``."""

    inner: Any
    hinge_axis: tuple[float, float, float]

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def _unit(v) -> tuple[float, float, float]:
    v = np.asarray(v, dtype=float)
    return tuple(float(x) for x in v / np.linalg.norm(v))


def _on_hinge(q0: np.ndarray, q: np.ndarray, axis) -> float:
    """How far ``q`` is from ``q0 ⊗ exp(θ a)`` for every ``θ``: the relative rotation's imaginary
    part across the axis."""
    relative = np.array(s3.multiply(s3.conjugate(tuple(q0)), tuple(q)))
    imaginary = relative[1:]
    return float(np.linalg.norm(imaginary - (imaginary @ np.asarray(axis)) * np.asarray(axis)))


def _learned(axis, seed: int = 3, dissipation: bool = True) -> tuple[ModelConfig, dict[str, np.ndarray]]:
    config = ModelConfig(control_dim=1, step_size=0.02, dissipation=dissipation, hinge_axis=axis)
    weights = init_weights(config, seed)
    rng = np.random.default_rng(seed)
    # Random, large weights: an anisotropic J(q) with products across the hinge, a potential with a
    # torque across it, a gain with a component across it — what a 3-D model trained on hinge data has.
    weights = {name: value + 0.5 * rng.standard_normal(value.shape) for name, value in weights.items()}
    return config, weights


def test_hinge_axis_is_stored_unit_and_checked() -> None:
    assert ModelConfig(hinge_axis=(0.0, 2.0, 0.0)).hinge_axis == (0.0, 1.0, 0.0)
    config = ModelConfig.from_dict(ModelConfig(hinge_axis=(1.0, 1.0, 0.0)).to_dict() | {"hinge_axis": [1, 1, 0]})
    assert config.hinge_axis == pytest.approx((math.sqrt(0.5), math.sqrt(0.5), 0.0))
    for bad in [(0.0, 0.0, 0.0), (1.0, 0.0), (math.nan, 0.0, 1.0)]:
        with pytest.raises(ValueError, match="hinge_axis"):
            ModelConfig(hinge_axis=bad)


def test_on_an_isotropic_body_it_is_the_converged_unconstrained_step() -> None:
    """The package's closed form for a hinge is isotropic with forces along the axis, so the
    unconstrained step stays on the hinge: the two steps must agree (to the Newton solve's accuracy),
    and giving the closed form its hinge axis changed nothing but the solve."""
    model = mujoco.MjModel.from_xml_string(OBLIQUE_HINGE)
    body = from_mujoco(model, "arm")
    axis = _unit(model.jnt_axis[0])
    assert body.hinge_axis == pytest.approx(axis)  # the closed form of a hinge steps on it
    free, hinged = replace(body, hinge_axis=None).terms(NP), body.terms(NP)
    q0 = np.array([0.9, 0.1, 0.3, 0.2]) / np.linalg.norm([0.9, 0.1, 0.3, 0.2])
    for angle, rate, u in [(0.0, 0.0, 0.0), (2.5, 4.0, 0.3), (-1.0, -9.0, -1.0), (math.pi, 0.01, 0.0)]:
        q = s3.multiply(tuple(q0), (math.cos(angle / 2), *(math.sin(angle / 2) * a for a in axis)))
        omega = tuple(rate * a for a in axis)
        reference = fvin.fvin_step(q, omega, (u,), free, 0.02, 12, NP)
        step = fvin.fvin_step(q, omega, (u,), hinged, 0.02, 1, NP, with_residual=True)
        np.testing.assert_allclose(step.q, reference.q, atol=1e-13)
        np.testing.assert_allclose(step.omega, reference.omega, atol=1e-11)
        assert step.residual < 1e-12


def test_any_terms_stay_on_the_hinge_and_conserve_the_hinge_energy() -> None:
    """Random learned terms (anisotropic, with everything across the hinge): the state never leaves the
    hinge over 2,000 steps, and without dissipation or control the energy of the motion about the hinge
    (constant J: ½ aᵀJa θ̇² + U) stays within the step's O(h²) band, without drift."""
    axis = _unit([0.2, -0.9, 0.4])
    config, weights = _learned(axis, dissipation=False)
    config = ModelConfig(**{**config.to_dict(), "variant": "fixed-inertia"})
    weights = init_weights(config, 5)
    weights = {k: v + 0.4 * np.random.default_rng(5).standard_normal(v.shape) for k, v in weights.items()}
    terms = LearnedTerms(weights, config, NP)
    q0 = np.array([0.5, 0.5, -0.5, 0.5])
    q, omega = tuple(q0), tuple(6.0 * a for a in axis)
    inertia_along = float(np.asarray(axis) @ np.asarray(terms.inertia(q)) @ np.asarray(axis))
    energies, off = [], []
    for _ in range(2000):
        out = fvin.fvin_step(q, omega, (0.0,), terms, config.step_size, config.newton_iters, NP)
        q, omega = out.q, out.omega
        off.append(max(_on_hinge(q0, np.array(q), axis),
                       float(np.linalg.norm(np.cross(np.array(omega), np.array(axis))))))
        energies.append(0.5 * inertia_along * float(np.dot(omega, axis)) ** 2 + float(terms.potential(q)))
    assert max(off) < 1e-12
    energies = np.array(energies)
    spread = energies.max() - energies.min()
    assert spread < 0.05 * abs(energies.mean()) + 1e-6
    # No drift: the first and last quarters oscillate in the same band.
    assert abs(energies[:500].mean() - energies[-500:].mean()) < 0.2 * spread + 1e-9


def test_a_3d_body_on_an_oblique_hinge_follows_mujoco_at_second_order() -> None:
    """Only aᵀJa, the gravity torque about a and aᵀg enter: the body's true, anisotropic inertia about
    the pivot and its unprojected centre of mass give MuJoCo's hinge motion, and halving h quarters the
    error (second order)."""
    model = mujoco.MjModel.from_xml_string(OBLIQUE_HINGE)
    data = mujoco.MjData(model)
    mass = float(model.body_mass[1])
    com = np.array(model.body_ipos[1])
    rotation = np.zeros(9)
    mujoco.mju_quat2Mat(rotation, model.body_iquat[1])
    rotation = rotation.reshape(3, 3)
    parallel_axis = mass * (com @ com * np.eye(3) - np.outer(com, com))
    inertia = rotation @ np.diag(model.body_inertia[1]) @ rotation.T + parallel_axis
    assert np.linalg.eigvalsh(inertia).max() > 3.0 * np.linalg.eigvalsh(inertia).min()  # far from isotropic
    axis = _unit(model.jnt_axis[0])
    body = PivotedRigidBody(inertia=tuple(map(tuple, inertia)), center_of_mass=tuple(com),
                            mass_gravity=mass * 9.81, actuator_axes=tuple((a,) for a in axis))
    terms = HingedTerms(body.terms(NP), axis)

    duration, start_angle = 1.0, 2.0
    data.qpos[0], data.qvel[0] = start_angle, 0.0
    mujoco.mj_forward(model, data)
    q_start, omega_start = tuple(data.xquat[1]), (0.0, 0.0, 0.0)
    for _ in range(round(duration / model.opt.timestep)):
        mujoco.mj_step(model, data)
    q_true = np.array(data.xquat[1])

    errors = []
    for h in (0.02, 0.01):
        q, omega = q_start, omega_start
        for _ in range(round(duration / h)):
            out = fvin.fvin_step(q, omega, (0.0,), terms, h, 1, NP)
            q, omega = out.q, out.omega
        errors.append(float(s3.geodesic_angle(tuple(q), tuple(q_true), NP)))
    assert errors[0] < 0.05
    assert 3.0 < errors[0] / errors[1] < 5.0


def test_every_backend_gives_the_same_step_and_finite_derivatives() -> None:
    """numpy, torch (with autograd) and CasADi evaluate the one step function alike — also hanging
    exactly at rest (φ = 0) and past the solvability limit (``|φ|`` held at π/4, residual > 0)."""
    axis = _unit([0.6, 0.3, 0.74])
    config, weights = _learned(axis)
    q0 = s3.multiply((0.9, 0.1, 0.3, 0.2), (1.0, 0.0, 0.0, 0.0))
    q0 = tuple(np.array(q0) / np.linalg.norm(q0))
    cases = [(q0, 0.0, 0.0), (q0, 3.0, 0.7), (q0, 400.0, 1.0)]  # rest, a swing, past the limit
    for q, rate, u in cases:
        omega = tuple(rate * a for a in axis)
        numpy_step = fvin.fvin_step(q, omega, (u,), LearnedTerms(weights, config, NP), 0.02, 2, NP, with_residual=True)

        torch_ops = get_ops("torch")
        tq = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in q]
        tw = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in omega]
        tu = [torch.tensor(u, dtype=torch.float64, requires_grad=True)]
        tweights = {k: torch.tensor(v) for k, v in weights.items()}
        torch_step = fvin.fvin_step(tuple(tq), tuple(tw), tuple(tu), LearnedTerms(tweights, config, torch_ops),
                                    0.02, 2, torch_ops, with_residual=True)
        total = sum(torch_step.q) + sum(torch_step.omega) + torch_step.residual
        total.backward()
        assert all(torch.isfinite(t.grad).all() for t in tq + tw + tu)

        ca_ops = get_ops("casadi")
        x = ca.SX.sym("x", 8)
        ca_step = fvin.fvin_step(tuple(x[i] for i in range(4)), tuple(x[4 + i] for i in range(3)), (x[7],),
                                 LearnedTerms(weights, config, ca_ops), 0.02, 2, ca_ops, with_residual=True)
        outputs = ca.vertcat(*ca_step.q, *ca_step.omega, ca_step.residual)
        function = ca.Function("f", [x], [outputs, ca.jacobian(outputs, x)])
        value, jacobian = function(np.concatenate([q, omega, [u]]))
        expected = np.concatenate([numpy_step.q, numpy_step.omega, [numpy_step.residual]])
        np.testing.assert_allclose(np.array(value).ravel(), expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose([float(t.detach()) for t in (*torch_step.q, *torch_step.omega, torch_step.residual)],
                                   expected, rtol=1e-12, atol=1e-12)
        assert np.all(np.isfinite(np.array(jacobian)))
        if rate == 400.0:
            assert numpy_step.residual > 1.0
            assert abs(abs(_increment_angle(q, numpy_step.q)) - math.pi / 4) < 1e-12
        else:
            assert numpy_step.residual < 1e-12


def _increment_angle(q, q_next) -> float:
    relative = s3.multiply(s3.conjugate(q), q_next)
    return math.atan2(float(np.linalg.norm(relative[1:])), float(relative[0]))


def test_the_step_residual_is_zero_on_the_step_and_sees_a_state_off_the_hinge() -> None:
    axis = _unit([0.6, 0.3, 0.74])
    config, weights = _learned(axis)
    terms = LearnedTerms(weights, config, NP)
    q = tuple(np.array([0.9, 0.1, 0.3, 0.2]) / np.linalg.norm([0.9, 0.1, 0.3, 0.2]))
    omega, u = tuple(2.0 * a for a in axis), (0.4,)
    out = fvin.fvin_step(q, omega, u, terms, config.step_size, 1, NP)
    residual = fvin.step_residual(q, omega, u, out.q, out.omega, terms, config.step_size, NP)
    assert len(residual) == 6 and max(abs(r) for r in residual) < 1e-12
    across = fvin.hinge_basis(axis)[0]
    tilted = s3.multiply(out.q, (math.cos(0.01), *(math.sin(0.01) * a for a in across)))
    assert max(abs(r) for r in fvin.step_residual(q, omega, u, tilted, out.omega, terms, config.step_size, NP)) > 1e-4
    spun = tuple(w + 0.1 * a for w, a in zip(out.omega, across))
    assert max(abs(r) for r in fvin.step_residual(q, omega, u, out.q, spun, terms, config.step_size, NP)) > 1e-4


def test_hinge_basis_is_orthonormal_and_right_handed() -> None:
    for axis in [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0), _unit([0.6, 0.3, 0.74]), _unit([-1e-9, 1.0, 1e-12])]:
        first, second = fvin.hinge_basis(axis)
        frame = np.array([axis, first, second])
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(frame) == pytest.approx(1.0)
