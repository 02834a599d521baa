"""Every property of a configuration space, tested once, for every registered space and a toy one.

Each test is parametrized over :func:`fvin_mpc.core.space.spaces` (ids: the space names) plus
``R1xS3-toy`` (``tests/toy_space.py``: a bead on a rail carrying a pivoted body, registered by a
fixture and taken out again). A registered space without a :class:`Case` below fails every test
here by name: a new space brings its fixture record.

Properties: NumPy, torch and CasADi evaluate the same step, residual and energy (learned and
closed-form terms); the exported step's Jacobian agrees with finite differences; the step from
``−q`` is the step from ``q`` (sign-invariant terms; a plain learned model is shown not to be);
second order against an ODE oracle (``solve_ivp``, DOP853, 1e-12) of the closed-form body;
bounded energy without drift; finite fast spins whose residual flags the solvability limit
``h|ω| = 1`` (DESIGN.md); the chart (``local ∘ retract = id``, sign-free) and the state check;
the checkpoint round trip; the real-time MPC's unrolled linearization against finite differences.
The toy space additionally exports, rolls out and runs the real-time MPC without a package edit.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
import pytest
import strategies as S
import torch
from scipy.integrate import solve_ivp
from toy_space import TOY, Rail, RailBody, ToyConfig

from fvin_mpc.control import linearization, rti
from fvin_mpc.control import model_export as export
from fvin_mpc.control.mpc import MPC, MPCSettings, RTIOptions
from fvin_mpc.core import fvin_so3, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint, save_checkpoint
from fvin_mpc.core.goals import HOVER
from fvin_mpc.core.networks import ModelConfig
from fvin_mpc.core.networks_r3s3 import R3S3Config
from fvin_mpc.core.networks_so3 import SO3ModelConfig
from fvin_mpc.core.quadrotor import QUADROTOR, Quadrotor
from fvin_mpc.core.rigid_body import PivotedRigidBody
from fvin_mpc.core.space import (
    R3S3,
    S3,
    SO3,
    ConfigurationSpace,
    get_space,
    register,
    space_of_config,
    spaces,
    unregister,
)
from fvin_mpc.core.state import UNIT_NORM_TOLERANCE

NP, TORCH, CA = get_ops("numpy"), get_ops("torch"), get_ops("casadi")

# ----------------------------------------------------------------------------- bodies
_J = np.array([[0.9, 0.1, -0.2], [0.1, 0.6, 0.05], [-0.2, 0.05, 0.4]])
#: An asymmetric heavy top with an off-axis centre of mass, two actuators and joint damping: the
#: gyroscopic term, gravity, the gain and the damping all enter (the pendulums' J = I/3 has no ω × Jω).
TOP = PivotedRigidBody(inertia=tuple(map(tuple, _J)), center_of_mass=(0.1, -0.2, -0.5), mass_gravity=7.0,
                       actuator_axes=((1.0, 0.2), (0.3, -1.0), (0.5, 0.4)), damping=0.3)
TOP_UNDAMPED = dataclasses.replace(TOP, damping=0.0)
#: A quadrotor on a tether: ``U(x, q)`` couples position and orientation (conservative without thrust).
TETHERED = Quadrotor(mass=QUADROTOR.mass, inertia=QUADROTOR.inertia, rotor_sites=QUADROTOR.rotor_sites,
                     rotor_spins=QUADROTOR.rotor_spins, yaw_coefficient=QUADROTOR.yaw_coefficient,
                     tether_stiffness=6.0, tether_site=(0.05, -0.03, 0.04), tether_anchor=(0.2, -0.1, 0.6))
RAIL = Rail(mass=0.8, stiffness=3.0)
TOY_BODY = RailBody(RAIL, TOP)
TOY_CONSERVATIVE = RailBody(RAIL, TOP_UNDAMPED)


class SO3Body:
    """A pivoted body's SO(3) terms (physical torques: half the S³ gains)."""

    def __init__(self, body: PivotedRigidBody) -> None:
        self.body, self.control_dim = body, body.control_dim

    def terms(self, ops):
        return fvin_so3.PivotedRigidBodySO3Terms(self.body, ops)


