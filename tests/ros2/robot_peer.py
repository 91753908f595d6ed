"""A plain rclpy node, independent of TeMoto, that watches (and may drive) a robot on ROS 2.

Run as ``python robot_peer.py ROBOT``; prints ``ready`` once its entities exist. It subscribes
to ``/ROBOT/odom``, ``/ROBOT/joint_states``, ``/ROBOT/fix`` and ``/diagnostics`` and prints one
JSON line per message received (``{"topic": "odom", "x": .., "y": .., "yaw": .., "v": ..}``,
``{"topic": "joint_states", "position": {name: rad}}``, ``{"topic": "fix", "lat": ..}``,
``{"topic": "diagnostics", "levels": {name: level}}``). A line on its stdin
``cmd_vel V W SECONDS`` publishes ``geometry_msgs/Twist`` (linear.x = V, angular.z = W) on
``/ROBOT/cmd_vel`` at 10 Hz for SECONDS, then prints ``{"topic": "cmd_vel_done",
"subscribers": N}`` (N: the subscriptions matched to its publisher); ``wait_subscriber SECONDS``
waits (at most that long) until its ``cmd_vel`` publisher is matched, then prints
``{"topic": "subscribers", "subscribers": N}``.

Ends on SIGINT or SIGTERM, or at the end of its stdin (exit 0, segments removed).
"""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState, NavSatFix

_print_lock = threading.Lock()


def say(obj: dict) -> None:
    with _print_lock:
        print(json.dumps(obj), flush=True)


def main() -> None:
    robot = sys.argv[1]
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda _s, _f: stop.set())
    node = rclpy.create_node("temoto_test_robot_peer")

    def on_odom(m: Odometry) -> None:
        q = m.pose.pose.orientation
        say(
            {
                "topic": "odom",
                "x": m.pose.pose.position.x,
                "y": m.pose.pose.position.y,
                "yaw": 2 * math.atan2(q.z, q.w),
                "v": m.twist.twist.linear.x,
                "frame": m.header.frame_id,
                "child": m.child_frame_id,
                "stamp": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
            }
        )

    def on_joints(m: JointState) -> None:
        say({"topic": "joint_states", "position": dict(zip(m.name, m.position, strict=True))})

    def on_fix(m: NavSatFix) -> None:
        say({"topic": "fix", "lat": m.latitude, "lon": m.longitude, "alt": m.altitude})

    def on_diag(m: DiagnosticArray) -> None:
        levels = {s.name: s.level[0] for s in m.status}
        say({"topic": "diagnostics", "levels": levels})

    node.create_subscription(Odometry, f"/{robot}/odom", on_odom, 10)
    node.create_subscription(JointState, f"/{robot}/joint_states", on_joints, 10)
    node.create_subscription(NavSatFix, f"/{robot}/fix", on_fix, 10)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    cmd = node.create_publisher(Twist, f"/{robot}/cmd_vel", 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def spin() -> None:
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.1)

    spinner = threading.Thread(target=spin, name="peer-executor")
    spinner.start()

    def commands() -> None:
        for line in sys.stdin:
            words = line.split()
            if len(words) == 2 and words[0] == "wait_subscriber":
                end = time.monotonic() + float(words[1])
                while cmd.get_subscription_count() == 0 and time.monotonic() < end:
                    time.sleep(0.05)
                say({"topic": "subscribers", "subscribers": cmd.get_subscription_count()})
            if len(words) == 4 and words[0] == "cmd_vel":
                v, w, seconds = float(words[1]), float(words[2]), float(words[3])
                end = time.monotonic() + seconds
                while time.monotonic() < end and not stop.is_set():
                    msg = Twist()
                    msg.linear.x, msg.angular.z = v, w
                    cmd.publish(msg)
                    time.sleep(0.1)
                say({"topic": "cmd_vel_done", "subscribers": cmd.get_subscription_count()})
        stop.set()

    reader = threading.Thread(target=commands, name="peer-stdin", daemon=True)
    reader.start()
    print("ready", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        spinner.join()
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
