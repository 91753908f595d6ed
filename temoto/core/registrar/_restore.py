"""The registrar's restore after a crash: settle what the crash left, then re-check the rest.

Registrar internal: :meth:`Registrar.register <temoto.core.registrar.Registrar.register>`
calls :func:`settle` once every server a restored catalog names is registered and the
:class:`~temoto.core.registrar._ledger.Ledger` has been rebuilt from the journal. The order of
the steps is ``docs/registrar.md``'s "Restore".
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

from temoto.core.registrar import records

if TYPE_CHECKING:
    from temoto.core.registrar._ledger import Entry, Ledger
    from temoto.core.registrar.server import RegistrarAPI

__all__ = ["settle"]

logger = logging.getLogger(__name__)


def settle(
    registrar: RegistrarAPI,
    ledger: Ledger,
    lock: threading.Lock,
    restored: list[Entry],
    unload: Callable[[Entry], None],
    transient: Callable[[str], bool] | None,
) -> None:
    """Settle the restored resources, then let their servers re-check them.

    Args:
        registrar: The registrar (its public ``release``, ``release_consumers``, ``server``
            and ``send_status`` are used).
        ledger: Its rebuilt ledger.
        lock: The lock that guards ``ledger``.
        restored: The restored resources, in the journal's order.
        unload: Unloads a resource that has no references (its dependencies first).
        transient: Which consumers died with the process (the registrar's ``transient``).
    """
    journal = ledger.journal
    logger.info(
        "restored %d resources from %s", len(restored), journal.path if journal else "catalog"
    )
    # Settle what the crash left, before any server is asked about its resources (a resource
    # unloaded here is never reported on): a resource whose last reference had been released
    # is unloaded; the references of consumers that died with the previous process are
    # released; a half-done load is undone (its dependencies released, the server told to
    # clean up).
    for entry in restored:
        with lock:
            if entry.slot < 0 or entry.loading or ledger.book.count(entry.slot):
                continue
            if ledger.live.get((entry.server, entry.key)) == entry.uid:
                del ledger.live[(entry.server, entry.key)]
        logger.warning("restore: %s had been released; unloading it", entry.uid)
        unload(entry)
    if transient is not None:
        gone = registrar.release_consumers(lambda ref: transient(ref.client))
        if gone:
            logger.info("restore: released %d references of consumers that are gone", gone)
    for entry in restored:
        if entry.loading and entry.uid in ledger.entries:
            logger.warning("restore: the load of %s was interrupted; undoing it", entry.uid)
            with lock:
                deps = ledger.dep_ids(entry)
            for dep in reversed(deps):
                if dep in ledger.refs:
                    registrar.release(dep)
            try:
                registrar.server(entry.server).on_abandoned(entry.request, entry.progress)
            except Exception:
                logger.exception("server '%s' failed to undo %s", entry.server, entry.uid)
            with lock:
                ledger.forget(entry, records.Abandon)
    # Then each server re-checks what is left of its resources (re-adopts them, or reports
    # them failed), dependencies before the resources holding them; a verdict is reported at
    # once, so a holder's server sees its dependencies' failures.
    with lock:
        order = ledger.restore_order(restored)
    for entry in order:
        with lock:
            if ledger.entries.get(entry.uid) is not entry or entry.loading:
                continue  # unloaded meanwhile (by an earlier hook's release): not reported
            info = ledger.info(entry)
        verdict = registrar.server(entry.server).on_restore(info)
        if verdict is not None and entry.uid in ledger.entries:
            registrar.send_status(entry.uid, verdict[0], verdict[1])
