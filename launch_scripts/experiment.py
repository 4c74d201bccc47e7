#!/usr/bin/env python3
"""The four-rock foot placement experiment of J 6.3 (Fig. 10-11), driven over ROS 2 like a person would.

Runs against a live terrain_sim + patch_mapper + step_executor (on `step_executor sim-bus`), using only
their public interfaces:

Training (J 6.3 "Foot Placement Training"), for each of the four training rocks:
  torque off (compliant) -> pose the servos by hand into the lookdown pose (`move <id> <ticks>` on the
  simulated bus's stdin, the simulator's equivalent of a person's hands) -> place the robot in front of
  the rock (/terrain_sim/place_at_rock) -> reset the mapper and wait for its patch map -> select the
  foothold patch nearest the rock's top (select_target, in base_link) -> pose and record a stepping
  motion (weight shift, lift, swing, place; the swing/place poses from the foothold position, so every
  rock gets its own motion) -> save_motion("rock N").

Tests (J 6.3 "Foot Placement Tests"), per trial: disarm, torque off, pose the lookdown pose with a small
random perturbation (hip yaw and ankle pitch of both legs: the whole robot turns and leans by a fraction
of a degree, within the matcher's rs = 1 cm / as = 20 deg), place the robot in front of the rock, reset
the mapper, wait for the first maps of the fresh volume, arm and watch /step_executor/status. The
executor matches every patch map it receives while armed; the first motion that plays is the outcome
(correct / wrong motion). "No match" is decided once `no_match_maps` patch maps made from depth frames
taken after arming (header.stamp later than the arm) have arrived and an executor status stamped after
the last of them still shows nothing playing: the executor has had each of those maps, and none matched.
`trial_timeout_s` only bounds a trial whose maps stop coming. (`--trial-end timeout` instead waits the
whole `trial_timeout_s` for a match, as a person with a stopwatch would.) Twenty trials per trained rock
and a few in front of every untrained rock (expected: nothing plays).

Output: the table (rock, trials, correct motion, wrong motion, no match), `results.json` (every trial
with its outcome, the maps it took and its phases' durations), and pictures (launch_scripts/
experiment_plots.py, matplotlib): per rock the patch map of its first match over the birds-eye depth
with the matched patch in red, per trained rock the map it was trained on, and the servo trajectories
from /joint_states.

Usage (nodes already running, e.g. from launch_scripts/demo.sh):
    .venv/bin/python launch_scripts/experiment.py --sim-bus-stdin build/demo/sim_bus.stdin --out build/demo/experiment
The same code runs in tests/test_demo_experiment.py with fewer trials. The robot model, the scene and the
stepping motion are in launch_scripts/experiment_robot.py.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, IO, Optional

import numpy as np

from experiment_robot import (JOINTS, REPO, SERVO_ID, SIM_BUS_PARAMS, SIM_MAPPER_CONFIG, SURFACE_NAMES, Rock, load_scene,  # noqa: F401
                              patch_normal, stepping_motion, ticks_from_rad)

sys.path.insert(0, str(REPO / "tests"))

import patchwalk_testing as pw  # noqa: E402  (the fixture library: RosHarness, binaries)

# A status stamped this long after a map arrived here was published after the executor had that map
# (both take it from the same DDS topic on this host; the executor's loop runs every 2 ms).
STATUS_AFTER_MAP_S = 0.25


def stamp_s(stamp) -> float:
    return stamp.sec + stamp.nanosec * 1e-9


# ---- ROS side ---------------------------------------------------------------------------------------------

class Latest:
    """Keeps the latest message of a topic (and a count), with a blocking wait; optional history hook."""

    def __init__(self, on_message: Optional[Callable] = None):
        self.cond = threading.Condition()
        self.msg = None
        self.count = 0
        self.received_at = 0.0
        self.on_message = on_message

    def __call__(self, msg) -> None:
        with self.cond:
            self.msg = msg
            self.count += 1
            self.received_at = time.monotonic()
            if self.on_message:
                self.on_message(msg)
            self.cond.notify_all()

    def wait(self, predicate: Callable[[object], bool], timeout: float, what: str):
        deadline = time.monotonic() + timeout
        with self.cond:
            while self.msg is None or not predicate(self.msg):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"{what}: not within {timeout:.0f} s (last: {self.describe()})")
                self.cond.wait(left)
            return self.msg

    def describe(self) -> str:
        return "nothing received" if self.msg is None else f"{self.count} received"


class LatestSerialized(Latest):
    """`Latest` for a subscription taking serialized messages (`raw=True`): a message is deserialized only
    when it is looked at (`msg`), so following a topic of large messages at 30 Hz costs a copy of its bytes,
    not a Python object per field. `on_message` gets the header stamp in s, read from the CDR bytes."""

    def __init__(self, msg_type, on_message: Optional[Callable[[float], None]] = None):
        super().__init__(on_message)
        self.msg_type = msg_type
        self._raw: Optional[bytes] = None
        self._decoded = None

    @property
    def msg(self):
        raw = self._raw
        if raw is None:
            return None
        if self._decoded is None or self._decoded[0] is not raw:
            from rclpy.serialization import deserialize_message
            self._decoded = (raw, deserialize_message(raw, self.msg_type))
        return self._decoded[1]

    @msg.setter
    def msg(self, raw) -> None:
        self._raw = raw

    def __call__(self, raw: bytes) -> None:
        with self.cond:
            self._raw = raw
            self.count += 1
            self.received_at = time.monotonic()
            if self.on_message:
                self.on_message(header_stamp_s(raw))
            self.cond.notify_all()


def _stamp_format(raw: bytes) -> str:
    # CDR after the 4-byte encapsulation header, whose second byte says the byte order.
    return "<iI" if raw[1] & 1 else ">iI"


def header_stamp(raw: bytes) -> tuple[int, int]:
    """`header.stamp` (sec, nanosec) of a serialized message whose first field is a std_msgs/Header."""
    return struct.unpack_from(_stamp_format(raw), raw, 4)


def header_stamp_s(raw: bytes) -> float:
    """`header_stamp` in s."""
    sec, nanosec = header_stamp(raw)
    return sec + nanosec * 1e-9


def with_header_stamp(raw: bytes, sec: int, nanosec: int) -> bytes:
    """The serialized message `raw` (first field a std_msgs/Header) with its stamp replaced."""
    return bytes(raw[:4]) + struct.pack(_stamp_format(raw), sec, nanosec) + bytes(raw[12:])


class Hand:
    """Poses the simulated servos by hand (torque off): `move <id> <ticks>` lines on sim-bus's stdin."""

    def __init__(self, stream: IO[str]):
        self.stream = stream

    def pose(self, pose: dict[str, float]) -> None:
        for joint in JOINTS:
            self.stream.write(f"move {SERVO_ID[joint]} {ticks_from_rad(pose.get(joint, 0.0)):.2f}\n")
        self.stream.flush()



