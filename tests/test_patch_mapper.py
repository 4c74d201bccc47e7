"""patch_mapper over ROS 2: depth/CameraInfo/IMU are received and counted in MapperStatus, reset
answers, large images go through, malformed images are rejected without stopping the node."""

from sensor_msgs.msg import CameraInfo, Image, Imu
from std_srvs.srv import Trigger
from patchwalk_msgs.msg import MapperStatus

import patchwalk_testing as pw


def _status(ros):
    return ros.collect(MapperStatus, "/patch_mapper/status")


def test_status_is_published_with_zero_counters(ros, patch_mapper):
    status = _status(ros).latest()
    assert status.frames_received == 0 and status.frames_processed == 0
    assert status.stamp.sec > 0


def test_depth_image_is_received_and_processed(ros, patch_mapper):
    status = _status(ros)
    info_pub = ros.publisher(CameraInfo, "/camera/depth/camera_info")
    ros.publish_until(info_pub, pw.camera_info(64, 48), status, lambda s: s.camera_infos_received >= 1)
    depth_pub = ros.publisher(Image, "/camera/depth/image_raw")
    got = ros.publish_until(depth_pub, pw.depth_image_16uc1(64, 48), status, lambda s: s.frames_processed >= 1)
    assert got.frames_received >= got.frames_processed >= 1
    assert got.frames_rejected == 0


def test_32fc1_depth_is_accepted(ros, patch_mapper):
    status = _status(ros)
    info_pub = ros.publisher(CameraInfo, "/camera/depth/camera_info")
    ros.publish_until(info_pub, pw.camera_info(32, 24), status, lambda s: s.camera_infos_received >= 1)
    depth_pub = ros.publisher(Image, "/camera/depth/image_raw")
    got = ros.publish_until(depth_pub, pw.depth_image_32fc1(32, 24), status, lambda s: s.frames_processed >= 1)
    assert got.frames_rejected == 0


def test_large_640x480_16uc1_image_goes_through(ros, patch_mapper):
    status = _status(ros)
    info_pub = ros.publisher(CameraInfo, "/camera/depth/camera_info")
    ros.publish_until(info_pub, pw.camera_info(640, 480), status, lambda s: s.camera_infos_received >= 1)
    depth_pub = ros.publisher(Image, "/camera/depth/image_raw")
    image = pw.depth_image_16uc1(640, 480)
    assert len(image.data) == 640 * 480 * 2
    got = ros.publish_until(depth_pub, image, status, lambda s: s.frames_processed >= 1)
    assert got.frames_rejected == 0


def test_imu_is_counted(ros, patch_mapper):
    status = _status(ros)
    imu = Imu()
    imu.header.frame_id = "imu"
    imu.linear_acceleration.z = 9.81
    imu_pub = ros.publisher(Imu, "/imu/data")
    got = ros.publish_until(imu_pub, imu, status, lambda s: s.imu_received >= 1)
    assert got.imu_received >= 1


def test_malformed_images_are_rejected_and_the_node_keeps_working(ros, patch_mapper):
    status = _status(ros)
    info_pub = ros.publisher(CameraInfo, "/camera/depth/camera_info")
    ros.publish_until(info_pub, pw.camera_info(64, 48), status, lambda s: s.camera_infos_received >= 1)
    depth_pub = ros.publisher(Image, "/camera/depth/image_raw")

    wrong_encoding = pw.depth_image_16uc1(64, 48)
    wrong_encoding.encoding = "rgb8"
    got = ros.publish_until(depth_pub, wrong_encoding, status, lambda s: s.frames_rejected >= 1)
    assert "rgb8" in got.last_error

    too_short = pw.depth_image_16uc1(64, 48)
    too_short.data = bytes(too_short.data[: len(too_short.data) // 2])
    got = ros.publish_until(depth_pub, too_short, status, lambda s: "bytes" in s.last_error)
    assert got.frames_rejected >= 2

    wrong_size = pw.depth_image_16uc1(32, 48)  # valid image, but not what CameraInfo says
    got = ros.publish_until(depth_pub, wrong_size, status, lambda s: "CameraInfo says" in s.last_error)

    bad_step = pw.depth_image_16uc1(64, 48)
    bad_step.step = 10
    ros.publish_until(depth_pub, bad_step, status, lambda s: "row step" in s.last_error)

    assert patch_mapper.alive()
    got = ros.publish_until(depth_pub, pw.depth_image_16uc1(64, 48), status, lambda s: s.frames_processed >= 1)
    assert got.frames_processed >= 1 and patch_mapper.alive()


def test_reset_answers(ros, patch_mapper):
    response = ros.call(Trigger, "/patch_mapper/reset")
    assert response.success
    assert "cleared" in response.message
