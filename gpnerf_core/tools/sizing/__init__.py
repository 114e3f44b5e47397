"""Sizing a model to a scene (driven by ``python -m gpnerf_core size``): measure the scene (``scene``), cost a
configuration before training it (``costs``), the knobs and their levels (``knobs``), the descent (``search``), the
short trial runs (``trials``) and what a sizing writes (``report``)."""
