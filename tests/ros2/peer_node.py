"""A plain rclpy node, independent of TeMoto, that the ROS 2 action tests talk to.

Run as ``python peer_node.py``; prints ``ready`` once its entities exist, and one line per
event the tests look for (``called``, ``goal``, ``canceled``, ``succeeded``). Serves:

* ``/peer/trigger`` (``std_srvs/srv/Trigger``): answers ``triggered N``;
* ``/peer/echo_in`` -> ``/peer/echo_out`` (``std_msgs/msg/String``): once a message arrived,
  republishes ``echo: <data>`` every 0.1 s (late subscribers see it too);
* ``/peer/fibonacci`` (``test_msgs/action/Fibonacci``): one feedback per step every 0.1 s,
  cancellable;
* the lifecycle node ``/peer_lifecycle``: prints ``configure``, ``activate``, ``deactivate``,
  ``cleanup`` on each transition; with ``PEER_SELF_DEACTIVATE_S`` set, it deactivates itself
  that long after being activated.

Ends on SIGINT or SIGTERM (exit 0, segments removed).
"""

from __future__ import annotations

import os
import signal
import threading
import time

import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String
from std_srvs.srv import Trigger
from test_msgs.action import Fibonacci


class PeerLifecycle(LifecycleNode):
    """Prints its transitions; may deactivate itself (``PEER_SELF_DEACTIVATE_S``)."""

    def __init__(self) -> None:
        super().__init__("peer_lifecycle")
        self._quit_after = float(os.environ.get("PEER_SELF_DEACTIVATE_S", "0"))
        self._timer: object = None

    def _say(self, what: str) -> TransitionCallbackReturn:
        print(what, flush=True)
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._say("configure")

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._quit_after > 0:
            self._timer = self.create_timer(self._quit_after, self._quit)
        return self._say("activate")

    def _quit(self) -> None:
        self.destroy_timer(self._timer)  # type: ignore[arg-type]
        self._quit_after = 0
        self.trigger_deactivate()

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._say("deactivate")

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._say("cleanup")


def main() -> None:
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda _s, _f: stop.set())
    node = rclpy.create_node("temoto_test_peer")
    calls = [0]
    echo: list[str] = []

    def trigger(_req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        calls[0] += 1
        resp.success = True
        resp.message = f"triggered {calls[0]}"
        print("called", flush=True)
        return resp

    node.create_service(Trigger, "/peer/trigger", trigger)
    pub = node.create_publisher(String, "/peer/echo_out", 10)
    node.create_subscription(String, "/peer/echo_in", lambda m: echo[:] or echo.append(m.data), 10)
    node.create_timer(0.1, lambda: echo and pub.publish(String(data=f"echo: {echo[0]}")))

    def execute(handle: object) -> Fibonacci.Result:
        print("goal", flush=True)
        seq = [0, 1]
        feedback = Fibonacci.Feedback()
        for _ in range(1, handle.request.order):  # type: ignore[attr-defined]
            if handle.is_cancel_requested:  # type: ignore[attr-defined]
                handle.canceled()  # type: ignore[attr-defined]
                print("canceled", flush=True)
                return Fibonacci.Result(sequence=seq)
            seq.append(seq[-1] + seq[-2])
            feedback.sequence = seq
            handle.publish_feedback(feedback)  # type: ignore[attr-defined]
            time.sleep(0.1)
        handle.succeed()  # type: ignore[attr-defined]
        print("succeeded", flush=True)
        return Fibonacci.Result(sequence=seq)

    group = ReentrantCallbackGroup()
    server = ActionServer(
        node,
        Fibonacci,
        "/peer/fibonacci",
        execute_callback=execute,
        goal_callback=lambda _g: GoalResponse.ACCEPT,
        cancel_callback=lambda _h: CancelResponse.ACCEPT,
        callback_group=group,
    )
    lifecycle = PeerLifecycle()
    executor = MultiThreadedExecutor(num_threads=2)  # the goal runs while cancels arrive
    executor.add_node(node)
    executor.add_node(lifecycle)
    print("ready", flush=True)
    try:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    executor.shutdown()  # its running callbacks end before their entities are destroyed
    server.destroy()
    lifecycle.destroy_node()
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
