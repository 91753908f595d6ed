"""Replay of the registrar's journal into plain state (restore after a crash).

Registrar internal. The records (see ``registry.py``) are applied in order; anything that does
not fit — an unknown operation, a missing key, a reference to an unknown resource — is
corruption: the catalog is never half-loaded.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from temoto.errors import CatalogCorruptError

__all__ = ["ReplayState", "replay"]


@dataclass(slots=True)
class ReplayState:
    """What a journal describes.

    Attributes:
        entries: Resources by id, as dicts with server, request, response, loaded, failed,
            progress, refs (reference records by id) and deps (reference ids).
        ref_owner: The resource of each reference id.
    """

    entries: dict[str, dict[str, Any]] = field(default_factory=dict)
    ref_owner: dict[str, str] = field(default_factory=dict)


def _ref_record(rec: Mapping[str, Any]) -> dict[str, Any]:
    return {
        "id": str(rec["id"]),
        "uid": str(rec["uid"]),
        "client": str(rec["client"]),
        "priority": int(rec["priority"]),
        "exclusive": bool(rec["exclusive"]),
        "holder": str(rec["holder"]),
        "suspended": bool(rec.get("suspended", False)),
    }


def replay(records: Iterable[Mapping[str, Any]], name: str) -> ReplayState:
    """Apply journal records.

    Args:
        records: The records, in order.
        name: The catalog's name, for messages.

    Returns:
        The resources the catalog describes.

    Raises:
        CatalogCorruptError: If a record does not fit the state built so far.
    """
    state = ReplayState()
    entries, owner = state.entries, state.ref_owner
    for index, rec in enumerate(records):
        try:
            _apply(rec, entries, owner)
        except (KeyError, TypeError, ValueError) as err:
            raise CatalogCorruptError(
                f"{name}: record {index + 1} ({rec.get('op', '?')!r}) does not fit: {err!r}"
            ) from None
    return state


def _add_ref(
    entries: dict[str, dict[str, Any]], owner: dict[str, str], ref: dict[str, Any], link: bool
) -> None:
    entries[ref["uid"]]["refs"][ref["id"]] = ref
    owner[ref["id"]] = ref["uid"]
    if link and ref["holder"]:
        entries[ref["holder"]]["deps"].append(ref["id"])


def _drop_entry(entries: dict[str, dict[str, Any]], owner: dict[str, str], uid: str) -> None:
    entry = entries.pop(uid)
    for ref_id in entry["refs"]:
        owner.pop(ref_id, None)


def _apply(
    rec: Mapping[str, Any], entries: dict[str, dict[str, Any]], owner: dict[str, str]
) -> None:
    op = rec["op"]
    if op == "begin":
        uid = str(rec["uid"])
        if uid in entries:
            raise ValueError(f"resource {uid} begun twice")
        entries[uid] = {
            "server": str(rec["server"]),
            "request": rec["request"],
            "response": None,
            "loaded": False,
            "failed": False,
            "progress": None,
            "refs": {},
            "deps": [],
        }
    elif op == "progress":
        entries[str(rec["uid"])]["progress"] = dict(rec["data"])
    elif op == "ref":
        for ref_id in rec.get("suspends", ()):
            entries[owner[str(ref_id)]]["refs"][str(ref_id)]["suspended"] = True
        _add_ref(entries, owner, _ref_record(rec), link=True)
    elif op == "load":
        entry = entries[str(rec["uid"])]
        entry["loaded"] = True
        entry["response"] = rec["response"]
        if rec.get("ref") is not None:
            _add_ref(entries, owner, _ref_record(rec["ref"]), link=True)
        if "refs" in rec:  # a compacted snapshot: complete lists, no linking
            for raw in rec["refs"]:
                _add_ref(entries, owner, _ref_record(raw), link=False)
            entry["deps"] = [str(d) for d in rec["deps"]]
            entry["failed"] = bool(rec["failed"])
    elif op == "deps":
        entries[str(rec["uid"])]["deps"] = [str(d) for d in rec["deps"]]
    elif op == "unref":
        ref_id = str(rec["id"])
        uid = owner.pop(ref_id)
        ref = entries[uid]["refs"].pop(ref_id)
        holder = entries.get(ref["holder"]) if ref["holder"] else None
        if holder is not None and ref_id in holder["deps"]:
            holder["deps"].remove(ref_id)
        for other in rec.get("resumes", ()):
            entries[owner[str(other)]]["refs"][str(other)]["suspended"] = False
    elif op in ("unload", "abandon"):
        _drop_entry(entries, owner, str(rec["uid"]))
    elif op == "failed":
        entries[str(rec["uid"])]["failed"] = True
    elif op == "recovered":
        entries[str(rec["uid"])]["failed"] = False
    elif op == "response":
        entries[str(rec["uid"])]["response"] = rec["response"]
    else:
        raise ValueError(f"unknown operation {op!r}")
