"""A ROS 2 peer for the example graph: plain rclpy, nothing of TeMoto.

Serves ``/arm/home`` (``std_srvs/srv/Trigger``), ``/arm/count`` (``test_msgs/action/Fibonacci``,
one feedback per step, cancellable) and the lifecycle node ``/gripper``. Run it with the Python
that has rclpy (``python examples/ros2/peer.py``); Ctrl-C ends it.
"""

from __future__ import annotations

import signal
import threading
import time

import rclpy
from rclpy.action import ActionServer, CancelResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import Trigger
from test_msgs.action import Fibonacci


class Gripper(LifecycleNode):
    def __init__(self) -> None:
        super().__init__("gripper")

    def _log(self, what: str) -> TransitionCallbackReturn:
        self.get_logger().info(what)
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._log("configured")

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._log("activated")

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._log("deactivated")

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._log("cleaned up")


def main() -> None:
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda _s, _f: stop.set())
    node = rclpy.create_node("arm")

    def home(_req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        resp.success, resp.message = True, "arm at home"
        return resp

    def count(handle: object) -> Fibonacci.Result:
        seq = [0, 1]
        for _ in range(1, min(handle.request.order, 46)):  # type: ignore[attr-defined]
            if handle.is_cancel_requested:  # type: ignore[attr-defined]
                handle.canceled()  # type: ignore[attr-defined]
                node.get_logger().info("count cancelled")
                return Fibonacci.Result(sequence=seq)
            seq.append(seq[-1] + seq[-2])  # int32: order 46 at most
            handle.publish_feedback(Fibonacci.Feedback(sequence=seq))  # type: ignore[attr-defined]
            time.sleep(0.1)
        handle.succeed()  # type: ignore[attr-defined]
        return Fibonacci.Result(sequence=seq)

    node.create_service(Trigger, "/arm/home", home)
    server = ActionServer(
        node,
        Fibonacci,
        "/arm/count",
        execute_callback=count,
        cancel_callback=lambda _h: CancelResponse.ACCEPT,
        callback_group=ReentrantCallbackGroup(),
    )
    gripper = Gripper()
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    executor.add_node(gripper)
    print("peer ready", flush=True)
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
    executor.shutdown()  # its running callbacks end before their entities are destroyed
    server.destroy()
    gripper.destroy_node()
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
