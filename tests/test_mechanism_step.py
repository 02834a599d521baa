"""The mechanism's forced variational step (:mod:`fvin_mpc.core.mechanism_step`) against independent references.

* MuJoCo's RK4 at a small timestep on the same MJCF: the step converges at second order in ``h`` on a cart-pole,
  a double pendulum, a rotary pendulum and a ball-jointed arm of the seeded family, damped and forced;
* the energy: unforced and undamped it stays bounded where explicit Euler's grows;
* identities: the converged step is time-reversible; ``D₁L_d`` (the backend's exact derivative) equals finite
  differences of ``L_d``; the Newton residual falls with ``K``;
* today's S³ step: a single ball joint steps to the same trajectory (1e-12); a hinge as an angle does not (the
  plain difference of angles, not the S³ hinge's ``sin Δθ``) and is the more accurate and solvable form here;
* hard cases: hanging at rest stays at rest, a folded chain, a fast spin, ``±q``;
* torch's autograd form equals CasADi's to round-off; bad inputs are refused in one line.
"""

from __future__ import annotations

import casadi as ca
import mujoco
import numpy as np
import pytest
import torch

from benchmarks.mechanism_step_check import (
    compile_step,
    explicit_euler_energy,
    member_model,
    mujoco_reference,
    random_start,
    state_error,
)
from fvin_mpc.core import fvin, rigid_body
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.blocks import Block, Hinge, StateLayout
from fvin_mpc.core.errors import UsageError
from fvin_mpc.core.mechanism_step import (
    ClosedFormMechanism,
    advance,
    discrete_lagrangian,
    lagrangian_slopes,
    mechanism_energy,
    mechanism_step,
)
from fvin_mpc.envs.joint_blocks import joint_layout

NP, CA, TORCH = get_ops("numpy"), get_ops("casadi"), get_ops("torch")
torch.set_num_threads(1)


def closed_form(model: mujoco.MjModel, damped: bool = True) -> tuple[StateLayout, ClosedFormMechanism]:
    return joint_layout(model), ClosedFormMechanism.from_mujoco(model, damped)


def single_body(joint: str, damping: float) -> mujoco.MjModel:
    """One body on a hinge (about y) or a ball at the world's origin: a full inertia off the axis, armature,
    damping and motors (three on the ball)."""
    gears = ["1.5 0 0", "0 2 0", "0 0 0.7"] if joint == "ball" else ["2"]
    axis = 'axis="0 1 0"' if joint == "hinge" else ""
    motors = "".join(f'<motor joint="j" gear="{gear}"/>' for gear in gears)
    return mujoco.MjModel.from_xml_string(f"""
<mujoco><option gravity="0 0 -9.81"><flag contact="disable"/></option>
  <worldbody><body name="body"><joint name="j" type="{joint}" {axis} damping="{damping}" armature="0.01"/>
    <inertial pos="0.05 0.02 -0.4" mass="1.3" fullinertia="0.05 0.04 0.03 0.003 -0.002 0.001"/></body></worldbody>
  <actuator>{motors}</actuator></mujoco>""")


#: Two capsules hanging straight down on hinges, and a ball-jointed link below: at qpos0 every centre of mass
#: lies exactly below its joint, so rest is an equilibrium in exact arithmetic.
HANGING = """
<mujoco><option gravity="0 0 -9.81"><flag contact="disable"/></option>
  <worldbody>
    <body name="upper"><joint name="shoulder" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03" mass="1"/>
      <body name="lower" pos="0 0 -0.5"><joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.03" mass="0.7"/>
        <body name="hand" pos="0 0 -0.4"><joint name="wrist" type="ball"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.2" size="0.02" mass="0.3"/></body></body></body>
  </worldbody>
  <actuator><motor joint="shoulder" gear="1"/></actuator></mujoco>"""


