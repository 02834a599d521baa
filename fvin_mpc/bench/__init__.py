"""``python -m fvin_mpc.bench <study>``: the command; the studies live in :mod:`fvin_mpc.studies.bench`."""
