"""/diagnostics (diagnostic_msgs/DiagnosticArray, 1 Hz) of both nodes: patch_mapper's inputs,
latency, drops, tracking and map; step_executor's bus, servos, cycle, library and safety, with an
injected bus fault on the simulated chain reported as ERROR naming the servo."""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from sensor_msgs.msg import Image
from patchwalk_msgs.msg import ExecutorStatus
from patchwalk_msgs.srv import PlayMotion

import patchwalk_testing as pw
from test_step_executor_sim_bus import executor_on_sim_bus, sim_bus, train_rock1  # noqa: F401  (fixtures)


def _statuses(array) -> dict[str, DiagnosticStatus]:
    return {s.name: s for s in array.status}


def _from(hardware_id: str):
    return lambda m: bool(m.status) and m.status[0].hardware_id == hardware_id


def test_step_executor_without_a_bus_reports_the_bus_as_an_error(ros, step_executor):
    diagnostics = ros.collect(DiagnosticArray, "/diagnostics")
    got = _statuses(diagnostics.wait_for(_from("step_executor")))
    bus = got["step_executor: servo bus"]
    assert bus.level == DiagnosticStatus.ERROR and "no servo bus" in bus.message, bus.message
    safety = got["step_executor: safety"]
    values = {kv.key: kv.value for kv in safety.values}
    assert values["estop_latched"] == "false" and values["armed"] == "false" and values["heartbeat_age_s"] == "never"
    assert got["step_executor: motion library"].level == DiagnosticStatus.WARN  # empty library
    assert all(s.hardware_id == "step_executor" for s in got.values())


def test_step_executor_reports_a_bus_fault_with_the_servo(ros, sim_bus, executor_on_sim_bus):
    diagnostics = ros.collect(DiagnosticArray, "/diagnostics")
    healthy = _statuses(diagnostics.wait_for(lambda m: _from("step_executor")(m) and any("servo 3" in s.name for s in m.status)))
    assert healthy["step_executor: servo bus"].level == DiagnosticStatus.OK
    assert healthy["step_executor: servo 3 (r_hip_roll)"].level == DiagnosticStatus.OK
    cycle = {kv.key: kv.value for kv in healthy["step_executor: control cycle"].values}
    assert float(cycle["rate_hz"]) > 0.0
    train_rock1(ros, sim_bus)
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    assert ros.call(PlayMotion, "/step_executor/play_motion", PlayMotion.Request(name="rock1")).success
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_PLAYING)
    time.sleep(0.2)
    sim_bus.command("silence 3")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_HOLDING_FAULT)
    diagnostics.clear()
    faulted = _statuses(diagnostics.wait_for(
        lambda m: _from("step_executor")(m) and _statuses(m)["step_executor: servo bus"].level == DiagnosticStatus.ERROR))
    bus = faulted["step_executor: servo bus"]
    assert "servo 3" in bus.message and "set_torque false" in bus.message, bus.message
    servo = faulted["step_executor: servo 3 (r_hip_roll)"]
    assert servo.level == DiagnosticStatus.ERROR and "r_hip_roll" in servo.message, servo.message


def test_patch_mapper_reports_inputs_latency_and_map(ros, patch_mapper):
    diagnostics = ros.collect(DiagnosticArray, "/diagnostics")
    idle = _statuses(diagnostics.wait_for(_from("patch_mapper")))
    assert idle["patch_mapper: inputs"].level == DiagnosticStatus.ERROR and "no depth" in idle["patch_mapper: inputs"].message
    # Depth frames without a CameraInfo are skipped: dropped, with the reason.
    depth = ros.publisher(Image, "/camera/depth/image_raw")
    ros.wait_for_subscriber(depth)
    diagnostics.clear()
    deadline = time.monotonic() + 10
    while True:
        depth.publish(pw.depth_image_16uc1(64, 48))
        time.sleep(0.05)
        arrays = [m for m in diagnostics.messages if _from("patch_mapper")(m)]
        dropped = [_statuses(m)["patch_mapper: dropped frames"] for m in arrays]
        if any(d.level == DiagnosticStatus.WARN for d in dropped) or time.monotonic() > deadline:
            break
    warned = [d for d in dropped if d.level == DiagnosticStatus.WARN]
    assert warned and "skipped" in warned[-1].message, [d.message for d in dropped]
    got = _statuses(arrays[-1])
    assert {"patch_mapper: inputs", "patch_mapper: latency", "patch_mapper: tracking", "patch_mapper: map"} <= got.keys()
    assert all(s.hardware_id == "patch_mapper" for s in got.values())
