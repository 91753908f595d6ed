"""The registrar's catalog records: one typed definition per operation, written and replayed.

:mod:`~temoto.core.registrar.journal` stores records as framed JSON objects; this module says
which objects. Each operation is one class below: its fields, its encoder (:meth:`Record.plain`,
the object the journal writes) and its replay (:meth:`Record.apply`, what it does to the state
being rebuilt). :data:`RECORDS` maps each ``op`` to its class; :func:`replay` reads a journal's
records back through it.

Long because every record is here, each with its encoder and its replay (and the two written
for every deduplicated request with their precompiled layouts): in one module, writing and
restoring cannot drift apart.

Records (every one also has ``"op"``; keys are written sorted, so the bytes do not depend on the
order below)::

    begin      uid server request             a load starts: a new resource, loading
    progress   uid data                       the load's checkpoint (``ctx.checkpoint``)
    load       uid response ref               the load returned; ``ref``: its first reference
    load       uid response ref:null refs deps failed
                                              compaction's snapshot of a loaded resource: its
                                              complete reference and dependency lists
    deps       uid deps                       compaction's dependency list of a loading resource
    ref        id uid client priority exclusive holder suspended suspends
                                              a reference to a loaded resource; ``suspends``:
                                              the references it pre-empted
    unref      id resumes                     a reference released; ``resumes``: the suspended
                                              references that became active again
    unload     uid                            the resource was unloaded
    abandon    uid                            its load failed, or a restore undid it
    failed     uid                            a FATAL status: no longer shared
    recovered  uid                            an OK status on a failed resource: shared again
    response   uid response                   ``update_response``

A reference inside ``load`` (``ref`` and each of ``refs``) has the fields of ``ref`` without
``op`` and ``suspends``. A reference with a ``holder`` is a dependency of that resource; ``load``
and ``ref`` append it to the holder's dependency list, a snapshot's ``refs`` do not (its
``deps`` is the complete list). Replay is strict: an unknown ``op``, a missing key (only
``suspended``, ``suspends`` and ``resumes`` may be left out: false, empty) or a record that
names an unknown resource or reference is :class:`~temoto.errors.CatalogCorruptError`.

The two records written for every deduplicated request (``ref`` per call, ``unref`` per
release) also have a precompiled layout (:meth:`Ref.text`, :meth:`Unref.text`): the very bytes
:meth:`Record.plain` gives through the journal's encoder, formatted without building a dict.
:meth:`Ref.layout` goes one step further for the registrar's own reference ids: the bytes of a
reference's record before and after its id, made once per (resource, client, priority,
exclusive, holder) and joined around each new id.
"""

from __future__ import annotations

import dataclasses
import json.encoder
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from temoto.core.registrar.journal import encode
from temoto.errors import CatalogCorruptError

__all__ = [
    "RECORDS",
    "Abandon",
    "Begin",
    "Deps",
    "Failed",
    "Load",
    "Progress",
    "Record",
    "Recovered",
    "Ref",
    "RefFields",
    "ReplayState",
    "ReplayedEntry",
    "Response",
    "Unload",
    "Unref",
    "replay",
]

_json_str = json.encoder.encode_basestring  # the encoder's own string quoting (C)
_JSON_BOOL = ("false", "true")  # indexed by a bool
_UNREF_ALONE = b'{"id":%s,"op":"unref","resumes":[]}'  # Unref.LAYOUT_ALONE as bytes


def _json_list(items: Iterable[str]) -> str:
    """A list of strings as the journal's encoder writes it."""
    return "[" + ",".join(map(_json_str, items)) + "]"


# ------------------------------------------------------------------------------ replay state


