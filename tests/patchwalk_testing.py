"""Fixture library of the patchwalk integration tests: real rclpy (ROS 2 Jazzy wheels) driving the real
node binaries over DDS on loopback.

- `ros_environment()` / `reserve_domain()`: the environment every participant of a test run shares
  (Fast DDS loopback profile, ROS_DOMAIN_ID unique per pytest worker, logs in a temp dir).
- `NodeProcess`: a node binary started with that environment; `stop()` sends SIGINT and checks the
  exit code (clean shutdown) and returns its log.
- `RosHarness`: one rclpy node spinning on a background thread with helpers that all take a timeout:
  `wait_for_nodes`, `collect` (subscription collector with `wait_for`), `publisher`, `call`,
  `publish_until`.

No assertion here depends on timing: timeouts only bound how long a test waits for something that
must happen.
"""

from __future__ import annotations

import fcntl
import os
import signal
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

REPO = Path(__file__).resolve().parents[1]
TARGET_DIR = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target")) / "release"
FASTDDS_PROFILE = REPO / "tests" / "fastdds_loopback.xml"

# How long to wait for something that must happen (discovery, a message, a response). Generous: CI
# machines are small and shared; a passing test never waits this long.
DEFAULT_TIMEOUT_S = 30.0

_domain_lock_file = None


def reserve_domain() -> int:
    """A ROS domain id no other patchwalk test process on this machine holds (flock on a file per id,
    released when the process exits). Domains 100..199 keep clear of the default 0."""
    global _domain_lock_file
    if _domain_lock_file is not None:
        return int(os.environ["ROS_DOMAIN_ID"])
    lock_dir = Path(tempfile.gettempdir()) / "patchwalk_ros_domains"
    lock_dir.mkdir(exist_ok=True)
    start = os.getpid() % 100
    for offset in range(100):
        domain = 100 + (start + offset) % 100
        handle = open(lock_dir / f"{domain}.lock", "w")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _domain_lock_file = handle
        return domain
    raise RuntimeError("no free ROS domain in 100..199")


def ros_environment(log_dir: Path) -> dict[str, str]:
    """Environment of the rclpy side and of the node binaries: DDS on loopback only."""
    domain = reserve_domain()
    env = {
        "ROS_DOMAIN_ID": str(domain),
        "ROS_DISTRO": "jazzy",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        # Jazzy's Fast DDS 2.14 reads FASTRTPS_*, not FASTDDS_*; without the profile's buffers large
        # messages are silently dropped.
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(FASTDDS_PROFILE),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_LOG_DIR": str(log_dir),
        # Wrong field types fail loudly in rclpy message constructors.
        "ROS_PYTHON_CHECK_FIELDS": "1",
        # patchwalk nodes: RustDDS restricted to 127.0.0.1 (also their default).
        "PATCHWALK_DDS_NETWORK": "loopback",
    }
    # The nodes' own default filter keeps the middleware's per-sample lines off (a new node otherwise
    # logs a line for each endpoint a long-lived participant ever disposed); RUST_LOG overrides it.
    if os.environ.get("RUST_LOG"):
        env["RUST_LOG"] = os.environ["RUST_LOG"]
    env.setdefault("HOME", os.environ.get("HOME", str(log_dir)))
    return env


def binary(name: str) -> Path:
    path = TARGET_DIR / name
    if not path.exists():
        raise FileNotFoundError(f"{path} not built: run `cargo build --release --workspace` first")
    return path


