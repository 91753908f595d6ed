"""The ``temoto`` console script: imports the command line with Ctrl-C taken care of.

A module outside the ``temoto`` package, so that nothing of it is imported before the
``try``: importing :mod:`temoto.cli` takes 0.1-0.2 s (seconds on a loaded machine), and a
Ctrl-C in that time printed a ``KeyboardInterrupt`` traceback. Now it ends the command quietly
with status 130, like a Ctrl-C once the command runs.
"""

from __future__ import annotations

import sys

__all__ = ["main"]


def main() -> int:
    """Import and run :func:`temoto.cli.main`.

    Returns:
        The exit status: for a Ctrl-C during the imports, 130, or 0 for ``temoto serve`` (a
        service stopped as asked, as once it runs).
    """
    try:
        from temoto.cli import main as cli_main
    except KeyboardInterrupt:
        command = next((a for a in sys.argv[1:] if not a.startswith("-")), "")
        return 0 if command == "serve" else 130
    return cli_main()


if __name__ == "__main__":
    sys.exit(main())
