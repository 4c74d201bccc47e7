"""rosbag2 MCAP bags against an independent implementation, the Python `rosbags` library (its writer,
its reader and the CDR serialisation of its Jazzy typestore):

(a) the TUM fr1_xyz excerpt written as a bag by `rosbags` replays with `patch_mapper replay` to the
    same trajectory as the dataset folder (ATE <= 4 mm against groundtruth.txt);
(b) `terrain_sim record --mcap` is read back by `rosbags` with every message intact;
(c) malformed bags give clear errors naming the topic and message index, skip the bad message and go
    on, and a broken file ends with an error exit code, never a panic.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

import patchwalk_testing as pw
from test_patch_mapper_pipeline import TUM, read_png16, rotation_matrix, tum_params

JAZZY = get_typestore(Stores.ROS2_JAZZY)
T = JAZZY.types
DEPTH, INFO, IMU, GROUNDTRUTH = "/camera/depth/image_raw", "/camera/depth/camera_info", "/imu/data", "/groundtruth"
# TUM's published fr1 intrinsics: what `Dataset::open` uses for a TUM folder without intrinsics.json.
TUM_K = (640, 480, 517.3, 516.5, 318.6, 255.3)


def header(t: float, frame_id: str):
    ns = int(round(t * 1e9))
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame_id)


def image_msg(t: float, depth: np.ndarray, encoding: str, step: int | None = None, data: bytes | None = None):
    height, width = depth.shape
    raw = depth.tobytes() if data is None else data
    return T["sensor_msgs/msg/Image"](
        header=header(t, "camera_optical"), height=height, width=width, encoding=encoding, is_bigendian=0,
        step=step if step is not None else width * depth.itemsize, data=np.frombuffer(raw, dtype=np.uint8),
    )


def camera_info_msg(t: float, fx: float = TUM_K[2]):
    width, height, _, fy, cx, cy = TUM_K
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(t, "camera_optical"), height=height, width=width, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]), r=np.eye(3).flatten(),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    )


def imu_msg(t: float, a: tuple[float, float, float]):
    vector3, quaternion = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    return T["sensor_msgs/msg/Imu"](
        header=header(t, "imu"), orientation=quaternion(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.full(9, -1.0),
        angular_velocity=vector3(x=0.0, y=0.0, z=0.0), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vector3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=np.zeros(9),
    )


def pose_msg(t: float, values: list[float]):
    tx, ty, tz, qx, qy, qz, qw = values
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=tx, y=ty, z=tz), orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)
    )
    return T["geometry_msgs/msg/PoseStamped"](header=header(t, "world"), pose=pose)


def numeric_rows(path: Path) -> list[list[float]]:
    return [[float(v) for v in line.split()] for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


def tum_depth_metres() -> list[tuple[float, np.ndarray]]:
    """The excerpt's frames as 32FC1 metres (value / 5000, 0 -> NaN): the folder replay's depths exactly."""
    frames = []
    for line in (TUM / "depth.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        t, name = line.split()
        raw = read_png16(TUM / name).astype(np.float64)
        metres = np.where(raw > 0, raw * (1.0 / 5000.0), np.nan).astype("<f4")
        frames.append((float(t), metres))
    return frames


def write_bag(path: Path, events: list[tuple[float, str, str, object]]) -> None:
    """Writes (time, topic, type, message) events with rosbags, in time order."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for t, topic, msgtype, msg in sorted(events, key=lambda e: e[0]):
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=JAZZY)
            writer.write(connections[topic], int(round(t * 1e9)), JAZZY.serialize_cdr(msg, msgtype))


def tum_events(frames=None, groundtruth: bool = True) -> list[tuple[float, str, str, object]]:
    events = []
    for t, metres in frames if frames is not None else tum_depth_metres():
        events.append((t, INFO, "sensor_msgs/msg/CameraInfo", camera_info_msg(t)))
        events.append((t, DEPTH, "sensor_msgs/msg/Image", image_msg(t, metres, "32FC1")))
    for t, ax, ay, az in numeric_rows(TUM / "accelerometer.txt"):
        events.append((t, IMU, "sensor_msgs/msg/Imu", imu_msg(t, (ax, ay, az))))
    if groundtruth:
        for row in numeric_rows(TUM / "groundtruth.txt"):
            events.append((row[0], GROUNDTRUTH, "geometry_msgs/msg/PoseStamped", pose_msg(row[0], row[1:])))
    return events


