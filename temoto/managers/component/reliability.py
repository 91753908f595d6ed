"""Reliability of a component candidate: a moving average of its outcomes (upstream's filter).

Upstream (``temoto_core``'s reliability filter, docs/design.md §6) keeps the last 100 ratings,
starts at 0.8 and clamps to [0, 1]. This is the same: a window of ``window`` outcomes,
pre-filled with the initial value, so a fresh candidate reads the initial value and each
outcome moves it by ``(outcome - oldest) / window``. Outcomes are 1.0 (served until released
without failing) and 0.0 (failed to start, or failed while active).

By default reliabilities are kept in memory only: a restarted manager starts again from the
descriptions' initial values. With a *reliability file* (``ComponentManager(...,
reliability_file=...)``) the recorded outcomes survive a restart. The file is JSON::

    {
     "version": 1,
     "window": 100,
     "components": {
      "robot_1/depth_camera": {"outcomes": [1]},
      "robot_1/lidar_3d": {"outcomes": [0, 0, 1]}
     }
    }

* ``version``: the format, 1.
* ``window``: the window of the manager that wrote it (a manager with a smaller window keeps
  only the newest outcomes).
* ``components``: per candidate key ``robot/name``, the outcomes it has *recorded*, oldest
  first, at most ``window`` of them: numbers in [0, 1] (``1`` success, ``0`` failure; ``true``
  and ``false`` are read as 1 and 0). The pre-filled initial values are not stored: a restored
  candidate starts from its description's initial value with these outcomes added, so a
  changed initial value still applies. Candidates that recorded nothing are left out.

:func:`save_outcomes` replaces the file atomically (``<file>.tmp`` in the same folder, flushed
and fsynced, ``os.replace`` over the file, the folder fsynced): after a crash at any instant the
file is the old one or the new one, complete. :func:`load_outcomes` ignores a stale
``<file>.tmp`` and raises :class:`~temoto.errors.ConfigError` naming the file for anything it
cannot use (not JSON, another version, a value of the wrong type or out of range).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from temoto.errors import ConfigError

__all__ = ["RELIABILITY_FILE_VERSION", "Reliability", "load_outcomes", "save_outcomes"]

#: The reliability file format this module reads and writes.
RELIABILITY_FILE_VERSION = 1

_TOP_KEYS = frozenset({"version", "window", "components"})


class Reliability:
    """A sliding-window mean of outcomes in [0, 1].

    Args:
        initial: The starting value (clamped to [0, 1]).
        window: How many outcomes the mean covers (>= 1).
        history: Outcomes recorded before (oldest first), added after the pre-fill; only the
            newest ``window`` count.

    Raises:
        ValueError: ``window`` < 1.
    """

    __slots__ = ("_recorded", "_sum", "_window")

    def __init__(
        self, initial: float = 0.8, window: int = 100, history: Iterable[float] = ()
    ) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        start = _clamp(initial)
        self._window: deque[float] = deque([start] * window, maxlen=window)
        self._sum = start * window
        self._recorded = 0
        for outcome in list(history)[-window:]:
            self.adjust(outcome)

    @property
    def value(self) -> float:
        """The current reliability, in [0, 1]."""
        return _clamp(self._sum / len(self._window))

    def adjust(self, outcome: float) -> float:
        """Add an outcome (clamped to [0, 1]); the oldest one leaves the window.

        Args:
            outcome: 1.0 for a success, 0.0 for a failure (values between are allowed).

        Returns:
            The new reliability.
        """
        rating = _clamp(outcome)
        self._sum += rating - self._window[0]
        self._window.append(rating)
        self._recorded = min(self._recorded + 1, len(self._window))
        return self.value

    def outcomes(self) -> list[float]:
        """The recorded outcomes still in the window, oldest first (not the pre-fill).

        Returns:
            At most ``window`` values in [0, 1].
        """
        if self._recorded == 0:
            return []
        return list(self._window)[len(self._window) - self._recorded :]

    def __repr__(self) -> str:
        return f"Reliability({self.value:.4f})"


def _clamp(value: float) -> float:
    return min(1.0, max(0.0, float(value)))


# ---------------------------------------------------------------------- the reliability file


def load_outcomes(path: str | Path, window: int) -> dict[str, list[float]]:
    """Read a reliability file (the format is in the module docstring).

    Args:
        path: The file. A missing file is an empty history.
        window: Keep only the newest ``window`` outcomes of each candidate.

    Returns:
        Candidate key ``robot/name`` -> its outcomes, oldest first.

    Raises:
        ConfigError: The file cannot be read, is not JSON, has another version, or holds an
            invalid value (the message names the file and the key path).
    """
    file = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read the reliability file: {err}", file=file) from err
    try:
        data: Any = json.loads(text)
    except ValueError as err:  # JSONDecodeError, or an integer too long to convert
        raise ConfigError(f"not a JSON reliability file: {err}", file=file) from err
    if not isinstance(data, dict):
        raise ConfigError(f"expected a JSON object, got {_kind(data)}", file=file)
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"unknown key(s): {', '.join(unknown)}", file=file)
    version = data.get("version")
    if version != RELIABILITY_FILE_VERSION or isinstance(version, bool):
        raise ConfigError(
            f"unsupported version {version!r} (this TeMoto reads version "
            f"{RELIABILITY_FILE_VERSION})",
            file=file,
            path="version",
        )
    saved_window = data.get("window")
    if isinstance(saved_window, bool) or not isinstance(saved_window, int) or saved_window < 1:
        raise ConfigError(
            f"must be an integer >= 1, got {saved_window!r}", file=file, path="window"
        )
    components = data.get("components")
    if not isinstance(components, dict):
        raise ConfigError(
            f"must be an object, got {_kind(components)}", file=file, path="components"
        )
    restored: dict[str, list[float]] = {}
    for key, entry in components.items():
        where = f"components[{key!r}]"
        robot, _, name = key.partition("/")
        if not robot or not name:
            raise ConfigError("a key must be 'robot/name'", file=file, path=where)
        if not isinstance(entry, dict) or set(entry) != {"outcomes"}:
            raise ConfigError(
                "must be an object with exactly the key 'outcomes'", file=file, path=where
            )
        outcomes = entry["outcomes"]
        if not isinstance(outcomes, list):
            raise ConfigError(
                f"must be a list, got {_kind(outcomes)}", file=file, path=f"{where}.outcomes"
            )
        values: list[float] = []
        for i, raw in enumerate(outcomes):
            value = _outcome(raw)
            if value is None:
                raise ConfigError(
                    f"an outcome must be a number in [0, 1] or a boolean, got {raw!r}",
                    file=file,
                    path=f"{where}.outcomes[{i}]",
                )
            values.append(value)
        restored[key] = values[-window:]
    return restored


def save_outcomes(path: str | Path, window: int, outcomes: Mapping[str, Sequence[float]]) -> None:
    """Replace a reliability file atomically (the format is in the module docstring).

    Writes ``<file>.tmp`` in the same folder, flushes and fsyncs it, renames it over the file
    and fsyncs the folder: a crash at any instant leaves the old file or the new one, complete.

    Args:
        path: The file.
        window: The writer's window (recorded in the file).
        outcomes: Candidate key -> its recorded outcomes, oldest first.

    Returns:
        None.

    Raises:
        OSError: The file could not be written (the old file is unchanged).
    """
    file = Path(path)
    lines = [
        f'  {json.dumps(key)}: {{"outcomes": {json.dumps([_plain(v) for v in values])}}}'
        for key, values in sorted(outcomes.items())
        if values
    ]
    text = (
        "{\n"
        f' "version": {RELIABILITY_FILE_VERSION},\n'
        f' "window": {window},\n'
        ' "components": {' + ("\n" + ",\n".join(lines) + "\n }" if lines else "}") + "\n}\n"
    )
    tmp = file.with_name(file.name + ".tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, file)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    _fsync_folder(file.parent)


def _fsync_folder(folder: Path) -> None:
    """Make the rename durable (POSIX: fsync the directory)."""
    if os.name == "nt":  # pragma: no cover - directories cannot be opened there
        return
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _outcome(raw: object) -> float | None:
    """An outcome read from the file, or None if it is not one."""
    if isinstance(raw, bool):
        return 1.0 if raw else 0.0
    if isinstance(raw, int | float) and 0 <= raw <= 1:  # NaN and infinities compare False
        return float(raw)
    return None


def _plain(value: float) -> float | int:
    """``1``/``0`` for a success/failure (readable), the number otherwise."""
    if value in (0.0, 1.0):
        return int(value)
    return value


def _kind(value: object) -> str:
    return "null" if value is None else type(value).__name__
