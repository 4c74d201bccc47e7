"""Both nodes come up on the ROS 2 graph with every endpoint of the README table, typed, and stop cleanly."""

import signal

NAMES_TOPICS = {
    # patch_mapper
    "/camera/depth/image_raw": "sensor_msgs/msg/Image",
    "/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo",
    "/imu/data": "sensor_msgs/msg/Imu",
    "/patch_mapper/patches": "patchwalk_msgs/msg/PatchArray",
    "/patch_mapper/markers": "visualization_msgs/msg/MarkerArray",
    "/patch_mapper/birds_eye_cloud": "sensor_msgs/msg/PointCloud2",
    "/patch_mapper/status": "patchwalk_msgs/msg/MapperStatus",
    # step_executor
    "/joint_states": "sensor_msgs/msg/JointState",
    "/step_executor/status": "patchwalk_msgs/msg/ExecutorStatus",
    "/step_executor/estop": "std_msgs/msg/Bool",
    "/step_executor/estop_state": "std_msgs/msg/Bool",
    "/step_executor/heartbeat": "std_msgs/msg/Empty",
    "/step_executor/play_motion/_action/feedback": "patchwalk_msgs/action/PlayMotion_FeedbackMessage",
    "/step_executor/play_motion/_action/status": "action_msgs/msg/GoalStatusArray",
    # both
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}

NAMES_SERVICES = {
    "/patch_mapper/reset": "std_srvs/srv/Trigger",
    "/step_executor/set_torque": "std_srvs/srv/SetBool",
    "/step_executor/record_keyframe": "patchwalk_msgs/srv/RecordKeyframe",
    "/step_executor/select_target": "patchwalk_msgs/srv/SelectTarget",
    "/step_executor/save_motion": "patchwalk_msgs/srv/SaveMotion",
    "/step_executor/list_motions": "patchwalk_msgs/srv/ListMotions",
    "/step_executor/delete_motion": "patchwalk_msgs/srv/DeleteMotion",
    "/step_executor/play_motion": "patchwalk_msgs/srv/PlayMotion",
    "/step_executor/stop": "std_srvs/srv/Trigger",
    "/step_executor/arm": "std_srvs/srv/SetBool",
    "/step_executor/play_motion/_action/send_goal": "patchwalk_msgs/action/PlayMotion_SendGoal",
    "/step_executor/play_motion/_action/cancel_goal": "action_msgs/srv/CancelGoal",
    "/step_executor/play_motion/_action/get_result": "patchwalk_msgs/action/PlayMotion_GetResult",
    "/step_executor/reboot_servos": "patchwalk_msgs/srv/RebootServos",
}


def test_both_nodes_appear_with_every_endpoint_typed(ros, patch_mapper, step_executor):
    ros.wait_for_nodes("/patch_mapper", "/step_executor")
    ros.wait_for_topic_types(NAMES_TOPICS)
    ros.wait_for_service_types(NAMES_SERVICES)
    assert patch_mapper.alive() and step_executor.alive()


def test_nodes_stop_cleanly_on_sigterm(ros, start_node):
    mapper = start_node("patch_mapper")
    executor = start_node("step_executor")
    ros.wait_for_nodes("/patch_mapper", "/step_executor")
    log = mapper.stop(signal.SIGTERM)
    assert "shutting down" in log
    log = executor.stop(signal.SIGTERM)
    assert "shutting down" in log


def test_unknown_parameter_is_rejected_by_name(start_node):
    node = start_node("patch_mapper", "--param", "ros.status_perod_s=1")
    assert node.proc.wait(timeout=30) != 0
    assert "status_perod_s" in node.log()