class Services:
    """Service clients kept for the whole experiment (a new client per call waits for discovery again)."""

    def __init__(self, harness: "pw.RosHarness", log: Callable[[str], None] = print):
        self.ros = harness
        self.log = log
        self.clients: dict[str, object] = {}

    def call(self, srv_type, name: str, request=None, timeout: float = pw.DEFAULT_TIMEOUT_S, attempt_s: float = 5.0):
        """The response of service `name`; a request lost while discovery settles is sent again after
        `attempt_s` (the services used here are idempotent). A client left without an answer to two
        sends is replaced by a new one (new DDS endpoints, discovered afresh) until `timeout`."""
        deadline = time.monotonic() + timeout
        while True:
            client = self.clients.get(name)
            if client is None:
                client = self.clients[name] = self.ros.client(srv_type, name)
            window = min(2 * attempt_s, max(0.0, deadline - time.monotonic()))
            try:
                return pw.call_on(client, srv_type, name, request, window, attempt_s, error=TimeoutError)
            except TimeoutError as e:
                self._drop(name)
                if time.monotonic() >= deadline:
                    raise TimeoutError(f"no response from {name} within {timeout} s, with new clients") from e
                self.log(f"  {e}; calling again with a new client")

    def _drop(self, name: str) -> None:
        client = self.clients.pop(name, None)
        if client is not None:
            with self.ros._lock:
                self.ros.node.destroy_client(client)

    def close(self) -> None:
        with self.ros._lock:
            for client in self.clients.values():
                self.ros.node.destroy_client(client)
        self.clients.clear()


