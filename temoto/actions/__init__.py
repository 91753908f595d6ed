"""Action plugins: the :class:`Action` base class that action authors subclass."""

from __future__ import annotations

from temoto.core.action import Action, Inputs, Outputs
from temoto.errors import StopRequested

__all__ = ["Action", "Inputs", "Outputs", "StopRequested"]
