"""The ROS 2 bridge process: ``python -m temoto.ros2.bridge --socket PATH``.

The only place rclpy is imported. It listens on a Unix socket; every connection gets a ready
frame, then requests (:mod:`temoto.ros2.protocol`), each served in a thread of its own so that
a ``cancel`` can reach a running goal. One node (``temoto_bridge_<pid>``) holds the publishers,
clients and action clients, cached per name and type; one single-threaded executor spins it in
the thread ``temoto-ros2-executor`` (the multi-threaded one had second-long latency tails).

The rclpy pitfalls handled here:

* A wrong ``RMW_IMPLEMENTATION`` makes ``import rclpy`` exit with code 102 (no exception): the
  variable is checked first (the RMW library must load) and a bad one is answered with an error
  frame naming it; if rclpy still exits with 102 the TeMoto side turns that into one line.
* rclpy's own signal handlers are not installed (``SignalHandlerOptions.NO``): SIGTERM and
  SIGINT set a stop event; the executor and connection threads are joined, the node destroyed
  and the context shut down, so Fast DDS removes its ``/dev/shm`` segments and the process exits
  0 (a never-joined executor thread would abort it at exit, 134).
* The bridge exits when its parent (the TeMoto process that started it) is gone.
* ``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE`` and ``RMW_IMPLEMENTATION`` are the
  user's: the bridge inherits them and changes none.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import logging
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Final

from temoto.ros2 import INSTALL_HINT
from temoto.ros2.convert import fill, import_type, to_json
from temoto.ros2.protocol import FrameError, recv_frame, send_frame

__all__ = ["main"]

logger = logging.getLogger(__name__)

#: The RMW that the PyPI wheels are built for (and rclpy's default).
DEFAULT_RMW: Final = "rmw_fastrtps_cpp"
#: Exit status when the bridge refuses to start (bad environment).
EXIT_BAD_ENV: Final = 2
#: Seconds between checks of the stop event and of the parent.
TICK_S: Final = 0.2
#: Seconds to wait for threads at shutdown.
JOIN_S: Final = 5.0


class OpError(Exception):
    """A request failed; its message (one line) is the reply's ``error``."""


def check_rmw(environ: Mapping[str, str]) -> str | None:
    """Whether the RMW named by ``RMW_IMPLEMENTATION`` can be loaded.

    Args:
        environ: The environment.

    Returns:
        None if it can (or the variable is unset), else the one-line error.
    """
    rmw = environ.get("RMW_IMPLEMENTATION", "")
    if not rmw:
        return None
    try:
        ctypes.CDLL(f"lib{rmw}.so")
    except OSError:
        return (
            f"RMW_IMPLEMENTATION={rmw}: lib{rmw}.so cannot be loaded; unset it to use "
            f"{DEFAULT_RMW}, or install that RMW"
        )
    return None


def _wait_future(future: Any, timeout: float | None, cancel: threading.Event | None = None) -> bool:
    """Wait for an rclpy future; False on timeout or when ``cancel`` is set first."""
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    deadline = None if timeout is None else time.monotonic() + timeout
    while not done.is_set():
        if cancel is not None and cancel.is_set():
            return False
        left = TICK_S if deadline is None else min(TICK_S, deadline - time.monotonic())
        if left <= 0:
            return False
        done.wait(left)
    return True