def replay(source: Path, out: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [str(pw.binary("patch_mapper")), "replay", str(source), "--out", str(out), "--picture-every", "0", *args],
        capture_output=True, text=True, timeout=600,
    )
    assert "panicked" not in result.stderr, result.stderr
    if check:
        assert result.returncode == 0, result.stderr
    return result


def stats(out: Path) -> dict:
    return json.loads((out / "stats.json").read_text())


@pytest.fixture(scope="module")
def tum_bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("bags") / "tum_fr1_xyz"
    write_bag(path, tum_events())
    return path


def test_rosbags_tum_bag_replays_like_the_folder(tum_bag, tmp_path):
    params = tum_params()
    replay(TUM, tmp_path / "folder", *params)
    bag_run = replay(tum_bag, tmp_path / "bag", *params)
    folder_poses = numeric_rows(tmp_path / "folder" / "trajectory.txt")
    bag_poses = numeric_rows(tmp_path / "bag" / "trajectory.txt")
    assert len(folder_poses) == len(bag_poses) == 37
    # The tracker's constant-velocity prediction scales the last step by the ratio of the frame
    # intervals, taken from the stamps: the bag holds them in nanoseconds, the folder in decimal
    # seconds, so ICP starts from predictions that differ by that rounding and ends within 0.1 mm
    # (identical with tracker.motion_prior.constant_velocity=false).
    for folder_row, bag_row in zip(folder_poses, bag_poses):
        assert max(abs(a - b) for a, b in zip(folder_row, bag_row)) < 1e-4, (folder_row, bag_row)
    folder_stats, bag_stats = stats(tmp_path / "folder"), stats(tmp_path / "bag")
    # The bag's ground truth comes from its /groundtruth topic, the folder's from groundtruth.txt.
    assert bag_stats["ate_frames"] == folder_stats["ate_frames"] == 37
    assert bag_stats["ate_m"] <= 0.004 and folder_stats["ate_m"] <= 0.004, (bag_stats, folder_stats)
    assert abs(bag_stats["ate_m"] - folder_stats["ate_m"]) < 1e-5
    assert bag_stats["messages_skipped"] == 0 and bag_stats["frames_skipped"] == 0
    print(f"TUM bag replay: {bag_stats['frames_per_s']:.2f} frames/s, ATE {bag_stats['ate_m'] * 1e3:.2f} mm; "
          f"folder {folder_stats['frames_per_s']:.2f} frames/s")
    assert "frames/s" in bag_run.stdout
    # The single .mcap file of the bag directory, with ground truth from a TUM file instead of the topic.
    mcap = next(tum_bag.glob("*.mcap"))
    replay(mcap, tmp_path / "file", *params, "--max-frames", "3", "--groundtruth-topic", "/none", "--groundtruth", str(TUM / "groundtruth.txt"))
    assert numeric_rows(tmp_path / "file" / "trajectory.txt") == bag_poses[:3]


