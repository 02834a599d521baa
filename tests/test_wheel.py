"""The package installs from a wheel without torch and runs its main command outside the repository.

Builds a wheel of this checkout (``pip wheel --no-deps``), installs it into a fresh virtual environment
(its dependencies from the package index, no torch), and from a temporary directory outside the
repository runs ``python -m fvin_mpc.swingup`` on the shipped checkpoint, which the wheel carries as
package data (``fvin_mpc/checkpoints``), with the compiled IPOPT MPC. The compile cache is the
default one (``~/.cache/fvin_mpc``), as a user would have it; when that cache does not hold this
NLP yet, the run also generates and compiles it (15–30 s more).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import venv
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]


def _run(command: list[str], cwd: Path, env: dict[str, str], timeout_s: float) -> subprocess.CompletedProcess:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s)
    assert result.returncode == 0, f"{' '.join(command)} exited {result.returncode}:\n{result.stdout}\n{result.stderr}"
    return result


def test_wheel_installs_without_torch_and_swings_up_outside_the_repository(tmp_path):
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["OMP_NUM_THREADS"] = "1"

    wheel_dir = tmp_path / "wheel"
    _run([sys.executable, "-m", "pip", "wheel", str(REPOSITORY), "--no-deps", "-q", "-w", str(wheel_dir)],
         cwd=tmp_path, env=env, timeout_s=300)
    (wheel,) = wheel_dir.glob("fvin_mpc-*.whl")

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
