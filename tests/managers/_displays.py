"""A one-node graph that shows a display: the built-in ``ShowDisplay`` action with its inputs."""

from __future__ import annotations

from typing import Any


def show_display_graph(name: str, **inputs: str | float) -> dict[str, Any]:
    """The UMRF graph ``name`` of one ``ShowDisplay`` node with these inputs (strings and
    numbers, e.g. ``source="robot", field="joints", duration=4.0``)."""
    return {
        "graph_name": name,
        "graph_entry": [{"name": "ShowDisplay", "instance_id": 0}],
        "graph_exit": [{"name": "ShowDisplay", "instance_id": 0}],
        "actions": [
            {
                "name": "ShowDisplay",
                "instance_id": 0,
                "type": "sync",
                "input_parameters": {
                    key: {
                        "pvf_type": "string" if isinstance(value, str) else "number",
                        "pvf_value": value,
                    }
                    for key, value in inputs.items()
                },
            }
        ],
    }
