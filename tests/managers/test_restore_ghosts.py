"""Restore without ghosts.

After a restart on the same catalog every restored resource is re-adopted or released: a
pipeline whose segments did not survive is FATAL (never shared with nothing behind it), the
references of consumers that died with the process are released first (an instance's are all),
an entry the restore itself unloaded gets no ``on_restore`` (no false "died while the manager was
down"), and an instance leaves an empty catalog when it closes. The crash test SIGKILLs the
robot command (``tools/crash_restore.py``; 30 rounds there, a few here).
"""

from __future__ import annotations

import importlib.util
import itertools
import logging
import os
import secrets
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import pytest

from temoto.core.registrar import (
    LoadContext,
    Registrar,
    ResourceInfo,
    ResourceServer,
    Status,
    StatusUpdate,
)
from temoto.core.registrar.journal import Journal
from temoto.core.registrar.records import replay
from temoto.instance import Instance
from temoto.managers.component import ComponentManager
from temoto.managers.component.messages import PipelineRequest
from temoto.managers.process import ProcessManager, ProcessRequest
from temoto.testing import ProcessLeakCheck
from temoto.transport import InProcessTransport

REPO = Path(__file__).resolve().parents[2]
DESCRIPTIONS = REPO / "examples" / "components" / "components.yaml"
ALARM = "died while the manager was down"
SLEEPER = ProcessRequest(sys.executable, ("-c", "import time; time.sleep(60)"))
_buses = itertools.count()


class Managers:
    """A registrar on a catalog with the Process and Component Managers (one "life")."""

    def __init__(self, catalog: Path, *, restore: bool = False, transient: Any = None) -> None:
        self.registrar = Registrar(
            "r", catalog=catalog, restore=restore, fsync="never", transient=transient
        )
        self.processes = ProcessManager(self.registrar, grace=1.0)
        self.components = ComponentManager(
            self.registrar, files=[DESCRIPTIONS], channel_prefix=f"ghosts-{os.getpid()}"
        )

    def crash(self) -> None:
        """What a SIGKILL leaves: the catalog as it is, the processes dead (they die with us)."""
        self.components.shutdown()
        self.processes.shutdown(stop_processes=True)
        self.registrar.close()

    def close(self) -> None:
        """Release what is held, stop everything."""
        if not self.registrar._closed:
            self.registrar.release_consumers()
        self.components.shutdown()
        self.processes.shutdown(stop_processes=True)
        self.registrar.close()


@pytest.fixture
def catalog(tmp_path: Path) -> Path:
    return tmp_path / "registrar.journal"


@pytest.fixture
def lives() -> Iterator[list[Managers]]:
    made: list[Managers] = []
    yield made
    for life in reversed(made):
        life.close()


def entries(path: Path) -> dict[str, dict[str, Any]]:
    """The resources a catalog describes (read from a copy: its registrar may hold it)."""
    copy = path.with_name("copy.journal")
    copy.write_bytes(path.read_bytes())
    journal = Journal(copy, fsync="never")
    try:
        return replay(journal.open(), str(path)).entries
    finally:
        journal.close()
        copy.unlink()


def test_a_restored_pipeline_whose_segments_died_is_fatal_and_never_shared(
    catalog: Path, lives: list[Managers], caplog: pytest.LogCaptureFixture
) -> None:
    first = Managers(catalog)
    old = first.registrar.call("pipeline", PipelineRequest("tracking"), client="run/Request_0")
    assert len(first.processes.running()) == 3
    first.crash()

    caplog.set_level(logging.INFO)
    again = Managers(catalog, restore=True)  # consumers kept: they may come back
    lives.append(again)
    info = again.registrar.info(old.resource_id)
    assert info.failed  # its segments (components) were not re-adopted
    # the restore stopped the segments' processes itself: no alarm about them
    assert not [r for r in caplog.records if ALARM in r.getMessage()]
    assert again.registrar.served("process") == []
    fresh = again.registrar.call("pipeline", PipelineRequest("tracking"), client="run2/Request_0")
    assert fresh.resource_id != old.resource_id
    assert len(again.processes.running()) == 3  # a pipeline with its processes behind it
    # the old consumer, back, lets go of the dead one: only the fresh one is left
    again.registrar.release(old.id)
    assert [r.id for r in again.registrar.served("pipeline")] == [fresh.resource_id]
    again.registrar.release(fresh.id)
    assert again.registrar.resources() == []
    assert again.processes.running() == []


