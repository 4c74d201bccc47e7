"""The e-stop is answered at once whatever else the executor is doing: during a library write of
several MB (a delete_motion with fsync runs off the node's loop) and during a burst of other calls.
The latencies are printed (pytest -s) and bounded loosely; the order of the answers is the point."""

from __future__ import annotations

import statistics
import threading
import time

from std_srvs.srv import Trigger
from patchwalk_msgs.srv import DeleteMotion, ListMotions

from test_large_service_replies import write_library


def _send(client, request):
    done = threading.Event()
    sent = time.monotonic()
    future = client.call_async(request)
    answered = {}
    future.add_done_callback(lambda _: (answered.setdefault("at", time.monotonic()), done.set()))
    return future, done, sent, answered


def _wait(pending, timeout=30.0):
    future, done, sent, answered = pending
    assert done.wait(timeout), "no answer"
    return future.result(), answered["at"] - sent, answered["at"]


def test_stop_is_answered_during_a_large_library_write(ros, start_node, tmp_path):
    names = write_library(tmp_path / "motions.yaml", 8000)
    start_node("step_executor", "--param", f"library_path={tmp_path / 'motions.yaml'}")
    ros.wait_for_nodes("/step_executor")
    delete = ros.client(DeleteMotion, "/step_executor/delete_motion")
    stop = ros.client(Trigger, "/step_executor/stop")
    listing = ros.client(ListMotions, "/step_executor/list_motions")
    for client in (delete, stop, listing):
        assert client.wait_for_service(timeout_sec=60.0)
    assert len(_wait(_send(listing, ListMotions.Request()))[0].motions) == len(names)
    _wait(_send(stop, Trigger.Request()))  # first call of each client out of the measurement
    latencies = []
    for name in names[:5]:
        deleting = _send(delete, DeleteMotion.Request(name=name))
        time.sleep(0.005)
        stopped = _send(stop, Trigger.Request())
        response, stop_latency, stop_at = _wait(stopped)
        assert response.success
        deleted, delete_latency, delete_at = _wait(deleting)
        assert deleted.success, deleted.message
        latencies.append(stop_latency)
        print(f"delete of 1 of {len(names)} motions: {delete_latency * 1e3:.1f} ms; "
              f"stop sent 5 ms later answered after {stop_latency * 1e3:.1f} ms")
        assert stop_at < delete_at, "the stop waited for the library write"
    print(f"stop during a library write: p50 {statistics.median(latencies) * 1e3:.1f} ms, max {max(latencies) * 1e3:.1f} ms")
    assert max(latencies) < 1.0
    assert [m.name for m in _wait(_send(listing, ListMotions.Request()))[0].motions] == names[5:]
