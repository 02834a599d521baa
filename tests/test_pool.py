"""The one execution backend (fvin_mpc.studies.pool.run_tasks): results in task order, failures
reported with their inputs while the other tasks finish, and the same results on a real local Ray
cluster as on the local process pool."""

import math

import numpy as np
import pytest

import fvin_mpc.studies.evaluation as ev
from fvin_mpc.studies.pool import TasksFailed, ray_session, run_tasks

#: Episode metrics that do not depend on timing (solve and CPU times do).
DETERMINISTIC_METRICS = ("success", "swung_up", "time_to_upright_s", "hold_error_rad", "controller_failures",
                         "skipped_observations", "max_abs_torque", "accumulated_cost")


@pytest.fixture(scope="session")
def ray_cluster():
    """A real local Ray cluster (2 CPUs, no dashboard) shared by this test process's Ray tests; under
    ``pytest -n 2`` each xdist worker starts its own (Ray picks free ports)."""
    with ray_session(num_cpus=2) as ray:
        yield ray


BACKENDS = [("process", 1), ("process", 2), ("ray", 2)]


@pytest.mark.parametrize("backend, workers", BACKENDS, ids=[f"{b}-{w}" for b, w in BACKENDS])
def test_results_in_task_order_and_a_failure_reported_with_its_inputs(backend, workers, request):
    if backend == "ray":
        request.getfixturevalue("ray_cluster")
    tasks = [(float(i * i),) for i in range(8)] + [(-1.0,)] + [(float(i * i),) for i in range(8, 11)]
    with pytest.raises(TasksFailed) as failed:
        run_tasks(math.sqrt, tasks, workers=workers, progress=False, backend=backend)
    error = failed.value
    assert error.results == [float(i) for i in range(8)] + [None] + [8.0, 9.0, 10.0]  # the rest ran, in order
    assert [(f.index, f.inputs) for f in error.failures] == [(8, (-1.0,))]
    assert error.failures[0].error == "ValueError: math domain error"
    assert "1 of 12 tasks failed" in str(error) and "task 8 (-1.0,)" in str(error)


def test_ray_runs_every_task_on_a_few_actors_in_order(ray_cluster):
    assert run_tasks(math.sqrt, [(float(i * i),) for i in range(20)], workers=2, progress=False,
                     backend="ray") == [float(i) for i in range(20)]


def test_bad_arguments():
    with pytest.raises(ValueError, match="workers"):
        run_tasks(math.sqrt, [(1.0,)], workers=0)
    with pytest.raises(ValueError, match="backend"):
        run_tasks(math.sqrt, [(1.0,)], backend="dask")


def test_evaluation_on_ray_equals_the_local_pool_per_seed(ray_cluster):
    config = ev.EvaluationConfig(episodes=3, duration_s=4.0, controllers=("energy-true", "zero"), seed=5)
    local = ev.evaluate(config, workers=2, progress=False)
    on_ray = ev.evaluate(config, workers=2, progress=False, backend="ray")
    assert local.summary["energy-true"]["successes"] >= 1  # not a trivial comparison
    for a, b in zip(local.episodes, on_ray.episodes, strict=True):
        assert (a["index"], a["seed"], a["q0"], a["omega0"]) == (b["index"], b["seed"], b["q0"], b["omega0"])
        for name in config.controllers:
            assert {k: a["results"][name][k] for k in DETERMINISTIC_METRICS} == \
                   {k: b["results"][name][k] for k in DETERMINISTIC_METRICS}
    for name in config.controllers:  # whole trajectories, bit for bit
        for x, y in zip(local.trajectories[name], on_ray.trajectories[name], strict=True):
            np.testing.assert_array_equal(x["angle"], y["angle"])
            np.testing.assert_array_equal(x["rate"], y["rate"])


def test_evaluation_task_that_raises_is_reported_and_the_others_complete(ray_cluster):
    config = ev.EvaluationConfig(episodes=2, duration_s=1.0, controllers=("zero",), seed=0)
    starts = ev.episode_starts(config)
    tasks = [("zero", starts[0]), ("no-such-controller", starts[1]), ("zero", starts[1])]
    with pytest.raises(TasksFailed) as failed:
        run_tasks(ev.run_task, tasks, ev._init_worker, (config,), workers=2, progress=False, backend="ray")
    results, failures = failed.value.results, failed.value.failures
    assert [r is None for r in results] == [False, True, False]
    assert [r["index"] for r in results if r is not None] == [0, 1]
    assert failures[0].inputs == tasks[1] and "unknown controller 'no-such-controller'" in failures[0].error


def test_cli_ray_address_needs_the_ray_backend(capsys, tmp_path):
    from fvin_mpc.evaluate import main

    assert main(["--episodes", "1", "--ray-address", "auto", "--out-dir", str(tmp_path)]) == 2
    assert "--ray-address needs --backend ray" in capsys.readouterr().err