# ----------------------------------------------------------------------------- against MuJoCo
@pytest.mark.parametrize("kind", ["cart_pole", "double_pendulum", "furuta", "ball_arm"])
def test_second_order_against_mujoco_rk4(kind):
    """Final-state error after 0.25 s against MuJoCo's RK4 at 1e-4 s (its error ~1e-13 here), damped, under a
    constant control: log–log slope 2 ± 0.1 over h = 12.5 … 1.5625 ms, the converged step (K = 4)."""
    model = member_model(kind, 0)
    x0, control = random_start(model, np.random.default_rng([7, 0]))
    layout, terms = closed_form(model)
    duration = 0.25
    reference = mujoco_reference(model, x0, control, duration, timestep=1e-4)
    sizes = [0.0125 / 2 ** i for i in range(4)]
    errors = []
    for h in sizes:
        states, residuals = compile_step(terms, layout, h, 4).rollout(x0, np.tile(control, (round(duration / h), 1)))
        assert residuals.max() < 1e-9
        errors.append(state_error(layout, states[-1], reference))
    slope = np.polyfit(np.log(sizes), np.log(errors), 1)[0]
    assert abs(slope - 2.0) < 0.1, (errors, slope)


def test_energy_stays_bounded_where_explicit_euler_grows():
    """Unforced, undamped, a chaotic double pendulum for 20 s at 5 ms: the step's energy error stays under 2 % of
    the energy's scale and does not drift (the last quarter's largest no more than 1.3 × the first quarter's);
    explicit Euler's grows past ten times that within 400 steps."""
    model = member_model("double_pendulum", 0)
    x0, _ = random_start(model, np.random.default_rng([7, 1]))
    layout, terms = closed_form(model, damped=False)
    states, _ = compile_step(terms, layout, 0.005, 3).rollout(x0, np.zeros((4000, model.nu)))
    energy = np.asarray(mechanism_energy(states, terms, layout, NP))
    scale = energy[0] - np.min(np.asarray(terms.potential(NP.unstack(states[:, layout.positions]), NP)))
    error = np.abs(energy - energy[0]) / scale
    assert error.max() < 2e-2
    assert error[3000:].max() <= 1.3 * error[:1000].max()
    euler = explicit_euler_energy(model, x0, 0.005, 400)
    assert np.abs(euler[-1] - euler[0]) / scale > 10.0 * error.max()


# ----------------------------------------------------------------------------- identities
def test_converged_step_is_time_reversible():
    """The discrete Lagrangian is symmetric in its ends: stepping from ``(q₁, −ν₁)`` returns to ``(q₀, −ν₀)``."""
    model = member_model("ball_arm", 1)
    x0, _ = random_start(model, np.random.default_rng([7, 2]))
    layout, terms = closed_form(model, damped=False)
    step = compile_step(terms, layout, 0.02, 8)
    x1, _ = step.step(x0, np.zeros(model.nu))
    back, _ = step.step(np.concatenate([x1[layout.positions], -x1[layout.rates]]), np.zeros(model.nu))
    assert state_error(layout, np.concatenate([back[layout.positions], -back[layout.rates]]), x0) < 1e-11


def test_lagrangian_slopes_are_the_derivatives_of_the_lagrangian():
    """``D₁L_d`` and ``D₂L_d`` (CasADi's exact derivative, evaluated) against central differences of ``L_d``
    (NumPy) along ``q ⊞ ε`` at either end, on a ball-and-hinge arm."""
    model = member_model("ball_arm", 0)
    layout, terms = closed_form(model)
    x0, _ = random_start(model, np.random.default_rng([7, 3]))
    q0 = x0[layout.positions]
    q1 = np.asarray(advance(layout, NP.unstack(q0), NP.unstack(0.02 * np.arange(1.0, model.nv + 1)), NP))
    h = 0.02
    symbols = ca.SX.sym("q0", model.nq), ca.SX.sym("q1", model.nq)
    for at_end in (False, True):
        slopes = lagrangian_slopes(terms, layout, CA.unstack(symbols[0]), CA.unstack(symbols[1]), h, CA, at_end)
        exact = np.asarray(ca.Function("slopes", list(symbols), [ca.vertcat(*slopes)])(q0, q1)).ravel()
        finite = np.zeros(model.nv)
        for i in range(model.nv):
            values = []
            for sign in (1.0, -1.0):
                epsilon = NP.unstack(sign * 1e-6 * np.eye(model.nv)[i])
                ends = (q0, np.asarray(advance(layout, NP.unstack(q1), epsilon, NP))) if at_end else \
                    (np.asarray(advance(layout, NP.unstack(q0), epsilon, NP)), q1)
                values.append(discrete_lagrangian(terms, layout, *ends, h, NP))
            finite[i] = (values[0] - values[1]) / 2e-6
        assert np.allclose(exact, finite, rtol=1e-6, atol=1e-8), (at_end, exact, finite)


