"""Actions shipped with TeMoto, in folders an engine's catalog can scan.

* :data:`ROBOT_ACTIONS`: the robot verbs (navigate, move joints, take off, fly, land, wait),
  which need a Robot Manager on the engine's registrar (``python -m temoto.managers.robot``
  adds the folder to its catalog).
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

__all__ = ["ROBOT_ACTIONS"]

#: The folder of the built-in robot actions.
ROBOT_ACTIONS: Final = Path(__file__).resolve().parent / "robot"
