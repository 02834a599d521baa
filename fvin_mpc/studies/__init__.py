"""Studies: evaluation, benchmarks, model-quality reports and the accuracy-vs-time studies of
``python -m fvin_mpc.bench``; one report writer (:mod:`~fvin_mpc.studies.report`).

The top layer: may use everything below it, and nothing below imports it.
"""
