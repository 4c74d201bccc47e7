"""Log lines on /rosout (rcl_interfaces/msg/Log), as rcl nodes forward them: a late subscriber (transient
local, as rcl's /rosout QoS) gets the start-up lines of patch_mapper and step_executor, named by the node
and its namespace, with level, file and line; the middleware's own lines stay off the topic."""

from __future__ import annotations

from rcl_interfaces.msg import Log
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

ROSOUT_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                        history=HistoryPolicy.KEEP_LAST, depth=1000)


def test_node_log_lines_reach_a_late_rosout_subscriber(ros, start_node):
    start_node("patch_mapper", "--ros-args", "-r", "__ns:=/robot7")
    start_node("step_executor", "--param", "ros.status_rate_hz=20")
    ros.wait_for_nodes("/robot7/patch_mapper", "/step_executor")
    logs = ros.collect(Log, "/rosout", ROSOUT_QOS)
    mapper = logs.wait_for(lambda m: m.name == "robot7.patch_mapper" and "patch_mapper running" in m.msg, timeout=30)
    assert mapper.level == Log.INFO
    assert mapper.file.endswith(".rs") and mapper.line > 0
    executor = logs.wait_for(lambda m: m.name == "step_executor" and "step_executor running" in m.msg, timeout=30)
    assert executor.level == Log.INFO
    # A missing servo bus is a warning of the executor, on /rosout with its level.
    warning = logs.wait_for(lambda m: m.name == "step_executor" and "servo bus not available" in m.msg, timeout=30)
    assert warning.level == Log.WARN
    assert not any(m.function.startswith(("rustdds", "ros2_client")) for m in logs.messages)
