"""The accuracy-vs-time studies (``python -m benchmarks``): their ``--quick`` variants run
end to end here, so the scripts stay alive, and their measurements obey the math they report.
No timing is asserted (the machines are shared); only that times are positive and finite."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from benchmarks.__main__ import STUDIES, build_parser, main
from benchmarks.common import pareto_mask
from benchmarks.study import StudyResult, write_study


@pytest.fixture(autouse=True)
def _isolated(tmp_path, monkeypatch):
    """Nothing lands in the repository or the user's cache: cwd and the compiled-code cache are temporary."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("FVIN_MPC_CACHE", str(tmp_path / "cache"))


def _positive_times(rows, *columns):
    for row in rows:
        for column in columns:
            value = row.get(column)
            if value is not None:
                assert np.isfinite(value) and value > 0, (column, row)


def test_every_registered_study_has_a_run_function_and_help():
    parser = build_parser()
    for name in STUDIES:
        with pytest.raises(SystemExit) as exit_info:
            parser.parse_args([name, "--help"])
        assert exit_info.value.code == 0


def test_pareto_mask_keeps_exactly_the_non_dominated_points():
    x = [1.0, 2.0, 3.0, 2.0, None, 0.5]
    y = [3.0, 1.0, 0.5, 2.0, 0.1, float("nan")]
    # (2, 2) is dominated by (2, 1); missing values are never on the front.
    assert pareto_mask(x, y).tolist() == [True, True, True, False, False, False]


def test_write_study_records_the_command(tmp_path):
    result = StudyResult(
        "demo", [{"a": 1.0, "b": None}], ["a", "b"], lambda figure, rows: figure.add_subplot().plot([0, 1])
    )
    paths = write_study(result, tmp_path / "out", ["demo", "--quick"])
    saved = json.loads(paths["json"].read_text())
    assert saved["command"] == "python -m benchmarks demo --quick"
    assert "`python -m benchmarks demo --quick`" in paths["md"].read_text()
    assert paths["png"].stat().st_size > 0


def test_sim_quick_via_cli(tmp_path, capsys):
    assert main(["sim", "--quick", "--out-dir", str(tmp_path / "bench")]) == 0
    rows = json.loads((tmp_path / "bench" / "sim.json").read_text())["rows"]
    integrators = {(r["integrator"], r["timestep_ms"]): r for r in rows if r["part"] == "integrator"}
    # RK4 (4th order) beats semi-implicit Euler (1st order) at the same step by orders of magnitude,
    # and its error shrinks ≈ 2⁴ per halving — here 5× smaller step: at least 100× smaller error.
    assert integrators[("rk4", 5.0)]["max_theta_error_rad"] < 1e-3 * integrators[("euler", 5.0)]["max_theta_error_rad"]
    assert integrators[("rk4", 1.0)]["max_theta_error_rad"] < 1e-2 * integrators[("rk4", 5.0)]["max_theta_error_rad"]
    # First order: 5× smaller step, ≈ 5× smaller error.
    ratio = integrators[("euler", 5.0)]["max_theta_error_rad"] / integrators[("euler", 1.0)]["max_theta_error_rad"]
    assert 3.0 < ratio < 8.0
    scene = [r for r in rows if r["part"] == "scene physics"]
    # Switching everything on must not change this scene's trajectory (nothing it adds ever acts).
    assert scene[1]["max_theta_difference_rad"] == 0.0
    _positive_times(rows, "wall_ms_median", "time_vs_declared")
    assert (tmp_path / "bench" / "sim.png").is_file()


def test_rootfinder_step_matches_converged_newton():
    from benchmarks.newton import rootfinder_step
    from fvin_mpc.control.model_export import from_rigid_body
    from fvin_mpc.core.backend import get_ops
    from fvin_mpc.core.rigid_body import PENDULUM

    reference = rootfinder_step(PENDULUM.terms(get_ops("casadi")), 0.05, "newton")
    newton6 = from_rigid_body(PENDULUM, 0.05, 6)
    rng = np.random.default_rng(0)
    for _ in range(5):
        angle = rng.uniform(-np.pi, np.pi)
        x = np.array([np.cos(angle / 2), 0.0, np.sin(angle / 2), 0.0, 0.0, rng.uniform(-8, 8), 0.0])
        u = rng.uniform(-2, 2, size=1)
        x_ref, residual = reference(x, u)
        x6, _ = newton6(x, u)
        assert float(residual) < 1e-9
        np.testing.assert_allclose(np.asarray(x_ref).ravel(), x6, atol=1e-12)


def test_newton_quick_residual_falls_with_k(tmp_path):
    from benchmarks import newton

    result = newton.run(quick=True)
    rows = {r["config"]: r for r in result.rows}
    k1, k2, converged = rows["K=1"], rows["K=2"], rows["rootfinder (newton)"]
    # Quadratic convergence: one more iteration shrinks the residual by orders of magnitude.
    assert k2["residual_max"] < 1e-2 * k1["residual_max"]
    assert converged["residual_max"] < 1e-9
    assert k2["vs_converged_omega_max"] < 1e-2 < k1["vs_converged_omega_max"]
    assert converged["vs_converged_omega_max"] == 0.0
    _positive_times(result.rows, "torch_batch_ms", "casadi_single_us", "casadi_map_ms", "mpc_ms_median")
    write_study(result, tmp_path, ["newton", "--quick"])


