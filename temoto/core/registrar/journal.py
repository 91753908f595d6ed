"""The registrar's durable catalog: an append-only, checksummed record log.

Every change the registrar makes is one record (a JSON object) copied into the file's pages
in the kernel's page cache before :meth:`Journal.append` returns, so it has reached the operating
system and survives SIGKILL of the process. The copy goes through a shared memory mapping of the
file (``mmap``, ``MAP_SHARED``): a store into it *is* the page cache, with no system call, so an
append costs a memory copy and a CRC (the kernel is entered only for the page fault of the first
store into each page, and to grow the file), and it is not held up by a running fsync. The
file is grown ahead of the appends, :data:`_PREALLOCATE` bytes (1 MiB) at a time, with
``posix_fallocate``, so its blocks exist before they are written (a full disk is an ``OSError``
from :meth:`Journal.append`, with nothing written, never a ``SIGBUS``); while the journal is
open, the file on disk therefore ends in zeros after the last record, and :meth:`Journal.close`
cuts them off. (On a file system that cannot map files, each append is one ``os.pwrite`` into
that space instead, logged once as a warning.) Against power loss the file is fsynced per the
``fsync`` policy (``os.fsync`` of the descriptor, which writes the mapped pages too):
``"group"`` (a background thread, at most every ``fsync_interval`` seconds while there are
unsynced records), ``"always"`` (before every ``append`` returns) or ``"never"`` (tests and
benchmarks; no ``os.fsync`` at all, not even when creating or compacting the file — only an
explicit :meth:`Journal.flush` syncs).

File format (all integers little-endian)::

    header  = b"TEMOTOJ1" version:u8                    9 bytes; version is 1
    frame   = length:u32 crc:u32 seq:u64 payload        16 bytes + length
    payload = UTF-8 JSON object, compact, sorted keys   length <= 64 MiB
    crc     = zlib.crc32(seq bytes + payload)           the 12 bytes after the crc field

Sequence numbers start at 1 in every file and grow by exactly 1 per frame.

Reading (:meth:`Journal.open`) tells a *torn tail* from *corruption*:

* Zeros after the last whole frame, up to the end of the file, are the unused preallocated
  space a process that did not close its journal (SIGKILL) leaves behind: they are cut off
  (logged at debug level; not a torn tail).
* A torn tail is damage that a crash can leave: the last frame is incomplete or fails its CRC
  and no valid frame follows it anywhere in the rest of the file. It is cut off (the file is
  truncated to the end of the last whole frame), logged as a warning and reported in
  :attr:`Journal.recovered_tail_bytes` (zeros after it included). A file shorter than the
  header whose bytes are a prefix of the header — including an empty file — is a torn header (a
  crash while the journal was being created): it is replaced by a fresh header, with a warning,
  and holds no records.
* Everything else is corruption and raises :class:`~temoto.errors.CatalogCorruptError` naming
  the file and the byte offset, leaving the file untouched: a wrong magic or version, a bad
  frame followed by a valid one, a sequence-number gap or repeat, a frame whose length is over
  64 MiB although the file holds that many bytes, and a payload with a valid CRC that is not a
  JSON object.

Compaction (:meth:`Journal.rewrite`) writes the live state to ``<path>.tmp``, fsyncs it,
renames it over the journal (``os.replace``) and fsyncs the directory: a crash at any point leaves
either the old or the new journal complete. A stale ``<path>.tmp`` from such a crash is removed
by the next :meth:`Journal.open`.

One process at a time: :meth:`Journal.open` takes an exclusive, non-blocking ``flock`` on the
file (POSIX) and raises :class:`~temoto.errors.ResourceBusyError` if another journal holds it.
The kernel drops the lock when the process dies, however it dies.
"""

from __future__ import annotations

import logging
import mmap
import os
import struct
import sys
import threading
import time
import zlib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

