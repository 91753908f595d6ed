"""``python -m temoto``: the command line (see :mod:`temoto.cli`).

``import temoto`` imports none of the framework (its public names load on first use), so the
command line's modules are all imported inside the ``try`` below: a Ctrl-C while they load
ends the command quietly, 130 (0 for ``temoto serve``, a service stopped as asked), as with the
``temoto`` console script.
"""

from __future__ import annotations

import sys

if __name__ == "__main__":
    try:
        from temoto.cli import main
    except KeyboardInterrupt:
        command = next((a for a in sys.argv[1:] if not a.startswith("-")), "")
        sys.exit(0 if command == "serve" else 130)
    sys.exit(main())
