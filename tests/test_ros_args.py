"""The ROS 2 command line and parameters of the nodes, through real rclpy: declared parameters with
rclpy's parameter client (list, get, describe, set, a refused value, a read-only key), the
`--ros-args` of `ros2 run`/`ros2 launch` (`-r __ns:=`, `-p`, `--params-file`), and two namespaced
robots on one domain without crosstalk."""

from __future__ import annotations

import re
import subprocess
import threading
import time
import pytest

from patchwalk_msgs.msg import ExecutorStatus, MapperStatus, PatchArray
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_srvs.srv import Trigger

import patchwalk_testing as pw

SIM_MAPPER_PARAMS = pw.REPO / "config" / "patch_mapper_sim.yaml"


class Params:
    """rclpy's AsyncParameterClient on the harness node, waiting on its futures."""

    def __init__(self, ros, node_name: str):
        with ros._lock:
            self.client = AsyncParameterClient(ros.node, node_name)
        assert self.client.wait_for_services(timeout_sec=pw.DEFAULT_TIMEOUT_S), f"{node_name}: no parameter services"

    @staticmethod
    def _wait(future):
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        assert done.wait(pw.DEFAULT_TIMEOUT_S), "no answer from the parameter service"
        return future.result()

    def names(self) -> list[str]:
        return list(self._wait(self.client.list_parameters()).result.names)

    def get(self, *names: str) -> list:
        return [Parameter.from_parameter_msg(_named(n, v)).value for n, v in zip(names, self._wait(self.client.get_parameters(list(names))).values)]

    def describe(self, name: str):
        return self._wait(self.client.describe_parameters([name])).descriptors[0]

    def set(self, name: str, value):
        return self._wait(self.client.set_parameters([Parameter(name, value=value)])).results[0]


def _named(name, value):
    from rcl_interfaces.msg import Parameter as ParameterMsg

    return ParameterMsg(name=name, value=value)


def test_parameters_list_get_describe_set_refuse_and_read_only(ros, start_node):
    mapper = start_node("patch_mapper", "--param", "ros.status_period_s=0.1")
    ros.wait_for_nodes("/patch_mapper")
    params = Params(ros, "/patch_mapper")
    names = params.names()
    for name in ["ros.status_period_s", "ros.depth_topic", "mapper.volume_edge_m", "mapper.fit.max_iterations", "use_sim_time"]:
        assert name in names, f"{name} not declared: {names}"
    assert len(names) > 50, "every config key is a parameter"
    assert params.get("ros.status_period_s", "ros.depth_topic", "use_sim_time") == [0.1, "camera/depth/image_raw", False]

    depth = params.describe("ros.depth_topic")
    assert depth.read_only and "restart" in depth.description, depth
    period = params.describe("ros.status_period_s")
    assert not period.read_only and "applied" in period.description, period

    # Refusals name the key and the reason; the value stays.
    for value, reason in [(-1.0, "duration"), ("fast", "a double"), (1, "decimal point")]:
        result = params.set("ros.status_period_s", value)
        assert not result.successful and "ros.status_period_s" in result.reason and reason in result.reason, result
    result = params.set("ros.depth_topic", "/elsewhere")
    assert not result.successful and "read-only" in result.reason, result
    result = params.set("mapper.volume_edge_m", 2.0)
    assert not result.successful and "read-only" in result.reason, result
    assert params.get("ros.status_period_s") == [0.1]

    # A mapper threshold (applied at the next frame) and the status period (at the next loop pass).
    iterations = params.get("mapper.fit.max_iterations")[0]
    assert params.set("mapper.fit.max_iterations", iterations + 1).successful
    assert params.get("mapper.fit.max_iterations") == [iterations + 1]

    status = ros.collect(MapperStatus, "/patch_mapper/status")
    status.wait_for(timeout=pw.DEFAULT_TIMEOUT_S)
    asked = time.monotonic()
    assert params.set("ros.status_period_s", 0.02).successful
    answered = time.monotonic()
    # Effect: the first two status messages 0.05 s apart or less (the old period was 0.1 s).
    status.clear()
    arrivals: list[float] = []
    deadline = time.monotonic() + pw.DEFAULT_TIMEOUT_S
    effect = None
    while effect is None and time.monotonic() < deadline:
        before = len(status.messages)
        status.wait_for(lambda _: len(status.messages) > before, timeout=5.0)
        arrivals.append(time.monotonic())
        if len(arrivals) >= 2 and arrivals[-1] - arrivals[-2] < 0.05:
            effect = arrivals[-1]
    assert effect is not None, "the status period did not change"
    window_start = time.monotonic()
    status.clear()
    time.sleep(2.0)
    rate = len(status.messages) / (time.monotonic() - window_start)
    assert rate > 15.0, f"status at {rate:.1f} Hz after setting a 0.02 s period (10 Hz before)"
    log = mapper.stop()
    taken = re.findall(r"parameters ros.status_period_s taken by the loop ([0-9.]+) ms", log)
    assert taken, log[-2000:]
    print(f"\nset -> response {1e3 * (answered - asked):.1f} ms; accepted -> loop {taken[-1]} ms; "
          f"set -> first faster status {1e3 * (effect - asked):.1f} ms; status now {rate:.1f} Hz")


