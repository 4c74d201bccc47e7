"""pytest fixtures of the patchwalk integration tests (see patchwalk_testing.py for the library).

Every pytest process (each xdist worker too) reserves its own ROS domain and puts the loopback DDS
environment into os.environ before rclpy is imported, so parallel workers and parallel runs on one
machine do not see each other.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

import patchwalk_testing as pw

_LOG_DIR = Path(tempfile.mkdtemp(prefix="patchwalk_pytest_"))
ENV = pw.ros_environment(_LOG_DIR)
os.environ.update(ENV)  # before rclpy is imported anywhere



def pytest_configure(config):
    config.addinivalue_line("markers", "fresh_clone: runs launch_scripts/demo.sh in a fresh clone (own venv from PyPI, minutes)")


# Binaries whose ROS node is started with `<binary> run ...`; others take their options directly.
RUN_SUBCOMMAND = {"patch_mapper", "step_executor", "terrain_sim"}


@pytest.fixture(scope="module")
def _ros_harness():
    """One rclpy participant per test module. A node that starts receives the whole discovery history
    of every participant on the graph, and Fast DDS keeps an entry for each endpoint a participant
    removed until every matched participant acknowledged it (a killed node holds it back until its
    lease ends): a harness living for the whole session (thousands of clients, subscriptions and nodes
    made and destroyed) would make each new node spend seconds taking it in before it sees the
    harness's newest subscriptions and clients, and the wait grows with the session's age."""
    harness = pw.RosHarness()
    yield harness
    harness.shutdown()


@pytest.fixture
def ros(_ros_harness):
    """The rclpy harness of this pytest process; what a test subscribes/publishes is destroyed after it."""
    yield _ros_harness
    _ros_harness.destroy_entities()


@pytest.fixture
def log_dir(tmp_path) -> Path:
    return tmp_path


@pytest.fixture
def start_node(log_dir):
    """Factory: `start_node("patch_mapper", "--param", "ros.status_period_s=0.2")` starts
    `<binary> run <args>` (`<binary> <args>` for binaries without a `run` subcommand); at teardown
    every node still running is stopped with SIGINT and must exit cleanly (exit code 0, no panic)."""
    started: list[pw.NodeProcess] = []

    def start(name: str, *args: str, env: dict[str, str] | None = None) -> pw.NodeProcess:
        args = ("run", *args) if name in RUN_SUBCOMMAND else args
        node = pw.NodeProcess(name, list(args), {**ENV, **(env or {})}, log_dir)
        started.append(node)
        return node

    yield start
    errors = []
    for node in started:
        try:
            if node.proc.returncode is None:
                node.stop()
        except AssertionError as e:
            errors.append(str(e))
    assert not errors, "\n".join(errors)


@pytest.fixture
def patch_mapper(ros, start_node):
    """A running patch_mapper on the graph, status every 0.1 s."""
    node = start_node("patch_mapper", "--param", "ros.status_period_s=0.1")
    ros.wait_for_nodes("/patch_mapper")
    return node


@pytest.fixture
def step_executor(ros, start_node):
    """A running step_executor on the graph, status at 20 Hz."""
    node = start_node("step_executor", "--param", "ros.status_rate_hz=20")
    ros.wait_for_nodes("/step_executor")
    return node
