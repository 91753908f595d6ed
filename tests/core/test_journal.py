from __future__ import annotations

import json
import logging
import os
import random
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto.core.registrar.journal import MAGIC, MAX_RECORD_BYTES, Journal
from temoto.errors import CatalogCorruptError, ResourceBusyError

ROOT = Path(__file__).resolve().parents[2]
HEADER_LEN = len(MAGIC) + 1

RECORDS: list[dict[str, Any]] = [
    {"op": "load", "uid": "r-1", "server": "process", "request": {"args": ["-v"], "x": 1.5}},
    {"op": "ref", "id": "a-1", "client": "Grüße/Move_3", "note": "日本語 ✓ \U0001f916", "n": None},
    {"op": "unload", "uid": "r-1", "nested": {"list": [1, 2, {"deep": True}]}},
]


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "catalog.journal"


@pytest.fixture
def journal(path: Path) -> Iterator[Journal]:
    j = Journal(path, fsync="never")
    j.open()
    yield j
    j.close()


def write_records(path: Path, records: list[dict[str, Any]]) -> list[int]:
    """Write a journal; return the file size after the header and after each record."""
    j = Journal(path, fsync="never")
    j.open()
    ends = [j.size]
    for record in records:
        j.append(record)
        ends.append(j.size)
    j.close()
    return ends


def written(path: Path) -> bytes:
    """The file's bytes without the zeros preallocated after the records (while it is open)."""
    return path.read_bytes().rstrip(b"\0")


def reopen(path: Path, **kwargs: Any) -> list[dict[str, Any]]:
    j = Journal(path, **kwargs)
    try:
        return j.open()
    finally:
        j.close()


def frame(seq: int, payload: bytes) -> bytes:
    seq_bytes = seq.to_bytes(8, "little")
    crc = zlib.crc32(seq_bytes + payload)
    return struct.pack("<II", len(payload), crc) + seq_bytes + payload


