"""The latency-aware closed loop: delayed torques act from the right MuJoCo sub-step, fixed-latency
episodes are deterministic, deadline misses are counted (``fvin_mpc.control.closed_loop``)."""

from __future__ import annotations

import numpy as np
import pytest

from fvin_mpc.control.closed_loop import episode_metrics, run_episode
from fvin_mpc.envs import RigidBodyEnv


class ConstantController:
    """Commands ``torque`` from the first call on; counts its calls."""

    def __init__(self, torque: float) -> None:
        self.torque, self.calls = torque, 0

    def __call__(self, x):
        self.calls += 1
        return np.array([self.torque]), {"success": True}

    def reset(self) -> None:
        self.calls = 0


class LinearController:
    """A deterministic state feedback, so that torques differ from period to period."""

    def __call__(self, x):
        return np.array([np.clip(-3.0 * x[2] - 0.5 * x[5], -2.0, 2.0)]), {"success": True}

    def reset(self) -> None:
        pass


START = {"qpos": np.array([0.4]), "qvel": np.array([0.0])}


def test_zero_fixed_latency_is_the_waiting_mode():
    env = RigidBodyEnv("pendulum")
    waiting, _ = run_episode(env, LinearController(), 1.0, START, latency="none")
    zero, _ = run_episode(env, LinearController(), 1.0, START, latency=0.0)
    np.testing.assert_array_equal(waiting.q, zero.q)
    np.testing.assert_array_equal(waiting.u, zero.u)
    assert waiting.deadline_misses == zero.deadline_misses == 0


def test_fixed_latency_is_deterministic():
    env = RigidBodyEnv("pendulum")
    first, _ = run_episode(env, LinearController(), 1.0, START, latency=0.012)
    second, _ = run_episode(env, LinearController(), 1.0, START, latency=0.012)
    np.testing.assert_array_equal(first.q, second.q)
    np.testing.assert_array_equal(first.omega, second.omega)
    assert not np.array_equal(first.q, run_episode(env, LinearController(), 1.0, START)[0].q)


def test_delayed_torque_acts_from_the_first_substep_after_the_delay():
    """Oracle: the same MJCF stepped one 5 ms sub-step at a time, zero torque for ⌈12/5⌉ = 3
    sub-steps, then the commanded torque."""
    env = RigidBodyEnv("pendulum")
    episode, _ = run_episode(env, ConstantController(1.5), 0.1, START, latency=0.012)
    fine = RigidBodyEnv("pendulum", control_period=0.005)
    observation, _ = fine.reset(options=START)
    trajectory = []
    for i in range(20):
        observation, *_ = fine.step(np.array([0.0 if i < 3 else 1.5]))
        trajectory.append(observation)
    np.testing.assert_allclose(episode.q[1], trajectory[9][:4], atol=1e-12)
    np.testing.assert_allclose(episode.omega[2], trajectory[19][4:], atol=1e-12)
    np.testing.assert_array_equal(episode.u[:, 0], [1.5, 1.5])
    assert episode.deadline_misses == 0


def test_deadline_misses_are_counted_and_observations_skipped():
    env = RigidBodyEnv("pendulum")
    controller = ConstantController(1.0)
    episode, _ = run_episode(env, controller, 1.0, START, latency=0.07)  # 70 ms > the 50 ms period
    periods = 20
    assert controller.calls == periods // 2  # busy for two periods after each observation
    assert episode.deadline_misses == periods // 2
    assert episode.skipped == periods // 2
    metrics = episode_metrics(episode)
    assert metrics["deadline_misses"] == periods // 2 and metrics["latency"] == 0.07
    assert metrics["first_period_missed"] is True  # the first call is one of them
    assert np.isfinite(metrics["solve_time_ms"]["median"])


