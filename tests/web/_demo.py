"""A small running demo for the live-view tests: conformance actions plus one resource holder."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from temoto import Action, ActionCatalog, ActionEngine, parse_graph, parse_umrf
from temoto.core.graph import UmrfGraph
from temoto.core.registrar import LoadContext, Registrar, ResourceServer

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"

#: Log lines of the logger action: one plain, one that would be markup if it were not escaped.
LOG_LINES = ["hello from the live view", "<b id='injected'>not bold</b> & <script>x()</script>"]


@dataclass(frozen=True)
class Camera:
    device: str


@dataclass(frozen=True)
class Opened:
    handle: int


class CameraServer(ResourceServer[Camera, Opened]):
    name = "camera"
    request_type = Camera
    response_type = Opened

    def __init__(self) -> None:
        self.unloads: list[str] = []

    def on_load(self, request: Camera, ctx: LoadContext) -> Opened:
        return Opened(7)

    def on_unload(self, request: Camera, response: Opened) -> None:
        self.unloads.append(request.device)


class Holder(Action):
    """Holds a camera until stopped."""

    acquired: threading.Event

    def on_run(self) -> bool:
        self.acquire("camera", Camera("/dev/video0"))
        self.log("holding the camera")
        type(self).acquired.set()
        self.wait_until_stopped()
        return True


def _ref(name: str, instance: int = 0, **extra: Any) -> dict[str, Any]:
    return {"name": name, "instance_id": instance, **extra}


def demo_graph(timer_s: float, name: str = "live_demo") -> UmrfGraph:
    """Logger -> (Timer -> Relay -> exit) and Logger -> Holder (stopped when the graph ends)."""
    run_on_true = ["on_true -> run", "on_false -> ignore", "on_stopped -> ignore",
                   "on_error -> ignore"]  # fmt: skip
    return parse_graph(
        {
            "graph_name": name,
            "graph_description": "the live view's demo",
            "graph_entry": [_ref("TaLogger")],
            "graph_exit": [_ref("TaRelayString")],
            "actions": [
                {
                    **_ref("TaLogger"),
                    "type": "sync",
                    "input_parameters": {
                        "messages": {"pvf_type": "strings", "pvf_value": LOG_LINES}
                    },
                    "children": [_ref("TaTimer"), _ref("Holder")],
                },
                {
                    **_ref("TaTimer"),
                    "type": "sync",
                    "input_parameters": {
                        "count_until": {"pvf_type": "number", "pvf_value": timer_s}
                    },
                    "parents": [_ref("TaLogger", required=True, conditions=run_on_true)],
                    "children": [_ref("TaRelayString")],
                },
                {
                    **_ref("Holder"),
                    "type": "sync",
                    "parents": [_ref("TaLogger", required=True, conditions=run_on_true)],
                },
                {
                    **_ref("TaRelayString"),
                    "type": "sync",
                    "input_parameters": {"string_in": {"pvf_type": "string", "pvf_value": "done"}},
                    "parents": [_ref("TaTimer", required=True, conditions=run_on_true)],
                },
            ],
        }
    )


@dataclass
class Demo:
    engine: ActionEngine
    registrar: Registrar
    camera: CameraServer
    acquired: threading.Event


@contextmanager
def demo_engine() -> Iterator[Demo]:
    acquired = threading.Event()
    holder = type("Holder", (Holder,), {"acquired": acquired})
    catalog = ActionCatalog([ACTIONS], use_entry_points=False)
    catalog.register(holder, parse_umrf({"name": "Holder", "type": "sync"}))
    registrar = Registrar("live-view-test")
    camera = CameraServer()
    registrar.register(camera)
    try:
        with ActionEngine("robot", actions=catalog, registrar=registrar) as engine:
            yield Demo(engine, registrar, camera, acquired)
    finally:
        registrar.close()
