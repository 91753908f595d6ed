"""Fleet identities and the roster: a key per robot and operator (docs/security.md).

An :class:`Identity` is one member's name and its Ed25519 private key, kept in an identity file
(YAML, readable by its owner only). A :class:`Roster` names the fleet's members and their public
keys, and the keys revoked so far, in a roster file (YAML) that every member reads; ``temoto
keys new|add|revoke|list`` manages both. A running member notices a changed roster file
(:meth:`Roster.refresh`) and refuses a removed or revoked member at once.

Identity file::

    # TeMoto fleet identity: keep this file secret (it holds a private key)
    name: robot_1
    private_key: ed25519:<base64 of the 32-byte seed>

Roster file::

    # TeMoto fleet roster: members and their Ed25519 public keys (temoto keys ...)
    members:
      operator: ed25519:<base64 of the 32-byte public key>
      robot_1: ed25519:...
    revoked:
      - {name: robot_2, key: "ed25519:..."}
    permissions:            # optional: without it every member may do everything
      - {who: [operator], may: ["graph.*"], targets: ["*"]}
      - {who: ["*"], may: [resource.request], targets: [camera]}
      - {who: [robot_1], may: [world.publish]}

The permissions are the fleet policy (:class:`Policy`), in the roster so that a change reaches
every member the way a revocation does. Actions: :data:`ACTIONS`.
"""

from __future__ import annotations

import base64
import binascii
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, final

__all__ = [
    "ACTIONS",
    "IDENTITY_ENV",
    "KEY_PREFIX",
    "ROSTER_ENV",
    "Credentials",
    "Identity",
    "Policy",
    "Roster",
    "RosterError",
    "public_key_from_text",
    "public_key_text",
]

#: Environment variable naming this member's identity file (read by the CLI only).
IDENTITY_ENV = "TEMOTO_FLEET_IDENTITY"
#: Environment variable naming the fleet's roster file (read by the CLI only).
ROSTER_ENV = "TEMOTO_FLEET_ROSTER"
#: How a key is written in the files: this prefix, then base64.
KEY_PREFIX = "ed25519:"
_KEY_BYTES = 32
#: What a policy rule may grant: graph control on a robot (the target is the instance's actor
#: name), a resource request (the target is the resource server), a world-model change (the
#: target is the publishing robot).
ACTIONS = (
    "graph.start",
    "graph.stop",
    "graph.pause",
    "graph.resume",
    "graph.modify",
    "resource.request",
    "world.publish",
)


@dataclass(frozen=True)
class Policy:
    """Who may do what on which target: a list of allow rules; anything else is refused.

    Each rule is ``(who, may, targets)``: patterns (``fnmatch``: ``*``, ``graph.*``) of member
    names, of :data:`ACTIONS` and of targets.

    Attributes:
        rules: The rules.
    """

    rules: tuple[tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]], ...]

    @classmethod
    def from_data(cls, data: Any) -> Policy:
        """Read the ``permissions`` list of a roster file.

        Args:
            data: The list of ``{who: [...], may: [...], targets: [...]}`` (``targets``
                defaults to ``["*"]``).

        Returns:
            The policy.

        Raises:
            ValueError: If a rule is malformed or names no known action.
        """
        from fnmatch import fnmatchcase

        if not isinstance(data, list):
            raise ValueError("'permissions' must be a list of {who, may, targets} rules")
        rules = []
        for i, rule in enumerate(data):
            if not isinstance(rule, dict) or set(rule) - {"who", "may", "targets"}:
                raise ValueError(f"permissions[{i}]: a rule has the keys who, may and targets")
            parts = []
            for key in ("who", "may", "targets"):
                value = rule.get(key, ["*"] if key == "targets" else None)
                if isinstance(value, str):
                    value = [value]
                if (
                    not isinstance(value, list)
                    or not value
                    or not all(isinstance(v, str) and v for v in value)
                ):
                    raise ValueError(f"permissions[{i}].{key}: a non-empty list of names")
                parts.append(tuple(value))
            for pattern in parts[1]:
                if not any(fnmatchcase(action, pattern) for action in ACTIONS):
                    raise ValueError(
                        f"permissions[{i}].may: {pattern!r} matches no action"
                        f" ({', '.join(ACTIONS)})"
                    )
            rules.append((parts[0], parts[1], parts[2]))
        return cls(tuple(rules))

    def to_data(self) -> list[dict[str, list[str]]]:
        """The rules as a roster file writes them (the inverse of :meth:`from_data`)."""
        return [{"who": list(w), "may": list(m), "targets": list(t)} for w, m, t in self.rules]

    def allows(self, who: str, action: str, target: str) -> bool:
        """Whether a rule lets ``who`` do ``action`` on ``target``.

        Args:
            who: The (authenticated) member.
            action: One of :data:`ACTIONS`.
            target: The robot or resource server.

        Returns:
            True if some rule matches all three.
        """
        from fnmatch import fnmatchcase

        return any(
            any(fnmatchcase(who, p) for p in names)
            and any(fnmatchcase(action, p) for p in actions)
            and any(fnmatchcase(target, p) for p in targets)
            for names, actions, targets in self.rules
        )