def thread_stacks(pid: int) -> str:
    """Every thread's backtrace of a live process (gdb, when installed), to show where a hang is."""
    import shutil

    if shutil.which("gdb") is None:
        return "(gdb not installed: no backtraces)"
    try:
        out = subprocess.run(["gdb", "-p", str(pid), "-batch", "-nx", "-ex", "set pagination off",
                              "-ex", "thread apply all bt 30"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"(gdb failed: {e})"
    return "\n".join(line for line in out.stdout.splitlines() if line.startswith(("Thread ", "#"))) or out.stderr


class NodeProcess:
    """A patchwalk node binary (`<name> run ...`) with its log captured to a file."""

    def __init__(self, name: str, args: list[str], env: dict[str, str], log_dir: Path,
                 executable: Optional[Path] = None, cwd: Optional[Path] = None):
        """`executable` defaults to the cargo build's `binary(name)`, `cwd` to the repository."""
        self.name = name
        self.log_path = log_dir / f"{name}-{time.monotonic_ns()}.log"
        self._log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [str(executable or binary(name)), *args],
            env={**os.environ, **env},
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=cwd or REPO,
        )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGINT, timeout: float = DEFAULT_TIMEOUT_S) -> str:
        """Send `sig`, wait for the exit, assert it was clean (exit code 0); return the log."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                stacks = thread_stacks(self.proc.pid)
                self.proc.kill()
                self.proc.wait()
                raise AssertionError(f"{self.name} did not exit within {timeout} s of {sig!r}:\n{self.log()}\n"
                                     f"its threads then:\n{stacks}")
        self._log.close()
        log = self.log_path.read_text(errors="replace")
        assert self.proc.returncode == 0, f"{self.name} exited with {self.proc.returncode}:\n{log}"
        assert "panicked" not in log, f"{self.name} panicked:\n{log}"
        return log

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._log.close()


@dataclass
class Collector:
    """Messages received on one topic, with a blocking wait."""

    topic: str
    messages: list = field(default_factory=list)
    _cond: threading.Condition = field(default_factory=threading.Condition)
    # What the subscribing side knows of the graph, for the failure message (e.g. the publisher count:
    # publishers seen but nothing received points at the publishing node not matching this reader).
    graph: Callable[[], str] = lambda: ""

    def _on_message(self, msg: Any) -> None:
        with self._cond:
            self.messages.append(msg)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[Any], bool] = lambda _: True, timeout: float = DEFAULT_TIMEOUT_S):
        """First message (received so far or later) that satisfies `predicate`."""
        deadline = time.monotonic() + timeout
        seen = 0
        with self._cond:
            while True:
                for msg in self.messages[seen:]:
                    if predicate(msg):
                        return msg
                seen = len(self.messages)
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.messages[-1] if self.messages else None
                    raise AssertionError(
                        f"no matching message on {self.topic} within {timeout} s "
                        f"({len(self.messages)} received, last: {last}; {self.graph()})"
                    )
                self._cond.wait(left)

    def latest(self, timeout: float = DEFAULT_TIMEOUT_S):
        self.wait_for(timeout=timeout)
        with self._cond:
            return self.messages[-1]

    def clear(self) -> None:
        with self._cond:
            self.messages.clear()


class RosHarness:
    """One rclpy context + node, spun by a background executor thread."""

    def __init__(self, name: str = "pytest_harness"):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self._rclpy = rclpy
        self.context = rclpy.Context()
        from rclpy.signals import SignalHandlerOptions

        # No rclpy signal handlers: Ctrl-C belongs to pytest.
        rclpy.init(context=self.context, domain_id=int(os.environ["ROS_DOMAIN_ID"]),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.callback_errors = 0  # exceptions raised by callbacks (printed; spinning goes on)
        self._thread = threading.Thread(target=self._spin, name="rclpy-spin", daemon=True)
        self._thread.start()
        self._lock = threading.Lock()
        self._entities: list = []  # subscriptions and publishers made for the current test
        self._heartbeats: list = []  # heartbeats started in the current test

    def _spin(self) -> None:
        """Spin until the context shuts down. An exception raised by a callback is printed and spinning
        goes on: one bad callback must not leave the harness deaf to everything after it."""
        import traceback

        from rclpy.executors import ExternalShutdownException, ShutdownException

        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except (ShutdownException, ExternalShutdownException):
                break
            except Exception:
                if not self.context.ok():
                    break
                self.callback_errors += 1
                print(f"rclpy harness {self.node.get_name()}: a callback raised (spinning on):", flush=True)
                traceback.print_exc()

    def destroy_entities(self) -> None:
        """Destroy the subscriptions and publishers created since the last call (end of a test), and
        stop its heartbeats (a failed test must not leave one beating for the next)."""
        for heartbeat in self._heartbeats:
            heartbeat.stop()
        self._heartbeats.clear()
        with self._lock:
            from rclpy.subscription import Subscription

            for entity in self._entities:
                if isinstance(entity, Subscription):
                    self.node.destroy_subscription(entity)
                else:
                    self.node.destroy_publisher(entity)
            self._entities.clear()

    def shutdown(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.shutdown(context=self.context)
        self._thread.join(timeout=5)

    # --- graph -------------------------------------------------------------------------------------

    def node_names(self) -> set[str]:
        return {(ns.rstrip("/") + "/" + name) for name, ns in self.node.get_node_names_and_namespaces()}

    def wait_for_nodes(self, *names: str, timeout: float = DEFAULT_TIMEOUT_S) -> None:
        wanted = {n if n.startswith("/") else "/" + n for n in names}
        deadline = time.monotonic() + timeout
        while not wanted <= self.node_names():
            if time.monotonic() > deadline:
                raise AssertionError(f"nodes {sorted(wanted - self.node_names())} not on the graph within {timeout} s "
                                     f"(graph: {sorted(self.node_names())})")
            time.sleep(0.1)

    def wait_for_topic_types(self, expected: dict[str, str], timeout: float = DEFAULT_TIMEOUT_S) -> None:
        """Wait until every topic of `expected` is on the graph with exactly that type."""
        self._wait_for_types(expected, self.node.get_topic_names_and_types, "topics", timeout)

    def wait_for_service_types(self, expected: dict[str, str], timeout: float = DEFAULT_TIMEOUT_S) -> None:
        self._wait_for_types(expected, self.node.get_service_names_and_types, "services", timeout)

    def _wait_for_types(self, expected, query, what, timeout) -> None:
        deadline = time.monotonic() + timeout
        while True:
            graph = {name: types for name, types in query()}
            missing = {n: t for n, t in expected.items() if t not in graph.get(n, [])}
            if not missing:
                return
            if time.monotonic() > deadline:
                raise AssertionError(f"{what} missing or mistyped after {timeout} s: {missing}; graph has "
                                     f"{ {n: graph.get(n) for n in missing} }")
            time.sleep(0.1)

    # --- topics --------------------------------------------------------------------------------------

    def collect(self, msg_type, topic: str, qos=None) -> Collector:
        from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy

        qos = qos or QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                                depth=10, durability=DurabilityPolicy.VOLATILE)
        collector = Collector(topic, graph=lambda: f"publishers on the graph: {self.node.count_publishers(topic)}")
        with self._lock:
            self._entities.append(self.node.create_subscription(msg_type, topic, collector._on_message, qos))
        return collector

    def publisher(self, msg_type, topic: str, qos=None):
        from rclpy.qos import qos_profile_sensor_data

        with self._lock:
            publisher = self.node.create_publisher(msg_type, topic, qos or qos_profile_sensor_data)
            self._entities.append(publisher)
            return publisher

    def wait_for_subscriber(self, publisher, timeout: float = DEFAULT_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout
        while publisher.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                raise AssertionError(f"no subscriber matched {publisher.topic_name} within {timeout} s")
            time.sleep(0.05)

    def publish_until(self, publisher, msg, collector: Collector, predicate: Callable[[Any], bool],
                      period: float = 0.2, timeout: float = DEFAULT_TIMEOUT_S):
        """Publish `msg` every `period` until `collector` receives a message satisfying `predicate`
        (best-effort sensor topics may drop a sample; the outcome, not the count, is asserted)."""
        self.wait_for_subscriber(publisher, timeout)
        deadline = time.monotonic() + timeout
        while True:
            publisher.publish(msg)
            try:
                return collector.wait_for(predicate, timeout=period)
            except AssertionError:
                if time.monotonic() > deadline:
                    return collector.wait_for(predicate, timeout=0.0)

    def heartbeat(self, period: float = 0.05) -> "Heartbeat":
        """Start publishing the operator's heartbeat (step_executor arms only while it arrives)."""
        heartbeat = Heartbeat(self.node, self._lock, period)
        self._heartbeats.append(heartbeat)
        return heartbeat

    # --- services ------------------------------------------------------------------------------------

    def client(self, srv_type, name: str, depth: int | None = None):
        """A service client; `depth` deepens its request/reply queues (rmw's default keeps 10, so an
        unpaced burst of more calls loses requests in the client's own writer)."""
        with self._lock:
            if depth is None:
                return self.node.create_client(srv_type, name)
            from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy, DurabilityPolicy

            qos = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=depth,
                             durability=DurabilityPolicy.VOLATILE)
            return self.node.create_client(srv_type, name, qos_profile=qos)

    def call(self, srv_type, name: str, request=None, timeout: float = DEFAULT_TIMEOUT_S, attempt_s: float = 5.0):
        """Call service `name` and return its response. A request lost while discovery settles is
        sent again after `attempt_s` (the services used here are idempotent)."""
        client = self.client(srv_type, name)
        try:
            return call_on(client, srv_type, name, request, timeout, attempt_s)
        finally:
            with self._lock:
                self.node.destroy_client(client)