def test_parameter_events_announce_declared_and_changed_values(ros, start_node):
    from rcl_interfaces.msg import ParameterEvent
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    start_node("step_executor", "--param", "ros.status_rate_hz=10.0")
    ros.wait_for_nodes("/step_executor")
    # The startup event (every declared parameter as new) is the writer's last sample: a late
    # transient-local reader gets it.
    latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    events = ros.collect(ParameterEvent, "/parameter_events", latched)
    startup = events.wait_for(lambda e: e.node == "/step_executor" and len(e.new_parameters) > 0, timeout=pw.DEFAULT_TIMEOUT_S)
    announced = {p.name: p.value for p in startup.new_parameters}
    assert "ros.status_rate_hz" in announced and "use_sim_time" in announced, sorted(announced)
    assert announced["ros.status_rate_hz"].double_value == 10.0
    assert startup.stamp.sec > 0, "stamped from the node clock (wall time here)"

    params = Params(ros, "/step_executor")
    assert params.set("ros.status_rate_hz", 25.0).successful
    changed = events.wait_for(lambda e: e.node == "/step_executor" and len(e.changed_parameters) > 0, timeout=pw.DEFAULT_TIMEOUT_S)
    assert [(p.name, p.value.double_value) for p in changed.changed_parameters] == [("ros.status_rate_hz", 25.0)]
    assert not changed.new_parameters and not changed.deleted_parameters
    # A refused value is no event.
    events.clear()
    assert not params.set("ros.status_rate_hz", -3.0).successful
    time.sleep(1.0)
    assert not [e for e in events.messages if e.node == "/step_executor"], events.messages


def test_ros_args_namespace_params_and_params_file(ros, start_node, log_dir, tmp_path):
    params_file = tmp_path / "params.yaml"
    params_file.write_text(
        "/**:\n  ros__parameters:\n    ros:\n      log_period_s: 3.0\n"
        "/robot1/patch_mapper:\n  ros__parameters:\n    ros.publish_markers: false\n"
        "/robot2/patch_mapper:\n  ros__parameters:\n    ros.log_period_s: 9.0\n"
    )
    # What launch_ros runs: no subcommand, the ROS arguments at the end.
    args = ["--ros-args", "-r", "__ns:=/robot1", "-p", "ros.status_period_s:=0.2", "--params-file", str(params_file),
            "--params-file", str(SIM_MAPPER_PARAMS), "--log-level", "info"]
    mapper = pw.NodeProcess("patch_mapper", args, {}, log_dir)
    try:
        ros.wait_for_nodes("/robot1/patch_mapper")
        params = Params(ros, "/robot1/patch_mapper")
        assert params.get("ros.status_period_s", "ros.log_period_s", "ros.publish_markers") == [0.2, 3.0, False]
        assert "[[0.0, -1.0, 0.0]" in params.get("mapper.acquire.camera_from_imu")[0].replace("\n", "")
        ros.wait_for_topic_types({"/robot1/camera/depth/image_raw": "sensor_msgs/msg/Image",
                                  "/robot1/patch_mapper/patches": "patchwalk_msgs/msg/PatchArray"})
        ros.wait_for_service_types({"/robot1/patch_mapper/reset": "std_srvs/srv/Trigger"})
        assert ros.call(Trigger, "/robot1/patch_mapper/reset").success
        ros.collect(MapperStatus, "/robot1/patch_mapper/status").wait_for(timeout=pw.DEFAULT_TIMEOUT_S)
        assert "/patch_mapper" not in ros.node_names()
    finally:
        mapper.stop()
    # `run` with the ROS arguments after it; a bad flag is named.
    bad = subprocess.run([str(pw.binary("patch_mapper")), "run", "--ros-args", "--bogus"], capture_output=True, text=True,
                         timeout=30, cwd=pw.REPO)
    assert bad.returncode == 2 and "--bogus" in bad.stderr, bad


