"""3-D model quality: held-out rollouts and the recovered inertia, ``python -m fvin_mpc.inertia``.

For a checkpoint of a body on a ball joint (scene ``spherical_pendulum``), against the closed-form
body read off the scene's MJCF (:func:`fvin_mpc.core.rigid_body.from_mujoco`):

* **Held-out rollouts** — open loop from unseen initial states under the recorded torques, geodesic
  angle error and ‖Δω‖ (:func:`fvin_mpc.studies.quality.rollout_error`), with the closed-form model through
  the same FVIN step as the floor (its error is the integrator's, not the learning's).
* **Scale** — ``(J, U, g) → λ(J, U, g)`` leaves the dynamics unchanged, so λ is fixed first, by least
  squares on the control gain over orientations uniform on S³: ``λ = Σ⟨g_learned, g_true⟩ / Σ‖g_true‖²``
  with ``g_true = 2·B`` (``B`` the actuators' torque axes; ``2·I₃`` here, ``DESIGN.md`` factor of two).
* **Inertia** — ``J(q)/λ`` at those orientations: its mean, the principal moments (eigenvalues) and
  principal axes (eigenvectors, angle to the true axes, sign-free) of the mean against the MJCF's
  inertia about the pivot, and how much the learned ``J`` varies with ``q`` (it is constant in truth).
* **Potential and gain** — ``U/λ`` (relative to hanging) and ``g/λ`` against the true ones.
* **Energy** — unforced rollouts from random states: relative drift of the learned energy
  and of the true energy of the predicted states.
"""

from __future__ import annotations
import argparse
import json
from pathlib import Path
from fvin_mpc.core.data import load_data
from fvin_mpc.studies.inertia import report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fvin_mpc.inertia", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", nargs="+", default=["spherical_pendulum_sign-invariant"],
                        help="one or more shipped names or paths (default: %(default)s)")
    parser.add_argument("--data", type=Path, default=Path("data/spherical_pendulum_heldout.npz"),
                        help="held-out trajectories (default: %(default)s)")
    parser.add_argument("--horizon", type=int, default=20, help="rollout steps (default: %(default)s = 1 s at h = 0.05)")
    parser.add_argument("--samples", type=int, default=512, help="orientations for the component comparison")
    parser.add_argument("--energy-steps", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0, help="seeds the sampled orientations and energy states")
    parser.add_argument("--json", type=Path, default=None, help="write the reports (a list) as JSON")
    args = parser.parse_args(argv)
    data = load_data(args.data)
    reports = []
    for name in args.checkpoint:
        result = report(name, data, args.horizon, args.samples, args.energy_steps, args.seed)
        for part in result["rollout"].values():
            part.pop("angle_error_per_step_mean", None)
        reports.append(result)
    text = json.dumps(reports if len(reports) > 1 else reports[0], indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(reports, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
