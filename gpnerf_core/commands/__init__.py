"""One module per command of ``python -m gpnerf_core``, each a thin layer: parse or compose, call the engine, write
the outputs. Each exposes ``main(argv) -> exit code``; ``gpnerf_core.cli`` dispatches to them by name. A command
module imports the engine (``gpnerf_core.engine``: launching, guarding, opening, ...) and the tool libraries, never another command or the CLI.
"""
