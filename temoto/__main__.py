"""``python -m temoto``: the command line (see :mod:`temoto.cli`)."""

from __future__ import annotations

import sys

from temoto.cli import main

if __name__ == "__main__":
    sys.exit(main())
