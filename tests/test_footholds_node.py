"""patch_mapper's foothold stage over ROS 2 with the real binaries: terrain_sim (the rocks on the table)
feeds the mapper with `ros.footholds.enabled` and `ros.route.enabled`; the node must publish the CNN's
footholds as a PoseArray in the fixed frame `odom`, on the table (z near the table's height in odom, which
the simulator's ground truth gives), with unit orientations and scores on `~/footholds/scored`; report the
stage in /diagnostics; and publish a nav_msgs/Path toward a goal sent on `~/route_goal`. No timing asserts:
the timeouts only bound a stage whose predictions stop coming."""

from __future__ import annotations

import json
import math
import statistics
import struct
import subprocess

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped
from nav_msgs.msg import Path
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from patchwalk_msgs.msg import PatchArray

import patchwalk_testing as pw

SIM_MAPPER_CONFIG = "config/patch_mapper_sim.yaml"
STAGE_PARAMS = ["--param", "ros.footholds.enabled=true", "--param", "ros.route.enabled=true",
                "--param", "ros.footholds.max_rate_hz=0"]
# The network takes about a second per frame on a loaded host; a few predictions must come in this.
TIMEOUT_S = 180.0


def scene() -> dict:
    return json.loads(subprocess.run([str(pw.binary("terrain_sim")), "scene", "--config", "config/terrain_sim.yaml"],
                                     check=True, capture_output=True, text=True, cwd=pw.REPO).stdout)


def camera_height_above_table(truth: dict) -> float:
    """World z of the camera minus the table's (the station the robot stands on is on the table top)."""
    station = truth["world_from_station"]["translation"]
    rock = next(r for r in truth["rocks"] if r["world_from_station"]["translation"] == station)
    base_z = rock["foothold"]["top_in_world"][2] - rock["foothold"]["top_in_base"][2]
    # The robot stands upright: base_link's z is vertical, the camera's offset adds directly.
    return base_z + truth["base_from_camera"]["translation"][2] - station[2]


def quaternion_norm(q) -> float:
    return math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)


def forward_in_odom(pose) -> tuple[float, float]:
    """The camera's viewing direction (optical z) made horizontal, in odom."""
    q = pose.orientation
    x, y = 2 * (q.x * q.z + q.y * q.w), 2 * (q.y * q.z - q.x * q.w)
    n = math.hypot(x, y)
    return x / n, y / n


def scores(cloud: PointCloud2) -> list[float]:
    names = [f.name for f in cloud.fields]
    assert names == ["x", "y", "z", "score"], names
    data = bytes(cloud.data)
    return [struct.unpack_from("<f", data, i * cloud.point_step + 12)[0] for i in range(cloud.width)]


def test_footholds_land_on_the_table_in_odom_and_a_goal_gets_a_route(ros, start_node):
    footholds = ros.collect(PoseArray, "/patch_mapper/footholds")
    scored = ros.collect(PointCloud2, "/patch_mapper/footholds/scored")
    arrays = ros.collect(PatchArray, "/patch_mapper/patches")
    routes = ros.collect(Path, "/patch_mapper/route")
    diagnostics = ros.collect(DiagnosticArray, "/diagnostics")
    start_node("terrain_sim", "--config", "config/terrain_sim.yaml")
    ros.wait_for_nodes("/terrain_sim", timeout=60)
    mapper = start_node("patch_mapper", "--config", SIM_MAPPER_CONFIG, *STAGE_PARAMS)
    ros.wait_for_nodes("/terrain_sim", "/patch_mapper", timeout=60)

    # The footholds of a mapped frame, in the fixed frame.
    holds = footholds.wait_for(lambda a: len(a.poses) >= 3, timeout=TIMEOUT_S)
    assert holds.header.frame_id == "odom"
    camera = arrays.wait_for(lambda a: True, timeout=60).camera_pose
    table_z = camera.position.z - camera_height_above_table(scene())
    heights = [p.position.z - table_z for p in holds.poses]
    # On the table top or on a rock (the rocks' tops are 5 cm above it): not under it, not in the air.
    assert all(-0.04 < h < 0.10 for h in heights), heights
    assert abs(statistics.median(heights)) < 0.03, heights
    fx, fy = forward_in_odom(camera)
    for pose in holds.poses:
        assert abs(quaternion_norm(pose.orientation) - 1.0) < 1e-6
        dx, dy = pose.position.x - camera.position.x, pose.position.y - camera.position.y
        ahead = dx * fx + dy * fy
        assert 0.05 < ahead < 1.5, f"foothold {ahead:.2f} m ahead of the camera"
    # The scores travel on ~/footholds/scored: at least the threshold, at most 1.
    cloud = scored.wait_for(lambda c: c.width >= 1, timeout=TIMEOUT_S)
    assert cloud.header.frame_id == "odom"
    assert all(0.5 <= s <= 1.0 for s in scores(cloud)), scores(cloud)
    # /diagnostics names the stage.
    status = diagnostics.wait_for(lambda a: any(s.name == "patch_mapper: footholds" for s in a.status), timeout=30)
    stage = next(s for s in status.status if s.name == "patch_mapper: footholds")
    assert "frames/s" in stage.message or "none predicted yet" in stage.message, stage.message

    # A goal 0.45 m ahead of the camera on the table (RViz's 2D goal tool sends z = 0 in the fixed frame).
    goal = PoseStamped()
    goal.header.frame_id = "odom"
    goal.pose.position.x = camera.position.x + 0.45 * fx
    goal.pose.position.y = camera.position.y + 0.45 * fy
    goal.pose.orientation.w = 1.0
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    goal_pub = ros.publisher(PoseStamped, "/patch_mapper/route_goal", reliable)
    try:
        route = ros.publish_until(goal_pub, goal, routes, lambda p: len(p.poses) >= 2, period=1.0, timeout=TIMEOUT_S)
    except AssertionError:
        last = [s for a in diagnostics.messages for s in a.status if s.name == "patch_mapper: footholds"]
        raise AssertionError(f"no route; the stage said: {last[-1].values if last else None}\n{mapper.log()[-3000:]}")
    assert route.header.frame_id == "odom"
    end = route.poses[-1].pose.position
    start = route.poses[0].pose.position
    # From near the robot toward the goal, over the table.
    assert math.hypot(end.x - goal.pose.position.x, end.y - goal.pose.position.y) < \
        math.hypot(start.x - goal.pose.position.x, start.y - goal.pose.position.y)
    assert all(-0.04 < p.pose.position.z - table_z < 0.10 for p in route.poses)
    assert mapper.alive()


def test_the_stage_is_off_by_default_and_its_endpoints_do_not_exist(ros, patch_mapper):
    def endpoints() -> set[str]:
        publishers = ros.node.get_publisher_names_and_types_by_node("patch_mapper", "/")
        subscriptions = ros.node.get_subscriber_names_and_types_by_node("patch_mapper", "/")
        return {name for name, _ in publishers + subscriptions}

    pw.wait_until(lambda: "/patch_mapper/status" in endpoints(), "the mapper's endpoints are discovered")
    for name in ("/patch_mapper/footholds", "/patch_mapper/footholds/scored", "/patch_mapper/route", "/patch_mapper/route_goal"):
        assert name not in endpoints(), name
