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

Tests (J 6.3 "Foot Placement Tests"): arm, then per trial: disarm, torque off, pose the lookdown pose
with a small random perturbation (hip yaw and ankle pitch of both legs: the whole robot turns and leans
by a fraction of a degree, within the matcher's rs = 1 cm / as = 20 deg), place the robot in front of
the rock, reset the mapper, arm and watch /step_executor/status: the first motion that plays is the
outcome (correct / wrong motion), no motion within the trial timeout is "no match". Twenty trials per
trained rock and a few in front of every untrained rock (expected: nothing plays).

Output: the table (rock, trials, correct motion, wrong motion, no match), `results.json`, and pictures
(PNG, written by a small built-in PNG writer): per trained rock the patch map over the birds-eye depth
with the matched patch highlighted, and the servo trajectories from /joint_states.

Usage (nodes already running, e.g. from launch_scripts/demo.sh):
    .venv/bin/python launch_scripts/experiment.py --sim-bus-stdin build/demo/sim_bus.stdin --out build/demo/experiment
The same code runs in tests/test_demo_experiment.py with fewer trials.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import struct
import subprocess
import sys
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, IO, Optional

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import patchwalk_testing as pw  # noqa: E402  (the fixture library: RosHarness, binaries)

# ---- robot constants (step_executor's embedded defaults, urdf/rpbp.urdf) --------------------------------

# Keyframe / joint_states order and servo ids (config/step_executor.yaml `servos`, zero offset 0, direction +1).
JOINTS = [
    "r_hip_yaw", "l_hip_yaw", "r_hip_roll", "l_hip_roll", "r_hip_pitch", "l_hip_pitch",
    "r_knee", "l_knee", "r_ankle_pitch", "l_ankle_pitch", "r_ankle_roll", "l_ankle_roll",
]
SERVO_ID = {name: i + 1 for i, name in enumerate(JOINTS)}
# URDF joint limits (rad).
LIMITS = {
    "r_hip_yaw": (-1.2, 1.2), "l_hip_yaw": (-1.2, 1.2),
    "r_hip_roll": (-0.5, 0.8), "l_hip_roll": (-0.8, 0.5),
    "r_hip_pitch": (-1.9, 0.6), "l_hip_pitch": (-1.9, 0.6),
    "r_knee": (0.0, 2.4), "l_knee": (0.0, 2.4),
    "r_ankle_pitch": (-1.3, 1.3), "l_ankle_pitch": (-1.3, 1.3),
    "r_ankle_roll": (-0.7, 0.7), "l_ankle_roll": (-0.7, 0.7),
}
TICKS_PER_REV = 4096.0
CENTER_TICKS = 2048.0
# Leg geometry (URDF): hip pitch axis 0.06 m below base_link, thigh and shin 0.1 m, sole 0.035 m below the ankle.
HIP_Y = {"r": -0.037, "l": 0.037}
HIP_Z = -0.060
THIGH = SHIN = 0.100
SOLE = 0.035
# base_link above the table with straight legs (terrain_sim motion.base_height_m).
BASE_HEIGHT = 0.295  # = -HIP_Z + THIGH + SHIN + SOLE below base_link
# Height of the stepping motion's standing sole below base_link: 1 cm short of full extension, a
# slightly bent knee keeps the leg IK away from its singularity.
STANCE_HEIGHT = 0.285

# Matcher thresholds of J 6.3 (step_executor defaults), used only to pick the patch to highlight.
RS_M = 0.01
AS_DEG = 20.0

# camera_from_imu of terrain_sim's IMU (imu.camera_from_imu_xyzw [0.5, -0.5, 0.5, 0.5]: imu x forward,
# y left, z up) as patch_mapper's row-major `mapper.acquire.camera_from_imu` parameter.
SIM_CAMERA_FROM_IMU = "[[0.0,-1.0,0.0],[0.0,0.0,-1.0],[1.0,0.0,0.0]]"

SURFACE_NAMES = ["elliptic_paraboloid", "hyperbolic_paraboloid", "cylindric_paraboloid", "circular_paraboloid",
                 "plane", "sphere", "circular_cylinder"]


def ticks_from_rad(q: float) -> float:
    return CENTER_TICKS + q * TICKS_PER_REV / (2.0 * math.pi)


def clamp_pose(pose: dict[str, float], margin: float = 0.01) -> dict[str, float]:
    """Joint values inside the limits by `margin` (a 0.088 deg servo tick must not round a value past a
    limit: record_keyframe refuses it); exact zeros (e.g. a straight knee at its limit) stay zero."""
    def clamp(j: str, q: float) -> float:
        return q if q == 0.0 else min(max(q, LIMITS[j][0] + margin), LIMITS[j][1] - margin)
    return {j: clamp(j, pose.get(j, 0.0)) for j in JOINTS}


# ---- small geometry ------------------------------------------------------------------------------------

def quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def expmap_to_matrix(r) -> np.ndarray:
    """Rotation matrix of an exponential-map vector (axis * angle), Rodrigues' formula."""
    r = np.asarray(r, dtype=float)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def pose_matrix(rotation: np.ndarray, translation) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def json_pose(p: dict) -> np.ndarray:
    return pose_matrix(quat_to_matrix(*p["rotation_xyzw"]), p["translation"])


def msg_pose(pose) -> np.ndarray:
    o, t = pose.orientation, pose.position
    return pose_matrix(quat_to_matrix(o.x, o.y, o.z, o.w), [t.x, t.y, t.z])


# ---- the scene (ground truth from `terrain_sim scene`) ----------------------------------------------------

@dataclass
class Rock:
    index: int
    name: str
    trained: bool
    surface_type: str
    world_from_station: np.ndarray
    top_in_world: np.ndarray
    # The training rock whose geometry this rock duplicates (twins_of_training), else None.
    twin_of: Optional[int] = None

    def top_in_base(self) -> np.ndarray:
        """The ground-truth foothold point in base_link when standing at the station in the lookdown pose."""
        world_from_base = self.world_from_station @ pose_matrix(np.eye(3), [0.0, 0.0, BASE_HEIGHT])
        return (np.linalg.inv(world_from_base) @ np.append(self.top_in_world, 1.0))[:3]


def load_scene(terrain_sim_args: list[str]) -> list[Rock]:
    """Rocks, stations and footholds of the scene terrain_sim runs (same config arguments)."""
    out = subprocess.run([str(pw.binary("terrain_sim")), "scene", *terrain_sim_args], check=True,
                         capture_output=True, text=True, cwd=REPO).stdout
    scene = json.loads(out)
    rocks = []
    for i, r in enumerate(scene["rocks"]):
        twin = None
        if r["name"].startswith("twin of rock "):
            twin = int(r["name"].rsplit(" ", 1)[1]) - 1
        rocks.append(Rock(i, r["name"], bool(r["trained"]), r["foothold"]["surface_type"],
                          json_pose(r["world_from_station"]), np.array(r["foothold"]["top_in_world"], float), twin))
    return rocks


# ---- the stepping motion (keyframes) ---------------------------------------------------------------------

def leg_ik(side: str, sole_in_base) -> dict[str, float]:
    """Joint angles putting the `side` sole (kept flat) at `sole_in_base`, clamped to the leg's reach:
    sagittal two-link IK (hip pitch, knee; ankle pitch keeps the sole level) plus hip/ankle roll for the
    lateral offset."""
    x, y, z = (float(v) for v in sole_in_base)
    ankle_x, ankle_z = x, z + SOLE - HIP_Z
    dy = y - HIP_Y[side]
    reach = math.hypot(ankle_x, math.hypot(ankle_z, dy))
    scale = min(1.0, 0.97 * (THIGH + SHIN) / max(reach, 1e-9))
    ankle_x, ankle_z, dy = ankle_x * scale, ankle_z * scale, dy * scale
    roll = math.atan2(dy, -ankle_z)  # rotation about x moves the foot sideways
    sagittal_z = -math.hypot(ankle_z, dy)
    d = math.hypot(ankle_x, sagittal_z)
    knee = 2.0 * math.acos(min(1.0, d / (THIGH + SHIN)))
    phi = math.atan2(-ankle_x, -sagittal_z)  # x = -d sin(phi), z = -d cos(phi)
    hip_pitch = phi - knee / 2.0
    return {f"{side}_hip_pitch": hip_pitch, f"{side}_knee": knee, f"{side}_ankle_pitch": -(hip_pitch + knee),
            f"{side}_hip_roll": roll, f"{side}_ankle_roll": -roll}


def stepping_motion(target_in_base: np.ndarray, normal_in_base: np.ndarray, clearance_m: float,
                    tempo: float) -> list[tuple[dict[str, float], float, float]]:
    """Keyframes (pose, move s, pause s) of a right-foot step onto `target_in_base`: lookdown, weight
    shift onto the left leg, lift, swing `clearance_m` above the target, place with the sole tilted to the
    patch normal. `tempo` scales the move times. Every pose is clamped to the joint limits."""
    zero = {j: 0.0 for j in JOINTS}
    shift = dict(zero, l_hip_roll=0.08, r_hip_roll=0.08, l_ankle_roll=-0.08, r_ankle_roll=-0.08)
    standing_sole = np.array([0.0, HIP_Y["r"], -STANCE_HEIGHT])
    lift = dict(shift, **leg_ik("r", standing_sole + [0.02, 0.0, 0.06]))
    above = np.array([0.75 * target_in_base[0], 0.5 * (HIP_Y["r"] + target_in_base[1]), target_in_base[2] + clearance_m])
    swing = dict(shift, **leg_ik("r", above))
    place = dict(shift, **leg_ik("r", target_in_base))
    # Sole along the patch normal n: pitch about y tilts (0,0,1) to (sin, 0, cos), roll about x to (0, -sin, cos).
    nx, ny, nz = (float(v) for v in normal_in_base)
    if nz < 0:
        nx, ny, nz = -nx, -ny, -nz
    place["r_ankle_pitch"] += math.atan2(nx, nz)
    place["r_ankle_roll"] += math.atan2(-ny, nz)
    return [(clamp_pose(zero), 0.4 * tempo, 0.1), (clamp_pose(shift), 0.5 * tempo, 0.1),
            (clamp_pose(lift), 0.5 * tempo, 0.1), (clamp_pose(swing), 0.6 * tempo, 0.1),
            (clamp_pose(place), 0.5 * tempo, 0.5)]


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


class Hand:
    """Poses the simulated servos by hand (torque off): `move <id> <ticks>` lines on sim-bus's stdin."""

    def __init__(self, stream: IO[str]):
        self.stream = stream

    def pose(self, pose: dict[str, float]) -> None:
        for joint in JOINTS:
            self.stream.write(f"move {SERVO_ID[joint]} {ticks_from_rad(pose.get(joint, 0.0)):.2f}\n")
        self.stream.flush()


@dataclass
class Trial:
    rock: str
    expected: Optional[str]
    played: Optional[str]
    last_match: str
    perturbation: dict
    seconds_to_match: Optional[float]
    fault: str = ""

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
        from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy, qos_profile_sensor_data
        from patchwalk_msgs.msg import ExecutorStatus, PatchArray
        from sensor_msgs.msg import JointState, PointCloud2
        from std_msgs.msg import UInt32

        self.ros, self.hand, self.rocks, self.config = harness, hand, rocks, config
        self.log = config.log
        self.rng = random.Random(config.seed)
        self.t0 = time.monotonic()
        reliable = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10,
                              durability=DurabilityPolicy.VOLATILE)
        self.joint_history: list[tuple[float, list[float]]] = []
        self.played_windows: list[tuple[float, float, str]] = []
        self.patches = Latest()
        self.cloud = Latest()
        self.status = Latest()
        self.rock_now = Latest()
        self.joints = Latest(on_message=self._on_joints)
        node = harness.node
        self._subs = [
            node.create_subscription(PatchArray, "/patch_mapper/patches", self.patches, reliable),
            node.create_subscription(PointCloud2, "/patch_mapper/birds_eye_cloud", self.cloud, reliable),
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

    def close(self) -> None:
        for sub in self._subs:
            self.ros.node.destroy_subscription(sub)
        self.ros.node.destroy_publisher(self.place_pub)

    def _on_joints(self, msg) -> None:
        order = {n: i for i, n in enumerate(msg.name)}
        if all(j in order for j in JOINTS):
            self.joint_history.append((time.monotonic() - self.t0, [msg.position[order[j]] for j in JOINTS]))

    # -- services ----------------------------------------------------------------------------------------

    def _call(self, srv_type, name: str, request=None, what: str = ""):
        response = self.ros.call(srv_type, name, request)
        if not response.success:
            raise RuntimeError(f"{name}{what}: {response.message}")
        return response

    def set_torque(self, on: bool) -> None:
        from std_srvs.srv import SetBool
        self._call(SetBool, "/step_executor/set_torque", SetBool.Request(data=on))

    def arm(self, on: bool) -> None:
        from std_srvs.srv import SetBool
        self._call(SetBool, "/step_executor/arm", SetBool.Request(data=on))

    def reset_mapper(self) -> None:
        from std_srvs.srv import Trigger
        self._call(Trigger, "/patch_mapper/reset")

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

    def fresh_map(self, min_maps: int = 3, min_patches: int = 1):
        """Reset the mapper, then wait for `min_maps` patch maps (with patches) from after the reset."""
        self.reset_mapper()
        start = self.patches.count
        return self.patches.wait(lambda m: self.patches.count >= start + min_maps and len(m.patches) >= min_patches,
                                 self.config.map_timeout_s, "patch map after reset")

    def lookdown(self, perturbation: Optional[dict[str, float]] = None) -> None:
        pose = {j: 0.0 for j in JOINTS}
        pose.update(perturbation or {})
        self.pose_by_hand(pose)

    # -- training (J 6.3 "Foot Placement Training") ------------------------------------------------------

    def train(self, rock: Rock) -> str:
        from patchwalk_msgs.srv import RecordKeyframe, SaveMotion, SelectTarget

        name = rock.name
        self.arm(False)
        self.set_torque(False)
        self.lookdown()
        self.place_at(rock)
        self.fresh_map(min_maps=10)
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
            response = self.ros.call(SelectTarget, "/step_executor/select_target", request)
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
                start = self.patches.count
                self.patches.wait(lambda m: self.patches.count >= start + 5, self.config.map_timeout_s, "patch maps")
        self.log(f"  {name}: target {SURFACE_NAMES[target.surface] if target.surface < 7 else target.surface} "
                 f"at ({target.center[0]:+.3f}, {target.center[1]:+.3f}, {target.center[2]:+.3f}) m in base_link, "
                 f"{miss * 1000:.1f} mm from the true top ({rock.surface_type})")
        # Each rock its own step: swing clearance and tempo differ, the sole follows the patch normal.
        order = sum(r.trained for r in self.rocks[: rock.index])
        keyframes = stepping_motion(np.array(target.center), patch_normal(target), 0.03 + 0.01 * order, 1.0 + 0.15 * order)
        for pose, move_s, pause_s in keyframes:
            self.pose_by_hand(pose)
            self._call(RecordKeyframe, "/step_executor/record_keyframe",
                       RecordKeyframe.Request(duration=move_s, pause=pause_s))
        self._call(SaveMotion, "/step_executor/save_motion", SaveMotion.Request(name=name))
        self.trained_targets[name] = target
        self.training_snapshots[name] = (self.patches.msg, self.cloud.msg)
        self.target_miss_m[name] = miss
        return name

    # -- tests (J 6.3 "Foot Placement Tests") -------------------------------------------------------------

    def trial(self, rock: Rock, expected: Optional[str]) -> Trial:
        cfg = self.config
        self.arm(False)
        self._wait_idle()
        self.set_torque(False)
        yaw = self.rng.uniform(-cfg.yaw_perturbation_rad, cfg.yaw_perturbation_rad)
        lean = self.rng.uniform(-cfg.lean_perturbation_rad, cfg.lean_perturbation_rad)
        perturbation = {"l_hip_yaw": yaw, "r_hip_yaw": yaw, "l_ankle_pitch": lean, "r_ankle_pitch": lean}
        self.lookdown(perturbation)
        self.place_at(rock)
        # A fresh map: maps already on their way when the mapper was reset show the previous rock.
        self.fresh_map(min_maps=2, min_patches=0)
        armed_at = time.monotonic()
        self.arm(True)
        played, last_match, seen_at, fault = None, "", None, ""
        snapshot = None
        deadline = armed_at + cfg.trial_timeout_s
        status_count = self.status.count
        while time.monotonic() < deadline:
            try:
                status = self.status.wait(lambda _: self.status.count > status_count, 0.5, "executor status")
            except TimeoutError:
                continue
            status_count = self.status.count
            if status.current_motion and status.state == self.ExecutorStatus.STATE_PLAYING:
                played, last_match, seen_at = status.current_motion, status.last_match, time.monotonic()
                snapshot = (self.patches.msg, self.cloud.msg)
                break
        self.arm(False)  # one execution per trial: the motion in progress finishes
        if played is not None:
            started = seen_at - self.t0
            final = self._wait_idle()
            if final.state == self.ExecutorStatus.STATE_HOLDING_FAULT:
                fault = final.last_fault
            self.played_windows.append((started, time.monotonic() - self.t0, played))
            if rock.name not in self.match_snapshots and snapshot[0] is not None:
                self.match_snapshots[rock.name] = (snapshot[0], snapshot[1], played)
        return Trial(rock.name, expected, played, last_match,
                     {k: round(v, 5) for k, v in perturbation.items()},
                     None if seen_at is None else round(seen_at - armed_at, 3), fault)

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
                         f"{'' if trial.seconds_to_match is None else f' after {trial.seconds_to_match:.1f} s'}")
        for rock in untrained:
            expected = motion_of.get(rock.twin_of) if rock.twin_of is not None else None
            self.log(f"{cfg.untrained_trials} trials in front of {rock.name} (not trained"
                     f"{'; twin of ' + expected if expected else ''})")
            for i in range(cfg.untrained_trials):
                trial = self.trial(rock, expected)
                trials.append(trial)
                self.log(f"  trial {i + 1:2d}: {'executed ' + trial.played if trial.played else 'no execution'}")
        self.arm(False)
        self._wait_idle()
        # Leave the robot standing in the lookdown pose in front of rock 1.
        self.set_torque(False)
        self.lookdown()
        if trained:
            self.place_at(trained[0])
        table = make_table(self.rocks, trials)
        results = {"table": table, "bus_faults_while_posing": self.faults, "trials": [t.__dict__ | {"outcome": t.outcome} for t in trials],
                   "trained_targets": {name: patch_dict(p) | {"miss_from_true_top_m": round(self.target_miss_m[name], 4)}
                                       for name, p in self.trained_targets.items()}}
        return results

    def write_pictures(self, out_dir: Path) -> list[Path]:
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for rock_name, (patch_array, cloud, motion) in self.match_snapshots.items():
            trained = self.trained_targets.get(motion)
            path = out_dir / f"patch_map_{rock_name.replace(' ', '_')}.png"
            write_png(path, render_patch_map(patch_array, cloud, trained, f"{rock_name}: matched {motion}"))
            written.append(path)
        for name, (patch_array, cloud) in self.training_snapshots.items():
            if patch_array is None:
                continue
            path = out_dir / f"training_{name.replace(' ', '_')}.png"
            write_png(path, render_patch_map(patch_array, cloud, self.trained_targets[name], f"training {name}: selected target"))
            written.append(path)
        if self.joint_history:
            path = out_dir / "servo_trajectories.png"
            write_png(path, render_trajectories(self.joint_history, self.played_windows))
            written.append(path)
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


