"""TF, simulated time and CameraInfo pairing over ROS 2 with the real binaries:
- the tree a tf2-style listener assembles from terrain_sim's /tf_static and patch_mapper's /tf
  (odom → base_link → camera_optical → imu) against the simulator's ground truth (`terrain_sim scene`);
- `use_sim_time`: terrain_sim --clock 0.5 drives /clock at half speed and the mapper's stamps follow it;
- a depth image whose size no CameraInfo has is rejected, with both sizes named;
- step_executor's /robot_description is the URDF, latched."""

from __future__ import annotations

import json
import math
import subprocess
import time

import numpy as np
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String
from tf2_msgs.msg import TFMessage
from patchwalk_msgs.msg import MapperStatus, PatchArray

import patchwalk_testing as pw

SIM_MAPPER_CONFIG = "config/patch_mapper_sim.yaml"
# tf2_ros's listener profiles.
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
TF_STATIC_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
LATCHED_QOS = TF_STATIC_QOS


def quat_matrix(x, y, z, w) -> np.ndarray:
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix(translation, rotation_xyzw) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(*rotation_xyzw)
    m[:3, 3] = translation
    return m


def transform_matrix(t) -> np.ndarray:
    tr, q = t.transform.translation, t.transform.rotation
    return matrix([tr.x, tr.y, tr.z], [q.x, q.y, q.z, q.w])


def pose_matrix(pose) -> np.ndarray:
    p, q = pose.position, pose.orientation
    return matrix([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])


