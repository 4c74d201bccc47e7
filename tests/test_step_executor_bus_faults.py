"""The ROS-visible part of the servo fault matrix: step_executor (`step_executor run`) on the simulated
MX-28 chain (`step_executor sim-bus`), one fault injected at a time through the chain's stdin. Each
must show on /step_executor/status as STATE_HOLDING_FAULT with the servo id and the reason, refuse
play_motion and record_keyframe while latched, and (for the communication faults, once the cause is
gone) clear with set_torque false. The reboot and reconnect recoveries, and every fault during a
motion and during training, are covered through the same master in the Rust test
`bus_fault_matrix.rs`."""

from __future__ import annotations

import time

import pytest
from std_srvs.srv import SetBool
from patchwalk_msgs.msg import ExecutorStatus
from patchwalk_msgs.srv import PlayMotion, RecordKeyframe

from test_sim_bus_dynamixel_sdk import SimBus

# (sim-bus command, expected fault_servo_id, text expected in last_fault, cleared by set_torque false)
FAULTS = [
    ("silence 5", 5, "no response", True),
    ("silence all", 1, "no response", True),
    ("crc 3", 3, "CRC", True),
    ("malformed 4", 4, "malformed status frame", True),
    ("wrongid 6 200", 6, "answer from servo 200", True),
    ("latency 3000", 1, "no response", True),
    ("hwerr 7 0x01", 7, "input voltage", False),
    ("hwerr 7 0x04", 7, "overheating", False),
    ("hwerr 7 0x08", 7, "motor encoder", False),
    ("hwerr 7 0x10", 7, "electrical shock", False),
    ("hwerr 7 0x20", 7, "overload", False),
    ("unplug", 0, "bus I/O error", False),
]


@pytest.fixture
def sim_bus():
    bus = SimBus(12)
    yield bus
    if bus.proc.poll() is None:
        assert bus.stop() == 0


# The first fault the cycle sees wins (an unplugged port can first show as a servo's timeout): one rerun.
@pytest.mark.flaky(reruns=1)
@pytest.mark.parametrize("command,servo,reason,clears", FAULTS, ids=[f[0] for f in FAULTS])
def test_fault_is_reported_latched_and_cleared(ros, start_node, sim_bus, tmp_path, command, servo, reason, clears):
    # 1 s answer budget: a pty on a loaded CI host (see test_step_executor_sim_bus.py).
    start_node("step_executor", "--param", f"bus.port={sim_bus.device}",
               "--param", "bus.response_timeout_ms=1000",
               "--param", f"library_path={tmp_path / 'motions.yaml'}",
               "--param", "ros.status_rate_hz=20")
    ros.wait_for_nodes("/step_executor")
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_IDLE and s.last_fault == "")
    assert ros.call(SetBool, "/step_executor/set_torque", SetBool.Request(data=True)).success

    sim_bus.command(command)
    faulted = status.wait_for(lambda s: s.state == ExecutorStatus.STATE_HOLDING_FAULT, timeout=15)
    assert faulted.fault_servo_id == servo, faulted.last_fault
    assert reason in faulted.last_fault, faulted.last_fault
    # Latched: nothing plays, nothing is recorded.
    played = ros.call(PlayMotion, "/step_executor/play_motion", PlayMotion.Request(name="none"))
    assert not played.success
    recorded = ros.call(RecordKeyframe, "/step_executor/record_keyframe", RecordKeyframe.Request(duration=0.5, pause=0.0))
    assert not recorded.success and "not current" in recorded.message, recorded.message
    assert status.latest().state == ExecutorStatus.STATE_HOLDING_FAULT

    if clears:
        sim_bus.command("clear")
        # Late answers of the latency fault drain before the fault is cleared.
        status.wait_for(lambda s: True, timeout=5)
        time.sleep(3.5 if command.startswith("latency") else 0.3)
        assert ros.call(SetBool, "/step_executor/set_torque", SetBool.Request(data=False)).success
        idle = status.wait_for(lambda s: s.state == ExecutorStatus.STATE_IDLE and s.last_fault == "", timeout=10)
        assert idle.fault_servo_id == 0
        recorded = ros.call(RecordKeyframe, "/step_executor/record_keyframe", RecordKeyframe.Request(duration=0.5, pause=0.0))
        assert recorded.success, recorded.message
    else:
        # A hardware error stays in the servo (and a lost port stays lost): torque off does not clear it.
        ros.call(SetBool, "/step_executor/set_torque", SetBool.Request(data=False))
        again = status.wait_for(lambda s: s.state == ExecutorStatus.STATE_HOLDING_FAULT and s.last_fault != "", timeout=10)
        assert reason in again.last_fault, again.last_fault
