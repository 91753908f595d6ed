"""The simulated vehicle's layers: each module's class calls only what it or a layer below has."""

from __future__ import annotations

import ast
import importlib
import inspect
import itertools
import textwrap

import pytest

# bottom to top, as the modules' docstrings list them
LAYERS = (
    ("sim_state", "VehicleState"),
    ("sim_telemetry", "VehicleTelemetry"),
    ("sim_auto", "AutoMission"),
    ("sim_flight", "FlightModel"),
    ("sim_failsafe", "Failsafes"),
    ("sim_commands", "CommandHandler"),
    ("sim", "SimVehicle"),
)


def _layer(module: str, name: str) -> type:
    cls = getattr(importlib.import_module(f"temoto.drivers.mavlink.{module}"), name)
    assert isinstance(cls, type)
    return cls


def test_each_layer_builds_on_the_one_below() -> None:
    classes = [_layer(m, n) for m, n in LAYERS]
    for below, above in itertools.pairwise(classes):
        assert above.__bases__ == (below,), above


@pytest.mark.parametrize(("module", "name"), LAYERS)
def test_a_layer_calls_nothing_above_it(module: str, name: str) -> None:
    cls = _layer(module, name)
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    called = {
        node.func.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id == "self"
    }
    assert called
    assert sorted(c for c in called if not hasattr(cls, c)) == []