def stamp(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def rotation_angle(a: np.ndarray, b: np.ndarray) -> float:
    r = a[:3, :3].T @ b[:3, :3]
    return math.acos(max(-1.0, min(1.0, (np.trace(r) - 1) / 2)))


def test_tf_tree_from_simulator_and_mapper_matches_ground_truth(ros, start_node, log_dir):
    statics = ros.collect(TFMessage, "/tf_static", TF_STATIC_QOS)
    dynamics = ros.collect(TFMessage, "/tf", TF_QOS)
    arrays = ros.collect(PatchArray, "/patch_mapper/patches")
    start_node("terrain_sim", "--config", "config/terrain_sim.yaml")
    mapper = start_node("patch_mapper", "--config", SIM_MAPPER_CONFIG)
    ros.wait_for_nodes("/terrain_sim", "/patch_mapper")
    scene = json.loads(subprocess.run([str(pw.binary("terrain_sim")), "scene", "--config", "config/terrain_sim.yaml"],
                                      check=True, capture_output=True, text=True, cwd=pw.REPO).stdout)

    # /tf_static: the simulator's mount, as its ground truth says.
    tree = {t.child_frame_id: t for t in statics.latest().transforms}
    assert tree["camera_optical"].header.frame_id == "base_link"
    assert tree["imu"].header.frame_id == "camera_optical"
    truth = scene["base_from_camera"]
    base_from_camera = transform_matrix(tree["camera_optical"])
    np.testing.assert_allclose(base_from_camera, matrix(truth["translation"], truth["rotation_xyzw"]), atol=1e-9)

    # /tf: odom → base_link at each PatchArray's stamp, through the robot tree to the tracked camera.
    array = arrays.wait_for(lambda a: len(a.patches) > 0, timeout=60.0)
    assert array.header.frame_id == "odom"
    wanted = stamp(array.header)

    def odom_to_base_at_stamp(msg):
        return any(t.child_frame_id == "base_link" and abs(stamp(t.header) - wanted) < 1e-9 for t in msg.transforms)

    odom_to_base = next(t for t in dynamics.wait_for(odom_to_base_at_stamp).transforms if t.child_frame_id == "base_link")
    assert odom_to_base.header.frame_id == "odom"
    odom_from_camera = transform_matrix(odom_to_base) @ base_from_camera
    np.testing.assert_allclose(odom_from_camera, pose_matrix(array.camera_pose), atol=1e-6)
    # The robot stands upright on its station (ground truth): in the gravity-aligned odom frame
    # base_link's z axis is vertical.
    odom_from_base = transform_matrix(odom_to_base)
    tilt = math.degrees(math.acos(min(1.0, odom_from_base[2, 2])))
    assert tilt < 3.0, f"base_link tilted {tilt:.2f}° in odom"
    station = scene["world_from_station"]
    world_from_station = matrix(station["translation"], station["rotation_xyzw"])
    assert math.degrees(math.acos(min(1.0, world_from_station[2, 2]))) < 1e-6
    # The mount came from TF, not from the config.
    pw.wait_until(lambda: "camera_from_imu from TF" in mapper.log(), "mapper took the IMU mount from /tf_static")


def test_sim_time_at_half_speed_drives_the_stamps(ros, start_node):
    clocks = ros.collect(Clock, "/clock", qos_profile_sensor_data)
    arrays = ros.collect(PatchArray, "/patch_mapper/patches")
    statuses = ros.collect(MapperStatus, "/patch_mapper/status")
    diagnostics = ros.collect(DiagnosticArray, "/diagnostics")
    start_node("terrain_sim", "--config", "config/terrain_sim.yaml", "--clock", "0.5")
    start_node("patch_mapper", "--config", SIM_MAPPER_CONFIG, "--param", "use_sim_time=true",
               "--param", "ros.status_period_s=0.2")
    ros.wait_for_nodes("/terrain_sim", "/patch_mapper")
    # The newest /clock at wall_0, not the first one received (that one can be seconds old by now).
    first = clocks.latest()
    wall_0, sim_0 = time.monotonic(), first.clock.sec + 1e-9 * first.clock.nanosec
    time.sleep(4.0)
    last = clocks.latest()
    wall_1, sim_1 = time.monotonic(), last.clock.sec + 1e-9 * last.clock.nanosec
    rate = (sim_1 - sim_0) / (wall_1 - wall_0)
    assert 0.4 < rate < 0.6, f"/clock ran at {rate:.2f} x real time"
    assert sim_1 < 100.0, "simulated time starts at 0"
    # Outputs carry simulated stamps: the depth frame's (PatchArray) and the node clock's (status).
    array = arrays.wait_for(lambda a: True, timeout=60.0)
    assert 0.0 <= stamp(array.header) < 100.0, stamp(array.header)
    statuses.clear()
    status = statuses.wait_for(lambda s: s.frames_processed > 0, timeout=60.0)
    now = clocks.latest()
    # The status is stamped from the node clock = the last /clock (100 Hz of sim time) it took.
    assert abs((status.stamp.sec + 1e-9 * status.stamp.nanosec) - (now.clock.sec + 1e-9 * now.clock.nanosec)) < 1.0
    # So is /diagnostics (REP-107 arrays are stamped from the node clock too).
    diagnostics.clear()
    array = diagnostics.wait_for(lambda a: any(s.hardware_id == "patch_mapper" for s in a.status), timeout=30.0)
    now = clocks.latest()
    assert abs(stamp(array.header) - (now.clock.sec + 1e-9 * now.clock.nanosec)) < 1.5, (stamp(array.header), now.clock)


def test_depth_image_without_camera_info_of_its_size_is_rejected(ros, patch_mapper):
    statuses = ros.collect(MapperStatus, "/patch_mapper/status")
    info_pub = ros.publisher(type(pw.camera_info(2, 2)), "/camera/depth/camera_info", qos_profile_sensor_data)
    depth_pub = ros.publisher(type(pw.depth_image_16uc1(2, 2)), "/camera/depth/image_raw", qos_profile_sensor_data)
    ros.wait_for_subscriber(depth_pub)
    ros.wait_for_subscriber(info_pub)
    info = pw.camera_info(320, 240)
    depth = pw.depth_image_16uc1(640, 480)

    def publish_pair():
        now = time.time()
        for msg in (info, depth):
            msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), int((now % 1) * 1e9)
        info_pub.publish(info)
        time.sleep(0.02)
        depth_pub.publish(depth)

    status = statuses.latest()
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and status.frames_rejected == 0:
        publish_pair()
        time.sleep(0.1)
        status = statuses.latest()
    assert status.frames_rejected > 0
    assert status.frames_processed == 0
    assert "640x480" in status.last_error and "320x240" in status.last_error, status.last_error


def test_robot_description_is_the_urdf_latched(ros, step_executor):
    descriptions = ros.collect(String, "/robot_description", LATCHED_QOS)
    text = descriptions.latest().data
    assert '<robot name="rpbp">' in text
    assert text == (pw.REPO / "urdf" / "rpbp.urdf").read_text()