@dataclass(frozen=True, slots=True)
class RefFields:
    """One reference as records carry it.

    Attributes:
        id: The reference id.
        uid: The resource it counts.
        client: The consumer's name.
        priority: Its priority.
        exclusive: Whether it wants the resource alone.
        holder: The resource holding it as a dependency, or "" for a consumer's reference.
        suspended: Whether a higher-priority reference pre-empted it.
    """

    id: str
    uid: str
    client: str
    priority: int
    exclusive: bool
    holder: str
    suspended: bool = False

    def plain(self) -> dict[str, Any]:
        """The reference as a JSON object (without ``op``).

        Returns:
            The fields by name.
        """
        return {
            "id": self.id,
            "uid": self.uid,
            "client": self.client,
            "priority": self.priority,
            "exclusive": self.exclusive,
            "holder": self.holder,
            "suspended": self.suspended,
        }

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> RefFields:
        """Read a reference (``suspended`` may be missing: false).

        Args:
            raw: The decoded JSON object.

        Returns:
            The reference.

        Raises:
            KeyError, TypeError, ValueError: If a field is missing or of the wrong kind.
        """
        return cls(
            str(raw["id"]),
            str(raw["uid"]),
            str(raw["client"]),
            int(raw["priority"]),
            bool(raw["exclusive"]),
            str(raw["holder"]),
            bool(raw.get("suspended", False)),
        )


@dataclass(slots=True)
class ReplayedEntry:
    """A resource as the records so far describe it.

    Attributes:
        server: Its server's name.
        request: Its request, as plain JSON data.
        response: Its response, as plain JSON data (None while loading).
        loaded: Whether its load finished.
        failed: Whether a FATAL status is in force.
        progress: The load's last checkpoint, or None.
        refs: Its references by id, in the order they were taken.
        deps: Ids of the references it holds as dependencies, oldest first.
    """

    server: str
    request: Any
    response: Any = None
    loaded: bool = False
    failed: bool = False
    progress: dict[str, Any] | None = None
    refs: dict[str, RefFields] = field(default_factory=dict)
    deps: list[str] = field(default_factory=list)


@dataclass(slots=True)
class ReplayState:
    """What a journal describes.

    Attributes:
        entries: Resources by id, in the order they were begun.
        ref_owner: The resource of each reference id.
    """

    entries: dict[str, ReplayedEntry] = field(default_factory=dict)
    ref_owner: dict[str, str] = field(default_factory=dict)

    def add_ref(self, ref: RefFields, *, link: bool) -> None:
        """Add a reference to its resource; with ``link``, to its holder's dependencies too.

        Args:
            ref: The reference.
            link: Append it to the holder's dependency list (not for a snapshot's lists).

        Raises:
            KeyError: If its resource (or linked holder) is unknown.
        """
        self.entries[ref.uid].refs[ref.id] = ref
        self.ref_owner[ref.id] = ref.uid
        if link and ref.holder:
            self.entries[ref.holder].deps.append(ref.id)

    def set_suspended(self, ref_id: str, suspended: bool) -> None:
        """Mark a reference suspended or active.

        Args:
            ref_id: The reference.
            suspended: The new state.

        Raises:
            KeyError: If the reference is unknown.
        """
        refs = self.entries[self.ref_owner[ref_id]].refs
        refs[ref_id] = dataclasses.replace(refs[ref_id], suspended=suspended)

    def drop(self, uid: str) -> None:
        """Forget a resource and its references.

        Args:
            uid: The resource.

        Raises:
            KeyError: If it is unknown.
        """
        entry = self.entries.pop(uid)
        for ref_id in entry.refs:
            self.ref_owner.pop(ref_id, None)


# ------------------------------------------------------------------------------ records


class Record(ABC):
    """One change of the registrar's state, as the catalog stores it.

    Subclasses are frozen dataclasses; ``op`` names the operation in the JSON object.
    """

    __slots__ = ()
    op: ClassVar[str]

    @abstractmethod
    def plain(self) -> dict[str, Any]:
        """The record as the JSON object the journal writes.

        Returns:
            The object, ``op`` included.
        """

    def encode(self) -> bytes:
        """The record's bytes in the journal (compact JSON, sorted keys, UTF-8).

        Returns:
            The payload.

        Raises:
            TypeError: If it holds data JSON cannot represent.
        """
        return encode(self.plain())

    @classmethod
    @abstractmethod
    def parse(cls, raw: Mapping[str, Any]) -> Record:
        """Read the record from its decoded JSON object.

        Args:
            raw: The object.

        Returns:
            The record.

        Raises:
            KeyError, TypeError, ValueError: If it does not have this record's fields.
        """

    @abstractmethod
    def apply(self, state: ReplayState) -> None:
        """Replay the record onto ``state``.

        Args:
            state: The state described by the records before this one.

        Raises:
            KeyError, ValueError: If the record does not fit the state.
        """