def test_terrain_sim_bag_reads_back_in_rosbags(tmp_path):
    frames = 10
    for encoding, target in (("16UC1", tmp_path / "sim.mcap"), ("32FC1", tmp_path / "sim_bag")):
        subprocess.run(
            [str(pw.binary("terrain_sim")), "record", "--mcap", str(target), "--frames", str(frames), "--depth-encoding", encoding],
            check=True, capture_output=True, text=True, timeout=300,
        )
        scene = json.loads(subprocess.run([str(pw.binary("terrain_sim")), "scene"], check=True, capture_output=True, text=True).stdout)
        imu_samples = math.floor((frames - 1) / 30 * 100) + 1
        # rosbags' own reader with the real Jazzy definitions (wire format) ...
        with Reader(target) as reader:
            counts = {c.topic: c.msgcount for c in reader.connections}
            types = {c.topic: c.msgtype for c in reader.connections}
            assert counts == {DEPTH: frames, INFO: frames, IMU: imu_samples, "/tf_static": 1, GROUNDTRUTH: frames}
            assert types[DEPTH] == "sensor_msgs/msg/Image" and types["/tf_static"] == "tf2_msgs/msg/TFMessage"
            messages = {topic: [] for topic in counts}
            for connection, timestamp, raw in reader.messages():
                msg = JAZZY.deserialize_cdr(raw, connection.msgtype)
                messages[connection.topic].append((timestamp, msg))
        for index, (timestamp, image) in enumerate(messages[DEPTH]):
            stamp_ns = image.header.stamp.sec * 10**9 + image.header.stamp.nanosec
            assert stamp_ns == timestamp == round(index / 30 * 1e9)
            info = messages[INFO][index][1]
            assert (image.width, image.height) == (info.width, info.height) and image.width > 0
            assert image.encoding == encoding and image.is_bigendian == 0
            assert image.step == image.width * (2 if encoding == "16UC1" else 4) and len(image.data) == image.height * image.step
            depth = np.frombuffer(image.data.tobytes(), dtype="<u2" if encoding == "16UC1" else "<f4").astype(np.float64)
            valid = depth[(depth > 0) & np.isfinite(depth)] * (0.001 if encoding == "16UC1" else 1.0)
            assert valid.size > 0.3 * depth.size and 0.2 < np.median(valid) < 2.0
            assert info.k[0] > 0 and info.k[8] == 1.0 and image.header.frame_id == info.header.frame_id == "camera_optical"
            gt_stamp = messages[GROUNDTRUTH][index][1].header.stamp
            assert (gt_stamp.sec, gt_stamp.nanosec) == (image.header.stamp.sec, image.header.stamp.nanosec)
        imu_stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in messages[IMU]]
        assert imu_stamps == pytest.approx([i / 100 for i in range(imu_samples)], abs=1e-9)
        assert all(abs(np.linalg.norm([m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]) - 9.81) < 0.5
                   for _, m in messages[IMU])
        (_, tf), = messages["/tf_static"]
        mounts = {(t.header.frame_id, t.child_frame_id): t.transform for t in tf.transforms}
        assert set(mounts) == {("base_link", "camera_optical"), ("camera_optical", "imu")}
        base_from_camera = mounts[("base_link", "camera_optical")]
        assert [base_from_camera.translation.x, base_from_camera.translation.y, base_from_camera.translation.z] == \
            pytest.approx(scene["base_from_camera"]["translation"], abs=1e-12)
        r = base_from_camera.rotation
        assert [r.x, r.y, r.z, r.w] == pytest.approx(scene["base_from_camera"]["rotation_xyzw"], abs=1e-12)
        # The IMU mount is the one the mapper is configured with for the simulated rig.
        imu_mount = mounts[("camera_optical", "imu")].rotation
        configured = next(line for line in (pw.REPO / "config" / "patch_mapper_sim.yaml").read_text().splitlines() if "camera_from_imu" in line)
        matrix = json.loads(configured.split(":", 1)[1].split("#")[0].strip())
        assert np.allclose(rotation_matrix(imu_mount.x, imu_mount.y, imu_mount.z, imu_mount.w), matrix, atol=1e-6)
        # ... and the schemas the bag carries are enough on their own (an empty typestore learns them).
        with AnyReader([target], default_typestore=get_typestore(Stores.EMPTY)) as reader:
            decoded = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()]
            assert len(decoded) == sum(counts.values())
    # The simulated bag replays, with its ground truth from /groundtruth.
    out = tmp_path / "replay"
    replay(tmp_path / "sim.mcap", out, "--config", str(pw.REPO / "config" / "patch_mapper_sim.yaml"))
    assert stats(out)["ate_frames"] == frames and stats(out)["frames"] == frames


