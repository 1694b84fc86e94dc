"""Progress output and stop requests (SIGINT, SIGTERM, a time budget)."""
from __future__ import annotations

import math
import signal
import sys

from .._signals import SignalLatch, take_over
from .errors import Interrupted, eprint


def fmt_time(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    if seconds < 60:
        return "%.1f s" % seconds
    if seconds < 3600:
        return "%dm%02ds" % divmod(int(round(seconds)), 60)
    h, rest = divmod(int(round(seconds)), 3600)
    return "%dh%02dm" % (h, rest // 60)


def fmt_rate(x: float) -> str:
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if x >= scale:
            return "%.3g %s" % (x / scale, unit)
    return "%.3g " % x


def exit_status(signum: int) -> int:
    """The shell's status for a process ended by ``signum`` (130 for SIGINT)."""
    return 128 + signum


class Progress:
    """A progress bar on stderr: redrawn in place on a terminal, a line every few
    seconds otherwise (the first one right after the first pass)."""

    def __init__(self, renderer, budget=None, enabled=True, stream=None):
        self.r = renderer
        self.budget = budget
        self.stream = stream or sys.stderr
        self.enabled = enabled and len(renderer.plan) > 1
        self.tty = self.enabled and self.stream.isatty()
        self.last = None
        self.first_pass = None
        self.drawn = False

    def line(self, elapsed: float) -> str:
        r = self.r
        total = len(r.plan)
        frac = r.passes_done / total
        width = 24
        fill = int(round(frac * width))
        rate = r.spp_done * r.pixels / elapsed if elapsed > 0 else 0.0
        if r.passes_done >= 2 and self.first_pass is not None:
            per_pass = (elapsed - self.first_pass) / (r.passes_done - 1)
        else:
            per_pass = elapsed / max(1, r.passes_done)
        left = per_pass * (total - r.passes_done)
        if self.budget is not None:
            left = min(left, max(0.0, self.budget - elapsed))
        workers = getattr(r, "workers_alive", None)       # a cluster's run
        return ("[%s%s] %d/%d passes, %d/%d spp, %ssamples/s, %s left%s"
                % ("#" * fill, "-" * (width - fill), r.passes_done, total, r.spp_done,
                   r.spp, fmt_rate(rate), fmt_time(left),
                   "" if workers is None else ", %d worker%s alive"
                   % (workers, "" if workers == 1 else "s")))

    def update(self, elapsed: float) -> None:
        if self.first_pass is None:
            self.first_pass = elapsed
        if not self.enabled:
            return
        interval = 0.1 if self.tty else max(1.0, min(30.0, elapsed / 10))
        if self.last is not None and elapsed - self.last < interval and not self.r.done:
            return
        self.last = elapsed
        text = "bdpt: " + self.line(elapsed)
        self.stream.write("\r" + text + "\033[K" if self.tty else text + "\n")
        self.stream.flush()
        self.drawn = True

    def finish(self) -> None:
        if self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()
        self.drawn = False


class StopRequest(SignalLatch):
    """SIGINT/SIGTERM for the whole command: the first is recorded, and the command
    stops at its next safe point (``check`` before rendering; after the current pass
    while rendering); a second aborts at once (KeyboardInterrupt), writing nothing
    more.  A signal that arrived while bdpt_drjit was imported counts as the first."""

    escalate = True

    def __init__(self):
        super().__init__()
        self.announce = None       # what to say on the first signal, once rendering

    def on_signal(self, signum: int) -> None:
        if self.announce:
            eprint("\nbdpt: %s: %s (again to abort)" % (signal.Signals(signum).name,
                                                         self.announce))

    def check(self) -> None:
        """Stop here (raise Interrupted) if a signal has arrived."""
        if self.signal is not None:
            raise Interrupted(self.signal)

    def __enter__(self):
        take_over(self)
        return self.install()

    def __exit__(self, *exc):
        self.restore()
        return False
