"""The mechanism's variational step (:mod:`fvin_mpc.core.mechanism_step`) against independent references.

On the mechanism family's members (:data:`fvin_mpc.envs.mechanism_family.MEMBERS`, or the ones named):

* **order** — final-state error after ``--duration`` s against MuJoCo's RK4 at a 1e-5 s timestep on the same
  MJCF (joint limits off), from a seeded random state under a seeded constant control, damping on, at four
  step sizes halving from ``--step``; the log–log slope, for the converged step (``K = 5``) and ``K = 2``;
* **energy** — unforced and undamped, the largest relative energy error over ``--energy-steps`` steps at ``h =
  --step`` (``K = 2`` and ``K = 5``), beside explicit Euler's on the same closed form;
* **newton** — on the first double pendulum, the residual after ``K = 1, 2, 3`` and the contraction ratio
  ``r₂/r₁`` over a grid of the fastest joint's ``h|ν|`` and of the elbow's fold (``cond M``).

``python -m benchmarks.mechanism_step_check --help``; ``docs/mechanisms.md`` holds the numbers and the command.
:func:`compile_step` (the step as one CasADi ``Function``, evaluated numerically, rolled out with ``mapaccum``)
and :func:`mujoco_reference` are what ``tests/test_mechanism_step.py`` uses too.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import casadi as ca
import mujoco
import numpy as np

from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.blocks import StateLayout
from fvin_mpc.core.errors import UsageError, run_command
from fvin_mpc.core.mechanism_step import (
    ClosedFormMechanism,
    MechanismTerms,
    advance,
    mechanism_energy,
    mechanism_step,
)
from fvin_mpc.envs.joint_blocks import joint_layout
from fvin_mpc.envs.mechanism_family import KINDS, mechanism_mjcf

CA, NP = get_ops("casadi"), get_ops("numpy")


# ----------------------------------------------------------------------------- the step, numerically
@dataclass(frozen=True)
class CompiledStep:
    """One mechanism's step as a CasADi ``Function`` ``(x, u) → (x_next, residual)``, evaluated numerically."""

    layout: StateLayout
    terms: MechanismTerms
    step_size: float
    newton_iters: int
    function: ca.Function

    def step(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, float]:
        x_next, residual = self.function(x, u)
        return np.asarray(x_next, dtype=float).ravel(), float(residual)

    def rollout(self, x0: np.ndarray, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States ``(N + 1, n)`` from ``x0`` under ``controls (N, m)``, and the ``N`` residuals."""
        controls = np.asarray(controls, dtype=float).reshape(len(controls), -1)
        states, residuals = self.function.mapaccum(len(controls))(x0, controls.T)
        return np.vstack([x0, np.asarray(states).T]), np.asarray(residuals, dtype=float).ravel()

    def energy(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(mechanism_energy(np.asarray(states, dtype=float), self.terms, self.layout, NP), dtype=float)


def compile_step(terms: MechanismTerms, layout: StateLayout, step_size: float, newton_iters: int) -> CompiledStep:
    """:func:`~fvin_mpc.core.mechanism_step.mechanism_step` on SX symbols, as one ``Function``."""
    x, u = ca.SX.sym("x", layout.state_dim), ca.SX.sym("u", terms.control_dim)
    result = mechanism_step(x, u, terms, layout, step_size, newton_iters, CA)
    function = ca.Function("mechanism_step", [x, u], [result.x, result.residual], ["x", "u"], ["x_next", "residual"])
    return CompiledStep(layout, terms, step_size, newton_iters, function)


def member_model(kind: str, seed: int) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(mechanism_mjcf(kind, seed))


# ----------------------------------------------------------------------------- references
def mujoco_reference(model: mujoco.MjModel, x0: np.ndarray, control: np.ndarray, duration: float,
                     timestep: float = 1e-5) -> np.ndarray:
    """The state after ``duration`` s under a constant control: MuJoCo's RK4 at ``timestep``, joint limits off
    (the step does not model their constraint forces) — an integrator independent of the closed form's code."""
    reference = copy.deepcopy(model)
    reference.opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4)
    reference.opt.timestep = timestep
    reference.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
    data = mujoco.MjData(reference)
    data.qpos[:], data.qvel[:] = x0[:reference.nq], x0[reference.nq:]
    data.ctrl[:] = control
    steps = int(round(duration / timestep))
    if abs(steps * timestep - duration) > 1e-12:
        raise UsageError(f"duration {duration} s is not a whole number of {timestep} s reference steps")
    for _ in range(steps):
        mujoco.mj_step(reference, data)
    return np.concatenate([data.qpos, data.qvel])


