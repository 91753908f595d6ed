"""``python -m temoto.managers.robot --profile hw_profiles/<robot>.yaml``: one robot's instance.

Starts everything the robot runs (docs/design.md §2): its drivers (or their simulators when the
profile says ``sim: true``), a registrar with the Process and Robot Managers, an engine whose
actor is the robot's name with the built-in robot actions, and the fleet services (graph
commands, shared graphs, RIS). With ``--mission GRAPH.json`` it runs that graph at once and
exits with its result (0 iff ``on_true``); without, it serves until SIGINT or SIGTERM.

Every way out leaves the devices in their declared safe state (``docs/safety.md``): the
drivers' shutdown applies it at a mission's end, after a failure or an exception; the first
SIGINT or SIGTERM makes every device safe at once (one line per device on stderr), stops the
mission and closes the instance, exiting 130 or 143 (0 when serving); a second one makes the
devices safe again and exits at once, without waiting for the mission's actions.

With ``sim: true`` the command prints, after its ``ready`` line, one line per simulated device:
the ``link`` that reaches its simulator and how a tool connects (``docs/simulators.md``), so a
ground station, ``can.viewer`` or a serial terminal can watch the robot's own simulators.
``--sim-out udp:HOST:PORT`` (repeatable) makes every simulated vehicle stream to that loopback
address too (QGroundControl listens on 14550); it needs ``sim: true`` and a MAVLink device.

``--record FILE.mcap`` records the runs, the action logs, the robot's telemetry (10 Hz) and the
fleet's envelopes (``docs/recording.md``); the file is finished at every way out but SIGKILL,
the second signal's immediate exit included.

``python -m temoto.managers.robot`` runs :func:`main`. Like every module of :mod:`temoto.cli`,
this one prints.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import secrets
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import IO, TYPE_CHECKING, Any

from temoto.actions.builtin import ROBOT_ACTIONS, VISUALIZATION_ACTIONS
from temoto.cli.common import EXIT_FAILED, EXIT_INVALID, EXIT_OK
from temoto.cli.fleet import (
    add_instance_options,
    fleet_key,
    instance_recording,
    state_files,
)
from temoto.cli.progress import ActionLogHandler, Progress
from temoto.cli.realism_opts import add_realism_options, announce_realism, resolve_seed
from temoto.cli.signals import SignalExit
from temoto.cli.sim_args import parse_udp_address
from temoto.cli.sim_devices import endpoint_for
from temoto.clock import MonotonicClock
from temoto.config import load_profile
from temoto.core.documents import load_graph
from temoto.core.states import NodeState, Result
from temoto.drivers import Driver, live_drivers, make_all_safe
from temoto.errors import ConfigError, DriverError, PluginError, ResourceError, TransportError
from temoto.managers.process import hurry_all
from temoto.managers.visualization.live import close_foxglove, open_foxglove

if TYPE_CHECKING:
    from temoto.transport.identity import Credentials

__all__ = ["main"]

#: The registrar client this command holds the robot as.
CLIENT = "robot-manager"

#: Real seconds the command waits at its end for a signal's per-device lines.
_LINES_WAIT = 2.0

logger = logging.getLogger(__name__)


class _SafeOnSignal:
    """What the robot command adds to :class:`~temoto.cli.signals.SignalExit`.

    The first signal starts a thread that makes every device safe at once (the signals'
    thread goes on to take a second signal); a second one makes them safe again and exits the
    process at once, without waiting for the mission's actions or the instance's close. Both
    run on :class:`SignalExit`'s thread, never in the signal handler (which may interrupt the
    main thread inside a lock: the serving ``stop.wait()`` hung on that).

    Args:
        err: Where the per-device lines go.
        serving: Whether the command serves (a signal is then the normal end: exit 0).
    """

    def __init__(self, err: IO[str], *, serving: bool) -> None:
        self.err = err
        self.serving = serving
        #: Called (in order) before a second signal exits the process, e.g. to finish a
        #: recording; what they raise is ignored.
        self.before_exit: list[Any] = []
        self.signals = SignalExit(first=(self._first,), hurry=(hurry_all, self._again))
        self._threads: list[threading.Thread] = []

    @property
    def exit_code(self) -> int | None:
        """None before a signal; then 0 when serving, else 130 (SIGINT) or 143 (SIGTERM)."""
        code = self.signals.exit_code
        return EXIT_OK if code is not None and self.serving else code

    def _first(self, signum: int) -> None:
        self._spawn(signum, False)

    def _again(self) -> None:
        self._spawn(self.signals.signum or signal.SIGINT, True)

    def _spawn(self, signum: int, urgent: bool) -> None:
        # the drivers as they are at the signal (the handler runs before the main thread goes
        # on to close the robot): a device shut down meanwhile still gets its line
        drivers = sorted(live_drivers(), key=lambda d: d.name)
        thread = threading.Thread(
            target=self._make_safe,
            args=(signum, urgent, drivers),
            name="temoto-safe",
            daemon=True,
        )
        self._threads.append(thread)
        thread.start()

    def join(self, timeout: float = _LINES_WAIT) -> None:
        """Wait (at most ``timeout`` real seconds) until every signal's lines are written."""
        deadline = time.monotonic() + timeout
        for thread in list(self._threads):
            thread.join(max(deadline - time.monotonic(), 0.0))

    def _make_safe(self, signum: int, urgent: bool, drivers: list[Driver]) -> None:
        reason = signal.Signals(signum).name
        lines = [f"{d.name}: {what}" for d, what in make_all_safe(reason, drivers=drivers)]
        self.err.writelines(f"  {line}\n" for line in lines)
        self.err.flush()
        if urgent:
            for callback in self.before_exit:
                with contextlib.suppress(Exception):
                    callback()
            with contextlib.suppress(Exception):
                sys.stdout.flush()
            os._exit(self.exit_code or EXIT_OK)


