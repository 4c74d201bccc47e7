"""Every joint step_executor publishes on /joint_states is a movable joint of urdf/rpbp.urdf, the model
robot_state_publisher turns those joint states into /tf with (a name it does not know leaves that link
without a transform in RViz)."""

from __future__ import annotations

import signal
import subprocess
import xml.etree.ElementTree as ET

import pytest
from sensor_msgs.msg import JointState

import patchwalk_testing as pw

URDF = pw.REPO / "urdf" / "rpbp.urdf"


@pytest.fixture
def sim_bus_device():
    proc = subprocess.Popen([str(pw.binary("step_executor")), "sim-bus", "--servos", "12"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    device = proc.stdout.readline().strip()
    assert device.startswith("/dev/"), f"sim-bus printed {device!r}: {proc.stderr.read()}"
    yield device
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=10) == 0


def movable_joints(urdf) -> set[str]:
    robot = ET.parse(urdf).getroot()
    assert robot.tag == "robot"
    return {j.get("name") for j in robot.findall("joint") if j.get("type") not in ("fixed", None)}


def test_published_joint_names_are_movable_joints_of_the_urdf(ros, start_node, sim_bus_device, tmp_path):
    joints = ros.collect(JointState, "/joint_states")
    start_node("step_executor", "--param", f"bus.port={sim_bus_device}", "--param", "bus.response_timeout_ms=1000",
               "--param", f"library_path={tmp_path / 'motions.yaml'}")
    msg = joints.wait_for(lambda m: len(m.name) > 0)
    names = list(msg.name)
    assert len(names) == 12 and len(set(names)) == 12, names
    assert len(msg.position) == len(names)
    unknown = set(names) - movable_joints(URDF)
    assert not unknown, f"/joint_states names {sorted(unknown)} are not movable joints of {URDF}"
