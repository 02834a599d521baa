import os

# Headless rendering for every test that touches MuJoCo's renderer.
os.environ.setdefault("MUJOCO_GL", "egl")
# One BLAS/OpenMP thread per test process: `pytest -n 2` already fills both cores, and
# oversubscribed torch threads spin-wait each other to a crawl.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402
import strategies  # noqa: E402  (tests/strategies.py; tests/ is on sys.path via this conftest)
from hypothesis import HealthCheck, settings  # noqa: E402

# ----------------------------------------------------------------------------- hypothesis profiles
# ci (default): derandomized, so every CI run checks the same examples and a failure reproduces
#   from the log alone (the falsifying example is printed, plus a @reproduce_failure blob); no
#   example database is written into the checkout. Budgets are set per test (strategies.budget).
# thorough: random seeds, 10× the examples, database on — for a deliberate bug hunt:
#   HYPOTHESIS_PROFILE=thorough python -m pytest tests/hard_cases -n 2
# dev: 0.1× the examples, for quick iteration on the suite itself.
_COMMON = dict(deadline=None, print_blob=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("ci", derandomize=True, database=None, **_COMMON)
settings.register_profile("thorough", derandomize=False, **_COMMON)
settings.register_profile("dev", derandomize=True, database=None, **_COMMON)
settings.load_profile(strategies.profile_name())


# ----------------------------------------------------------------------------- generated-case count
def pytest_configure(config):
    config._hypothesis_cases_from_workers = 0


def pytest_sessionfinish(session):
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:  # an xdist worker: report to the controller
        workeroutput["hypothesis_cases"] = strategies.CASES["count"]


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    output = getattr(node, "workeroutput", None) or {}
    node.config._hypothesis_cases_from_workers += int(output.get("hypothesis_cases", 0))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    total = strategies.CASES["count"] + getattr(config, "_hypothesis_cases_from_workers", 0)
    if total:
        terminalreporter.write_line(f"hypothesis: {total} generated cases (profile {strategies.profile_name()})")
