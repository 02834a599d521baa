"""The real-time iteration's QP beside the QP solvers a user would pick, on the same QPs recorded from closed loops:
``python -m benchmarks.qp_peers record``, then ``python -m benchmarks.qp_peers solve`` (docs/peers.md).

**Recording.** Per scene one closed-loop episode of the learned real-time MPC (the scene's settings, the wall-clock
budgets lifted so that every run records the same QPs; waiting mode). Before each warm call the previous call's
plan (``info["states"]``, ``info["controls"]``) is shifted by one step as the preparation shifts it (the last node
the model's step from the last one under the last control plus ``d̂``, its rates clipped to the ``ω`` bound) and the
controller's own ``rti_linearize_blocks`` is evaluated at it through CasADi: the stage Hessians ``H_k`` (in
``(δ_k, Δu_k)``), gradients ``g_k``, ``[A_k B_k]``, gaps ``c_k``, the terminal ``H_N``, ``g_N``; ``δ_0`` is fixed by the
measured state in the first node's chart; the boxes are the control bounds minus the plan's controls. The QPs go to
``<cache>/<scene>_qps.npz`` (not in git). The fourth scene, ``two_tops``, is the S³ × S³ toy of ``tests/two_tops.py``
(two tops joined by a spring, closed form, the model its own plant): a product of blocks standing in for a
mechanism until the mechanism models reach the controllers.

**Solving.** Each QP is solved by

* ``riccati``: the controller's compiled ``rti_feedback`` at its default ``qp_iterations`` — a fixed count of
  interior-point iterations, each a Riccati recursion; it also applies the trust region to the states, not to the
  controls, so its ``Δu`` is ``U_new − Ū``. Timed as the bare compiled call (CasADi's buffer interface: no
  conversions) and through ``Function.__call__`` (the interface);
* ``hpipm``: CasADi's ``hpipm`` conic interface on the stage-wise QP (options ``N``, ``nx``, ``nu``, ``ng``; mode
  ``speed``): through Python (its own ``t_wall_solver`` is the solve, the rest interface) and, where CasADi's C code
  of it compiles against the HPIPM and BLASFEO it ships, as a bare compiled call (``hpipm-c``);
* ``daqp`` (dual active set) and ``proxqp`` (proxsuite's dense ProxQP, box constraints) on the condensed QP (the
  states eliminated: ``N·m`` variables, boxes only; the condensing is timed apart), and ``osqp`` (ADMM, polished) on
  the full-space sparse QP, cold every time; each reports its own solve time.

Accuracy against a converged reference (HPIPM in ``robust`` mode at tolerances of 1e-12, checked against daqp's
active-set solution): the largest ``|Δu − Δu*|`` over the horizon as a fraction of the torque range, the first
control's, and the natural residual of the condensed QP, ``‖Δu − Π_box(Δu − ∇f(Δu))‖_∞`` (zero exactly at the
solution; no multipliers needed). Times: every solver on every QP, ``--repeats`` times in turn (median per QP), then
median and p90 over the QPs — ratios within one run; the machine is shared, so absolute times are noisy.
``python -m benchmarks.qp_peers instructions`` counts instructions per QP under callgrind (repeatable on a loaded
machine).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import casadi as ca
import numpy as np

from fvin_mpc._cli import run_command
from fvin_mpc.control import model_export
from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.flight import quadrotor_model, quadrotor_mpc, quadrotor_mpc_settings, recovery_starts
from fvin_mpc.control.model_export import compile_functions
from fvin_mpc.control.mpc import MPCSettings, RTIOptions
from fvin_mpc.control.problem import control_bounds
from fvin_mpc.control.rti import RealTimeMPC
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc, scene_mpc_settings
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.errors import UsageError
from fvin_mpc.core.goals import GoalSet
from fvin_mpc.core.rigid_body import PivotedRigidBody
from fvin_mpc.core.space import register, spaces
from fvin_mpc.envs import QuadrotorEnv
from fvin_mpc.envs.scenes import resolve_scene

SCENES = ("pendulum", "spherical_pendulum", "quadrotor", "two_tops")
#: Seconds of closed loop recorded per scene (the two tops: periods of their own loop).
DURATION_S = {"pendulum": 6.0, "spherical_pendulum": 6.0, "quadrotor": 3.0, "two_tops": 3.0}
SOLVERS = ("riccati", "hpipm", "hpipm-c", "daqp", "proxqp", "osqp")
DEFAULT_CACHE = Path("data/peers")
#: The converged reference's HPIPM options: robust mode, tolerances far below any solver's compared here.
REFERENCE_HPIPM = {"mode": "robust", "iter_max": 300, "res_g_max": 1e-12, "res_b_max": 1e-12, "res_d_max": 1e-12,
                   "res_m_max": 1e-12, "warm_start": 0}
#: The peer rows' HPIPM options: its ``speed`` mode and default tolerances, no warm start (as the Riccati QP).
PEER_HPIPM = {"mode": "speed", "iter_max": 50, "warm_start": 0}
#: OSQP's settings: tolerances a user would set for MPC, polished (its active-set refinement), cold every time.
OSQP_SETTINGS = {"eps_abs": 1e-6, "eps_rel": 1e-6, "max_iter": 20000, "polishing": True, "warm_starting": False,
                 "verbose": False}
RECORD_FIELDS = ("X", "U", "x0", "H", "HN", "g", "gN", "AB", "c", "delta0", "low", "high")


# ----------------------------------------------------------------------------- the recorded QPs
@dataclass(frozen=True)
class StageQP:
    """One QP of the real-time iteration, stage-wise: ``min Σ_k ½[δ_k;Δu_k]ᵀH_k[δ_k;Δu_k] + g_kᵀ[δ_k;Δu_k] +
    ½δ_NᵀH_Nδ_N + g_Nᵀδ_N`` s.t. ``δ_{k+1} = A_kδ_k + B_kΔu_k + c_k``, ``δ_0`` given, ``low_k ≤ Δu_k ≤ high_k``.

    Attributes (``s = n_δ + m``): ``H (s, sN)``, ``HN (n_δ, n_δ)``, ``g (s, N)``, ``gN (n_δ,)``, ``AB (n_δ, sN)``,
    ``c (n_δ, N)``, ``delta0 (n_δ,)``, ``low``, ``high`` ``(m, N)`` — the boxes on ``Δu``.
    """

    H: np.ndarray
    HN: np.ndarray
    g: np.ndarray
    gN: np.ndarray
    AB: np.ndarray
    c: np.ndarray
    delta0: np.ndarray
    low: np.ndarray
    high: np.ndarray

    @property
    def dims(self) -> tuple[int, int, int]:
        """``(N, n_δ, m)``."""
        nd, n = self.c.shape
        return n, nd, self.low.shape[0]


def condensed(qp: StageQP) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The QP in the controls alone, the states eliminated by the dynamics: ``min ½vᵀH_cv + f_cᵀv`` over
    ``v = (Δu_0, …, Δu_{N−1})`` (stage-major) within the boxes, and the affine map to the states,
    ``δ_k = M[k]v + w[k]``. Returns ``(H_c, f_c, M (N+1, n_δ, Nm), w (N+1, n_δ))``."""
    n, nd, m = qp.dims
    s = nd + m
    M, w = np.zeros((n + 1, nd, n * m)), np.zeros((n + 1, nd))
    w[0] = qp.delta0
    hessian, gradient = np.zeros((n * m, n * m)), np.zeros(n * m)
    for k in range(n):
        a, b = qp.AB[:, k * s:k * s + nd], qp.AB[:, k * s + nd:(k + 1) * s]
        lift = np.zeros((s, n * m))  # [δ_k; Δu_k] = lift v + offset
        lift[:nd], lift[nd:, k * m:(k + 1) * m] = M[k], np.eye(m)
        offset = np.concatenate([w[k], np.zeros(m)])
        block = qp.H[:, k * s:(k + 1) * s]
        hessian += lift.T @ block @ lift
        gradient += lift.T @ (block @ offset + qp.g[:, k])
        M[k + 1] = a @ M[k]
        M[k + 1][:, k * m:(k + 1) * m] += b
        w[k + 1] = a @ w[k] + qp.c[:, k]
    hessian += M[n].T @ qp.HN @ M[n]
    gradient += M[n].T @ (qp.HN @ w[n] + qp.gN)
    return 0.5 * (hessian + hessian.T), gradient, M, w


