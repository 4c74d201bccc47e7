"""Wire compatibility of every patchwalk_msgs message between rclpy (rosidl-generated C types) and the
Rust structs: a fully populated message goes rclpy -> Rust (`patchwalk_interface_echo`) -> rclpy and
must come back equal in every field. The CDR format is positional, so a field order or type mismatch
would show up here as changed values."""

import pytest

from builtin_interfaces.msg import Time
from patchwalk_msgs.msg import ExecutorStatus, MapperStatus, MotionSummary, Patch, PatchArray


def patch(i: int) -> Patch:
    p = Patch(id=1000 + i, surface=Patch.HYPERBOLIC_PARABOLOID, boundary=Patch.QUADRILATERAL)
    p.curvatures = [2.5 + i, -4.25]
    p.boundary_params = [0.01, 0.02, 0.03, 0.04, 0.05 + i]
    p.rotation = [0.1, -0.2, 0.3]
    p.center = [1.5, -2.5, 0.25 + i]
    p.pose.position.x, p.pose.position.y, p.pose.position.z = 1.5, -2.5, 0.25 + i
    p.pose.orientation.x, p.pose.orientation.w = 0.5, 0.8660254037844386
    p.covariance = [float(k) / 7 for k in range(12 * 12)]
    p.residual = 0.00123
    p.num_points = 4321 + i
    p.first_seen = Time(sec=1_700_000_000, nanosec=1 + i)
    p.last_seen = Time(sec=1_700_000_100, nanosec=999_999_999)
    return p


def patch_array(n: int) -> PatchArray:
    msg = PatchArray(patches=[patch(i) for i in range(n)])
    msg.header.frame_id = "map"
    msg.header.stamp = Time(sec=12, nanosec=34)
    msg.camera_pose.position.z = 0.47
    msg.camera_pose.orientation.y, msg.camera_pose.orientation.w = 0.6, 0.8
    return msg


def mapper_status() -> MapperStatus:
    return MapperStatus(stamp=Time(sec=5, nanosec=6), frames_received=2**40 + 1, frames_processed=7,
                        frames_skipped=8, frames_rejected=9, camera_infos_received=10, imu_received=11,
                        patches_in_map=12, last_error="depth image rejected: ünïcode ok",
                        timing_names=["acquire", "fusion", "fit"], timing_ms=[0.5, 12.25, 3.0])


def executor_status() -> ExecutorStatus:
    return ExecutorStatus(stamp=Time(sec=1, nanosec=2), state=ExecutorStatus.STATE_HOLDING_FAULT, armed=True,
                          torque_enabled=True, current_motion="rock_3", keyframe_index=4, last_match="rock_2",
                          fault_servo_id=11, last_fault="servo 11: overload", library_size=4,
                          recorded_keyframes=6)


CASES = {
    "Patch": (Patch, lambda: patch(0)),
    "PatchArray": (PatchArray, lambda: patch_array(3)),
    "MapperStatus": (MapperStatus, mapper_status),
    "ExecutorStatus": (ExecutorStatus, executor_status),
    "MotionSummary": (MotionSummary, lambda: MotionSummary(name="rock_1", surface=Patch.SPHERE,
                                                           boundary=Patch.CIRCLE, keyframe_count=9,
                                                           duration=4.5)),
}


@pytest.fixture
def echo(ros, start_node):
    node = start_node("patchwalk_interface_echo")
    ros.wait_for_nodes("/patchwalk_interface_echo")
    return node


@pytest.mark.parametrize("name", sorted(CASES))
def test_message_round_trips_through_rust_unchanged(ros, echo, name):
    msg_type, make = CASES[name]
    sent = make()
    out = ros.collect(msg_type, f"/patchwalk_echo/out/{name}")
    pub = ros.publisher(msg_type, f"/patchwalk_echo/in/{name}", qos=10)
    received = ros.publish_until(pub, sent, out, lambda _: True, period=0.5)
    assert received == sent


def test_large_patch_array_round_trips(ros, echo):
    """~400 kB each way: fragmented in both directions."""
    sent = patch_array(300)
    out = ros.collect(PatchArray, "/patchwalk_echo/out/PatchArray")
    pub = ros.publisher(PatchArray, "/patchwalk_echo/in/PatchArray", qos=10)
    received = ros.publish_until(pub, sent, out, lambda m: len(m.patches) == 300, period=1.0)
    assert received == sent
