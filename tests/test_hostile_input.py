"""Hostile input over ROS 2: one badly stamped message must not wedge patch_mapper, and the executor's
services refuse names and points that would be stored or used broken, naming the field and the rule."""

from __future__ import annotations

import math
import time

from geometry_msgs.msg import Point
from sensor_msgs.msg import CameraInfo, Image, Imu
from std_srvs.srv import Trigger
from patchwalk_msgs.msg import MapperStatus
from patchwalk_msgs.srv import DeleteMotion, PlayMotion, SaveMotion, SelectTarget

import patchwalk_testing as pw

FAR_FUTURE_S = 2**31 - 2


def _stamp(msg, seconds: float) -> None:
    msg.header.stamp.sec = int(seconds)
    msg.header.stamp.nanosec = int(round((seconds - int(seconds)) * 1e9)) % 1_000_000_000


def _imu(seconds: float) -> Imu:
    msg = Imu()
    msg.header.frame_id = "imu"
    _stamp(msg, seconds)
    # At rest the accelerometer measures "up": gravity along the camera's y axis (the identity camera_from_imu).
    msg.linear_acceleration.y = -9.81
    return msg


def _depth(seconds: float) -> Image:
    msg = pw.depth_image_16uc1(64, 48)
    _stamp(msg, seconds)
    return msg


def test_a_far_future_depth_frame_and_imu_sample_do_not_wedge_the_mapper(ros, patch_mapper):
    status = ros.collect(MapperStatus, "/patch_mapper/status")
    info_pub = ros.publisher(CameraInfo, "/camera/depth/camera_info")
    ros.publish_until(info_pub, pw.camera_info(64, 48), status, lambda s: s.camera_infos_received >= 1)
    imu_pub = ros.publisher(Imu, "/imu/data")
    depth_pub = ros.publisher(Image, "/camera/depth/image_raw")
    ros.wait_for_subscriber(imu_pub)
    ros.wait_for_subscriber(depth_pub)

    # An IMU sample stamped 2^31 - 1 s alone, then a depth frame stamped 2^31 - 2 s with an IMU sample
    # near it: refused where they enter, naming the clock check.
    ros.publish_until(imu_pub, _imu(2**31 - 1), status, lambda s: "IMU stamp" in s.last_error)
    got = ros.publish_until(depth_pub, _depth(FAR_FUTURE_S), status, lambda s: s.frames_rejected >= 1)
    imu_pub.publish(_imu(FAR_FUTURE_S))
    assert "ahead of the node clock" in got.last_error, got.last_error
    assert got.frames_processed == 0

    def normal_frames_until(predicate, timeout: float = 30.0):
        deadline = time.monotonic() + timeout
        while True:
            now = time.time()
            imu_pub.publish(_imu(now - 0.002))
            imu_pub.publish(_imu(now))
            depth_pub.publish(_depth(now))
            try:
                return status.wait_for(predicate, timeout=0.15)
            except AssertionError:
                if time.monotonic() > deadline:
                    return status.wait_for(predicate, timeout=0.0)

    # Correctly stamped frames after them are processed, and keep being processed.
    first = normal_frames_until(lambda s: s.frames_processed >= 2)
    later = normal_frames_until(lambda s: s.frames_processed >= first.frames_processed + 3)
    assert later.frames_processed > first.frames_processed
    assert "is not after" not in later.last_error and "IMU gap" not in later.last_error, later.last_error

    # A reset clears every piece of time state; frames after it are processed.
    assert ros.call(Trigger, "/patch_mapper/reset").success
    after_reset = normal_frames_until(lambda s: s.frames_processed >= later.frames_processed + 3)
    assert after_reset.frames_processed >= later.frames_processed + 3
    assert patch_mapper.alive()


def _control_and_bidi_names() -> list[tuple[str, str]]:
    return [
        ("", "empty"),
        ("   ", "empty"),
        ("x" * 129, "128 bytes"),
        ("ab\ncd", "control"),
        ("step\u202eevil", "bidirectional"),
        ("step\u2066x", "bidirectional"),
        ("tab\there", "control"),
    ]


def test_motion_names_are_validated_naming_the_rule(ros, step_executor):
    for name, rule in _control_and_bidi_names():
        for srv_type, service in ((SaveMotion, "save_motion"), (DeleteMotion, "delete_motion"), (PlayMotion, "play_motion")):
            request = srv_type.Request()
            request.name = name
            response = ros.call(srv_type, f"/step_executor/{service}", request)
            assert not response.success, (service, name)
            assert "name" in response.message and rule in response.message, (service, repr(name), response.message)
    assert step_executor.alive()


def test_select_target_refuses_a_non_finite_point(ros, step_executor):
    for bad in (math.nan, math.inf, -math.inf):
        for mode in (SelectTarget.Request.MODE_NEAREST_POINT, SelectTarget.Request.MODE_FIT_AT_POINT):
            request = SelectTarget.Request()
            request.mode = mode
            request.point = Point(x=0.2, y=bad, z=0.0)
            request.radius = 0.05
            response = ros.call(SelectTarget, "/step_executor/select_target", request)
            assert not response.success, (mode, bad, response.message)
            assert "point" in response.message and "finite" in response.message, response.message
    assert step_executor.alive()
