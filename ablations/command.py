"""The error shell of the long-running commands (``ablate-sweep``, ``ablate-paper``, ``ablate-memory``): bad input
as one line and exit status 2, an interruption as the line that says what is kept and exit status 130."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

__all__ = ["command_errors"]


@contextlib.contextmanager
def command_errors(interrupted: Callable[[], str]) -> Iterator[None]:
    """Inside: a ValueError ends the command with ``error: <message>`` on stderr and exit status 2; a
    KeyboardInterrupt (the command has stopped its work) with the line ``interrupted()`` gives and status 130."""
    try:
        yield
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print(interrupted(), file=sys.stderr)
        raise SystemExit(130) from None
