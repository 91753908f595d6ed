"""Component Manager reliabilities in a file: restored after a restart, written atomically."""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest
from _statuses import Statuses

from temoto.core.registrar import Registrar, Status
from temoto.errors import ConfigError, ResourceLoadError
from temoto.managers.component import (
    ComponentDescription,
    ComponentManager,
    ComponentManagerClient,
    ComponentRequest,
    Reliability,
)
from temoto.managers.component.manager import COMPONENT_STATS
from temoto.managers.process import ProcessManager

WAIT = 10.0
LOGGER = "temoto.managers.component"


def peer(name: str) -> ComponentDescription:
    """A long-running component of type ``tie`` (equal priorities: reliability ranks)."""
    return ComponentDescription(
        name, "tie", sys.executable, ("-S", "-I", "-c", "import time; time.sleep(60)"), priority=1
    )


#: Cannot start (program missing): each request rates it 0 without starting a process.
GHOST = ComponentDescription("ghost", "phantom", "/nonexistent/ghost")


class Robot:
    """A registrar, a Process Manager and a Component Manager using ``file``."""

    def __init__(self, stack: ExitStack, file: Path, **kwargs: Any) -> None:
        self.registrar = Registrar("r1")
        stack.callback(self.registrar.close)
        self.processes = ProcessManager(self.registrar, grace=1.0)
        stack.callback(self.processes.shutdown)
        self.components = ComponentManager(
            self.registrar,
            channel_prefix=f"test-{os.getpid()}-rel",
            reliability_file=file,
            **kwargs,
        )
        stack.callback(self.components.shutdown)
        stack.callback(self.release_all)

    def release_all(self) -> None:
        for info in self.registrar.resources():
            for ref in info.references:
                if not ref.holder:
                    self.registrar.release(ref.id)

    def fail_ghost(self) -> None:
        """Record one failure of ``r1/ghost`` (it cannot start)."""
        with pytest.raises(ResourceLoadError, match="no candidate of type 'phantom' could start"):
            self.registrar.call("component", ComponentRequest("phantom"))


@pytest.fixture
def stack() -> Iterator[ExitStack]:
    with ExitStack() as stack:
        yield stack


