"""Hydra configs of gpnerf-core, installed as the package ``gpnerf_conf`` (source: the repository's ``conf/``)."""
