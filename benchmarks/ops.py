"""``ops``: what a learned model's structure costs the controller, in CasADi operations per stage.

The real-time iteration linearizes the step ``F(x, u)`` at every stage of its plan each period, so
the learned/closed-form time ratio of a period is mostly the ratio of ``[F, ∂F/∂(x, u)]``'s
operation counts (``casadi.Function.n_instructions``; the compiled C code executes one statement
per instruction). Rows: the closed-form pendulum, the shipped planar checkpoints, and two untrained
prototypes that make the networks sign-invariant by reading the even features ``q qᵀ`` (one
evaluation) instead of averaging over ``±q`` (two) — with a configuration-dependent inertia network
and with a constant inertia. The prototypes' weights are random: an operation count depends on the
structure (widths, which terms depend on ``q``), not on the weights' values.

Further columns count what the real-time iteration evaluates per stage with each of its dynamics
constraints (``RTIOptions.dynamics``): ``unrolled`` — the gap of ``F`` and its Jacobian in the
7 chart directions ``(δ_k, Δu_k)`` (:func:`fvin_mpc.control.linearization.unrolled_stage_function`), differentiated as
written and, as the RTI builds it, on the terms' first-order expansions (:mod:`fvin_mpc.control.term_expansion`);
``implicit`` — the terms and their 3 chart derivatives once per node plus the stage's
implicit-function solve (:mod:`fvin_mpc.control.implicit_dynamics`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmarks.study import StudyResult
from fvin_mpc.control import implicit_dynamics
from fvin_mpc.control import model_export as export
from fvin_mpc.control.linearization import unrolled_stage_function
from fvin_mpc.control.scene import scene_env, scene_model
from fvin_mpc.core import s3
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.checkpoint import load_checkpoint
from fvin_mpc.core.networks import mlp, scalar_mlp_value_and_gradient
from fvin_mpc.core.space import PIVOTED

#: Shipped planar checkpoints counted, beside the closed form.
CHECKPOINTS = ("pendulum_sign-invariant", "pendulum_fixed-inertia", "pendulum_plain")
COLUMNS = ["model", "structure", "step_ops", "step_jacobian_ops", "vs_closed_form", "rti_unrolled_ops",
           "rti_unrolled_expanded_ops", "rti_implicit_ops", "implicit_vs_closed_form"]
#: The prototypes' even features ``q_i q_j``, ``i ≤ j``, and their networks' hidden layers (the shipped models').
FEATURE_PAIRS = tuple((i, j) for i in range(4) for j in range(i, 4))
HIDDEN_LAYERS = 2
CA = get_ops("casadi")


def _features(q: Any) -> Any:
    return CA.stack([q[i] * q[j] for i, j in FEATURE_PAIRS])


class EvenFeatureTerms:
    """Prototype :class:`~fvin_mpc.core.fvin.RigidBodyTerms`: tanh MLPs (2 × ``width``) of the ten
    products ``q_i q_j`` (``i ≤ j``) — even in ``q``, so sign-invariant with one evaluation — for
    ``U``, ``g`` and, unless ``constant_inertia``, the inertia's Cholesky factor. Random weights."""

    control_dim = 1

    def __init__(self, constant_inertia: bool, seed: int = 0, width: int = 10) -> None:
        rng = np.random.default_rng(seed)
        self.constant_inertia = constant_inertia
        self._weights: dict[str, np.ndarray] = {}
        for name, outputs in (("inertia", 6), ("potential", 1), ("gain", 3)):
            sizes = [len(FEATURE_PAIRS), width, width, outputs]
            for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
                self._weights[f"{name}_w{i}"] = 0.3 * rng.normal(size=(n_out, n_in))
                self._weights[f"{name}_b{i}"] = 0.1 * rng.normal(size=n_out)

    def _network(self, name: str, q: Any) -> tuple[Any, ...]:
        """The package's own MLP (:func:`fvin_mpc.core.networks.mlp`) on the even features."""

        return CA.unstack(mlp(self._weights, name, HIDDEN_LAYERS, _features(q), CA))

    def inertia(self, q: Any) -> Any:
        zero = 0.0 * q[0]
        if self.constant_inertia:
            return s3.symmetric_from_cholesky(tuple(zero + v for v in (1.0, 0.0, 1.0, 0.0, 0.0, 1.0)), 1e-3)
        return s3.symmetric_from_cholesky(self._network("inertia", q), 1e-3)

    def potential_gradient(self, q: Any) -> Any:
        """``∂U/∂q`` by the package's hand-written backpropagation to the features, then ``∂(q_i q_j)/∂q``."""

        _, feature_gradient = scalar_mlp_value_and_gradient(self._weights, "potential", HIDDEN_LAYERS, _features(q), CA)
        gradient = [0.0 * q[0]] * 4
        for g, (i, j) in zip(CA.unstack(feature_gradient), FEATURE_PAIRS):
            gradient[i] = gradient[i] + g * q[j]
            gradient[j] = gradient[j] + g * q[i]
        return tuple(gradient)

    def control_gain(self, q: Any) -> Any:
        return tuple((gain,) for gain in self._network("gain", q))

    def dissipation(self, q: Any) -> None:
        return None


def count(step: Any) -> tuple[int, int]:
    """Instructions of ``step`` (``F(x[7], u[m]) -> x_next, …``) and of ``[F, ∂F/∂(x, u)]``."""
    import casadi as ca

    x, u = ca.SX.sym("x", 7), ca.SX.sym("u", step.size1_in(1))
    x_next = step(x, u)[0]
    with_jacobian = ca.Function("f", [x, u], [x_next, ca.jacobian(x_next, ca.vertcat(x, u))])
    return int(ca.Function("f", [x, u], [x_next]).n_instructions()), int(with_jacobian.n_instructions())


