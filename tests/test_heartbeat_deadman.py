"""The heartbeat deadman: arming needs heartbeats on /step_executor/heartbeat; when they stop for
ros.heartbeat_timeout_s (0.5 s) the executor disarms by itself, holds a running motion and says why
(status last_fault). Prints how long after the last heartbeat the disarm was seen."""

from __future__ import annotations

import time

import pytest
from std_srvs.srv import SetBool
from patchwalk_msgs.msg import ExecutorStatus

from test_step_executor_sim_bus import patch_map, sim_bus, train_rock1  # noqa: F401  (fixtures)


@pytest.fixture
def executor_with_deadman(ros, start_node, sim_bus, tmp_path):
    """The executor on the simulated chain with a 1.0 s deadman: longer than a Python heartbeat
    thread stalls on a loaded host, and well within the motion the test trains (4.2 s), so the hold
    comes while it plays even when its PLAYING status reaches the test late."""
    node = start_node("step_executor", "--param", f"bus.port={sim_bus.device}",
                      "--param", "bus.response_timeout_ms=1000",
                      "--param", f"library_path={tmp_path / 'motions.yaml'}",
                      "--param", "ros.status_rate_hz=20", "--param", "ros.heartbeat_timeout_s=1.0")
    ros.wait_for_nodes("/step_executor")
    return node


def test_heartbeats_stopping_disarm_within_the_timeout(ros, step_executor):
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    heartbeat = ros.heartbeat()
    heartbeat.wait_for_executor()
    time.sleep(0.3)
    assert ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True)).success
    status.wait_for(lambda s: s.armed)
    time.sleep(1.0)
    assert status.latest().armed, "kept armed while heartbeats arrive"
    status.clear()
    heartbeat.stop()
    stopped = time.monotonic()
    got = status.wait_for(lambda s: not s.armed, timeout=5.0)
    elapsed = time.monotonic() - stopped
    print(f"deadman: disarm seen on /step_executor/status {elapsed * 1000:.0f} ms after the last heartbeat "
          f"(timeout 500 ms, heartbeat period 50 ms, status at 5 Hz)")
    assert "deadman" in got.last_fault and "heartbeat" in got.last_fault, got.last_fault
    assert elapsed < 3.0, "sanity bound only"
    # Arming is refused without heartbeats, and allowed again once they come back.
    response = ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True))
    assert not response.success and "heartbeat" in response.message, response.message
    with ros.heartbeat() as again:
        again.wait_for_executor()
        time.sleep(0.3)
        assert ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True)).success


def test_a_matched_motion_is_held_when_heartbeats_stop(ros, sim_bus, executor_with_deadman):
    pub = train_rock1(ros, sim_bus, seconds=2.0)
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    heartbeat = ros.heartbeat()
    heartbeat.wait_for_executor()
    time.sleep(0.3)
    assert ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True)).success
    pub.publish(patch_map(0.0))
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_PLAYING and s.current_motion == "rock1")
    status.clear()
    heartbeat.stop()
    stopped = time.monotonic()
    # Held by the deadman (a motion that ended by itself leaves no deadman fault).
    held = status.wait_for(lambda s: s.state != ExecutorStatus.STATE_PLAYING, timeout=5.0)
    elapsed = time.monotonic() - stopped
    print(f"deadman: motion held {elapsed * 1000:.0f} ms after the last heartbeat")
    assert held.state == ExecutorStatus.STATE_IDLE and "deadman" in held.last_fault, (
        f"{held.last_fault!r}; the executor's log:\n" + "\n".join(executor_with_deadman.log().splitlines()[-40:]))
