"""argparse for the commands and data tools that parse their own arguments (``report``, ``stress``, ``data ...``)."""

from __future__ import annotations

import argparse
from typing import NoReturn

from gpnerf_core.errors import ConfigError


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose usage errors are one ``ConfigError`` line (exit code 2 through ``cli.main``), not argparse's
    usage block and ``SystemExit``."""

    def error(self, message: str) -> NoReturn:
        raise ConfigError(f"{self.prog}: {message}")