class RosterError(ValueError):
    """An identity or roster file that cannot be used; the message names the file and why."""


def public_key_text(raw: bytes) -> str:
    """Write a raw 32-byte Ed25519 key as ``ed25519:<base64>``.

    Args:
        raw: The key bytes.

    Returns:
        Its text form.
    """
    return KEY_PREFIX + base64.b64encode(raw).decode("ascii")


def public_key_from_text(text: str) -> bytes:
    """Read a key written as ``ed25519:<base64>`` (see :func:`public_key_text`).

    Args:
        text: The key's text form.

    Returns:
        The 32 key bytes.

    Raises:
        ValueError: If the text is not such a key.
    """
    if not isinstance(text, str) or not text.startswith(KEY_PREFIX):
        raise ValueError(f"a key must be written as {KEY_PREFIX}<base64>, got {text!r:.80}")
    try:
        raw = base64.b64decode(text[len(KEY_PREFIX) :].strip(), validate=True)
    except (binascii.Error, ValueError):
        raise ValueError(f"the key {text!r:.80} is not valid base64") from None
    if len(raw) != _KEY_BYTES:
        raise ValueError(f"an Ed25519 key has {_KEY_BYTES} bytes, {text!r:.80} has {len(raw)}")
    return raw


def _load_yaml(path: Path, what: str) -> dict[str, Any]:
    import yaml

    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise RosterError(f"cannot read the {what} {str(path)!r}: {err.strerror or err}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise RosterError(f"the {what} {str(path)!r} is not valid YAML: {err}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise RosterError(f"the {what} {str(path)!r} must be a mapping, got {type(data).__name__}")
    return data


def _write_atomically(path: Path, text: str, mode: int) -> None:
    """Replace ``path`` by ``text`` in one rename, so a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            out.write(text)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@final
class Identity:
    """One member's name and Ed25519 private key.

    Args:
        name: The member's name (its fleet sender id).
        seed: The 32-byte private key seed.

    Raises:
        ValueError: If the name is empty or the seed is not 32 bytes.
    """

    def __init__(self, name: str, seed: bytes) -> None:
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
        from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

        if not isinstance(name, str) or not name:
            raise ValueError(f"an identity needs a non-empty name, got {name!r}")
        if not isinstance(seed, bytes) or len(seed) != _KEY_BYTES:
            raise ValueError(f"an Ed25519 private key seed has {_KEY_BYTES} bytes")
        self.name = name
        self._key = Ed25519PrivateKey.from_private_bytes(seed)
        self._seed = seed
        #: The raw 32-byte public key.
        self.public_key = self._key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)

    def __repr__(self) -> str:
        return f"<Identity {self.name!r} {public_key_text(self.public_key)}>"

    @classmethod
    def generate(cls, name: str) -> Identity:
        """A new identity with a fresh random key.

        Args:
            name: The member's name.

        Returns:
            The identity.
        """
        return cls(name, os.urandom(_KEY_BYTES))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Identity:
        """Read an identity file.

        Args:
            path: The file.

        Returns:
            The identity.

        Raises:
            RosterError: If the file cannot be read or is not an identity file.
        """
        where = Path(path)
        data = _load_yaml(where, "identity file")
        name, key = data.get("name"), data.get("private_key")
        if not isinstance(name, str) or not name:
            raise RosterError(f"the identity file {str(where)!r} has no 'name'")
        try:
            return cls(name, public_key_from_text(key if isinstance(key, str) else ""))
        except ValueError as err:
            raise RosterError(f"the identity file {str(where)!r}: private_key: {err}") from None

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write this identity to a file readable by its owner only (mode 0600).

        Args:
            path: The file; replaced if it exists.
        """
        text = (
            "# TeMoto fleet identity: keep this file secret (it holds a private key)\n"
            f"name: {_yaml_str(self.name)}\n"
            f"private_key: {public_key_text(self._seed)}\n"
        )
        _write_atomically(Path(path), text, 0o600)

    def sign(self, data: bytes) -> bytes:
        """Sign ``data`` (64-byte Ed25519 signature).

        Args:
            data: What to sign.

        Returns:
            The signature.
        """
        return self._key.sign(data)


def _yaml_str(text: str) -> str:
    import yaml

    dumped: str = yaml.safe_dump(text, default_flow_style=True, width=10**6)
    return dumped.strip().removesuffix("...").strip()


@final
class Roster:
    """The fleet's members and their public keys, from a roster file.

    Args:
        members: Name to raw public key.
        revoked: (name, raw public key) pairs revoked so far.
        path: The file it was read from (None: built in memory, never refreshed).

    Raises:
        ValueError: If a key is not 32 bytes or a name is empty.
    """

    def __init__(
        self,
        members: dict[str, bytes],
        revoked: list[tuple[str, bytes]] | None = None,
        *,
        path: Path | None = None,
        policy: Policy | None = None,
    ) -> None:
        for name, key in members.items():
            if not isinstance(name, str) or not name:
                raise ValueError(f"a member needs a non-empty name, got {name!r}")
            if not isinstance(key, bytes) or len(key) != _KEY_BYTES:
                raise ValueError(f"member {name!r}: an Ed25519 public key has {_KEY_BYTES} bytes")
        self.members = dict(members)
        self.revoked = list(revoked or [])
        #: The fleet policy; None: every member may do everything.
        self.policy = policy
        self.path = path
        self._stamp = self._stat()
        self._verifiers: dict[bytes, Any] = {}

    def __repr__(self) -> str:
        return f"<Roster {len(self.members)} members, {len(self.revoked)} revoked>"

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Roster:
        """Read a roster file; a missing file is an empty roster only for ``temoto keys``.

        Args:
            path: The file.

        Returns:
            The roster.

        Raises:
            RosterError: If the file cannot be read or holds an invalid entry.
        """
        where = Path(path)
        data = _load_yaml(where, "roster file")
        members_raw = data.get("members") or {}
        revoked_raw = data.get("revoked") or []
        if not isinstance(members_raw, dict) or not isinstance(revoked_raw, list):
            raise RosterError(
                f"the roster file {str(where)!r}: 'members' must be a mapping and 'revoked' a list"
            )
        members: dict[str, bytes] = {}
        for name, key in members_raw.items():
            try:
                members[str(name)] = public_key_from_text(key)
            except ValueError as err:
                raise RosterError(
                    f"the roster file {str(where)!r}: member {name!r}: {err}"
                ) from None
        revoked: list[tuple[str, bytes]] = []
        for entry in revoked_raw:
            try:
                if not isinstance(entry, dict):
                    raise ValueError("each revoked entry must be {name: ..., key: ...}")
                key = public_key_from_text(str(entry.get("key", "")))
                revoked.append((str(entry.get("name", "")), key))
            except ValueError as err:
                raise RosterError(f"the roster file {str(where)!r}: revoked: {err}") from None
        policy = None
        if data.get("permissions") is not None:
            try:
                policy = Policy.from_data(data["permissions"])
            except ValueError as err:
                raise RosterError(f"the roster file {str(where)!r}: {err}") from None
        bad = {key for _, key in revoked} & set(members.values())
        if bad:
            names = sorted(n for n, k in members.items() if k in bad)
            raise RosterError(
                f"the roster file {str(where)!r}: {', '.join(map(repr, names))} use a revoked key"
            )
        return cls(members, revoked, path=where, policy=policy)

    def save(self, path: str | os.PathLike[str] | None = None) -> None:
        """Write the roster (atomically: running members never read half a file).

        Args:
            path: The file; :attr:`path` when None.

        Raises:
            ValueError: If there is no path.
        """
        where = Path(path) if path is not None else self.path
        if where is None:
            raise ValueError("this roster has no file: give a path")
        lines = ["# TeMoto fleet roster: members and their Ed25519 public keys (temoto keys ...)"]
        lines.append("members:" if self.members else "members: {}")
        lines += [
            f"  {_yaml_str(n)}: {public_key_text(k)}" for n, k in sorted(self.members.items())
        ]
        lines.append("revoked:" if self.revoked else "revoked: []")
        lines += [
            f"  - {{name: {_yaml_str(n)}, key: {public_key_text(k)!r}}}".replace("'", '"')
            for n, k in self.revoked
        ]
        if self.policy is not None:
            import yaml

            lines.append(
                yaml.safe_dump(
                    {"permissions": self.policy.to_data()},
                    default_flow_style=None,
                    sort_keys=False,
                    width=100,
                ).rstrip("\n")
            )
        _write_atomically(where, "\n".join(lines) + "\n", 0o644)
        self.path = where
        self._stamp = self._stat()

    def _stat(self) -> tuple[int, int, int] | None:
        if self.path is None:
            return None
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    def refresh(self) -> bool:
        """Re-read the roster file if it changed since it was read.

        A file that became unreadable or invalid keeps the roster as it was (the caller logs).

        Returns:
            True if the roster changed.

        Raises:
            RosterError: If the changed file is invalid (the roster is unchanged).
        """
        if self.path is None:
            return False
        stamp = self._stat()
        if stamp == self._stamp:
            return False
        self._stamp = stamp
        fresh = Roster.load(self.path)
        changed = (fresh.members, fresh.revoked, fresh.policy) != (
            self.members,
            self.revoked,
            self.policy,
        )
        self.members, self.revoked, self.policy = fresh.members, fresh.revoked, fresh.policy
        return changed

    def key_of(self, name: str) -> bytes | None:
        """The public key of a member, or None if it is not (or no longer) one."""
        return self.members.get(name)

    def verify(self, name: str, signature: bytes, data: bytes) -> bool:
        """Whether ``signature`` is ``name``'s Ed25519 signature of ``data`` (False if no member).

        Args:
            name: The claimed signer.
            signature: The signature.
            data: What was signed.

        Returns:
            True if it verifies against the roster's key of ``name``.
        """
        from cryptography.exceptions import InvalidSignature
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

        key = self.members.get(name)
        if key is None:
            return False
        verifier = self._verifiers.get(key)
        if verifier is None:
            verifier = self._verifiers[key] = Ed25519PublicKey.from_public_bytes(key)
        try:
            verifier.verify(signature, data)
        except InvalidSignature:
            return False
        return True

    def add(self, name: str, key: bytes, *, replace: bool = False) -> None:
        """Add a member.

        Args:
            name: Its name.
            key: Its raw 32-byte public key.
            replace: Allow replacing the key of an existing member (the old key is revoked).

        Raises:
            ValueError: If the key was revoked, is another member's, or the name exists without
                ``replace``.
        """
        if len(key) != _KEY_BYTES:
            raise ValueError(f"an Ed25519 public key has {_KEY_BYTES} bytes")
        if any(k == key for _, k in self.revoked):
            raise ValueError(f"this key was revoked; make a new one (temoto keys new {name})")
        other = next((n for n, k in self.members.items() if k == key and n != name), None)
        if other is not None:
            raise ValueError(f"this key is already member {other!r}'s")
        if name in self.members and self.members[name] != key:
            if not replace:
                raise ValueError(f"{name!r} is already a member with another key (use --replace)")
            self.revoked.append((name, self.members[name]))
        self.members[name] = key

    def revoke(self, name: str) -> bytes:
        """Remove a member and record its key as revoked.

        Args:
            name: The member.

        Returns:
            Its key.

        Raises:
            KeyError: If there is no such member.
        """
        if name not in self.members:
            raise KeyError(name)
        key = self.members.pop(name)
        self.revoked.append((name, key))
        return key


@dataclass(frozen=True)
class Credentials:
    """What a member needs in a fleet with a roster: its identity and the roster.

    Attributes:
        identity: This member's name and private key.
        roster: The fleet's members.
    """

    identity: Identity
    roster: Roster

    @classmethod
    def load(cls, identity: str | os.PathLike[str], roster: str | os.PathLike[str]) -> Credentials:
        """Read an identity file and a roster file, and check that they agree.

        Args:
            identity: The identity file.
            roster: The roster file.

        Returns:
            The credentials.

        Raises:
            RosterError: If a file is unusable or the identity is not a member with that key.
        """
        me, members = Identity.load(identity), Roster.load(roster)
        known = members.key_of(me.name)
        if known is None:
            raise RosterError(f"{me.name!r} is not a member of the roster {str(roster)!r}")
        if known != me.public_key:
            raise RosterError(
                f"the roster {str(roster)!r} has another key for {me.name!r} than the identity "
                f"file {str(identity)!r}"
            )
        return cls(me, members)
