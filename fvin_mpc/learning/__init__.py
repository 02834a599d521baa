"""Learning: data collection on a scene, the torch model and its training.

The only layer that imports torch; it builds on :mod:`fvin_mpc.core` and :mod:`fvin_mpc.envs`.
"""