def state_error(layout: StateLayout, a: np.ndarray, b: np.ndarray) -> float:
    """The largest entry of ``a``'s difference from ``b`` in angles, lengths and rates (a quaternion's as its
    rotation's angle to first order, the same for ``±q``)."""
    return float(np.max(np.abs(layout.rates_over_step(layout.local(b, a), 1.0))))


def explicit_euler_energy(model: mujoco.MjModel, x0: np.ndarray, step_size: float, steps: int) -> np.ndarray:
    """The closed form's energy along explicit Euler (``ν += h M⁻¹(−bias)``, ``q ⊞= h ν``), undamped, unforced."""
    terms = ClosedFormMechanism.from_mujoco(model, damped=False)
    layout = joint_layout(model)
    x, energies = np.array(x0, dtype=float), []
    with np.errstate(all="ignore"):  # it diverges: the energy is reported as inf from there on
        for _ in range(steps + 1):
            energies.append(float(mechanism_energy(x, terms, layout, NP)))
            if not np.isfinite(energies[-1]) or abs(energies[-1]) > 1e12:
                energies[-1] = math.inf
                break
            qpos, qvel = x[layout.positions], x[layout.rates]
            computed = terms.tree.numpy_terms(qpos, qvel)
            spring = terms.tree.numpy_terms(qpos, np.zeros(model.nv))["passive"]  # undamped: the springs alone
            acceleration = np.linalg.solve(computed["mass"], spring - computed["bias"])
            qpos = np.asarray(advance(layout, NP.unstack(qpos), NP.unstack(step_size * qvel), NP), dtype=float)
            x = np.concatenate([qpos, qvel + step_size * acceleration])
    return np.array(energies)