# ---- pictures: a small PNG writer, a 3x5 bitmap font, lines -------------------------------------------------

def write_png(path: Path, rgb: np.ndarray) -> None:
    """RGB uint8 (h, w, 3) as an 8-bit truecolour PNG (filter 0 on every row)."""
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].astype(np.uint8).tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    path.write_bytes(png)


# Each glyph: 5 rows of 3 bits (octal digit per row, MSB = left column).
_FONT = {
    "0": "75557", "1": "26227", "2": "71747", "3": "71717", "4": "55711", "5": "74717", "6": "74757", "7": "71111",
    "8": "75757", "9": "75717", "A": "25755", "B": "65656", "C": "34443", "D": "65556", "E": "74647", "F": "74644",
    "G": "34553", "H": "55755", "I": "72227", "J": "11152", "K": "55655", "L": "44447", "M": "57755", "N": "65555",
    "O": "25552", "P": "65644", "Q": "25563", "R": "65655", "S": "34216", "T": "72222", "U": "55557", "V": "55552",
    "W": "55775", "X": "55255", "Y": "55222", "Z": "71247", " ": "00000", ".": "00002", ":": "02020", "-": "00700",
    "_": "00007", ";": "02024", "/": "11244", "(": "24442", ")": "42224", "%": "51245", "=": "07070", ",": "00024", "+": "02720",
}