def test_newton_residual_falls_with_iterations_and_says_when_it_does_not_converge():
    """On a double pendulum at h|ν| = 0.1 the residual falls quadratically (K = 1, 2, 3, 6; ratio r₂/r₁ < 1) to
    round-off; at h|ν| = 3 the step still returns finite numbers and K = 2's residual says they are wrong."""
    model = member_model("double_pendulum", 0)
    layout, terms = closed_form(model, damped=False)
    h = 0.02
    steps = {k: compile_step(terms, layout, h, k) for k in (1, 2, 3, 6)}
    direction = np.array([1.0, -1.0])
    moderate = np.concatenate([model.qpos0 + [0.0, 1.0], (0.1 / h) * direction])
    residual = {k: step.step(moderate, np.zeros(model.nu))[1] for k, step in steps.items()}
    assert residual[1] > residual[2] > residual[3] > residual[6] and residual[6] < 1e-12
    assert residual[2] / residual[1] < 1e-2 and residual[3] < 10.0 * residual[2] ** 2 / residual[1] + 1e-14
    fast = np.concatenate([model.qpos0 + [0.0, 1.0], (3.0 / h) * direction])
    x_next, fast_residual = steps[2].step(fast, np.zeros(model.nu))
    assert np.all(np.isfinite(x_next)) and fast_residual > 1.0


# ----------------------------------------------------------------------------- today's single-body steps
@pytest.mark.parametrize("damping", [0.0, 0.3])
def test_a_ball_joint_steps_as_the_s3_step(damping):
    """One body on a ball joint (full inertia, armature, damping, three motors): the mechanism step and the S³
    step (:func:`fvin_mpc.core.fvin.fvin_step`, closed-form body) give the same 100-step trajectory to 1e-12, at
    the same K (the Newton iterates coincide: ``ξ = h w/2``)."""
    model = single_body("ball", damping)
    layout, terms = closed_form(model)
    s3_terms = rigid_body.from_mujoco(model, "body").terms(NP)
    rng = np.random.default_rng([7, 4])
    quaternion = rng.normal(size=4)
    x0 = np.concatenate([quaternion / np.linalg.norm(quaternion), rng.normal(size=3)])
    control = rng.uniform(-0.5, 0.5, size=model.nu)
    for k in (2, 4):
        states, _ = compile_step(terms, layout, 0.02, k).rollout(x0, np.tile(control, (100, 1)))
        q, omega = tuple(x0[:4]), tuple(x0[4:])
        for x in states[1:]:
            result = fvin.fvin_step(q, omega, tuple(control), s3_terms, 0.02, k, NP)
            q, omega = tuple(float(c) for c in result.q), tuple(float(c) for c in result.omega)
            assert np.abs(np.concatenate([q, omega]) - x).max() < 1e-12


