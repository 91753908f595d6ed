"""Crash test of the restore: SIGKILL the robot command, restart it on the same state dir.

``python tools/crash_restore.py [--kills 30] [--seed 0] [--profile FILE] [--state-dir DIR]``

Each round starts ``python -m temoto.managers.robot --profile FILE --local --state-dir DIR
--components examples/components/components.yaml --mission M``, where the mission M holds a
component pipeline (camera -> detector -> tracker: three processes) while it reads its output,
after moving the robot. The command is SIGKILLed at one of three moments, in turn: during
start-up (a random delay after the spawn, on the catalog of a run killed while it held its
pipeline, so before, while or after the restore), while the graph loads the pipeline (right after
``RequestPipeline_0 RUNNING``) and while it holds it (after ``RequestPipeline_0 FINISHED``).
Then the command is restarted on the same state dir with the same mission, and the round checks:

* the mission ends ``on_true`` (exit 0);
* while the restarted run holds its pipeline, the processes that carry this script's marker
  (everything the commands started) are exactly the command and its pipeline's processes, and
  the registrar's journal holds only that run's resources (no entry restored from the killed
  run: a restored entry keeps the boot id of the run that loaded it);
* its log has no "died while the manager was down" (no false alarm: the killed run's
  processes are stopped by the restore itself, never reported);
* after it exits, no marked process is left and the journal holds no resource at all.

Prints one line per round and a summary; exits 0 iff every check held. The test suite runs a
few rounds (``tests/managers/test_restore_ghosts.py``); 30 rounds (40 SIGKILLs) take about 50 s.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

if TYPE_CHECKING:
    from temoto.core.registrar.records import ReplayedEntry

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "hw_profiles" / "sim_arm.yaml"
COMPONENTS = ROOT / "examples" / "components" / "components.yaml"
#: Where the command is SIGKILLed, in turn.
MOMENTS = ("start-up", "loading", "holding")
#: The pipeline's processes (the ``tracking`` template has three segments).
PIPELINE_PROCESSES = 3
#: The false alarm a restore would raise for processes it had stopped itself (never expected).
FALSE_ALARM = "died while the manager was down"

MISSION: dict[str, Any] = {
    "graph_name": "move_then_track",
    "graph_description": "Moves the arm, then holds the tracking pipeline while reading from it.",
    "graph_entry": [{"name": "MoveJoints", "instance_id": 0}],
    "graph_exit": [{"name": "WaitForComponentData", "instance_id": 0}],
    "actions": [
        {
            "name": "MoveJoints",
            "instance_id": 0,
            "type": "sync",
            "input_parameters": {"pose": {"pvf_type": "string", "pvf_value": "home"}},
            "children": [{"name": "RequestPipeline", "instance_id": 0}],
        },
        {
            "name": "RequestPipeline",
            "instance_id": 0,
            "type": "sync",
            "parents": [{"name": "MoveJoints", "instance_id": 0}],
            "input_parameters": {"template": {"pvf_type": "string", "pvf_value": "tracking"}},
            "children": [{"name": "WaitForComponentData", "instance_id": 0}],
        },
        {
            # the graph's result: on_false if the pipeline's output does not come (a pipeline
            # shared with nothing behind it)
            "name": "WaitForComponentData",
            "instance_id": 0,
            "type": "sync",
            "parents": [{"name": "RequestPipeline", "instance_id": 0}],
            "input_parameters": {
                "count": {"pvf_type": "number", "pvf_value": 100},
                "timeout": {"pvf_type": "number", "pvf_value": 5},
            },
        },
    ],
}


@dataclass
class Round:
    """What one kill and restart showed.

    Attributes:
        index: The round's number (from 0).
        moment: When the kill was aimed at (:data:`MOMENTS`).
        kills: How many SIGKILLs the round made (a start-up round kills a run holding its
            pipeline first, so that the killed start-up has a catalog to restore).
        seen: The last line the killed command had printed ("" for none).
        inherited: Resources in the journal the restart started from.
        result: The restarted mission's last line.
        code: The restarted command's exit code.
        seconds: How long the restarted command ran.
        extra: Marked processes, while the restarted run held its pipeline, that were neither
            the command nor its pipeline's processes.
        pipeline: How many processes its pipeline had then.
        ghosts: Journal entries then that the restarted run did not load (restored ones).
        alarms: Lines of its log with :data:`FALSE_ALARM`.
        left: Marked processes still running after it exited.
        journal_left: Resources in the journal after it exited.
    """

    index: int
    moment: str
    kills: int = 0
    seen: str = ""
    inherited: int = -1
    result: str = ""
    code: int | None = None
    seconds: float = 0.0
    extra: list[int] = field(default_factory=list)
    pipeline: int = -1
    ghosts: list[str] = field(default_factory=list)
    alarms: list[str] = field(default_factory=list)
    left: list[int] = field(default_factory=list)
    journal_left: int = -1

    @property
    def ok(self) -> bool:
        """Whether every check held."""
        return (
            self.code == 0
            and ": on_true in " in self.result
            and not self.extra
            and self.pipeline == PIPELINE_PROCESSES
            and not self.ghosts
            and not self.alarms
            and not self.left
            and self.journal_left == 0
        )

    def line(self) -> str:
        """One line for people."""
        verdict = "ok" if self.ok else "FAILED"
        return (
            f"round {self.index:2d} kill {self.moment:8s} (after {self.seen or 'nothing'!r}):"
            f" {self.inherited} resources in the journal; restart {self.result or '?'}"
            f" exit {self.code} in {self.seconds:.2f} s;"
            f" pipeline {self.pipeline} processes, extra {self.extra}, ghosts {self.ghosts},"
            f" alarms {len(self.alarms)}, left {self.left}, journal {self.journal_left}: {verdict}"
        )


class _Command:
    """The robot command, its stdout read line by line on a thread."""

    def __init__(self, argv: list[str], env: dict[str, str], log: IO[str]) -> None:
        self.proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=log, text=True, env=env, cwd=ROOT
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.last = ""
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_for(self, text: str, timeout: float) -> bool:
        """Read lines until one contains ``text`` (True) or the output ends or time is up."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return False
            if line is None:
                return False
            self.last = line
            if text in line:
                return True

    def drain(self) -> None:
        """Take the lines read so far (``last`` is then the newest)."""
        while True:
            try:
                line = self.lines.get_nowait()
            except queue.Empty:
                return
            if line is None:
                return
            self.last = line

    def finish(self, timeout: float) -> int | None:
        """Wait for the exit; read the rest of the output."""
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            code = None
        self._reader.join(5)
        self.drain()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return code


