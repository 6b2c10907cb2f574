"""Interrupts (Ctrl-C, a scheduler's SIGTERM) that are not lost inside JAX.

While XLA runs a compiled loop (NUTS's warm-up and sampling, with the chains vectorised) the
main thread runs no Python, and Python raises the ``KeyboardInterrupt`` of a Ctrl-C at the next
Python code it runs there: often a callback of JAX's (its garbage-collection hook), whose
exceptions Python reports as "ignored" and drops, so that the command ran on to its end as if
nothing had been pressed.  The command line's handler therefore records the request as well as
raising it, and the long steps check the record between their steps (:func:`check_interrupt`):
an interrupt is honoured at the latest when the step running at that moment ends.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable

__all__ = ["check_interrupt", "interrupt_requested", "handling_interrupts"]

_REQUESTED = threading.Event()


def check_interrupt() -> None:
    """Raise ``KeyboardInterrupt`` where an interrupt was requested and not yet acted on."""
    if _REQUESTED.is_set():
        raise KeyboardInterrupt


def interrupt_requested() -> bool:
    """Whether an interrupt was requested while :func:`handling_interrupts` was in force."""
    return _REQUESTED.is_set()


def _on_signal(signum, frame):  # noqa: ARG001 - the signal module's signature
    _REQUESTED.set()
    raise KeyboardInterrupt


class handling_interrupts:
    """Within this context, SIGINT and SIGTERM are recorded (:func:`check_interrupt`) and raised as
    ``KeyboardInterrupt``; the handlers before it are restored on leaving.  A signal the process
    ignores stays ignored (a shell starts its background jobs ignoring SIGINT, as Python itself
    respects), and only the main thread can install handlers: elsewhere this does nothing."""

    def __enter__(self) -> handling_interrupts:
        _REQUESTED.clear()
        self._before: dict[int, Callable | int | None] = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                if signal.getsignal(sig) is not signal.SIG_IGN:
                    self._before[sig] = signal.signal(sig, _on_signal)
        self._hook = sys.unraisablehook

        def quiet(unraisable, previous=self._hook) -> None:
            # an interrupt dropped inside a callback is recorded, and acted on: no traceback for it
            if not isinstance(unraisable.exc_value, KeyboardInterrupt):
                previous(unraisable)

        sys.unraisablehook = quiet
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._before.items():
            signal.signal(sig, handler)
        sys.unraisablehook = self._hook
        _REQUESTED.clear()
