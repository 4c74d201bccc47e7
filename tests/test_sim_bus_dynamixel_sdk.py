"""The official ROBOTIS `dynamixel-sdk` (PyPI) talks to the simulated MX-28 chain started by
`step_executor sim-bus`: ping, read, write, sync write / sync read, EEPROM lock, and injected faults
(silence, hardware error) as the SDK reports them. No ROS involved."""

from __future__ import annotations

import signal
import subprocess
import time

import pytest
import dynamixel_sdk as dxl

import patchwalk_testing as pw

# The SDK budgets 2 x LATENCY_TIMER (16 ms: an FTDI adapter's USB latency) + 2 ms for an answer. A pty is
# served through kernel work queues, which on a loaded CI machine (pytest -n nproc, ROS nodes) can lag
# by tens of ms, and with both cores saturated a process can wait 200 ms for a time slice (seen: 3
# timeouts in 80 runs of this file, 4 at a time, beside two release builds). Give it the SDK's own
# knob, 250 ms (a ~500 ms answer budget, as the rclpy tests give the Rust master; a silenced servo
# still times out, just later).
dxl.port_handler.LATENCY_TIMER = 250

PROTOCOL = 2.0
BAUD = 1_000_000
MODEL_MX28_P2 = 30
ADDR_MODEL, ADDR_RETURN_DELAY, ADDR_TORQUE, ADDR_HW_ERROR = 0, 9, 64, 70
ADDR_GOAL, ADDR_MOVING, ADDR_PRESENT = 116, 122, 132
ACCESS_ERROR = 7
ALERT = 0x80


class SimBus:
    """`step_executor sim-bus --servos N` with its stdin kept for fault commands."""

    def __init__(self, servos: int):
        self.proc = subprocess.Popen(
            [str(pw.binary("step_executor")), "sim-bus", "--servos", str(servos)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.device = self.proc.stdout.readline().strip()
        assert self.device.startswith("/dev/"), f"sim-bus printed {self.device!r}: {self.proc.stderr.read()}"

    def command(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        time.sleep(0.1)  # applied by the chain's control thread

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGINT)
        return self.proc.wait(timeout=10)


@pytest.fixture
def sim_bus():
    bus = SimBus(12)
    yield bus
    if bus.proc.poll() is None:
        assert bus.stop() == 0


@pytest.fixture
def sdk(sim_bus):
    port = dxl.PortHandler(sim_bus.device)
    assert port.openPort()
    assert port.setBaudRate(BAUD)
    yield port, dxl.PacketHandler(PROTOCOL)
    port.closePort()


def ok(result, error) -> None:
    assert result == dxl.COMM_SUCCESS and error == 0, f"result {result}, error {error:#x}"


def test_ping_every_servo_reports_mx28_protocol2(sdk):
    port, packet = sdk
    for dxl_id in range(1, 13):
        model, result, error = packet.ping(port, dxl_id)
        ok(result, error)
        assert model == MODEL_MX28_P2
    _, result, _ = packet.ping(port, 13)
    assert result == dxl.COMM_RX_TIMEOUT
    found, result = packet.broadcastPing(port)
    assert result == dxl.COMM_SUCCESS
    assert sorted(found) == list(range(1, 13))
    assert all(model == MODEL_MX28_P2 for model, _firmware in found.values())


def test_read_write_and_eeprom_lock(sdk):
    port, packet = sdk
    model, result, error = packet.read2ByteTxRx(port, 4, ADDR_MODEL)
    ok(result, error)
    assert model == MODEL_MX28_P2
    ok(*packet.write1ByteTxRx(port, 4, ADDR_RETURN_DELAY, 0))  # EEPROM, torque off: allowed
    ok(*packet.write1ByteTxRx(port, 4, ADDR_TORQUE, 1))
    result, error = packet.write1ByteTxRx(port, 4, ADDR_RETURN_DELAY, 10)  # EEPROM, torque on
    assert result == dxl.COMM_SUCCESS and error == ACCESS_ERROR
    ok(*packet.write4ByteTxRx(port, 4, ADDR_GOAL, 2548))
    # Arrived: the present position is the goal and the servo has stopped. Present Position is
    # rounded to ticks, so it can read the goal in the last tick of the move, still moving.
    deadline = time.time() + 3.0
    present, moving = 2048, 1
    while time.time() < deadline:
        present, result, error = packet.read4ByteTxRx(port, 4, ADDR_PRESENT)
        ok(result, error)
        moving, result, error = packet.read1ByteTxRx(port, 4, ADDR_MOVING)
        ok(result, error)
        if present == 2548 and moving == 0:
            break
        time.sleep(0.01)
    assert (present, moving) == (2548, 0)


def test_group_sync_write_and_sync_read_twelve_servos(sdk):
    port, packet = sdk
    ids = list(range(1, 13))
    torque = dxl.GroupSyncWrite(port, packet, ADDR_TORQUE, 1)
    for dxl_id in ids:
        assert torque.addParam(dxl_id, [1])
    assert torque.txPacket() == dxl.COMM_SUCCESS
    goals = {dxl_id: 2048 + 20 * dxl_id for dxl_id in ids}
    writer = dxl.GroupSyncWrite(port, packet, ADDR_GOAL, 4)
    for dxl_id, goal in goals.items():
        assert writer.addParam(dxl_id, list(goal.to_bytes(4, "little")))
    assert writer.txPacket() == dxl.COMM_SUCCESS
    reader = dxl.GroupSyncRead(port, packet, ADDR_PRESENT, 4)
    for dxl_id in ids:
        assert reader.addParam(dxl_id)
    deadline = time.time() + 3.0
    while True:
        assert reader.txRxPacket() == dxl.COMM_SUCCESS
        present = {dxl_id: reader.getData(dxl_id, ADDR_PRESENT, 4) for dxl_id in ids}
        if present == goals or time.time() > deadline:
            break
        time.sleep(0.01)
    assert present == goals


def test_injected_faults_are_seen_by_the_sdk(sim_bus, sdk):
    port, packet = sdk
    sim_bus.command("silence 3")
    _, result, _ = packet.ping(port, 3)
    assert result == dxl.COMM_RX_TIMEOUT
    sim_bus.command("hwerr 5 0x20")  # overload
    value, result, error = packet.read1ByteTxRx(port, 5, ADDR_HW_ERROR)
    assert result == dxl.COMM_SUCCESS
    assert error & ALERT and value == 0x20
    result, error = packet.reboot(port, 5)
    assert result == dxl.COMM_SUCCESS
    # A rebooting servo is silent for its boot time (as a real MX-28): ping until it answers.
    deadline = time.monotonic() + 5.0
    while packet.ping(port, 5)[1] != dxl.COMM_SUCCESS:
        assert time.monotonic() < deadline, "servo 5 did not answer within 5 s of its reboot"
    value, result, error = packet.read1ByteTxRx(port, 5, ADDR_HW_ERROR)
    ok(result, error)
    assert value == 0
    sim_bus.command("clear")
    _, result, error = packet.ping(port, 3)
    ok(result, error)


def test_sim_bus_exits_cleanly_on_sigint(sim_bus):
    assert sim_bus.stop() == 0