#: The node changes the robot command prints.
_SHOWN = frozenset({NodeState.RUNNING, NodeState.FINISHED, NodeState.ERROR})


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m temoto.managers.robot",
        description="Run one robot: its drivers (or simulators), managers, engine and fleet"
        " link, from a hardware profile.",
    )
    p.add_argument("--profile", required=True, metavar="FILE", help="hardware profile (YAML)")
    p.add_argument("--mission", metavar="GRAPH.json", help="run this graph, then exit")
    p.add_argument("--actions", action="append", default=[], metavar="DIR", help="more actions")
    p.add_argument("--graphs", action="append", default=[], metavar="DIR", help="graph folder")
    p.add_argument("--timeout", type=float, metavar="SECONDS", help="stop the mission after this")
    p.add_argument(
        "--sim-out",
        type=parse_udp_address,
        action="append",
        default=[],
        metavar="udp:HOST:PORT",
        help="with sim: true, also stream the simulated vehicle to this loopback address, for a"
        " ground station (repeatable; QGroundControl listens on udp:127.0.0.1:14550)",
    )
    add_realism_options(p)
    p.add_argument(
        "--local",
        action="store_true",
        help="no fleet: nothing is sent to or taken from the network (a mission on one robot)",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    add_instance_options(p, "the fleet this robot joins (unless --local)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the robot.

    Args:
        argv: Arguments without the program name.

    Returns:
        The exit status: 0 (served until stopped, or the mission ended ``on_true``), 1 (the
        mission ended otherwise, or a device failed), 2 (invalid input).
    """
    args = _parser().parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    interrupts = _SafeOnSignal(sys.stderr, serving=args.mission is None)
    with interrupts.signals:
        try:
            code = _run(args, interrupts)
        except (ConfigError, PluginError) as err:
            sys.stderr.write(f"temoto-robot: error: {err}\n")
            code = EXIT_INVALID
        except (DriverError, ResourceError, TransportError) as err:
            inner = load_error(err)
            sys.stderr.write(f"temoto-robot: error: {inner}\n")
            code = EXIT_INVALID if isinstance(inner, ConfigError | PluginError) else EXIT_FAILED
    interrupts.join()  # the per-device lines of a signal are out before the exit
    signalled = interrupts.exit_code
    return code if signalled is None else signalled


def _run(args: argparse.Namespace, interrupts: _SafeOnSignal) -> int:
    from temoto.transport import InProcessTransport, Transport, open_transport

    t0 = time.monotonic()
    clock = MonotonicClock()
    profile = load_profile(args.profile, clock=clock)
    _check_sim_out(args.sim_out, profile)
    resolve_seed(args)
    if profile.sim:
        announce_realism(args, sys.stderr)
    mission = load_graph(args.mission) if args.mission else None
    state = state_files(args)
    transport: Transport
    if args.local:
        transport = InProcessTransport(f"local-{profile.robot}-{secrets.token_hex(4)}")
        key: bytes | Credentials | None = secrets.token_bytes(32)  # nobody else is on this bus
    else:
        key = fleet_key(args, f"robot '{profile.robot}'")
        transport = open_transport(args.fleet_url)
    with instance_recording(args, "robot", profile.robot, transport) as recorder:
        if recorder is not None:
            interrupts.before_exit.append(recorder.close)  # a second signal: finished, then exit
        return _run_instance(
            args, interrupts, (t0, clock), (profile, mission, state), transport, key, recorder
        )


def _run_instance(
    args: argparse.Namespace,
    interrupts: _SafeOnSignal,
    started: tuple[float, MonotonicClock],
    inputs: tuple[Any, Any, Any],
    transport: Any,
    key: bytes | Credentials | None,
    recorder: Any,
) -> int:
    from temoto.instance import Instance
    from temoto.managers.robot.client import RobotManagerClient
    from temoto.managers.robot.manager import RobotManager

    t0, clock = started
    profile, mission, state = inputs
    out = sys.stdout
    with Instance(
        profile.robot,
        transport=transport,
        key=key,
        fleet=args.fleet,
        insecure=key is None,
        actions=[ROBOT_ACTIONS, VISUALIZATION_ACTIONS, *args.actions],  # ShowDisplay too
        graphs=args.graphs,
        catalog=state.catalog,
        world=state.world,
        reliability_file=state.reliability,
        silence_s=args.fleet_silence,
        resend_s=args.fleet_resend,
        live_view_port=args.live_view,
        component_files=args.components,
    ) as instance:
        manager = RobotManager(
            instance.registrar,
            profile,
            clock=clock,
            sim_gcs=args.sim_out,
            realism=args.realism,
            seed=args.seed,
        )
        instance.add_manager(manager)
        # load the robot now: a device that does not answer fails here, not mid-mission
        # references this command held before a restart died with its process: let them go
        # (a restored robot is FATAL: its drivers ran there), then load the robot afresh
        stale = instance.registrar.release_client(CLIENT)
        if stale:
            logger.info("released %d references of the previous run", stale)
        robot = RobotManagerClient(instance.registrar).request(client=CLIENT)
        live = None
        try:
            live = open_foxglove(args, instance, robot)  # --foxglove: docs/visualization.md
            if recorder is not None:
                instance.engine.add_instrument(recorder)
                recorder.sample(robot)
                out.write(f"recording to {recorder.path}\n")
            where = "simulated" if profile.sim else "hardware"
            out.write(
                f"robot '{profile.robot}' ready in {time.monotonic() - t0:.2f} s ({where};"
                f" {', '.join(robot.features) or 'no features'};"
                f" fleet {'off' if args.local else args.fleet_url})\n"
            )
            if instance.live_view is not None:
                out.write(f"live view: {instance.live_view.url}\n")
            for sim in manager.simulated():
                line = endpoint_for(sim.name, sim.driver, sim.simulator, sim.settings, args.sim_out)
                out.write(f"  simulator {line.summary()}\n")
            out.flush()
            if mission is None:
                sys.stderr.write(f"robot '{profile.robot}' serving; Ctrl-C stops it\n")
                interrupts.signals.stop.wait()
                return EXIT_OK
            signals = interrupts.signals
            if signals.stop.is_set():
                return EXIT_FAILED  # main() returns the signal's exit code
            progress = Progress(out, clock, t0, states=_SHOWN)
            instance.engine.add_instrument(progress)
            action_logs = ActionLogHandler(progress)  # the actions' progress lines, in order
            action_logs.install()
            try:
                outcome = _mission(instance.engine, mission, args.timeout, signals.stop)
            finally:
                progress.finish()
                action_logs.remove()
            if signals.stop.is_set():
                name = signal.Signals(signals.signum or signal.SIGINT).name
                out.write(f"{mission.name}: interrupted ({name})\n")
                # the stop waited for the actions already: do not wait for them a second time
                instance.engine.shutdown(timeout=_AFTER_STOP)
                return EXIT_FAILED
            result = outcome.result.value if outcome.result else "none"
            out.write(f"{mission.name}: {result} in {time.monotonic() - t0:.2f} s\n")
            for error in outcome.errors:
                sys.stderr.write(f"  error: {error}\n")
            return EXIT_OK if outcome.result is Result.TRUE else EXIT_FAILED
        finally:
            if recorder is not None:
                recorder.stop_sampling()  # before the robot goes
            close_foxglove(live)
            # at every way out but a second signal: the catalog keeps nothing of this run
            _release(instance.registrar, robot.resource.id)


def _check_sim_out(sim_out: Sequence[tuple[str, int]], profile: Any) -> None:
    """``--sim-out`` needs simulators, and a vehicle among them."""
    if not sim_out:
        return
    if not profile.sim:
        raise ConfigError(f"--sim-out: {profile.source} has sim: false (no simulated vehicle)")
    if not any(spec.driver == "mavlink" for spec in profile.devices.values()):
        raise ConfigError(f"--sim-out: {profile.source} has no MAVLink vehicle to stream")


def _release(registrar: Any, reference: str) -> None:
    """Release this command's reference to the robot (the instance closes after it)."""
    try:
        registrar.release(reference)
    except ResourceError as err:
        logger.debug("releasing the robot: %s", err)


def _mission(engine: Any, mission: Any, timeout: float | None, stop: threading.Event) -> Any:
    """Run the mission until it ends, ``timeout`` passes or a signal comes (then stop it)."""
    name = engine.start(mission)
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        try:
            engine.wait(name, _POLL)
            break
        except TimeoutError:
            pass
        if stop.is_set():
            engine.stop(name)  # a second signal exits without waiting for this
            break
        if deadline is not None and time.monotonic() >= deadline:
            logger.warning("mission %s did not end within %s s; stopping it", name, timeout)
            engine.stop(name)
            break
    return engine.outcome(name)


def load_error(err: BaseException) -> BaseException:
    """What a failed load says, for people: the device's own error, no internal requests.

    A robot that cannot be loaded fails inside the registrar, which wraps the driver's error in
    ``server 'robot' could not load {...}: ...``; the innermost error that is not such a
    wrapper names the robot, the device and what went wrong (the manager's
    ``robot sim_arm, device arm: could not start: servo 1 (shoulder_pan) does not answer PING
    on /dev/ttyUSB0: ...``).

    Args:
        err: The error the command caught.

    Returns:
        The innermost error (``err`` itself when it wraps nothing).
    """
    from temoto.errors import ResourceLoadError

    inner: BaseException = err
    seen: set[int] = set()
    while isinstance(inner, ResourceLoadError) and inner.__cause__ is not None:
        if id(inner) in seen:
            break
        seen.add(id(inner))
        inner = inner.__cause__
    return inner


#: Real seconds between the mission's checks for a signal.
_POLL = 0.05
#: Real seconds the engine's shutdown waits for actions after an interrupted mission's stop.
_AFTER_STOP = 0.5


if __name__ == "__main__":
    sys.exit(main())