def marked_processes(needle: bytes) -> list[int]:
    """Live processes (not zombies) whose environment holds ``needle`` (``NAME=value``)."""
    found = []
    for name in os.listdir("/proc"):
        if not name.isdigit() or int(name) == os.getpid():
            continue
        try:
            with open(f"/proc/{name}/environ", "rb") as f:
                env = f.read().split(b"\0")
            with open(f"/proc/{name}/stat", "rb") as f:
                state = f.read().rpartition(b")")[2].split()[0]
        except OSError:
            continue
        if needle in env and state not in (b"Z", b"X"):
            found.append(int(name))
    return sorted(found)


def journal_entries(catalog: Path) -> dict[str, ReplayedEntry]:
    """The resources a registrar journal describes (read from a copy: the owner holds a lock)."""
    from temoto.core.registrar.journal import Journal
    from temoto.core.registrar.records import replay

    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "copy.journal"
        shutil.copyfile(catalog, copy)
        journal = Journal(copy, fsync="never")
        try:
            records = journal.open()
        finally:
            journal.close()
    return replay(records, str(catalog)).entries


def _boot(uid: str) -> str:
    """The boot id in a resource id (``server:boot-n``)."""
    return uid.partition(":")[2].rpartition("-")[0]


def crash_rounds(
    kills: int,
    workdir: Path,
    *,
    seed: int = 0,
    profile: Path = PROFILE,
    variable: str = "TEMOTO_TEST_PROCESS_MARK",
    mark: str = "",
    report: Callable[[Round], None] | None = None,
) -> list[Round]:
    """Kill and restart the robot command ``kills`` times on one state dir.

    Args:
        kills: How many rounds.
        workdir: Where the state dir, the mission and the logs go.
        seed: Seed of the kill delays.
        profile: The hardware profile.
        variable: The environment variable that marks every process the commands start.
        mark: Its value (default: a fresh one).
        report: Called with each round when it is done.

    Returns:
        The rounds.
    """
    rng = random.Random(seed)
    mark = mark or f"crash-restore-{os.getpid()}-{seed}"
    needle = f"{variable}={mark}".encode()
    env = {**os.environ, variable: mark}
    env.pop("TEMOTO_FLEET_KEY", None)
    state = workdir / "state"
    mission = workdir / "mission.graph.json"
    mission.write_text(json.dumps(MISSION))
    argv = [
        sys.executable,
        "-m",
        "temoto.managers.robot",
        "--profile",
        str(profile),
        "--local",
        "--state-dir",
        str(state),
        "--components",
        str(COMPONENTS),
        "--mission",
        str(mission),
    ]
    rounds = []
    for index in range(kills):
        moment = MOMENTS[index % len(MOMENTS)]
        outcome = Round(index, moment)
        with open(workdir / f"killed-{index}.log", "w") as log:
            if moment == "start-up":
                # first leave a run's state behind, so that this start-up has a catalog to
                # restore and is killed before, while or after it restores it
                primer = _Command(argv, env, log)
                primer.wait_for("RequestPipeline_0 FINISHED", 20)
                primer.proc.send_signal(signal.SIGKILL)
                primer.finish(10)
                outcome.kills += 1
            victim = _Command(argv, env, log)
            if moment == "start-up":
                time.sleep(rng.uniform(0.1, 0.5))
            elif moment == "loading":
                victim.wait_for("RequestPipeline_0 RUNNING", 20)
                time.sleep(rng.uniform(0.0, 0.03))
            else:
                victim.wait_for("RequestPipeline_0 FINISHED", 20)
                time.sleep(rng.uniform(0.0, 0.15))
            victim.proc.send_signal(signal.SIGKILL)
            victim.finish(10)
            outcome.kills += 1
            outcome.seen = victim.last
        outcome.inherited = len(journal_entries(state / "registrar.journal"))
        log_path = workdir / f"restart-{index}.log"
        with open(log_path, "w") as log:
            t0 = time.monotonic()
            restart = _Command(argv, env, log)
            if restart.wait_for("WaitForComponentData_0 RUNNING", 30):
                others = set(marked_processes(needle)) - {restart.proc.pid}
                entries = journal_entries(state / "registrar.journal")
                current = {_boot(uid) for uid in entries if uid.startswith("pipeline:")}
                outcome.ghosts = sorted(uid for uid in entries if _boot(uid) not in current)
                pids = {
                    int(e.response["pid"])
                    for uid, e in entries.items()
                    if uid.startswith("process:") and e.loaded and _boot(uid) in current
                }
                outcome.pipeline = len(others & pids)
                outcome.extra = sorted(others - pids)
            outcome.code = restart.finish(30)
            outcome.seconds = time.monotonic() - t0
            outcome.result = restart.last
        outcome.alarms = [ln for ln in log_path.read_text().splitlines() if FALSE_ALARM in ln]
        deadline = time.monotonic() + 3
        while True:
            outcome.left = marked_processes(needle)
            if not outcome.left or time.monotonic() > deadline:
                break
            time.sleep(0.02)
        outcome.journal_left = len(journal_entries(state / "registrar.journal"))
        rounds.append(outcome)
        if report is not None:
            report(outcome)
    for pid in marked_processes(needle):  # whatever a failed round left behind
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    return rounds