def test_malformed_messages_are_skipped_with_their_topic_and_index(tmp_path):
    frames = tum_depth_metres()[:6]
    events = [e for e in tum_events(frames, groundtruth=False) if e[1] != INFO]
    for index, (t, metres) in enumerate(frames):
        # CameraInfo 1 has NaN intrinsics (the others are good).
        events.append((t, INFO, "sensor_msgs/msg/CameraInfo", camera_info_msg(t, fx=math.nan if index == 1 else TUM_K[2])))
    t2, metres2 = frames[2]
    t3, metres3 = frames[3]
    # Depth 2's data is shorter than height × step; depth 3 is an RGB image.
    events = [e for e in events if not (e[1] == DEPTH and e[0] in (t2, t3))]
    events.append((t2, DEPTH, "sensor_msgs/msg/Image", image_msg(t2, metres2, "32FC1", data=metres2.tobytes()[:1000])))
    events.append((t3, DEPTH, "sensor_msgs/msg/Image", image_msg(t3, np.zeros((480, 640), dtype=np.uint8), "rgb8", step=1920,
                                                                data=bytes(480 * 1920))))
    bag = tmp_path / "bad_messages"
    write_bag(bag, events)
    out = tmp_path / "out"
    result = replay(bag, out, *tum_params())
    assert f"topic {DEPTH} message 2: data is 1000 bytes, shorter than height × step = 480 × 2560 = 1228800" in result.stderr
    assert f'topic {DEPTH} message 3: encoding "rgb8" is not a depth encoding' in result.stderr
    assert f"topic {INFO} message 1: invalid intrinsics: fx = NaN must be positive and finite" in result.stderr
    assert stats(out)["frames"] == 4 and stats(out)["messages_skipped"] == 3
    assert len(numeric_rows(out / "trajectory.txt")) == 4


def test_schema_mismatch_and_unknown_encoding_name_the_topic(tmp_path):
    frames = tum_depth_metres()[:3]
    # The depth topic carries IMU messages: nothing to replay, an error exit naming the topic and message.
    events = [e for e in tum_events(frames, groundtruth=False) if e[1] != DEPTH]
    events += [(t, DEPTH, "sensor_msgs/msg/Imu", imu_msg(t, (0.0, 0.0, 9.8))) for t, _ in frames]
    bag = tmp_path / "schema_mismatch"
    write_bag(bag, events)
    result = replay(bag, tmp_path / "out1", check=False)
    assert result.returncode == 1
    assert f'no usable depth images on topic {DEPTH} (first problem: topic {DEPTH} message 0: schema "sensor_msgs/msg/Imu" ' \
           f"is not the expected sensor_msgs/msg/Image)" in result.stderr, result.stderr
    # The IMU channel's message encoding is not CDR: its messages are skipped, the frames replay.
    bag = tmp_path / "unknown_encoding"
    write_bag(bag, tum_events(frames, groundtruth=False))
    mcap = next(bag.glob("*.mcap"))
    topic = IMU.encode()
    pattern = len(topic).to_bytes(4, "little") + topic + b"\x03\x00\x00\x00cdr"
    data = mcap.read_bytes()
    assert pattern in data
    mcap.write_bytes(data.replace(pattern, pattern[:-3] + b"xdr"))
    out = tmp_path / "out2"
    result = replay(bag, out, *tum_params())
    assert f'topic {IMU} message 0: message encoding "xdr" is not cdr' in result.stderr
    assert f"more messages of {IMU}" in result.stderr
    assert stats(out)["frames"] == 3


def test_broken_files_end_with_an_error_exit_code(tmp_path):
    bag = tmp_path / "sim.mcap"
    subprocess.run([str(pw.binary("terrain_sim")), "record", "--mcap", str(bag), "--frames", "12", "--compression", "none"],
                   check=True, capture_output=True, timeout=300)
    data = bag.read_bytes()
    config = ["--config", str(pw.REPO / "config" / "patch_mapper_sim.yaml")]
    # Cut in the middle of the data section: the frames before the cut are replayed, then an error exit.
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    result = replay(cut, tmp_path / "out_cut", *config, check=False)
    assert result.returncode == 1, result.stderr
    assert "could not be read to its end" in result.stderr and str(cut) in result.stderr
    assert 0 < stats(tmp_path / "out_cut")["frames"] < 12
    # Garbage, an empty file, a file cut inside its header: error exits naming the file.
    for name, content in (("garbage.mcap", b"\x89MCAP0\r\nthis is not an mcap file" * 10), ("empty.mcap", b""), ("short.mcap", data[:20])):
        path = tmp_path / name
        path.write_bytes(content)
        result = replay(path, tmp_path / f"out_{name}", *config, check=False)
        assert result.returncode == 1, (name, result.stderr)
        assert str(path) in result.stderr, (name, result.stderr)
    # A bag directory whose metadata.yaml names another storage.
    directory = tmp_path / "sqlite_bag"
    directory.mkdir()
    (directory / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  storage_identifier: sqlite3\n  relative_file_paths: [a.db3]\n")
    result = replay(directory, tmp_path / "out_sqlite", check=False)
    assert result.returncode == 1 and 'storage "sqlite3" is not supported' in result.stderr
