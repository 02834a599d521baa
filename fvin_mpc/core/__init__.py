"""The math core: S³ algebra, the forced variational step, learned and closed-form ``J``, ``U``, ``g``,
checkpoints and trajectory files.

Written once for NumPy, torch and CasADi: only :mod:`fvin_mpc.core.backend` knows the three
libraries apart, and nothing here imports torch or CasADi at module level or any other layer of
the package (``tests/test_layers.py``).
"""
