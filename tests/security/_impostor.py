"""Processes of tests/security/test_impostor_processes.py: a member that speaks as another.

``python _impostor.py ROLE URL IDENTITY ROSTER ARGS...``, every role a library-level process
that seals with its own valid key (IDENTITY, a roster member) and names another member inside
its messages, or the honest observer that reports what it took in:

``actor NAME GRAPH ACTIONS``
    runs GRAPH as actor NAME (an ActionEngine whose fleet link speaks as the identity's name);
    prints the run's result.
``replier NAME SECONDS``
    answers every graph command with OK and publishes feedback, both naming actor NAME.
``world NAME SECONDS``
    advertises a RIS offer and publishes a world-model item, both as robot NAME.
``observer NAME SECONDS ACTIONS``
    a whole Instance NAME with its own identity; after SECONDS prints JSON: the robots its RIS
    heard, the names of its world-model items and its services' ``impostor`` counters.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any


def _link(url: str, identity: str, roster: str) -> Any:
    from temoto.transport import FleetAuth, FleetLink, open_transport
    from temoto.transport.identity import Credentials

    creds = Credentials.load(identity, roster)
    transport = open_transport(url)
    return FleetLink(transport, FleetAuth("temoto", creds.identity.name, creds))


def actor(url: str, identity: str, roster: str, name: str, graph: str, actions: str) -> None:
    from temoto.core.catalog import ActionCatalog
    from temoto.core.documents import load_graph
    from temoto.core.engine import ActionEngine
    from temoto.fleet import FleetActorLink

    link = _link(url, identity, roster)
    with (
        FleetActorLink(link, name) as actors,
        ActionEngine(
            name, actions=ActionCatalog([actions]), link=actors, handshake_timeout=8.0
        ) as engine,
    ):
        run = engine.start(load_graph(graph))
        try:
            print(engine.wait(run, 20.0).value, flush=True)
        except Exception as err:  # a failed handshake: the result is what the test looks at
            print(f"failed: {err}", flush=True)
    link.transport.close()


def replier(url: str, identity: str, roster: str, name: str, seconds: str) -> None:
    from temoto.fleet.common import new
    from temoto.fleet.control import COMMAND_CHANNEL, FEEDBACK_CHANNEL, REPLY_CHANNEL
    from temoto.lcm_types import graph_command_reply_t, graph_feedback_t
    from temoto.transport import codec

    link = _link(url, identity, roster)

    def on_command(opened: Any) -> None:
        msg = codec.decode(opened.type, opened.payload)
        reply = new(graph_command_reply_t)
        reply.request_id, reply.actor, reply.graph = msg.request_id, name, msg.graph
        reply.session, reply.code, reply.message = msg.session or msg.graph, 1, "started"
        link.send(REPLY_CHANNEL, *codec.encode(reply))
        feedback = new(graph_feedback_t)
        feedback.actor, feedback.graph, feedback.session = name, msg.graph, msg.graph
        feedback.state, feedback.result = "finished", "on_true"
        link.send(FEEDBACK_CHANNEL, *codec.encode(feedback))

    link.listen(COMMAND_CHANNEL, on_command)
    print("ready", flush=True)
    time.sleep(float(seconds))
    link.transport.close()


def world(url: str, identity: str, roster: str, name: str, seconds: str) -> None:
    from temoto.core.registrar import Registrar
    from temoto.fleet import ResourceInfoSync
    from temoto.managers.context import ContextManager
    from temoto.managers.process import ProcessManager

    link = _link(url, identity, roster)
    registrar = Registrar(name)
    with (
        ProcessManager(registrar),
        ResourceInfoSync(link, registrar, name, period_s=0.2),
        ContextManager(name, link=link, registrar=registrar) as context,
    ):
        print("ready", flush=True)
        deadline = time.monotonic() + float(seconds)
        n = 0
        while time.monotonic() < deadline:
            context.add(f"crate{n}", "object")  # a change each time: published at once
            n += 1
            time.sleep(0.2)
    link.transport.close()


def observer(url: str, identity: str, roster: str, name: str, seconds: str, actions: str) -> None:
    from temoto.instance import Instance
    from temoto.transport import open_transport
    from temoto.transport.identity import Credentials

    creds = Credentials.load(identity, roster)
    with Instance(name, transport=open_transport(url), key=creds, actions=[actions]) as inst:
        print("ready", flush=True)
        time.sleep(float(seconds))
        report = {
            "robots": [r.robot for r in inst.ris.robots()],
            "items": sorted(i.name for i in inst.context.items()),
            "impostor": {
                "ris": inst.ris.stats.get("impostor", 0),
                "context": inst.context.stats.get("impostor", 0),
            },
        }
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    role, *rest = sys.argv[1:]
    {"actor": actor, "replier": replier, "world": world, "observer": observer}[role](*rest)