@dataclass
class Trial:
    rock: str
    expected: Optional[str]
    played: Optional[str]
    last_match: str
    perturbation: dict
    seconds_to_match: Optional[float]
    fault: str = ""
    # Patch maps from depth frames taken after arming that had arrived when the outcome was decided.
    maps_after_arm: int = 0
    # Durations (s): prepare (disarm, motion end, pose, place), map (reset -> first fresh maps),
    # decide (arm -> outcome), motion (the matched motion, start -> idle).
    phases: dict = field(default_factory=dict)

    @property
    def outcome(self) -> str:
        if self.played is None:
            return "no match"
        return "correct" if self.played == self.expected else "wrong"


@dataclass
class ExperimentConfig:
    trials_per_rock: int = 20
    untrained_trials: int = 5          # per untrained rock
    untrained_rocks: Optional[int] = None  # how many untrained rocks to visit (None = all)
    # "decided": a trial ends when its outcome is decided (a motion plays, or no_match_maps maps after
    # arming did not match); "timeout": a trial without a match waits the whole trial_timeout_s.
    trial_end: str = "decided"
    no_match_maps: int = 100
    # "first": the first execution per rock plays the whole motion, later ones are ended (torque off, the
    # trainer catching the robot) as soon as they started, the outcome being decided; "all": every one.
    full_motions: str = "first"
    trial_timeout_s: float = 20.0  # the map of a fresh volume fills in ~1-3 s on a quiet machine, slower under load
    map_timeout_s: float = 30.0
    # Perturbation of the placement (uniform, rad): hip yaw and ankle pitch of both legs.
    yaw_perturbation_rad: float = 0.01
    lean_perturbation_rad: float = 0.008
    seed: int = 1
    # Training target (J 6.3: "we manually select a neighborhood where we would like the robot to place
    # its foot and we fit a patch"): "nearest" takes the mapped patch nearest the rock top, as the
    # trainer picking one of the patches the robot itself sees; "fit" fits the mapper's cloud within
    # foot_radius_m of the top (select_target MODE_FIT_AT_POINT).
    target_mode: str = "nearest"
    target_timeout_s: float = 60.0
    foot_radius_m: float = 0.05
    out_dir: Path = REPO / "build" / "demo" / "experiment"
    pictures: bool = True
    log: Callable[[str], None] = print


