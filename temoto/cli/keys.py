"""``temoto keys``: identities and the fleet roster (docs/security.md).

* ``temoto keys new NAME -o FILE [--roster ROSTER]`` makes an Ed25519 identity (a private key
  file, mode 0600) and prints its public key; with ``--roster`` adds it as a member.
* ``temoto keys add ROSTER NAME KEY`` adds a member (``KEY``: ``ed25519:...`` or the member's
  identity file); ``--replace`` gives an existing member a new key (the old one is revoked).
* ``temoto keys revoke ROSTER NAME`` removes a member and records its key as revoked: running
  members notice the changed file and refuse it at once.
* ``temoto keys list ROSTER`` prints the members, the revoked keys and the permissions.

Exit status 0 on success, 2 on invalid input (a one-line message). Like :mod:`temoto.cli`, this
module prints.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_parser", "main"]

_HELP = {
    "new": "make an identity (an Ed25519 key pair) for a robot or an operator",
    "add": "add a member (name and public key) to a roster",
    "revoke": "remove a member from a roster and refuse its key from now on",
    "list": "print a roster's members, revoked keys and permissions",
}


def add_parser(sub: Any) -> None:
    """Add ``temoto keys`` to the top-level subparsers.

    Args:
        sub: The ``add_subparsers()`` object of the top-level parser.
    """
    keys = sub.add_parser(
        "keys",
        help="identities and the fleet roster (docs/security.md)",
        description="Manage fleet identities and the roster: a key per robot and operator."
        " Members run with --fleet-identity FILE --fleet-roster ROSTER (or $TEMOTO_FLEET_IDENTITY"
        " and $TEMOTO_FLEET_ROSTER); running members re-read a changed roster at once.",
    )
    ksub = keys.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    new = ksub.add_parser("new", help=_HELP["new"], description=_HELP["new"] + ".")
    new.add_argument("name", metavar="NAME", help="the member's name (its --actor or sender)")
    new.add_argument(
        "-o", "--output", required=True, metavar="FILE", help="identity file to write (0600)"
    )
    new.add_argument("--roster", metavar="ROSTER", help="also add the new member to this roster")
    new.add_argument("--force", action="store_true", help="overwrite an existing identity file")
    add = ksub.add_parser("add", help=_HELP["add"], description=_HELP["add"] + ".")
    add.add_argument("roster", metavar="ROSTER", help="roster file (created if missing)")
    add.add_argument("name", metavar="NAME", help="the member's name")
    add.add_argument("key", metavar="KEY", help="its public key (ed25519:...) or identity file")
    add.add_argument(
        "--replace", action="store_true", help="give an existing member this key (revokes the old)"
    )
    revoke = ksub.add_parser("revoke", help=_HELP["revoke"], description=_HELP["revoke"] + ".")
    revoke.add_argument("roster", metavar="ROSTER", help="roster file")
    revoke.add_argument("name", metavar="NAME", help="the member to remove")
    show = ksub.add_parser("list", help=_HELP["list"], description=_HELP["list"] + ".")
    show.add_argument("roster", metavar="ROSTER", help="roster file")


def _roster(path: str, *, create: bool) -> Any:
    from temoto.transport.identity import Roster

    if create and not Path(path).exists():
        return Roster({}, path=Path(path))
    return Roster.load(path)


def _public_key(text: str) -> bytes:
    from temoto.transport.identity import KEY_PREFIX, Identity, public_key_from_text

    if text.startswith(KEY_PREFIX):
        return public_key_from_text(text)
    return Identity.load(text).public_key


def main(args: argparse.Namespace) -> int:
    """Run ``temoto keys ...``.

    Args:
        args: The parsed arguments.

    Returns:
        0 on success, 2 on invalid input.
    """
    from temoto.transport.identity import Identity, public_key_text

    try:
        if args.keys_command == "new":
            out = Path(args.output)
            if out.exists() and not args.force:
                raise ValueError(f"{out} exists (use --force to overwrite it)")
            roster = _roster(args.roster, create=True) if args.roster else None
            me = Identity.generate(args.name)
            if roster is not None:
                roster.add(args.name, me.public_key)
            me.save(out)
            if roster is not None:
                roster.save()
            sys.stdout.write(f"{args.name} {public_key_text(me.public_key)}\n")
            return 0
        if args.keys_command == "add":
            roster = _roster(args.roster, create=True)
            roster.add(args.name, _public_key(args.key), replace=args.replace)
            roster.save()
            sys.stdout.write(f"added {args.name!r} to {args.roster}\n")
            return 0
        if args.keys_command == "revoke":
            roster = _roster(args.roster, create=False)
            try:
                roster.revoke(args.name)
            except KeyError:
                raise ValueError(f"{args.name!r} is not a member of {args.roster}") from None
            roster.save()
            sys.stdout.write(f"revoked {args.name!r} in {args.roster}\n")
            return 0
        roster = _roster(args.roster, create=False)
        for name, key in sorted(roster.members.items()):
            sys.stdout.write(f"member  {name}  {public_key_text(key)}\n")
        for name, key in roster.revoked:
            sys.stdout.write(f"revoked {name}  {public_key_text(key)}\n")
        if roster.policy is None:
            sys.stdout.write("permissions: none (every member may do everything)\n")
        for who, may, targets in roster.policy.rules if roster.policy else ():
            sys.stdout.write(
                f"allow   {','.join(who)} may {','.join(may)} on {','.join(targets)}\n"
            )
        return 0
    except (ValueError, OSError) as err:  # RosterError is a ValueError
        sys.stderr.write(f"temoto: error: keys {args.keys_command}: {err}\n")
        return 2


if __name__ == "__main__":  # python -m temoto.cli.keys: temoto keys, on its own
    from temoto.cli import command_main

    sys.exit(command_main("keys"))
