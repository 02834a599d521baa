"""Studies: closed-loop evaluation, model quality, the quadrotor study and training sweeps; one
process pool (:mod:`~fvin_mpc.studies.pool`) and one report writer (:mod:`~fvin_mpc.studies.report`).

The top layer: may use everything below it, and nothing below imports it. The research studies are
not here: they are the repository's ``benchmarks/`` folder, which imports this package.
"""
