"""Reading the files a user names (graphs, profiles, traces, action descriptions) safely.

A FIFO, a device or a socket given where a file is expected would block ``open()`` (a FIFO
without a writer waits forever) or read without end (``/dev/zero``); only regular files are
read. The check is made twice: with :func:`os.stat` before the open, and with
:func:`os.fstat` on the descriptor, which is opened with ``O_NONBLOCK`` so that a file swapped
for a FIFO between the two cannot block either.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["NotRegularFileError", "check_regular", "read_regular_text"]

_KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a folder"),
)


class NotRegularFileError(OSError):
    """A path names something other than a regular file (its ``strerror`` says what)."""


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def check_regular(path: str | Path, *, missing_ok: bool = False) -> None:
    """Refuse a path that exists and is not a regular file (symbolic links are followed).

    Args:
        path: The file.
        missing_ok: A path that does not exist passes (a file about to be written).

    Raises:
        NotRegularFileError: It is a FIFO, a device, a socket or a folder.
        OSError: It cannot be looked at (missing, unless ``missing_ok``; no permission).
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        if missing_ok:
            return
        raise
    if not stat.S_ISREG(mode):
        what = _kind(mode)
        raise NotRegularFileError(errno.EINVAL, f"{what}, not a regular file", str(path))


def read_regular_text(path: str | Path) -> str:
    """The text (UTF-8) of a regular file; anything else is refused without blocking.

    Args:
        path: The file.

    Returns:
        Its text.

    Raises:
        NotRegularFileError: It is a FIFO, a device, a socket or a folder.
        OSError: It cannot be read.
        UnicodeDecodeError: It is not UTF-8.
    """
    check_regular(path)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise NotRegularFileError(errno.EINVAL, f"{_kind(mode)}, not a regular file", str(path))
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=True) as stream:
            fd = -1
            data = stream.read()
    finally:
        if fd >= 0:
            os.close(fd)
    return data.decode("utf-8")
