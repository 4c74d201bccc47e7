"""terrain_sim over ROS 2: the simulated Carmine publishes 640x480 16UC1 depth with matching
CameraInfo, the IMU reads |a| = g at 100 Hz, stamps are consistent, /terrain_sim/place_at_rock moves
the robot (bad indices are ignored), and /joint_states moves the camera."""

from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from std_msgs.msg import UInt32

import patchwalk_testing as pw

JOINTS = ["r_hip_yaw", "l_hip_yaw", "r_hip_roll", "l_hip_roll", "r_hip_pitch", "l_hip_pitch",
          "r_knee", "l_knee", "r_ankle_pitch", "l_ankle_pitch", "r_ankle_roll", "l_ankle_roll"]


def _start(ros, start_node, *params):
    args = []
    for p in params:
        args += ["--param", p]
    node = start_node("terrain_sim", "--config", "config/terrain_sim.yaml", *args)
    ros.wait_for_nodes("/terrain_sim")
    return node


def _stamp(msg):
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _depths_mm(image):
    data = bytes(image.data)
    return [int.from_bytes(data[i:i + 2], "little") for i in range(0, len(data), 2)]


def _mean_valid_depth_mm(image):
    valid = [d for d in _depths_mm(image) if d > 0]
    return sum(valid) / len(valid), len(valid)


def test_publishes_depth_camera_info_and_imu(ros, start_node):
    images = ros.collect(Image, "/camera/depth/image_raw", qos_profile_sensor_data)
    infos = ros.collect(CameraInfo, "/camera/depth/camera_info", qos_profile_sensor_data)
    imus = ros.collect(Imu, "/imu/data", qos_profile_sensor_data)
    node = _start(ros, start_node)
    image = images.latest()
    assert (image.width, image.height, image.encoding, image.step) == (640, 480, "16UC1", 1280)
    assert image.is_bigendian == 0 and len(image.data) == 640 * 480 * 2
    assert image.header.frame_id == "camera_optical"
    mean_mm, valid = _mean_valid_depth_mm(image)
    # Lookdown pose over the table: almost every pixel valid, depths between 0.35 and 1.5 m.
    assert valid > 0.9 * 640 * 480
    assert 350 < mean_mm < 1500
    info = infos.latest()
    assert (info.width, info.height) == (640, 480)
    assert abs(info.k[0] - 570.3) < 1e-6 and abs(info.k[4] - 570.3) < 1e-6
    assert info.header.frame_id == "camera_optical"
    imu = imus.wait_for(lambda m: True)
    a = imu.linear_acceleration
    assert abs((a.x ** 2 + a.y ** 2 + a.z ** 2) ** 0.5 - 9.81) < 0.3
    assert imu.header.frame_id == "imu"
    # Default mount (URDF): gravity reaction along imu +z, pitched by the 0.85 rad lookdown tilt.
    assert a.z > 5.0
    assert node.alive()


def test_stamps_are_consistent(ros, start_node):
    images = ros.collect(Image, "/camera/depth/image_raw", qos_profile_sensor_data)
    infos = ros.collect(CameraInfo, "/camera/depth/camera_info", qos_profile_sensor_data)
    imus = ros.collect(Imu, "/imu/data", qos_profile_sensor_data)
    _start(ros, start_node)
    imus.wait_for(lambda m: len(imus.messages) >= 40)
    images.wait_for(lambda m: len(images.messages) >= 5)
    imu_stamps = [_stamp(m) for m in imus.messages]
    assert all(b > a for a, b in zip(imu_stamps, imu_stamps[1:])), "IMU stamps must increase"
    # 100 Hz clock: stamps are multiples of 10 ms after the start (drops only widen a gap).
    gaps = [b - a for a, b in zip(imu_stamps, imu_stamps[1:])]
    assert abs(min(gaps) - 0.01) < 1e-3
    image_stamps = [_stamp(m) for m in images.messages]
    assert all(b > a for a, b in zip(image_stamps, image_stamps[1:]))
    assert abs(min(b - a for a, b in zip(image_stamps, image_stamps[1:])) - 1 / 30) < 1e-3
    # Each image has a CameraInfo with the same stamp, on the IMU's clock.
    infos.wait_for(lambda m: abs(_stamp(m) - image_stamps[-1]) < 1e-6)
    # The images that fall within the IMU samples received lie next to one of them (the first samples
    # of either stream may be lost while its subscription matches, and best-effort drops widen gaps).
    overlap = [t for t in image_stamps if imu_stamps[0] <= t <= imu_stamps[-1]]
    assert overlap, (image_stamps, imu_stamps[0], imu_stamps[-1])
    assert all(min(abs(t - s) for s in imu_stamps) < 0.05 for t in overlap)


def test_place_at_rock_moves_the_robot_and_bad_index_is_ignored(ros, start_node):
    rock = ros.collect(UInt32, "/terrain_sim/rock")
    images = ros.collect(Image, "/camera/depth/image_raw", qos_profile_sensor_data)
    node = _start(ros, start_node)
    assert rock.latest().data == 0
    place = ros.publisher(UInt32, "/terrain_sim/place_at_rock", rock_qos())
    ros.publish_until(place, UInt32(data=2), rock, lambda m: m.data == 2)
    place.publish(UInt32(data=99))
    pw.wait_until(lambda: "no rock with index 99" in node.log(), "the bad index to be rejected")
    rock.clear()
    assert rock.latest().data == 2
    assert node.alive()
    # Still publishing after the bad request.
    images.clear()
    assert images.latest().width == 640


def test_joint_states_move_the_camera(ros, start_node):
    images = ros.collect(Image, "/camera/depth/image_raw", qos_profile_sensor_data)
    _start(ros, start_node)
    joints = ros.publisher(JointState, "/joint_states")
    zero = JointState(name=JOINTS, position=[0.0] * 12)
    ros.wait_for_subscriber(joints)
    joints.publish(zero)
    # Zero angles are the URDF's lookdown pose, the node's pose before any joint state.
    images.clear()
    before = _mean_valid_depth_mm(images.latest())[0]
    # Crouch: knees bent, hips and ankles compensating; the feet stay planted, the head goes down.
    crouch = JointState(name=JOINTS, position=[0.0, 0.0, 0.0, 0.0, -0.4, -0.4, 0.8, 0.8, -0.4, -0.4, 0.0, 0.0])

    def moved(image):
        return abs(_mean_valid_depth_mm(image)[0] - before) > 5.0

    got = ros.publish_until(joints, crouch, images, moved, period=0.3)
    assert moved(got)


def rock_qos():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10,
                      durability=DurabilityPolicy.VOLATILE)
