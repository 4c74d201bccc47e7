"""Service replies of any size reach an rclpy client, and the client's later calls keep working.

A reply larger than one datagram goes out as DATA_FRAG submessages that carry the request's sample
identity in their inline QoS (the "enhanced" RPC mapping). These tests drive the real step_executor
with one rclpy client per service and alternate small and large replies on it, without resending a
request: a reply that is lost or that blocks the client's reliable stream fails the test.
"""

from __future__ import annotations

import json
import threading
import time

import pytest

from patchwalk_msgs.srv import ListMotions, SaveMotion

# Bound for one answer; a working reply comes back in milliseconds.
ANSWER_TIMEOUT_S = 10.0
JOINTS = ["r_hip_yaw", "l_hip_yaw", "r_hip_roll", "l_hip_roll", "r_hip_pitch", "l_hip_pitch",
          "r_knee", "l_knee", "r_ankle_pitch", "l_ankle_pitch", "r_ankle_roll", "l_ankle_roll"]


def write_library(path, count: int) -> list[str]:
    """A motion library file (step_executor's YAML schema; JSON is YAML) with `count` motions."""
    names = [f"motion_{i:04d}_on_rock_{i % 7}" for i in range(count)]
    motions = [{
        "name": name,
        "patch": {"surface": "sphere", "boundary": "circle", "d": [0.03], "k": [9.5],
                  "r": [0.0, 0.0, 0.1], "c": [0.12, 0.04, -0.27]},
        "keyframes": [{"positions": [0.1] * len(JOINTS), "move_s": 0.5, "pause_s": 0.25},
                      {"positions": [-0.1] * len(JOINTS), "move_s": 1.0, "pause_s": 0.0}],
    } for name in names]
    path.write_text(json.dumps({"schema_version": 1, "joints": JOINTS, "motions": motions}))
    return names


def call_once(client, request, timeout: float = ANSWER_TIMEOUT_S):
    """One request, no resend: the response, or an AssertionError naming how long it waited."""
    done = threading.Event()
    started = time.monotonic()
    future = client.call_async(request)
    future.add_done_callback(lambda _: done.set())
    if not done.wait(timeout):
        client.remove_pending_request(future)
        raise AssertionError(f"no response within {timeout} s")
    return future.result(), time.monotonic() - started


@pytest.fixture
def library_executor(ros, start_node, tmp_path):
    names = write_library(tmp_path / "motions.yaml", 1000)
    node = start_node("step_executor", "--param", f"library_path={tmp_path / 'motions.yaml'}")
    ros.wait_for_nodes("/step_executor")
    return node, names


def test_save_motion_replies_of_every_size_arrive_on_one_client(ros, step_executor):
    """Without a servo bus save_motion fails with a message that quotes the name: the reply size is
    the name's size. 100 kB replies and small ones alternate on the same client."""
    client = ros.client(SaveMotion, "/step_executor/save_motion")
    assert client.wait_for_service(timeout_sec=30.0)
    for size in [8, 1_400, 8, 2_000, 100_000, 8, 5_000, 100_000, 100_000, 8, 300_000, 8]:
        name = ("n%07d" % size) * (size // 8) if size >= 8 else "n"
        response, _ = call_once(client, SaveMotion.Request(name=name))
        assert not response.success
        assert name in response.message, f"reply to a {size} B name does not quote it"


def test_list_motions_of_a_thousand_motions_and_calls_after_it(ros, library_executor, tmp_path):
    _, names = library_executor
    listing = ros.client(ListMotions, "/step_executor/list_motions")
    save = ros.client(SaveMotion, "/step_executor/save_motion")
    assert listing.wait_for_service(timeout_sec=30.0) and save.wait_for_service(timeout_sec=30.0)
    for _ in range(5):
        response, _ = call_once(listing, ListMotions.Request())
        assert response.success
        assert [m.name for m in response.motions] == names
        assert all(m.keyframe_count == 2 and m.duration == pytest.approx(1.75) for m in response.motions)
        small, _ = call_once(save, SaveMotion.Request(name="x"))
        assert not small.success and '"x"' in small.message
        large, _ = call_once(save, SaveMotion.Request(name="y" * 100_000))
        assert "y" * 100_000 in large.message
