"""A running action's log is visible in the run's snapshot before the action returns."""

from __future__ import annotations

import threading

from temoto import Action, ActionCatalog, ActionEngine, Result, parse_graph, parse_umrf


def test_the_log_of_a_running_action_shows_in_graph_json() -> None:
    logged = threading.Event()
    release = threading.Event()

    class Talker(Action):
        def on_run(self) -> bool:
            self.log("half way there")
            logged.set()
            release.wait(10)
            return True

    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(Talker, parse_umrf({"name": "Talker", "type": "sync"}))
    graph = parse_graph({"graph_name": "g", "actions": [{"name": "Talker", "type": "sync"}]})
    with ActionEngine(actions=catalog) as engine:
        engine.start(graph)
        assert logged.wait(5)
        (action,) = engine.graph_json("g")["actions"]
        assert action["state"] == "RUNNING"
        assert [m["message"] for m in action["runtime"]["messages"]] == ["half way there"]
        release.set()
        assert engine.wait("g", 5) is Result.TRUE
