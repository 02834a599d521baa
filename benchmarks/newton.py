"""``newton``: K unrolled Newton iterations of the implicit step vs a converged root finder.

For ``K = 1 … 6`` and CasADi's ``rootfinder`` (converged reference, ``--rootfinder newton``
or ``kinsol``): the Newton residual and the one-step and 40-step (2 s at h = 0.05) rollout
errors against held-out MuJoCo trajectories (``data/<scene>_heldout.npz``, collected with
``python -m fvin_mpc.collect --seed 1 --trajectories 64 --steps 40`` if missing; for
``spherical_pendulum`` the speed-bounded set of ``docs/spherical.md``, see
:func:`~benchmarks.common.heldout_data`), the
difference from the converged step, the time of one step (torch batched, CasADi single
call, CasADi ``map`` over the batch), and MPC solve time and closed-loop swing-up from rest
on MuJoCo (:func:`fvin_mpc.control.closed_loop.run_episode`) with the scene's MPC settings
(:func:`fvin_mpc.control.scene.scene_mpc_settings`; ``--horizon`` overrides the horizon).

``--model learned`` (default) uses the shipped ``<scene>_sign-invariant`` checkpoint (or
``--checkpoint``), ``--model true`` the closed-form body read off the scene's MJCF.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from benchmarks.common import NOISE_NOTE, checkpoint_or_none, heldout_data, make_env, plot_pareto, solve_stats
from benchmarks.study import StudyResult, StudySkipped, median_time
from fvin_mpc.control.model_export import from_checkpoint, from_rigid_body
from fvin_mpc.control.scene import scene_mpc_settings
from fvin_mpc.core import fvin, s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.networks import LearnedTerms
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.learning.collection import collect
from fvin_mpc.learning.timing import batched_step_call, tensor_weights, torch_threads

BATCH = 1024


# ----------------------------------------------------------------------------- converged step
def rootfinder_step(terms_ca: Any, step_size: float, plugin: str = "newton") -> Any:
    """``F(x[7], u[m]) -> (x_next[7], residual)`` with the implicit equation solved by CasADi's ``rootfinder``.

    Steps 1–2 and 4–5 are :func:`fvin_mpc.core.fvin.fvin_step`'s own (:func:`~fvin_mpc.core.fvin.implicit_problem`,
    :func:`~fvin_mpc.core.fvin.finish_step`); step 3, ``Φ(ξ) = C``, is solved to convergence (abstol 1e-14)
    from the first Newton iterate.
    """
    import casadi as ca

    ops = get_ops("casadi")
    m, h = terms_ca.control_dim, step_size
    x, u, xi = ca.SX.sym("x", 7), ca.SX.sym("u", m), ca.SX.sym("xi", 3)
    q, omega = tuple(x[i] for i in range(4)), tuple(x[4 + i] for i in range(3))
    controls = tuple(u[i] for i in range(m))
    problem = fvin.implicit_problem(q, omega, controls, terms_ca, h)
    xi_components = tuple(xi[i] for i in range(3))
    mismatch = s3.sub(fvin.implicit_lhs(xi_components, problem.inertia, ops), problem.rhs)
    equation = ca.Function("implicit", [xi, ca.vertcat(x, u)], [ca.vertcat(*mismatch)])
    options = {"abstol": 1e-15, "abstolStep": 1e-16, "max_iter": 50} if plugin == "newton" else {"abstol": 1e-15}
    # A state without a converged solution (past the solvability limit) must not abort the study:
    # the residual output says which ones, and the comparison with the converged step skips them.
    options["error_on_fail"] = False
    solver = ca.rootfinder("implicit_solve", plugin, equation, options)
    first = ca.Function("first_iterate", [x, u], [ca.vertcat(*s3.scale(-1.0, s3.solve3(problem.inertia, problem.rhs)))])
    result = fvin.finish_step(q, xi_components, problem, terms_ca, h, ops, with_residual=True)
    finish = ca.Function("finish", [x, u, xi], [ca.vertcat(*result.q, *result.omega), result.residual])

    X, U = ca.MX.sym("x", 7), ca.MX.sym("u", m)
    xi_star = solver(first(X, U), ca.vertcat(X, U))
    x_next, res = finish(X, U, xi_star)
    return ca.Function(f"fvin_step_{plugin}", [X, U], [x_next, res], ["x", "u"], ["x_next", "residual"])


# ----------------------------------------------------------------------------- evaluation
def _casadi_rollout(
    step: Any, q0: np.ndarray, omega0: np.ndarray, controls: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Batched rollout with ``step.map(B)``: states ``(B, T+1, 7)``, residuals ``(B, T)``."""
    batch, steps = controls.shape[:2]
    mapped = step.map(batch)
    x = np.concatenate([q0, omega0], axis=1).T
    states, residuals = [x.T], []
    for k in range(steps):
        x_next, residual = mapped(x, controls[:, k].T)
        x = np.asarray(x_next)
        states.append(x.T)
        residuals.append(np.asarray(residual).ravel())
    return np.stack(states, 1), np.stack(residuals, 1)


