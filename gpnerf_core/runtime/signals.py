"""SIGTERM as an exception, so that a command stopped by ``kill``, a scheduler or torchrun's agent unwinds like Ctrl-C:
``finally`` blocks run, child processes started with ``subprocess.run`` are killed with it (it kills its child on any
exception), finished results can be saved, and one line is printed instead of nothing.

The training loop replaces this handler while it runs (``training.interrupt.StopRequest``: stop after the step, write a
checkpoint) and restores it afterwards.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType


class Terminated(BaseException):
    """SIGTERM arrived (a ``BaseException``, like ``KeyboardInterrupt``: ``except Exception`` does not swallow it)."""

    signum = signal.SIGTERM
    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """While entered (main thread only), SIGTERM raises ``Terminated``; the previous handler comes back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interrupted_by(exc: BaseException | None) -> BaseException | None:
    """The ``KeyboardInterrupt`` or ``Terminated`` that ``exc`` is, or that it replaced while unwinding, else None.

    A library's cleanup can raise an error of its own while the interruption unwinds through it (OmegaConf's
    ``flag_override`` did, on a half-built node), leaving the interruption only as the new error's ``__context__``.
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (KeyboardInterrupt, Terminated)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def interruption(exc: BaseException) -> tuple[str, int]:
    """``(signal name, exit code)`` of a ``KeyboardInterrupt`` (SIGINT, 130) or ``Terminated`` (SIGTERM, 143)."""
    if isinstance(exc, Terminated):
        return "SIGTERM", Terminated.exit_code
    return "SIGINT", 128 + signal.SIGINT
