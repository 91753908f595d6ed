"""Fast DDS shared-memory segments left in ``/dev/shm`` by a process that crashed.

Fast DDS's shared-memory transport creates, per participant and per port, a segment
(``fastrtps_<id>`` in Jazzy's Fast DDS 2.14, ``fastdds_<id>`` in Fast DDS 3), a lock file next
to it (``<segment>_el``) that a live user holds with ``flock``, and for ports a named semaphore
(``sem.<segment>_mutex``). A clean exit removes them; a crash (or SIGKILL) leaves them. A
segment whose lock file nobody holds is a zombie; this is the test ``fastdds shm clean`` makes.

A peer that still sends to a dead participant (until its lease runs out) re-creates that
participant's port segment and semaphore, without a lock file: a port segment with no lock file,
untouched for :data:`PORT_MIN_AGE_S`, is a zombie too.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import time
from pathlib import Path
from typing import Final

__all__ = ["PORT_MIN_AGE_S", "SHM_DIR", "clean_stale_segments", "fastdds_segments"]

logger = logging.getLogger(__name__)

#: Where POSIX shared memory lives on Linux.
SHM_DIR: Final = Path("/dev/shm")
_PREFIXES: Final = ("fastrtps_", "fastdds_")
_PORT: Final = re.compile(r"^(fastrtps|fastdds)_port\d+$")
#: Seconds a port segment without a lock file must be old to be removed (its creator may be
#: about to make the lock file).
PORT_MIN_AGE_S: Final = 1.0


def fastdds_segments(shm_dir: Path = SHM_DIR) -> list[str]:
    """The names of Fast DDS's files in ``shm_dir`` (segments, lock files, semaphores).

    Args:
        shm_dir: The shared-memory directory.

    Returns:
        The names, sorted.
    """
    try:
        names = os.listdir(shm_dir)
    except OSError:
        return []
    return sorted(
        n
        for n in names
        if n.startswith(_PREFIXES) or n.startswith(("sem.fastrtps_", "sem.fastdds_"))
    )


def clean_stale_segments(shm_dir: Path = SHM_DIR) -> list[str]:
    """Remove the Fast DDS segments no live process uses.

    Each lock file is locked exclusively without blocking; if that succeeds nobody holds it, and
    its segment, the lock file and the segment's semaphore are removed while the lock is held.

    Args:
        shm_dir: The shared-memory directory.

    Returns:
        The segment names removed.
    """
    removed: list[str] = []
    for name in fastdds_segments(shm_dir):
        if not name.endswith("_el") or name.startswith("sem."):
            continue
        segment = name[: -len("_el")]
        try:
            fd = os.open(shm_dir / name, os.O_RDONLY)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # in use
            for leftover in (segment, f"sem.{segment}_mutex", name):
                with contextlib.suppress(FileNotFoundError):
                    (shm_dir / leftover).unlink()
            removed.append(segment)
        finally:
            os.close(fd)
    names = set(fastdds_segments(shm_dir))
    for name in sorted(names):
        if not _PORT.match(name) or f"{name}_el" in names:
            continue
        try:
            age = time.time() - (shm_dir / name).stat().st_mtime
        except OSError:
            continue
        if age < PORT_MIN_AGE_S:
            continue
        for leftover in (name, f"sem.{name}_mutex"):
            with contextlib.suppress(FileNotFoundError):
                (shm_dir / leftover).unlink()
        removed.append(name)
    if removed:
        logger.info("removed stale Fast DDS segments from %s: %s", shm_dir, ", ".join(removed))
    return removed