# ----------------------------------------------------------------------------- the measures
def random_start(model: mujoco.MjModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A start state (angles and travels ~N(0, 0.7²) from ``qpos0``, quaternions uniform, rates ~N(0, 1)) and a
    constant control uniform in ±0.5 (inside every member's ``ctrlrange``)."""
    qpos = model.qpos0 + 0.7 * rng.normal(size=model.nq)
    for joint in range(model.njnt):
        kind = int(model.jnt_type[joint])
        offset = {int(mujoco.mjtJoint.mjJNT_FREE): 3, int(mujoco.mjtJoint.mjJNT_BALL): 0}.get(kind)
        if offset is not None:
            start = int(model.jnt_qposadr[joint]) + offset
            quat = rng.normal(size=4)
            qpos[start:start + 4] = quat / np.linalg.norm(quat)
    return np.concatenate([qpos, rng.normal(size=model.nv)]), rng.uniform(-0.5, 0.5, size=model.nu)


def convergence(kind: str, seed: int, rng: np.random.Generator, duration: float, step: float,
                newton_iters: int) -> dict[str, Any]:
    """Final-state errors at ``step, step/2, step/4, step/8`` against :func:`mujoco_reference` and their slope."""
    model = member_model(kind, seed)
    x0, control = random_start(model, rng)
    layout, terms = joint_layout(model), ClosedFormMechanism.from_mujoco(model)
    reference = mujoco_reference(model, x0, control, duration)
    sizes = [step / 2 ** i for i in range(4)]
    errors = []
    for h in sizes:
        steps = int(round(duration / h))
        states, _ = compile_step(terms, layout, h, newton_iters).rollout(x0, np.tile(control, (steps, 1)))
        errors.append(state_error(layout, states[-1], reference))
    slope = float(np.polyfit(np.log(sizes), np.log(errors), 1)[0])
    return {"member": f"{kind} {seed}", "blocks": "+".join(b.kind for b in layout.blocks), "K": newton_iters,
            "step_sizes": sizes, "errors": errors, "slope": slope}


def energy_behaviour(kind: str, seed: int, rng: np.random.Generator, step: float, steps: int,
                     newton_iters: int) -> dict[str, Any]:
    """The largest energy error over ``steps`` unforced undamped steps relative to :func:`energy_scale`, and
    explicit Euler's from the same start (over at most 2,000 of its steps)."""
    model = member_model(kind, seed)
    x0, _ = random_start(model, rng)
    layout, terms = joint_layout(model), ClosedFormMechanism.from_mujoco(model, damped=False)
    states, residuals = compile_step(terms, layout, step, newton_iters).rollout(x0, np.zeros((steps, model.nu)))
    energy = np.asarray(mechanism_energy(states, terms, layout, NP), dtype=float)
    scale = energy_scale(energy, terms, layout, states)
    euler_steps = min(steps, 2000)
    euler = explicit_euler_energy(model, x0, step, euler_steps)
    return {"member": f"{kind} {seed}", "K": newton_iters, "h": step, "steps": steps,
            "energy_error": float(np.max(np.abs(energy - energy[0])) / scale),
            "final_energy_error": float(abs(energy[-1] - energy[0]) / scale),
            "max_residual": float(np.max(residuals)),
            "euler_steps": euler_steps, "euler_energy_error": float(np.max(np.abs(euler - euler[0])) / scale)}


def energy_scale(energy: np.ndarray, terms: ClosedFormMechanism, layout: StateLayout, states: np.ndarray) -> float:
    """The energy's scale: the start's kinetic energy plus its potential above the lowest potential along the
    trajectory (a potential's zero is arbitrary; a relative error needs a scale that is not)."""
    potential = np.asarray(terms.potential(NP.unstack(states[:, layout.positions]), NP), dtype=float)
    potential = np.broadcast_to(potential, energy.shape)
    return float(energy[0] - potential.min())


def newton_region(kind: str, seed: int, step: float, rates: Sequence[float], folds: Sequence[float]) -> list[dict]:
    """Residuals after ``K = 1, 2, 3`` from states with the shoulder at rest straight down, the elbow folded by
    ``fold`` (rad), and rates ``ν = (ρ/h)·(1, −1)/√2``... scaled so the fastest joint's ``h|ν|`` is ``ρ``."""
    model = member_model(kind, seed)
    layout, terms = joint_layout(model), ClosedFormMechanism.from_mujoco(model, damped=False)
    steps = {k: compile_step(terms, layout, step, k) for k in (1, 2, 3, 6)}
    rows = []
    for fold in folds:
        qpos = model.qpos0.copy()
        qpos[1] += fold
        mass = terms.tree.numpy_terms(qpos, np.zeros(model.nv))["mass"]
        for rate in rates:
            direction = np.array([1.0, -1.0] + [0.0] * (model.nv - 2))
            x = np.concatenate([qpos, (rate / step) * direction])
            residual = {k: steps[k].step(x, np.zeros(model.nu))[1] for k in steps}
            rows.append({"fold": fold, "cond_M": float(np.linalg.cond(mass)), "h_nu": rate,
                         "r1": residual[1], "r2": residual[2], "r3": residual[3], "r6": residual[6],
                         "ratio": residual[2] / residual[1] if residual[1] > 0 else 0.0})
    return rows


# ----------------------------------------------------------------------------- the command
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.mechanism_step_check",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--members", nargs="*", default=None, metavar="KIND:SEED",
                        help="members as kind:seed (default: seed 0 of every kind)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the start states and controls (default 0)")
    parser.add_argument("--duration", type=float, default=0.5, help="order check's horizon, s (default 0.5)")
    parser.add_argument("--step", type=float, default=0.02, help="largest step size, s (default 0.02)")
    parser.add_argument("--energy-steps", type=int, default=100_000, help="unforced steps (default 100000)")
    parser.add_argument("--only", choices=("order", "energy", "newton"), nargs="*", default=None,
                        help="the measures to run (default: all)")
    parser.add_argument("--output", type=Path, default=None, help="a JSON file for the results (default: none)")
    parser.add_argument("--force", action="store_true", help="overwrite --output if it exists")
    return parser


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    args = build_parser().parse_args(argv)
    if args.output is not None and args.output.exists() and not args.force:
        raise UsageError(f"{args.output} exists; pass --force to overwrite it")
    if args.duration <= 0 or args.step <= 0 or args.energy_steps < 1:
        raise UsageError("--duration, --step and --energy-steps must be positive")
    members = [(kind, 0) for kind in KINDS] if args.members is None else []
    for text in args.members or []:
        kind, _, seed = text.partition(":")
        if kind not in KINDS or not seed.lstrip("-").isdigit():
            raise UsageError(f"--members takes kind:seed with kind one of {list(KINDS)}, got {text!r}")
        members.append((kind, int(seed)))
    args.member_list = members
    return args


def _per_member(args: argparse.Namespace, iterations: Sequence[int], measure: Any, describe: Any) -> list[dict]:
    """``measure(kind, seed, rng, K)`` of every member and ``K``, each row printed as ``describe`` says."""
    rows = []
    for kind, seed in args.member_list:
        for k in iterations:
            rows.append(measure(kind, seed, np.random.default_rng([args.seed, seed, KINDS.index(kind)]), k))
            print(describe(rows[-1]), flush=True)
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    args = _parse(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    only = set(args.only or ("order", "energy", "newton"))
    results: dict[str, Any] = {"seed": args.seed}
    if "order" in only:
        results["order"] = _per_member(
            args, (5, 2), lambda kind, seed, rng, k: convergence(kind, seed, rng, args.duration, args.step, k),
            lambda row: (f"order  {row['member']:18s} {row['blocks']:18s} K={row['K']}: errors "
                         f"{' '.join(f'{e:.2e}' for e in row['errors'])}  slope {row['slope']:.3f}"))
    if "energy" in only:
        results["energy"] = _per_member(
            args, (2, 5), lambda kind, seed, rng, k: energy_behaviour(kind, seed, rng, args.step, args.energy_steps, k),
            lambda row: (f"energy {row['member']:18s} K={row['K']} h={row['h']}: max |ΔE|/E {row['energy_error']:.2e} "
                         f"over {row['steps']} steps (end {row['final_energy_error']:.2e}, max residual "
                         f"{row['max_residual']:.1e}); explicit Euler {row['euler_energy_error']:.2e} over "
                         f"{row['euler_steps']}"))
    if "newton" in only:
        kind, seed = next(((k, s) for k, s in args.member_list if k == "double_pendulum"), ("double_pendulum", 0))
        rows = newton_region(kind, seed, args.step, (0.05, 0.1, 0.2, 0.5, 1.0, 1.5, 2.0, 3.0),
                             (0.0, math.pi / 2, 2.5, 2.9, 3.1))
        results["newton"] = {"member": f"{kind} {seed}", "h": args.step, "rows": rows}
        print(f"newton {kind} {seed}, h = {args.step}: fold  cond M  h|ν|  r1  r2  r3  r6  r2/r1")
        for row in rows:
            print(f"  {row['fold']:.3f} {row['cond_M']:8.1f} {row['h_nu']:5.2f} {row['r1']:.1e} {row['r2']:.1e} "
                  f"{row['r3']:.1e} {row['r6']:.1e} {row['ratio']:.2e}", flush=True)
    if args.output is not None:
        args.output.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_command(main))
