"""SIGINT and SIGTERM as a request to stop training cleanly at the end of the current step."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType
from typing import Any

HANDLED = (signal.SIGINT, signal.SIGTERM)


class TrainingInterrupted(Exception):
    """Training stopped on a signal after writing a checkpoint.

    Attributes:
        signum: the signal; the process exits with ``128 + signum`` (130 for SIGINT, 143 for SIGTERM).
        step: the step the checkpoint holds; checkpoint: its path (None on processes that do not write).
    """

    def __init__(self, signum: int, step: int, checkpoint: Any) -> None:
        super().__init__(f"{signal.Signals(signum).name} at step {step}")
        self.signum = signum
        self.step = step
        self.checkpoint = checkpoint

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


class StopNow(BaseException):
    """A stop signal arrived inside ``StopRequest.raising``: what was running unwinds (a ``BaseException``, so
    ``except Exception`` does not swallow it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopRequest:
    """While entered, SIGINT/SIGTERM set ``signum`` instead of interrupting; the loop polls it after each step.

    Repeated signals are absorbed: torchrun forwards the terminal's Ctrl-C to its workers, so each worker sees
    it twice, and the checkpoint must still be written. Outside the main thread this is a no-op (signals can
    only be handled there).
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}
        self._raising = False

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for sig in HANDLED:
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc_info: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is None:
            self.signum = signum
        if self._raising:
            self._raising = False
            raise StopNow(signum)

    @contextlib.contextmanager
    def raising(self) -> Iterator[None]:
        """While entered, a signal (or one already received) raises ``StopNow`` at once instead of waiting for the
        end of the step: for work between steps that may take minutes (an ``eval.every_steps`` evaluation)."""
        if self.signum is not None:
            raise StopNow(self.signum)
        self._raising = True
        try:
            yield
        finally:
            self._raising = False
