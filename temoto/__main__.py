"""``python -m temoto``: the command line (see :mod:`temoto.cli`)."""

from __future__ import annotations

import sys

if __name__ == "__main__":
    try:
        from temoto.cli import main
    except KeyboardInterrupt:  # a Ctrl-C during the imports: no traceback (status 130)
        sys.exit(130)
    sys.exit(main())
