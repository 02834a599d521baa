"""The package installs from a wheel without torch and runs its main command outside the repository.

Two checks on one wheel of this checkout (``pip wheel --no-deps``, about 6 s):

* in the default suite, the wheel's contents: the shipped checkpoints and the scenes' MJCF are package
  data (``fvin_mpc/checkpoints``, ``fvin_mpc/envs/scenes``), and torch is only an extra's requirement;
* marked slow (``python -m pytest -m slow tests/test_wheel.py``), the wheel installed into a fresh
  virtual environment (its dependencies from the package index, no torch) and, from a temporary
  directory outside the repository, ``python -m fvin_mpc.swingup`` on the shipped checkpoint with the
  compiled IPOPT MPC. Measured on the shared 2-core machine: 64 s when the default compile cache
  (``~/.cache/fvin_mpc``) already holds the NLP, 127 s when it does not and the run generates and
  compiles it, as on a fresh CI machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]


def _run(command: list[str], cwd: Path, env: dict[str, str], timeout_s: float) -> subprocess.CompletedProcess:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s)
    assert result.returncode == 0, (
        f"{' '.join(command)} exited {result.returncode}:\n{result.stdout}\n{result.stderr}")
    return result


def _clean_env() -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["OMP_NUM_THREADS"] = "1"
    return env


def _source_tree(destination: Path) -> Path:
    """The checkout's files (tracked, and untracked ones git does not ignore) copied to ``destination``:
    a wheel built in the checkout itself would also pack what an earlier build left in its ignored
    ``build/`` folder (modules since moved or deleted)."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPOSITORY,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = REPOSITORY / name
        if source.is_file():
            (destination / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, destination / name)
    return destination


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    wheel_dir = tmp_path_factory.mktemp("wheel")
    source = _source_tree(tmp_path_factory.mktemp("source"))
    _run([sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "-q", "-w", str(wheel_dir)],
         cwd=wheel_dir, env=_clean_env(), timeout_s=300)
    (built,) = wheel_dir.glob("fvin_mpc-*.whl")
    return built


def test_wheel_ships_checkpoints_and_scenes_and_needs_no_torch(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        (metadata,) = [name for name in names if name.endswith(".dist-info/METADATA")]
        requirements = [line for line in archive.read(metadata).decode().splitlines()
                        if line.startswith("Requires-Dist:")]
    shipped = sorted(path.name for path in (REPOSITORY / "checkpoints").iterdir()
                     if path.suffix in (".safetensors", ".json"))
    assert shipped, "no shipped checkpoints in the repository"
    assert [name for name in shipped if f"fvin_mpc/checkpoints/{name}" not in names] == []
    scenes = sorted(path.name for path in (REPOSITORY / "envs" / "scenes").glob("*.xml"))
    assert [name for name in scenes if f"fvin_mpc/envs/scenes/{name}" not in names] == []
    # the C controller's hand-written driver, which `python -m fvin_mpc.export --controller` copies
    template = sorted(path.name for path in (REPOSITORY / "fvin_mpc" / "control" / "c_template").iterdir())
    assert template and [name for name in template if f"fvin_mpc/control/c_template/{name}" not in names] == []
    torch_requirements = [line for line in requirements if line.split()[1].lower().startswith("torch")]
    assert torch_requirements and all("extra ==" in line for line in torch_requirements), torch_requirements
    # The research studies stay in the clone: neither benchmarks/ nor the studies moved there ship.
    research = [name for name in names if name.startswith("benchmarks/") or name.endswith(
        ("/data_efficiency.py", "/mlp_baseline.py", "/pendulum_v1_reference.py", "/spherical_report.py"))]
    assert research == []
    assert {"fvin_mpc/quality.py", "fvin_mpc/studies/model_quality.py", "fvin_mpc/studies/evaluation.py"} <= names


@pytest.mark.slow
def test_wheel_installs_without_torch_and_swings_up_outside_the_repository(wheel, tmp_path):
    env = _clean_env()

    environment = tmp_path / "venv"
    venv.create(environment, with_pip=True)
    python = str(environment / "bin" / "python")
    _run([python, "-m", "pip", "install", "-q", str(wheel)], cwd=tmp_path, env=env, timeout_s=600)

    outside = tmp_path / "elsewhere"
    outside.mkdir()
    located = _run([python, "-c",
                    "import importlib.util, json, fvin_mpc\n"
                    "from fvin_mpc.core.checkpoint import CHECKPOINT_DIR\n"
                    "print(json.dumps({'package': fvin_mpc.__file__, 'checkpoints': str(CHECKPOINT_DIR),\n"
                    "                  'torch': importlib.util.find_spec('torch') is not None}))"],
                   cwd=outside, env=env, timeout_s=120)
    where = json.loads(located.stdout)
    assert where["torch"] is False, "the wheel's dependencies brought torch"
    assert Path(where["package"]).is_relative_to(environment)
    assert Path(where["checkpoints"]).is_relative_to(environment)
    assert (Path(where["checkpoints"]) / "pendulum_sign-invariant.safetensors").is_file()

    swingup = _run([python, "-m", "fvin_mpc.swingup", "--duration", "2", "--plot", "", "--quiet"],
                   cwd=outside, env=env, timeout_s=300)
    summary = json.loads(swingup.stdout)
    assert summary["model"] == "pendulum_sign-invariant"
    assert summary["true_model"] is False
    assert summary["solver"] == "ipopt"
    assert summary["solve_time_ms"]["median"] > 0
    assert list(outside.iterdir()) == [], "the command wrote into the working directory"
