"""One TeMoto instance: what a robot (or an operator station) runs (docs/design.md §2).

An :class:`Instance` puts together an :class:`~temoto.core.engine.ActionEngine` whose actor is
the robot's name, a :class:`~temoto.core.registrar.Registrar` with the Process Manager on it,
and the fleet: an authenticated link on a transport, the actor link for shared graphs, the
:class:`~temoto.fleet.control.GraphControlServer` that takes ``temoto graph start|stop|...``
commands, and resource sharing — the Resource Info Synchronizer advertising this robot's
servers and :class:`~temoto.fleet.resources.RemoteResources` (the ``"remote"`` server for what
only another robot serves, and the provider for the others' requests). The Component Manager
(``"component"``, ``"pipeline"``; candidates on other robots through RIS) and the Context
Manager (``"context"``, the world model synchronised with the other robots) run on the same
registrar, and their built-in actions are in the engine's catalog, as are the ROS 2 actions
(``"ros2"``: bridge processes; ``"ros2_lifecycle"``: lifecycle nodes; ``docs/ros2.md``).
``temoto serve`` runs one until SIGINT or SIGTERM; the Robot Manager builds on it.

Closing stops the runs (their actions get their stop request, their resources are released),
then the fleet services and the managers, releases whatever is still held, then stops the
processes and closes the transport, in that order, so nothing started by the instance outlives
it and its catalog ends empty.

Restarted on the catalog of a previous run (``--state-dir``), an instance releases every
reference that run held: graph runs are not persistent (a run that died with its process is
not resumed), nor is anything else that holds resources in an instance. What only they held is
unloaded (processes stopped) before the servers re-check the rest (``docs/registrar.md``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from temoto._closing import Closing
from temoto.actions.builtin import COMPONENT_ACTIONS, CONTEXT_ACTIONS, ROS2_ACTIONS
from temoto.clock import Clock
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.engine import ActionEngine
from temoto.core.registrar import Registrar
from temoto.fleet.actors import FleetActorLink
from temoto.fleet.control import GraphControlServer
from temoto.fleet.resources import RemoteResources
from temoto.fleet.ris import ResourceInfoSync
from temoto.managers.component import ComponentManager
from temoto.managers.context import ContextManager
from temoto.managers.process import ProcessManager
from temoto.ros2.lifecycle import Ros2LifecycleManager
from temoto.ros2.manager import Ros2Manager
from temoto.transport.auth import FleetAuth
from temoto.transport.base import Transport
from temoto.transport.link import FleetLink

if TYPE_CHECKING:
    from temoto.transport.identity import Credentials
    from temoto.web import LiveView

__all__ = ["Instance"]

logger = logging.getLogger(__name__)


class Instance(Closing):
    """An engine, a registrar with its managers, and the fleet services, for one actor.

    Args:
        actor: The robot's (or station's) name: the engine's actor and the fleet sender id.
        transport: The fleet transport; the instance closes it (also when it cannot start).
        key: The fleet key, or this member's credentials (identity and roster,
            docs/security.md), or None with ``insecure=True``.
        fleet: The fleet's name (part of every message's authentication).
        insecure: Run without a key (any host could command this instance; logged).
        actions: Folders of actions.
        graphs: Folders of graphs (what ``temoto graph start NAME`` can start).
        catalog: The registrar's journal file (None: kept in memory only). One left by an
            earlier run is restored and settled: the references it lists are released (their
            holders died with that run), so what they held is unloaded (processes stopped).
        world: The Context Manager's world-model file (None: kept in memory only).
        reliability_file: The Component Manager's reliabilities (None: kept in memory only).
        handshake_timeout: Seconds to wait for the other actors of a shared graph.
        stop_timeout: Seconds an action may take to stop.
        feedback_period_s: Every run's state is published this often.
        clock: The engine's clock (default: real time).
        silence_s: Another actor of a shared graph not heard for this long is lost.
        resend_s: Handshakes and notifications are resent this often until answered.
        component_files: Component descriptions and pipeline templates (YAML or JSON).
        live_view_port: Serve the live view of running graphs (:mod:`temoto.web`) on this
            localhost port (0: any free port; None: no live view).
        advert_period_s: The RIS advertises this robot's servers this often; a robot not
            heard for three periods is lost (its remote resources become FATAL here).

    Raises:
        ValueError: ``actor`` is empty.
        TransportError: The fleet link cannot listen.
        CatalogCorruptError: The registrar's or the world model's journal is damaged.
        ConfigError: The reliability file cannot be used.
        ResourceBusyError: Another process has one of those journals open.
    """

    def __init__(
        self,
        actor: str,
        *,
        transport: Transport,
        key: bytes | Credentials | None,
        fleet: str = "temoto",
        insecure: bool = False,
        actions: Iterable[str | Path] = (),
        graphs: Iterable[str | Path] = (),
        catalog: str | Path | None = None,
        world: str | Path | None = None,
        reliability_file: str | Path | None = None,
        handshake_timeout: float = 5.0,
        stop_timeout: float = 5.0,
        feedback_period_s: float = 1.0,
        advert_period_s: float = 1.0,
        clock: Clock | None = None,
        silence_s: float = 3.0,
        resend_s: float = 0.1,
        live_view_port: int | None = None,
        component_files: Iterable[str | Path] = (),
    ) -> None:
        if not actor:
            transport.close()  # it was handed over: closed on every way out
            raise ValueError("an instance needs an actor name")
        self.actor = actor
        self.transport = transport
        self._closed = False
        self._managers: list[object] = []
        closing: list[object] = []
        try:
            # Every consumer of this registrar lives in this process (graph runs, the robot
            # command, the managers' own holds, what the provider holds for other robots):
            # after a crash none of them is coming back for its references.
            self.registrar = Registrar(
                actor, catalog=catalog, restore=catalog is not None, transient=_died_with_us
            )
            closing.append(self.registrar)
            self.processes = ProcessManager(self.registrar)
            closing.append(self.processes)
            # ROS 2 bridges (docs/ros2.md): rclpy is imported only in a bridge process, when a
            # ROS 2 action asks for one; without the ros2 extra that action fails in one line.
            self.ros2 = Ros2Manager(self.registrar)
            self.ros2_lifecycle = Ros2LifecycleManager(self.registrar)
            self.link = FleetLink(transport, FleetAuth(fleet, actor, key, insecure=insecure))
            self.actors = FleetActorLink(self.link, actor, silence_s=silence_s, resend_s=resend_s)
            closing.append(self.actors)
            self.ris = ResourceInfoSync(self.link, self.registrar, actor, period_s=advert_period_s)
            closing.append(self.ris)
            self.resources = RemoteResources(self.link, self.registrar, self.ris)
            closing.append(self.resources)
            self.components = ComponentManager(
                self.registrar,
                files=component_files,
                ris=self.ris,
                reliability_file=reliability_file,
            )
            closing.append(self.components)
            self.context = ContextManager(
                actor, link=self.link, registrar=self.registrar, clock=clock, store=world
            )
            closing.append(self.context)
            self.engine = ActionEngine(
                actor,
                actions=ActionCatalog([COMPONENT_ACTIONS, CONTEXT_ACTIONS, ROS2_ACTIONS, *actions]),
                graphs=GraphIndex(graphs),
                stop_timeout=stop_timeout,
                registrar=self.registrar,
                link=self.actors,
                handshake_timeout=handshake_timeout,
                clock=clock,
            )
            closing.append(self.engine)
            self.live_view: LiveView | None = None
            if live_view_port is not None:
                from temoto.web import LiveView  # an HTTP server: imported only when asked for

                self.live_view = LiveView(self.engine, port=live_view_port)
                closing.append(self.live_view)
            self.control = GraphControlServer(
                self.engine,
                self.link,
                feedback_period_s=feedback_period_s,
                stop_timeout=stop_timeout * 2,
            )
        except BaseException:
            for part in reversed(closing):
                _close(part)
            transport.close()
            raise

    def close(self) -> None:
        """Stop everything the instance runs, in dependency order (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.control.close()  # no new commands
        if self.live_view is not None:
            _close(self.live_view)
        parts = (
            self.engine,  # runs stopped, their resources released
            *reversed(self._managers),
            self.components,
            self.context,
            self.resources,  # what others hold here is released, what we hold there too
            self.ris,
            self.actors,
            self.processes,
            self.registrar,
            self.transport,
        )
        for part in parts:
            if part is self.processes:
                # What a consumer above did not release (one that died in an action, a
                # reference taken outside a run) goes now: the catalog ends empty.
                self._release_leftovers()
                # Nothing this instance started outlives it (its consumers above have released
                # what they held; this stops the rest, e.g. of runs that did not stop in time).
                try:
                    self.processes.shutdown(stop_processes=True)
                except Exception:
                    logger.exception("closing the process manager failed")
                self.ros2.shutdown()  # segments a crashed bridge's peers re-created
                continue
            _close(part)

    def _release_leftovers(self) -> None:
        try:
            left = [
                f"{r.client} ({r.resource_id})" for r in self.registrar.references() if not r.holder
            ]
            if left:
                logger.info("releasing what was still held at close: %s", ", ".join(left))
            self.registrar.release_consumers()
        except Exception:
            logger.exception("releasing the references left at close failed")

    def add_manager(self, manager: object) -> None:
        """Have :meth:`close` shut ``manager`` down after the engine (e.g. a Robot Manager).

        Args:
            manager: Anything with a ``shutdown()`` or ``close()`` method.
        """
        self._managers.append(manager)


def _died_with_us(client: str) -> bool:
    """Restore: every consumer of an instance's catalog died with the process that wrote it."""
    return True


def _close(part: object) -> None:
    """Shut one part down (``shutdown()``, else ``close()``).

    A failure is logged, and the others still close.
    """
    try:
        stop = getattr(part, "shutdown", None) or getattr(part, "close")  # noqa: B009
        stop()
    except Exception:
        logger.exception("closing %s failed", type(part).__name__)
