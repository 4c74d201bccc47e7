"""Open3D side of the fusion benchmark: the CPU tensor pipeline (VoxelBlockGrid integrate + raycast,
frame-to-model point-to-plane RGBD odometry) on the same TUM frames and parameters as
`bench_fusion` (block resolution 8, truncation 4 voxels, depth max 3 m, 2 threads).
Prints per-stage median / p95 / p99 (ms) and the ATE against the ground truth."""

import argparse
import pathlib
import time

import numpy as np
import open3d as o3d
import open3d.core as o3c

# TUM freiburg1 intrinsics, as used by patch_mapper (Intrinsics::tum_freiburg1).
FX, FY, CX, CY = 517.3, 516.5, 318.6, 255.3


def read_list(path):
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            rows.append(line.split())
    return rows


def nearest_pose(groundtruth, stamp, max_gap=0.02):
    times = groundtruth[:, 0]
    i = int(np.argmin(np.abs(times - stamp)))
    return groundtruth[i] if abs(times[i] - stamp) <= max_gap else None


def ate_rmse(estimate, reference):
    e, r = np.asarray(estimate), np.asarray(reference)
    me, mr = e.mean(0), r.mean(0)
    u, _, vt = np.linalg.svd((r - mr).T @ (e - me))
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1, 1, d]) @ vt
    aligned = (rotation @ (e - me).T).T + mr
    return float(np.sqrt(np.mean(np.sum((aligned - r) ** 2, axis=1))))


def stats(name, values):
    v = np.sort(np.asarray(values))
    pick = lambda p: v[int(round((len(v) - 1) * p))]
    print(f"  {name:<28} median {pick(0.5):7.2f} ms   p95 {pick(0.95):7.2f} ms   p99 {pick(0.99):7.2f} ms   (n = {len(v)})")


def run(root, voxel, passes, device):
    frames = read_list(root / "depth.txt")
    groundtruth = np.array([[float(x) for x in row] for row in read_list(root / "groundtruth.txt")])
    depths = [o3d.t.io.read_image(str(root / f)).to(device) for _, f in frames]
    intrinsic = o3c.Tensor([[FX, 0, CX], [0, FY, CY], [0, 0, 1]], o3c.Dtype.Float64)
    height, width = depths[0].rows, depths[0].columns
    colour = o3d.t.geometry.Image(o3c.Tensor(np.zeros((height, width, 3), np.uint8))).to(device)
    depth_scale, depth_max, trunc = 5000.0, 3.0, 4.0
    timings = {"odometry": [], "integrate": [], "raycast 640x480": [], "frame": []}
    ates = []
    for _ in range(passes):
        model = o3d.t.pipelines.slam.Model(voxel, 8, 60000, o3c.Tensor(np.eye(4)), device)
        input_frame = o3d.t.pipelines.slam.Frame(height, width, intrinsic, device)
        raycast_frame = o3d.t.pipelines.slam.Frame(height, width, intrinsic, device)
        pose = np.eye(4)
        estimate, reference = [], []
        for i, depth in enumerate(depths):
            start = time.perf_counter()
            input_frame.set_data_from_image("depth", depth)
            input_frame.set_data_from_image("color", colour)
            if i > 0:
                t0 = time.perf_counter()
                result = model.track_frame_to_model(input_frame, raycast_frame, depth_scale, depth_max)
                pose = pose @ result.transformation.cpu().numpy()
                timings["odometry"].append((time.perf_counter() - t0) * 1e3)
            model.update_frame_pose(i, o3c.Tensor(pose))
            t0 = time.perf_counter()
            model.integrate(input_frame, depth_scale, depth_max, trunc)
            timings["integrate"].append((time.perf_counter() - t0) * 1e3)
            t0 = time.perf_counter()
            model.synthesize_model_frame(raycast_frame, depth_scale, 0.1, depth_max, trunc, False)
            timings["raycast 640x480"].append((time.perf_counter() - t0) * 1e3)
            if i > 0:
                timings["frame"].append((time.perf_counter() - start) * 1e3)
            gt = nearest_pose(groundtruth, float(frames[i][0]))
            if gt is not None:
                estimate.append(pose[:3, 3].copy())
                reference.append(gt[1:4])
        ates.append(ate_rmse(estimate, reference))
    print(f"open3d {o3d.__version__} voxel {voxel * 1e3:.0f} mm (block resolution 8, truncation {trunc:.0f} voxels):")
    for name, values in timings.items():
        stats(name, values)
    print(f"  => {1e3 / np.median(timings['frame']):.1f} Hz (median frame), ATE {[round(a * 1e3, 1) for a in ates]} mm")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("dataset", type=pathlib.Path)
    parser.add_argument("--passes", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    o3d.utility.set_max_threads(args.threads) if hasattr(o3d.utility, "set_max_threads") else None
    device = o3c.Device("CPU:0")
    for voxel in (0.005, 0.01):
        run(args.dataset, voxel, args.passes, device)


if __name__ == "__main__":
    main()
