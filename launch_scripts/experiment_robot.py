"""The robot and the scene of the four-rock experiment (launch_scripts/experiment.py), without ROS: joint
order and limits of urdf/rpbp.urdf, servo ticks, the lookdown camera pose, small rotation helpers, the
leg inverse kinematics of the stepping motion that the trainer poses by hand, patch geometry (Patch.msg
outline and normal), and the rocks with their ground-truth footholds from `terrain_sim scene`.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

import patchwalk_testing as pw  # noqa: E402  (binary paths)


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

# patch_mapper's configuration for the simulated rig (terrain_sim's IMU mount).
SIM_MAPPER_CONFIG = REPO / "config" / "patch_mapper_sim.yaml"

# step_executor's bus settings for the simulated chain (`step_executor sim-bus`), as launch_scripts/demo.sh
# passes them: a user process behind a pty, sharing the CPU with the simulator and the mapper, gets 500 ms per
# answer (RS-485: 34) and is too slow only after 25 late cycles in a row or below 20 % of the cycle rate (a real
# bus: 5 cycles, 50 %).
SIM_BUS_PARAMS = ["--param", "bus.response_timeout_ms=500", "--param", "bus.slow_bus.consecutive_misses=25",
                  "--param", "bus.slow_bus.min_rate_percent=20"]

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


# ---- patch geometry (Patch.msg) and the camera ------------------------------------------------------------

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


def base_from_camera_lookdown() -> np.ndarray:
    """URDF lookdown pose: head (0.01, 0, 0.14) + camera (0.03, 0, 0.03), pitched 0.85 rad, optical frame."""
    pitch = 0.85
    base_from_link = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
    link_from_optical = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    return pose_matrix(base_from_link @ link_from_optical, [0.04, 0.0, 0.17])


BASE_FROM_CAMERA_LOOKDOWN = base_from_camera_lookdown()
