"""fvin_mpc — learned forced variational integrators on S³ (S3FVIN) for model-based control.

Layers, each importing only those above it in this list (``tests/test_layers.py`` reads the
imports and holds the line):

* :mod:`fvin_mpc.core` — the math, written once for NumPy, torch and CasADi: ``backend`` (the only
  backend-specific code), ``s3`` (quaternion algebra), ``fvin`` (the forced step), ``fvin_r3s3`` (translation and rotation
  together) and ``quadrotor``, ``networks``
  (learned ``J``, ``U``, ``g``, ``D``), ``rigid_body`` (closed-form bodies, read off an MJCF),
  ``state`` (the state ``x = (q, ω)`` and its validator), ``checkpoint``, ``data``.
* :mod:`fvin_mpc.envs` — Gymnasium environments over MuJoCo scenes and the scene declarations
  (the repository's ``envs/`` folder, installed under this name).
* :mod:`fvin_mpc.learning` — data collection, the torch model, training: the only torch importers.
* :mod:`fvin_mpc.control` — ``export`` (CasADi function, compile cache), ``mpc`` (IPOPT MPC with
  multi-start), ``energy_shaping``, ``closed_loop`` (episodes and metrics), ``scene`` (the model,
  MPC and settings a scene calls for — the one path every command takes). No torch.
* :mod:`fvin_mpc.studies` — evaluation, Pendulum-v1, model quality, inertia, the spherical study,
  the accuracy-vs-time studies (``studies.bench``, written by ``studies.report``), one process pool
  (``studies.pool``) and one episode-start generator (``studies.starts``).

The top-level modules are the commands, thin over the library: ``python -m fvin_mpc.swingup``,
``fly`` (the quadrotor's recovery and figure-eight), ``collect``, ``train``, ``export``, ``evaluate``,
``pendulum_v1``, ``quality``, ``inertia``, ``spherical_report``, ``sweep`` and ``bench``.
"""

__version__ = "0.1.0"
