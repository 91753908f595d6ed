"""Reliability of a component candidate: a moving average of its outcomes (upstream's filter).

Upstream (``temoto_core``'s reliability filter, REFERENCE §4.3) keeps the last 100 ratings, starts
at 0.8 and clamps to [0, 1]. This is the same: a window of ``window`` outcomes, pre-filled with
the initial value, so a fresh candidate reads the initial value and each outcome moves it by
``(outcome - oldest) / window``. Outcomes are 1.0 (served until released without failing) and
0.0 (failed to start, or failed while active). Kept in memory only: a restarted manager starts
again from the descriptions' initial values.
"""

from __future__ import annotations

from collections import deque

__all__ = ["Reliability"]


class Reliability:
    """A sliding-window mean of outcomes in [0, 1].

    Args:
        initial: The starting value (clamped to [0, 1]).
        window: How many outcomes the mean covers (>= 1).

    Raises:
        ValueError: ``window`` < 1.
    """

    __slots__ = ("_sum", "_window")

    def __init__(self, initial: float = 0.8, window: int = 100) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        start = _clamp(initial)
        self._window: deque[float] = deque([start] * window, maxlen=window)
        self._sum = start * window

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
        return self.value

    def __repr__(self) -> str:
        return f"Reliability({self.value:.4f})"


def _clamp(value: float) -> float:
    return min(1.0, max(0.0, float(value)))
