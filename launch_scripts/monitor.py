#!/usr/bin/env python3
"""Print the status of both patchwalk nodes once a second (rclpy from the test venv, DDS on loopback).

    .venv/bin/python launch_scripts/monitor.py [--once]

Uses the same environment as launch_scripts/demo.sh (ROS_DOMAIN_ID, the loopback Fast DDS profile).
"""

import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("ROS_DOMAIN_ID", "0")
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(REPO / "tests" / "fastdds_loopback.xml"))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
os.environ.setdefault("ROS_LOG_DIR", str(REPO / "build" / "demo" / "ros_log"))

import rclpy  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from patchwalk_msgs.msg import ExecutorStatus, MapperStatus  # noqa: E402

STATES = {0: "idle", 1: "playing", 2: "holding_fault", 3: "estopped"}


def main() -> int:
    once = "--once" in sys.argv
    rclpy.init()
    node = rclpy.create_node("patchwalk_monitor")
    latest = {}
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(MapperStatus, "/patch_mapper/status", lambda m: latest.__setitem__("mapper", m), qos)
    node.create_subscription(ExecutorStatus, "/step_executor/status", lambda m: latest.__setitem__("executor", m), qos)
    try:
        next_print = time.monotonic() + 1.0
        while rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.1)
            if time.monotonic() < next_print:
                continue
            next_print += 1.0
            m, e = latest.get("mapper"), latest.get("executor")
            mapper = (f"patch_mapper: frames {m.frames_received} received, {m.frames_processed} processed, "
                      f"{m.frames_skipped} skipped, {m.frames_rejected} rejected; {m.patches_in_map} patches"
                      + (f"; last error: {m.last_error}" if m.last_error else "")) if m else "patch_mapper: (no status yet)"
            executor = (f"step_executor: {STATES.get(e.state, e.state)}, armed={e.armed}, torque={e.torque_enabled}, "
                        f"{e.library_size} motions" + (f", fault: {e.last_fault}" if e.last_fault else "")) \
                if e else "step_executor: (no status yet)"
            print(f"{time.strftime('%H:%M:%S')}  {mapper} | {executor}", flush=True)
            if once and m and e:
                return 0
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
