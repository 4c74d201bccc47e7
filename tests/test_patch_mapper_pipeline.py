"""patch_mapper end to end over ROS 2 on real recorded data: the TUM fr1_xyz excerpt (tests/data) is
published as 16UC1 depth + CameraInfo + IMU with its own stamps; the node must publish a PatchArray in
the tracker's `odom` frame with sane patches, and keep publishing after bad messages are injected."""

from __future__ import annotations

import math
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, Image, Imu, PointCloud2
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray
from patchwalk_msgs.msg import MapperStatus, PatchArray

import patchwalk_testing as pw

TUM = Path(__file__).parent / "data" / "tum_fr1_xyz"
# camera_from_imu of the TUM Kinect, from `calibration::calibrate_dataset` on this excerpt (J 2.2
# Procrustes; quaternion x, y, z, w).
TUM_CAMERA_FROM_IMU_XYZW = (-0.015746670364592534, 0.020181442753723376, 0.9996718027836491, -0.0010190486230470933)


def rotation_matrix(x: float, y: float, z: float, w: float) -> list[list[float]]:
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def read_png16(path: Path) -> np.ndarray:
    """16-bit greyscale PNG -> uint16 array (no third-party decoder in the test venv)."""
    data = path.read_bytes()
    pos, idat, width, height = 8, b"", 0, 0
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            assert (depth, colour, interlace) == (16, 0, 0), f"{path}: not a 16-bit greyscale PNG"
        elif kind == b"IDAT":
            idat += body
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(height, 1 + 2 * width)
    out = np.zeros((height, 2 * width), dtype=np.uint8)
    previous = np.zeros(2 * width, dtype=np.uint8)
    for row in range(height):
        kind, line = raw[row, 0], raw[row, 1:]
        if kind == 0:
            recon = line.copy()
        elif kind == 1:  # Sub: per byte lane (2 bytes per pixel) a running sum mod 256
            recon = np.empty_like(line)
            recon[0::2] = np.cumsum(line[0::2], dtype=np.uint8)
            recon[1::2] = np.cumsum(line[1::2], dtype=np.uint8)
        elif kind == 2:  # Up
            recon = line + previous
        else:  # Average / Paeth: sequential
            recon = np.zeros_like(line)
            for i in range(line.size):
                a = int(recon[i - 2]) if i >= 2 else 0
                b = int(previous[i])
                c = int(previous[i - 2]) if i >= 2 else 0
                if kind == 3:
                    pred = (a + b) // 2
                else:
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                recon[i] = (int(line[i]) + pred) & 0xFF
        out[row] = recon
        previous = recon
    return out.view(">u2").astype(np.uint16).reshape(height, width)


def stamp(msg, seconds: float) -> None:
    msg.header.stamp.sec = int(seconds)
    msg.header.stamp.nanosec = int(round((seconds - int(seconds)) * 1e9)) % 1_000_000_000


