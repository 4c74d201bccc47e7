#!/usr/bin/env python3
"""Latency and CPU bench of patch_mapper on terrain_sim's 30 Hz Carmine-like stream.

Starts terrain_sim and patch_mapper (release binaries, DDS on loopback, a private ROS domain), waits
until the patch map holds at least --min-patches patches, then for --seconds measures:
  - end to end: PatchArray arrival (wall clock) minus its header stamp (= the depth frame's stamp,
    terrain_sim's nominal frame time, before it renders the frame): render + DDS in + pipeline + DDS out;
  - through DDS: PatchArray arrival minus the arrival of its depth frame at this process (which
    subscribes to the images too): DDS in + pipeline + DDS out, without the simulator's rendering;
  - in node: MapperStatus `depth_in_to_patches_out` (depth message taken from DDS -> PatchArray
    published) and the per-stage timings, sampled from every status message;
  - CPU per node from /proc/<pid>/stat (utime + stime over the window, % of one core).
Prints p50/p99; asserts nothing.

With --bag, a recorded rosbag2 MCAP bag (e.g. `terrain_sim record --terrain <heightmap.png> --mcap
walk.mcap --compression none`) is played instead of running terrain_sim: this process publishes its
depth images, camera infos and IMU samples at the recorded pace, restamped to the wall clock, so the
rendering of a large terrain does not take the CPU the mapper is measured on. The bag is played by a
second process (this script with --play), so that reading and publishing the images does not hold
the interpreter lock of the process that timestamps the PatchArray arrivals. "Through DDS" is then
PatchArray arrival minus the publication of its depth frame.

Usage: .venv/bin/python launch_scripts/bench_patch_mapper.py [--seconds 20] [--min-patches 100] [--bag walk.mcap]
(build first: cargo build --release -p patch_mapper -p terrain_sim).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
import patchwalk_testing as pw  # noqa: E402

# The --play process inherits the environment (ROS domain, DDS profile) of the bench that started it.
PLAYER_MARK = "PATCHWALK_BENCH_PLAYER"
if os.environ.get(PLAYER_MARK):
    LOG_DIR = Path(os.environ["ROS_LOG_DIR"])
    ENV = dict(os.environ)
else:
    LOG_DIR = Path(tempfile.mkdtemp(prefix="bench_patch_mapper_"))
    ENV = pw.ros_environment(LOG_DIR)
    os.environ.update(ENV)  # before rclpy is imported

# patch_mapper's configuration for the simulated rig (terrain_sim's IMU mount).
SIM_MAPPER_CONFIG = REPO / "config" / "patch_mapper_sim.yaml"


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    # utime, stime are fields 14, 15 (1-based) of the whole line; after ")" they are 12, 13 (1-based).
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def percentiles(values: list[float]) -> str:
    if not values:
        return "no samples"
    ordered = sorted(values)
    pick = lambda p: ordered[min(len(ordered) - 1, round((len(ordered) - 1) * p))]  # noqa: E731
    return f"p50 {pick(0.5):7.2f} ms  p99 {pick(0.99):7.2f} ms  max {ordered[-1]:7.2f} ms  (n = {len(ordered)})"


def play_bag(harness, bag: Path, published) -> None:
    """Publishes the bag's depth images, camera infos and IMU samples at their recorded pace, each
    stamp replaced by the wall-clock time of its slot (the CDR header's stamp, bytes 4..12, patched
    in the serialized message), and reports each depth frame's stamp and publication time
    (`published((sec, nanosec), wall_s)`) when it is out. The messages are read into memory first,
    so that reading and parsing the bag does not take CPU while the mapper is measured (a camera
    driver publishes what it has)."""
    from experiment import with_header_stamp
    from rclpy.qos import qos_profile_sensor_data
    from rosbags.highlevel import AnyReader
    from sensor_msgs.msg import CameraInfo, Image, Imu

    types = {"sensor_msgs/msg/Image": Image, "sensor_msgs/msg/CameraInfo": CameraInfo, "sensor_msgs/msg/Imu": Imu}
    publishers = {}
    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.msgtype in types]
        with harness._lock:
            for c in connections:
                publishers[c.topic] = harness.node.create_publisher(types[c.msgtype], c.topic, qos_profile_sensor_data)
        messages = [(c.topic, c.msgtype, bag_ns, raw) for c, bag_ns, raw in reader.messages(connections=connections)]
        time.sleep(1.0)  # discovery of the mapper's subscriptions
        start_wall, start_bag = time.time() + 0.1, None
        for topic, msgtype, bag_ns, raw in messages:
            start_bag = bag_ns if start_bag is None else start_bag
            slot = start_wall + (bag_ns - start_bag) * 1e-9
            delay = slot - time.time()
            if delay > 0:
                time.sleep(delay)
            sec, nanosec = int(slot), int((slot - int(slot)) * 1e9)
            publishers[topic].publish(with_header_stamp(raw, sec, nanosec))
            if msgtype == "sensor_msgs/msg/Image":
                published((sec, nanosec), time.time())


def player_main(bag: Path) -> int:
    """The --play process: plays `bag` (see `play_bag`) and prints `sec nanosec wall_s` per depth frame."""
    harness = pw.RosHarness("bench_patch_mapper_player")
    try:
        harness.wait_for_nodes("/patch_mapper")
        play_bag(harness, bag, lambda stamp, wall: print(f"{stamp[0]} {stamp[1]} {wall:.6f}", flush=True))
    finally:
        harness.shutdown()
    return 0


def read_player(player, published) -> None:
    """Hands each depth frame the --play process reports to `published((sec, nanosec), wall_s)`."""
    for line in player.stdout:
        fields = line.split()
        if len(fields) == 3:
            published((int(fields[0]), int(fields[1])), float(fields[2]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--min-patches", type=int, default=100)
    parser.add_argument("--param", action="append", default=[], help="extra patch_mapper --param")
    parser.add_argument("--sim-param", action="append", default=[],
                        help="extra terrain_sim -p, e.g. scene.terrain.path=<heightmap.png> to walk over a terrain")
    parser.add_argument("--bag", type=Path, help="play this MCAP bag instead of running terrain_sim")
    parser.add_argument("--cells-per-side", type=int, default=16, help="mapper.seeds.cells_per_side")
    parser.add_argument("--play", type=Path, help=argparse.SUPPRESS)  # the bag player process
    args = parser.parse_args()
    if args.play:
        return player_main(args.play)

    from experiment import header_stamp
    from patchwalk_msgs.msg import MapperStatus, PatchArray
    from sensor_msgs.msg import Image

    mapper_params = {
        "ros.status_period_s": "0.05",
        # More cells than J's Vg = 8 (8 cm instead of 16 cm) so the map holds >= 100 foot-size patches.
        "mapper.seeds.cells_per_side": str(args.cells_per_side),
        "mapper.seeds.per_cell": "2",
        "mapper.seeds.max_seeds": "128",
    }
    mapper_args = ["--config", str(SIM_MAPPER_CONFIG)]
    mapper_args += [a for k, v in mapper_params.items() for a in ("--param", f"{k}={v}")]
    mapper_args += [a for p in args.param for a in ("--param", p)]
    harness = pw.RosHarness("bench_patch_mapper")
    sim = None if args.bag else pw.NodeProcess("terrain_sim", ["run", *[a for p in args.sim_param for a in ("-p", p)]], ENV, LOG_DIR)
    mapper = pw.NodeProcess("patch_mapper", ["run", *mapper_args], ENV, LOG_DIR)
    nodes = [n for n in (sim, mapper) if n is not None]
    player = None  # the --play process
    lock = threading.Lock()
    arrivals: list[tuple[float, float, int, int]] = []  # (arrival wall s, stamp s, patches, serialized bytes)
    statuses: list = []
    depth_arrivals: dict[tuple[int, int], float] = {}  # depth stamp (sec, nanosec) -> arrival wall s
    through_dds: list[float] = []  # PatchArray arrival - its depth frame's arrival (ms)

    patches_in_map = [0]  # from the latest status message

    def on_patches(raw: bytes):
        # Serialized (raw=True): the arrival is not delayed by building a Python object per field of
        # every patch, which is this process's cost, not the mapper's. Stamp from the CDR header.
        now = time.time()
        sec, nanosec = header_stamp(raw)
        with lock:
            arrivals.append((now, sec + nanosec * 1e-9, patches_in_map[0], len(raw)))
            depth_arrival = depth_arrivals.pop((sec, nanosec), None)
            if depth_arrival is not None:
                through_dds.append((now - depth_arrival) * 1e3)

    def depth_seen(stamp: tuple[int, int], at: float):
        """A depth frame arrived here (from terrain_sim) or was published (from the bag) at wall time `at`."""
        with lock:
            depth_arrivals[stamp] = at
            while len(depth_arrivals) > 300:  # frames the mapper skipped
                depth_arrivals.pop(next(iter(depth_arrivals)))

    def on_depth(msg):
        depth_seen((msg.header.stamp.sec, msg.header.stamp.nanosec), time.time())

    def on_status(msg):
        with lock:
            statuses.append(msg)
            patches_in_map[0] = msg.patches_in_map

    try:
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

        qos = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10,
                         durability=DurabilityPolicy.VOLATILE)
        with harness._lock:
            harness.node.create_subscription(PatchArray, "/patch_mapper/patches", on_patches, qos, raw=True)
            harness.node.create_subscription(MapperStatus, "/patch_mapper/status", on_status, qos)
            if not args.bag:
                harness.node.create_subscription(Image, "/camera/depth/image_raw", on_depth, qos_profile_sensor_data)
        if args.bag:
            harness.wait_for_nodes("/patch_mapper")
            player = subprocess.Popen([sys.executable, __file__, "--play", str(args.bag)], stdout=subprocess.PIPE, text=True,
                                      env={**os.environ, PLAYER_MARK: "1"})
            threading.Thread(target=read_player, args=(player, depth_seen), daemon=True).start()
        else:
            harness.wait_for_nodes("/patch_mapper", "/terrain_sim")
        deadline = time.monotonic() + 120.0
        print(f"waiting for >= {args.min_patches} patches in the map ...", flush=True)
        while True:
            with lock:
                patches = arrivals[-1][2] if arrivals else 0
            if patches >= args.min_patches:
                break
            if time.monotonic() > deadline or not all(n.alive() for n in nodes):
                print(f"only {patches} patches after 120 s (" + ", ".join(f"{n.name} alive {n.alive()}" for n in nodes) + ")")
                break
            time.sleep(0.2)
        with lock:
            arrivals.clear()
            statuses.clear()
            through_dds.clear()
        cpu0 = {n.name: cpu_seconds(n.proc.pid) for n in nodes}
        cpu0["this process"] = cpu_seconds(os.getpid())
        if player is not None:
            cpu0["bag player"] = cpu_seconds(player.pid)
        t0 = time.monotonic()
        time.sleep(args.seconds)
        wall = time.monotonic() - t0
        cpu1 = {n.name: cpu_seconds(n.proc.pid) for n in nodes}
        cpu1["this process"] = cpu_seconds(os.getpid())
        if player is not None:
            cpu1["bag player"] = cpu_seconds(player.pid)
        with lock:
            window, status_window, dds_window = list(arrivals), list(statuses), list(through_dds)
    finally:
        if player is not None:
            player.terminate()
            try:
                player.wait(timeout=10)
            except subprocess.TimeoutExpired:
                player.kill()
        for node in reversed(nodes):
            try:
                node.stop()
            except AssertionError as e:
                print(f"{node.name}: {e}".splitlines()[0])
        harness.shutdown()

    source = f"the bag {args.bag}" if args.bag else "terrain_sim (640x480 @ 30 Hz)"
    print(f"\npatch_mapper on {source}, {wall:.1f} s window, {os.cpu_count()} cores")
    print(f"PatchArray messages: {len(window)} ({len(window) / wall:.1f} Hz); patches in the map "
          f"min {min((a[2] for a in window), default=0)} max {max((a[2] for a in window), default=0)}")
    sizes = sorted(a[3] for a in window)
    if sizes:
        print(f"PatchArray serialized: median {sizes[len(sizes) // 2] / 1e3:.0f} kB, max {sizes[-1] / 1e3:.0f} kB")
    print("end to end (arrival - depth stamp):   " + percentiles([(a[0] - a[1]) * 1e3 for a in window]))
    print("through DDS (arrival - depth arrival): " + percentiles(dds_window))
    if status_window:
        last = status_window[-1]
        print(f"frames received {last.frames_received}, processed {last.frames_processed}, "
              f"skipped {last.frames_skipped} (busy drops + bad input), rejected {last.frames_rejected}")
        names = list(last.timing_names)
        for name in names:
            samples = {}
            for s in status_window:  # one sample per processed frame seen in a status message
                if name in s.timing_names:
                    samples[s.frames_processed] = s.timing_ms[list(s.timing_names).index(name)]
            print(f"  in node {name:<24} " + percentiles(list(samples.values())))
    for name in cpu0:
        print(f"CPU {name:<13} {100.0 * (cpu1[name] - cpu0[name]) / wall:6.1f} % of one core")
    print(f"logs: {LOG_DIR}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
