"""``temoto demo N``: one of the thesis' five demonstrations, headless, on the simulators.

The first signal raises :class:`~temoto.cli.signals.Interrupted` inside the demonstration,
which cleans up on its way out as it does for Ctrl-C. Like every module of :mod:`temoto.cli`,
it prints.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from temoto.cli.common import (
    EXIT_INVALID,
    EXIT_OTHER_RESULT,
    EXIT_TRUE,
    error,
    factor,
    signal_name,
)
from temoto.cli.realism_opts import add_realism_options, announce_realism, resolve_seed
from temoto.cli.signals import FORCE_EXIT_S, Interrupted, SignalExit, make_devices_safe
from temoto.managers.visualization.live import add_foxglove_option

__all__ = ["add_parser", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto demo N``."""
    demo = sub.add_parser(
        "demo",
        help="run one of the thesis' five demonstrations on the simulators",
        description="Run a demonstration headless and print its timeline (docs/demos.md).",
    )
    demo.add_argument("number", type=int, choices=range(1, 6), metavar="N", help="1 to 5")
    demo.add_argument(
        "--speed",
        type=factor,
        default=1.0,
        metavar="F",
        help="run the robots' clocks F times faster than real time (default 1)",
    )
    add_realism_options(demo)  # the robots' simulators (demonstrations 2 to 5)
    add_foxglove_option(demo)  # demonstration 1's displays, live (docs/visualization.md)


def main(args: argparse.Namespace) -> int:
    """Run ``temoto demo N``: exit 0 iff the demonstration's checks passed."""
    from temoto.demos import DEMOS, run_demo

    # The first signal raises KeyboardInterrupt (Interrupted) inside the demonstration, which
    # cleans up on its way out as it does for Ctrl-C; its processes are stopped by then.
    resolve_seed(args)
    if args.number != 1:  # demonstration 1's sensors are processes, not simulated devices
        announce_realism(args, sys.stderr)
    try:
        with SignalExit(raise_first=True, force_exit=FORCE_EXIT_S) as signals:
            try:
                report = run_demo(
                    args.number,
                    sys.stdout,
                    speed=args.speed,
                    foxglove=_fg(args),
                    realism=args.realism,
                    seed=args.seed,
                )
            finally:
                signals.raising = False
                if signals.signum is not None:
                    make_devices_safe(f"temoto demo stopped by {signal_name(signals.signum)}")
    except Interrupted as stop:
        sys.stderr.write(f"temoto: demonstration {args.number} stopped\n")
        return 128 + stop.signum
    except ModuleNotFoundError as err:
        if not (err.name or "").startswith("temoto.demos"):
            raise
        error(f"demonstration {args.number} ({DEMOS[args.number][0]}) is not built yet")
        return EXIT_INVALID
    except ValueError as err:
        error(err)
        return EXIT_INVALID
    if signals.exit_code is not None:  # the signal came after the demonstration had ended
        return signals.exit_code
    return EXIT_TRUE if report.ok else EXIT_OTHER_RESULT


def _fg(args: argparse.Namespace) -> tuple[str, int] | None:
    """``--foxglove [PORT]`` and ``--foxglove-host`` as ``run_demo`` takes them."""
    return None if args.foxglove is None else (args.foxglove_host, args.foxglove)


if __name__ == "__main__":  # python -m temoto.cli.demo: temoto demo, on its own
    from temoto.cli import command_main

    sys.exit(command_main("demo"))
