"""The first call of a fresh client answers as fast as later ones: an operator's e-stop from a new
process must not wait for a DDS heartbeat period.

Two kinds of fresh clients, each waiting for the service like any client does before the first call
of `/step_executor/stop` and `/step_executor/list_motions` is timed: a new rclpy node in the harness's
context (new endpoints on a participant the server already knows: the server discovers the client's
request writer just as the first request arrives), and a new rclpy context (its own DDS participant,
as a new process has). The bound is end to end across processes, generous for a loaded machine, and
far below the 3 s a request lost to unfinished discovery costs (Fast DDS resends it on its next
periodic heartbeat).
"""

from __future__ import annotations

import os
import statistics
import threading
import time

from std_srvs.srv import Trigger
from patchwalk_msgs.srv import ListMotions

FIRST_CALL_BOUND_S = 1.0
ROUNDS_SHARED = 15
ROUNDS_OWN = 5


class FreshClientNode:
    """A new rclpy node spun on its own thread: in `context` (sharing its participant), or in a new
    context of its own (a new participant)."""

    def __init__(self, name: str, context=None):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self._rclpy = rclpy
        self._own_context = context is None
        if self._own_context:
            context = rclpy.Context()
            rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
                       signal_handler_options=SignalHandlerOptions.NO)
        self.context = context
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # context shut down
            pass

    def first_call_s(self, srv_type, service: str, timeout: float = 10.0) -> float:
        """Seconds from sending the first request (after wait_for_service) to its response."""
        client = self.node.create_client(srv_type, service)
        assert client.wait_for_service(timeout_sec=30.0), f"{service} not available"
        done = threading.Event()
        started = time.monotonic()
        future = client.call_async(srv_type.Request())
        future.add_done_callback(lambda _: done.set())
        assert done.wait(timeout), f"no response from {service} within {timeout} s"
        elapsed = time.monotonic() - started
        assert future.result() is not None
        return elapsed

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        if self._own_context:
            self._rclpy.shutdown(context=self.context)
        self._thread.join(timeout=5)


SERVICES = (("/step_executor/stop", Trigger), ("/step_executor/list_motions", ListMotions))


def measure(make_node, rounds: int) -> dict[str, list[float]]:
    times: dict[str, list[float]] = {service: [] for service, _ in SERVICES}
    for round_index in range(rounds):
        for service, srv_type in SERVICES:
            node = make_node(f"first_call_{round_index}_{service.rsplit('/', 1)[-1]}")
            try:
                times[service].append(node.first_call_s(srv_type, service))
            finally:
                node.close()
    return times


def check(times: dict[str, list[float]], what: str) -> None:
    report = {s: f"p50 {statistics.median(t) * 1e3:.1f} ms, max {max(t) * 1e3:.1f} ms" for s, t in times.items()}
    print(f"first-call latency, {what}: {report}")
    for service, samples in times.items():
        assert max(samples) < FIRST_CALL_BOUND_S, f"{service}: first calls took {samples} s ({report[service]})"


def settled(ros) -> None:
    """One answered call before the timed ones: a server that has just started first takes in the
    discovery history of the harness's participant (which grows with every node and client the test
    module made), and the first call of the first client would time that instead of the client's."""
    ros.call(ListMotions, "/step_executor/list_motions")


def test_first_call_of_a_new_node_on_a_known_participant_is_fast(ros, step_executor):
    settled(ros)
    check(measure(lambda name: FreshClientNode(name, ros.context), ROUNDS_SHARED), "new nodes, shared participant")


def test_first_call_of_a_new_participant_is_fast(ros, step_executor):
    settled(ros)
    check(measure(FreshClientNode, ROUNDS_OWN), "new participants")