def test_a_hinge_angle_is_the_more_accurate_and_solvable_form_than_the_s3_hinge():
    """One body on a hinge: as an angle the step's kinetic term is the plain difference (Störmer–Verlet for a
    constant ``M``), not the S³ hinge step's ``sin Δθ`` — a different discretization, both second order. Against
    MuJoCo's RK4 its error is half the S³ hinge's here, and at h|θ̇| = 1.2 it is solved exactly where the S³
    hinge's equation has no solution (its residual says so)."""
    model = single_body("hinge", 0.0)
    layout, terms = closed_form(model)
    s3_terms = rigid_body.from_mujoco(model, "body").terms(NP)
    x0, control, duration, h = np.array([0.7, 1.5]), np.array([0.3]), 1.0, 0.02
    reference = mujoco_reference(model, x0, control, duration, timestep=1e-4)
    states, _ = compile_step(terms, layout, h, 5).rollout(x0, np.tile(control, (50, 1)))
    q, omega = (np.cos(0.35), 0.0, np.sin(0.35), 0.0), (0.0, 1.5, 0.0)  # the same state on S³ (about y)
    for _ in range(50):
        result = fvin.fvin_step(q, omega, tuple(control), s3_terms, h, 5, NP)
        q, omega = tuple(float(c) for c in result.q), tuple(float(c) for c in result.omega)
    s3_error = max(abs(2.0 * np.arctan2(q[2], q[0]) - reference[0]), abs(omega[1] - reference[1]))
    block_error = np.abs(states[-1] - reference).max()
    assert 1e-5 < block_error < 0.7 * s3_error
    fast = 1.2 / h
    _, block_residual = compile_step(terms, layout, h, 5).step(np.array([0.0, fast]), np.zeros(1))
    s3 = fvin.fvin_step((1.0, 0.0, 0.0, 0.0), (0.0, fast, 0.0), (0.0,), s3_terms, h, 5, NP, with_residual=True)
    assert block_residual < 1e-12 and float(s3.residual) > 1.0


# ----------------------------------------------------------------------------- hard cases
def test_hanging_at_rest_stays_at_rest():
    """Straight down, at rest, unforced: 500 steps later every entry is still 0 (the ball's quaternion 1) to
    round-off."""
    model = mujoco.MjModel.from_xml_string(HANGING)
    layout, terms = closed_form(model)
    x0 = np.concatenate([model.qpos0, np.zeros(model.nv)])
    states, residuals = compile_step(terms, layout, 0.01, 2).rollout(x0, np.zeros((500, model.nu)))
    assert np.abs(states - x0).max() < 1e-14 and residuals.max() < 1e-14


def test_folded_chain_converges_and_keeps_its_energy():
    """A double pendulum folded to 0.1 rad from its links' overlap (``cond M`` in the hundreds where the links
    are alike, here measured) swinging: K = 4 converges every step to 1e-8 and the energy
    stays within 2 % of its scale."""
    model = member_model("double_pendulum", 1)
    layout, terms = closed_form(model, damped=False)
    qpos = model.qpos0 + [0.3, np.pi - 0.1]
    mass = terms.tree.numpy_terms(qpos, np.zeros(model.nv))["mass"]
    assert np.linalg.cond(mass) > 3.0  # ill conditioned compared with the straight chain's
    x0 = np.concatenate([qpos, [2.0, -1.0]])
    states, residuals = compile_step(terms, layout, 0.01, 4).rollout(x0, np.zeros((1000, model.nu)))
    energy = np.asarray(mechanism_energy(states, terms, layout, NP))
    scale = energy[0] - np.min(np.asarray(terms.potential(NP.unstack(states[:, layout.positions]), NP)))
    assert residuals.max() < 1e-8 and np.abs(energy - energy[0]).max() < 2e-2 * scale


def test_fast_spin_of_a_ball_joint():
    """The two-ball arm's shoulder spinning at 60 rad/s (h|ω| = 0.6 at 10 ms) about an axis the links' inertia
    couples to: K = 2's residual says the step is unconverged (the first iterate, from ``M(q_k)``, misses the
    Coriolis terms) and K = 8 converges the step to 1e-10 with unit quaternions. (Rolled out, K = 8 fails to
    converge within a few steps from here: a known limit, see docs/mechanisms.md.)"""
    model = member_model("ball_arm", 1)
    layout, terms = closed_form(model, damped=False)
    x0 = np.concatenate([model.qpos0, [0.0, 0.0, 60.0], np.zeros(model.nv - 3)])
    assert compile_step(terms, layout, 0.01, 2).step(x0, np.zeros(model.nu))[1] > 1.0
    x1, residual = compile_step(terms, layout, 0.01, 8).step(x0, np.zeros(model.nu))
    assert residual < 1e-10
    for quaternion in layout.quaternions:
        assert abs(np.linalg.norm(x1[quaternion]) - 1.0) < 1e-13