@dataclass(frozen=True, slots=True)
class _UidRecord(Record):
    """A record that names one resource and nothing else."""

    uid: str

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": self.op, "uid": self.uid}

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> _UidRecord:
        """See :meth:`Record.parse`."""
        return cls(str(raw["uid"]))


@dataclass(frozen=True, slots=True)
class Begin(Record):
    """A load starts: a new resource, loading."""

    op: ClassVar[str] = "begin"
    uid: str
    server: str
    request: Any

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": "begin", "uid": self.uid, "server": self.server, "request": self.request}

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Begin:
        """See :meth:`Record.parse`."""
        return cls(str(raw["uid"]), str(raw["server"]), raw["request"])

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        if self.uid in state.entries:
            raise ValueError(f"resource {self.uid} begun twice")
        state.entries[self.uid] = ReplayedEntry(self.server, self.request)


@dataclass(frozen=True, slots=True)
class Progress(Record):
    """A loading resource's checkpoint."""

    op: ClassVar[str] = "progress"
    uid: str
    data: dict[str, Any]

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": "progress", "uid": self.uid, "data": self.data}

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Progress:
        """See :meth:`Record.parse`."""
        return cls(str(raw["uid"]), dict(raw["data"]))

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.entries[self.uid].progress = self.data


@dataclass(frozen=True, slots=True)
class Load(Record):
    """A load returned (``ref``: its first reference), or compaction's snapshot of a resource.

    A snapshot has ``ref`` None and ``refs``, ``deps`` and ``failed`` set (all three or none).
    """

    op: ClassVar[str] = "load"
    uid: str
    response: Any
    ref: RefFields | None
    refs: tuple[RefFields, ...] | None = None
    deps: tuple[str, ...] = ()
    failed: bool = False

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        out = {
            "op": "load",
            "uid": self.uid,
            "response": self.response,
            "ref": None if self.ref is None else self.ref.plain(),
        }
        if self.refs is not None:
            out["refs"] = [r.plain() for r in self.refs]
            out["deps"] = list(self.deps)
            out["failed"] = self.failed
        return out

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Load:
        """See :meth:`Record.parse`."""
        first = raw.get("ref")
        ref = RefFields.parse(first) if first is not None else None
        if "refs" not in raw:
            return cls(str(raw["uid"]), raw["response"], ref)
        return cls(
            str(raw["uid"]),
            raw["response"],
            ref,
            tuple(RefFields.parse(r) for r in raw["refs"]),
            tuple(str(d) for d in raw["deps"]),
            bool(raw["failed"]),
        )

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        entry = state.entries[self.uid]
        entry.loaded = True
        entry.response = self.response
        if self.ref is not None:
            state.add_ref(self.ref, link=True)
        if self.refs is not None:  # a snapshot: complete lists, no linking
            for ref in self.refs:
                state.add_ref(ref, link=False)
            entry.deps = list(self.deps)
            entry.failed = self.failed


@dataclass(frozen=True, slots=True)
class Deps(Record):
    """Compaction's dependency list of a resource still loading."""

    op: ClassVar[str] = "deps"
    uid: str
    deps: tuple[str, ...]

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": "deps", "uid": self.uid, "deps": list(self.deps)}

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Deps:
        """See :meth:`Record.parse`."""
        return cls(str(raw["uid"]), tuple(str(d) for d in raw["deps"]))

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.entries[self.uid].deps = list(self.deps)