from temoto.core.registrar._frames import (
    FORMAT_VERSION,
    FRAME,
    FRAME_HEAD,
    HEADER,
    MAGIC,
    MAX_RECORD_BYTES,
    content_end,
    parse,
)
from temoto.core.registrar._json import make_encoder
from temoto.errors import CatalogCorruptError, ResourceBusyError

if sys.platform != "win32":
    import fcntl

__all__ = ["FORMAT_VERSION", "MAGIC", "MAX_RECORD_BYTES", "FsyncPolicy", "Journal", "encode"]

logger = logging.getLogger(__name__)

FsyncPolicy = Literal["group", "always", "never"]

_LEN_CRC = struct.Struct("<II")
_SEQ = struct.Struct("<Q")
_READ_CHUNK = 1 << 20
_ENCODE = make_encoder(  # _ENCODE(record, 0)[0]: the payload's text
    default=None, ensure_ascii=False, separators=(",", ":"), sort_keys=True, allow_nan=True
)
_POLICIES = ("group", "always", "never")
#: Appends write into a shared mapping of the file; it is grown by at least this many bytes
#: at a time (allocated on disk at once, so a full disk is an OSError, never a SIGBUS).
_PREALLOCATE = 1 << 20
_GRANULE = mmap.ALLOCATIONGRANULARITY


