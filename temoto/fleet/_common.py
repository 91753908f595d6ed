"""Deprecated alias of :mod:`temoto.fleet.common`, kept while the managers move to it."""

from __future__ import annotations

from temoto.fleet.common import (
    CallQueue,
    Closing,
    check_clock,
    check_name,
    check_seconds,
    decode_or_count,
    new,
)

__all__ = [
    "CallQueue",
    "Closing",
    "check_clock",
    "check_name",
    "check_seconds",
    "decode_or_count",
    "new",
]
