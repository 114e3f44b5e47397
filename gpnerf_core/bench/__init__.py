"""``python -m gpnerf_core bench``: speed and memory of the engine's training step and whole-view rendering.

Figures are measured, printed and written (``bench.json``), never asserted in unit tests. ``sizes`` holds the
presets, ``measure`` runs one measurement in a fresh process (so its peak memory is its own), ``machine`` measures the
matmul peak the figures are compared with, ``command`` runs them all and writes the table.
"""