class FsyncSpy:
    """Stands in for os.fsync; records the end of the records in the file at each call."""

    def __init__(self) -> None:
        self.sizes: list[int] = []
        self.cond = threading.Condition()

    def __call__(self, fd: int) -> None:
        size = len(os.pread(fd, os.fstat(fd).st_size, 0).rstrip(b"\0"))
        with self.cond:
            self.sizes.append(size)
            self.cond.notify_all()

    def wait_for_size(self, size: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: size in self.sizes, timeout)

    def wait_until(self, done: Callable[[], bool], timeout: float) -> bool:
        """Wait for ``done()``, looked at after each fsync and every 10 ms (the journal counts
        an fsync as done only after it returned)."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while not done():
                if time.monotonic() > deadline:
                    return False
                self.cond.wait(0.01)
        return True


# -- round trip --------------------------------------------------------------------------------


def test_records_come_back_in_order_including_unicode(path: Path) -> None:
    write_records(path, RECORDS)
    assert reopen(path) == RECORDS


def test_a_new_journal_is_just_a_header(path: Path, journal: Journal) -> None:
    assert path.read_bytes() == MAGIC + b"\x01"
    assert journal.size == HEADER_LEN
    assert journal.record_count == 0
    assert journal.recovered_tail_bytes == 0


def test_payloads_are_compact_sorted_utf8_json(path: Path, journal: Journal) -> None:
    journal.append({"b": "ü", "a": [1, 2]})
    assert written(path)[HEADER_LEN + 16 :] == '{"a":[1,2],"b":"ü"}'.encode()


def test_size_and_record_count_track_the_file(path: Path, journal: Journal) -> None:
    for record in RECORDS:
        journal.append(record)
    assert journal.record_count == len(RECORDS)
    assert journal.size == len(written(path))
    journal.close()
    assert journal.size == path.stat().st_size


def test_reopening_continues_the_sequence(path: Path) -> None:
    write_records(path, RECORDS[:2])
    j = Journal(path, fsync="never")
    assert j.open() == RECORDS[:2]
    assert j.record_count == 2
    end = j.size
    j.append(RECORDS[2])
    j.close()
    assert struct.unpack_from("<Q", path.read_bytes(), end + 8) == (3,)
    assert reopen(path) == RECORDS


def test_a_missing_directory_is_created(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "catalog.journal"
    write_records(path, RECORDS[:1])
    assert reopen(path) == RECORDS[:1]


# -- torn tails --------------------------------------------------------------------------------


def test_a_torn_last_record_is_cut_off_at_every_length(
    path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ends = write_records(path, RECORDS)
    full = path.read_bytes()
    for length in range(ends[2], ends[3]):
        path.write_bytes(full[:length])
        caplog.clear()
        j = Journal(path, fsync="never")
        with caplog.at_level(logging.WARNING, logger="temoto.core.registrar.journal"):
            assert j.open() == RECORDS[:2], length
        j.close()
        assert j.recovered_tail_bytes == length - ends[2]
        assert path.stat().st_size == ends[2]
        assert bool(caplog.records) == (length > ends[2])
    path.write_bytes(full)
    assert reopen(path) == RECORDS


def test_a_torn_record_is_followed_by_new_appends(path: Path) -> None:
    ends = write_records(path, RECORDS)
    with path.open("r+b") as f:
        f.truncate(ends[3] - 3)
    j = Journal(path, fsync="never")
    assert j.open() == RECORDS[:2]
    j.append({"again": 3})
    j.close()
    assert reopen(path) == [*RECORDS[:2], {"again": 3}]


def test_a_complete_last_frame_failing_its_crc_is_a_torn_tail(path: Path) -> None:
    ends = write_records(path, RECORDS)
    data = bytearray(path.read_bytes())
    data[ends[3] - 2] ^= 0x20
    path.write_bytes(data)
    j = Journal(path, fsync="never")
    assert j.open() == RECORDS[:2]
    j.close()
    assert j.recovered_tail_bytes == ends[3] - ends[2]


def test_a_zeroed_tail_after_the_last_record_is_cut_off_as_preallocated_space(path: Path) -> None:
    ends = write_records(path, RECORDS)
    with path.open("ab") as f:
        f.write(bytes(4096))
    j = Journal(path, fsync="never")
    assert j.open() == RECORDS
    j.close()
    assert j.recovered_tail_bytes == 0
    assert path.stat().st_size == ends[3]


def test_an_absurd_length_in_a_short_last_frame_is_a_torn_tail(path: Path) -> None:
    ends = write_records(path, RECORDS)
    with path.open("ab") as f:
        f.write(struct.pack("<IIQ", MAX_RECORD_BYTES + 1, 0, 4) + b"{}")
    assert reopen(path) == RECORDS
    assert path.stat().st_size == ends[3]


@pytest.mark.parametrize("content", [b"", b"T", MAGIC, MAGIC[:5]])
def test_an_empty_or_torn_header_starts_a_fresh_journal(
    path: Path, content: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    path.write_bytes(content)
    j = Journal(path, fsync="never")
    with caplog.at_level(logging.WARNING, logger="temoto.core.registrar.journal"):
        assert j.open() == []
    assert "torn header" in caplog.text
    assert j.recovered_tail_bytes == len(content)
    j.append(RECORDS[0])
    j.close()
    assert reopen(path) == RECORDS[:1]


# -- corruption --------------------------------------------------------------------------------


def assert_corrupt(path: Path, offset: int) -> CatalogCorruptError:
    before = path.read_bytes()
    j = Journal(path, fsync="never")
    with pytest.raises(CatalogCorruptError) as info:
        j.open()
    j.close()
    assert path.read_bytes() == before
    assert info.value.offset == offset
    assert info.value.file == str(path)
    assert str(path) in str(info.value)
    assert f"byte {offset}" in str(info.value)
    return info.value


@pytest.mark.parametrize("where", [0, 3, 4, 7, 8, 12, 16, 20, -1], ids=lambda w: f"frame_byte_{w}")
def test_a_flipped_byte_in_a_middle_record_is_corruption(path: Path, where: int) -> None:
    ends = write_records(path, RECORDS)
    data = bytearray(path.read_bytes())
    position = ends[1] + where if where >= 0 else ends[2] + where
    data[position] ^= 0x40
    path.write_bytes(data)
    err = assert_corrupt(path, ends[1])
    assert "valid frame" in str(err) or "sequence number" in str(err)


def test_a_frame_with_an_absurd_length_and_enough_bytes_is_corruption(path: Path) -> None:
    ends = write_records(path, RECORDS[:1])
    with path.open("r+b") as f:
        f.seek(ends[1])
        f.write(struct.pack("<IIQ", MAX_RECORD_BYTES + 1, 0, 2))
        f.truncate(ends[1] + 16 + MAX_RECORD_BYTES + 1)  # sparse
    err = assert_corrupt(path, ends[1])
    assert "over the limit" in str(err)


@pytest.mark.parametrize(
    "content",
    [b"NOTAJOURNAL-AT-ALL", b"temotoj1\x01", b"TEMOTOJ2\x01", b"XY", b"TEMOTOJ1\x01"[:4] + b"X"],
)
def test_a_bad_magic_is_corruption(path: Path, content: bytes) -> None:
    path.write_bytes(content)
    err = assert_corrupt(path, 0)
    assert "magic" in str(err)


def test_an_unsupported_version_is_corruption(path: Path) -> None:
    path.write_bytes(MAGIC + b"\x02" + frame(1, b"{}"))
    err = assert_corrupt(path, len(MAGIC))
    assert "version 2" in str(err)


@pytest.mark.parametrize("seq", [4, 9, 2, 1, 0], ids=["gap", "jump", "repeat", "back", "zero"])
def test_a_sequence_gap_or_repeat_is_corruption(path: Path, seq: int) -> None:
    ends = write_records(path, RECORDS[:2])  # sequence numbers 1 and 2; 3 comes next
    with path.open("ab") as f:
        f.write(frame(seq, b'{"crafted":true}'))
    err = assert_corrupt(path, ends[2])
    assert "sequence number" in str(err)


@pytest.mark.parametrize(
    "payload",
    [b"not json", b"[1,2]", b'"text"', b"42", b"null", b"\xff\xfe{}", b"", b'{"a":1'],
)
def test_a_payload_that_is_not_a_json_object_is_corruption(path: Path, payload: bytes) -> None:
    ends = write_records(path, RECORDS[:1])
    with path.open("ab") as f:
        f.write(frame(2, payload))
    assert_corrupt(path, ends[1])


def test_a_bad_frame_before_a_valid_one_is_corruption_even_when_hand_crafted(path: Path) -> None:
    ends = write_records(path, RECORDS[:1])
    with path.open("ab") as f:
        f.write(b"\x00" * 7)  # a hole that is not a frame...
        f.write(frame(2, b"{}"))  # ...then a valid frame
    err = assert_corrupt(path, ends[1])
    assert f"valid frame at byte {ends[1] + 7}" in str(err)


# -- writing -----------------------------------------------------------------------------------


def test_an_unserialisable_record_raises_type_error_and_writes_nothing(
    path: Path, journal: Journal
) -> None:
    journal.append(RECORDS[0])
    size = journal.size
    circular: dict[str, Any] = {}
    circular["self"] = circular
    for bad in ({"x": object()}, {"x": {1, 2}}, circular, {"x": "\ud800"}, ["not", "a", "map"]):
        with pytest.raises(TypeError):
            journal.append(bad)  # type: ignore[arg-type]
    assert journal.size == size == len(written(path))
    assert journal.record_count == 1


def test_any_mapping_is_accepted(journal: Journal, path: Path) -> None:
    from types import MappingProxyType

    journal.append(MappingProxyType({"a": 1}))
    journal.close()
    assert reopen(path) == [{"a": 1}]


def test_appending_after_close_or_before_open_raises(path: Path) -> None:
    j = Journal(path, fsync="never")
    with pytest.raises(RuntimeError, match="not open"):
        j.append({})
    j.open()
    j.close()
    j.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        j.append({})
    with pytest.raises(RuntimeError, match="already opened"):
        j.open()


def test_bad_settings_are_refused(path: Path) -> None:
    with pytest.raises(ValueError, match="fsync"):
        Journal(path, fsync="sometimes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="fsync_interval"):
        Journal(path, fsync_interval=-1)


def test_a_second_journal_on_the_same_file_is_refused_while_the_first_is_open(path: Path) -> None:
    first = Journal(path, fsync="never")
    first.open()
    second = Journal(path, fsync="never")
    with pytest.raises(ResourceBusyError):
        second.open()
    second.close()
    first.close()
    assert reopen(path) == []


def test_appends_from_many_threads_all_land_in_order(path: Path) -> None:
    j = Journal(path, fsync="group", fsync_interval=0.01)
    j.open()

    def work(thread: int) -> None:
        for i in range(300):
            j.append({"t": thread, "i": i})

    threads = [threading.Thread(target=work, args=(t,)) for t in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    j.close()
    records = reopen(path)
    assert len(records) == 8 * 300
    for thread in range(8):
        assert [r["i"] for r in records if r["t"] == thread] == list(range(300))


# -- rewrite (compaction) ----------------------------------------------------------------------


def test_rewrite_keeps_exactly_the_given_records_and_appends_continue(path: Path) -> None:
    j = Journal(path, fsync="always")
    j.open()
    for i in range(50):
        j.append({"i": i})
    j.rewrite(RECORDS[:2])
    assert j.record_count == 2
    assert j.size == path.stat().st_size
    j.append(RECORDS[2])
    j.close()
    assert reopen(path) == RECORDS
    assert not path.with_name(path.name + ".tmp").exists()


def test_rewrite_to_nothing_leaves_a_bare_header(path: Path, journal: Journal) -> None:
    journal.append(RECORDS[0])
    journal.rewrite([])
    assert path.read_bytes() == MAGIC + b"\x01"
    assert journal.record_count == 0


def test_rewrite_with_an_unserialisable_record_changes_nothing(
    path: Path, journal: Journal
) -> None:
    journal.append(RECORDS[0])
    before = path.read_bytes()
    with pytest.raises(TypeError):
        journal.rewrite([RECORDS[1], {"x": object()}])
    assert path.read_bytes() == before
    assert not path.with_name(path.name + ".tmp").exists()
    journal.append(RECORDS[1])
    journal.close()
    assert reopen(path) == RECORDS[:2]


def test_a_stray_tmp_file_from_a_crashed_rewrite_does_not_confuse_open(path: Path) -> None:
    write_records(path, RECORDS)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(MAGIC + b"\x01" + frame(1, b'{"half":"written"}')[:-3])
    assert reopen(path) == RECORDS
    assert not tmp.exists()


def test_a_rewrite_that_renamed_its_file_is_what_reopens(path: Path) -> None:
    j = Journal(path, fsync="never")
    j.open()
    j.append(RECORDS[0])
    j.rewrite([RECORDS[1]])
    j.close()
    assert reopen(path) == [RECORDS[1]]


# -- fsync policies ----------------------------------------------------------------------------


def test_fsync_always_syncs_every_append_before_it_returns(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    j = Journal(path, fsync="always")
    j.open()
    spy = FsyncSpy()
    monkeypatch.setattr(os, "fsync", spy)
    sizes = []
    for i in range(10):
        j.append({"i": i})
        sizes.append(j.size)
    assert spy.sizes == sizes
    j.close()
    assert spy.sizes == sizes  # nothing left to sync


def test_fsync_never_never_syncs_unless_flushed(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    spy = FsyncSpy()
    monkeypatch.setattr(os, "fsync", spy)
    j = Journal(path, fsync="never")
    j.open()
    for i in range(100):
        j.append({"i": i})
    j.rewrite([{"i": 0}])
    j.append({"i": 1})
    assert spy.sizes == []
    j.flush()
    j.flush()  # nothing new
    assert spy.sizes == [j.size]
    j.append({"i": 2})
    j.close()
    assert spy.sizes == [j.size - len(frame(3, b'{"i":2}'))]


def test_fsync_group_coalesces_appends_and_syncs_soon_after_the_last(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    interval = 0.05
    j = Journal(path, fsync="group", fsync_interval=interval)
    j.open()
    spy = FsyncSpy()
    monkeypatch.setattr(os, "fsync", spy)
    for i in range(1000):
        j.append({"i": i, "pad": "x" * 100})
    assert spy.wait_for_size(j.size, timeout=interval + 5.0)
    # The fsync that found the last record in the file may have been asked for before it was
    # appended (the appends ran on while it did); then one more follows within an interval.
    assert spy.wait_until(lambda: j.unsynced == 0, timeout=interval + 5.0)
    assert 1 <= len(spy.sizes) <= 6
    synced = len(spy.sizes)
    time.sleep(3 * interval)  # idle: the flusher must not sync again
    assert len(spy.sizes) == synced
    j.append({"late": True})
    assert spy.wait_for_size(j.size, timeout=interval + 5.0)
    j.close()
    assert len(spy.sizes) == synced + 1
    assert not any(t.name == "temoto-journal-fsync" for t in threading.enumerate())


def test_close_syncs_what_the_flusher_has_not(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    j = Journal(path, fsync="group", fsync_interval=60.0)
    j.open()
    spy = FsyncSpy()
    monkeypatch.setattr(os, "fsync", spy)
    j.append({"i": 0})  # starts the flusher, which syncs it at once
    assert spy.wait_for_size(j.size, timeout=5.0)
    j.append({"i": 1})  # inside the 60 s rate limit
    j.close()  # must not wait out the interval
    assert spy.sizes[-1] == j.size
    assert len(spy.sizes) == 2


def test_flush_syncs_only_when_something_is_unsynced(
    path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    j = Journal(path, fsync="always")
    j.open()
    spy = FsyncSpy()
    monkeypatch.setattr(os, "fsync", spy)
    j.flush()
    assert spy.sizes == []
    j.append({})
    j.flush()
    assert len(spy.sizes) == 1
    j.close()


# -- SIGKILL -----------------------------------------------------------------------------------

CHILD = """
import os, sys
sys.path.insert(0, sys.argv[1])
from temoto.core.registrar.journal import Journal
j = Journal(sys.argv[2], fsync=sys.argv[3], fsync_interval=0.005, serialized=sys.argv[4] == "1")
j.open()
os.write(1, b"ready\\n")
for i in range(10**7):
    j.append({"i": i, "pad": "ü" * 40})
    os.write(1, b"%d\\n" % i)