def _sim_bus(log_dir, name):
    log = open(log_dir / f"sim_bus_{name}.log", "w")
    bus = subprocess.Popen([str(pw.binary("step_executor")), "sim-bus"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                           stderr=log, text=True, cwd=pw.REPO)
    pty = bus.stdout.readline().strip()
    assert pty.startswith("/dev/"), f"sim-bus printed {pty!r}"
    return bus, pty


# Six nodes started at once while the harness's participant is up: each is on the graph with its
# node name (Fast DDS used to miss the endpoints a new participant announced during its own discovery).
def test_two_namespaced_robots_share_a_domain_without_crosstalk(ros, start_node, log_dir):
    buses = {}
    executors = []
    try:
        for robot in ["robot1", "robot2"]:
            bus, pty = _sim_bus(log_dir, robot)
            buses[robot] = bus
            ns = ["--ros-args", "-r", f"__ns:=/{robot}"]
            start_node("terrain_sim", *ns, "-p", "camera.rate_hz:=10.0")
            start_node("patch_mapper", *ns, "--params-file", str(SIM_MAPPER_PARAMS))
            executors.append(start_node("step_executor", *ns, "-p", f"bus.port:={pty}", "-p", "bus.response_timeout_ms:=500.0",
                                        "-p", f"library_path:={log_dir / robot / 'motions.yaml'}", "-p", "ros.status_rate_hz:=20.0"))
        nodes = [f"/{r}/{n}" for r in ["robot1", "robot2"] for n in ["terrain_sim", "patch_mapper", "step_executor"]]
        ros.wait_for_nodes(*nodes, timeout=90)
        # Each mapper's maps come from its own simulator and reach its own executor only.
        for robot in ["robot1", "robot2"]:
            patches = ros.collect(PatchArray, f"/{robot}/patch_mapper/patches")
            patches.wait_for(lambda m: len(m.patches) > 0, timeout=120)

            def endpoints(topic, query):
                # The nodes named on the graph (rclpy may also list a RustDDS endpoint a second time
                # without its node, `_NODE_NAME_UNKNOWN_`; the harness's own collectors are left out).
                with ros._lock:
                    return sorted((i.node_namespace, i.node_name) for i in query(topic)
                                  if i.node_name not in (ros.node.get_name(), "_NODE_NAME_UNKNOWN_"))

            deadline = time.monotonic() + pw.DEFAULT_TIMEOUT_S
            while True:
                seen = {
                    "patch publishers": endpoints(f"/{robot}/patch_mapper/patches", ros.node.get_publishers_info_by_topic),
                    "patch subscribers": endpoints(f"/{robot}/patch_mapper/patches", ros.node.get_subscriptions_info_by_topic),
                    "depth publishers": endpoints(f"/{robot}/camera/depth/image_raw", ros.node.get_publishers_info_by_topic),
                    "depth subscribers": endpoints(f"/{robot}/camera/depth/image_raw", ros.node.get_subscriptions_info_by_topic),
                    "joint state subscribers": endpoints(f"/{robot}/joint_states", ros.node.get_subscriptions_info_by_topic),
                }
                expected = {
                    "patch publishers": [(f"/{robot}", "patch_mapper")],
                    "patch subscribers": [(f"/{robot}", "step_executor")],
                    "depth publishers": [(f"/{robot}", "terrain_sim")],
                    "depth subscribers": [(f"/{robot}", "patch_mapper")],
                    "joint state subscribers": [(f"/{robot}", "terrain_sim")],
                }
                if seen == expected or time.monotonic() > deadline:
                    break
                time.sleep(0.2)
            assert seen == expected, f"{robot}: {seen}"
        # No endpoint of the two robots' nodes is left on a root-namespace name. (Root-namespace topics of
        # other nodes may be on the graph: earlier tests on this domain, the harness itself.)
        with ros._lock:
            root_topics = [t for t, _ in ros.node.get_topic_names_and_types() if t.startswith(("/patch_mapper", "/camera", "/step_executor"))]
            left = [(t, e.node_namespace, e.node_name) for t in root_topics
                    for e in ros.node.get_publishers_info_by_topic(t) + ros.node.get_subscriptions_info_by_topic(t)
                    if e.node_namespace in ("/robot1", "/robot2")]
        assert not left, f"endpoints of the namespaced robots left in the root namespace: {left}"

        # A stop to one robot does not stop the other.
        status1 = ros.collect(ExecutorStatus, "/robot1/step_executor/status")
        status2 = ros.collect(ExecutorStatus, "/robot2/step_executor/status")
        assert ros.call(Trigger, "/robot1/step_executor/stop").success
        status1.wait_for(lambda s: s.state == ExecutorStatus.STATE_ESTOPPED, timeout=pw.DEFAULT_TIMEOUT_S)
        status2.clear()
        latest2 = status2.wait_for(timeout=pw.DEFAULT_TIMEOUT_S)
        assert latest2.state != ExecutorStatus.STATE_ESTOPPED, latest2
        status2.clear()
        time.sleep(1.0)
        assert all(s.state != ExecutorStatus.STATE_ESTOPPED for s in status2.messages)
        assert ros.call(Trigger, "/robot1/step_executor/reset_estop").success
    finally:
        for executor in executors:
            if executor.alive():
                executor.stop()
        for bus in buses.values():
            bus.terminate()
            bus.wait(timeout=30)
