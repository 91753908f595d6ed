"""An instance started with a live view serves it until it closes."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from temoto.instance import Instance
from temoto.transport.inprocess import InProcessTransport

ACTIONS = Path(__file__).resolve().parents[2] / "examples" / "actions" / "conformance"
GRAPH = {
    "graph_name": "relay",
    "graph_entry": [{"name": "TaRelayString", "instance_id": 0}],
    "graph_exit": [{"name": "TaRelayString", "instance_id": 0}],
    "actions": [
        {
            "name": "TaRelayString",
            "instance_id": 0,
            "type": "sync",
            "input_parameters": {"string_in": {"pvf_type": "string", "pvf_value": "x"}},
        }
    ],
}


def test_the_live_view_lists_the_instances_runs_and_stops_with_it() -> None:
    with Instance(
        "A",
        transport=InProcessTransport("live-view-instance"),
        key=bytes(32),
        actions=[ACTIONS],
        live_view_port=0,
    ) as instance:
        assert instance.live_view is not None
        url = instance.live_view.base_url
        instance.engine.run(GRAPH, timeout=10)
        with urllib.request.urlopen(f"{url}api/graphs", timeout=5) as reply:
            runs = json.load(reply)
    assert any("relay" in json.dumps(run) for run in runs["graphs"]), runs
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(f"{url}api/graphs", timeout=2)
