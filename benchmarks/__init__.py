"""The research studies behind the reports in ``docs/``: run from a clone, not installed.

Every study is a module run from the repository's root with ``python -m``: the accuracy-vs-time
studies through one dispatcher (``python -m benchmarks <study>``), the two studies with their own
command line as ``python -m benchmarks.<module>``. They import the installed ``fvin_mpc``; nothing
in ``fvin_mpc`` imports them (``tests/test_layers.py``). ``benchmarks/README.md`` lists them.
"""