def read(file: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(file.read_text(encoding="utf-8"))
    return data


def write(file: Path, components: dict[str, list[Any]], window: int = 100) -> None:
    data = {
        "version": 1,
        "window": window,
        "components": {key: {"outcomes": outcomes} for key, outcomes in components.items()},
    }
    file.write_text(json.dumps(data), encoding="utf-8")


def test_reliability_keeps_recorded_outcomes_only() -> None:
    rel = Reliability(0.8, 3)
    assert rel.outcomes() == []
    rel.adjust(0.0)
    assert rel.outcomes() == [0.0]
    again = Reliability(0.8, 3, history=[0, 1, 1, 1, 0])  # only the newest 3 count
    assert again.outcomes() == [1.0, 1.0, 0.0]
    assert again.value == pytest.approx(2 / 3)
    assert Reliability(0.8, 100, history=[0]).value == pytest.approx(0.792)


def test_outcomes_survive_a_restart_and_rank_candidates(stack: ExitStack, tmp_path: Path) -> None:
    file = tmp_path / "reliability.json"
    first = Robot(stack, file)
    first.components.add([peer("a_sensor"), peer("b_sensor")])
    assert not file.exists()  # nothing recorded yet, nothing written
    ranked = first.components.candidates("tie")
    assert [c.description.name for c in ranked] == ["a_sensor", "b_sensor"]  # a tie: by key
    client = ComponentManagerClient(first.registrar)
    statuses = Statuses()
    handle = client.request("tie", on_status=statuses)
    assert handle.name == "a_sensor"
    os.kill(handle.response.pid, signal.SIGKILL)  # a fails: failover to b
    assert "switched from r1/a_sensor to r1/b_sensor" in statuses.first(Status.WARNING).message
    client.release(handle)  # b served until released: a success
    assert read(file) == {
        "version": 1,
        "window": 100,
        "components": {"r1/a_sensor": {"outcomes": [0]}, "r1/b_sensor": {"outcomes": [1]}},
    }
    first.components.shutdown()
    assert first.processes.running() == []

    with ExitStack() as again:  # the restarted manager
        second = Robot(again, file)
        second.components.add([peer("a_sensor"), peer("b_sensor")])
        assert second.components.reliability("a_sensor") == pytest.approx(0.792)
        assert second.components.reliability("b_sensor") == pytest.approx(0.802)
        ranked = second.components.candidates("tie")
        assert [c.description.name for c in ranked] == ["b_sensor", "a_sensor"]

    with ExitStack() as plain:  # without a file: today's behaviour, from the descriptions
        registrar = Registrar("r1")
        plain.callback(registrar.close)
        manager = ComponentManager(registrar)
        plain.callback(manager.shutdown)
        manager.add([peer("a_sensor"), peer("b_sensor")])
        assert manager.reliability("a_sensor") == 0.8
        assert manager.stats["reliability_write_errors"] == 0
        assert "reliability_write_errors" in COMPONENT_STATS


def test_a_larger_saved_window_keeps_the_newest_outcomes(stack: ExitStack, tmp_path: Path) -> None:
    file = tmp_path / "reliability.json"
    write(file, {"r1/a_sensor": [0] * 50 + [1] * 100}, window=200)
    robot = Robot(stack, file)  # window 100
    robot.components.add([peer("a_sensor"), GHOST])
    assert robot.components.reliability("a_sensor") == 1.0  # the 50 old failures are gone
    robot.fail_ghost()
    saved = read(file)
    assert saved["window"] == 100
    assert saved["components"] == {
        "r1/a_sensor": {"outcomes": [1] * 100},
        "r1/ghost": {"outcomes": [0]},
    }
    with ExitStack() as small:  # and a smaller window than the file's
        registrar = Registrar("r2")
        small.callback(registrar.close)
        manager = ComponentManager(registrar, robot="r1", window=4, reliability_file=file)
        small.callback(manager.shutdown)
        manager.add([peer("a_sensor")])
        assert manager.reliability("a_sensor") == 1.0


def test_history_of_a_component_described_later_is_kept(stack: ExitStack, tmp_path: Path) -> None:
    file = tmp_path / "reliability.json"
    write(file, {"r1/late": [0] * 10, "r9/elsewhere": [1, 0.5]})
    robot = Robot(stack, file)
    robot.components.add([GHOST])
    robot.fail_ghost()  # a write while "late" is not described: its history stays in the file
    assert read(file)["components"] == {
        "r1/ghost": {"outcomes": [0]},
        "r1/late": {"outcomes": [0] * 10},
        "r9/elsewhere": {"outcomes": [1, 0.5]},
    }
    described = tmp_path / "late.yaml"
    described.write_text(
        "components:\n  - {name: late, type: phantom, executable: /bin/true, reliability: 0.9}\n"
    )
    robot.components.add_file(described)
    # restored outcomes on top of the description's initial value: 0.9 - 10 * 0.9 / 100
    assert robot.components.reliability("late") == pytest.approx(0.81)
    robot.components.shutdown()
    with ExitStack() as again:
        second = Robot(again, file)
        second.components.add_file(described)
        assert second.components.reliability("late") == pytest.approx(0.81)


def test_a_failed_write_keeps_the_old_file_and_is_counted(
    stack: ExitStack,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    file = tmp_path / "reliability.json"
    tmp = tmp_path / "reliability.json.tmp"
    robot = Robot(stack, file)
    robot.components.add([GHOST])
    robot.fail_ghost()
    before = file.read_bytes()
    assert read(file)["components"] == {"r1/ghost": {"outcomes": [0]}}

    def crash(src: object, dst: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", crash)  # the write dies between the .tmp and the rename
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        robot.fail_ghost()  # the start failure is reported, the write failure is not raised
        robot.fail_ghost()
    assert file.read_bytes() == before
    assert not tmp.exists()
    assert robot.components.stats["reliability_write_errors"] == 2
    warnings = [r for r in caplog.records if "reliability file" in r.getMessage()]
    assert len(warnings) == 1  # once per streak of failures
    assert "No space left on device" in warnings[0].getMessage()
    assert robot.components.reliability("ghost") == pytest.approx(0.8 - 3 * 0.008)

    monkeypatch.undo()
    robot.components.shutdown()  # the failed write is retried
    assert read(file)["components"] == {"r1/ghost": {"outcomes": [0, 0, 0]}}
    assert robot.components.stats["reliability_write_errors"] == 2

    tmp.write_text('{"version": 1, "window": 100, "comp')  # a crash left a torn .tmp behind
    with ExitStack() as again:
        second = Robot(again, file)
        second.components.add([GHOST])
        assert second.components.reliability("ghost") == pytest.approx(0.8 - 3 * 0.008)
        second.fail_ghost()
        assert read(file)["components"] == {"r1/ghost": {"outcomes": [0, 0, 0, 0]}}
        assert not tmp.exists()


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("{not json", "not a JSON reliability file"),
        ("[]", "expected a JSON object, got list"),
        ('{"version": 2, "window": 100, "components": {}}', "version: unsupported version 2"),
        ('{"window": 100, "components": {}}', "version: unsupported version None"),
        ('{"version": 1, "window": 0, "components": {}}', "window: must be an integer >= 1"),
        ('{"version": 1, "window": 100, "components": []}', "components: must be an object"),
        ('{"version": 1, "window": 100, "components": {}, "x": 1}', r"unknown key\(s\): x"),
        (
            '{"version": 1, "window": 100, "components": {"lidar": {"outcomes": []}}}',
            r"components\['lidar'\]: a key must be 'robot/name'",
        ),
        (
            '{"version": 1, "window": 100, "components": {"r1/a": [1, 0]}}',
            r"components\['r1/a'\]: must be an object with exactly the key 'outcomes'",
        ),
        (
            '{"version": 1, "window": 100, "components": {"r1/a": {"outcomes": "10"}}}',
            r"components\['r1/a'\].outcomes: must be a list, got str",
        ),
        (
            '{"version": 1, "window": 100, "components": {"r1/a": {"outcomes": [1, "yes"]}}}',
            r"components\['r1/a'\].outcomes\[1\]: an outcome must be a number in \[0, 1\]",
        ),
        (
            '{"version": 1, "window": 100, "components": {"r1/a": {"outcomes": [1.5]}}}',
            r"outcomes\[0\]: an outcome must be a number in \[0, 1\] or a boolean, got 1.5",
        ),
        (
            '{"version": 1, "window": 100, "components": {"r1/a": {"outcomes": [NaN]}}}',
            r"outcomes\[0\]: an outcome must be a number",
        ),
    ],
)
def test_a_corrupt_file_is_a_config_error_naming_it(
    tmp_path: Path, text: str, problem: str
) -> None:
    file = tmp_path / "reliability.json"
    file.write_text(text, encoding="utf-8")
    registrar = Registrar("r1")
    try:
        with pytest.raises(ConfigError, match=problem) as caught:
            ComponentManager(registrar, reliability_file=file)
        assert str(caught.value).startswith(f"{file}: ")
        assert caught.value.file == str(file)
        assert registrar.servers() == []  # nothing registered: fix the file, start again
        assert file.read_text(encoding="utf-8") == text  # and it was not overwritten
    finally:
        registrar.close()


def test_an_unreadable_file_is_a_config_error(tmp_path: Path) -> None:
    registrar = Registrar("r1")
    try:
        with pytest.raises(ConfigError, match="cannot read the reliability file"):
            ComponentManager(registrar, reliability_file=tmp_path)  # a folder
        booleans = tmp_path / "booleans.json"  # true/false read as 1/0
        write(booleans, {"r1/ghost": [True, False, False]})
        with ComponentManager(registrar, reliability_file=booleans) as manager:
            manager.add([GHOST])
            assert manager.reliability("ghost") == pytest.approx(0.8 + (0.2 - 0.8 - 0.8) / 100)
    finally:
        registrar.close()