@dataclass(frozen=True, slots=True)
class Ref(Record):
    """A reference to a loaded resource; ``suspends``: the references it pre-empted."""

    op: ClassVar[str] = "ref"
    ref: RefFields
    suspends: tuple[str, ...] = ()

    #: The record's bytes with the fields in sorted order (see :meth:`text`).
    LAYOUT: ClassVar[str] = (
        '{"client":%s,"exclusive":%s,"holder":%s,"id":%s,"op":"ref","priority":%d,'
        '"suspended":%s,"suspends":%s,"uid":%s}'
    )
    #: The layout of an active reference that pre-empted nothing: every deduplicated call.
    LAYOUT_ACTIVE: ClassVar[str] = (
        '{"client":%s,"exclusive":%s,"holder":%s,"id":%s,"op":"ref","priority":%d,'
        '"suspended":false,"suspends":[],"uid":%s}'
    )

    #: :data:`LAYOUT_ACTIVE` up to the id's characters, and from them on (see :meth:`layout`).
    LAYOUT_HEAD: ClassVar[str] = '{"client":%s,"exclusive":%s,"holder":%s,"id":"'
    LAYOUT_TAIL: ClassVar[str] = (
        '","op":"ref","priority":%d,"suspended":false,"suspends":[],"uid":%s}'
    )

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": "ref", **self.ref.plain(), "suspends": list(self.suspends)}

    @staticmethod
    def layout(
        uid: str, client: str, priority: int, exclusive: bool, holder: str
    ) -> tuple[bytes, bytes] | None:
        """The record of an active reference that pre-empted nothing, around its id.

        ``head + id.encode() + tail`` is :meth:`text`'s record (UTF-8) for an ``id`` whose
        characters JSON writes as they are: ASCII letters, digits and ``-`` (the registrar's
        ids: its boot token in hex, ``-``, a counter).

        Args:
            uid: The resource.
            client: The consumer.
            priority: Its priority.
            exclusive: Whether it wants the resource alone.
            holder: Its holder, or "".

        Returns:
            (head, tail), or None if ``priority`` is not an ``int`` or ``exclusive`` not a
            ``bool`` (see :meth:`text`).
        """
        if type(priority) is not int or (exclusive is not False and exclusive is not True):
            return None
        head = Ref.LAYOUT_HEAD % (_json_str(client), _JSON_BOOL[exclusive], _json_str(holder))
        tail = Ref.LAYOUT_TAIL % (priority, _json_str(uid))
        return head.encode("utf-8"), tail.encode("utf-8")

    def encode(self) -> bytes:
        """See :meth:`Record.encode`; from :data:`LAYOUT` when the field types allow."""
        r = self.ref
        text = Ref.text(
            r.id, r.uid, r.client, r.priority, r.exclusive, r.holder, r.suspended, self.suspends
        )
        return encode(self.plain()) if text is None else text.encode("utf-8")

    @staticmethod
    def text(
        ref_id: str,
        uid: str,
        client: str,
        priority: int,
        exclusive: bool,
        holder: str,
        suspended: bool,
        suspends: Iterable[str],
    ) -> str | None:
        """The record's JSON text from :data:`LAYOUT`, without building a dict.

        Args:
            ref_id: The reference id.
            uid: The resource.
            client: The consumer.
            priority: Its priority.
            exclusive: Whether it wants the resource alone.
            holder: Its holder, or "".
            suspended: Whether it is suspended.
            suspends: Ids of the references it pre-empted.

        Returns:
            The text (what :meth:`Record.plain` gives through the journal's encoder), or None
            if ``priority`` is not an ``int`` or ``exclusive`` or ``suspended`` not a ``bool``
            (the layout would write them differently; use :meth:`encode`).
        """
        if (
            type(priority) is not int
            or (exclusive is not False and exclusive is not True)
            or (suspended is not False and suspended is not True)
        ):
            return None
        if suspended is False and not suspends:
            return Ref.LAYOUT_ACTIVE % (
                _json_str(client),
                "true" if exclusive else "false",
                _json_str(holder) if holder else '""',
                _json_str(ref_id),
                priority,
                _json_str(uid),
            )
        return Ref.LAYOUT % (
            _json_str(client),
            _JSON_BOOL[exclusive],
            _json_str(holder),
            _json_str(ref_id),
            priority,
            _JSON_BOOL[suspended],
            _json_list(suspends) if suspends else "[]",
            _json_str(uid),
        )

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Ref:
        """See :meth:`Record.parse`."""
        return cls(RefFields.parse(raw), tuple(str(s) for s in raw.get("suspends", ())))

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        for ref_id in self.suspends:
            state.set_suspended(ref_id, True)
        state.add_ref(self.ref, link=True)