class Journal:
    """Append-only, checksummed record log; the registrar's durable catalog.

    The file format and the recovery rules are described in the module docstring. A journal is
    used once: construct, :meth:`open`, :meth:`append` (from any thread, unless ``serialized``),
    :meth:`close`.

    Args:
        path: The journal file. Its directory is created if missing.
        fsync: ``"group"`` (a background thread fsyncs at most every ``fsync_interval`` seconds
            while records are unsynced), ``"always"`` (fsync before each append returns) or
            ``"never"`` (no automatic fsync at all).
        fsync_interval: Seconds between group fsyncs.
        serialized: The owner makes its calls of the append methods, :meth:`rewrite`,
            :meth:`flush` and :meth:`close` one at a time (the registrar makes them all under
            its own lock), so an append takes no lock of its own. False (default): any thread
            may append at any time.

    Attributes:
        recovered_tail_bytes: How many bytes of a torn tail (or torn header) :meth:`open` cut
            off; 0 if none.

    Raises:
        ValueError: If ``fsync`` is not a known policy or ``fsync_interval`` is negative.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        fsync: FsyncPolicy = "group",
        fsync_interval: float = 0.1,
        serialized: bool = False,
    ) -> None:
        if fsync not in _POLICIES:
            raise ValueError(f"fsync must be one of {', '.join(_POLICIES)}, not {fsync!r}")
        if fsync_interval < 0:
            raise ValueError(f"fsync_interval must not be negative, not {fsync_interval!r}")
        self._path = Path(path)
        self._policy: FsyncPolicy = fsync
        self._group = fsync == "group"
        self._serialized = bool(serialized)
        self._interval = float(fsync_interval)
        self.recovered_tail_bytes = 0
        # _lock (the condition's lock) guards the descriptor's use for writing and every counter
        # below. _sync_lock is held while fsyncing the current descriptor and while swapping or
        # closing it; when both are needed, _lock is taken first.
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._sync_lock = threading.Lock()
        self._fd = -1
        # The mapping appends write into: file bytes [_map_start, _map_end) of _fd. The file's
        # size on disk is _allocated (>= _size; the bytes between are zeros).
        self._map: mmap.mmap | None = None
        self._map_start = 0
        self._map_end = 0
        self._allocated = 0
        self._mappable = True  # False once mmap failed: appends use os.pwrite
        self._open = False
        self._closing = False
        self._seq = 0  # the last frame's sequence number: also the number of records
        self._size = 0
        self._written = 0  # appends made (monotonic across rewrites)
        self._synced = 0  # the value of _written that the last fsync covered
        self._flusher: threading.Thread | None = None
        self._flusher_waiting = False

    # -- properties ---------------------------------------------------------------------------

    @property
    def path(self) -> Path:
        """The journal file."""
        return self._path

    @property
    def record_count(self) -> int:
        """Records in the file: those read by :meth:`open` (or :meth:`rewrite`) plus appended."""
        return self._seq

    @property
    def size(self) -> int:
        """The end of the last record in the file, in bytes, header included.

        This is the file's size once the journal is closed; while it is open, the file on
        disk is longer (zeros preallocated for the next appends).
        """
        return self._size

    @property
    def unsynced(self) -> int:
        """How many appends the last fsync did not cover (0: all of them are on disk)."""
        return self._written - self._synced

    # -- opening ------------------------------------------------------------------------------

    def open(self) -> list[dict[str, Any]]:
        """Open the journal, creating it if missing, and read back every record.

        Returns:
            The records in the order they were appended.

        Raises:
            CatalogCorruptError: If the file is damaged other than by a torn tail (the file is
                left untouched).
            ResourceBusyError: If another journal (in this or another process) has it open.
            RuntimeError: If this journal was opened or closed before.
            OSError: If the file cannot be created, read or written.
        """
        with self._lock:
            if self._open or self._closing or self._fd >= 0:
                raise RuntimeError(f"journal {self._path} was already opened")
            self._path.parent.mkdir(parents=True, exist_ok=True)
            fd, created = self._open_locked()
            try:
                self._remove_stale_tmp()
                records = self._load(fd, created)
            except BaseException:
                os.close(fd)
                raise
            self._fd = fd
            self._open = True
            return records

    def _open_locked(self) -> tuple[int, bool]:
        """Open (or create) the file and lock it; retry if it was replaced meanwhile."""
        for _ in range(100):
            created = True
            try:
                fd = os.open(self._path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                created = False
                try:
                    fd = os.open(self._path, os.O_RDWR)
                except FileNotFoundError:
                    continue
            try:
                _lock_file(fd, self._path)
                if _same_file(fd, self._path):
                    return fd, created
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)  # compacted by its previous owner between open and lock: try again
        raise ResourceBusyError(f"{self._path}: the journal keeps being replaced by another owner")

    def _remove_stale_tmp(self) -> None:
        tmp = self._tmp_path()
        try:
            tmp.unlink()
        except FileNotFoundError:
            return
        logger.warning("journal %s: removed %s left by an interrupted compaction", self._path, tmp)

    def _load(self, fd: int, created: bool) -> list[dict[str, Any]]:
        data = _read_all(fd)
        n = len(data)
        if n < len(HEADER):
            if not HEADER.startswith(data):
                raise self._corrupt(0, "not a TeMoto journal (bad magic)")
            if created:
                logger.debug("journal %s: created", self._path)
            else:
                logger.warning(
                    "journal %s: torn header (%d of %d bytes); starting a fresh journal",
                    self._path,
                    n,
                    len(HEADER),
                )
            self.recovered_tail_bytes = n
            if n:
                os.ftruncate(fd, 0)
            _write_all(fd, HEADER)
            if self._policy != "never":
                os.fsync(fd)
                _fsync_dir(self._path.parent)
            self._size = self._allocated = len(HEADER)
            return []
        if data[: len(MAGIC)] != MAGIC:
            raise self._corrupt(0, "not a TeMoto journal (bad magic)")
        version = data[len(MAGIC)]
        if version != FORMAT_VERSION:
            raise self._corrupt(len(MAGIC), f"unsupported journal format version {version}")
        records, end = parse(data, str(self._path))
        if end < n:
            if end >= content_end(data):
                logger.debug(
                    "journal %s: cut off %d bytes of preallocated zeros at byte %d",
                    self._path,
                    n - end,
                    end,
                )
            else:
                self.recovered_tail_bytes = n - end
                logger.warning(
                    "journal %s: cut off a torn last record (%d bytes at byte %d)",
                    self._path,
                    n - end,
                    end,
                )
            os.ftruncate(fd, end)
            if self._policy != "never":
                os.fsync(fd)
        self._seq = len(records)
        self._size = self._allocated = end
        return records

    def _corrupt(self, offset: int, message: str) -> CatalogCorruptError:
        return CatalogCorruptError(message, file=str(self._path), offset=offset)

    # -- writing ------------------------------------------------------------------------------

    def append(self, record: Mapping[str, Any]) -> None:
        """Append one record; it has reached the operating system when this returns.

        Thread-safe. With ``fsync="always"`` it is also on disk; with ``"group"`` it will be
        within about ``fsync_interval`` seconds.

        Args:
            record: A JSON-serialisable mapping with string keys.

        Raises:
            TypeError: If the record cannot be serialised as JSON (nothing is written).
            ValueError: If its JSON is larger than :data:`MAX_RECORD_BYTES` (nothing written).
            RuntimeError: If the journal is not open (never opened, or closed).
            OSError: If the file cannot be grown for it (a full disk); nothing is written.
        """
        self.append_json(encode(record))

    def append_text(self, text: str) -> None:
        """Append one record given as its JSON text (encoded by the caller from a layout).

        For records written so often that building a dict and running the JSON encoder
        for each would be half their cost (the registrar's references). The text must be a
        JSON object; it is read back with :func:`json.loads` like any other record.

        Args:
            text: The record's JSON text.

        Raises:
            ValueError: If the text is larger than :data:`MAX_RECORD_BYTES` (nothing written).
            RuntimeError, OSError: As :meth:`append`.
        """
        self.append_json(text.encode("utf-8"))

    def append_json(self, payload: bytes) -> None:
        """Append one record given as its JSON text's UTF-8 bytes (see :meth:`append_text`).

        Args:
            payload: The record's JSON text, UTF-8.

        Raises:
            ValueError: If it is larger than :data:`MAX_RECORD_BYTES` (nothing written).
            RuntimeError, OSError: As :meth:`append`.
        """
        size = len(payload)
        if size > MAX_RECORD_BYTES:
            raise ValueError(f"journal record is {size} bytes, over {MAX_RECORD_BYTES}")
        if self._serialized:  # the owner's calls never overlap: no lock (see the class)
            self._put(payload, size)
        else:
            with self._lock:
                self._put(payload, size)
        if self._group:
            # After _written grew: the flusher sets _flusher_waiting before it looks at
            # _written, under the lock it waits on, so one of the two sees the other.
            if self._flusher_waiting:
                self._wake_flusher()
            elif self._flusher is None:
                self._start_flusher()
        elif self._policy == "always":
            self._sync()

    def _put(self, payload: bytes, size: int) -> None:
        """Write one frame after the last (the caller holds _lock, or is the serialized owner)."""
        pos = self._size
        end = pos + FRAME_HEAD + size
        if end > self._map_end:  # also when not open: then nothing is mapped
            self._grow(end)  # raises (nothing written) if not open, or the disk is full
        seq = self._seq + 1
        crc = zlib.crc32(payload, zlib.crc32(_SEQ.pack(seq)))
        mapped = self._map
        if mapped is None:  # the file cannot be mapped (see _grow)
            _write_all(self._fd, FRAME.pack(size, crc, seq) + payload, pos)
        else:
            # The payload first, the frame head last: a process killed in between leaves a
            # frame whose head is zeros, which fails its CRC (a torn tail).
            start = self._map_start
            mapped[pos + FRAME_HEAD - start : end - start] = payload
            FRAME.pack_into(mapped, pos - start, size, crc, seq)
        self._seq = seq
        self._size = end
        self._written += 1

    def _grow(self, end: int) -> None:
        """Map a window of the file from the frame at ``_size`` past ``end`` (caller holds _lock).

        The file is extended with its blocks allocated (``posix_fallocate``) before it is
        mapped, so a full disk raises OSError here, with nothing written. On a file system that
        cannot map files, nothing is mapped, and appends write each frame with ``os.pwrite``
        (one system call, which has reached the operating system when it returns) into the
        space allocated here.

        Raises:
            RuntimeError: If the journal is not open.
            OSError: If the file cannot be extended or mapped.
        """
        if not self._open:
            raise self._not_open()
        start = self._size - self._size % _GRANULE
        stop = max(end, self._size + _PREALLOCATE)
        stop += -stop % _GRANULE
        if stop > self._allocated:
            _allocate(self._fd, self._allocated, stop - self._allocated)
            self._allocated = stop
        mapped = None
        if self._mappable:
            try:
                mapped = mmap.mmap(self._fd, stop - start, offset=start)
            except OSError as err:  # a file system that cannot map files
                self._mappable = False
                logger.warning(
                    "journal %s: the file cannot be mapped (%s); appending with pwrite",
                    self._path,
                    err,
                )
        old, self._map = self._map, mapped
        self._map_start, self._map_end = start, stop
        if old is not None:
            old.close()  # its pages stay in the page cache: fsync of the file writes them

    def _unmap(self) -> None:
        """Close the mapping (caller holds _lock, or no append can run any more)."""
        mapped, self._map = self._map, None
        self._map_start = self._map_end = 0
        if mapped is not None:
            mapped.close()

    def _not_open(self) -> RuntimeError:
        state = "closed" if self._closing else "not open"
        return RuntimeError(f"journal {self._path} is {state}")

    def rewrite(self, records: Iterable[Mapping[str, Any]]) -> None:
        """Replace the journal's content with ``records`` (compaction).

        The new file gets a fresh header and sequence numbers from 1. It is written to
        ``<path>.tmp``, fsynced, renamed over the journal and the directory fsynced; a crash at
        any point leaves either the old or the new journal complete. Appends then continue in
        the new file. Appends made by other threads while this runs land either in the old
        file (and are dropped with it) or after the new records.

        Args:
            records: The whole live state, as records.

        Raises:
            TypeError: If a record cannot be serialised (the journal is unchanged).
            ValueError: If a record is larger than :data:`MAX_RECORD_BYTES` (unchanged).
            RuntimeError: If the journal is not open.
            OSError: If writing or renaming the new file fails (the journal is unchanged).
        """
        parts = [HEADER]
        count = 0
        for count, record in enumerate(records, 1):
            payload = encode(record)
            seq_bytes = count.to_bytes(8, "little")
            crc = zlib.crc32(payload, zlib.crc32(seq_bytes))
            parts += (_LEN_CRC.pack(len(payload), crc), seq_bytes, payload)
        data = b"".join(parts)
        durable = self._policy != "never"
        tmp = self._tmp_path()
        with self._lock:
            if not self._open:
                raise self._not_open()
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o644)
            try:
                _lock_file(fd, tmp)
                os.fchmod(fd, os.fstat(self._fd).st_mode & 0o7777)
                _write_all(fd, data)
                if durable:
                    os.fsync(fd)
                with self._sync_lock:
                    os.replace(tmp, self._path)
                    self._unmap()
                    old, self._fd = self._fd, fd
                    self._synced = self._written
            except BaseException:
                os.close(fd)
                tmp.unlink(missing_ok=True)
                raise
            self._seq = count
            self._size = self._allocated = len(data)
            os.close(old)
            if durable:
                _fsync_dir(self._path.parent)
        logger.info("journal %s: compacted to %d records, %d bytes", self._path, count, len(data))

    def _tmp_path(self) -> Path:
        return self._path.with_name(self._path.name + ".tmp")

    # -- syncing ------------------------------------------------------------------------------

    def flush(self) -> None:
        """Fsync now if anything was appended since the last fsync (under any policy).

        Raises:
            OSError: If the fsync fails.
        """
        self._sync()

    def _sync(self) -> None:
        with self._sync_lock:
            target = self._written  # every append counted here has finished its write
            if target <= self._synced or self._fd < 0:
                return
            os.fsync(self._fd)
            self._synced = target

    def _start_flusher(self) -> None:
        """Start the group-fsync thread, unless another append just did."""
        with self._lock:
            if self._flusher is not None or self._closing:
                return
            self._flusher = threading.Thread(
                target=self._flush_loop, name="temoto-journal-fsync", daemon=True
            )
            self._flusher.start()

    def _wake_flusher(self) -> None:
        with self._cond:
            if self._flusher_waiting:
                self._flusher_waiting = False
                self._cond.notify()

    def _flush_loop(self) -> None:
        cond = self._cond
        while True:
            with cond:
                while not self._closing:
                    self._flusher_waiting = True  # first, then look: see append_json
                    if self._written > self._synced:
                        break
                    cond.wait()
                self._flusher_waiting = False
                if self._closing:
                    return  # close() does the final fsync
            try:
                self._sync()
            except OSError:
                logger.exception("journal %s: fsync failed", self._path)
            with cond:  # rate limit: appends do not notify during this wait, close() does
                deadline = time.monotonic() + self._interval
                while not self._closing:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    cond.wait(remaining)

    def close(self) -> None:
        """Fsync (unless ``fsync="never"``), stop the flusher thread and close the file.

        Idempotent. Appending afterwards raises RuntimeError.

        Raises:
            OSError: If the final fsync fails (the file is closed anyway).
        """
        with self._cond:
            if self._closing:
                return
            self._closing = True
            self._open = False
            self._cond.notify_all()
            flusher = self._flusher
        if flusher is not None:
            flusher.join()
        with self._lock, self._sync_lock:
            fd, self._fd = self._fd, -1
            if fd < 0:
                return
            try:
                self._unmap()
                if self._allocated > self._size:  # the preallocated zeros
                    os.ftruncate(fd, self._size)
                    self._allocated = self._size
                if self._policy != "never" and self._written > self._synced:
                    os.fsync(fd)
                    self._synced = self._written
            finally:
                os.close(fd)

    def __repr__(self) -> str:
        return (
            f"<Journal {str(self._path)!r} records={self._seq} size={self._size} "
            f"fsync={self._policy}>"
        )


def encode(record: Mapping[str, Any]) -> bytes:
    """A record's payload as :meth:`Journal.append` writes it: compact JSON, sorted keys, UTF-8.

    Args:
        record: A JSON-serialisable mapping with string keys.

    Returns:
        The bytes.

    Raises:
        TypeError: If the record cannot be serialised as JSON.
        ValueError: If its JSON is larger than :data:`MAX_RECORD_BYTES`.
    """
    if type(record) is not dict:
        if not isinstance(record, Mapping):
            raise TypeError(f"a journal record must be a mapping, not {type(record).__name__}")
        record = dict(record)
    try:
        payload = _ENCODE(record, 0)[0].encode("utf-8")
    except (ValueError, RecursionError) as exc:  # a circular reference, a lone surrogate
        raise TypeError(f"journal record is not JSON-serialisable: {exc}") from exc
    if len(payload) > MAX_RECORD_BYTES:
        raise ValueError(f"journal record is {len(payload)} bytes, over {MAX_RECORD_BYTES}")
    return payload


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, _READ_CHUNK):
        chunks.append(chunk)
    return b"".join(chunks)


def _write_all(fd: int, data: bytes, offset: int = 0) -> None:
    """Write ``data`` at ``offset`` in the file ``fd``, looping on short writes."""
    view = memoryview(data)
    done = 0
    while done < len(data):
        done += os.pwrite(fd, view[done:], offset + done)


def _allocate(fd: int, offset: int, length: int) -> None:
    """Extend the file by ``length`` bytes at ``offset`` (its size), allocated on disk."""
    allocate = getattr(os, "posix_fallocate", None)  # not on Windows or macOS
    if allocate is None:
        os.ftruncate(fd, offset + length)
    else:
        allocate(fd, offset, length)


def _fsync_dir(directory: Path) -> None:
    if sys.platform == "win32":
        return
    dfd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def _lock_file(fd: int, path: Path) -> None:
    if sys.platform == "win32":
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise ResourceBusyError(f"{path}: the journal is open in another registrar") from None


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (mine.st_dev, mine.st_ino) == (st.st_dev, st.st_ino)
