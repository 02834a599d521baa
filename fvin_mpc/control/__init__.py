"""The control runtime: CasADi export, MPC, energy shaping, the closed loop and the model and
controller a scene calls for.

Needs CasADi, NumPy and (for the plant) MuJoCo, never torch; builds on :mod:`fvin_mpc.core` and
:mod:`fvin_mpc.envs`.
"""
