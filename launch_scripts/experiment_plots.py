"""Pictures of the four-rock experiment (launch_scripts/experiment.py), drawn with matplotlib (Agg, PNG):

- `patch_map_figure`: birds-eye view of one patch map (robot's forward up): the mapper's birds-eye cloud
  coloured by height, every map patch outlined in the colour of its surface type, the patch matching the
  trained target (same type, centre within 3 rs, normal within as) thick red, the target itself a cross;
- `trajectories_figure`: the 12 servo positions from /joint_states over the whole run, the automatic
  executions shaded.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from experiment_robot import (AS_DEG, BASE_FROM_CAMERA_LOOKDOWN, JOINTS, RS_M, SURFACE_NAMES,  # noqa: E402
                              msg_pose, patch_normal, patch_outline)

# Outline colour per Patch.surface (elliptic, hyperbolic, cylindric, circular paraboloid, plane, sphere, cylinder).
TYPE_COLORS = ["#e67828", "#c83cc8", "#3ca0e6", "#f0c83c", "#e6e6e6", "#78dc78", "#a0a0ff"]
MATCH_COLOR = "#ff2828"


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


def trained_in_map(patch_array, trained) -> tuple[np.ndarray, np.ndarray]:
    """Centre and normal of the trained patch (base_link) in the map frame of `patch_array`, with the
    lookdown base_from_camera."""
    map_from_base = msg_pose(patch_array.camera_pose) @ np.linalg.inv(BASE_FROM_CAMERA_LOOKDOWN)
    center = (map_from_base @ np.append(np.array(trained.center), 1.0))[:3]
    return center, map_from_base[:3, :3] @ patch_normal(trained)


def matching_patch_id(patch_array, trained):
    """Id of the map patch matching the trained one (J 6.3 tests: same type, normal within AS_DEG, the
    nearest centre within 3 RS_M), or None."""
    if trained is None:
        return None
    center, normal = trained_in_map(patch_array, trained)
    best = None
    for p in patch_array.patches:
        if p.surface != trained.surface:
            continue
        dist = float(np.linalg.norm(np.array(p.center) - center))
        angle = math.degrees(math.acos(min(1.0, abs(float(patch_normal(p) @ normal)))))
        if angle < AS_DEG and (best is None or dist < best[0]):
            best = (dist, p.id)
    return best[1] if best is not None and best[0] < 3 * RS_M else None


def patch_map_figure(patch_array, cloud, trained, title: str, metres: float = 0.7) -> Figure:
    """Birds-eye view of a patch map, in metres from the view centre (0.55 `metres` ahead of the camera):
    right of the robot to the right, forward up."""
    map_from_camera = msg_pose(patch_array.camera_pose)
    forward = map_from_camera[:3, 2].copy()
    forward[2] = 0.0
    forward = forward / (np.linalg.norm(forward) or 1.0)
    left = np.array([-forward[1], forward[0], 0.0])
    origin = map_from_camera[:3, 3] + forward * (metres * 0.55)

    def view(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rel = np.atleast_2d(points) - origin
        return -(rel @ left), rel @ forward

    fig, ax = plt.subplots(figsize=(6.4, 6.8), dpi=100)
    ax.set_facecolor("#141414")
    if cloud is not None:
        xyz = cloud_xyz(cloud)
        if len(xyz):
            u, v = view(xyz)
            lo, hi = np.percentile(xyz[:, 2], [2, 98])
            dots = ax.scatter(u, v, c=xyz[:, 2], cmap="viridis", vmin=lo, vmax=max(hi, lo + 1e-6), s=4,
                              marker="s", linewidths=0, rasterized=True)
            fig.colorbar(dots, ax=ax, shrink=0.7, label="height in the map frame (m)")
    matched_id = matching_patch_id(patch_array, trained)
    for p in patch_array.patches:
        if p.id != matched_id:
            color = TYPE_COLORS[p.surface] if p.surface < len(TYPE_COLORS) else "white"
            ax.plot(*view(patch_outline(p)), color=color, lw=1)
    for p in patch_array.patches:
        if p.id == matched_id:
            ax.plot(*view(patch_outline(p)), color=MATCH_COLOR, lw=3, zorder=5)
    if trained is not None:
        u, v = view(trained_in_map(patch_array, trained)[0])
        ax.plot(u, v, "+", color="white", ms=14, mew=1.5, zorder=6)
    u, v = view(map_from_camera[:3, 3])
    ax.plot(u, v, "^", color="white", ms=10, zorder=6)
    half = metres / 2
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xlabel("right of the view centre (m)")
    ax.set_ylabel("ahead of the view centre (m)")
    ax.set_title(f"{title}\n{len(patch_array.patches)} patches; red: matching the trained target (+); ^: camera",
                 fontsize=10)
    types = sorted({int(p.surface) for p in patch_array.patches if p.id != matched_id and p.surface < len(TYPE_COLORS)})
    handles = [Line2D([], [], color=TYPE_COLORS[t], lw=1, label=SURFACE_NAMES[t]) for t in types]
    if matched_id is not None:
        handles.append(Line2D([], [], color=MATCH_COLOR, lw=3, label="match"))
    if handles:
        ax.legend(handles=handles, loc="lower left", fontsize=7, facecolor="#333333", labelcolor="white", framealpha=0.8)
    fig.tight_layout()
    return fig


def trajectories_figure(history: list[tuple[float, list[float]]], windows: list[tuple[float, float, str]]) -> Figure:
    """The 12 joint positions over time (s since the experiment started), the executions shaded."""
    history = list(history)  # a snapshot: /joint_states keeps appending from the executor thread
    t = np.array([h[0] for h in history])
    q = np.array([h[1] for h in history]).reshape(len(history), len(JOINTS))
    fig, ax = plt.subplots(figsize=(14, 7.6), dpi=100)
    for start, end, _ in windows:
        ax.axvspan(start, end, color="#e8f0ff", lw=0)
    colors = plt.get_cmap("tab20").colors
    for j, name in enumerate(JOINTS):
        ax.plot(t, q[:, j], color=colors[j % len(colors)], lw=1, label=name)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("servo position (rad)")
    span = float(t.max() - t.min()) if len(t) else 0.0
    ax.set_title(f"servo positions from /joint_states over {span:.0f} s; shaded: {len(windows)} automatic executions")
    ax.grid(True, color="#dddddd", lw=0.5)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    fig.tight_layout()
    return fig


def save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, format="png")
    plt.close(fig)
    return path


def figure_rgb(fig: Figure) -> np.ndarray:
    """The rendered figure as RGB uint8 (h, w, 3)."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