class Experiment:
    def __init__(self, harness: "pw.RosHarness", hand: Hand, rocks: list[Rock], config: ExperimentConfig):
        from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy
        from patchwalk_msgs.msg import ExecutorStatus, PatchArray
        from sensor_msgs.msg import JointState, PointCloud2
        from std_msgs.msg import UInt32

        if config.trial_end not in ("decided", "timeout"):
            raise ValueError(f"trial_end {config.trial_end!r}: 'decided' or 'timeout'")
        if config.full_motions not in ("first", "all"):
            raise ValueError(f"full_motions {config.full_motions!r}: 'first' or 'all'")
        self.ros, self.hand, self.rocks, self.config = harness, hand, rocks, config
        self.services = Services(harness, config.log)
        # The trainer watches the robot: the executor arms only while this heartbeat arrives (its
        # deadman disarms and holds within ros.heartbeat_timeout_s when it stops).
        self.heartbeat = harness.heartbeat()
        self.log = config.log
        self.rng = random.Random(config.seed)
        self.t0 = time.monotonic()
        reliable = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10,
                              durability=DurabilityPolicy.VOLATILE)
        self.joint_history: list[tuple[float, list[float]]] = []
        self.played_windows: list[tuple[float, float, str]] = []
        # (header.stamp, wall time of arrival) of every patch map, in arrival order.
        self.map_arrivals: list[tuple[float, float]] = []
        self.patches = LatestSerialized(PatchArray, on_message=lambda stamp: self.map_arrivals.append((stamp, time.time())))
        self.cloud = LatestSerialized(PointCloud2)
        self.status = Latest()
        self.rock_now = Latest()
        self.joints = Latest(on_message=self._on_joints)
        node = harness.node
        with harness._lock:
            self._subs = [
                node.create_subscription(PatchArray, "/patch_mapper/patches", self.patches, reliable, raw=True),
                node.create_subscription(PointCloud2, "/patch_mapper/birds_eye_cloud", self.cloud, reliable, raw=True),
                node.create_subscription(ExecutorStatus, "/step_executor/status", self.status, reliable),
                node.create_subscription(UInt32, "/terrain_sim/rock", self.rock_now, reliable),
                node.create_subscription(JointState, "/joint_states", self.joints, reliable),
            ]
            self.place_pub = node.create_publisher(UInt32, "/terrain_sim/place_at_rock", reliable)
        self.ExecutorStatus = ExecutorStatus
        self.UInt32 = UInt32
        self.faults: list[str] = []  # bus faults seen (and cleared) while posing by hand
        self.trained_targets: dict[str, object] = {}  # motion name -> trained Patch (base_link)
        self.target_miss_m: dict[str, float] = {}      # motion name -> distance of its patch to the true top
        self.training_snapshots: dict[str, tuple] = {}  # motion name -> (PatchArray, PointCloud2) at training
        self.match_snapshots: dict[str, tuple] = {}   # rock name -> (PatchArray, PointCloud2 or None, motion)
        self.full_motion_played: set[str] = set()      # rocks in front of which a whole motion played

    def close(self) -> None:
        self.heartbeat.stop()
        self.services.close()
        with self.ros._lock:
            for sub in self._subs:
                self.ros.node.destroy_subscription(sub)
            self.ros.node.destroy_publisher(self.place_pub)

    def _on_joints(self, msg) -> None:
        order = {n: i for i, n in enumerate(msg.name)}
        if all(j in order for j in JOINTS):
            self.joint_history.append((time.monotonic() - self.t0, [msg.position[order[j]] for j in JOINTS]))

    def maps_after(self, wall_time: float) -> list[tuple[float, float]]:
        """The patch maps (stamp, arrival) made from depth frames taken after `wall_time` (time.time())."""
        fresh = []
        for m in reversed(self.map_arrivals):  # stamps increase (one camera), newest last
            if m[0] <= wall_time:
                break
            fresh.append(m)
        return fresh[::-1]

    # -- services ----------------------------------------------------------------------------------------

    def _call(self, srv_type, name: str, request=None, what: str = ""):
        response = self.services.call(srv_type, name, request)
        if not response.success:
            raise RuntimeError(f"{name}{what}: {response.message}")
        return response

    def set_torque(self, on: bool) -> None:
        from std_srvs.srv import SetBool
        self._call(SetBool, "/step_executor/set_torque", SetBool.Request(data=on))

    def arm(self, on: bool) -> None:
        from std_srvs.srv import SetBool
        if on:
            self.heartbeat.wait_for_executor()
            # Arming is refused until a heartbeat has arrived: retry briefly after discovery.
            deadline = time.monotonic() + 5.0
            while True:
                response = self.services.call(SetBool, "/step_executor/arm", SetBool.Request(data=True))
                if response.success:
                    return
                if "heartbeat" not in response.message or time.monotonic() > deadline:
                    raise RuntimeError(f"/step_executor/arm: {response.message}")
                time.sleep(0.05)
        self._call(SetBool, "/step_executor/arm", SetBool.Request(data=on))

    def reset_mapper(self) -> float:
        """Reset the mapper; returns the wall time just before the request (maps stamped later are fresh)."""
        from std_srvs.srv import Trigger
        at = time.time()
        self._call(Trigger, "/patch_mapper/reset")
        return at

    # -- robot handling ----------------------------------------------------------------------------------

    def pose_by_hand(self, pose: dict[str, float]) -> None:
        """Torque must be off. Moves the servos and waits until /joint_states reports the pose."""
        target = [pose.get(j, 0.0) for j in JOINTS]
        for attempt in range(3):
            self.hand.pose(pose)
            try:
                self.joints.wait(lambda m: self._close_to(m, target), self.config.map_timeout_s / 3,
                                 "joint_states reach the hand pose")
                break
            except TimeoutError as e:
                status = self.status.msg
                order = {n: i for i, n in enumerate(self.joints.msg.name)} if self.joints.msg else {}
                off = {j: round(self.joints.msg.position[order[j]] - q, 4) for j, q in zip(JOINTS, target) if j in order}
                problem = (f"{e}; torque_enabled={getattr(status, 'torque_enabled', '?')} "
                           f"state={getattr(status, 'state', '?')} fault={getattr(status, 'last_fault', '?')!r}; "
                           f"joint_states - hand pose: {off}")
                if attempt == 2:
                    raise TimeoutError(problem) from None
                # A bus fault (e.g. a lost status packet) holds the servos until torque off clears it.
                self.faults.append(problem)
                self.log(f"  retrying the hand pose: {problem}")
                self.set_torque(False)
        # One more joint state so terrain_sim (which follows /joint_states) has it too.
        count = self.joints.count
        self.joints.wait(lambda _: self.joints.count > count + 2, 5.0, "joint_states after the hand pose")

    def record_pose(self, pose: dict[str, float], move_s: float, pause_s: float) -> None:
        """Pose by hand and record the keyframe. A bus fault latched in between (the executor then refuses
        to record positions that are not current) is cleared as while posing: torque off, pose again."""
        from patchwalk_msgs.srv import RecordKeyframe
        for attempt in range(3):
            self.pose_by_hand(pose)
            response = self.services.call(RecordKeyframe, "/step_executor/record_keyframe",
                                          RecordKeyframe.Request(duration=move_s, pause=pause_s))
            if response.success:
                return
            problem = f"/step_executor/record_keyframe: {response.message}"
            if "positions not current" not in response.message or attempt == 2:
                raise RuntimeError(problem)
            self.faults.append(problem)
            self.log(f"  recording again after a bus fault: {problem}")
            self.set_torque(False)

    @staticmethod
    def _close_to(msg, target: list[float], tol: float = 0.01) -> bool:
        order = {n: i for i, n in enumerate(msg.name)}
        if not all(j in order for j in JOINTS):
            return False
        return all(abs(msg.position[order[j]] - q) < tol for j, q in zip(JOINTS, target))

    def place_at(self, rock: Rock) -> None:
        """Place the robot in front of `rock` (terrain_sim re-plants the feet at its station)."""
        self.rock_now.msg = None
        deadline = time.monotonic() + self.config.map_timeout_s
        while True:
            self.place_pub.publish(self.UInt32(data=rock.index))
            try:
                self.rock_now.wait(lambda m: m.data == rock.index, 0.5, "terrain_sim reports the rock")
                return
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"terrain_sim did not report standing in front of {rock.name}")

    def fresh_map(self, min_maps: int = 3, min_patches: int = 1) -> float:
        """Reset the mapper, then wait for `min_maps` patch maps made from depth frames taken after the
        reset, the last with at least `min_patches` patches. Returns the wall time of the reset."""
        reset_at = self.reset_mapper()
        self.wait_maps_after(reset_at, min_maps, min_patches, "patch map after reset")
        return reset_at

    def wait_maps_after(self, wall_time: float, n: int, min_patches: int = 0, what: str = "patch maps"):
        # The stamps come from map_arrivals; a map is decoded only to count its patches.
        return self.patches.wait(lambda m: len(self.maps_after(wall_time)) >= max(n, 1)
                                 and (min_patches == 0 or len(m.patches) >= min_patches), self.config.map_timeout_s, what)

    def lookdown(self, perturbation: Optional[dict[str, float]] = None) -> None:
        pose = {j: 0.0 for j in JOINTS}
        pose.update(perturbation or {})
        self.pose_by_hand(pose)

    # -- training (J 6.3 "Foot Placement Training") ------------------------------------------------------

    def train(self, rock: Rock) -> str:
        from patchwalk_msgs.srv import SaveMotion, SelectTarget

        name = rock.name
        self.arm(False)
        self.set_torque(False)
        self.lookdown()
        self.place_at(rock)
        # The trainer looks at a grown map (~2 s of frames) before choosing.
        self.fresh_map(min_maps=40)
        point = rock.top_in_base()
        fit = self.config.target_mode == "fit"
        mode = SelectTarget.Request.MODE_FIT_AT_POINT if fit else SelectTarget.Request.MODE_NEAREST_POINT
        request = SelectTarget.Request(mode=mode, radius=self.config.foot_radius_m)
        request.point.x, request.point.y, request.point.z = (float(v) for v in point)
        # Like a trainer who wants the foot on the top: wait while the map grows (cells whose seeds failed
        # get new seeds every frame; mapped patches stay, so the nearest one only gets nearer) until the
        # target lies within 15 mm of the top; at target_timeout_s keep the last selection.
        deadline = time.monotonic() + self.config.target_timeout_s
        while True:
            response = self.services.call(SelectTarget, "/step_executor/select_target", request)
            target = response.patch
            miss = float(np.linalg.norm(np.array(target.center) - point)) if response.success else float("inf")
            if miss < 0.015:
                break
            if time.monotonic() > deadline:
                if not response.success:
                    raise RuntimeError(f"select_target on {name}: {response.message}")
                break
            if fit:
                time.sleep(0.5)
            else:
                self.wait_maps_after(time.time(), 10)
        self.log(f"  {name}: target {SURFACE_NAMES[target.surface] if target.surface < 7 else target.surface} "
                 f"at ({target.center[0]:+.3f}, {target.center[1]:+.3f}, {target.center[2]:+.3f}) m in base_link, "
                 f"{miss * 1000:.1f} mm from the true top ({rock.surface_type})")
        # Each rock its own step: swing clearance and tempo differ, the sole follows the patch normal.
        order = sum(r.trained for r in self.rocks[: rock.index])
        keyframes = stepping_motion(np.array(target.center), patch_normal(target), 0.03 + 0.01 * order, 1.0 + 0.15 * order)
        for pose, move_s, pause_s in keyframes:
            self.record_pose(pose, move_s, pause_s)
        self._call(SaveMotion, "/step_executor/save_motion", SaveMotion.Request(name=name))
        self.trained_targets[name] = target
        self.training_snapshots[name] = (self.patches.msg, self.cloud.msg)
        self.target_miss_m[name] = miss
        return name

    # -- tests (J 6.3 "Foot Placement Tests") -------------------------------------------------------------

    def trial(self, rock: Rock, expected: Optional[str]) -> Trial:
        cfg = self.config
        phases = {}
        began = time.monotonic()
        self.arm(False)
        self._wait_idle()
        self.set_torque(False)
        yaw = self.rng.uniform(-cfg.yaw_perturbation_rad, cfg.yaw_perturbation_rad)
        lean = self.rng.uniform(-cfg.lean_perturbation_rad, cfg.lean_perturbation_rad)
        perturbation = {"l_hip_yaw": yaw, "r_hip_yaw": yaw, "l_ankle_pitch": lean, "r_ankle_pitch": lean}
        self.lookdown(perturbation)
        self.place_at(rock)
        placed = time.monotonic()
        phases["prepare"] = placed - began
        # A fresh map: maps made from frames taken before the reset show the previous rock.
        self.fresh_map(min_maps=2, min_patches=0)
        armed_wall = time.time()
        self.arm(True)
        armed_at = time.monotonic()
        phases["map"] = armed_at - placed
        played, last_match, seen_at, fault = None, "", None, ""
        snapshot = None
        deadline = armed_at + cfg.trial_timeout_s
        status_count = self.status.count
        maps_seen = 0
        while time.monotonic() < deadline:
            try:
                status = self.status.wait(lambda _: self.status.count > status_count, 0.5, "executor status")
            except TimeoutError:
                continue
            status_count = self.status.count
            fresh = self.maps_after(armed_wall)
            maps_seen = len(fresh)
            if status.current_motion and status.state == self.ExecutorStatus.STATE_PLAYING:
                played, last_match, seen_at = status.current_motion, status.last_match, time.monotonic()
                snapshot = (self.patches.msg, self.cloud.msg)
                break
            # No match: the executor has had no_match_maps maps while armed (a status published after the
            # last of them arrived here) and plays nothing.
            if (cfg.trial_end == "decided" and maps_seen >= cfg.no_match_maps
                    and stamp_s(status.stamp) > fresh[cfg.no_match_maps - 1][1] + STATUS_AFTER_MAP_S):
                break
        disarmed_wall = time.time()
        self.arm(False)  # one execution per trial: the motion in progress finishes
        decided_at = time.monotonic()
        if played is None:
            # A match taken just before the disarm still plays: it counts.
            status = self.status.wait(lambda s: stamp_s(s.stamp) > disarmed_wall + 0.05, 10.0, "executor status after disarm")
            if status.current_motion and status.state == self.ExecutorStatus.STATE_PLAYING:
                played, last_match, seen_at = status.current_motion, status.last_match, time.monotonic()
                snapshot = (self.patches.msg, self.cloud.msg)
        phases["decide"] = (seen_at or decided_at) - armed_at
        if played is not None:
            started = seen_at - self.t0
            if cfg.full_motions == "first" and rock.name in self.full_motion_played:
                self.set_torque(False)  # the outcome is decided: catch the robot, the motion ends
            self.full_motion_played.add(rock.name)
            final = self._wait_idle()
            phases["motion"] = time.monotonic() - seen_at
            if final.state == self.ExecutorStatus.STATE_HOLDING_FAULT:
                fault = final.last_fault
            self.played_windows.append((started, time.monotonic() - self.t0, played))
            if rock.name not in self.match_snapshots and snapshot[0] is not None:
                self.match_snapshots[rock.name] = (snapshot[0], snapshot[1], played)
        return Trial(rock.name, expected, played, last_match,
                     {k: round(v, 5) for k, v in perturbation.items()},
                     None if seen_at is None else round(seen_at - armed_at, 3), fault, maps_seen,
                     {k: round(v, 3) for k, v in phases.items()})

    def _wait_idle(self):
        return self.status.wait(lambda s: s.state != self.ExecutorStatus.STATE_PLAYING, 60.0, "motion finished")

    # -- the whole experiment ---------------------------------------------------------------------------

    def run(self) -> dict:
        cfg = self.config
        self.status.wait(lambda _: True, cfg.map_timeout_s, "/step_executor/status")
        self.joints.wait(lambda _: True, cfg.map_timeout_s, "/joint_states (is step_executor on the sim bus?)")
        trained = [r for r in self.rocks if r.trained]
        untrained = [r for r in self.rocks if not r.trained]
        if cfg.untrained_rocks is not None:
            untrained = untrained[: cfg.untrained_rocks]
        self.log(f"training {len(trained)} rocks (J 6.3): place, map, select the foothold patch, record a step")
        motion_of: dict[int, str] = {}
        for rock in trained:
            motion_of[rock.index] = self.train(rock)
        trials: list[Trial] = []
        for rock in trained:
            self.log(f"{cfg.trials_per_rock} trials in front of {rock.name}")
            for i in range(cfg.trials_per_rock):
                trial = self.trial(rock, motion_of[rock.index])
                trials.append(trial)
                self.log(f"  trial {i + 1:2d}: {trial.outcome:8s} played={trial.played or '-'}"
                         f"{'' if trial.seconds_to_match is None else f' after {trial.seconds_to_match:.1f} s'}"
                         f" ({trial.maps_after_arm} maps)")
        for rock in untrained:
            expected = motion_of.get(rock.twin_of) if rock.twin_of is not None else None
            self.log(f"{cfg.untrained_trials} trials in front of {rock.name} (not trained"
                     f"{'; twin of ' + expected if expected else ''})")
            for i in range(cfg.untrained_trials):
                trial = self.trial(rock, expected)
                trials.append(trial)
                self.log(f"  trial {i + 1:2d}: {'executed ' + trial.played if trial.played else 'no execution'}"
                         f" ({trial.maps_after_arm} maps, {trial.phases['decide']:.1f} s)")
        self.arm(False)
        self._wait_idle()
        # Leave the robot standing in the lookdown pose in front of rock 1.
        self.set_torque(False)
        self.lookdown()
        if trained:
            self.place_at(trained[0])
        table = make_table(self.rocks, trials)
        matched = [t.maps_after_arm for t in trials if t.played is not None]
        results = {"table": table, "trial_end": cfg.trial_end, "no_match_maps": cfg.no_match_maps,
                   "full_motions": cfg.full_motions,
                   "most_maps_to_a_match": max(matched, default=None),
                   "bus_faults_while_posing": self.faults, "trials": [t.__dict__ | {"outcome": t.outcome} for t in trials],
                   "trained_targets": {name: patch_dict(p) | {"miss_from_true_top_m": round(self.target_miss_m[name], 4)}
                                       for name, p in self.trained_targets.items()}}
        return results

    def write_pictures(self, out_dir: Path) -> list[Path]:
        import experiment_plots as plots

        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for rock_name, (patch_array, cloud, motion) in self.match_snapshots.items():
            trained = self.trained_targets.get(motion)
            path = out_dir / f"patch_map_{rock_name.replace(' ', '_')}.png"
            written.append(plots.save(plots.patch_map_figure(patch_array, cloud, trained, f"{rock_name}: matched {motion}"), path))
        for name, (patch_array, cloud) in self.training_snapshots.items():
            if patch_array is None:
                continue
            path = out_dir / f"training_{name.replace(' ', '_')}.png"
            figure = plots.patch_map_figure(patch_array, cloud, self.trained_targets[name], f"training {name}: selected target")
            written.append(plots.save(figure, path))
        if self.joint_history:
            path = out_dir / "servo_trajectories.png"
            written.append(plots.save(plots.trajectories_figure(self.joint_history, self.played_windows), path))
        return written