def test_newton_skips_with_a_message_when_the_checkpoint_is_absent(tmp_path, capsys):
    assert main(["newton", "--checkpoint", "no-such-checkpoint", "--out-dir", str(tmp_path)]) == 0
    assert "skipped newton" in capsys.readouterr().err
    assert not (tmp_path / "newton.json").exists()


def test_horizon_quick(tmp_path):
    from benchmarks import horizon

    result = horizon.run(quick=True)
    for row in result.rows:
        assert row["N"] == round(row["horizon_s"] / row["h"])
        assert np.isfinite(row["cost_integral"]) and row["cost_integral"] > 0
    _positive_times(result.rows, "mpc_ms_median", "mpc_ms_p95")
    write_study(result, tmp_path, ["horizon", "--quick"])


def test_rti_quick_pairs_learned_with_closed_form(tmp_path):
    from benchmarks import rti_knobs as rti

    result = rti.run(quick=True)
    assert [(r["config"], r["model"]) for r in result.rows] == [
        (label, model) for label in rti.QUICK for model in ("learned", "closed form")]
    for row in result.rows:
        # the feedback is part of the whole time per period
        assert 0 < row["feedback_ms_median"] <= row["call_ms_median"] + 1e-9, row
        assert row["starts"] == 2 and np.isfinite(row["cost_mean"]) and row["cost_mean"] > 0
    for learned, closed in zip(result.rows[::2], result.rows[1::2]):
        assert learned["learned_vs_true"] == pytest.approx(learned["call_ms_median"] / closed["call_ms_median"])
        assert closed["learned_vs_true"] is None
    write_study(result, tmp_path, ["rti", "--quick"])


def test_ops_counts_order_the_structures(tmp_path):
    """Fewer networks, fewer evaluations of each, a constant inertia: fewer operations per stage."""
    from benchmarks import ops

    result = ops.run(quick=True)
    by_model = {r["model"]: r["step_jacobian_ops"] for r in result.rows}
    assert (by_model["closed form"] < by_model["prototype, even features, constant J"]
            < by_model["prototype, even features"] < by_model["pendulum_sign-invariant"])
    for row in result.rows:
        assert 0 < row["step_ops"] < row["step_jacobian_ops"], row
    # the implicit dynamics evaluate each network once per node, not twice per stage in 7 directions
    learned = next(r for r in result.rows if r["model"] == "pendulum_sign-invariant")
    assert learned["rti_implicit_ops"] < 0.6 * learned["rti_unrolled_ops"]
    write_study(result, tmp_path, ["ops", "--quick"])


def test_solver_quick(tmp_path):
    from benchmarks import solver

    result = solver.run(quick=True)
    assert {r["solver"] for r in result.rows} == {"ipopt", "sqpmethod", "fatrop"}
    for row in result.rows:
        assert row["solver_failures"] == 0, row
    _positive_times(result.rows, "mpc_ms_median", "iterations_mean")
    write_study(result, tmp_path, ["solver", "--quick"])


def test_realtime_rows_put_every_learned_checkpoint_beside_the_closed_form():
    from benchmarks import solver

    rows = solver.realtime_rows(
        duration=0.5,
        scenes=("pendulum",),
        configs=(("rti", {"solver": "rti", "compile": "none"}, 0.001),),
        extra_checkpoints={"pendulum": ("pendulum_fixed-inertia",)},
    )
    assert [r["model"] for r in rows] == ["learned", "closed form", "learned (fixed-inertia)"]
    closed = rows[1]
    assert closed["learned_vs_true"] is None
    for row in (rows[0], rows[2]):
        assert row["learned_vs_true"] == pytest.approx(row["call_ms_median"] / closed["call_ms_median"])
        assert 0 < row["feedback_ms_median"] <= row["call_ms_median"] + 1e-9, row


@pytest.mark.parametrize("overrides", [{"solver": "sqpmethod"}, {"solver": "sqpmethod", "ipopt": {"hessian": "exact"}},
                                       {"solver": "fatrop", "ipopt": {"hessian": "exact"}, "compile": "none"}])
def test_other_nlp_solvers_find_ipopts_plan(overrides):
    from fvin_mpc.control.model_export import from_rigid_body
    from fvin_mpc.control.mpc import MPC, MPCSettings
    from fvin_mpc.core.rigid_body import PENDULUM

    model = from_rigid_body(PENDULUM, 0.05, 2, name="bench_test")
    base = MPCSettings().updated(horizon=12, compile="none", ipopt={"tol": 1e-9})
    q, omega = np.array([np.cos(0.4), 0.0, np.sin(0.4), 0.0]), np.array([0.0, 1.0, 0.0])
    ipopt = MPC(model, base, (0, 0, 1, 0), [-2.0], [2.0])
    other = MPC(model, base.updated(**{k: v for k, v in overrides.items() if k != "compile"}),
                (0, 0, 1, 0), [-2.0], [2.0])
    u_ref, info_ref = ipopt(np.r_[q, omega])
    u, info = other(np.r_[q, omega])
    assert info["success"] and info_ref["success"]
    assert info["cost"] == pytest.approx(info_ref["cost"], rel=1e-6)
    np.testing.assert_allclose(info["controls"], info_ref["controls"], atol=1e-4)
    # Warm-started second call (shifted plan, and multipliers where the solver takes them).
    _, again = other(np.r_[q, omega])
    assert again["success"]


