"""kill -9 of the executor at random moments of a library write leaves the library old or new, never
broken, and a restart cleans up what the killed write left behind.

Each round starts step_executor on a library of 800 motions, asks it to delete one (the write of the
whole file runs on its job worker), waits until the write has begun (its temp file appears beside
the library) and kills the process with SIGKILL after a random delay of 0-20 ms: while writing, at
fsync, around the rename, or after it. PATCHWALK_CRASH_ROUNDS raises the number of
rounds (default 12; the long campaign uses 100)."""

from __future__ import annotations

import os
import random
import threading
import time

import yaml

from patchwalk_msgs.srv import DeleteMotion, ListMotions

from test_large_service_replies import write_library

ROUNDS = int(os.environ.get("PATCHWALK_CRASH_ROUNDS", "12"))


def _motion_names(path):
    data = yaml.safe_load(path.read_text())
    assert data["schema_version"] == 1
    return [m["name"] for m in data["motions"]]


def test_kill_9_during_library_writes_never_breaks_the_library(ros, start_node, tmp_path):
    library = tmp_path / "motions.yaml"
    names = write_library(library, 800)
    rng = random.Random(20261201)
    outcomes = {"old": 0, "new": 0}
    for round_index in range(ROUNDS):
        node = start_node("step_executor", "--param", f"library_path={library}")
        ros.wait_for_nodes("/step_executor")
        client = ros.client(DeleteMotion, "/step_executor/delete_motion")
        assert client.wait_for_service(timeout_sec=60.0)
        victim = names[0]
        done = threading.Event()
        client.call_async(DeleteMotion.Request(name=victim)).add_done_callback(lambda _: done.set())
        stale = {p.name for p in tmp_path.iterdir() if p.name.startswith(".motions.yaml.tmp-")}
        deadline, resend = time.monotonic() + 20.0, time.monotonic() + 1.0
        while not done.is_set() and not any(p.name.startswith(".motions.yaml.tmp-") and p.name not in stale for p in tmp_path.iterdir()):
            assert time.monotonic() < deadline, "the delete never started writing"
            if time.monotonic() > resend:  # a request lost while discovery settles
                client.call_async(DeleteMotion.Request(name=victim)).add_done_callback(lambda _: done.set())
                resend = time.monotonic() + 1.0
            time.sleep(0.0002)
        time.sleep(rng.uniform(0.0, 0.02))
        node.kill()
        after = _motion_names(library)  # parses: never a torn file
        if after == names:
            outcomes["old"] += 1
        else:
            assert after == names[1:], f"round {round_index}: neither the old nor the new library"
            outcomes["new"] += 1
            names = after
    print(f"{ROUNDS} kills during deletes: library old {outcomes['old']}, new {outcomes['new']}, broken 0")
    # A restart removes the temp files killed writes left beside the library and serves the library.
    node = start_node("step_executor", "--param", f"library_path={library}")
    ros.wait_for_nodes("/step_executor")
    response = ros.call(ListMotions, "/step_executor/list_motions")
    assert [m.name for m in response.motions] == names
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".motions.yaml.tmp-")]
    assert not leftovers, f"stale temp files after a restart: {leftovers}"