def patch_dict(p) -> dict:
    return {"surface": SURFACE_NAMES[p.surface] if p.surface < len(SURFACE_NAMES) else int(p.surface),
            "boundary": int(p.boundary), "curvatures": list(p.curvatures), "boundary_params": list(p.boundary_params),
            "rotation": list(p.rotation), "center": list(p.center)}


def make_table(rocks: list[Rock], trials: list[Trial]) -> list[dict]:
    rows = []
    for rock in rocks:
        mine = [t for t in trials if t.rock == rock.name]
        if not mine:
            continue
        expects_motion = any(t.expected for t in mine)
        rows.append({
            "rock": rock.name,
            "trained": rock.trained,
            "trials": len(mine),
            "correct motion": sum(t.outcome == "correct" for t in mine) if expects_motion else None,
            "wrong motion": sum(t.outcome == "wrong" for t in mine),
            "no match": sum(t.outcome == "no match" for t in mine),
        })
    return rows


def format_table(rows: list[dict]) -> str:
    header = f"{'rock':<14}{'trained':>8}{'trials':>8}{'correct motion':>16}{'wrong motion':>14}{'no match':>10}"
    lines = [header, "-" * len(header)]
    for r in rows:
        correct = "-" if r["correct motion"] is None else str(r["correct motion"])
        lines.append(f"{r['rock']:<14}{'yes' if r['trained'] else 'no':>8}{r['trials']:>8}{correct:>16}"
                     f"{r['wrong motion']:>14}{r['no match']:>10}")
    return "\n".join(lines)