def test_references_of_consumers_gone_with_the_process_are_released_at_restore(
    catalog: Path, lives: list[Managers], caplog: pytest.LogCaptureFixture
) -> None:
    first = Managers(catalog)
    first.registrar.call("pipeline", PipelineRequest("tracking"), client="run/Request_0")
    kept = first.registrar.call("process", SLEEPER, client="keeper")
    first.crash()

    caplog.set_level(logging.INFO)
    again = Managers(catalog, restore=True, transient=lambda client: client.startswith("run/"))
    lives.append(again)
    # the graph run's pipeline, its components and their processes are gone, quietly
    assert [(r.server, r.consumers) for r in again.registrar.resources()] == [
        ("process", ["keeper"])
    ]
    assert again.registrar.info(kept.resource_id).failed  # this one did die while we were down
    alarms = [r.getMessage() for r in caplog.records if ALARM in r.getMessage()]
    assert len(alarms) == 1
    assert str(kept.response.pid) in alarms[0]
    again.registrar.release(kept.id)
    assert entries(catalog) == {}


def test_a_pipeline_whose_segment_failed_for_good_is_not_shared(
    catalog: Path, lives: list[Managers]
) -> None:
    life = Managers(catalog)
    lives.append(life)
    fatal = threading.Event()

    def on_status(update: StatusUpdate) -> None:
        if update.status is Status.FATAL:
            fatal.set()

    request = PipelineRequest("tracking", failover=False)
    first = life.registrar.call("pipeline", request, client="a", on_status=on_status)
    camera = dict(first.response.segments)["camera"]
    pid = life.components.active()[camera].pid
    os.kill(pid, signal.SIGKILL)
    assert fatal.wait(10)
    assert life.registrar.info(first.resource_id).failed
    second = life.registrar.call("pipeline", request, client="b")
    assert second.resource_id != first.resource_id
    assert pid not in life.processes.running()
    assert len(life.processes.running()) == 5  # the fresh three, the first's two survivors


def test_an_interrupted_component_load_releases_its_candidate_at_restore(
    catalog: Path, lives: list[Managers], no_leaked_processes: ProcessLeakCheck
) -> None:
    # What a crash while a component started its candidate leaves: the component begun (with
    # its checkpoint), the candidate's process loaded and held by the component's client.
    first = Managers(catalog)
    held = first.registrar.call("process", SLEEPER, client="r/component:old-1")
    pid = held.response.pid
    first.components.shutdown()
    first.processes.shutdown()  # the process keeps running, as if its guard had not acted yet
    first.registrar.close()
    journal = Journal(catalog, fsync="never")
    journal.open()
    request = {
        "type": "camera",
        "name": "",
        "outputs": [],
        "inputs": [],
        "parameters": [],
        "local_only": False,
        "failover": True,
    }
    journal.append(
        {"op": "begin", "uid": "component:old-1", "server": "component", "request": request}
    )
    journal.append(
        {"op": "progress", "uid": "component:old-1", "data": {"client": "r/component:old-1"}}
    )
    journal.close()
    assert pid in no_leaked_processes.leftovers()

    again = Managers(catalog, restore=True)
    lives.append(again)
    assert again.registrar.resources() == []
    assert pid not in no_leaked_processes.leftovers()


@dataclass
class Recording(ResourceServer[Any, Any]):
    """A server whose resources may depend on the ``"leaf"`` server's; records its restore."""

    registrar: Registrar
    server: str
    calls: list[str] = field(default_factory=list)
    verdict: tuple[Status, str] | None = None

    request_type: ClassVar[type[Any]] = str
    response_type: ClassVar[type[Any]] = str

    @property
    def name(self) -> str:  # type: ignore[override]
        return self.server

    def on_load(self, request: Any, ctx: LoadContext) -> Any:
        if self.server == "top":
            self.registrar.call("leaf", f"leaf-of-{request}")
        return f"{self.server}:{request}"

    def on_unload(self, request: Any, response: Any) -> None:
        self.calls.append(f"unload {request}")

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        deps = [self.registrar.info(r).failed for r in resource.dependencies]
        self.calls.append(f"restore {resource.request} deps-failed={deps}")
        return self.verdict