# ----------------------------------------------------------------------------- ODE oracles (independent of the package)
def _rotation_rhs(
    body: PivotedRigidBody, q: np.ndarray, omega: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``q̇ = ½ q ⊗ (0, ω)``, ``J ω̇ = Jω × ω + τ_gravity + B u − d ω``."""
    inertia = np.array(body.inertia)
    torque = np.cross(inertia @ omega, omega) + S.physical_torque(body, q / np.linalg.norm(q), omega, u)
    return 0.5 * S.quat_multiply(q, np.concatenate([[0.0], omega])), np.linalg.solve(inertia, torque)


def pivoted_ode(body: PivotedRigidBody) -> Callable[[np.ndarray], Callable]:
    def with_control(u):
        def rhs(_, y):
            return np.concatenate(_rotation_rhs(body, y[:4], y[4:], u))
        return rhs
    return with_control


def quadrotor_ode(body: Quadrotor) -> Callable[[np.ndarray], Callable]:
    """Newton–Euler of an untethered quadrotor: ``ẋ = v``, ``m v̇ = R e_z Σu − m g e_z``, Euler's equation."""
    inertia, torque_map = np.array(body.inertia), np.array(body.torque_map)

    def with_control(u):
        def rhs(_, y):
            q, v, omega = y[3:7], y[7:10], y[10:]
            rot = S.rotation_matrix(q / np.linalg.norm(q))
            force = rot[:, 2] * np.sum(u) - body.mass * body.gravity * np.array([0.0, 0.0, 1.0])
            omega_dot = np.linalg.solve(inertia, torque_map @ u - np.cross(omega, inertia @ omega))
            return np.concatenate([v, 0.5 * S.quat_multiply(q, np.concatenate([[0.0], omega])), force / body.mass,
                                   omega_dot])
        return rhs
    return with_control


def toy_ode(rail_body: RailBody) -> Callable[[np.ndarray], Callable]:
    """``m s̈ = u₀ − k s − m g`` beside the pivoted body's equations under ``u₁…``."""
    rail = rail_body.rail

    def with_control(u):
        def rhs(_, y):
            q_dot, omega_dot = _rotation_rhs(rail_body.body, y[1:5], y[6:9], u[1:])
            s_ddot = (u[0] - rail.stiffness * y[0]) / rail.mass - rail.gravity
            return np.concatenate([[y[5]], q_dot, [s_ddot], omega_dot])
        return rhs
    return with_control


# ----------------------------------------------------------------------------- fixture records
@dataclass(frozen=True)
class Case:
    """What the tests need of one space.

    Attributes:
        space: the space.
        body: a closed-form body (``terms(ops)``), forced and damped where the space has damping.
        conservative: the same without damping (energy test; run unforced).
        ode: ``ode(u)`` → ``rhs(t, y)`` of ``body`` on the space's state (the convergence oracle).
        inertia: ``body``'s ``J`` (fast spins are about its principal axes).
        config: a small learned config whose terms are sign-invariant.
        plain_config: a learned config whose terms are not (the sign test's negative control), or ``None``.
        h: step size of the properties; ``duration``: of the convergence test.
        u_center, u_spread: controls are drawn uniform in ``u_center ± u_spread``.
        omega_scale, position_scale, velocity_scale: of the sampled states.
        init_scales: the space's ``init_weights`` scales.
    """

    space: ConfigurationSpace
    body: Any
    conservative: Any
    ode: Callable[[np.ndarray], Callable]
    inertia: np.ndarray
    config: Any
    plain_config: Any
    h: float
    duration: float
    u_center: np.ndarray
    u_spread: float
    omega_scale: float = 2.0
    position_scale: float = 0.5
    velocity_scale: float = 1.0
    init_scales: dict = field(default_factory=dict)

    def states(self, n: int, seed: int) -> np.ndarray:
        """``(n, state_dim)``: uniform unit quaternions, Gaussian positions and rates."""
        layout, rng = self.space.layout, np.random.default_rng(seed)
        x = np.empty((n, layout.state_dim))
        x[:, layout.positions] = self.position_scale * rng.normal(size=(n, layout.positions.stop))
        q = rng.normal(size=(n, 4))
        x[:, layout.attitude("test").quaternion] = q / np.linalg.norm(q, axis=1, keepdims=True)
        x[:, layout.rates] = self.velocity_scale * rng.normal(size=(n, layout.state_dim - layout.rates.start))
        x[:, layout.attitude("test").omega] = self.omega_scale * rng.normal(size=(n, 3))
        return x

    def controls(self, n: int, seed: int) -> np.ndarray:
        rng = np.random.default_rng(seed + 1000)
        return self.u_center + self.u_spread * rng.uniform(-1.0, 1.0, size=(n, len(self.u_center)))

    def weights(self, config: Any = None, seed: int = 3) -> dict[str, np.ndarray]:
        """The space's initialization with every network weight and bias perturbed: at initialization
        the hidden biases are 0 and tanh is odd, so a sign-averaged network is constant (``g ≡ 0``,
        ``∇U ≡ 0``) and a test on fresh weights would not see the gain or the potential."""
        config = self.config if config is None else config
        weights = self.space.init_weights(config, seed, **self.init_scales)
        rng = np.random.default_rng(seed + 100)
        for name, value in weights.items():
            if re.search(r"_[wb]\d+$", name):
                spread = 0.1 * np.max(np.abs(value)) if np.any(value) else 0.3
                weights[name] = value + spread * rng.normal(size=value.shape)
        return weights

    def learned(self, ops, config: Any = None, seed: int = 3) -> Any:
        config = self.config if config is None else config
        weights = self.weights(config, seed)
        if ops is TORCH:
            weights = {name: torch.as_tensor(value) for name, value in weights.items()}
        return self.space.learned_terms(weights, config, ops)

    @property
    def options(self) -> dict[str, Any]:
        return self.space.step_options(self.config)


CASES = {
    "S3": Case(S3, TOP, TOP_UNDAMPED, pivoted_ode(TOP), _J,
               ModelConfig(variant="sign-invariant", control_dim=2, hidden_width=6, hidden_layers=1, dissipation=True),
               ModelConfig(variant="plain", control_dim=2, hidden_width=6, hidden_layers=1),
               h=0.05, duration=1.0, u_center=np.zeros(2), u_spread=1.0),
    "SO3": Case(SO3, SO3Body(TOP), SO3Body(TOP_UNDAMPED), pivoted_ode(TOP), _J,
                SO3ModelConfig(variant="so3-matrix", control_dim=2, hidden_width=6, hidden_layers=1), None,
                h=0.05, duration=1.0, u_center=np.zeros(2), u_spread=1.0),
    "R3xS3": Case(R3S3, QUADROTOR, TETHERED, quadrotor_ode(QUADROTOR), np.array(QUADROTOR.inertia),
                  R3S3Config(variant="sign-invariant", hidden_width=6, hidden_layers=1, position_in_forces=True),
                  R3S3Config(variant="plain", hidden_width=6, hidden_layers=1),
                  h=0.02, duration=0.5, u_center=np.full(4, QUADROTOR.hover_thrust), u_spread=0.3,
                  omega_scale=3.0, init_scales={"inertia": 0.01}),
    TOY.name: Case(TOY, TOY_BODY, TOY_CONSERVATIVE, toy_ode(TOY_BODY), _J, ToyConfig(), None,
                   h=0.05, duration=1.0, u_center=np.array([RAIL.mass * RAIL.gravity, 0.0, 0.0]), u_spread=1.0),
}
# The toy's closed form has two torques (TOP) and a rail force; its learned config one torque.
CASES[TOY.name] = dataclasses.replace(CASES[TOY.name], config=ToyConfig(control_dim=3),
                                     plain_config=ToyConfig(variant="plain", control_dim=3))

SPACE_NAMES = [space.name for space in spaces()] + [TOY.name]


@pytest.fixture
def toy():
    """The toy space, registered for one test and taken out again (per test, not per module: under
    xdist another module's tests may run in between and must not see it)."""
    before = spaces()
    register(TOY)
    yield TOY
    unregister(TOY.name)
    assert spaces() == before


@pytest.fixture(params=SPACE_NAMES, ids=SPACE_NAMES)
def case(request) -> Case:
    name = request.param
    if name == TOY.name:
        request.getfixturevalue("toy")
    if name not in CASES:
        pytest.fail(f"registered space {name!r} has no fixture record (Case) in tests/test_spaces.py")
    case = CASES[name]
    assert get_space(name) is case.space
    return case


# ----------------------------------------------------------------------------- helpers
def numpy_step(case: Case, terms: Any, x: np.ndarray, u: np.ndarray, k: int = 3, h: float | None = None):
    return case.space.step(x, u, terms, case.h if h is None else h, k, NP, **case.options)


def same_state(case: Case, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Max-norm difference per state (rows), the quaternion compared up to sign."""
    qs = case.space.layout.attitude("test").quaternion
    dq = np.minimum(np.max(np.abs(a[..., qs] - b[..., qs]), -1), np.max(np.abs(a[..., qs] + b[..., qs]), -1))
    rest = np.delete(np.arange(a.shape[-1]), np.arange(qs.start, qs.stop))
    return np.maximum(dq, np.max(np.abs(a[..., rest] - b[..., rest]), -1))


def evaluate(function: ca.Function, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A CasADi step mapped over rows: ``(x_next (n, nx), residual (n,))``."""
    x_next, residual = function.map(len(x))(x.T, u.T)
    return np.asarray(x_next).T, np.asarray(residual).ravel()


# ----------------------------------------------------------------------------- backends
@pytest.mark.parametrize("terms_kind", ["learned", "closed-form"])
def test_numpy_torch_and_casadi_agree(case, terms_kind):
    """The same step, residual and energy on all three backends, to rounding."""
    make = case.learned if terms_kind == "learned" else case.body.terms
    x, u = case.states(12, seed=1), case.controls(12, seed=1)
    x_np, r_np = numpy_step(case, make(NP), x, u)
    x_t, r_t = case.space.step(torch.as_tensor(x), torch.as_tensor(u), make(TORCH), case.h, 3, TORCH, **case.options)
    casadi_terms = make(CA)
    x_ca, r_ca = evaluate(export.step_function(casadi_terms, case.h, 3, space=case.space, **case.options), x, u)
    assert x_np.shape == x.shape and np.all(np.isfinite(x_np))
    assert np.max(np.abs(x_np - x)) > 1e-3  # it moved: the comparison below is not of three copies of x
    np.testing.assert_allclose(x_t.numpy(), x_np, rtol=0, atol=1e-12)
    np.testing.assert_allclose(x_ca, x_np, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r_t.numpy(), r_np, rtol=0, atol=1e-9)
    np.testing.assert_allclose(r_ca, r_np, rtol=0, atol=1e-9)
    assert np.max(r_np) < 1e-3  # K = 3 at moderate rates: converged
    e_np = case.space.energy(x, make(NP), NP)
    e_t = case.space.energy(torch.as_tensor(x), make(TORCH), TORCH).numpy()
    energy = export.energy_function(casadi_terms, space=case.space)
    e_ca = np.asarray(energy.map(len(x))(x.T)).ravel()
    assert e_np.shape == (len(x),) and np.ptp(e_np) > 1e-6
    np.testing.assert_allclose(e_t, e_np, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(e_ca, e_np, rtol=1e-13, atol=1e-12)


@pytest.mark.parametrize("terms_kind", ["learned", "closed-form"])
def test_exported_jacobian_matches_finite_differences(case, terms_kind):
    make = case.learned if terms_kind == "learned" else case.body.terms
    step = export.step_function(make(CA), case.h, 3, space=case.space, **case.options)
    n, m = case.space.state_dim, len(case.u_center)
    x_sym, u_sym = ca.SX.sym("x", n), ca.SX.sym("u", m)
    xu = ca.vertcat(x_sym, u_sym)
    jacobian = ca.Function("J", [x_sym, u_sym], [ca.jacobian(step(x_sym, u_sym)[0], xu)])
    terms = make(NP)
    eps = 1e-6
    for x, u in zip(case.states(3, seed=4), case.controls(3, seed=4)):
        point = np.concatenate([x, u])
        numeric = np.empty((n, n + m))
        for j in range(n + m):
            d = np.zeros(n + m)
            d[j] = eps
            plus = numpy_step(case, terms, (point + d)[:n], (point + d)[n:])[0]
            minus = numpy_step(case, terms, (point - d)[:n], (point - d)[n:])[0]
            numeric[:, j] = (plus - minus) / (2 * eps)
        exact = np.asarray(jacobian(x, u))
        assert np.max(np.abs(exact[:, n:])) > 1e-4  # the controls act
        np.testing.assert_allclose(exact, numeric, rtol=1e-6, atol=1e-6 * np.max(np.abs(exact)))


# ----------------------------------------------------------------------------- sign invariance
def test_the_step_from_minus_q_is_the_same_rotation(case):
    """Sign-invariant terms (closed form; the learned sign-invariant variant; SO(3) by construction):
    ``q_{k+1}(−q) = −q_{k+1}(q)`` and the same rates and residual. A plain learned model differs."""
    qs = case.space.layout.attitude("test").quaternion
    x, u = case.states(16, seed=5), case.controls(16, seed=5)
    flipped = x.copy()
    flipped[:, qs] *= -1.0
    for terms in (case.body.terms(NP), case.learned(NP)):
        plus, r_plus = numpy_step(case, terms, x, u)
        minus, r_minus = numpy_step(case, terms, flipped, u)
        np.testing.assert_allclose(minus[:, qs], -plus[:, qs], rtol=0, atol=1e-12)
        rest = np.delete(np.arange(x.shape[1]), np.arange(qs.start, qs.stop))
        np.testing.assert_allclose(minus[:, rest], plus[:, rest], rtol=0, atol=1e-11)
        np.testing.assert_allclose(r_minus, r_plus, rtol=0, atol=1e-9)
        np.testing.assert_allclose(case.space.energy(flipped, terms, NP), case.space.energy(x, terms, NP),
                                   rtol=1e-13, atol=1e-13)
    if case.plain_config is not None:
        plain = case.learned(NP, case.plain_config)
        options = case.space.step_options(case.plain_config)
        plus = case.space.step(x, u, plain, case.h, 3, NP, **options)[0]
        minus = case.space.step(flipped, u, plain, case.h, 3, NP, **options)[0]
        assert np.max(same_state(case, plus, minus)) > 1e-6


# ----------------------------------------------------------------------------- convergence
def test_second_order_against_an_ode_oracle(case):
    """The error at ``duration`` against DOP853 (rtol = atol = 1e-12) falls ≈ 4× per halving of h:
    observed order in [1.7, 2.5] for both halvings; orientations compared up to sign."""
    x0, u = case.states(3, seed=6), case.controls(3, seed=6)
    x0[:, case.space.layout.attitude("test").omega] *= 0.75
    terms = case.body.terms(NP)
    truth = np.array([solve_ivp(case.ode(ui), (0.0, case.duration), xi, method="DOP853", rtol=1e-12,
                                atol=1e-12).y[:, -1] for xi, ui in zip(x0, u)])
    quaternion = case.space.layout.attitude("test").quaternion
    truth[:, quaternion] /= np.linalg.norm(truth[:, quaternion], axis=1, keepdims=True)
    errors = []
    for halvings in range(3):
        h = case.h / 2**halvings
        x = x0
        for _ in range(round(case.duration / h)):
            x = numpy_step(case, terms, x, u, k=6, h=h)[0]
        errors.append(np.max(same_state(case, x, truth)))
    errors = np.array(errors)
    orders = np.log2(errors[:-1] / errors[1:])
    assert errors[0] < 0.5, errors  # the oracle and the step describe the same body
    assert np.all((orders > 1.7) & (orders < 2.5)), (orders, errors)


# ----------------------------------------------------------------------------- energy
def test_energy_bounded_without_drift(case):
    """Unforced, undamped closed form, 400 steps: the energy oscillates within 3 % of its start
    (relative to the batch's largest energy) and does not grow: the last 100 steps stray no further
    than twice the first 100's."""
    terms = case.conservative.terms(NP)
    x = case.states(6, seed=7)
    u = np.zeros((6, len(case.u_center)))
    e0 = case.space.energy(x, terms, NP)
    energies = [e0]
    for _ in range(400):
        x = numpy_step(case, terms, x, u, k=4)[0]
        energies.append(case.space.energy(x, terms, NP))
    energies = np.array(energies)
    assert np.all(np.isfinite(energies))
    relative = np.abs(energies - e0) / np.max(np.abs(e0))  # one scale for the batch (an energy may be ≈ 0)
    assert np.max(relative) < 0.03, np.max(relative, axis=0)
    assert np.max(relative) > 1e-6  # the energy is computed from the moving state: not trivially constant
    assert np.max(relative[-100:]) < 2.0 * np.max(relative[:100]) + 1e-12  # no secular growth
    norms = np.linalg.norm(x[:, case.space.layout.attitude("test").quaternion], axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-12)


# ----------------------------------------------------------------------------- fast spins
@pytest.mark.parametrize("terms_kind", ["closed-form", "learned"])
def test_fast_spins_are_finite_and_their_residual_flags_the_limit(case, terms_kind):
    """Spins about each principal axis of ``J`` (closed form; learned: the coordinate axes, ``J``
    near isotropic), at rest otherwise: ``h|ω|`` below the solvability limit 1 (DESIGN.md) gives a
    converged step (K = 8: residual < 1e-6 rad/s), past it (1.5 … 300) a residual of at least 5 % of
    ``|ω|`` — and every output finite, ``|q| = 1``."""
    if terms_kind == "closed-form":
        terms = case.body.terms(NP)
        axes = np.linalg.eigh(case.inertia)[1].T
    else:
        terms = case.learned(NP)
        axes = np.eye(3)
    rates = np.array([0.3, 0.7, 1.5, 3.0, 30.0, 300.0])
    layout = case.space.layout
    x = np.repeat(case.states(1, seed=8), len(axes) * len(rates), axis=0)
    x[:, layout.rates] = 0.0
    x[:, layout.attitude("test").omega] = (rates[None, :, None] * axes[:, None, :]).reshape(-1, 3) / case.h
    u = np.repeat(case.u_center[None, :], len(x), axis=0)
    x_next, residual = numpy_step(case, terms, x, u, k=8)
    assert np.all(np.isfinite(x_next)) and np.all(np.isfinite(residual))
    residual = residual.reshape(len(axes), len(rates))
    speeds = np.linalg.norm(x[:, layout.attitude("test").omega], axis=1).reshape(len(axes), len(rates))
    below, past = residual[:, rates < 1.0], residual[:, rates > 1.0] / speeds[:, rates > 1.0]
    assert np.max(below) < 1e-6, residual
    assert np.min(past) > 0.05, residual / speeds  # at least 5 % of |ω| unexplained
    norms = np.linalg.norm(x_next[:, layout.attitude("test").quaternion], axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-9)


# ----------------------------------------------------------------------------- chart and check
def test_the_torch_model_of_each_space_steps_and_rolls_out_as_the_space(case):
    """``model_for(config)`` is the space's step in torch: its ``step_state`` equals NumPy's, and its
    rollout (the fast one of S³ and SO(3), which carry terms or ``R`` from step to step) equals the
    shell's generic rollout through ``space.step``."""
    from fvin_mpc.learning.model import FVINModel, model_for

    weights = case.weights()
    model = model_for(case.config, weights)
    assert model.space is case.space
    x, u = case.states(6, seed=4), case.controls(6, seed=4)
    expected, residual = case.space.step(x, u, case.learned(NP), case.config.step_size, case.config.newton_iters, NP,
                                         **case.options)
    with torch.no_grad():
        x_next, model_residual = model.step_state(torch.as_tensor(x), torch.as_tensor(u))
        controls = torch.as_tensor(np.stack([u, u[::-1], u], axis=1))
        fast = model.rollout(*model.pack(torch.as_tensor(x)), controls)
        generic = FVINModel.rollout(model, *model.pack(torch.as_tensor(x)), controls)
    np.testing.assert_allclose(x_next.numpy(), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(model_residual.numpy(), residual, rtol=0, atol=1e-9)
    assert same_state(case, model.unpack(*fast).numpy(), model.unpack(*generic).numpy()).max() < 1e-12
    assert np.max(np.abs(fast[1][:, -1].numpy() - fast[1][:, 0].numpy())) > 1e-3  # the rates moved


def test_local_inverts_retract_and_ignores_the_sign(case):
    layout, space = case.space.layout, case.space
    rng = np.random.default_rng(9)
    x_bar = case.states(20, seed=9)
    delta = rng.normal(size=(20, layout.tangent_dim))
    delta[:, layout.attitude("test").chart] *= 0.7
    x = space.retract(x_bar, delta)
    assert x.shape == x_bar.shape
    np.testing.assert_allclose(np.linalg.norm(x[:, layout.attitude("test").quaternion], axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(space.local(x_bar, x), delta, rtol=0, atol=1e-12)
    y = case.states(20, seed=10)
    qs = layout.attitude("test").quaternion
    y[:, qs] *= np.sign(np.sum(y[:, qs] * x_bar[:, qs], 1))[:, None]
    back = space.retract(x_bar, space.local(x_bar, y))
    assert np.max(same_state(case, back, y)) < 1e-12
    flipped, bar_flipped = y.copy(), x_bar.copy()
    flipped[:, layout.attitude("test").quaternion] *= -1.0
    bar_flipped[:, layout.attitude("test").quaternion] *= -1.0
    np.testing.assert_allclose(space.local(x_bar, flipped), space.local(x_bar, y), rtol=0, atol=1e-12)
    np.testing.assert_allclose(space.local(bar_flipped, y), space.local(x_bar, y), rtol=0, atol=1e-12)
    # only the chart's entries see the quaternion; the rest is plain subtraction
    chart = layout.attitude("test").chart
    rest = np.delete(np.arange(layout.tangent_dim), np.arange(chart.start, chart.stop))
    states = np.delete(np.arange(layout.state_dim), np.arange(qs.start, qs.stop))
    np.testing.assert_allclose(space.local(x_bar, y)[:, rest], (y - x_bar)[:, states], atol=1e-15)
    # the same chart on CasADi (what the real-time MPC builds from) and on torch
    for i in range(3):
        np.testing.assert_allclose(np.asarray(layout.retract(ca.DM(x_bar[i]), ca.DM(delta[i]), CA)).ravel(),
                                   x[i], atol=1e-14)
        np.testing.assert_allclose(np.asarray(layout.local(ca.DM(x_bar[i]), ca.DM(y[i]), CA)).ravel(),
                                   space.local(x_bar[i], y[i]), atol=1e-12)
    torch_ops = TORCH
    np.testing.assert_allclose(layout.retract(torch.as_tensor(x_bar), torch.as_tensor(delta), torch_ops).numpy(), x,
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(layout.local(torch.as_tensor(x_bar), torch.as_tensor(y), torch_ops).numpy(),
                               space.local(x_bar, y), rtol=0, atol=1e-12)


def test_distance_to_a_goal_is_sign_invariant_and_sin_squared_of_half_the_angle(case):
    """``distance`` is the attitude's ``1 − ⟨q, q_goal⟩² = sin²(angle/2)`` plus the squared offset of every
    Euclidean position (rates do not count): zero on the goal's configuration for either sign of either
    quaternion."""
    x = case.states(8, seed=9)
    layout = case.space.layout
    qs = layout.attitude("test").quaternion
    goal = x[0].copy()
    goal[layout.rates] += 1.0
    angle = s3.geodesic_angles(x[:, qs], goal[qs])
    positions = np.delete(np.arange(layout.positions.stop), np.arange(qs.start, qs.stop))
    offset = np.sum((x[:, positions] - goal[positions]) ** 2, axis=1)
    np.testing.assert_allclose(case.space.distance(x, goal), np.sin(angle / 2) ** 2 + offset, atol=1e-12)
    other_sign = goal.copy()
    other_sign[qs] *= -1
    np.testing.assert_allclose(case.space.distance(x, other_sign), case.space.distance(x, goal), atol=1e-15)
    flipped = x.copy()
    flipped[:, qs] *= -1
    np.testing.assert_allclose(case.space.distance(flipped, goal), case.space.distance(x, goal), atol=1e-15)
    assert case.space.distance(x[0], goal) == pytest.approx(0.0, abs=1e-15)
    assert np.all(case.space.distance(x[1:], goal) > 0)


def test_check_normalizes_within_tolerance_and_rejects_the_rest(case):
    layout = case.space.layout
    x = case.states(1, seed=11)[0]
    slightly = x.copy()
    slightly[layout.attitude("test").quaternion] *= 1.0 + 0.5 * UNIT_NORM_TOLERANCE
    checked = case.space.check(slightly)
    assert checked.dtype == np.float64 and checked is not slightly
    np.testing.assert_allclose(np.linalg.norm(checked[layout.attitude("test").quaternion]), 1.0, atol=1e-15)
    qs = layout.attitude("test").quaternion
    others = np.delete(np.arange(layout.state_dim), np.arange(qs.start, qs.stop))
    np.testing.assert_allclose(checked[others], x[others], atol=0)
    np.testing.assert_array_equal(slightly[qs], x[qs] * (1.0 + 0.5 * UNIT_NORM_TOLERANCE))
    for bad_norm in (1.0 + 3.0 * UNIT_NORM_TOLERANCE, 1.0 - 3.0 * UNIT_NORM_TOLERANCE, 0.0):
        wrong = x.copy()
        wrong[layout.attitude("test").quaternion] *= bad_norm
        with pytest.raises(ValueError, match="unit quaternion"):
            case.space.check(wrong)
    for shape in ((layout.state_dim - 1,), (layout.state_dim + 1,), (1, layout.state_dim), ()):
        with pytest.raises(ValueError, match="shape"):
            case.space.check(np.ones(shape))
    nan = x.copy()
    nan[-1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        case.space.check(nan)


# ----------------------------------------------------------------------------- checkpoints
def test_checkpoint_round_trip_exports_the_same_model(case, tmp_path):
    config, weights = case.config, case.weights()
    stem = save_checkpoint(tmp_path / f"model-{case.space.name}", config, weights, scene="synthetic")
    checkpoint = load_checkpoint(stem)
    assert checkpoint.space is case.space and checkpoint.config == config
    assert space_of_config(checkpoint.config) is case.space
    loaded = export.from_checkpoint(checkpoint)
    direct = export.from_terms(case.space, case.learned(CA), case.learned(NP), config.step_size, config.newton_iters,
                               "direct", **case.space.step_options(config))
    assert loaded.space is case.space and loaded.state_dim == case.space.state_dim
    x, u = case.states(6, seed=12), case.controls(6, seed=12)
    np.testing.assert_array_equal(evaluate(loaded.step, x, u)[0], evaluate(direct.step, x, u)[0])
    for xi in x:
        assert loaded.energy(xi) == direct.energy(xi)
    other = export.from_terms(case.space, case.learned(CA, seed=4), case.learned(NP, seed=4), config.step_size,
                              config.newton_iters, "other", **case.space.step_options(config))
    assert np.max(np.abs(evaluate(other.step, x, u)[0] - evaluate(loaded.step, x, u)[0])) > 1e-8


# ----------------------------------------------------------------------------- the real-time MPC's linearization
def test_unrolled_stage_linearization_matches_finite_differences(case):
    """``linearization.unrolled_stage_function``: ``c = 0`` at consistent nodes (``x̄_{k+1} = F(x̄_k, ū)``) and
    ``[A B]`` equal to central differences of ``local(x̄_{k+1}, F(retract(x̄_k, δ), ū + Δu))``."""
    model = export.from_closed_form(case.space, case.body, case.h, 3, **case.options)
    layout, m = case.space.layout, model.control_dim
    stage = linearization.unrolled_stage_function(model.step, layout, m)
    eps = 1e-6
    for x_bar, u_bar in zip(case.states(2, seed=13), case.controls(2, seed=13)):
        x_next = model(x_bar, u_bar)[0]
        c, ab = (np.asarray(v) for v in stage(x_bar, u_bar, x_next, np.zeros(m)))
        np.testing.assert_allclose(c.ravel(), 0.0, atol=1e-12)
        shifted = x_next.copy()
        shifted[layout.attitude("test").quaternion] *= -1.0  # the same node with the other sign: still no gap
        np.testing.assert_allclose(np.asarray(stage(x_bar, u_bar, shifted, np.zeros(m))[0]).ravel(), 0.0, atol=1e-12)
        disturbance = np.full(m, 0.1)
        c_d = np.asarray(stage(x_bar, u_bar, x_next, disturbance)[0]).ravel()
        np.testing.assert_allclose(c_d, layout.local(x_next, model(x_bar, u_bar + disturbance)[0]), atol=1e-12)
        nd = layout.tangent_dim
        numeric = np.empty((nd, nd + m))
        for j in range(nd + m):
            d = np.zeros(nd + m)
            d[j] = eps
            ends = [
                layout.local(x_next, model(layout.retract(x_bar, s * d[:nd]), u_bar + s * d[nd:])[0]) for s in (1, -1)
            ]
            numeric[:, j] = (ends[0] - ends[1]) / (2 * eps)
        np.testing.assert_allclose(ab, numeric, rtol=1e-6, atol=1e-6 * np.max(np.abs(ab)))


# ----------------------------------------------------------------------------- the toy space, end to end
def test_toy_registers_once_and_is_found_by_name_and_config(toy):
    assert toy in spaces() and get_space("R1xS3-toy") is toy and space_of_config(ToyConfig()) is toy
    with pytest.raises(ValueError, match="registered"):
        register(toy)
    with pytest.raises(ValueError, match="not a model config"):
        toy.learned_terms(toy.init_weights(ToyConfig(), 0), ModelConfig(), NP)
    with pytest.raises(NotImplementedError):
        toy.closed_form(None, "bead")
    assert toy.state_dim == 9 and toy.layout.tangent_dim == 8


def test_toy_exports_rolls_out_and_its_rail_is_velocity_verlet(toy):
    """``export.from_terms`` on the toy's closed form: a rollout matches the NumPy step; with no
    spring the rail is exact under constant gravity and force (Velocity-Verlet), and the rotation
    is the S³ model's own step on the same body."""
    model = export.from_terms(toy, TOY_BODY.terms(CA), TOY_BODY.terms(NP), 0.05, 3, "toy")
    assert model.space is toy and model.state_dim == 9 and model.control_dim == 3
    x0 = CASES[toy.name].states(1, seed=14)[0]
    controls = CASES[toy.name].controls(20, seed=14)
    states = model.rollout(x0, controls)
    assert states.shape == (21, 9)
    x = x0
    for k, u in enumerate(controls):
        x = toy.step(x, u, TOY_BODY.terms(NP), 0.05, 3, NP)[0]
        np.testing.assert_allclose(states[k + 1], x, rtol=0, atol=1e-12)
    free = RailBody(Rail(mass=0.8, stiffness=0.0), TOP)
    free_model = export.from_terms(toy, free.terms(CA), free.terms(NP), 0.05, 3, "toy-free")
    u = np.array([2.0, 0.3, -0.2])
    states = free_model.rollout(x0, np.tile(u, (30, 1)))
    t, a = 0.05 * 30, u[0] / 0.8 - 9.81
    np.testing.assert_allclose(states[-1, 0], x0[0] + x0[5] * t + 0.5 * a * t * t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(states[-1, 5], x0[5] + a * t, rtol=0, atol=1e-12)
    s3_model = export.from_rigid_body(TOP, 0.05, 3)
    pivoted = s3_model.rollout(np.concatenate([x0[1:5], x0[6:9]]), np.tile(u[1:], (30, 1)))
    np.testing.assert_allclose(states[:, [1, 2, 3, 4, 6, 7, 8]], pivoted, rtol=0, atol=1e-12)
    assert model.energy(x0) == pytest.approx(float(toy.energy(x0, TOY_BODY.terms(NP), NP)), abs=0)


def test_toy_real_time_mpc_returns_bounded_controls_and_lifts_the_bead(toy):
    """The real-time MPC on the toy (not pivoted: the goal is a whole state), built without compiling
    C (``compile="none"``): its holding control is the rail's ``k s_goal + m g``; every call gives a
    finite control within the bounds; 40 calls on the model bring the bead to the goal height. IPOPT
    solves the same problem (its first push too is harder than holding); the implicit dynamics
    (spaces with ``step_residual``) refuse the toy instead of running it as something else."""
    model = export.from_terms(toy, TOY_BODY.terms(CA), TOY_BODY.terms(NP), 0.05, 3, "toy")
    settings = MPCSettings(solver="rti", horizon=10, compile="none", cold_starts=("goal",), position_weight=2.0,
                           velocity_weight=0.2, terminal_position_weight=20.0, terminal_velocity_weight=2.0,
                           orientation_residual="rotation-vector", rti=RTIOptions(cold_budget_s=60.0, cold_iter=3))
    low, high = np.array([0.0, -2.0, -2.0]), np.array([20.0, 2.0, 2.0])
    goal = np.array([0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    controller = rti.RealTimeMPC(model, settings, goal, low, high, goal_set=HOVER)
    assert controller.target_control[0] == pytest.approx(RAIL.stiffness * 0.5 + RAIL.mass * RAIL.gravity, rel=1e-9)
    x = np.array([0.0, np.cos(0.2), np.sin(0.2), 0.0, 0.0, 0.0, 0.5, 0.0, 0.0])
    for k in range(40):
        u, info = controller(x)
        assert u.shape == (3,) and np.all(np.isfinite(u)) and np.all(u >= low) and np.all(u <= high), (k, u)
        assert info["success"] and info["states"].shape == (11, 9) and np.all(np.isfinite(info["states"]))
        if k == 0:  # below the goal and pulled down: the first push is harder than holding there
            assert u[0] > controller.target_control[0] + 1.0
        x = model(x, u)[0]
        controller.prepare()
    assert abs(x[0] - 0.5) < 0.02 and abs(x[5]) < 0.05, x
    # The same problem solved by IPOPT to convergence: the toy is no special case for it either.
    ipopt = MPC(model, dataclasses.replace(settings, solver="ipopt"), goal, low, high, goal_set=HOVER)
    start = np.array([0.0, np.cos(0.2), np.sin(0.2), 0.0, 0.0, 0.0, 0.5, 0.0, 0.0])
    u, info = ipopt(start)
    assert info["success"] and np.all(u >= low) and np.all(u <= high) and u[0] > ipopt.target_control[0] + 1.0
    with pytest.raises(ValueError, match="step's own equations"):  # the toy has no step_residual
        rti.RealTimeMPC(model, settings.updated(rti={"dynamics": "implicit"}), goal, low, high, goal_set=HOVER)