def rti_stage_counts(model: Any) -> tuple[int, int, int]:
    """Instructions per stage of the RTI's unrolled dynamics differentiated as written, the same on the terms'
    first-order expansions (what the RTI builds, :mod:`fvin_mpc.control.term_expansion`), and of its implicit
    dynamics (node + stage); ``model`` an :class:`~fvin_mpc.control.model_export.ExportedModel` with terms."""
    terms = model.casadi_terms
    unrolled = unrolled_stage_function(model.step, PIVOTED, terms.control_dim)
    expanded = unrolled_stage_function(model.step, PIVOTED, terms.control_dim, model=model)
    node, layout = implicit_dynamics.node_terms_function(terms)
    stage = implicit_dynamics.implicit_stage_function(terms, layout, model.step_size)
    return (int(unrolled.n_instructions()), int(expanded.n_instructions()),
            int(node.n_instructions() + stage.n_instructions()))


def run(quick: bool = False, seed: int = 0, **_: Any) -> StudyResult:
    structures = {
        "sign-invariant": "`J(q)`, `U(q)`, `g(q)`, each averaged over `±q`; `J` also at `q_{k+1}`",
        "fixed-inertia": "constant `J`; `U(q)`, `g(q)`",
        "plain": "`J(q)`, `U(q)`, `g(q)`; `J` also at `q_{k+1}`",
    }
    rows: list[dict[str, Any]] = []
    env = scene_env("pendulum", true_model=True)
    closed = scene_model(env, true_model=True)  # the rod read off the MJCF, as the controllers use it
    env.close()
    rows.append({"model": "closed form", "structure": "the rod's `J`, `U`, `g`",
                 **_counts(closed)})
    for name in CHECKPOINTS[:1] if quick else CHECKPOINTS:
        checkpoint = load_checkpoint(name)
        model = export.from_checkpoint(checkpoint)
        rows.append({"model": name, "structure": structures.get(checkpoint.config.variant, checkpoint.config.variant),
                     **_counts(model)})
    for constant, label in ((False, "`J(q)`, `U`, `g` of `q qᵀ`"), (True, "constant `J`; `U`, `g` of `q qᵀ`")):
        terms = EvenFeatureTerms(constant, seed=seed)
        # (no energy: the prototypes' terms have no potential value, which nothing here reads)
        prototype = export.ExportedModel(step=export.step_function(terms, 0.05, 2), step_size=0.05, newton_iters=2,
                                         control_dim=terms.control_dim, numpy_terms=None, name="prototype",
                                         energy_function=None, casadi_terms=terms)
        rows.append({"model": "prototype, even features" + (", constant J" if constant else ""),
                     "structure": label + " (untrained, random weights)", **_counts(prototype)})
    for row in rows:
        row["vs_closed_form"] = row["step_jacobian_ops"] / rows[0]["step_jacobian_ops"]
        row["implicit_vs_closed_form"] = row["rti_implicit_ops"] / rows[0]["rti_implicit_ops"]
    notes = [
        "`step_ops`: instructions of the exported step `F(x, u)` (K = 2, h = 0.05); `step_jacobian_ops`: of "
        "`[F, ∂F/∂(x, u)]`, what the real-time iteration evaluates per stage and period; `vs_closed_form`: "
        "its ratio to the closed form's. Counts, not timings: they do not depend on the machine.",
        "The configuration-dependent inertia network is the expensive part (its value and derivatives at both "
        "ends of the step); averaging over `±q` doubles every network.",
        "`rti_unrolled_ops`: the RTI's stage with the unrolled step (its gap and Jacobian in the 7 chart "
        "directions), differentiated as written; `rti_unrolled_expanded_ops`: the same stage as the RTI "
        "builds it since 2026-11-27, its Jacobian on the terms' first-order expansions "
        "(fvin_mpc/control/term_expansion.py; the same derivatives); `rti_implicit_ops`: with the implicit "
        "dynamics, the terms and their 3 chart derivatives once per node plus the stage's implicit-function "
        "solve; `implicit_vs_closed_form`: its ratio to the closed form's. Measured periods of both are in "
        "docs/realtime.md.",
    ]
    return StudyResult("ops", rows, COLUMNS, plot, notes)


def _counts(model: Any) -> dict[str, int]:
    step_ops, jacobian_ops = count(model.step)
    unrolled_ops, expanded_ops, implicit_ops = rti_stage_counts(model)
    return {"step_ops": step_ops, "step_jacobian_ops": jacobian_ops, "rti_unrolled_ops": unrolled_ops,
            "rti_unrolled_expanded_ops": expanded_ops, "rti_implicit_ops": implicit_ops}


def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
    """Operations per stage — the step, the RTI's unrolled and implicit stages — one bar group per model."""
    axes = figure.subplots()
    positions = np.arange(len(rows))
    axes.barh(positions - 0.27, [r["step_ops"] for r in rows], height=0.27, label="step")
    axes.barh(positions, [r["rti_unrolled_ops"] for r in rows], height=0.27, label="RTI stage, unrolled step")
    axes.barh(positions + 0.27, [r["rti_implicit_ops"] for r in rows], height=0.27,
              label="RTI stage, implicit (node + stage)")
    axes.set_yticks(positions, [r["model"] for r in rows], fontsize=7)
    axes.invert_yaxis()
    axes.set_xlabel("CasADi instructions per stage")
    axes.legend(fontsize=7)