def tum_frames() -> list[tuple[float, np.ndarray]]:
    frames = []
    for line in (TUM / "depth.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        t, name = line.split()
        # TUM depth: metres = value / 5000 -> millimetres for 16UC1.
        depth_mm = np.round(read_png16(TUM / name).astype(np.float64) / 5.0).astype("<u2")
        frames.append((float(t), depth_mm))
    return frames


def tum_accelerometer() -> list[tuple[float, float, float, float]]:
    rows = []
    for line in (TUM / "accelerometer.txt").read_text().splitlines():
        if not line.startswith("#") and line.strip():
            rows.append(tuple(float(v) for v in line.split()))
    return rows


def depth_msg(t: float, depth_mm: np.ndarray) -> Image:
    msg = Image()
    stamp(msg, t)
    msg.header.frame_id = "camera_optical"
    msg.height, msg.width = depth_mm.shape
    msg.encoding = "16UC1"
    msg.step = depth_mm.shape[1] * 2
    msg.data = depth_mm.astype("<u2").tobytes()
    return msg


def imu_msg(t: float, ax: float, ay: float, az: float) -> Imu:
    msg = Imu()
    stamp(msg, t)
    msg.header.frame_id = "imu"
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = ax, ay, az
    return msg


def tum_camera_info() -> CameraInfo:
    # TUM's published fr1 depth intrinsics (tests/data/README.md).
    msg = pw.camera_info(640, 480)
    fx, fy, cx, cy = 517.3, 516.5, 318.6, 255.3
    msg.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]
    msg.p = [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def tum_params() -> list[str]:
    matrix = rotation_matrix(*TUM_CAMERA_FROM_IMU_XYZW)
    params = {
        "ros.status_period_s": "0.1",
        # The Kinect is ~1 m from the desk: a 2.56 m volume at 1 cm voxels; the desk fills the view.
        "tracker.tsdf.voxel_size_m": "0.01",
        "tracker.tsdf.size_m": "2.56",
        "mapper.volume_edge_m": "2.56",
        "mapper.saliency.fixation_radius_m": ".inf",
        "mapper.time_limit_ms": ".inf",
        # More, smaller cells than J's Vg = 8: most seeds on the cluttered desk fail J's coverage test.
        "mapper.seeds.cells_per_side": "16",
        "mapper.seeds.per_cell": "2",
        "mapper.seeds.max_seeds": "256",
        "mapper.acquire.camera_from_imu": str(matrix),
        # The data set has no TF: its IMU mount is the calibrated matrix above, used at once.
        "ros.tf.extrinsics_from_tf": "false",
    }
    return [arg for key, value in params.items() for arg in ("--param", f"{key}={value}")]


class Player:
    """Publishes the TUM excerpt: CameraInfo, then per depth frame the IMU samples up to its stamp."""

    def __init__(self, ros):
        self.ros = ros
        self.info = ros.publisher(CameraInfo, "/camera/depth/camera_info")
        self.depth = ros.publisher(Image, "/camera/depth/image_raw")
        self.imu = ros.publisher(Imu, "/imu/data")
        self.frames = tum_frames()
        self.accel = tum_accelerometer()
        self.next_imu = 0
        self.last_imu_stamp = -math.inf
        for publisher in (self.info, self.depth, self.imu):
            ros.wait_for_subscriber(publisher)

    def play(self, period_s: float, time_offset: float = 0.0) -> None:
        self.next_imu = 0
        self.last_imu_stamp = -math.inf
        for t, depth_mm in self.frames:
            self.info.publish(tum_camera_info())
            self.publish_imu_until(t + 0.03, time_offset)
            self.depth.publish(depth_msg(t + time_offset, depth_mm))
            time.sleep(period_s)

    def publish_imu_until(self, until: float, time_offset: float) -> None:
        # Every 4th sample (~200 Hz) so best-effort queues are not flooded; repeated stamps skipped.
        while self.next_imu < len(self.accel) and self.accel[self.next_imu][0] <= until:
            t, ax, ay, az = self.accel[self.next_imu]
            if self.next_imu % 4 == 0 and t > self.last_imu_stamp:
                self.imu.publish(imu_msg(t + time_offset, ax, ay, az))
                self.last_imu_stamp = t
                time.sleep(0.0005)
            self.next_imu += 1


def check_patch_array(array: PatchArray) -> None:
    assert array.header.frame_id == "odom"
    q = array.camera_pose.orientation
    assert abs(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w - 1.0) < 1e-6
    for patch in array.patches:
        assert 0 <= patch.surface <= 6 and 0 <= patch.boundary <= 3
        values = [*patch.curvatures, *patch.boundary_params, *patch.rotation, *patch.center, patch.residual]
        assert all(math.isfinite(v) for v in values), patch
        p = math.isqrt(len(patch.covariance))
        assert p * p == len(patch.covariance) and p >= len(patch.boundary_params) + len(patch.curvatures) + 5
        assert all(math.isfinite(v) for v in patch.covariance)
        # Diagonal of a covariance: non-negative.
        assert all(patch.covariance[i * p + i] >= 0.0 for i in range(p))
        assert 0.0 <= patch.residual < 0.05 and patch.num_points > 0
        assert (patch.first_seen.sec, patch.first_seen.nanosec) <= (patch.last_seen.sec, patch.last_seen.nanosec)


@pytest.fixture
def tum_mapper(ros, start_node):
    node = start_node("patch_mapper", *tum_params())
    ros.wait_for_nodes("/patch_mapper")
    return node


def test_tum_sequence_gives_a_patch_array_in_the_map_frame(ros, tum_mapper):
    arrays = ros.collect(PatchArray, "/patch_mapper/patches")
    status = ros.collect(MapperStatus, "/patch_mapper/status")
    player = Player(ros)
    player.play(period_s=0.1)
    array = arrays.wait_for(lambda a: len(a.patches) >= 1, timeout=30.0)
    check_patch_array(array)
    # The camera looks down at the desk: patches lie below the camera in the z-up map frame.
    camera_z = array.camera_pose.position.z
    assert all(p.center[2] < camera_z for p in array.patches)
    got = status.wait_for(lambda s: s.frames_processed >= 10 and s.patches_in_map >= 1 and "total" in s.timing_names)
    assert len(got.timing_names) == len(got.timing_ms)
    assert tum_mapper.alive()


def test_markers_and_birds_eye_cloud_reach_their_subscribers(ros, tum_mapper):
    # The node builds them only while a subscription is matched (counted every status period).
    markers = ros.collect(MarkerArray, "/patch_mapper/markers")
    clouds = ros.collect(PointCloud2, "/patch_mapper/birds_eye_cloud")
    Player(ros).play(period_s=0.1)
    array = markers.wait_for(lambda m: len(m.markers) >= 1, timeout=30.0)
    assert all(m.header.frame_id == "odom" for m in array.markers)
    cloud = clouds.wait_for(lambda c: c.width * c.height > 0, timeout=30.0)
    assert cloud.header.frame_id == "odom" and len(cloud.data) == cloud.row_step * cloud.height
    assert tum_mapper.alive()


def test_bad_messages_do_not_stop_the_node(ros, tum_mapper):
    arrays = ros.collect(PatchArray, "/patch_mapper/patches")
    status = ros.collect(MapperStatus, "/patch_mapper/status")
    player = Player(ros)
    t0, depth_mm = player.frames[0]
    # Depth before any CameraInfo: skipped.
    ros.publish_until(player.depth, depth_msg(t0 - 10.0, depth_mm), status, lambda s: s.frames_skipped >= 1)
    player.info.publish(tum_camera_info())
    player.publish_imu_until(t0 + 0.03, 0.0)
    bad = [
        ("wrong encoding", lambda m: setattr(m, "encoding", "rgb8")),
        ("wrong size", lambda m: (setattr(m, "width", 320), setattr(m, "step", 640), setattr(m, "data", bytes(m.data[: 320 * 2 * 480])))),
        ("truncated", lambda m: setattr(m, "data", bytes(m.data[:1000]))),
        ("all zero", lambda m: setattr(m, "data", bytes(len(m.data)))),
    ]
    for _, corrupt in bad:
        msg = depth_msg(t0, depth_mm)
        corrupt(msg)
        player.depth.publish(msg)
        time.sleep(0.05)
    # NaN depth as 32FC1.
    nan = Image()
    stamp(nan, t0)
    nan.height, nan.width, nan.encoding, nan.step = 480, 640, "32FC1", 640 * 4
    nan.data = np.full((480, 640), np.nan, dtype="<f4").tobytes()
    player.depth.publish(nan)
    # IMU garbage and an out-of-order sample.
    player.imu.publish(imu_msg(t0, float("nan"), 0.0, 0.0))
    player.imu.publish(imu_msg(t0 - 5.0, 0.0, 9.8, 0.0))
    # A good frame, then the same stamp again (duplicate) and an older one (out of order).
    player.depth.publish(depth_msg(t0, depth_mm))
    time.sleep(0.3)
    player.depth.publish(depth_msg(t0, depth_mm))
    time.sleep(0.3)
    player.depth.publish(depth_msg(t0 - 1.0, depth_mm))
    time.sleep(0.3)
    # A frame 100 s later without IMU samples around it: IMU gap (repeated: best-effort may drop one).
    got = ros.publish_until(player.depth, depth_msg(t0 + 100.0, depth_mm), status, lambda s: "IMU gap" in s.last_error)
    got = status.wait_for(lambda s: s.frames_rejected >= 2 and s.frames_skipped >= 3)
    assert got.last_error
    assert tum_mapper.alive()
    # Reset, then the sequence again: the node still maps and publishes.
    assert ros.call(Trigger, "/patch_mapper/reset").success
    arrays.clear()
    player.play(period_s=0.1, time_offset=200.0)
    array = arrays.wait_for(lambda a: a.header.stamp.sec >= int(t0 + 200.0), timeout=30.0)
    check_patch_array(array)
    assert tum_mapper.alive()
    assert "panicked" not in tum_mapper.log()