# ---- command line --------------------------------------------------------------------------------------

def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim-bus-stdin", required=True, type=Path,
                        help="FIFO (or file) read by `step_executor sim-bus` as its stdin: hand posing")
    parser.add_argument("--trials", type=int, default=20, help="trials per trained rock (J 6.3: 20)")
    parser.add_argument("--untrained-trials", type=int, default=5, help="trials per untrained rock")
    parser.add_argument("--untrained-rocks", type=int, default=None, help="untrained rocks to visit (default all)")
    parser.add_argument("--trial-end", choices=("decided", "timeout"), default=ExperimentConfig.trial_end,
                        help="end a trial when its outcome is decided (default), or wait --trial-timeout for a match")
    parser.add_argument("--no-match-maps", type=int, default=ExperimentConfig.no_match_maps,
                        help="patch maps after arming without a match that decide 'no match'")
    parser.add_argument("--full-motions", choices=("first", "all"), default=ExperimentConfig.full_motions,
                        help="play the whole matched motion in the first trial per rock (later ones end once it "
                             "started) or in every trial")
    parser.add_argument("--trial-timeout", type=float, default=ExperimentConfig.trial_timeout_s,
                        help="s to wait for a match per trial at most")
    parser.add_argument("--seed", type=int, default=1, help="seed of the placement perturbations")
    parser.add_argument("--target-mode", choices=("fit", "nearest"), default=ExperimentConfig.target_mode,
                        help="training target: fit the mapper's cloud at the rock top (J 6.3) or the nearest map patch")
    parser.add_argument("--out", type=Path, default=REPO / "build" / "demo" / "experiment")
    parser.add_argument("--terrain-sim-param", action="append", default=[], metavar="KEY=VALUE",
                        help="the -p overrides terrain_sim runs with (to read the same scene)")
    args = parser.parse_args()

    rocks = load_scene([a for p in args.terrain_sim_param for a in ("-p", p)])
    config = ExperimentConfig(trials_per_rock=args.trials, untrained_trials=args.untrained_trials,
                              untrained_rocks=args.untrained_rocks, trial_end=args.trial_end,
                              no_match_maps=args.no_match_maps, full_motions=args.full_motions, trial_timeout_s=args.trial_timeout,
                              seed=args.seed, target_mode=args.target_mode, out_dir=args.out)
    harness = pw.RosHarness("experiment")
    started = time.monotonic()
    try:
        with open(args.sim_bus_stdin, "w") as stream:
            experiment = Experiment(harness, Hand(stream), rocks, config)
            results = experiment.run()
            results["wall_time_s"] = round(time.monotonic() - started, 1)
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "results.json").write_text(json.dumps(results, indent=2))
            print("writing the pictures")
            pictures = experiment.write_pictures(args.out)
            experiment.close()
    finally:
        harness.shutdown()
    print()
    print(f"=== experiment table (J 6.3; {results['wall_time_s']:.0f} s)")
    print(format_table(results["table"]))
    print()
    print(f"results: {args.out / 'results.json'}")
    for path in pictures:
        print(f"picture: {path}")
    ok = all(r["wrong motion"] == 0 and (r["correct motion"] in (None, r["trials"])) for r in results["table"])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
