"""What the command line's modules share: exit codes, error lines, output files, option types.

Not public API: the modules of :mod:`temoto.cli` use it. Like them, it prints (to standard
error only).
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import signal
import stat
import sys
from pathlib import Path
from typing import IO, Any

from temoto._files import check_regular
from temoto.errors import ConfigError

__all__ = [
    "EXIT_BROKEN_PIPE",
    "EXIT_FAILED",
    "EXIT_INVALID",
    "EXIT_OK",
    "EXIT_OTHER_RESULT",
    "EXIT_TRUE",
    "add_paths",
    "error",
    "factor",
    "non_empty",
    "not_negative",
    "open_output",
    "positive",
    "seconds",
    "signal_name",
]

#: The exit statuses of every command (the robot command's too).
EXIT_OK = 0
#: A command that did not do what it was asked (a device failed, no answer, nothing found).
EXIT_FAILED = 1
#: Invalid input: a one-line message naming the file, key or option.
EXIT_INVALID = 2
#: A graph's run ended ``on_true`` (``temoto run``, ``temoto demo``, a robot's mission).
EXIT_TRUE = EXIT_OK
#: A graph's run ended with any other result.
EXIT_OTHER_RESULT = EXIT_FAILED
EXIT_BROKEN_PIPE = 128 + 13  # SIGPIPE
#: The longest error line printed; the rest is counted, not shown.
MAX_ERROR_CHARS = 1000


def error(err: BaseException | str) -> None:
    """Write the one-line error of the command line: ``temoto: error: ...``.

    Args:
        err: The error, or its text.
    """
    text = str(err)
    if len(text) > MAX_ERROR_CHARS:  # a value quoted whole (a YAML alias bomb: 8 MB)
        text = f"{text[:MAX_ERROR_CHARS]}... ({len(text) - MAX_ERROR_CHARS} characters more)"
    sys.stderr.write(f"temoto: error: {text}\n")


def open_output(path: str | Path) -> IO[str]:
    """A file the command writes (``--trace``, ``-o``), opened for writing.

    Args:
        path: The file.

    Returns:
        The open file (text, UTF-8).

    Raises:
        ConfigError: It cannot be written (no such folder, no permission, a FIFO or a device
            rather than a regular file), in one line.
    """
    if str(path) == os.devnull:  # the one device worth writing to: output thrown away
        return open(os.devnull, "w", encoding="utf-8")
    try:
        check_regular(path, missing_ok=True)
        # O_NONBLOCK: a FIFO put there since the check fails (ENXIO) instead of blocking
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NONBLOCK, 0o666)
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise OSError(errno.EINVAL, "not a regular file")
            os.set_blocking(fd, True)
            return open(fd, "w", encoding="utf-8")
        except BaseException:
            os.close(fd)
            raise
    except OSError as err:
        raise ConfigError(f"{path}: cannot write: {err.strerror or err}") from None


def signal_name(signum: int) -> str:
    """``SIGINT`` for 2, and so on.

    Args:
        signum: A signal number.

    Returns:
        Its name.
    """
    return signal.Signals(signum).name


def add_paths(p: argparse.ArgumentParser | Any) -> None:
    """Add ``--actions DIR`` and ``--graphs DIR`` (both repeatable) to a command's parser.

    Args:
        p: The command's parser.
    """
    p.add_argument(
        "--actions",
        action="append",
        default=[],
        metavar="DIR",
        help="folder of actions (repeatable)",
    )
    p.add_argument(
        "--graphs",
        action="append",
        default=[],
        metavar="DIR",
        help="folder of graphs (repeatable)",
    )


def seconds(text: str, *, zero: bool) -> float:
    """A duration option's value: a finite number of seconds, above 0 (or at least 0)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not zero):
        bound = "at least 0" if zero else "more than 0"
        raise argparse.ArgumentTypeError(f"{text!r}: must be {bound} seconds")
    return value


def factor(text: str) -> float:
    """``--speed`` and the like: a finite number more than 0 (not ``inf``, ``nan``, 0, -1)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number more than 0")
    return value


def non_empty(text: str) -> str:
    """``--actor`` and the like: a name that is not empty (nor only blanks)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("must not be empty")
    return text


def positive(text: str) -> float:
    """``--timeout`` and the like: seconds, more than 0."""
    return seconds(text, zero=False)


def not_negative(text: str) -> float:
    """``--stop-timeout``: seconds, 0 or more (0: give up at once on an action asked to stop)."""
    return seconds(text, zero=True)
