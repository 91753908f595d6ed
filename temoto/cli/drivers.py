"""The driver side of the command line: ``temoto drivers list`` and ``temoto drivers detect``.

``detect`` asks each driver's :meth:`~temoto.drivers.base.Driver.detect` for the devices it can
reach and prints them as a hardware profile's ``devices:`` block (YAML, or JSON with
``--json``), ready to paste into a profile and rename joints in. Looking never moves anything:
drivers only listen or ping (``docs/robot-manager.md``).

Kept apart from :mod:`temoto.cli` (which owns the parser, logging and exit codes) so that other
commands import no driver code. Like :mod:`temoto.cli`, this module prints.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from typing import IO, Any

from temoto.cli.common import EXIT_FAILED, EXIT_INVALID, EXIT_OK
from temoto.errors import ConfigError, DriverUnavailableError, PluginError

__all__ = ["add_parser", "main"]

#: ``detect`` found no device.
EXIT_NOTHING = EXIT_FAILED

#: The library each built-in driver's extra installs (to say which are usable without importing).
_LIBRARY = {"can": "can", "dynamixel": "dynamixel_sdk", "mavlink": "pymavlink"}


def add_parser(sub: Any) -> None:
    """Add ``temoto drivers list|detect`` to the top-level subparsers.

    Args:
        sub: The ``add_subparsers()`` object of the top-level parser.

    Returns:
        None.
    """
    drivers = sub.add_parser("drivers", help="device drivers: list them, find devices")
    dsub = drivers.add_subparsers(dest="drivers_command", required=True, metavar="TOOL")
    dsub.add_parser("list", help="the drivers a profile can name, and whether each is installed")
    detect = dsub.add_parser(
        "detect",
        help="find reachable devices and print them as a profile's devices: block",
        description=(
            "Ask drivers for the devices they can reach (listening and pinging only: nothing"
            " moves) and print them as profile entries with placeholder joint names."
        ),
    )
    detect.add_argument(
        "driver",
        nargs="*",
        metavar="DRIVER",
        help="the drivers to ask (default: every installed one)",
    )
    detect.add_argument(
        "--link",
        action="append",
        default=[],
        metavar="LINK",
        help=(
            "where to look, as a profile's link value: serial:/dev/ttyUSB0?baud=57600,"
            " udp:0.0.0.0:14550, or '{interface: socketcan, channel: can0}' (repeatable;"
            " default: each driver's own candidates, e.g. every serial port)"
        ),
    )
    detect.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help=(
            "seconds to listen or wait for answers per link and baud rate (default: each"
            " driver's own: 2.5 for MAVLink, whose vehicles send a heartbeat a second; 1 else)"
        ),
    )
    detect.add_argument("--json", action="store_true", help="print JSON instead of YAML")


def main(args: argparse.Namespace, out: IO[str] | None = None) -> int:
    """Run ``temoto drivers list`` or ``temoto drivers detect``.

    Args:
        args: The parsed arguments.
        out: Where to print (default standard output); progress and errors go to stderr.

    Returns:
        0; for ``detect``, 1 when no device was found and 2 when a driver or link was invalid.

    Raises:
        ConfigError: A ``--link`` value is not YAML.
    """
    from temoto.drivers.registry import driver_names  # driver code only for this command

    out = out or sys.stdout
    if args.drivers_command == "list":
        for name in driver_names():
            out.write(f"{name:12} {_availability(name)}\n")
        return EXIT_OK
    return _detect(args, out)


def _availability(name: str) -> str:
    """``installed``, or the pip command that installs a built-in driver's library."""
    from temoto.drivers.registry import BUILTIN_DRIVERS

    spec = BUILTIN_DRIVERS.get(name)
    if spec is None:
        return "installed (entry point)"
    extra = spec[1]
    library = _LIBRARY.get(extra)
    if library and importlib.util.find_spec(library) is None:
        return f"not installed: pip install 'temoto[{extra}]'"
    return "installed"


def _links(texts: list[str]) -> list[Any] | None:
    """``--link`` values as profile link values (YAML: a URL string or a mapping)."""
    import yaml

    if not texts:
        return None
    links = []
    for text in texts:
        try:
            links.append(yaml.safe_load(text))
        except yaml.YAMLError as err:
            raise ConfigError(f"--link {text!r} is not a link value: {err}") from err
    return links


def _detect(args: argparse.Namespace, out: IO[str]) -> int:
    import yaml

    from temoto.drivers.registry import driver_class, driver_names

    if args.timeout is not None and not args.timeout > 0:
        raise ConfigError(f"--timeout must be positive, got {args.timeout}")
    timing: dict[str, float] = {} if args.timeout is None else {"timeout": args.timeout}
    links = _links(args.link)
    names = args.driver or [n for n in driver_names() if _availability(n) == "installed"]
    found: list[dict[str, Any]] = []
    failed = False
    for name in names:
        where = "the given links" if links else "its own candidates"
        sys.stderr.write(f"temoto: asking {name} for devices on {where} ...\n")
        try:
            entries = driver_class(name).detect(links, **timing)
        except (ValueError, DriverUnavailableError, PluginError) as err:
            sys.stderr.write(f"temoto: error: {name}: {err}\n")
            failed = True
            continue
        sys.stderr.write(f"temoto: {name}: {len(entries)} found\n")
        found.extend(entries)
    if args.json:
        out.write(json.dumps(found, indent=2) + "\n")
    elif found:
        devices: dict[str, Any] = {}
        for entry in found:
            devices[_device_name(entry["driver"], devices)] = entry
        out.write(yaml.safe_dump({"devices": devices}, sort_keys=False, default_flow_style=None))
    if failed:
        return EXIT_INVALID
    return EXIT_OK if found else EXIT_NOTHING


def _device_name(driver: str, taken: dict[str, Any]) -> str:
    """``<driver>_<n>``, the first not taken (the user renames it)."""
    n = 1
    while f"{driver}_{n}" in taken:
        n += 1
    return f"{driver}_{n}"


if __name__ == "__main__":  # python -m temoto.cli.drivers: temoto drivers, on its own
    from temoto.cli import command_main

    sys.exit(command_main("drivers"))