HEARTBEAT_TOPIC = "/step_executor/heartbeat"


class Heartbeat:
    """std_msgs/Empty on /step_executor/heartbeat every `period` s from a thread of its own (an rclpy
    timer would share the spin thread with the test's callbacks), until `stop()`. The executor's
    deadman disarms and holds when heartbeats stop for `ros.heartbeat_timeout_s` (0.5 s)."""

    def __init__(self, node, lock: threading.Lock, period: float = 0.05):
        from std_msgs.msg import Empty

        self._node, self._lock, self._period = node, lock, period
        with lock:
            self._publisher = node.create_publisher(Empty, HEARTBEAT_TOPIC, 10)
        self._msg = Empty()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period):
            try:
                self._publisher.publish(self._msg)
            except Exception:  # the node is being destroyed
                return

    def wait_for_executor(self, timeout: float = DEFAULT_TIMEOUT_S) -> None:
        """Until the executor's subscription has matched and its `/diagnostics` (1 Hz) report a
        heartbeat younger than its timeout: discovery can match this side's writer before the
        executor's reader, and heartbeats sent in between are lost, so a matched subscription alone
        does not mean an `arm` would be accepted."""
        from diagnostic_msgs.msg import DiagnosticArray

        wait_until(lambda: self._publisher.get_subscription_count() > 0, f"a subscriber on {HEARTBEAT_TOPIC}", timeout)
        seen = threading.Event()

        def on_diagnostics(msg) -> None:
            for status in msg.status:
                if status.name.endswith("safety"):
                    values = {v.key: v.value for v in status.values}
                    try:
                        if float(values["heartbeat_age_s"]) < float(values["heartbeat_timeout_s"]):
                            seen.set()
                    except (KeyError, ValueError):  # "never": no heartbeat arrived yet
                        pass

        with self._lock:
            subscription = self._node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        try:
            assert seen.wait(timeout), f"the executor's diagnostics never reported a heartbeat within {timeout} s"
        finally:
            with self._lock:
                self._node.destroy_subscription(subscription)

    def stop(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=5)
        with self._lock:
            self._node.destroy_publisher(self._publisher)

    def __enter__(self) -> "Heartbeat":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def call_on(client, srv_type, name: str, request=None, timeout: float = DEFAULT_TIMEOUT_S, attempt_s: float = 5.0,
            error: type[Exception] = AssertionError):
    """The response of `client` (service `name`): wait for the service, send, and send again after
    `attempt_s` when no answer came (a request lost while discovery settles); `error` when the
    service does not appear or answer within `timeout`."""
    if not client.wait_for_service(timeout_sec=timeout):
        raise error(f"service {name} not available within {timeout} s")
    request = request if request is not None else srv_type.Request()
    deadline = time.monotonic() + timeout
    sent = 0
    while True:
        sent += 1
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if done.wait(min(attempt_s, max(0.0, deadline - time.monotonic()))):
            return future.result()
        client.remove_pending_request(future)
        if time.monotonic() > deadline:
            raise error(f"no response from {name} within {timeout} s ({sent} requests sent; the service was "
                        f"{'still' if client.service_is_ready() else 'no longer'} on the graph)")


