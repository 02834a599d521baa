"""The learned-DP swing-up for Pendulum-v1 (``--dp-swing-up``): greedy policy, handover, choice by simulation."""

import numpy as np
import pytest

from benchmarks import pendulum_v1_exact as exact
from benchmarks import pendulum_v1_mpc as v1
from benchmarks import pendulum_v1_plan as plan
from benchmarks import pendulum_v1_value as pv
from benchmarks.pendulum_v1_report import build_parser, main
from fvin_mpc.control import model_export as export
from fvin_mpc.core.rigid_body import PENDULUM
from fvin_mpc.envs.pendulum_v1 import state_from_v1_observation


@pytest.fixture(scope="module")
def true_model():
    return export.from_rigid_body(PENDULUM, 0.05, 2, name="test_plan_true_pendulum")


@pytest.fixture(scope="module")
def true_value(true_model):
    """The true pendulum's value for Pendulum-v1's cost on a coarse grid (DP as the learned model's)."""
    torques = np.linspace(-2.0, 2.0, 11)
    next_theta, next_rate = pv.learned_transitions(true_model, *pv.grid_axes(64, 33), torques)
    return pv.value_iteration(next_theta, next_rate, torques, 120)


def v1_state(theta, theta_dot):
    return state_from_v1_observation([np.cos(theta), np.sin(theta), theta_dot])


class RecordingMPC:
    """Stands in for the MPC: a constant torque, counting its calls and resets."""

    def __init__(self, torque=0.0):
        self.torque, self.calls, self.resets = torque, 0, 0

    def __call__(self, x):
        self.calls += 1
        return np.array([self.torque]), {"success": True}

    def reset(self):
        self.resets += 1


class CatchingMPC(RecordingMPC):
    """Stands in for the MPC near upright: a saturated PD law on Pendulum-v1's angle (it cannot swing up)."""

    def __call__(self, x):
        self.calls += 1
        theta, rate = plan.v1_angles(x)
        return np.clip([-(20.0 * theta[0] + 5.0 * rate[0])], -2.0, 2.0), {"success": True}


def test_caught_is_the_upright_region_with_wrapped_angles():
    assert plan.caught(np.array([3.0, 0.1]), np.array([0.0, 1.0]))
    assert plan.caught(np.array([2 * np.pi + 0.1]), np.array([-1.0]))  # θ wraps to 0.1
    assert not plan.caught(np.array([0.1]), np.array([2.0]))  # too fast
    assert not plan.caught(np.array([np.pi, 0.5]), np.array([0.0, 0.0]))


def test_greedy_torque_is_the_argmin_over_the_models_steps(true_model):
    thetas, rates = pv.grid_axes(32, 17)
    table = 5.0 * (1 - np.cos(thetas))[:, None] + 0.3 * rates[None, :] ** 2 + 0.2 * np.sin(thetas)[:, None] * rates
    controller = plan.DPSwingUpController(RecordingMPC(), true_model, table, torques=21, lookahead=3)
    for theta, theta_dot in [(2.5, 0.3), (-1.0, 2.0), (0.4, -3.0)]:
        x = v1_state(theta, theta_dot)
        u, next_state = controller.greedy_torque(x)
        totals = []
        for torque in controller.torques:
            x_next = true_model(x, np.array([torque]))[0]
            next_theta, next_rate = plan.v1_angles(x_next)
            totals.append(
                float(exact.v1_cost(theta, theta_dot, torque)) + float(pv.interpolate(table, next_theta, next_rate)[0])
            )
        assert u == pytest.approx(controller.torques[int(np.argmin(totals))])
        np.testing.assert_allclose(next_state, true_model(x, np.array([u]))[0], atol=1e-12)
    with pytest.raises(ValueError):
        plan.DPSwingUpController(RecordingMPC(), true_model, table, lookahead=0)


def test_greedy_rollout_is_a_model_trajectory_within_the_bounds(true_model, true_value):
    controller = plan.DPSwingUpController(RecordingMPC(), true_model, true_value, lookahead=5)
    states, controls = controller.greedy_rollout(v1_state(np.pi - 0.05, 0.0), 40)
    assert states.shape == (41, 7) and controls.shape == (40,)
    assert np.all(np.abs(controls) <= 2.0)
    np.testing.assert_allclose(states, true_model.rollout(states[0], controls[:, None]), atol=1e-10)
    # From near hanging the value's policy pumps: the speed grows beyond what one push gives.
    assert np.abs(plan.v1_angles(states)[1]).max() > 2.0


def test_swing_up_hands_over_to_the_mpc_once_caught(true_model, true_value):
    mpc = RecordingMPC(torque=0.7)
    controller = plan.DPSwingUpController(mpc, true_model, true_value, lookahead=10)
    near_upright = v1_state(0.05, 0.0)
    assert controller.hands_over_at_once(near_upright)
    u, info = controller(near_upright)
    assert u[0] == 0.7 and info["phase"] == "mpc" and mpc.calls == 1
    controller.reset()
    hanging = v1_state(np.pi - 0.05, 0.0)
    assert not controller.hands_over_at_once(hanging)
    u, info = controller(hanging)
    assert info["phase"] == "dp" and mpc.calls == 1 and abs(u[0]) <= 2.0
    # The swing-up phase on the model ends in the MPC's hands.
    state, phases = hanging, []
    for _ in range(150):
        u, info = controller(state)
        phases.append(info["phase"])
        state = true_model(state, u)[0]
    assert phases[0] == "dp" and phases[-1] == "mpc"
    assert phases.index("mpc") > 0 and all(p == "mpc" for p in phases[phases.index("mpc"):])


