"""How the command line reports problems: one line on stderr, never a traceback."""
from __future__ import annotations

import re
import signal
import sys


class CLIError(Exception):
    """A problem with the user's input: reported as one line, exit status ``code``."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


class Interrupted(Exception):
    """SIGINT or SIGTERM arrived before there was anything to write."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def eprint(*parts) -> None:
    print(*parts, file=sys.stderr, flush=True)


def python_cause(text: str) -> str:
    """The Python exception inside a Mitsuba message: Mitsuba wraps an error raised
    by a Python plugin (such as bdpt's constructor) as '<where>: Traceback (most
    recent call last): <frames> <Type>: <message>'; keep '<where>: <message>'."""
    head, sep, tail = text.partition("Traceback (most recent call last):")
    if not sep:
        return text
    last = [line for line in tail.strip().splitlines() if line.strip()][-1]
    return head.strip() + " " + re.sub(r"^[\w.]+(Error|Exception|Warning): ", "", last.strip())


def one_line(exc_or_text) -> str:
    """An exception's message on one line, without 'bdpt: ' or '[file.cpp:123] '."""
    text = python_cause(str(exc_or_text))
    text = re.sub(r"\[[\w./-]+\.(?:cpp|h|py):\d+\]\s*", "", text)
    text = re.sub(r"\s*\n\s*-?\s*", "; ", text.strip())
    text = re.sub(r"(^|: )(bdpt:\s*)+", r"\1", text)
    text = re.sub(r"\s+", " ", text)
    return text.strip("; ") or exc_or_text.__class__.__name__
