"""SIGINT and SIGTERM, recorded instead of acted on where acting at once breaks things.

A KeyboardInterrupt raised while Mitsuba's and Dr.Jit's extension modules initialize
leaves them half-built: Python then prints 20-140 lines of unrelated errors, and
sometimes aborts ("Fatal Python error: PyThreadState_Get").  ``held_during_import``
records such a signal and acts on it once the imports are done.  The command line
keeps recording signals while it renders, so that it can stop between passes.
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class SignalLatch:
    """Handlers that record the first SIGINT/SIGTERM; a second one raises
    KeyboardInterrupt if ``escalate``, else is recorded as well."""

    escalate = False

    def __init__(self):
        self.signal = None
        self.old = {}              # the handlers to restore

    def on_signal(self, signum: int) -> None:
        """Called on the first signal."""

    def _handler(self, signum, frame):
        if self.signal is None:
            self.signal = signum
            self.on_signal(signum)
        elif self.escalate:
            raise KeyboardInterrupt

    def install(self) -> "SignalLatch":
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                old = signal.signal(sig, self._handler)
                self.old.setdefault(sig, signal.SIG_DFL if old is None else old)
        return self

    def restore(self) -> None:
        for sig, old in self.old.items():
            signal.signal(sig, old)
        self.old = {}


def started_as_command() -> bool:
    """Is this process the ``bdpt`` command (``python -m bdpt_drjit`` or the script)?"""
    argv = list(getattr(sys, "orig_argv", ()))
    if "-m" in argv[:-1] and argv[argv.index("-m") + 1] == "bdpt_drjit":
        return True
    return os.path.basename(sys.argv[0] if sys.argv else "") == "bdpt"


_handed_over = None


@contextlib.contextmanager
def held_during_import():
    """Record SIGINT/SIGTERM while the body imports native modules.  Afterwards the
    ``bdpt`` command takes the record over (``take_over``); in any other program a
    recorded signal is delivered again, now that it is safe."""
    global _handed_over
    latch = SignalLatch().install()
    try:
        yield
    except BaseException:
        latch.restore()
        raise
    if started_as_command():
        _handed_over = latch       # its handlers stay until the command replaces them
        return
    latch.restore()
    if latch.signal is not None:
        signal.raise_signal(latch.signal)


def take_over(latch: SignalLatch) -> None:
    """Give ``latch`` the signal recorded during import, and the handlers to restore."""
    global _handed_over
    if _handed_over is not None:
        latch.signal, latch.old = _handed_over.signal, _handed_over.old
        _handed_over = None