@dataclass(frozen=True, slots=True)
class Unref(Record):
    """A reference released; ``resumes``: suspended references active again."""

    op: ClassVar[str] = "unref"
    id: str
    resumes: tuple[str, ...] = ()

    #: The record's bytes (see :meth:`text`).
    LAYOUT: ClassVar[str] = '{"id":%s,"op":"unref","resumes":%s}'
    #: The layout with no ``resumes``, the common case.
    LAYOUT_ALONE: ClassVar[str] = '{"id":%s,"op":"unref","resumes":[]}'

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": "unref", "id": self.id, "resumes": list(self.resumes)}

    def encode(self) -> bytes:
        """See :meth:`Record.encode`; from :data:`LAYOUT`."""
        return Unref.text(self.id, self.resumes).encode("utf-8")

    @staticmethod
    def payload(ref_id: str) -> bytes:
        """The record of a release that resumed nothing, as the journal's bytes (UTF-8).

        Args:
            ref_id: The released reference.

        Returns:
            ``text(ref_id).encode("utf-8")``.
        """
        return _UNREF_ALONE % _json_str(ref_id).encode("utf-8")

    @staticmethod
    def text(ref_id: str, resumes: Iterable[str] = ()) -> str:
        """The record's JSON text from :data:`LAYOUT`, without building a dict.

        Args:
            ref_id: The released reference.
            resumes: Ids of the references active again.

        Returns:
            The text (what :meth:`Record.plain` gives through the journal's encoder).
        """
        if not resumes:
            return Unref.LAYOUT_ALONE % _json_str(ref_id)
        return Unref.LAYOUT % (_json_str(ref_id), _json_list(resumes))

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Unref:
        """See :meth:`Record.parse`."""
        return cls(str(raw["id"]), tuple(str(r) for r in raw.get("resumes", ())))

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        uid = state.ref_owner.pop(self.id)
        ref = state.entries[uid].refs.pop(self.id)
        holder = state.entries.get(ref.holder) if ref.holder else None
        if holder is not None and self.id in holder.deps:
            holder.deps.remove(self.id)
        for other in self.resumes:
            state.set_suspended(other, False)


@dataclass(frozen=True, slots=True)
class Unload(_UidRecord):
    """The resource was unloaded."""

    op: ClassVar[str] = "unload"

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.drop(self.uid)


@dataclass(frozen=True, slots=True)
class Abandon(_UidRecord):
    """The resource's load failed, or a restore undid it."""

    op: ClassVar[str] = "abandon"

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.drop(self.uid)


@dataclass(frozen=True, slots=True)
class Failed(_UidRecord):
    """A FATAL status: the resource is no longer shared."""

    op: ClassVar[str] = "failed"

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.entries[self.uid].failed = True


@dataclass(frozen=True, slots=True)
class Recovered(_UidRecord):
    """An OK status on a failed resource: shared again."""

    op: ClassVar[str] = "recovered"

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.entries[self.uid].failed = False


@dataclass(frozen=True, slots=True)
class Response(Record):
    """A new response for a loaded resource (``update_response``)."""

    op: ClassVar[str] = "response"
    uid: str
    response: Any

    def plain(self) -> dict[str, Any]:
        """See :meth:`Record.plain`."""
        return {"op": "response", "uid": self.uid, "response": self.response}

    @classmethod
    def parse(cls, raw: Mapping[str, Any]) -> Response:
        """See :meth:`Record.parse`."""
        return cls(str(raw["uid"]), raw["response"])

    def apply(self, state: ReplayState) -> None:
        """See :meth:`Record.apply`."""
        state.entries[self.uid].response = self.response


#: Every record class by its ``op``.
RECORDS: dict[str, type[Record]] = {
    cls.op: cls
    for cls in (
        Begin,
        Progress,
        Load,
        Deps,
        Ref,
        Unref,
        Unload,
        Abandon,
        Failed,
        Recovered,
        Response,
    )
}


def replay(records: Iterable[Mapping[str, Any]], name: str) -> ReplayState:
    """Apply journal records, in order, to an empty state.

    Args:
        records: The decoded records (what :meth:`Journal.open` returns).
        name: The catalog's name, for messages.

    Returns:
        The resources the catalog describes.

    Raises:
        CatalogCorruptError: If a record is unknown or does not fit the state built so far
            (the catalog is never half-loaded).
    """
    state = ReplayState()
    for index, raw in enumerate(records):
        try:
            op = raw["op"]
            cls = RECORDS.get(op) if type(op) is str else None
            if cls is None:
                raise ValueError(f"unknown operation {op!r}")
            cls.parse(raw).apply(state)
        except (KeyError, TypeError, ValueError) as err:
            raise CatalogCorruptError(
                f"{name}: record {index + 1} ({raw.get('op', '?')!r}) does not fit: {err!r}"
            ) from None
    return state
