"""The first call of a fresh client answers as fast as later ones: an operator's e-stop from a new
process must not wait for a DDS heartbeat period.

Each round starts a new rclpy context (its own DDS participant, as a new process would have), waits
for the service like any client does, and times the first call of `/step_executor/stop` and
`/step_executor/list_motions` from there. The bound is end to end across processes, generous for a
loaded machine, and far below the 3 s a request or reply lost to unfinished discovery would cost.
"""

from __future__ import annotations

import os
import statistics
import threading
import time

from std_srvs.srv import Trigger
from patchwalk_msgs.srv import ListMotions

FIRST_CALL_BOUND_S = 1.0
ROUNDS = 6


class FreshParticipant:
    """A new rclpy context with one node, spun on its own thread."""

    def __init__(self, name: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
                   signal_handler_options=SignalHandlerOptions.NO)
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
        self._rclpy.shutdown(context=self.context)
        self._thread.join(timeout=5)


def test_first_call_of_a_fresh_client_is_fast(ros, step_executor):
    times: dict[str, list[float]] = {"/step_executor/stop": [], "/step_executor/list_motions": []}
    for round_index in range(ROUNDS):
        for service, srv_type in (("/step_executor/stop", Trigger), ("/step_executor/list_motions", ListMotions)):
            participant = FreshParticipant(f"first_call_{round_index}_{service.rsplit('/', 1)[-1]}")
            try:
                times[service].append(participant.first_call_s(srv_type, service))
            finally:
                participant.close()
    report = {s: f"p50 {statistics.median(t) * 1e3:.1f} ms, max {max(t) * 1e3:.1f} ms" for s, t in times.items()}
    print(f"first-call latency over {ROUNDS} fresh participants: {report}")
    for service, samples in times.items():
        assert max(samples) < FIRST_CALL_BOUND_S, f"{service}: first calls took {samples} s ({report[service]})"