def wait_until(condition: Callable[[], bool], what: str, timeout: float = DEFAULT_TIMEOUT_S, period: float = 0.05):
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not true within {timeout} s")
        time.sleep(period)


def depth_image_16uc1(width: int, height: int, frame_id: str = "camera_optical"):
    """A sensor_msgs/Image 16UC1 (mm): a tilted plane from 0.8 m to ~1.4 m, with a hole of zeros."""
    import numpy as np
    from sensor_msgs.msg import Image

    v, u = np.mgrid[0:height, 0:width]
    depth_mm = (800 + 600 * v / max(height - 1, 1) + 50 * u / max(width - 1, 1)).astype("<u2")
    depth_mm[: height // 8, : width // 8] = 0
    msg = Image()
    msg.header.frame_id = frame_id
    msg.height, msg.width = height, width
    msg.encoding = "16UC1"
    msg.is_bigendian = 0
    msg.step = width * 2
    msg.data = depth_mm.tobytes()
    return msg


def depth_image_32fc1(width: int, height: int, frame_id: str = "camera_optical"):
    import numpy as np
    from sensor_msgs.msg import Image

    depth_m = np.full((height, width), 1.25, dtype="<f4")
    depth_m[0, 0] = np.nan
    msg = Image()
    msg.header.frame_id = frame_id
    msg.height, msg.width = height, width
    msg.encoding = "32FC1"
    msg.step = width * 4
    msg.data = depth_m.tobytes()
    return msg


def camera_info(width: int, height: int, f: float = 525.0, frame_id: str = "camera_optical"):
    from sensor_msgs.msg import CameraInfo

    msg = CameraInfo()
    msg.header.frame_id = frame_id
    msg.width, msg.height = width, height
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = [f, 0.0, (width - 1) / 2, 0.0, f, (height - 1) / 2, 0.0, 0.0, 1.0]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [f, 0.0, (width - 1) / 2, 0.0, 0.0, f, (height - 1) / 2, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg
