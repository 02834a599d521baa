"""``ops``: what a learned model's structure costs the controller, in CasADi operations per stage.

The real-time iteration linearizes the step ``F(x, u)`` at every stage of its plan each period, so
the learned/closed-form time ratio of a period is mostly the ratio of ``[F, ∂F/∂(x, u)]``'s
operation counts (``casadi.Function.n_instructions``; the compiled C code executes one statement
per instruction). Rows: the closed-form pendulum, the shipped planar checkpoints, and two untrained
prototypes that make the networks sign-invariant by reading the even features ``q qᵀ`` (one
evaluation) instead of averaging over ``±q`` (two) — with a configuration-dependent inertia network
and with a constant inertia. The prototypes' weights are random: an operation count depends on the
structure (widths, which terms depend on ``q``), not on the weights' values.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fvin_mpc.studies.report import StudyResult

#: Shipped planar checkpoints counted, beside the closed form.
CHECKPOINTS = ("pendulum_sign-invariant", "pendulum_fixed-inertia", "pendulum_plain")
COLUMNS = ["model", "structure", "step_ops", "step_jacobian_ops", "vs_closed_form"]


class EvenFeatureTerms:
    """Prototype :class:`~fvin_mpc.core.fvin.RigidBodyTerms`: tanh MLPs (2 × ``width``) of the ten
    products ``q_i q_j`` (``i ≤ j``) — even in ``q``, so sign-invariant with one evaluation — for
    ``U``, ``g`` and, unless ``constant_inertia``, the inertia's Cholesky factor. Random weights."""

    control_dim = 1

    def __init__(self, constant_inertia: bool, seed: int = 0, width: int = 10) -> None:
        rng = np.random.default_rng(seed)
        self.constant_inertia = constant_inertia

        def network(outputs: int) -> list[tuple[np.ndarray, np.ndarray]]:
            sizes = [10, width, width, outputs]
            return [(0.3 * rng.normal(size=(n_out, n_in)), 0.1 * rng.normal(size=n_out))
                    for n_in, n_out in zip(sizes[:-1], sizes[1:])]

        self._inertia, self._potential, self._gain = network(6), network(1), network(3)

    @staticmethod
    def _evaluate(layers: list[tuple[np.ndarray, np.ndarray]], q: Any) -> Any:
        import casadi as ca

        x = ca.vertcat(*[q[i] * q[j] for i in range(4) for j in range(i, 4)])
        for index, (weight, bias) in enumerate(layers):
            x = ca.mtimes(ca.DM(weight), x) + ca.DM(bias)
            if index < len(layers) - 1:
                x = ca.tanh(x)
        return x

    def inertia(self, q: Any) -> Any:
        from fvin_mpc.core import s3

        zero = 0.0 * q[0]
        if self.constant_inertia:
            return s3.symmetric_from_cholesky(tuple(zero + v for v in (1.0, 0.0, 1.0, 0.0, 0.0, 1.0)), 1e-3)
        factor = self._evaluate(self._inertia, q)
        return s3.symmetric_from_cholesky(tuple(factor[i] for i in range(6)), 1e-3)

    def potential_gradient(self, q: Any) -> Any:
        import casadi as ca

        point = ca.SX.sym("q", 4)
        gradient = ca.substitute(ca.gradient(self._evaluate(self._potential, point), point), point, ca.vertcat(*q))
        return tuple(gradient[i] for i in range(4))

    def control_gain(self, q: Any) -> Any:
        gain = self._evaluate(self._gain, q)
        return tuple((gain[i],) for i in range(3))

    def dissipation(self, q: Any) -> None:
        return None


def count(step: Any) -> tuple[int, int]:
    """Instructions of ``step`` (``F(x[7], u[m]) -> x_next, …``) and of ``[F, ∂F/∂(x, u)]``."""
    import casadi as ca

    x, u = ca.SX.sym("x", 7), ca.SX.sym("u", step.size1_in(1))
    x_next = step(x, u)[0]
    with_jacobian = ca.Function("f", [x, u], [x_next, ca.jacobian(x_next, ca.vertcat(x, u))])
    return int(ca.Function("f", [x, u], [x_next]).n_instructions()), int(with_jacobian.n_instructions())


def run(quick: bool = False, seed: int = 0, **_: Any) -> StudyResult:
    from fvin_mpc.control import export
    from fvin_mpc.core.checkpoint import load_checkpoint
    from fvin_mpc.control.scene import scene_env, scene_model

    structures = {
        "sign-invariant": "`J(q)`, `U(q)`, `g(q)`, each averaged over `±q`; `J` also at `q_{k+1}`",
        "fixed-inertia": "constant `J`; `U(q)`, `g(q)`",
        "plain": "`J(q)`, `U(q)`, `g(q)`; `J` also at `q_{k+1}`",
    }
    rows: list[dict[str, Any]] = []
    env = scene_env("pendulum", true_model=True)
    closed = scene_model(env, true_model=True)  # the rod read off the MJCF, as the controllers use it
    env.close()
    rows.append({"model": "closed form", "structure": "the rod's `J`, `U`, `g`", **_counts(closed.step)})
    for name in CHECKPOINTS[:1] if quick else CHECKPOINTS:
        checkpoint = load_checkpoint(name)
        rows.append({"model": name, "structure": structures.get(checkpoint.config.variant, checkpoint.config.variant),
                     **_counts(export.from_checkpoint(checkpoint).step)})
    for constant, label in ((False, "`J(q)`, `U`, `g` of `q qᵀ`"), (True, "constant `J`; `U`, `g` of `q qᵀ`")):
        terms = EvenFeatureTerms(constant, seed=seed)
        step = export.step_function(terms, 0.05, 2)
        rows.append({"model": "prototype, even features" + (", constant J" if constant else ""),
                     "structure": label + " (untrained, random weights)", **_counts(step)})
    for row in rows:
        row["vs_closed_form"] = row["step_jacobian_ops"] / rows[0]["step_jacobian_ops"]
    notes = [
        "`step_ops`: instructions of the exported step `F(x, u)` (K = 2, h = 0.05); `step_jacobian_ops`: of "
        "`[F, ∂F/∂(x, u)]`, what the real-time iteration evaluates per stage and period; `vs_closed_form`: "
        "its ratio to the closed form's. Counts, not timings: they do not depend on the machine.",
        "The configuration-dependent inertia network is the expensive part (its value and derivatives at both "
        "ends of the step); averaging over `±q` doubles every network. The measured periods are in "
        "docs/realtime.md (the fixed-inertia checkpoint's RTI period is 1.27× the closed form's, the "
        "sign-invariant one's 1.81×).",
    ]
    return StudyResult("ops", rows, COLUMNS, plot, notes)


def _counts(step: Any) -> dict[str, int]:
    step_ops, jacobian_ops = count(step)
    return {"step_ops": step_ops, "step_jacobian_ops": jacobian_ops}


def plot(figure: Any, rows: list[dict[str, Any]]) -> None:
    """Operations per stage, step and step with its Jacobian, one bar pair per model."""
    axes = figure.subplots()
    positions = np.arange(len(rows))
    axes.barh(positions + 0.2, [r["step_jacobian_ops"] for r in rows], height=0.4, label="step + Jacobian")
    axes.barh(positions - 0.2, [r["step_ops"] for r in rows], height=0.4, label="step")
    axes.set_yticks(positions, [r["model"] for r in rows], fontsize=7)
    axes.invert_yaxis()
    axes.set_xlabel("CasADi instructions per stage")
    axes.legend(fontsize=7)