def _errors(states: np.ndarray, q_true: np.ndarray, omega_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sign-invariant angle (rad) and ‖Δω‖ (rad/s) between predicted ``states (…, 7)`` and data."""
    q_hat = states[..., :4] / np.linalg.norm(states[..., :4], axis=-1, keepdims=True)
    d = np.clip(np.abs((q_hat * q_true).sum(-1)), 0.0, 1.0)
    angle = 2.0 * np.arctan2(np.sqrt(np.maximum(0.0, 1.0 - d * d)), d)
    return angle, np.linalg.norm(states[..., 4:] - omega_true, axis=-1)


def _torch_step_time(source: Any, newton_iters: int, q: np.ndarray, omega: np.ndarray, u: np.ndarray,
                     repeats: int) -> float:

    if source["kind"] == "learned":

        checkpoint = source["checkpoint"]

        def terms_of(ops: Any) -> Any:
            return LearnedTerms(tensor_weights(checkpoint.weights), checkpoint.config, ops)
    else:
        terms_of = source["body"].terms
    call = batched_step_call(terms_of, source["step_size"], newton_iters, q, omega, u)
    with torch_threads(1):
        return median_time(call, repeats)[0]


def _casadi_single_time(step: Any, x: np.ndarray, u: np.ndarray, repeats: int, calls: int = 200) -> float:
    def call() -> None:
        for i in range(calls):
            step(x[i % x.shape[0]], u[i % u.shape[0]])

    return median_time(call, repeats)[0] / calls


def _casadi_map_time(step: Any, x: np.ndarray, u: np.ndarray, repeats: int) -> float:
    mapped = step.map(x.shape[0])
    xt, ut = np.ascontiguousarray(x.T), np.ascontiguousarray(u.T)
    return median_time(lambda: mapped(xt, ut), repeats)[0]


# ----------------------------------------------------------------------------- study
def _source(scene: str, model: str, checkpoint: str | None, control_period: float | None) -> dict[str, Any]:
    env = make_env(scene, control_period)
    base = env.unwrapped
    if model == "true":
        # The study is of the unrolled Newton solve: a hinge's closed form steps on its hinge, solved exactly
        # (no iterations to count), so the body is taken free to turn — the same motion, the 3-D solve.
        body = replace(from_mujoco(base.model, base.body_name), hinge_axis=None)
        return {"kind": "true", "body": body, "step_size": base.dt, "env": env, "label": f"true {scene}"}
    name = checkpoint or f"{scene}_sign-invariant"
    ckpt = checkpoint_or_none(name)
    if ckpt is None:
        raise StudySkipped(f"checkpoint {name!r} not found (checkpoints/{name}.json): train it with "
                           f"`python -m fvin_mpc.train --data data/{scene}.npz --out checkpoints/{name}`, "
                           "or run the study with --model true")
    if abs(ckpt.config.step_size - base.dt) > 1e-9:
        raise ValueError(
            f"checkpoint step {ckpt.config.step_size} s differs from the scene's control period {base.dt} s"
        )
    return {"kind": "learned", "checkpoint": ckpt, "step_size": ckpt.config.step_size, "env": env, "label": name}


def _exported(source: dict[str, Any], newton_iters: int) -> Any:
    if source["kind"] == "learned":
        return from_checkpoint(source["checkpoint"], newton_iters)
    return from_rigid_body(source["body"], source["step_size"], newton_iters, name=f"true_{newton_iters}")


def _casadi_terms(source: dict[str, Any]) -> Any:
    ops = get_ops("casadi")
    if source["kind"] == "learned":
        return LearnedTerms(source["checkpoint"].weights, source["checkpoint"].config, ops)
    return source["body"].terms(ops)


def run(quick: bool = False, seed: int = 0, repeats: int = 5, scene: str = "pendulum", model: str = "learned",
        checkpoint: str | None = None, rootfinder: str = "newton", horizon: int | None = None, duration: float = 8.0,
        iters: str = "1,2,3,4,5,6", **_: Any) -> StudyResult:
    from tqdm.auto import tqdm

    source = _source(scene, "true" if quick else model, checkpoint, None)
    h = source["step_size"]
    ks = [1, 2] if quick else [int(k) for k in iters.split(",")]
    repeats = 2 if quick else repeats
    if quick:

        data = collect(scene, 8, 10, 1, progress=False)
        horizon, duration = 10, 1.0
    else:
        data = heldout_data(scene, seed=1)
    m = data.u.shape[2]
    # One-step inputs: every recorded state with its control; targets: the next recorded state.
    q_in, w_in = data.q[:, :-1].reshape(-1, 4), data.omega[:, :-1].reshape(-1, 3)
    u_in = data.u.reshape(-1, 1, m)
    q_next, w_next = data.q[:, 1:].reshape(-1, 4), data.omega[:, 1:].reshape(-1, 3)
    reps = int(np.ceil(BATCH / q_in.shape[0]))
    xb = np.tile(np.concatenate([q_in, w_in], 1), (reps, 1))[:BATCH]
    ub = np.tile(u_in[:, 0], (reps, 1))[:BATCH]

    mpc_settings = scene_mpc_settings(source["env"], horizon=horizon)
    reference = rootfinder_step(_casadi_terms(source), h, rootfinder)
    ref_one, ref_residual = _casadi_rollout(reference, q_in, w_in, u_in)
    converged = ref_residual[:, 0] < 1e-8
    configs: list[tuple[str, Any, int | None]] = [(f"K={k}", None, k) for k in ks] + [
        (f"rootfinder ({rootfinder})", reference, None)
    ]
    rows: list[dict[str, Any]] = []
    env = source["env"]
    # Each K costs a closed-loop swing-up (minutes on the 3-D scene): show where the study is.
    for label, function, k in tqdm(configs, desc=f"newton study ({scene})", disable=quick):
        exported = _exported(source, k) if k is not None else None
        step = exported.step if exported is not None else function
        one, one_residual = _casadi_rollout(step, q_in, w_in, u_in)
        roll, roll_residual = _casadi_rollout(step, data.q[:, 0], data.omega[:, 0], data.u)
        angle1, omega1 = _errors(one[:, 1], q_next, w_next)
        angle_t, omega_t = _errors(roll, data.q, data.omega)
        row = {
            "config": label,
            "K": k if k is not None else "converged",
            "residual_max": float(max(one_residual.max(), roll_residual.max())),
            "residual_median": float(np.median(one_residual)),
            "vs_converged_omega_max": float(np.abs(one[converged, 1, 4:] - ref_one[converged, 1, 4:]).max()),
            "reference_unconverged": int((~converged).sum()),
            "one_step_angle_mean": float(angle1.mean()),
            "one_step_omega_mean": float(omega1.mean()),
            "rollout_angle_final_mean": float(angle_t[:, -1].mean()),
            "rollout_angle_mean": float(angle_t.mean()),
            "rollout_omega_final_mean": float(omega_t[:, -1].mean()),
            "rollout_s": data.u.shape[1] * h,
            "torch_batch_ms": 1e3 * _torch_step_time(source, k, xb[:, :4], xb[:, 4:], ub, repeats)
            if k is not None
            else None,
            "casadi_single_us": 1e6 * _casadi_single_time(step, xb, ub, repeats),
            "casadi_map_ms": 1e3 * _casadi_map_time(step, xb, ub, repeats),
        }
        if exported is not None:
            settings = replace(mpc_settings, compile="none" if quick else "cached")
            metrics = solve_stats(env, exported, settings, duration, seed=seed)
            row.update(mpc_ms_median=metrics["solver_ms_median"], mpc_ms_p95=metrics["solver_ms_p95"],
                       iterations_mean=metrics["iterations_mean"], success=metrics["success"],
                       time_to_upright_s=metrics["time_to_upright_s"], solver_failures=metrics["solver_failures"],
                       mpc_build_s=metrics["build_s"], compile_cached=metrics["compile_cached"])
        rows.append(row)

    k2 = next((r for r in rows if r["K"] == 2), None)
    notes = [
        f"Model: **{source['label']}** (h = {h} s); held-out data: {data.q.shape[0]} MuJoCo trajectories × "
        f"{data.u.shape[1]} steps (seed 1). One-step errors from every recorded state ({q_in.shape[0]} transitions); "
        f"rollout errors at the end of the {data.u.shape[1]}-step ({data.u.shape[1] * h:g} s) open-loop rollout. "
        "`residual` is the Newton residual of the implicit equation in rad/s (`fvin.StepResult.residual`); "
        "`vs_converged_omega_max` the largest |Δω| of one step against the root finder's, over the "
        "states where the root finder converged (`reference_unconverged` counts the others: no solution "
        "there, e.g. past the solvability limit).",
        f"Step time: torch (`fvin_step`, no grad, one thread) on a batch of {BATCH}; CasADi `Function` called once per "
        f"state "
        f"(µs per call, Python overhead included) and `map`ped over the {BATCH} states (ms per batch). "
        f"MPC: the scene's settings (`fvin_mpc.control.scene.scene_mpc_settings`), IPOPT, Gauss–Newton Hessian, "
        f"{'interpreted' if quick else 'compiled (cached)'}, primal–dual warm start, N = {mpc_settings.horizon}, "
        f"max_iter {mpc_settings.ipopt.max_iter}, terminal energy weight {mpc_settings.terminal_energy_weight:g}, "
        "swing-up "
        f"from rest for {duration:g} s on MuJoCo; solve-time columns are IPOPT's own time per control step. "
        "The root finder is not used inside the MPC (it cannot be expanded into the SX step the MPC compiles); "
        "the last K row with residual ≈ 0 stands for it.",
        NOISE_NOTE,
    ]
    if k2 is not None:
        ref_row = rows[-1]
        notes.insert(
            1,
            f"At K = 2 the {data.u.shape[1] * h:g} s rollout error is {k2['rollout_angle_final_mean']:.3g} rad vs "
            f"{ref_row['rollout_angle_final_mean']:.3g} rad converged: from K = 2 on, the model's own "
            "error (learned terms, discretization) dominates the Newton error.",
        )

    def plot(figure: Any, rows_: list[dict[str, Any]]) -> None:
        left, right = figure.subplots(1, 2)
        # An exact 0 cannot sit on a log axis: clipped at 1e-16 in the plot only.
        clipped = [dict(r, vs_converged_omega_max=max(r["vs_converged_omega_max"], 1e-16)) for r in rows_]
        plot_pareto(left, clipped, "casadi_map_ms", "vs_converged_omega_max", "config",
                    f"CasADi step time, map over {BATCH} (ms)", "one-step |Δω| vs converged (rad/s)")
        with_mpc = [r for r in rows_ if r.get("mpc_ms_median")]
        plot_pareto(right, with_mpc, "mpc_ms_median", "rollout_angle_final_mean", "config",
                    "MPC solve time, median (ms)", f"{data.u.shape[1] * h:g} s rollout angle error (rad)")
        figure.suptitle(f"Newton iterations — {source['label']}", fontsize=10)

    return StudyResult("newton" if scene == "pendulum" else f"newton-{scene}", rows,
                       ["config", "residual_max", "vs_converged_omega_max", "reference_unconverged",
                        "one_step_angle_mean", "one_step_omega_mean", "rollout_angle_final_mean",
                        "rollout_omega_final_mean", "torch_batch_ms", "casadi_single_us", "casadi_map_ms",
                        "mpc_ms_median", "mpc_ms_p95", "iterations_mean", "success", "time_to_upright_s",
                        "mpc_build_s"], plot, notes)


def add_arguments(parser: Any) -> None:
    parser.add_argument("--scene", default="pendulum", help="built-in scene (default: %(default)s)")
    parser.add_argument("--model", choices=["learned", "true"], default="learned",
                        help="learned checkpoint or the closed-form body (default: %(default)s)")
    parser.add_argument("--checkpoint", default=None, help="checkpoint name or path (default: <scene>_sign-invariant)")
    parser.add_argument("--rootfinder", choices=["newton", "kinsol"], default="newton",
                        help="CasADi rootfinder plugin of the converged reference (default: %(default)s)")
    parser.add_argument(
        "--horizon", type=int, default=None, help="MPC horizon N (default: the scene's, scene_mpc_settings)"
    )
    parser.add_argument("--duration", type=float, default=8.0, help="closed-loop seconds (default: %(default)s)")
    parser.add_argument("--iters", default="1,2,3,4,5,6", help="comma-separated K values (default: %(default)s)")
