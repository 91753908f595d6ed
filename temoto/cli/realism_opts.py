"""``--realism off|typical|harsh`` and ``--seed N``: the simulators' imperfect world.

Every command that runs simulators takes both: ``typical`` by default (seeded sensor noise,
stream jitter, now and then a late or lost frame: :mod:`temoto.drivers.realism`, figures in
``docs/simulators.md``, "Realism"), ``off`` for today's exact figures. The seed is chosen at
random unless given, and printed once on stderr (``realism typical, seed N``) so a failing run
can be replayed with ``--seed N``.
"""

from __future__ import annotations

import argparse
from typing import IO

from temoto.drivers.realism import LEVEL_NAMES, new_seed

__all__ = ["DEFAULT_REALISM", "add_realism_options", "announce_realism", "resolve_seed"]

#: The level a command runs its simulators at unless told otherwise.
DEFAULT_REALISM = "typical"


def _seed(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {value}")
    return value


def add_realism_options(parser: argparse.ArgumentParser, *, suppress: bool = False) -> None:
    """Add ``--realism`` and ``--seed`` to a command that runs simulators.

    Args:
        parser: The command's parser.
        suppress: Leave the names unset when not given (for subparsers sharing them: read
            them with :func:`resolve_seed`, which fills in the defaults).
    """
    parser.add_argument(
        "--realism",
        choices=LEVEL_NAMES,
        default=argparse.SUPPRESS if suppress else DEFAULT_REALISM,
        help="the simulators' imperfections: seeded sensor noise, stream jitter, late and lost"
        f" frames (docs/simulators.md, Realism; default {DEFAULT_REALISM}; off: exact figures)",
    )
    parser.add_argument(
        "--seed",
        type=_seed,
        default=argparse.SUPPRESS if suppress else None,
        metavar="N",
        help="the realism's random seed (default: a fresh one, printed; give it again to"
        " replay a run)",
    )


def resolve_seed(args: argparse.Namespace) -> int | None:
    """The run's seed: ``--seed``, else a fresh one (None at ``--realism off``).

    Args:
        args: Parsed with :func:`add_realism_options`.

    Returns:
        The seed, stored back in ``args.seed`` (``args.realism`` gets its default too).
    """
    args.realism = getattr(args, "realism", DEFAULT_REALISM)
    args.seed = getattr(args, "seed", None)
    if args.realism == "off":
        args.seed = None
    elif args.seed is None:
        args.seed = new_seed()
    seed: int | None = args.seed
    return seed


def announce_realism(args: argparse.Namespace, out: IO[str]) -> None:
    """Print ``realism <level>, seed <N>`` (or ``realism off``) once, on ``out``.

    Args:
        args: Parsed with :func:`add_realism_options`, the seed resolved.
        out: Where to print (stderr).
    """
    if args.realism == "off":
        out.write("realism off\n")
    else:
        out.write(f"realism {args.realism}, seed {args.seed}\n")
    out.flush()
