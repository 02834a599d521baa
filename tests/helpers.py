"""Synthetic trajectories of a closed-form body, for training tests that must not need MuJoCo data."""

import numpy as np

from fvin_mpc.core import fvin
from fvin_mpc.core.backend import get_ops
from fvin_mpc.core.data import TrajectoryData

NP = get_ops("numpy")


def synthetic_hinge_data(body, trajectories=48, steps=10, seed=0):
    """Hinge-about-y trajectories of ``body`` integrated with 20 FVIN substeps per 0.05 s period
    (a finer integrator than the model being trained), random angles, rates and torques."""
    rng = np.random.default_rng(seed)
    terms = body.terms(NP)
    theta, omega0 = rng.uniform(-np.pi, np.pi, trajectories), rng.uniform(-5, 5, trajectories)
    u = rng.uniform(-2, 2, (trajectories, steps, 1))
    zero = 0 * theta
    q, omega = (np.cos(theta / 2), zero, np.sin(theta / 2), zero), (zero, omega0, zero)
    qs, omegas = [np.stack(q, -1)], [np.stack(omega, -1)]
    for k in range(steps):
        for _ in range(20):
            out = fvin.fvin_step(q, omega, (u[:, k, 0],), terms, 0.0025, 4, NP)
            q, omega = out.q, out.omega
        qs.append(np.stack(q, -1))
        omegas.append(np.stack(omega, -1))
    return TrajectoryData(np.stack(qs, 1), np.stack(omegas, 1), u, {"control_period": 0.05, "scene": "synthetic"})
