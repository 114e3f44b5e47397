"""Speed and memory of the engine's training step and whole-view rendering (measured by ``python -m gpnerf_core bench``,
whose command module is ``gpnerf_core.commands.bench``).

Figures are measured, printed and written (``bench.json``), never asserted in unit tests. ``sizes`` holds the
presets, ``measure`` runs one measurement in a fresh process (so its peak memory is its own), ``machine`` measures the
matmul peak the figures are compared with; ``profile`` and ``precision`` are stand-alone measurements
(``python -m gpnerf_core.tools.bench.profile``, ``.precision``).
"""