"""


@pytest.mark.slow
def test_every_record_reported_as_appended_survives_sigkill(tmp_path: Path) -> None:
    rng = random.Random(20240611)
    for run in range(20):
        path = tmp_path / f"kill-{run}.journal"
        policy = ("never", "group", "always")[run % 3]
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(ROOT), str(path), policy, str(run % 2)],
            stdout=subprocess.PIPE,
        )
        try:
            assert child.stdout is not None
            assert child.stdout.readline() == b"ready\n"
            time.sleep(rng.uniform(0.0, 0.05))
            child.send_signal(signal.SIGKILL)
            out = child.stdout.read()
        finally:
            child.kill()
            child.wait()
            if child.stdout is not None:
                child.stdout.close()
        assert child.returncode == -signal.SIGKILL
        reported = sum(1 for line in out.split(b"\n")[:-1])
        records = reopen(path, fsync="never")
        assert reported <= len(records) <= reported + 1, (run, policy)
        assert records == [{"i": i, "pad": "ü" * 40} for i in range(len(records))]


def test_the_compact_encoding_matches_json_dumps(path: Path, journal: Journal) -> None:
    journal.append(RECORDS[1])
    payload = written(path)[HEADER_LEN + 16 :]
    expected = json.dumps(RECORDS[1], sort_keys=True, ensure_ascii=False, separators=(",", ":"))
    assert payload == expected.encode()


def test_append_text_writes_a_record_read_back_like_any_other(path: Path) -> None:
    j = Journal(path, fsync="never")
    j.open()
    j.append_text('{"id":"a-1","op":"unref","resumes":["b ✓"]}')
    size = j.size
    with pytest.raises(ValueError, match="over"):
        j.append_text('{"x":"' + "a" * MAX_RECORD_BYTES + '"}')
    assert j.size == size  # nothing written
    j.close()
    assert reopen(path) == [{"id": "a-1", "op": "unref", "resumes": ["b ✓"]}]


# -- the mapped, preallocated file ---------------------------------------------------------------


def test_the_file_is_preallocated_while_open_and_exact_once_closed(path: Path) -> None:
    j = Journal(path, fsync="never")
    j.open()
    j.append(RECORDS[0])
    assert path.stat().st_size >= j.size + 4096  # room for the next appends, zeros
    assert path.read_bytes()[j.size :].count(0) == path.stat().st_size - j.size
    j.close()
    assert path.stat().st_size == j.size


def test_preallocated_zeros_left_by_a_killed_process_are_not_a_torn_tail(
    path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    j = Journal(path, fsync="never")
    j.open()
    for record in RECORDS:
        j.append(record)
    size = j.size
    copy = path.with_name("killed.journal")
    copy.write_bytes(path.read_bytes())  # what SIGKILL leaves: the records, then zeros
    j.close()
    assert copy.stat().st_size > size
    k = Journal(copy, fsync="never")
    with caplog.at_level(logging.WARNING):
        assert k.open() == RECORDS
    k.close()
    assert k.recovered_tail_bytes == 0
    assert not caplog.records
    assert copy.read_bytes() == path.read_bytes()


def test_a_frame_killed_while_copied_in_is_a_torn_tail(
    path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ends = write_records(path, RECORDS)
    data = bytearray(path.read_bytes())
    data[ends[2] : ends[2] + 16] = bytes(16)  # the payload was copied in, the head was not
    path.write_bytes(bytes(data) + bytes(100_000))  # and the preallocated zeros after it
    with caplog.at_level(logging.WARNING):
        assert reopen(path) == RECORDS[:2]
    assert "torn last record" in caplog.text
    assert path.stat().st_size == ends[2]


def test_appends_cross_the_preallocated_space_and_records_larger_than_it(path: Path) -> None:
    big = {"blob": "x" * (3 << 20)}  # three times the preallocation step
    records = [{"i": i, "pad": "y" * 300} for i in range(8000)]  # > 2 MiB in all
    records[4000:4000] = [big]
    j = Journal(path, fsync="never")
    j.open()
    for record in records:
        j.append(record)
    j.close()
    assert reopen(path) == records


def test_a_full_disk_refuses_the_append_and_writes_nothing(
    path: Path, journal: Journal, monkeypatch: pytest.MonkeyPatch
) -> None:
    journal.append(RECORDS[0])
    size = journal.size

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    monkeypatch.setattr(os, "ftruncate", full)
    with pytest.raises(OSError, match="No space"):
        journal.append({"big": "z" * (2 << 20)})  # needs more than is allocated
    assert journal.size == size
    assert journal.record_count == 1
    monkeypatch.undo()
    journal.append(RECORDS[1])
    journal.close()
    assert reopen(path) == RECORDS[:2]


def test_a_file_that_cannot_be_mapped_is_appended_to_with_pwrite(
    path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import mmap

    def unmappable(*args: Any, **kwargs: Any) -> mmap.mmap:
        raise OSError(19, "No such device")

    monkeypatch.setattr(mmap, "mmap", unmappable)
    j = Journal(path, fsync="never")
    j.open()
    with caplog.at_level(logging.WARNING):
        for record in RECORDS:
            j.append(record)
        j.append({"big": "b" * (2 << 20)})  # past the first allocation
    assert caplog.text.count("cannot be mapped") == 1
    assert path.stat().st_size > j.size  # preallocated all the same
    copy = path.with_name("killed.journal")
    copy.write_bytes(path.read_bytes())
    j.close()
    assert path.stat().st_size == j.size
    assert reopen(path) == [*RECORDS, {"big": "b" * (2 << 20)}]
    assert reopen(copy) == [*RECORDS, {"big": "b" * (2 << 20)}]


def test_a_serialized_journal_wakes_its_flusher_after_every_idle_spell(path: Path) -> None:
    j = Journal(path, fsync="group", fsync_interval=0.001, serialized=True)
    j.open()
    spy = FsyncSpy()  # only for its condition: os.fsync itself runs
    written = []
    for burst in range(40):
        for i in range(burst % 4 + 1):
            record = {"burst": burst, "i": i}
            j.append(record)
            written.append(record)
        # the flusher was waiting (or about to): each burst must be synced without another
        assert spy.wait_until(lambda: j.unsynced == 0, timeout=10.0), burst
    j.close()
    assert reopen(path) == written