def main(argv: list[str] | None = None) -> int:
    """Run the rounds and print them.

    Args:
        argv: Arguments without the program name.

    Returns:
        0 iff every round's checks held.
    """
    p = argparse.ArgumentParser(prog="tools/crash_restore.py", description=__doc__.split("\n")[0])
    p.add_argument("--kills", type=int, default=30, help="rounds (default 30)")
    p.add_argument("--seed", type=int, default=0, help="seed of the kill delays (default 0)")
    p.add_argument("--profile", type=Path, default=PROFILE, help="hardware profile")
    p.add_argument("--state-dir", type=Path, help="work here (default: a temporary directory)")
    args = p.parse_args(argv)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="temoto-crash-") as tmp:
        workdir = args.state_dir or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        rounds = crash_rounds(
            args.kills,
            workdir,
            seed=args.seed,
            profile=args.profile,
            report=lambda r: print(r.line(), flush=True),
        )
    failed = [r.index for r in rounds if not r.ok]
    seen = {m: sum(1 for r in rounds if r.moment == m) for m in MOMENTS}
    inherited = max((r.inherited for r in rounds), default=0)
    print(
        f"{sum(r.kills for r in rounds)} SIGKILLs in {len(rounds)} rounds"
        f" ({', '.join(f'{n} {m}' for m, n in seen.items())}), at most {inherited} resources"
        f" left in the journal by a kill,"
        f" {len(rounds) - len(failed)} restarts clean, failed rounds {failed}"
        f" in {time.monotonic() - t0:.1f} s"
    )
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