def draw_text(img: np.ndarray, x: int, y: int, text: str, color, scale: int = 2) -> None:
    for ch in text.upper():
        rows = _FONT.get(ch, "77777")
        for ry, digit in enumerate(rows):
            bits = int(digit, 8)
            for rx in range(3):
                if bits & (4 >> rx):
                    y0, x0 = y + ry * scale, x + rx * scale
                    img[max(y0, 0):max(y0 + scale, 0), max(x0, 0):max(x0 + scale, 0)] = color
        x += 4 * scale


def draw_polyline(img: np.ndarray, pts: np.ndarray, color, width: int = 1) -> None:
    h, w, _ = img.shape
    for a, b in zip(pts[:-1], pts[1:]):
        n = int(max(abs(b[0] - a[0]), abs(b[1] - a[1]))) + 2
        xs = np.linspace(a[0], b[0], n)
        ys = np.linspace(a[1], b[1], n)
        for ox in range(-(width // 2), width - width // 2):
            for oy in range(-(width // 2), width - width // 2):
                xi = np.round(xs).astype(int) + ox
                yi = np.round(ys).astype(int) + oy
                ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
                img[yi[ok], xi[ok]] = color


def colormap(t: np.ndarray) -> np.ndarray:
    """Blue -> teal -> yellow (viridis-like) for t in [0, 1]."""
    anchors = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)
    t = np.clip(t, 0, 1) * (len(anchors) - 1)
    i = np.minimum(t.astype(int), len(anchors) - 2)
    f = (t - i)[..., None]
    return (anchors[i] * (1 - f) + anchors[i + 1] * f).astype(np.uint8)


def cloud_xyz(cloud) -> np.ndarray:
    """x, y, z (float32 fields) of a sensor_msgs/PointCloud2 as an (n, 3) array."""
    offsets = {f.name: f.offset for f in cloud.fields if f.datatype == 7}  # FLOAT32
    if not all(k in offsets for k in "xyz") or cloud.point_step == 0:
        return np.zeros((0, 3))
    n = cloud.width * cloud.height
    data = np.frombuffer(bytes(cloud.data), dtype=np.uint8)[: n * cloud.point_step].reshape(n, cloud.point_step)
    dtype = ">f4" if cloud.is_bigendian else "<f4"
    cols = [data[:, offsets[k]: offsets[k] + 4].copy().view(dtype).reshape(-1) for k in "xyz"]
    xyz = np.stack(cols, axis=1).astype(float)
    return xyz[np.all(np.isfinite(xyz), axis=1)]


def patch_outline(p, samples: int = 48) -> np.ndarray:
    """Boundary of a patch (Patch.msg) as points in the message frame."""
    d = list(p.boundary_params)
    t = np.linspace(0, 2 * math.pi, samples)
    if p.boundary == 1 and d:  # circle
        xy = np.stack([d[0] * np.cos(t), d[0] * np.sin(t)], 1)
    elif p.boundary == 0 and len(d) >= 2:  # ellipse
        xy = np.stack([d[0] * np.cos(t), d[1] * np.sin(t)], 1)
    elif p.boundary == 2 and len(d) >= 2:  # rectangle (half sizes)
        xy = np.array([[d[0], d[1]], [-d[0], d[1]], [-d[0], -d[1]], [d[0], -d[1]], [d[0], d[1]]])
    else:  # quadrilateral and anything else: a circle of the mean size
        r = float(np.mean(np.abs(d[:4]))) if d else 0.01
        xy = np.stack([r * np.cos(t), r * np.sin(t)], 1)
    k = list(p.curvatures) + [0.0, 0.0]
    kx, ky = (k[0], k[1]) if len(p.curvatures) == 2 else (k[0], k[0]) if p.surface in (3, 5) else (k[0], 0.0)
    z = 0.5 * (kx * xy[:, 0] ** 2 + ky * xy[:, 1] ** 2)
    local = np.column_stack([xy, z])
    return local @ expmap_to_matrix(p.rotation).T + np.array(p.center)


def patch_normal(p) -> np.ndarray:
    return expmap_to_matrix(p.rotation)[:, 2]


TYPE_COLORS = [(230, 120, 40), (200, 60, 200), (60, 160, 230), (240, 200, 60), (230, 230, 230), (120, 220, 120),
               (160, 160, 255)]


def render_patch_map(patch_array, cloud, trained, title: str, size: int = 520, metres: float = 0.7) -> np.ndarray:
    """Birds-eye view (robot's forward up) of the depth cloud coloured by height, every map patch outlined
    in its type colour, the patch matching the trained one filled red-outlined and thick."""
    img = np.full((size + 40, size, 3), 20, np.uint8)
    map_from_camera = msg_pose(patch_array.camera_pose)
    forward = map_from_camera[:3, 2].copy()
    forward[2] = 0.0
    forward = forward / (np.linalg.norm(forward) or 1.0)
    left = np.array([-forward[1], forward[0], 0.0])
    origin = map_from_camera[:3, 3] + forward * (metres * 0.55)

    def to_px(points: np.ndarray) -> np.ndarray:
        rel = points - origin
        u = size / 2 - (rel @ left) / metres * size
        v = 40 + size / 2 - (rel @ forward) / metres * size
        return np.stack([u, v], 1)

    if cloud is not None:
        xyz = cloud_xyz(cloud)
        if len(xyz):
            px = to_px(xyz).astype(int)
            ok = (px[:, 0] >= 0) & (px[:, 0] < size) & (px[:, 1] >= 40) & (px[:, 1] < size + 40)
            z = xyz[ok, 2]
            lo, hi = np.percentile(z, 2), np.percentile(z, 98)
            colors = colormap((z - lo) / max(hi - lo, 1e-6))
            # Birds-eye points are ~1 cm apart: 3x3 dots.
            for du in (-1, 0, 1):
                for dv in (-1, 0, 1):
                    u = np.clip(px[ok, 0] + du, 0, size - 1)
                    v = np.clip(px[ok, 1] + dv, 40, size + 39)
                    img[v, u] = colors
    # The patch matching the trained one (J 6.3 tests: same type, near position and normal), in the map
    # frame: trained patch (base_link) -> map with the lookdown base_from_camera.
    matched_id = None
    if trained is not None:
        map_from_base = map_from_camera @ np.linalg.inv(BASE_FROM_CAMERA_LOOKDOWN)
        c = (map_from_base @ np.append(np.array(trained.center), 1.0))[:3]
        n = map_from_base[:3, :3] @ patch_normal(trained)
        best = None
        for p in patch_array.patches:
            if p.surface != trained.surface:
                continue
            dist = float(np.linalg.norm(np.array(p.center) - c))
            angle = math.degrees(math.acos(min(1.0, abs(float(patch_normal(p) @ n)))))
            if angle < AS_DEG and (best is None or dist < best[0]):
                best = (dist, p.id)
        if best is not None and best[0] < 3 * RS_M:
            matched_id = best[1]
        cross = to_px(np.array([c]))[0]
        draw_polyline(img, np.array([[cross[0] - 8, cross[1]], [cross[0] + 8, cross[1]]]), (255, 255, 255), 1)
        draw_polyline(img, np.array([[cross[0], cross[1] - 8], [cross[0], cross[1] + 8]]), (255, 255, 255), 1)
    for p in patch_array.patches:
        if p.id == matched_id:
            continue
        color = TYPE_COLORS[p.surface] if p.surface < len(TYPE_COLORS) else (255, 255, 255)
        draw_polyline(img, to_px(patch_outline(p)), color, 1)
    for p in patch_array.patches:
        if p.id == matched_id:
            draw_polyline(img, to_px(patch_outline(p)), (255, 40, 40), 3)
    # The robot (camera position) and a 10 cm scale bar.
    cam = to_px(np.array([map_from_camera[:3, 3]]))[0]
    draw_polyline(img, np.array([[cam[0] - 6, cam[1] + 6], [cam[0], cam[1] - 6], [cam[0] + 6, cam[1] + 6],
                                 [cam[0] - 6, cam[1] + 6]]), (255, 255, 255), 2)
    bar = size / metres * 0.10
    draw_polyline(img, np.array([[10, size + 30], [10 + bar, size + 30]]), (255, 255, 255), 2)
    draw_text(img, int(14 + bar), size + 26, "10 CM", (255, 255, 255))
    draw_text(img, 8, 8, title, (255, 255, 255))
    draw_text(img, 8, 22, f"{len(patch_array.patches)} patches; red: matching the trained target (+)", (200, 200, 200))
    return img


def render_trajectories(history: list[tuple[float, list[float]]], windows: list[tuple[float, float, str]],
                        width: int = 1400, height: int = 760) -> np.ndarray:
    """The 12 joint positions over time, trial executions shaded, one colour per joint with a legend."""
    img = np.full((height, width, 3), 255, np.uint8)
    history = list(history)  # a snapshot: /joint_states keeps appending from the executor thread
    t = np.array([h[0] for h in history])
    q = np.array([h[1] for h in history])
    left, right, top, bottom = 60, width - 170, 40, height - 40
    t0, t1 = float(t.min()), float(max(t.max(), t.min() + 1e-3))
    q0, q1 = -1.9, 2.4

    def px(tt, qq):
        return np.stack([left + (tt - t0) / (t1 - t0) * (right - left), bottom - (qq - q0) / (q1 - q0) * (bottom - top)], -1)

    for start, end, name in windows:
        a, b = px(np.array([start, end]), np.array([0.0, 0.0]))[:, 0].astype(int)
        img[top:bottom, max(a, left):min(b + 1, right)] = (232, 240, 255)
    for level in (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0):
        y = int(px(np.array([t0]), np.array([level]))[0, 1])
        img[y, left:right] = (200, 200, 200) if level else (120, 120, 120)
        draw_text(img, 8, y - 5, f"{level:+.1f}", (60, 60, 60))
    palette = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
               (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207), (0, 0, 0), (255, 0, 255)]
    for j, name in enumerate(JOINTS):
        draw_polyline(img, px(t, q[:, j]), palette[j], 1)
        y = top + 10 + 22 * j
        img[y:y + 4, right + 12:right + 32] = palette[j]
        draw_text(img, right + 38, y - 3, name, (0, 0, 0))
    img[top:bottom, left] = img[bottom, left:right] = (0, 0, 0)
    draw_text(img, left, 12, f"servo positions (rad) from /joint_states over {t1 - t0:.0f} s; shaded: "
              f"{len(windows)} automatic executions", (0, 0, 0))
    step = max(5.0, round((t1 - t0) / 10.0 / 5.0) * 5.0)
    for tick in np.arange(math.ceil(t0 / step) * step, t1, step):
        x = int(px(np.array([tick]), np.array([0.0]))[0, 0])
        img[bottom:bottom + 5, x] = (0, 0, 0)
        draw_text(img, x - 8, bottom + 8, f"{tick:.0f}", (0, 0, 0))
    draw_text(img, right - 60, bottom + 22, "time (s)", (0, 0, 0))
    return img


def base_from_camera_lookdown() -> np.ndarray:
    """URDF lookdown pose: head (0.01, 0, 0.14) + camera (0.03, 0, 0.03), pitched 0.85 rad, optical frame."""
    pitch = 0.85
    base_from_link = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    link_from_optical = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    return pose_matrix(base_from_link @ link_from_optical, [0.04, 0.0, 0.17])


BASE_FROM_CAMERA_LOOKDOWN = base_from_camera_lookdown()


# ---- command line --------------------------------------------------------------------------------------

def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sim-bus-stdin", required=True, type=Path,
                        help="FIFO (or file) read by `step_executor sim-bus` as its stdin: hand posing")
    parser.add_argument("--trials", type=int, default=20, help="trials per trained rock (J 6.3: 20)")
    parser.add_argument("--untrained-trials", type=int, default=5, help="trials per untrained rock")
    parser.add_argument("--untrained-rocks", type=int, default=None, help="untrained rocks to visit (default all)")
    parser.add_argument("--trial-timeout", type=float, default=20.0, help="s to wait for a match per trial")
    parser.add_argument("--seed", type=int, default=1, help="seed of the placement perturbations")
    parser.add_argument("--target-mode", choices=("fit", "nearest"), default=ExperimentConfig.target_mode,
                        help="training target: fit the mapper's cloud at the rock top (J 6.3) or the nearest map patch")
    parser.add_argument("--out", type=Path, default=REPO / "build" / "demo" / "experiment")
    parser.add_argument("--terrain-sim-param", action="append", default=[], metavar="KEY=VALUE",
                        help="the -p overrides terrain_sim runs with (to read the same scene)")
    args = parser.parse_args()

    rocks = load_scene([a for p in args.terrain_sim_param for a in ("-p", p)])
    config = ExperimentConfig(trials_per_rock=args.trials, untrained_trials=args.untrained_trials,
                              untrained_rocks=args.untrained_rocks, trial_timeout_s=args.trial_timeout,
                              seed=args.seed, target_mode=args.target_mode, out_dir=args.out)
    harness = pw.RosHarness("experiment")
    started = time.monotonic()
    try:
        with open(args.sim_bus_stdin, "w") as stream:
            experiment = Experiment(harness, Hand(stream), rocks, config)
            results = experiment.run()
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "results.json").write_text(json.dumps(results, indent=2))
            pictures = experiment.write_pictures(args.out)
            experiment.close()
    finally:
        harness.shutdown()
    print()
    print(f"=== experiment table (J 6.3; {time.monotonic() - started:.0f} s)")
    print(format_table(results["table"]))
    print()
    print(f"results: {args.out / 'results.json'}")
    for path in pictures:
        print(f"picture: {path}")
    ok = all(r["wrong motion"] == 0 and (r["correct motion"] in (None, r["trials"])) for r in results["table"])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