def test_waiting_mode_summaries_do_not_claim_zero_deadline_misses():
    """With latency "none" the simulator waits for the controller: no period has a deadline, so a
    summary says the misses were not measured instead of a 0 that reads as "kept real time"."""
    from fvin_mpc.control.closed_loop import NOT_MEASURED
    from fvin_mpc.studies.evaluation import summarize

    env = RigidBodyEnv("pendulum")
    waiting, _ = run_episode(env, LinearController(), 0.5, START, latency="none")
    delayed, _ = run_episode(env, LinearController(), 0.5, START, latency=0.01)
    assert episode_metrics(waiting)["deadline_misses"] == NOT_MEASURED == "not measured"
    assert episode_metrics(waiting)["first_period_missed"] == NOT_MEASURED
    assert episode_metrics(delayed)["deadline_misses"] == 0
    assert episode_metrics(delayed)["first_period_missed"] is False

    def record(episode):
        return {"metrics": episode_metrics(episode), "controller_time_s": episode.controller_time_s,
                "feedback_time_s": episode.feedback_s, "index": 0}

    assert summarize([record(waiting)])["deadline_misses"] == NOT_MEASURED
    assert summarize([record(delayed), record(delayed)])["deadline_misses"] == 0


def test_prepare_is_called_after_each_delivered_torque():
    class Preparing(ConstantController):
        prepared = 0

        def prepare(self) -> None:
            assert self.calls == self.prepared + 1  # after the call that delivered the torque
            self.prepared += 1

    controller = Preparing(0.0)
    run_episode(RigidBodyEnv("pendulum"), controller, 0.5, START, latency="measured")
    assert controller.prepared == controller.calls == 10


def test_the_garbage_collector_stays_out_of_the_controllers_time():
    """No automatic collection inside the call or the preparation (a full one took longer than a period);
    on again between them, and as it was after the episode, with nothing left frozen."""
    import gc

    class Watching(ConstantController):
        seen: list[bool] = []

        def __call__(self, x):
            self.seen.append(gc.isenabled())
            return super().__call__(x)

        def prepare(self) -> None:
            self.seen.append(gc.isenabled())

    class Stepping(RigidBodyEnv):
        enabled: list[bool] = []

        def step(self, *args, **kwargs):
            self.enabled.append(gc.isenabled())
            return super().step(*args, **kwargs)

    controller = Watching(0.0)
    run_episode(Stepping("pendulum"), controller, 0.5, START, latency="measured")
    assert controller.seen == [False] * 20
    assert Stepping.enabled and all(Stepping.enabled)
    assert gc.isenabled() and gc.get_freeze_count() == 0


@pytest.mark.parametrize("latency", ["soon", -0.01, float("nan")])
def test_invalid_latency_raises(latency):
    with pytest.raises(ValueError):
        run_episode(RigidBodyEnv("pendulum"), ConstantController(0.0), 0.1, latency=latency)


def test_feedback_time_is_the_call_alone_and_measured_delay_uses_it():
    """The call sleeps 3 ms and the preparation 6 ms: the feedback time (the plant's delay) sees only
    the call, the whole controller time both; skipped periods have neither."""
    import time

    class Slow(ConstantController):
        def __call__(self, x):
            time.sleep(0.003)
            return super().__call__(x)

        def prepare(self) -> None:
            time.sleep(0.006)

    for latency in ("none", "measured"):
        episode, _ = run_episode(RigidBodyEnv("pendulum"), Slow(0.0), 0.5, START, latency=latency)
        assert np.all(episode.feedback_s >= 0.003) and np.all(episode.controller_time_s >= 0.009)
        assert np.all(episode.feedback_s < episode.controller_time_s - 0.005)
        if latency == "measured":
            np.testing.assert_array_equal(episode.compute_s, episode.feedback_s)
    skipping, _ = run_episode(RigidBodyEnv("pendulum"), ConstantController(0.0), 1.0, START, latency=0.07)
    assert np.isnan(skipping.feedback_s[1]) and np.isfinite(skipping.feedback_s[0])
