"""Measurements that print figures (never timed unit tests): run them as modules, e.g.
``python -m gpnerf_core.benchmarks.precision +experiment=paper/gpnerf``."""
