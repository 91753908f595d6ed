"""The TeMoto side of a bridge connection: requests, their events, and cancel.

One :class:`BridgeClient` per user (an action opens one for its run); requests may overlap
(a ``cancel`` is sent while a goal runs). A reader thread (``temoto-ros2-client``) routes the
replies and events to the waiting requests; :meth:`close` joins it.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from temoto.errors import ResourceError
from temoto.ros2.protocol import FrameError, recv_frame, send_frame

__all__ = ["BridgeClient", "BridgeError"]

logger = logging.getLogger(__name__)

#: Seconds between checks of ``stop`` while a request waits.
POLL_S = 0.05


class BridgeError(ResourceError):
    """A bridge request failed (its message is the bridge's one line), or the bridge is gone.

    Args:
        message: The one line.
        gone: True when the connection to the bridge was lost (not a failed request).
    """

    def __init__(self, message: str, *, gone: bool = False) -> None:
        super().__init__(message)
        self.gone = gone


class _Pending:
    def __init__(self, on_event: Callable[[dict[str, Any]], None] | None) -> None:
        self.done = threading.Event()
        self.reply: dict[str, Any] | None = None
        self.on_event = on_event


class BridgeClient:
    """A connection to a bridge's socket.

    Args:
        path: The socket path (the ``"ros2"`` resource's response).
        timeout: Seconds to wait for the bridge's ready frame.

    Raises:
        BridgeError: No bridge answers there, or it refused to start (its one line).
    """

    def __init__(self, path: str, timeout: float = 10.0) -> None:
        self.path = path
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._sock.settimeout(timeout)
            self._sock.connect(path)
            hello = recv_frame(self._sock)
            self._sock.settimeout(None)
        except (OSError, FrameError) as exc:
            self._sock.close()
            raise BridgeError(f"the ROS 2 bridge at {path} does not answer: {exc}") from None
        if not hello.get("ready"):
            self._sock.close()
            raise BridgeError(str(hello.get("error") or f"the ROS 2 bridge refused: {hello}"))
        self.hello = hello
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._write = threading.Lock()
        self._pending: dict[int, _Pending] = {}
        self._closed = False
        self._lost = ""
        self._reader = threading.Thread(target=self._read, name="temoto-ros2-client")
        self._reader.start()

    def _read(self) -> None:
        try:
            while True:
                msg = recv_frame(self._sock)
                with self._lock:
                    pending = self._pending.get(msg.get("id", -1))
                if pending is None:
                    continue
                if "event" in msg:
                    if pending.on_event is not None:
                        try:
                            pending.on_event(msg)
                        except Exception:
                            logger.exception("a bridge event handler failed")
                    continue
                pending.reply = msg
                pending.done.set()
        except (FrameError, OSError) as exc:
            with self._lock:
                self._lost = "the connection was closed" if self._closed else str(exc)
                waiting = list(self._pending.values())
            for pending in waiting:
                pending.done.set()

    def request(
        self,
        op: str,
        *,
        reply_timeout: float | None = None,
        stop: Callable[[], bool] | None = None,
        on_event: Callable[[dict[str, Any]], None] | None = None,
        started: Callable[[int], None] | None = None,
        **fields: Any,
    ) -> dict[str, Any]:
        """Send a request and wait for its reply.

        Args:
            op: The operation (``publish``, ``wait_message``, ``call_service``, ``send_goal``,
                ``cancel``, ``ping``).
            reply_timeout: Seconds to wait for the reply (None: until it comes or the bridge
                is gone); the bridge applies the request's own ``timeout`` field.
            stop: Polled while waiting; once it returns True the request is cancelled (the
                bridge then replies soon, with an error saying so).
            on_event: Called (in the reader thread) with the request's events.
            started: Called with the request's id once it is sent (to cancel it later).
            **fields: The request's fields.

        Returns:
            The reply's ``result``.

        Raises:
            BridgeError: The request failed (the bridge's one line), the bridge is gone, or no
                reply within ``timeout``.
        """
        rid = next(self._ids)
        pending = _Pending(on_event)
        with self._lock:
            if self._lost:
                raise BridgeError(f"the ROS 2 bridge is gone: {self._lost}", gone=True)
            self._pending[rid] = pending
        try:
            with self._write:
                send_frame(self._sock, {"id": rid, "op": op, **fields})
            if started is not None:
                started(rid)
            deadline = None if reply_timeout is None else time.monotonic() + reply_timeout
            cancelled = False
            while not pending.done.wait(POLL_S):
                if not cancelled and stop is not None and stop():
                    cancelled = True
                    with self._write:
                        send_frame(
                            self._sock, {"id": next(self._ids), "op": "cancel", "target": rid}
                        )
                if deadline is not None and time.monotonic() >= deadline:
                    raise BridgeError(
                        f"the ROS 2 bridge did not answer {op} within {reply_timeout:g} s"
                    )
        except OSError as exc:
            raise BridgeError(f"the ROS 2 bridge is gone: {exc}", gone=True) from None
        finally:
            with self._lock:
                self._pending.pop(rid, None)
        reply = pending.reply
        if reply is None:
            raise BridgeError(f"the ROS 2 bridge is gone: {self._lost}", gone=True)
        if not reply.get("ok"):
            raise BridgeError(str(reply.get("error")))
        result = reply.get("result")
        return result if isinstance(result, dict) else {}

    def cancel(self, rid: int) -> None:
        """Cancel a running request (a goal); its own reply says how it ended.

        Args:
            rid: The request's id (from ``started``).
        """
        with contextlib.suppress(BridgeError):
            self.request("cancel", reply_timeout=5.0, target=rid)

    def close(self) -> None:
        """Close the connection (the bridge cancels what still runs) and join the reader."""
        with self._lock:
            self._closed = True
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        self._reader.join()
        self._sock.close()

    def __enter__(self) -> BridgeClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
