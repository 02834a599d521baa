"""fvin_mpc — learned forced variational integrators on S³ (S3FVIN) for model-based control.

Layers (each imports only the ones above it):

* :mod:`fvin_mpc.backend`, :mod:`fvin_mpc.s3`, :mod:`fvin_mpc.fvin` — the S³ algebra and
  the FVIN step, written once for NumPy, torch and CasADi.
* :mod:`fvin_mpc.networks`, :mod:`fvin_mpc.rigid_body` — learned and closed-form ``J``, ``U``, ``g``.
* :mod:`fvin_mpc.checkpoint`, :mod:`fvin_mpc.data` — safetensors checkpoints, trajectory files.
* :mod:`fvin_mpc.model`, :mod:`fvin_mpc.train`, :mod:`fvin_mpc.collect` — training (needs torch).
* :mod:`fvin_mpc.export`, :mod:`fvin_mpc.mpc`, :mod:`fvin_mpc.energy_shaping` — control runtime
  (CasADi + NumPy, no torch).
"""

__version__ = "0.1.0"
