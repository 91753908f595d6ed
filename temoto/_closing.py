"""``with`` support for anything that has a ``close()``: leaving the block closes it."""

from __future__ import annotations

from types import TracebackType
from typing import Self

__all__ = ["Closing"]


class Closing:
    """Context-manager support: ``with x:`` returns ``x`` and calls ``x.close()`` on the way out."""

    def close(self) -> None:  # pragma: no cover - every subclass defines it
        """Release what the object holds."""
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
