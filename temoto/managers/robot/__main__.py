"""``python -m temoto.managers.robot --profile hw_profiles/<robot>.yaml``: one robot's instance.

A thin entry: the command is :mod:`temoto.cli.robot`.
"""

from __future__ import annotations

import sys

if __name__ == "__main__":
    from temoto.cli.robot import main

    sys.exit(main())