def test_simulated_episode_cost_is_the_summed_v1_cost(true_model):
    x0 = v1_state(1.0, -0.5)
    total, controls = plan.simulate_episode_cost(RecordingMPC(torque=5.0), true_model, x0, 12)
    assert np.all(controls == 2.0)  # clipped to the bound
    expected, state = 0.0, x0
    for u in controls:
        theta, rate = plan.v1_angles(state)
        expected += float(exact.v1_cost(theta[0], rate[0], u))
        state = true_model(state, np.array([u]))[0]
        state[4:] = np.clip(state[4:], -8.0, 8.0)
    assert total == pytest.approx(expected, rel=1e-12)


def test_choice_runs_the_candidate_cheapest_on_the_model(true_model):
    pushes = {"left": RecordingMPC(-2.0), "none": RecordingMPC(0.0), "right": RecordingMPC(2.0)}
    x0 = v1_state(0.3, 0.0)  # near upright, falling: the three constant torques cost differently
    costs = {name: plan.simulate_episode_cost(c, true_model, x0, 30)[0] for name, c in pushes.items()}
    chooser = plan.SimulatedChoiceController(pushes, true_model, 30)
    u, info = chooser(x0)
    assert info["choice"] == min(costs, key=costs.get) and u[0] == pushes[info["choice"]].torque
    assert info["simulated_costs"] == pytest.approx(costs)
    assert chooser(x0)[0][0] == u[0]  # later calls: the chosen candidate
    chooser.reset()
    assert chooser.choice is None
    # A candidate that acts as another is not simulated; one distinct candidate needs no simulation.
    twin = plan.SimulatedChoiceController(
        pushes, true_model, 30, same_as=lambda name, x: None if name == "none" else "none"
    )
    before = {name: c.calls for name, c in pushes.items()}
    _, info = twin(x0)
    assert info["choice"] == "none" and info["simulated_costs"] == {}
    assert {name: c.calls - before[name] for name, c in pushes.items()} == {"left": 0, "none": 1, "right": 0}
    # The first candidate is the default: another runs only if cheaper by more than the margin.
    default = min(costs, key=costs.get)
    ordered = {"other": pushes[max(costs, key=costs.get)], "best": pushes[default]}
    gap = max(costs.values()) - costs[default]
    assert plan.SimulatedChoiceController(ordered, true_model, 30, margin=0.5 * gap)(x0)[1]["choice"] == "best"
    assert plan.SimulatedChoiceController(ordered, true_model, 30, margin=2.0 * gap)(x0)[1]["choice"] == "other"
    with pytest.raises(ValueError):
        plan.SimulatedChoiceController({}, true_model, 30)
    with pytest.raises(ValueError):
        plan.SimulatedChoiceController(pushes, true_model, 30, margin=-1.0)


def test_swing_up_controller_never_does_worse_on_the_model_than_the_plain_mpc(true_model, true_value):
    """The choice simulates the plain MPC too: from any start the chosen candidate's simulated cost is at
    most the plain MPC's, and from near upright (handover at once) nothing is simulated."""
    mpc = CatchingMPC()
    controller = plan.swing_up_controller(mpc, true_model, true_value, lookaheads=(10, 20), simulated_steps=60,
                                          margin=0.0)
    for theta in (np.pi - 0.1, 0.05):
        controller.reset()
        _, info = controller(v1_state(theta, 0.0))
        costs = info["simulated_costs"]
        if theta == 0.05:
            assert costs == {} and info["choice"] == "mpc"
        else:
            assert set(costs) == {"mpc", "dp-swing-up-10", "dp-swing-up-20"}
            assert costs[info["choice"]] <= costs["mpc"]
            assert info["choice"] != "mpc"  # the PD law never swings up: the DP's pumping is cheaper
    with pytest.raises(ValueError):
        plan.swing_up_controller(mpc, true_model, true_value, lookaheads=())


def test_swing_up_config_and_cli_flags_are_checked():
    with pytest.raises(ValueError):
        plan.SwingUpConfig(dp_lookaheads=(0,))
    with pytest.raises(ValueError):
        plan.SwingUpConfig(true_model=True)
    with pytest.raises(ValueError):
        plan.SwingUpConfig(dp_choice_margin=-1.0)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--dp-swing-up", "--dp-lookahead", "0"])
    assert build_parser().parse_args(["--dp-swing-up", "--dp-lookahead", "30,40"]).dp_lookahead == (30, 40)
    assert main(["--dp-lookahead", "30", "--no-reference", "--episodes", "1", "--quiet"]) != 0  # needs --dp-swing-up


@pytest.mark.slow
def test_on_seed_53_the_learned_swing_up_is_chosen_and_beats_the_plain_mpc_on_the_plant():
    """The case the swing-up is for: from near hanging (seed 53) the plain MPC's cold call takes an extra
    swing. On the learned model the swing-up simulates cheaper by more than the margin, and on Pendulum-v1
    its episode's return beats the plain MPC's."""
    import gymnasium

    config = plan.SwingUpConfig(episodes=1, seed=53, reference=False, terminal_energy_weight=3000.0,
                                rank_cold_starts=True)
    controller = plan.build_swing_up_controller(config)
    env = gymnasium.make("Pendulum-v1")
    swing_up = v1.run_v1_episode(env, controller, 53)
    costs = controller.simulated_costs
    assert controller.choice == "dp-swing-up-30"
    assert costs["dp-swing-up-30"] < costs["mpc"] - config.dp_choice_margin
    plain = v1.run_v1_episode(env, controller.candidates["mpc"], 53)
    assert np.all(np.abs(swing_up["controls"]) <= 2.0)
    assert swing_up["upright_at_end"] and swing_up["return"] > plain["return"] + 10.0
