"""The examples and hardware profiles the docs use, from an installed wheel or a clone.

A wheel carries the repository's ``examples/`` and ``hw_profiles/`` as package data
(``temoto/_examples/``, copied by ``setup.py``); in a clone (an editable install) they are the
repository's own folders. ``temoto examples DIR`` copies them into ``DIR``, so that the
commands of README.md and docs/ run from ``DIR`` as they do from a clone.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from temoto.errors import ConfigError

__all__ = ["EXAMPLE_DIRS", "copy_examples", "examples_root"]

#: The folders copied (as in the repository).
EXAMPLE_DIRS = ("examples", "hw_profiles")


def examples_root() -> Path:
    """The folder holding ``examples/`` and ``hw_profiles/``.

    Returns:
        The wheel's ``temoto/_examples``, or the clone's root.

    Raises:
        ConfigError: Neither has them (a wheel built without them).
    """
    package = Path(__file__).resolve().parent
    for root in (package / "_examples", package.parent):
        if all((root / name).is_dir() for name in EXAMPLE_DIRS):
            return root
    raise ConfigError(
        "this installation has no examples (a wheel built without them): use a clone of the"
        " repository"
    )


def copy_examples(target: str | Path) -> list[Path]:
    """Copy the examples and hardware profiles into ``target`` (made if missing).

    Args:
        target: The folder; ``examples/`` and ``hw_profiles/`` are made in it.

    Returns:
        The folders made.

    Raises:
        ConfigError: One of them exists already in ``target``, or cannot be written.
    """
    root = examples_root()
    out = Path(target)
    made = []
    for name in EXAMPLE_DIRS:
        if (out / name).exists():
            raise ConfigError(f"{out / name}: exists already (nothing was copied over it)")
    try:
        for name in EXAMPLE_DIRS:
            shutil.copytree(
                root / name,
                out / name,
                ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
            )
            made.append(out / name)
    except OSError as err:
        raise ConfigError(f"{out}: cannot copy the examples: {err.strerror or err}") from None
    return made