def test_a_quaternion_and_its_negative_step_alike():
    """``q`` and ``−q`` (every ball of a two-ball arm) give the same next configuration up to sign, the same rates."""
    model = member_model("ball_arm", 1)
    layout, terms = closed_form(model)
    x0, control = random_start(model, np.random.default_rng([7, 5]))
    flipped = x0.copy()
    for quaternion in layout.quaternions:
        flipped[quaternion] *= -1.0
    step = compile_step(terms, layout, 0.02, 3)
    (x1, r1), (y1, r2) = step.step(x0, control), step.step(flipped, control)
    for quaternion in layout.quaternions:
        y1[quaternion] *= -1.0
    assert np.abs(x1 - y1).max() < 1e-13 and abs(r1 - r2) < 1e-13


# ----------------------------------------------------------------------------- backends and inputs
def test_torch_step_equals_casadi_and_is_differentiable():
    """torch (autograd for ``D₁``, ``D₂`` and the Newton Jacobian) on a batch of three states equals the CasADi
    ``Function`` to 1e-12, and its gradient with respect to the start state is finite."""
    model = member_model("ball_arm", 0)
    layout, terms = closed_form(model)
    rng = np.random.default_rng([7, 6])
    starts = [random_start(model, rng) for _ in range(3)]
    x = torch.tensor(np.array([s[0] for s in starts]), dtype=torch.float64, requires_grad=True)
    u = torch.tensor(np.array([s[1] for s in starts]), dtype=torch.float64)
    result = mechanism_step(x, u, terms, layout, 0.02, 3, TORCH)
    step = compile_step(terms, layout, 0.02, 3)
    for i, (x0, control) in enumerate(starts):
        expected, residual = step.step(x0, control)
        assert np.abs(result.x[i].detach().numpy() - expected).max() < 1e-12
        assert abs(float(result.residual[i].detach()) - residual) < 1e-12
    (gradient,) = torch.autograd.grad(result.x.sum(), x)
    assert torch.isfinite(gradient).all() and gradient.abs().max() > 0.1


class Wheel(Block):
    """A block kind the step has no chart for."""

    kind = "wheel"
    position_size = 1
    tangent_size = 1
    chart_units = ("angle",)
    angular_rates = (True,)
    chart_scales = (1.0,)


def test_bad_inputs_are_refused_in_one_line():
    model = member_model("furuta", 0)
    layout, terms = closed_form(model)
    x, u = ca.SX.sym("x", layout.state_dim), ca.SX.sym("u", terms.control_dim)
    cases = [
        (lambda: mechanism_step(x, u, terms, layout, 0.01, 0, CA), "newton_iters"),
        (lambda: mechanism_step(x, u, terms, layout, -0.01, 2, CA), "step_size"),
        (lambda: mechanism_step(ca.SX.sym("y", 3), u, terms, layout, 0.01, 2, CA), "state has 3"),
        (lambda: mechanism_step(x, ca.SX.sym("v", 4), terms, layout, 0.01, 2, CA), "control has 4"),
        (lambda: mechanism_step(x, u, terms, StateLayout((Hinge(), Hinge(), Hinge()), "three"), 0.01, 2, CA),
         "state has"),
        (lambda: mechanism_step(x, u, terms, StateLayout((Wheel(), Hinge()), "wheel"), 0.01, 2, CA), "no chart"),
    ]
    for call, words in cases:
        with pytest.raises(UsageError, match=words) as caught:
            call()
        assert "\n" not in str(caught.value)
