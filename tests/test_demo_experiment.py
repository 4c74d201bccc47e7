"""The demo's experiment table as a test: the J 6.3 four-rock experiment of launch_scripts/experiment.py against the real binaries (simulated servo bus, terrain_sim, patch_mapper,
step_executor), with 2 trials per trained rock and 1 in front of an untrained rock instead of 20.

Asserted: every trial in front of a trained rock executes that rock's trained motion, nothing is executed
in front of the untrained rock, no wrong motion anywhere, and the pictures are written. No timing asserts:
a trial ends when its outcome is decided, the timeouts only bound a trial whose maps stop coming.
"""

from __future__ import annotations

import subprocess
import sys

import patchwalk_testing as pw

sys.path.insert(0, str(pw.REPO / "launch_scripts"))
import experiment as ex  # noqa: E402
import experiment_robot as robot  # noqa: E402

TRIALS_PER_ROCK = 2
UNTRAINED_TRIALS = 1


def test_four_rock_experiment_matches_every_trained_rock_and_nothing_else(ros, start_node, log_dir):
    bus_log = open(log_dir / "sim_bus.log", "w")
    bus = subprocess.Popen([str(pw.binary("step_executor")), "sim-bus"], stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, stderr=bus_log, text=True, cwd=pw.REPO)
    experiment = None
    executor = None
    try:
        pty = bus.stdout.readline().strip()
        assert pty.startswith("/dev/"), f"sim-bus printed {pty!r}"
        # One at a time, each on the graph before the next starts (discovery is unicast on loopback).
        start_node("terrain_sim")
        ros.wait_for_nodes("/terrain_sim", timeout=60)
        start_node("patch_mapper", "--config", str(ex.SIM_MAPPER_CONFIG))
        ros.wait_for_nodes("/patch_mapper", timeout=60)
        # A pty served by a user process on a loaded host: the demo's simulated-bus settings.
        executor = start_node("step_executor", "--param", f"bus.port={pty}", *ex.SIM_BUS_PARAMS,
                              "--param", f"library_path={log_dir / 'motions.yaml'}",
                              "--param", "ros.status_rate_hz=20")
        ros.wait_for_nodes("/terrain_sim", "/patch_mapper", "/step_executor", timeout=60)
        rocks = ex.load_scene([])
        config = ex.ExperimentConfig(trials_per_rock=TRIALS_PER_ROCK, untrained_trials=UNTRAINED_TRIALS,
                                     untrained_rocks=1, out_dir=log_dir / "experiment")
        experiment = ex.Experiment(ros, ex.Hand(bus.stdin), rocks, config)
        results = experiment.run()
        pictures = experiment.write_pictures(config.out_dir)
    finally:
        if experiment is not None:
            experiment.close()
        # The executor goes first: it must not outlive its bus.
        if executor is not None:
            executor.stop()
        bus.terminate()
        bus.wait(timeout=30)
        bus_log.close()

    table = {row["rock"]: row for row in results["table"]}
    report = ex.format_table(results["table"])
    trained = [r.name for r in rocks if r.trained]
    assert len(trained) == 4, trained
    # Never a wrong motion. A trial may end without a match: the maps are stochastic (random seeds in
    # 1 cm cells) and slow on a loaded host; the full demo (20 trials per rock, load 8-10) measured
    # 19, 20, 17 and 20 of 20 correct. One miss per rock is allowed here.
    for name in trained:
        row = table[name]
        assert row["trials"] == TRIALS_PER_ROCK, report
        assert row["correct motion"] >= TRIALS_PER_ROCK - 1, report
    untrained = [row for row in results["table"] if not row["trained"]]
    assert len(untrained) == 1, report
    assert untrained[0]["trials"] == UNTRAINED_TRIALS and untrained[0]["no match"] == UNTRAINED_TRIALS, report
    assert all(row["wrong motion"] == 0 for row in results["table"]), report
    # Every trained target is the rock's foothold patch (within the select radius of the true top).
    assert set(results["trained_targets"]) == set(trained)
    for name, target in results["trained_targets"].items():
        assert target["miss_from_true_top_m"] < 0.03, (name, target)
    names = {p.name for p in pictures}
    assert "servo_trajectories.png" in names
    assert {f"patch_map_{n.replace(' ', '_')}.png" for n in trained} <= names
    for path in pictures:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pictures_show_the_cloud_and_highlight_the_matched_patch(tmp_path):
    """The picture helpers without ROS: a synthetic map with a trained patch and one decoy; the PNG decodes
    to the rendered pixels and the matched patch (not the decoy) is outlined in red."""
    import numpy as np
    from PIL import Image

    import experiment_plots as plots
    from patchwalk_msgs.msg import Patch, PatchArray
    from sensor_msgs.msg import PointCloud2, PointField

    base_from_camera = robot.BASE_FROM_CAMERA_LOOKDOWN
    map_from_base = robot.pose_matrix(np.eye(3), [0.0, 0.0, robot.BASE_HEIGHT])
    map_from_camera = map_from_base @ base_from_camera
    msg = PatchArray()
    msg.header.frame_id = "map"
    q = msg.camera_pose.orientation
    rot = map_from_camera[:3, :3]
    q.w = float(np.sqrt(1.0 + np.trace(rot)) / 2.0)
    q.x, q.y, q.z = (float(v) for v in (np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]]) / (4 * q.w)))
    p = msg.camera_pose.position
    p.x, p.y, p.z = (float(v) for v in map_from_camera[:3, 3])

    def patch(pid, surface, center):
        out = Patch(id=pid, surface=surface, boundary=Patch.CIRCLE)
        out.curvatures = [-15.0] if surface == Patch.CIRCULAR_PARABOLOID else []
        out.boundary_params = [0.03]
        out.center = [float(v) for v in center]
        return out

    trained_in_base = patch(0, Patch.CIRCULAR_PARABOLOID, [0.28, 0.0, -0.235])
    msg.patches = [patch(1, Patch.CIRCULAR_PARABOLOID, [0.282, 0.0, 0.05]), patch(2, Patch.PLANE, [0.28, 0.12, 0.0])]
    xs, ys = np.meshgrid(np.linspace(0.05, 0.5, 80), np.linspace(-0.25, 0.25, 80))
    points = np.stack([xs.ravel(), ys.ravel(), 0.01 * xs.ravel()], 1).astype("<f4")
    cloud = PointCloud2(height=1, width=len(points), point_step=12, row_step=12 * len(points), is_dense=True)
    cloud.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    cloud.data = points.tobytes()
    assert plots.cloud_xyz(cloud).shape == (len(points), 3)

    # The patch like the trained one is the match, not the plane beside it.
    assert plots.matching_patch_id(msg, trained_in_base) == 1
    fig = plots.patch_map_figure(msg, cloud, trained_in_base, "test")
    img = plots.figure_rgb(fig)
    red = np.all(np.abs(img.astype(int) - (255, 40, 40)) < 30, axis=-1)
    legend = fig.axes[0].get_legend().get_window_extent()  # display coordinates: y up
    red[int(img.shape[0] - legend.y1) - 1:int(img.shape[0] - legend.y0) + 1, int(legend.x0) - 1:int(legend.x1) + 1] = False
    assert red.sum() > 50  # the matched patch's outline
    # The decoy plane is 12 cm to the left (left of the image centre): no red there.
    ys_red, xs_red = np.nonzero(red)
    axes = fig.axes[0].get_window_extent()
    centre_x = (axes.x0 + axes.x1) / 2
    assert xs_red.min() > centre_x - 0.06 / 0.7 * axes.width
    path = plots.save(fig, tmp_path / "map.png")
    with Image.open(path) as png:
        assert png.format == "PNG" and png.size == (img.shape[1], img.shape[0])

    fig = plots.trajectories_figure([(0.0, [0.0] * 12), (1.0, [0.5] * 12), (2.0, [0.0] * 12)], [(0.5, 1.5, "rock 1")])
    assert len(fig.axes[0].lines) == 12 and len(fig.axes[0].patches) == 1  # 12 joints, one shaded execution
    with Image.open(plots.save(fig, tmp_path / "traj.png")) as png:
        assert png.format == "PNG"