def test_fatrop_setting_is_validated():
    from fvin_mpc.control.mpc import MPCSettings

    with pytest.raises(ValueError, match="fatrop"):
        MPCSettings(solver="fatrop")
    with pytest.raises(ValueError, match="unknown solver"):
        MPCSettings(solver="snopt")


def test_width_quick_caches_the_trained_model(tmp_path):
    from benchmarks import width

    first = width.run(quick=True)
    second = width.run(quick=True)
    assert [r["trained_now"] for r in first.rows] == [True]
    assert [r["trained_now"] for r in second.rows] == [False]
    # The cached model is the same model: same error, and the training time of the real run.
    assert second.rows[0]["rollout_angle_final_mean"] == first.rows[0]["rollout_angle_final_mean"]
    assert second.rows[0]["train_s"] == first.rows[0]["train_s"] > 0
    write_study(second, tmp_path, ["width", "--quick"])


def test_train_speed_quick(tmp_path):
    from benchmarks import train_speed

    result = train_speed.run(quick=True)
    _positive_times(result.rows, "s_per_iter_median")
    write_study(result, tmp_path, ["train-speed", "--quick"])


def test_compiled_mpc_accepts_a_model_name_with_dots():
    # Regression: checkpoint stems like "pendulum-h0.02_sign-invariant" once made an invalid C file prefix.
    from fvin_mpc.control.model_export import from_rigid_body
    from fvin_mpc.control.mpc import MPC, MPCSettings
    from fvin_mpc.core.rigid_body import PENDULUM

    model = from_rigid_body(PENDULUM, 0.02, 2, name="pendulum-h0.02_test")
    controller = MPC(model, replace(MPCSettings(), horizon=3), (0, 0, 1, 0), [-2.0], [2.0])
    assert controller.compile_report is not None
    u, info = controller(np.r_[np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3)])
    assert np.all(np.isfinite(u)) and -2.0 <= u[0] <= 2.0


# ---------------------------------------------------------------------- held-out data
def test_heldout_data_never_overwrites_a_different_set(tmp_path):
    """A file at the held-out path that holds other data is refused, not silently replaced
    (the spherical set, speed-bounded, was once overwritten by an unbounded collection)."""
    from benchmarks.common import heldout_data
    from fvin_mpc.core.data import save_data
    from fvin_mpc.learning.collection import collect

    path = tmp_path / "data" / "pendulum_heldout.npz"
    save_data(path, collect("pendulum", 2, 3, 7, progress=False))  # seed 7, not the held-out seed 1
    before = path.read_bytes()
    with pytest.raises(ValueError, match="delete it"):
        heldout_data("pendulum", seed=1, trajectories=2, steps=3, path=path)
    assert path.read_bytes() == before


def test_spherical_heldout_data_is_speed_bounded(tmp_path):
    from benchmarks.common import BOUNDED_HELDOUT, heldout_data

    path = tmp_path / "spherical.npz"
    data = heldout_data("spherical_pendulum", seed=1, trajectories=3, steps=5, path=path)
    assert data.metadata["collector"] == "speed-bounded"  # the method's name, not a module path that moves
    assert np.abs(data.omega).max() <= BOUNDED_HELDOUT["spherical_pendulum"]["max_speed"]
    again = heldout_data("spherical_pendulum", seed=1, trajectories=3, steps=5, path=path)  # loaded, not redrawn
    np.testing.assert_array_equal(again.q, data.q)


def test_flyer_report_tells_the_cold_first_periods_apart():
    """The family report counts deadline misses per model and, where the flights recorded it, how many were
    the cold first period; flights cached before that was recorded give no bracket rather than a 0."""
    from benchmarks.flyer_report import _first_period_misses, _misses_text

    def record(rows):
        flights = {"recovery": rows[:-1], "figure_eight": rows[-1]}
        return {"learned": flights, "closed_form": flights}

    recorded = record([{"deadline_misses": 2, "first_period_missed": True},
                       {"deadline_misses": 0, "first_period_missed": False},
                       {"deadline_misses": 1, "first_period_missed": False}])
    assert _first_period_misses([recorded], "learned") == 1
    assert _misses_text([recorded], "learned") == "3 (1)"
    older = record([{"deadline_misses": 2}, {"deadline_misses": 0}])
    assert _first_period_misses([older], "learned") is None
    assert _misses_text([recorded, older], "learned") == "5"
    waiting = record([{"deadline_misses": "not measured", "first_period_missed": "not measured"}] * 2)
    assert _misses_text([waiting], "learned") == "—"