class Bridge:
    """The node, its executor thread, and the entities it serves requests with.

    Args:
        rclpy: The imported rclpy module.
        stop: Set to end the bridge.
    """

    def __init__(self, rclpy: Any, stop: threading.Event) -> None:
        from rclpy.executors import SingleThreadedExecutor

        self._rclpy = rclpy
        self.stop = stop
        self.node = rclpy.create_node(f"temoto_bridge_{os.getpid()}")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._lock = threading.Lock()
        self._publishers: dict[tuple[str, str], Any] = {}
        self._clients: dict[tuple[str, str], Any] = {}
        self._action_clients: dict[tuple[str, str], Any] = {}
        self._spinner = threading.Thread(target=self._spin, name="temoto-ros2-executor")
        self._spinner.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while not self.stop.is_set():
                self.executor.spin_once(timeout_sec=TICK_S)
        except ExternalShutdownException:
            pass
        except Exception:
            logger.exception("the executor failed")
            self.stop.set()

    def close(self) -> None:
        """Join the executor thread, destroy the node, shut rclpy down (removes the segments)."""
        self.stop.set()
        self._spinner.join(JOIN_S)
        with contextlib.suppress(Exception):
            self.executor.shutdown(timeout_sec=1.0)
        with contextlib.suppress(Exception):
            self.node.destroy_node()
        self._rclpy.try_shutdown()

    # ------------------------------------------------------------------------------ operations

    def publish(self, req: dict[str, Any], _event: Callable[[dict[str, Any]], None]) -> Any:
        """Publish one message, after waiting up to ``timeout`` for a subscriber."""
        topic, type_name = str(req["topic"]), str(req["type"])
        cls = import_type(type_name, "msg")
        msg = fill(cls(), dict(req.get("message") or {}))
        with self._lock:
            pub = self._publishers.get((topic, type_name))
            if pub is None:
                pub = self.node.create_publisher(cls, topic, 10)
                self._publishers[(topic, type_name)] = pub
        deadline = time.monotonic() + float(req.get("timeout") or 0)
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            if self.stop.wait(0.02):
                raise OpError("the bridge is stopping")
        pub.publish(msg)
        return {"subscribers": pub.get_subscription_count()}

    def wait_message(self, req: dict[str, Any], _event: Callable[[dict[str, Any]], None]) -> Any:
        """The next message on a topic, within ``timeout`` seconds."""
        topic, type_name = str(req["topic"]), str(req["type"])
        timeout = float(req.get("timeout") or 0) or None
        cls = import_type(type_name, "msg")
        got: list[Any] = []
        arrived = threading.Event()

        def on_message(msg: Any) -> None:
            if not got:
                got.append(msg)
                arrived.set()

        with self._lock:
            sub = self.node.create_subscription(cls, topic, on_message, 10)
        try:
            deadline = None if timeout is None else time.monotonic() + timeout
            cancel: threading.Event = req["_cancel"]
            while not arrived.wait(0.02):
                if self.stop.is_set() or cancel.is_set():
                    raise OpError(f"waiting for a message on {topic} was cancelled")
                if deadline is not None and time.monotonic() >= deadline:
                    raise OpError(f"no {type_name} message on {topic} within {timeout:g} s")
        finally:
            with self._lock:
                self.node.destroy_subscription(sub)
        return {"message": to_json(got[0])}

    def subscribe(self, req: dict[str, Any], event: Callable[[dict[str, Any]], None]) -> Any:
        """Every message on a topic as a ``message`` event, until the request is cancelled.

        The messages are handed over in the request's own thread (the executor's callback only
        keeps the newest ``depth`` of them), so a slow connection never holds the executor up.
        """
        topic, type_name = str(req["topic"]), str(req["type"])
        depth = max(1, int(req.get("depth") or 10))
        cls = import_type(type_name, "msg")
        queue: list[Any] = []
        arrived = threading.Condition()

        def on_message(msg: Any) -> None:
            with arrived:
                queue.append(msg)
                del queue[:-depth]
                arrived.notify()

        with self._lock:
            sub = self.node.create_subscription(cls, topic, on_message, depth)
        cancel: threading.Event = req["_cancel"]
        count = 0
        try:
            while not (self.stop.is_set() or cancel.is_set()):
                with arrived:
                    arrived.wait_for(lambda: bool(queue), TICK_S)
                    got, queue[:] = list(queue), []
                for msg in got:
                    event({"event": "message", "message": to_json(msg)})
                count += len(got)
        finally:
            with self._lock:
                self.node.destroy_subscription(sub)
        return {"messages": count}

    def call_service(self, req: dict[str, Any], _event: Callable[[dict[str, Any]], None]) -> Any:
        """Call a service; its response, within ``timeout`` seconds (discovery included)."""
        service, type_name = str(req["service"]), str(req["type"])
        timeout = float(req.get("timeout") or 0) or None
        cls = import_type(type_name, "srv")
        request = fill(cls.Request(), dict(req.get("request") or {}))
        with self._lock:
            client = self._clients.get((service, type_name))
            if client is None:
                client = self.node.create_client(cls, service)
                self._clients[(service, type_name)] = client
        start = time.monotonic()
        cancel: threading.Event = req["_cancel"]
        if not self._wait_ready(client.service_is_ready, timeout, cancel, service):
            raise OpError(f"no {type_name} service {service} within {timeout:g} s")
        left = None if timeout is None else max(0.0, timeout - (time.monotonic() - start))
        future = client.call_async(request)
        if not _wait_future(future, left, cancel):
            client.remove_pending_request(future)
            if cancel.is_set():
                raise OpError(f"the call to {service} was cancelled")
            raise OpError(f"the service {service} did not answer within {timeout:g} s")
        return {"response": to_json(future.result())}

    def _wait_ready(
        self, ready: Callable[[], bool], timeout: float | None, cancel: threading.Event, what: str
    ) -> bool:
        """Wait for discovery (a service or action server); False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not ready():
            if deadline is not None and time.monotonic() >= deadline:
                return False
            if cancel.wait(0.02) or self.stop.is_set():
                raise OpError(f"waiting for {what} was cancelled")
        return True

    def send_goal(self, req: dict[str, Any], event: Callable[[dict[str, Any]], None]) -> Any:
        """Send a goal; feedback as events; its result. Cancelled when the request is."""
        from rclpy.action import ActionClient

        action, type_name = str(req["action"]), str(req["type"])
        timeout = float(req.get("timeout") or 0) or None
        cancel: threading.Event = req["_cancel"]
        cls = import_type(type_name, "action")
        goal = fill(cls.Goal(), dict(req.get("goal") or {}))
        with self._lock:
            client = self._action_clients.get((action, type_name))
            if client is None:
                client = ActionClient(self.node, cls, action)
                self._action_clients[(action, type_name)] = client
        start = time.monotonic()
        if not self._wait_ready(client.server_is_ready, timeout, cancel, action):
            raise OpError(f"no {type_name} action server {action} within {timeout:g} s")

        def left() -> float | None:
            return None if timeout is None else max(0.0, timeout - (time.monotonic() - start))

        sent = client.send_goal_async(
            goal,
            feedback_callback=lambda fb: event(
                {"event": "feedback", "feedback": to_json(fb.feedback)}
            ),
        )
        if not _wait_future(sent, left(), self.stop):
            raise OpError(
                f"the action server {action} did not answer the goal within {timeout:g} s"
            )
        handle = sent.result()
        if not handle.accepted:
            raise OpError(f"the action server {action} rejected the goal")
        result = handle.get_result_async()
        if not _wait_future(result, left(), cancel):
            why = "cancelled" if cancel.is_set() else f"timed out after {timeout:g} s"
            cancelled = handle.cancel_goal_async()
            if _wait_future(cancelled, JOIN_S, self.stop):
                _wait_future(result, JOIN_S, self.stop)
            raise OpError(f"the goal on {action} was {why} (cancel sent and confirmed)")
        from action_msgs.msg import GoalStatus

        out = result.result()
        names = {
            v: k[len("STATUS_") :] for k, v in vars(GoalStatus).items() if k.startswith("STATUS_")
        }
        return {"status": names.get(out.status, str(out.status)), "result": to_json(out.result)}


class Connection:
    """One client: reads requests, serves each in a thread, writes replies.

    Args:
        bridge: The bridge.
        sock: The accepted socket.
        number: Its number (thread names).
    """

    def __init__(self, bridge: Bridge, sock: socket.socket, number: int) -> None:
        self._bridge = bridge
        self._sock = sock
        self._write = threading.Lock()
        self._ops: dict[int, tuple[threading.Thread, threading.Event]] = {}
        self.thread = threading.Thread(target=self._run, name=f"temoto-ros2-conn-{number}")

    def _send(self, obj: dict[str, Any]) -> None:
        with self._write, contextlib.suppress(OSError):
            send_frame(self._sock, obj)

    def close(self) -> None:
        """End the connection (its thread then joins its operations)."""
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)

    def _run(self) -> None:
        self._send({"ready": True, "pid": os.getpid(), "rmw": _rmw(), "domain_id": _domain()})
        try:
            while True:
                try:
                    req = recv_frame(self._sock)
                except (FrameError, OSError):
                    break
                self._dispatch(req)
        finally:
            for _thread, cancel in list(self._ops.values()):
                cancel.set()
            for thread, _cancel in list(self._ops.values()):
                thread.join(JOIN_S * 2)
            self._sock.close()

    def _dispatch(self, req: dict[str, Any]) -> None:
        rid = req.get("id")
        op = req.get("op")
        if op == "cancel":
            target = self._ops.get(int(req.get("target", -1)))
            if target is not None:
                target[1].set()
            self._send({"id": rid, "ok": True, "result": {}})
            return
        handler = {
            "ping": lambda _r, _e: {},
            "publish": self._bridge.publish,
            "wait_message": self._bridge.wait_message,
            "call_service": self._bridge.call_service,
            "send_goal": self._bridge.send_goal,
            "subscribe": self._bridge.subscribe,
        }.get(str(op))
        if handler is None or not isinstance(rid, int):
            self._send({"id": rid, "ok": False, "error": f"unknown operation {op!r}"})
            return
        cancel = threading.Event()
        req["_cancel"] = cancel
        for done in [k for k, (t, _c) in self._ops.items() if not t.is_alive()]:
            self._ops.pop(done)[0].join()
        thread = threading.Thread(
            target=self._serve, args=(handler, req), name=f"{self.thread.name}-op-{rid}"
        )
        self._ops[rid] = (thread, cancel)
        thread.start()

    def _serve(self, handler: Callable[..., Any], req: dict[str, Any]) -> None:
        rid = req["id"]
        try:
            result = handler(req, lambda ev: self._send({"id": rid, **ev}))
        except (OpError, ValueError) as exc:
            self._send({"id": rid, "ok": False, "error": str(exc)})
        except KeyError as exc:
            self._send({"id": rid, "ok": False, "error": f"the request has no {exc}"})
        except Exception as exc:
            logger.exception("request %s failed", req.get("op"))
            self._send({"id": rid, "ok": False, "error": f"{type(exc).__name__}: {exc}"})
        else:
            self._send({"id": rid, "ok": True, "result": result})


def _rmw() -> str:
    return os.environ.get("RMW_IMPLEMENTATION") or DEFAULT_RMW


def _domain() -> int:
    try:
        return int(os.environ.get("ROS_DOMAIN_ID", "0"))
    except ValueError:
        return 0


def _refuse(listener: socket.socket, error: str, stop: threading.Event) -> int:
    """Answer the first connection with the error (within 10 s), and exit."""
    sys.stderr.write(f"temoto-ros2-bridge: {error}\n")
    listener.settimeout(TICK_S)
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and not stop.is_set():
        try:
            conn, _ = listener.accept()
        except TimeoutError:
            continue
        with conn, contextlib.suppress(OSError):
            send_frame(conn, {"error": error})
        break
    return EXIT_BAD_ENV


def main(argv: list[str] | None = None) -> int:
    """Run the bridge until SIGTERM or SIGINT, or until the parent is gone.

    Args:
        argv: The arguments (``--socket PATH [--parent PID]``).

    Returns:
        The exit status: 0, or 2 when the environment is wrong.
    """
    parser = argparse.ArgumentParser(prog="python -m temoto.ros2.bridge")
    parser.add_argument("--socket", required=True, help="the Unix socket path to listen on")
    parser.add_argument(
        "--parent",
        type=int,
        default=0,
        help="exit when this process is gone (default: the parent at start)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="temoto-ros2-bridge: %(message)s")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda _s, _f: stop.set())
    parent = args.parent or os.getppid()
    path = Path(args.socket)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind(str(path))
        listener.listen(16)
        error = check_rmw(os.environ)
        if error is not None:
            return _refuse(listener, error, stop)
        try:
            import rclpy  # exits 102 on an RMW it cannot use (checked above)
            from rclpy.signals import SignalHandlerOptions
        except ImportError:
            return _refuse(
                listener, f"the ROS 2 actions need rclpy in {sys.executable}: {INSTALL_HINT}", stop
            )

        rclpy.init(args=[], signal_handler_options=SignalHandlerOptions.NO)
        bridge = Bridge(rclpy, stop)
        connections: list[Connection] = []
        accepted = 0
        try:
            listener.settimeout(TICK_S)
            while not stop.is_set():
                if os.getppid() != parent:  # re-parented: the parent is gone
                    logger.info("the TeMoto process that started the bridge is gone; stopping")
                    break
                try:
                    sock, _ = listener.accept()
                except TimeoutError:
                    continue
                sock.settimeout(None)
                accepted += 1
                conn = Connection(bridge, sock, accepted)
                for old in [c for c in connections if not c.thread.is_alive()]:
                    old.thread.join()
                    connections.remove(old)
                connections.append(conn)
                conn.thread.start()
        finally:
            stop.set()
            for conn in connections:
                conn.close()
            for conn in connections:
                conn.thread.join(JOIN_S * 3)
            bridge.close()
    finally:
        listener.close()
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
    return 0


if __name__ == "__main__":
    sys.exit(main())
