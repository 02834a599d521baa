"""The S³ pendulums' real-time MPC before and after the R³ × S³ generalization, in one run.

``python docs/quadrotor/before_after.py --before ee4f73a`` loads ``fvin_mpc/control/rti.py`` as it was at
``--before`` (``git show``) beside the current one, records one swing-up per scene and model with the
current controller (fixed 10 ms latency, generous cold budget: deterministic), then replays its
measured states through both controllers alternately, call by call, and reports the CPU time per
call (feedback + preparation, ``time.thread_time``) and whether the two gave the same controls.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fvin_mpc.control.closed_loop import run_episode
from fvin_mpc.control.scene import scene_env, scene_model, scene_mpc_settings


def load_before(revision: str):
    source = subprocess.run(["git", "show", f"{revision}:fvin_mpc/control/rti.py"], capture_output=True, text=True,
                            check=True).stdout
    path = Path(tempfile.mkdtemp()) / "rti_before.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("rti_before", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--before", default="ee4f73a", help="git revision of the earlier rti.py")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    from fvin_mpc.control import rti as after

    before = load_before(args.before)
    print(
        "| scene | model | calls | before: CPU ms median / p90 | after: CPU ms median / p90 | after / before | same "
        "controls |"
    )
    print("|---|---|---|---|---|---|---|")
    for scene in ("pendulum", "spherical_pendulum"):
        for learned in (True, False):
            env = scene_env(scene, true_model=not learned)
            model = scene_model(env, true_model=not learned)
            settings = scene_mpc_settings(env, solver="rti", rti={"cold_budget_s": 60.0})
            base = env.unwrapped
            controllers = {
                name: module.RealTimeMPC(model, settings, base.goal, base.torque_low, base.torque_high, rest=base.rest)
                for name, module in (("before", before), ("after", after))
            }
            episode, _ = run_episode(env, controllers["after"], 6.0, latency=0.01)
            times = {name: [] for name in controllers}
            controls = {name: [] for name in controllers}
            for _ in range(args.repeats):
                for controller in controllers.values():
                    controller.reset()
                for x in episode.states[:-1]:
                    for name, controller in controllers.items():
                        start = time.thread_time()
                        u, _ = controller(x)
                        controller.prepare()
                        times[name].append(time.thread_time() - start)
                        controls[name].append(u)
            calls = len(episode.states) - 1
            cpu = {name: 1e3 * np.array(values).reshape(args.repeats, calls)[:, 1:] for name, values in times.items()}
            same = np.array_equal(np.array(controls["before"]), np.array(controls["after"]))
            b, a = (np.median(cpu[name]) for name in ("before", "after"))
            print(
                f"| {scene} | {'learned' if learned else 'closed form'} | {calls - 1} × {args.repeats} | "
                f"{b:.3f} / {np.percentile(cpu['before'], 90):.3f} | {a:.3f} / {np.percentile(cpu['after'], 90):.3f} | "
                f"{a / b:.3f} | {same} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
