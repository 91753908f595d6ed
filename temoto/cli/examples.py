"""``temoto examples DIR``: copy the examples and hardware profiles the docs use into DIR.

Like every module of :mod:`temoto.cli`, it prints.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

__all__ = ["add_parser", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto examples DIR``."""
    ex = sub.add_parser(
        "examples",
        help="copy the examples and hardware profiles the docs use into a folder",
        description="Copy examples/ and hw_profiles/ (as in the repository) into DIR, so that"
        " the commands of the README and docs/ run from DIR with an installed wheel.",
    )
    ex.add_argument("dir", metavar="DIR", help="the folder (made if missing)")


def main(args: argparse.Namespace) -> int:
    """Run ``temoto examples DIR``."""
    from temoto.examples import copy_examples

    for folder in copy_examples(args.dir):
        sys.stdout.write(f"wrote {folder}\n")
    return 0


if __name__ == "__main__":  # python -m temoto.cli.examples: temoto examples, on its own
    from temoto.cli import command_main

    sys.exit(command_main("examples"))