def natural_residual(hessian: np.ndarray, gradient: np.ndarray, low: np.ndarray, high: np.ndarray,
                     v: np.ndarray) -> float:
    """``‖v − Π_[low,high](v − (H v + f))‖_∞`` of the box-constrained QP ``min ½vᵀHv + fᵀv``: zero exactly at its
    solution (the KKT conditions with the multipliers eliminated)."""
    return float(np.max(np.abs(v - np.clip(v - (hessian @ v + gradient), low, high))))


def stage_major(array: np.ndarray) -> np.ndarray:
    """``(m, N)`` per-stage values as the condensed QP's vector ``(Δu_0, …, Δu_{N−1})``."""
    return np.asarray(array, dtype=float).T.ravel()


@dataclass(frozen=True)
class FullSpaceLayout:
    """The full-space QP of a :class:`StageQP` in HPIPM's stage order ``z = (Δu_0, δ_1, Δu_1, …, δ_N)``: the
    fixed sparsity of its Hessian (dense stage blocks) and of its equality matrix (rows ``B_0Δu_0 − δ_1``,
    ``A_kδ_k + B_kΔu_k − δ_{k+1}``), whatever the values — one pattern for every QP of a scene."""

    n: int
    nd: int
    m: int

    @property
    def size(self) -> int:
        return self.n * (self.nd + self.m)

    def control(self, k: int) -> slice:
        start = k * (self.nd + self.m)
        return slice(start, start + self.m)

    def state(self, k: int) -> slice:
        """``δ_k``, ``k ≥ 1``."""
        start = (k - 1) * (self.nd + self.m) + self.m
        return slice(start, start + self.nd)

    def matrices(self, qp: StageQP) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(P, q, A, b, (lower, upper))`` dense: ``min ½zᵀPz + qᵀz`` s.t. ``Az = b``, ``lower ≤ z ≤ upper``."""
        n, nd, s = self.n, self.nd, self.nd + self.m
        hessian, gradient = np.zeros((self.size, self.size)), np.zeros(self.size)
        equality, rhs = np.zeros((n * nd, self.size)), np.zeros(n * nd)
        lower, upper = np.full(self.size, -np.inf), np.full(self.size, np.inf)
        for k in range(n):
            block, u = qp.H[:, k * s:(k + 1) * s], self.control(k)
            a, b = qp.AB[:, k * s:k * s + nd], qp.AB[:, k * s + nd:(k + 1) * s]
            rows = slice(k * nd, (k + 1) * nd)
            hessian[u, u] = block[nd:, nd:]
            gradient[u] = qp.g[nd:, k]
            if k == 0:
                gradient[u] += block[nd:, :nd] @ qp.delta0
                rhs[rows] = -qp.c[:, 0] - a @ qp.delta0
            else:
                x = self.state(k)
                hessian[x, x], hessian[u, x], hessian[x, u] = block[:nd, :nd], block[nd:, :nd], block[:nd, nd:]
                gradient[x] = qp.g[:nd, k]
                equality[rows, x] = a
                rhs[rows] = -qp.c[:, k]
            equality[rows, u] = b
            equality[rows, self.state(k + 1)] = -np.eye(nd)
            lower[u], upper[u] = qp.low[:, k], qp.high[:, k]
        hessian[self.state(n), self.state(n)] = qp.HN
        gradient[self.state(n)] += qp.gN
        return hessian, gradient, equality, rhs, (lower, upper)

    def hessian_pattern(self) -> np.ndarray:
        pattern = np.zeros((self.size, self.size), dtype=bool)
        pattern[self.control(0), self.control(0)] = True
        for k in range(1, self.n + 1):
            span = slice(self.state(k).start, self.state(k).stop + (self.m if k < self.n else 0))
            pattern[span, span] = True
        return pattern

    def equality_pattern(self) -> np.ndarray:
        n, nd = self.n, self.nd
        pattern = np.zeros((n * nd, self.size), dtype=bool)
        for k in range(n):
            rows = slice(k * nd, (k + 1) * nd)
            pattern[rows, self.control(k)] = True
            if k > 0:
                pattern[rows, self.state(k)] = True
            pattern[rows, self.state(k + 1)] = np.eye(nd, dtype=bool)
        return pattern

    def controls_of(self, z: np.ndarray) -> np.ndarray:
        """``Δu (m, N)`` of a full-space solution."""
        return np.stack([z[self.control(k)] for k in range(self.n)], axis=1)


def casadi_sparse(values: np.ndarray, pattern: np.ndarray) -> ca.DM:
    """``values`` as a CasADi matrix with the structural nonzeros ``pattern`` (zeros inside it kept)."""
    rows, cols = np.nonzero(pattern.T)  # column-major order: CasADi's nonzero order
    sparsity = ca.Sparsity.triplet(pattern.shape[0], pattern.shape[1], cols.tolist(), rows.tolist())
    triplet_rows, triplet_cols = sparsity.get_triplet()
    return ca.DM(sparsity, values[np.asarray(triplet_rows), np.asarray(triplet_cols)])


# ----------------------------------------------------------------------------- recording from closed loops
def _two_tops_module() -> Any:
    """``tests/two_tops.py`` (a test module, not package code), loaded by path."""
    path = Path(__file__).resolve().parents[1] / "tests" / "two_tops.py"
    spec = importlib.util.spec_from_file_location("two_tops", path)
    if spec is None or spec.loader is None:
        raise UsageError(f"the two-tops toy scene needs {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("two_tops", module)
    spec.loader.exec_module(module)
    return module


def two_tops_controller() -> tuple[Any, Any, np.ndarray]:
    """The real-time MPC of the two tops on their closed-form model (its own plant), the model and the start:
    both tops hanging level, the goal both turned by 0.6 rad about different axes."""

    tops = _two_tops_module()
    if tops.TWO_TOPS.name not in {space.name for space in spaces()}:
        register(tops.TWO_TOPS)
    axes = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    top_a = PivotedRigidBody(inertia=((0.9, 0.1, -0.2), (0.1, 0.6, 0.05), (-0.2, 0.05, 0.4)),
                             center_of_mass=(0.1, -0.2, -0.5), mass_gravity=3.0, actuator_axes=axes, damping=0.2)
    top_b = PivotedRigidBody(inertia=((0.5, 0.0, 0.1), (0.0, 0.7, 0.0), (0.1, 0.0, 0.6)),
                             center_of_mass=(0.0, 0.1, -0.4), mass_gravity=2.0, actuator_axes=axes, damping=0.2)
    body = tops.TwoTops(top_a, top_b, stiffness=1.5)
    model = model_export.from_terms(tops.TWO_TOPS, body.terms(get_ops("casadi")), body.terms(get_ops("numpy")), 0.05,
                                    3, "two-tops")
    settings = MPCSettings(solver="rti", horizon=20, compile="none", cold_starts=("rollout+", "rollout-"),
                           orientation_residual="rotation-vector", omega_weight=0.05, terminal_orientation_weight=20.0,
                           control_weight=0.01, rti=RTIOptions(cold_budget_s=math.inf, budget_s=math.inf))
    goal = np.r_[np.cos(0.3), np.sin(0.3), 0.0, 0.0, np.cos(0.3), 0.0, np.sin(0.3), 0.0, np.zeros(6)]
    poses = GoalSet("poses", "both tops at their attitudes, at rest", attitude_at_rest=False)
    controller = RealTimeMPC(model, settings, goal, -3.0 * np.ones(6), 3.0 * np.ones(6), goal_set=poses)
    start = np.r_[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros(6)]
    return controller, model, start


def scene_controller(scene: str, seed: int) -> tuple[Any, Any, dict[str, Any] | None, int]:
    """``(env, controller, reset options, env seed)`` of a built-in scene: its learned real-time MPC with the
    scene's settings and the wall-clock budgets lifted; the swing-ups from hanging at rest, the quadrotor from its
    first tumbling recovery start."""

    lifted = {"budget_s": math.inf, "cold_budget_s": math.inf}
    if resolve_scene(scene).goal_set.attitude_at_rest:
        env = scene_env(scene)
        controller = scene_mpc(env, scene_model(env), scene_mpc_settings(env, solver="rti").updated(rti=lifted))
        return env, controller, None, seed
    env = QuadrotorEnv(resolve_scene(scene))
    controller = quadrotor_mpc(env, quadrotor_model(env), quadrotor_mpc_settings().updated(rti=lifted))
    options, start_seed = recovery_starts(env.unwrapped.goal_state[:3], count=3, seed=seed)[1]
    return env, controller, options, start_seed


def loop_function(controller: Any, name: str) -> ca.Function:
    """One of the controller's generated loop functions by name."""
    for function in controller.loop_functions:
        if function.name() == name:
            return function
    raise UsageError(f"the controller has no loop function {name!r}; it has "
                     f"{[function.name() for function in controller.loop_functions]}")