def test_restore_asks_dependencies_first_and_never_about_what_it_unloaded(
    catalog: Path,
) -> None:
    rr = Registrar("rr", catalog=catalog, fsync="never")
    rr.register(Recording(rr, "top"))
    rr.register(Recording(rr, "leaf"))
    rr.call("top", "kept", client="survivor")
    rr.call("top", "dropped", client="run/Node_0")
    rr.close()

    again = Registrar(
        "rr", catalog=catalog, restore=True, fsync="never", transient=lambda c: "/" in c
    )
    top = Recording(again, "top")
    leaf = Recording(again, "leaf", verdict=(Status.FATAL, "gone"))
    again.register(top)  # registered first, but asked after its dependencies
    again.register(leaf)
    assert leaf.calls == ["unload leaf-of-dropped", "restore leaf-of-kept deps-failed=[]"]
    assert top.calls == ["unload dropped", "restore kept deps-failed=[True]"]
    again.close()


def test_an_instance_releases_a_dead_runs_references_at_restore_and_everything_at_close(
    catalog: Path,
) -> None:
    first = Registrar("robot", catalog=catalog, fsync="never")
    processes = ProcessManager(first)
    first.call("process", SLEEPER, client="a_run/Node_0")
    processes.shutdown(stop_processes=True)
    first.close()
    assert len(entries(catalog)) == 1

    key = secrets.token_bytes(32)
    with Instance(
        "robot", transport=InProcessTransport(f"ghosts-{next(_buses)}"), key=key, catalog=catalog
    ) as instance:
        assert instance.registrar.resources() == []  # released, not reported dead
        instance.registrar.call("process", SLEEPER, client="outside_any_run")
    assert entries(catalog) == {}  # what was still held at close was released


def _crash_tool() -> Any:
    spec = importlib.util.spec_from_file_location(
        "crash_restore", REPO / "tools" / "crash_restore.py"
    )
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["crash_restore"] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_sigkilled_robot_command_restarts_clean_on_its_state_dir(
    tmp_path: Path, no_leaked_processes: ProcessLeakCheck
) -> None:
    tool = _crash_tool()
    rounds = tool.crash_rounds(
        len(tool.MOMENTS),  # one kill at each moment; tools/crash_restore.py runs 30
        tmp_path,
        seed=14,
        variable=no_leaked_processes.variable,
        mark=no_leaked_processes.mark,
    )
    assert [r.moment for r in rounds] == list(tool.MOMENTS)
    failed = [r.line() for r in rounds if not r.ok]
    assert not failed, "\n".join(failed)


def test_serve_restores_without_ghosts_and_leaves_an_empty_catalog_at_sigterm(
    tmp_path: Path,
) -> None:
    # A catalog left by a run killed while one of its graph runs held a process.
    state = tmp_path / "state"
    state.mkdir()
    catalog = state / "registrar.journal"
    first = Registrar("a", catalog=catalog, fsync="never")
    processes = ProcessManager(first)
    first.call("process", SLEEPER, client="a_run/Node_0")
    processes.shutdown(stop_processes=True)
    first.close()
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    bus = f"inproc://ghosts-{os.getpid()}"
    argv = ["-m", "temoto", "serve", "--actor", "a", "--insecure", "--fleet-url", bus]
    serve = subprocess.Popen(
        [sys.executable, *argv, "--state-dir", str(state)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert serve.stdout is not None
        assert serve.stdout.readline() == "ready\n"
        assert entries(catalog) == {}  # the dead run's reference was released at restore
        serve.send_signal(signal.SIGTERM)
        _, err = serve.communicate(timeout=20)
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.communicate()
    assert serve.returncode == 0, err
    assert ALARM not in err
    assert entries(catalog) == {}
