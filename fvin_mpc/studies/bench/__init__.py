"""The accuracy-vs-time studies run by ``python -m fvin_mpc.bench <study>``; each module has
``run(quick, seed, repeats, **options) -> StudyResult`` and optionally ``add_arguments(parser)``."""
