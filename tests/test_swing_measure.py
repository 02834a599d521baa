"""The swing measure and the swing excitation (docs/excitation.md): checked against independent references."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fvin_mpc.core import s3
from fvin_mpc.core.rigid_body import from_mujoco
from fvin_mpc.envs import RigidBodyEnv
from fvin_mpc.learning.excitation import SwingPhysics, collect_swings
from fvin_mpc.learning.swing_measure import closed_form_step, rigid_body_step, swing_apex_error, swing_probe

DAMPED = str(Path(__file__).resolve().parent / "data" / "damped_point_pendulum.xml")


def test_the_closed_form_swings_as_mujoco_does_and_wrong_damping_does_not():
    # At the MJCF's own 20 ms (the scene's default period is coarser): apexes resolved to a few degrees.
    probe = swing_probe(DAMPED, control_period=0.02)
    # The plant's swings span the last climb: some stop well short of upright, some pass over it.
    assert probe.plant_apex.max() > np.radians(20.0) and probe.plant_apex.min() < np.radians(3.0)
    true = swing_apex_error(closed_form_step(DAMPED, control_period=0.02), probe)
    assert true["swing_energy_error"] < 0.01
    env = RigidBodyEnv(DAMPED, control_period=0.02)
    body = from_mujoco(env.unwrapped.model, env.unwrapped.body_name)
    for factor in (0.7, 1.3):  # the learned damping of docs/excitation.md's pendulum was 20–40 % low
        wrong = swing_apex_error(rigid_body_step(replace(body, damping=factor * body.damping), env.unwrapped.dt),
                                 probe)
        assert wrong["swing_energy_error"] > 3.0 * true["swing_energy_error"]
    # Less damping: the model believes the climb easier than it is and ends nearer upright.
    weak = swing_apex_error(rigid_body_step(replace(body, damping=0.7 * body.damping), env.unwrapped.dt), probe)
    stops_short = probe.plant_apex > np.radians(10.0)
    assert np.all(np.array(weak["model_apex_deg"])[stops_short] < np.degrees(probe.plant_apex[stops_short]))


def test_the_swing_excitation_reaches_the_energy_span_under_saturated_controls():
    data = collect_swings(DAMPED, trajectories=20, seed=3, progress=False)
    coverage = data.metadata["energy_coverage"]
    assert coverage["max"] >= 1.2 and coverage["p95"] >= 1.0  # in units of the hanging-to-upright span
    assert data.metadata["saturated_share"] > 0.3
    # Recompute the energies from the states with the closed form (not the collector's own numbers).
    env = RigidBodyEnv(DAMPED)
    physics = SwingPhysics(env)
    q, omega = data.state[..., :4].reshape(-1, 4), data.state[..., 4:].reshape(-1, 3)
    energy = np.array([physics.potential(a) - physics.rest_energy + 0.5 * b @ physics.inertia(a) @ b
                       for a, b in zip(q, omega)]) / physics.scales.energy_span
    assert energy.max() == pytest.approx(coverage["max"])
    # Near upright (within 0.3 rad) and at every height in between.
    angles = s3.geodesic_angles(q, env.unwrapped.goal)
    assert (angles < 0.3).mean() > 0.02
    assert np.histogram(angles, bins=6, range=(0, np.pi))[0].min() > 0


def test_selection_returns_the_lowest_measure_within_the_validation_tolerance():
    from fvin_mpc.core.networks import ModelConfig
    from fvin_mpc.learning.training import TrainSettings, train

    data = collect_swings(DAMPED, trajectories=8, steps=12, seed=0, progress=False)
    config = ModelConfig(step_size=data.control_period, hidden_width=4, dissipation=True)
    calls = []

    def measure(model):  # an independent record: the measure of each evaluation, in order
        calls.append(float(model.numpy_weights()[next(iter(model.weights))].sum()))
        return [5.0, 4.0, 1.0, 3.0, 2.0, 6.0][len(calls) - 1]

    settings = TrainSettings(optimizer="adam", iterations=6, eval_every=1, patience=0, selection_tolerance=1e9)
    model, report = train(data, config, settings, progress=False, measure=measure)
    assert [h["measure"] for h in report["history"]] == [5.0, 4.0, 1.0, 3.0, 2.0, 6.0][:len(report["history"])]
    chosen = report["selected"]
    best = min(report["history"], key=lambda h: h["measure"])
    assert chosen["iteration"] == best["iteration"] and chosen["measure"] == best["measure"]
    assert float(model.numpy_weights()[next(iter(model.weights))].sum()) == pytest.approx(calls[best["iteration"] - 1])
    strict = train(data, config, replace(settings, selection_tolerance=0.0), progress=False,
                   measure=lambda model: 0.0)[1]["selected"]
    assert strict["iteration"] == strict["best_validation_iteration"]


def test_collect_then_train_with_defaults_records_the_swing_measure(tmp_path, capsys):
    from fvin_mpc import collect, train

    data = tmp_path / "d.npz"
    arguments = ["--scene", DAMPED, "--trajectories", "10", "--steps", "24", "--out", str(data), "--quiet"]
    assert collect.main(arguments) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["collector"] == "swing-excitation" and out["transitions"] == 240
    assert train.main(["--data", str(data), "--out", str(tmp_path / "m"), "--iterations", "3", "--quiet",
                       "--hidden-width", "8"]) == 0
    summary = json.loads(capsys.readouterr().out)
    metadata = json.loads((tmp_path / "m.json").read_text())
    swing = metadata["training"]["swing"]
    assert summary["swing_energy_error"] == swing["swing_energy_error"] >= 0.0
    assert len(swing["model_apex_deg"]) == len(swing["plant_apex_deg"]) == 12
    assert metadata["training"]["selected"]["by"] == "measure"


def test_the_divergence_audit_passes_resolved_swings_and_catches_energy_the_controls_did_not_put_in():
    from fvin_mpc.learning.excitation import DIVERGENCE_TOLERANCE

    data = collect_swings(DAMPED, trajectories=10, seed=4, progress=False)
    physics = SwingPhysics(RigidBodyEnv(DAMPED))
    audits = [physics.divergence(states, controls) for states, controls in zip(data.state, data.u)]
    assert max(audits) < 0.1 * DIVERGENCE_TOLERANCE
    # A hanging body whose speed grows by 20 % a period under zero torque: every joule is the integrator's.
    grown = np.zeros((12, 7))
    grown[:, :4] = physics.env.unwrapped.rest
    grown[:, 4:] = np.outer(1.2 ** np.arange(12), [0.0, 0.3 * physics.scales.speed, 0.0])
    assert physics.divergence(grown, np.zeros((11, data.u.shape[-1]))) > 1.0
    # Full torque along the motion could have put that energy in: not a divergence.
    assert physics.divergence(grown[:3], np.full((2, data.u.shape[-1]), 1e3)) <= 0.0


def test_a_ball_scene_whose_first_data_diverged_is_collected_within_the_energy_band(tmp_path):
    from fvin_mpc.envs.families import write_family
    from fvin_mpc.learning.excitation import DIVERGENCE_TOLERANCE, MAX_ENERGY, START_SPEED_CAP, energy_spread_state

    # Report member 9012: a point mass at 1:30 about its long axis on 2 motors, whose first data set
    # spun up to 680 rad/s in MuJoCo's implicitfast steps (energy ×10⁴ in 33 periods) and reached 13
    # energy spans at the 95th percentile.
    (scene,) = write_family("ball", [9012], tmp_path)
    data = collect_swings(str(scene), seed=0, progress=False)
    env = RigidBodyEnv(str(scene))
    physics = SwingPhysics(env)
    assert max(physics.divergence(s, u) for s, u in zip(data.state, data.u)) <= DIVERGENCE_TOLERANCE
    assert np.abs(data.omega).max() < 10.0 * physics.scales.speed
    coverage = data.metadata["energy_coverage"]
    assert coverage["p95"] <= 1.5 * MAX_ENERGY and coverage["max"] >= 1.0  # the band, and the swing-up's span
    rng = np.random.default_rng(0)
    speeds = [np.linalg.norm(energy_spread_state(env, physics, rng)[1]) for _ in range(50)]
    assert max(speeds) <= START_SPEED_CAP * physics.scales.speed * (1 + 1e-12)


def test_diverged_trajectories_are_replaced_and_a_scene_that_always_diverges_is_refused(monkeypatch):
    from fvin_mpc.learning import excitation

    audits = iter([1.0, 1.0, 0.0] + [0.0] * 100)  # the first start's trajectory diverges twice
    monkeypatch.setattr(excitation.SwingPhysics, "divergence", lambda self, states, controls: next(audits))
    with pytest.warns(UserWarning, match="replaced 2 of 10 trajectories"):
        data = collect_swings(DAMPED, trajectories=10, seed=4, progress=False)
    assert data.metadata["diverged_trajectories"] == 2 and data.num_trajectories == 10
    monkeypatch.setattr(excitation.SwingPhysics, "divergence", lambda self, states, controls: 1.0)
    with pytest.raises(RuntimeError, match="timestep"):
        collect_swings(DAMPED, trajectories=10, seed=4, progress=False)
