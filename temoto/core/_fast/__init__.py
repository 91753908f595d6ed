"""Hot paths with a compiled twin: the one place the rest of TeMoto imports them from.

Each kernel ``x`` is written once as typed, plain Python in ``_x_py.py``; ``setup.py`` compiles
that same file with Cython as the extension ``_x_c`` (``_x_c.pxd`` adds the C declarations), see
docs/development.md §7 and ``docs/fast.md``. This selector decides once, at import:

- ``TEMOTO_NO_EXTENSIONS`` set (to anything but ``""`` or ``0``), or an interpreter other than
  CPython: the pure-Python modules are used.
- Otherwise the compiled modules are tried first; if any is missing (no compiler when TeMoto
  was installed), all pure modules are used and a warning is logged once.
- ``TEMOTO_REQUIRE_EXTENSIONS=1`` turns that fallback into an :class:`ImportError` (CI sets it,
  so a broken build cannot silently pass as the pure one).

Attributes:
    COMPILED: True if the compiled kernels are in use.
    BUILD: ``"compiled"`` or ``"pure"``, for ``temoto --version`` and start-up logs.
    Evolution: The evolution kernel (:mod:`temoto.core._fast._evolution_py`).
    RefBook: The registrar's reference-count and dependency book
        (:mod:`temoto.core._fast._refbook_py`).
    R_TRUE, R_FALSE, R_STOPPED, R_ERROR: The evolution kernel's result codes.
    P_RUN, P_PAUSE, P_RESTART, P_STOP, P_BYPASS, P_IGNORE, P_LOOP: Its response codes.
    SHIFT: A wave step is ``edge << SHIFT | response << 1 | ready``.

The codes are plain integers, defined once in ``_evolution_py.py`` and read from the kernel
module in use (the compiled one keeps them as module attributes).
"""

from __future__ import annotations

import importlib
import logging
import os
import platform
from typing import TYPE_CHECKING

__all__ = [
    "BUILD",
    "COMPILED",
    "P_BYPASS",
    "P_IGNORE",
    "P_LOOP",
    "P_PAUSE",
    "P_RESTART",
    "P_RUN",
    "P_STOP",
    "R_ERROR",
    "R_FALSE",
    "R_STOPPED",
    "R_TRUE",
    "SHIFT",
    "Evolution",
    "RefBook",
    "kernels",
]

logger = logging.getLogger(__name__)

#: The kernels; each has a ``_<name>_py.py`` source and a ``_<name>_c`` extension.
KERNELS = ("evolution", "refbook")


def _flag(name: str) -> bool:
    return os.environ.get(name, "") not in ("", "0")


def _load_compiled() -> tuple[object, ...] | None:
    """Import every compiled kernel, or None if extensions are off or any is missing."""
    if _flag("TEMOTO_NO_EXTENSIONS") or platform.python_implementation() != "CPython":
        return None
    try:
        modules = tuple(importlib.import_module(f"{__name__}._{k}_c") for k in KERNELS)
    except ImportError as err:
        if _flag("TEMOTO_REQUIRE_EXTENSIONS"):
            raise ImportError(
                "TEMOTO_REQUIRE_EXTENSIONS is set but the compiled kernels cannot be imported"
                f" ({err}); reinstall with a C compiler and Cython available"
                " (pip install -e .), or unset TEMOTO_REQUIRE_EXTENSIONS"
            ) from err
        logger.warning(
            "temoto: compiled kernels not available (%s); using the pure-Python build, which is"
            " slower. Reinstall with a C compiler to build them.",
            err,
        )
        return None
    return modules


if TYPE_CHECKING:
    from temoto.core._fast._evolution_py import (
        P_BYPASS,
        P_IGNORE,
        P_LOOP,
        P_PAUSE,
        P_RESTART,
        P_RUN,
        P_STOP,
        R_ERROR,
        R_FALSE,
        R_STOPPED,
        R_TRUE,
        SHIFT,
        Evolution,
    )
    from temoto.core._fast._refbook_py import RefBook

    COMPILED = False
else:
    _compiled = _load_compiled()
    if _compiled is None:
        from temoto.core._fast import _evolution_py as _evolution
        from temoto.core._fast._refbook_py import RefBook

        COMPILED = False
    else:
        _evolution = _compiled[0]
        RefBook = _compiled[1].RefBook
        COMPILED = True
    Evolution = _evolution.Evolution
    # the kernel's codes, from the module in use (one definition: _evolution_py.py)
    R_TRUE, R_FALSE, R_STOPPED, R_ERROR = (
        _evolution.R_TRUE,
        _evolution.R_FALSE,
        _evolution.R_STOPPED,
        _evolution.R_ERROR,
    )
    P_RUN, P_PAUSE, P_RESTART, P_STOP = (
        _evolution.P_RUN,
        _evolution.P_PAUSE,
        _evolution.P_RESTART,
        _evolution.P_STOP,
    )
    P_BYPASS, P_IGNORE, P_LOOP = _evolution.P_BYPASS, _evolution.P_IGNORE, _evolution.P_LOOP
    SHIFT = _evolution.SHIFT
    del _compiled, _evolution

BUILD = "compiled" if COMPILED else "pure"


def kernels() -> dict[str, str]:
    """Which file each kernel was loaded from (for diagnostics and tests).

    Returns:
        Kernel name -> module file path.
    """
    import sys

    out: dict[str, str] = {}
    for name, cls in (("evolution", Evolution), ("refbook", RefBook)):
        module = sys.modules[cls.__module__]
        out[name] = str(getattr(module, "__file__", "?"))
    return out