class QPRecorder:
    """A controller that records, before each warm call, the QP that call solves (module docstring) and then
    calls the real-time MPC it wraps; everything else is the wrapped controller's."""

    def __init__(self, controller: Any) -> None:
        self.controller = controller
        self.linearize = loop_function(controller, "rti_linearize_blocks")
        self.predict = loop_function(controller, "rti_predict")
        self.records: list[dict[str, np.ndarray]] = []
        self._plan: tuple[np.ndarray, np.ndarray] | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.controller, name)

    def reset(self) -> None:
        self.controller.reset()
        self._plan = None

    def __call__(self, x: Any) -> tuple[np.ndarray, dict[str, Any]]:
        x0 = np.asarray(x, dtype=float)
        if self._plan is not None:
            self.records.append(self.qp_at(*self._plan, x0))
        u, info = self.controller(x0)
        self._plan = (np.array(info["states"], dtype=float), np.array(info["controls"], dtype=float))
        return u, info

    def shifted(self, states: np.ndarray, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plan shifted by one step as the preparation shifts it: the last node the model's step from the old
        last node under the last control plus ``d̂``, its angular rates clipped to the ``ω`` bound."""
        c = self.controller
        last = np.asarray(self.predict(states[-1], controls[-1] + c.disturbance, c.parameters)[0], dtype=float).ravel()
        rates = c.layout.angular_rates
        bound = c.settings.omega_bound_fraction / c.model.step_size
        last[rates] = np.clip(last[rates], -bound, bound)
        return np.vstack([states[1:], last]), np.vstack([controls[1:], controls[-1:]])

    def qp_at(self, states: np.ndarray, controls: np.ndarray, x0: np.ndarray) -> dict[str, np.ndarray]:
        """The QP at the previous plan shifted, ``δ_0`` from the measured ``x0``: the generated linearization's
        blocks (every stage's Jacobians computed afresh) and the boxes."""

        c = self.controller
        states, controls = self.shifted(states, controls)
        references, targets = c.reference_window()
        kept = self.linearize.sparsity_in(self.linearize.index_in("J_kept")).shape
        rows, items = self.linearize.sparsity_in(self.linearize.index_in("points_kept")).shape
        points = np.ones((rows, items))
        if (rows, items) == (states.shape[1] + controls.shape[1], controls.shape[0]):
            points = np.vstack([states[:-1].T, controls.T])
        outputs = self.linearize(states.T, controls.T, references.T, c.disturbance, targets.T, c.parameters,
                                 np.zeros(kept), points, np.ones((1, items)))
        H, HN, g, gN, AB, gaps = (np.asarray(output, dtype=float) for output in outputs[:6])
        low, high = control_bounds(c.torque_low, c.torque_high, c.horizon, c.settings.torque_reserve)
        return {"X": states.T, "U": controls.T, "x0": x0, "H": H, "HN": HN, "g": g, "gN": gN.ravel(), "AB": AB,
                "c": gaps, "delta0": np.asarray(c.layout.local(states[0], x0), dtype=float),
                "low": low.T - controls.T, "high": high.T - controls.T}


def record(scene: str, seed: int) -> tuple[Any, list[dict[str, np.ndarray]]]:
    """The scene's controller and the QPs of one closed-loop episode (:class:`QPRecorder`)."""
    if scene == "two_tops":
        controller, model, x = two_tops_controller()
        recorder = QPRecorder(controller)
        recorder.reset()
        for _ in range(int(round(DURATION_S[scene] / model.step_size))):
            u, _ = recorder(x)
            x = np.asarray(model(x, u)[0], dtype=float).ravel()
            controller.prepare()
        return controller, recorder.records

    env, controller, options, env_seed = scene_controller(scene, seed)
    recorder = QPRecorder(controller)
    try:
        run_episode(env, recorder, DURATION_S[scene], options, env_seed, latency="none")
    finally:
        env.close()
    return controller, recorder.records


def save_records(path: Path, scene: str, controller: Any, records: list[dict[str, np.ndarray]], seed: int) -> None:
    meta = {"scene": scene, "model": controller.model.name, "horizon": controller.horizon,
            "tangent_dim": controller.layout.tangent_dim, "control_dim": controller.model.control_dim,
            "torque_range": (np.asarray(controller.torque_high) - np.asarray(controller.torque_low)).tolist(),
            "qp_iterations": controller.settings.rti.qp_iterations, "seed": seed}
    arrays = {name: np.stack([r[name] for r in records]) for name in RECORD_FIELDS}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, meta=json.dumps(meta), **arrays)


def load_records(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    if not path.is_file():
        raise UsageError(f"{path} is not there: run python -m benchmarks.qp_peers record first")
    with np.load(path) as data:
        return json.loads(str(data["meta"])), {name: data[name] for name in RECORD_FIELDS}


def stage_qp(arrays: dict[str, np.ndarray], index: int) -> StageQP:
    return StageQP(**{name: arrays[name][index] for name in ("H", "HN", "g", "gN", "AB", "c", "delta0", "low",
                                                               "high")})


# ----------------------------------------------------------------------------- the solvers
@dataclass
class Solved:
    """One solve: ``du (m, N)``, wall seconds of the call from Python, the solver's own seconds where it reports
    them (else NaN), whether it says it succeeded."""

    du: np.ndarray
    wall_s: float
    own_s: float
    success: bool


def hpipm_solver(layout: FullSpaceLayout, options: dict[str, Any], name: str = "peer_hpipm") -> ca.Function:
    """CasADi's ``hpipm`` conic interface on ``layout``'s stage-wise QP."""
    h = casadi_sparse(np.ones((layout.size, layout.size)), layout.hessian_pattern()).sparsity()
    a = casadi_sparse(np.ones((layout.n * layout.nd, layout.size)), layout.equality_pattern()).sparsity()
    structure = {"N": layout.n, "nx": [0] + [layout.nd] * layout.n, "nu": [layout.m] * layout.n + [0],
                 "ng": [0] * (layout.n + 1)}
    return ca.conic(name, "hpipm", {"h": h, "a": a}, {**structure, "hpipm": dict(options), "error_on_fail": False})


def hpipm_arguments(layout: FullSpaceLayout, qp: StageQP) -> dict[str, Any]:
    P, q, A, b, (lower, upper) = layout.matrices(qp)
    return {"h": casadi_sparse(P, layout.hessian_pattern()), "g": ca.DM(q),
            "a": casadi_sparse(A, layout.equality_pattern()), "lba": ca.DM(b), "uba": ca.DM(b),
            "lbx": ca.DM(lower), "ubx": ca.DM(upper)}


def compiled_hpipm(solver: ca.Function, folder: Path) -> ca.Function | None:
    """``solver`` (an ``hpipm`` conic) as C, compiled against the HPIPM and BLASFEO CasADi ships and loaded; ``None``
    (and the compiler's message on stderr) where that does not build."""
    casadi_dir = Path(ca.__file__).parent
    folder.mkdir(parents=True, exist_ok=True)
    source, library = folder / f"{solver.name()}.c", folder / f"{solver.name()}.so"
    if not library.is_file():
        solver.generate(source.name, {"with_header": False})
        shutil.move(source.name, source)
        process = subprocess.run(["gcc", "-O2", "-fPIC", "-shared", "-march=native", str(source), "-I",
                                  str(casadi_dir / "include"), "-L", str(casadi_dir), "-lhpipm", "-lblasfeo",
                                  f"-Wl,-rpath,{casadi_dir}", "-lm", "-o", str(library)],
                                 capture_output=True, text=True)
        if process.returncode != 0:
            print(f"hpipm-c: the generated HPIPM call does not compile:\n{process.stderr[-2000:]}", file=sys.stderr)
            return None
    return ca.external(solver.name(), str(library))


class BareCall:
    """A compiled CasADi function called through its buffer interface: inputs copied into preallocated arrays, one
    C call, outputs read — the call the real-time loop makes, without ``Function.__call__``'s conversions."""

    def __init__(self, function: ca.Function) -> None:
        self.function = function
        self.buffer, self.evaluate = function.buffer()
        self.inputs = [np.zeros(function.sparsity_in(i).nnz()) for i in range(function.n_in())]
        self.outputs = [np.zeros(function.sparsity_out(i).nnz()) for i in range(function.n_out())]
        for i, array in enumerate(self.inputs):
            self.buffer.set_arg(i, memoryview(array))
        for i, array in enumerate(self.outputs):
            self.buffer.set_res(i, memoryview(array))

    def set(self, index: int, value: Any) -> None:
        """Input ``index`` from a dense array of its shape, or a CasADi matrix of its sparsity."""
        if isinstance(value, ca.DM):
            self.inputs[index][:] = np.asarray(value.nonzeros(), dtype=float)
        else:
            self.inputs[index][:] = np.asarray(value, dtype=float).ravel(order="F")

    def timed(self) -> float:
        start = time.perf_counter()
        self.evaluate()
        return time.perf_counter() - start


class PeerSolvers:
    """Every solver of the comparison, built once per scene, each ``solve(name, qp, condensed) -> Solved``."""

    def __init__(self, controller: Any, layout: FullSpaceLayout, build_folder: Path, solvers: Sequence[str]) -> None:

        self.layout, self.names = layout, tuple(solvers)
        feedback = loop_function(controller, "rti_feedback")
        prefix = re.sub(r"[^0-9A-Za-z_]", "_", f"peers_{controller.model.name}")
        compiled, _ = compile_functions([feedback], prefix=prefix, kernels=getattr(controller, "loop_kernels", ()))
        self.feedback = compiled["rti_feedback"]
        self.feedback_bare = BareCall(self.feedback)
        self.hpipm = hpipm_solver(layout, PEER_HPIPM)
        self.reference = hpipm_solver(layout, REFERENCE_HPIPM, "reference_hpipm")
        self.hpipm_c = None
        if "hpipm-c" in self.names:
            function = compiled_hpipm(self.hpipm, build_folder / f"hpipm_{layout.n}_{layout.nd}_{layout.m}")
            self.hpipm_c = None if function is None else BareCall(function)
        self._osqp = None

    def riccati(self, record: dict[str, np.ndarray], index: int) -> tuple[Solved, Solved]:
        """The compiled ``rti_feedback``, bare and through ``Function.__call__``: ``Δu = U_new − Ū``."""
        arguments = [record[name][index] for name in ("X", "U", "x0", "H", "HN", "g", "gN", "AB", "c")]
        for i, argument in enumerate(arguments):
            self.feedback_bare.set(i, argument)
        bare_s = self.feedback_bare.timed()
        n, _, m = self.layout.n, self.layout.nd, self.layout.m
        u_new = self.feedback_bare.outputs[1].reshape(n, m).T
        du = u_new - record["U"][index]
        start = time.perf_counter()
        called = self.feedback(*arguments)
        call_s = time.perf_counter() - start
        du_call = np.asarray(called[1], dtype=float) - record["U"][index]
        finite = bool(np.all(np.isfinite(du)))
        return Solved(du, bare_s, bare_s, finite), Solved(du_call, call_s, bare_s, finite)

    def conic(self, solver: ca.Function, arguments: dict[str, Any]) -> Solved:
        start = time.perf_counter()
        solution = solver(**arguments)
        wall = time.perf_counter() - start
        stats = solver.stats()
        z = np.asarray(solution["x"], dtype=float).ravel()
        return Solved(self.layout.controls_of(z), wall, float(stats.get("t_wall_solver", math.nan)),
                      bool(stats.get("success", False)))

    def hpipm_compiled(self, arguments: dict[str, Any]) -> Solved:
        assert self.hpipm_c is not None
        function = self.hpipm_c.function
        for i in range(function.n_in()):
            name = function.name_in(i)
            self.hpipm_c.set(i, arguments[name] if name in arguments else np.zeros(function.sparsity_in(i).nnz()))
        seconds = self.hpipm_c.timed()
        z = self.hpipm_c.outputs[function.index_out("x")]
        return Solved(self.layout.controls_of(z.copy()), seconds, seconds,
                      self.hpipm_c.buffer.ret() == 0 and bool(np.all(np.isfinite(z))))

    @staticmethod
    def daqp(hessian: np.ndarray, gradient: np.ndarray, low: np.ndarray, high: np.ndarray, shape: tuple[int, int]
             ) -> Solved:
        import daqp

        start = time.perf_counter()
        v, _, exitflag, info = daqp.solve(hessian, gradient, np.zeros((0, gradient.size)), high, low)
        wall = time.perf_counter() - start
        own = float(info.get("solve_time", math.nan)) + float(info.get("setup_time", 0.0))
        return Solved(np.asarray(v).reshape(shape[1], shape[0]).T, wall, own, exitflag == 1)

    @staticmethod
    def proxqp(hessian: np.ndarray, gradient: np.ndarray, low: np.ndarray, high: np.ndarray, shape: tuple[int, int]
               ) -> Solved:
        import proxsuite

        start = time.perf_counter()
        qp = proxsuite.proxqp.dense.QP(gradient.size, 0, 0, box_constraints=True)
        qp.settings.eps_abs = 1e-9
        qp.settings.eps_rel = 0.0
        qp.settings.compute_timings = True
        qp.init(hessian, gradient, None, None, None, None, None, low, high)
        qp.solve()
        wall = time.perf_counter() - start
        info = qp.results.info
        own = 1e-6 * (float(info.solve_time) + float(info.setup_time))
        success = info.status == proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
        return Solved(np.asarray(qp.results.x).reshape(shape[1], shape[0]).T, wall, own, success)

    def osqp(self, qp: StageQP) -> Solved:
        import osqp
        import scipy.sparse as sparse

        layout = self.layout
        P, q, A, b, (lower, upper) = layout.matrices(qp)
        controls = np.concatenate([np.arange(layout.control(k).start, layout.control(k).stop) for k in range(layout.n)])
        selector = np.zeros((controls.size, layout.size))
        selector[np.arange(controls.size), controls] = 1.0
        constraint = np.vstack([A, selector])
        constraint_pattern = np.vstack([layout.equality_pattern(), selector.astype(bool)])
        hessian_pattern = np.triu(layout.hessian_pattern())

        def with_pattern(values: np.ndarray, pattern: np.ndarray) -> Any:
            rows, cols = np.nonzero(pattern)
            return sparse.csc_matrix((values[rows, cols], (rows, cols)), shape=pattern.shape)

        P_sparse, A_sparse = with_pattern(P, hessian_pattern), with_pattern(constraint, constraint_pattern)
        low_all, high_all = np.concatenate([b, lower[controls]]), np.concatenate([b, upper[controls]])
        start = time.perf_counter()
        if self._osqp is None:
            self._osqp = osqp.OSQP()
            self._osqp.setup(P_sparse, q, A_sparse, low_all, high_all, **OSQP_SETTINGS)
        else:
            self._osqp.update(q=q, l=low_all, u=high_all, Px=P_sparse.data, Ax=A_sparse.data)
        result = self._osqp.solve()
        wall = time.perf_counter() - start
        info = result.info
        own = float(info.solve_time) + float(getattr(info, "update_time", 0.0) or 0.0)
        success = str(getattr(info, "status", "")).lower().startswith("solved")
        return Solved(layout.controls_of(np.asarray(result.x, dtype=float)), wall, own, success)


def solve_scene(controller: Any, meta: dict[str, Any], arrays: dict[str, np.ndarray], solvers: Sequence[str],
                repeats: int, build_folder: Path, limit: int | None = None) -> dict[str, Any]:
    """Every QP of one scene by every solver, ``repeats`` times in turn; per solver the times (median per QP, then
    median and p90 over the QPs, µs) and the accuracy against the reference (module docstring)."""
    count = arrays["H"].shape[0] if limit is None else min(limit, arrays["H"].shape[0])
    n, nd, m = meta["horizon"], meta["tangent_dim"], meta["control_dim"]
    layout = FullSpaceLayout(n, nd, m)
    peers = PeerSolvers(controller, layout, build_folder, solvers)
    rows = ["riccati", "riccati (Function call)", *[s for s in solvers if s != "riccati"]]
    if peers.hpipm_c is None and "hpipm-c" in rows:
        rows.remove("hpipm-c")
    span = np.asarray(meta["torque_range"], dtype=float)[:, None]
    results: dict[str, dict[str, list[float]]] = {r: {k: [] for k in ("wall", "own", "du", "first", "kkt", "fail")}
                                                  for r in rows}
    reference_gap, condense_s, active = [], [], []
    for index in range(count):
        qp = stage_qp(arrays, index)
        start = time.perf_counter()
        hessian, gradient, _, _ = condensed(qp)
        condense_s.append(time.perf_counter() - start)
        low, high = stage_major(qp.low), stage_major(qp.high)
        arguments = hpipm_arguments(layout, qp)
        reference = peers.conic(peers.reference, arguments)
        daqp_check = peers.daqp(hessian, gradient, low, high, (m, n))
        reference_gap.append(float(np.max(np.abs(reference.du - daqp_check.du) / span)))
        v_star = stage_major(reference.du)
        active.append(int(np.sum((v_star <= low + 1e-9) | (v_star >= high - 1e-9))))
        runs: dict[str, list[Solved]] = {r: [] for r in rows}
        for _ in range(repeats):
            for name in solvers:
                if name == "riccati":
                    bare, called = peers.riccati(arrays, index)
                    runs["riccati"].append(bare)
                    runs["riccati (Function call)"].append(called)
                elif name == "hpipm":
                    runs[name].append(peers.conic(peers.hpipm, arguments))
                elif name == "hpipm-c" and peers.hpipm_c is not None:
                    runs[name].append(peers.hpipm_compiled(arguments))
                elif name == "daqp":
                    runs[name].append(peers.daqp(hessian, gradient, low, high, (m, n)))
                elif name == "proxqp":
                    runs[name].append(peers.proxqp(hessian, gradient, low, high, (m, n)))
                elif name == "osqp":
                    runs[name].append(peers.osqp(qp))
        for name, solved in runs.items():
            if not solved:
                continue
            last = solved[-1]
            row = results[name]
            row["wall"].append(float(np.median([s.wall_s for s in solved])))
            row["own"].append(float(np.median([s.own_s for s in solved])))
            row["du"].append(float(np.max(np.abs(last.du - reference.du) / span)))
            row["first"].append(float(np.max(np.abs(last.du[:, 0] - reference.du[:, 0]) / span[:, 0])))
            row["kkt"].append(natural_residual(hessian, gradient, low, high, stage_major(last.du)))
            row["fail"].append(0.0 if last.success else 1.0)
    summary: dict[str, Any] = {}
    for name, row in results.items():
        if not row["wall"]:
            continue
        wall, own = 1e6 * np.array(row["wall"]), 1e6 * np.array(row["own"])
        summary[name] = {
            "call_us_median": float(np.median(wall)), "call_us_p90": float(np.percentile(wall, 90)),
            "own_us_median": float(np.nanmedian(own)) if np.any(np.isfinite(own)) else None,
            "own_us_p90": float(np.nanpercentile(own, 90)) if np.any(np.isfinite(own)) else None,
            "du_max": float(np.max(row["du"])), "du_median": float(np.median(row["du"])),
            "first_control_max": float(np.max(row["first"])), "kkt_median": float(np.median(row["kkt"])),
            "kkt_max": float(np.max(row["kkt"])), "failures": int(np.sum(row["fail"]))}
    base = summary["riccati"]["call_us_median"]
    for row in summary.values():
        row["call_vs_riccati"] = row["call_us_median"] / base
    return {"scene": meta["scene"], "model": meta["model"], "qps": count, "horizon": n, "tangent_dim": nd,
            "control_dim": m, "qp_iterations": meta["qp_iterations"], "repeats": repeats,
            "reference_vs_daqp_max": float(np.max(reference_gap)), "active_bounds_median": float(np.median(active)),
            "condense_us_median": 1e6 * float(np.median(condense_s)), "solvers": summary}


# ----------------------------------------------------------------------------- instruction counts
#: The function each solver's instructions are counted inside (callgrind ``--toggle-collect``).
COUNTED_FUNCTION = {"riccati": "rti_feedback", "hpipm": "d_ocp_qp_ipm_solve", "daqp": "daqp_solve*",
                    "osqp": "osqp_solve", "proxqp": "*proxqp*dense*solve*"}


def replay(controller: Any, meta: dict[str, Any], arrays: dict[str, np.ndarray], solver: str, count: int,
           build_folder: Path) -> None:
    """Solve the first ``count`` QPs with one solver, untimed: what :func:`instructions` runs under callgrind."""
    layout = FullSpaceLayout(meta["horizon"], meta["tangent_dim"], meta["control_dim"])
    peers = PeerSolvers(controller, layout, build_folder, [solver])
    m, n = meta["control_dim"], meta["horizon"]
    for index in range(count):
        qp = stage_qp(arrays, index)
        if solver == "riccati":
            peers.riccati(arrays, index)
        elif solver == "hpipm":
            peers.conic(peers.hpipm, hpipm_arguments(layout, qp))
        elif solver == "osqp":
            peers.osqp(qp)
        else:
            hessian, gradient, _, _ = condensed(qp)
            getattr(peers, solver)(hessian, gradient, stage_major(qp.low), stage_major(qp.high), (m, n))


def instructions(scene: str, solver: str, count: int, cache: Path) -> float:
    """Instructions per QP inside :data:`COUNTED_FUNCTION` of ``solver``, under callgrind, over ``count`` QPs."""
    if shutil.which("valgrind") is None:
        raise UsageError("instruction counts need valgrind (apt-get install valgrind)")
    with tempfile.TemporaryDirectory(prefix="qp_peers_callgrind_") as folder:
        out = Path(folder) / "callgrind.out"
        command = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", "--collect-atstart=no",
                   f"--toggle-collect={COUNTED_FUNCTION[solver]}", sys.executable, "-m", "benchmarks.qp_peers",
                   "replay", "--scene", scene, "--solver", solver, "--qps", str(count), "--cache", str(cache)]
        environment = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
        process = subprocess.run(command, capture_output=True, text=True, env=environment)
        if process.returncode != 0:
            raise RuntimeError(f"callgrind run failed: {process.stderr[-2000:]}")
        for line in out.read_text().splitlines():
            if line.startswith("summary:") or line.startswith("totals:"):
                return float(line.split()[1]) / count
    raise RuntimeError("callgrind wrote no totals")


# ----------------------------------------------------------------------------- commands
def controller_for(scene: str, meta: dict[str, Any] | None, seed: int) -> Any:
    """The scene's controller (for its generated functions), checked against the recorded QPs' shapes."""
    if scene == "two_tops":
        controller = two_tops_controller()[0]
    else:
        env, controller, _, _ = scene_controller(scene, seed)
        env.close()
    if meta is not None and (meta["horizon"], meta["tangent_dim"], meta["control_dim"]) != (
            controller.horizon, controller.layout.tangent_dim, controller.model.control_dim):
        raise UsageError(f"the recorded {scene} QPs are not this controller's (horizon, n_δ, m differ); "
                         "record them again with --force")
    return controller


def table(results: list[dict[str, Any]], counts: dict[str, dict[str, float]]) -> str:
    lines = ["| scene (N, n_δ, m, QPs) | solver | call µs median / p90 | own µs median | × riccati | "
             "max |Δu − Δu*| / range | first control | KKT residual median / max | failed | instructions / QP |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for result in results:
        label = (f"{result['scene']} ({result['horizon']}, {result['tangent_dim']}, {result['control_dim']}, "
                 f"{result['qps']})")
        for name, row in result["solvers"].items():
            own = "—" if row["own_us_median"] is None else f"{row['own_us_median']:.0f}"
            count = counts.get(result["scene"], {}).get(name)
            lines.append(f"| {label} | {name} | {row['call_us_median']:.0f} / {row['call_us_p90']:.0f} | {own} | "
                         f"{row['call_vs_riccati']:.2f} | {row['du_max']:.1e} | {row['first_control_max']:.1e} | "
                         f"{row['kkt_median']:.1e} / {row['kkt_max']:.1e} | {row['failures']} | "
                         f"{'—' if count is None else f'{count / 1e3:.0f}k'} |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.qp_peers", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    recorder = commands.add_parser("record", help="record the QPs of one closed loop per scene")
    solver = commands.add_parser("solve", help="solve the recorded QPs with every solver; the table")
    counter = commands.add_parser("instructions", help="instructions per QP under callgrind")
    replayer = commands.add_parser("replay", help="solve recorded QPs with one solver, untimed (callgrind's run)")
    for command in (recorder, solver, counter, replayer):
        command.add_argument("--cache", type=Path, default=DEFAULT_CACHE,
                             help="folder of the recorded QPs and built solvers (default: %(default)s)")
        command.add_argument("--seed", type=int, default=0, help="the quadrotor's recovery start (default: 0)")
    for command in (recorder, solver, counter):
        command.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES), help="default: all")
    recorder.add_argument("--force", action="store_true", help="record over existing recordings")
    solver.add_argument("--solvers", nargs="+", choices=SOLVERS, default=list(SOLVERS), help="default: all")
    solver.add_argument("--repeats", type=int, default=5, help="solves of each QP per solver (default: 5)")
    solver.add_argument("--qps", type=int, default=None, help="at most this many QPs per scene (default: all)")
    solver.add_argument("--instructions", type=Path, default=None,
                        help="a JSON of `instructions` to put in the table's last column")
    for command in (solver, counter):
        command.add_argument("--out", type=Path, default=None, help="JSON results (refused if present, unless --force)")
        command.add_argument("--force", action="store_true", help="replace --out")
    counter.add_argument("--solvers", nargs="+", choices=sorted(COUNTED_FUNCTION), default=["riccati", "hpipm"],
                         help="default: %(default)s")
    counter.add_argument("--qps", type=int, default=10, help="QPs per count (default: 10)")
    replayer.add_argument("--scene", choices=SCENES, required=True)
    replayer.add_argument("--solver", choices=sorted(COUNTED_FUNCTION), required=True)
    replayer.add_argument("--qps", type=int, default=10)
    return parser


def _check_out(args: argparse.Namespace) -> None:
    if getattr(args, "out", None) is not None and args.out.exists() and not args.force:
        raise UsageError(f"--out {args.out} exists; pass --force to replace it, or give another path")
    if getattr(args, "repeats", 1) < 1 or (getattr(args, "qps", None) is not None and args.qps < 1):
        raise UsageError("--repeats and --qps must be >= 1")


def main(argv: Sequence[str] | None = None) -> int:
    import torch

    torch.set_num_threads(1)
    args = build_parser().parse_args(argv)
    _check_out(args)
    if args.command == "record":
        present = [scene for scene in args.scenes if (args.cache / f"{scene}_qps.npz").exists()]
        if present and not args.force:
            raise UsageError(f"{args.cache} already holds recordings of {', '.join(present)}; pass --force to "
                             "record them again")
        for scene in args.scenes:
            controller, records = record(scene, args.seed)
            save_records(args.cache / f"{scene}_qps.npz", scene, controller, records, args.seed)
            print(f"{scene}: {len(records)} QPs → {args.cache / f'{scene}_qps.npz'}", file=sys.stderr)
        return 0
    if args.command == "replay":
        meta, arrays = load_records(args.cache / f"{args.scene}_qps.npz")
        replay(controller_for(args.scene, meta, args.seed), meta, arrays, args.solver, args.qps, args.cache / "build")
        return 0
    if args.command == "instructions":
        counts: dict[str, dict[str, float]] = {}
        for scene in args.scenes:
            load_records(args.cache / f"{scene}_qps.npz")
            counts[scene] = {solver: instructions(scene, solver, args.qps, args.cache) for solver in args.solvers}
            print(scene, {k: f"{v / 1e3:.0f}k" for k, v in counts[scene].items()}, file=sys.stderr)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"command": "python -m benchmarks.qp_peers instructions " + " ".join(
                sys.argv[2:] if argv is None else list(argv)[1:]), "qps": args.qps, "counts": counts}, indent=1))
        print(json.dumps(counts, indent=1))
        return 0
    counts = json.loads(args.instructions.read_text())["counts"] if args.instructions else {}
    results = []
    for scene in args.scenes:
        meta, arrays = load_records(args.cache / f"{scene}_qps.npz")
        controller = controller_for(scene, meta, args.seed)
        results.append(solve_scene(controller, meta, arrays, args.solvers, args.repeats, args.cache / "build",
                                   args.qps))
        print(table(results[-1:], counts), file=sys.stderr)
    text = table(results, counts)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"command": "python -m benchmarks.qp_peers solve", "repeats": args.repeats,
                                        "results": results}, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(run_command(main))
