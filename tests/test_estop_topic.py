"""The e-stop topic: a `true` on /step_executor/estop (std_msgs/Bool, reliable, transient local)
latches the e-stop like the stop service; the latched state is on /step_executor/estop_state
(transient local) for a subscriber that comes late; a `false` never clears it (reset_estop does)."""

from __future__ import annotations

import time

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger
from patchwalk_msgs.msg import ExecutorStatus

LATCHED = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     history=HistoryPolicy.KEEP_LAST, depth=1)


def test_a_true_on_the_topic_latches_and_a_late_subscriber_sees_it(ros, step_executor):
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_IDLE)
    estop = ros.publisher(Bool, "/step_executor/estop", qos=LATCHED)
    ros.wait_for_subscriber(estop)
    estop.publish(Bool(data=True))
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_ESTOPPED)
    # A subscriber created after the stop gets the latched state at once.
    late = ros.collect(Bool, "/step_executor/estop_state", qos=LATCHED)
    assert late.wait_for(lambda m: True).data is True
    # Refused while latched, like after the service.
    response = ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True))
    assert not response.success and "reset_estop" in response.message, response.message
    # `false` does not clear it.
    estop.publish(Bool(data=False))
    time.sleep(0.5)
    assert status.latest().state == ExecutorStatus.STATE_ESTOPPED
    status.clear()
    for _ in range(50):
        if ros.call(Trigger, "/step_executor/reset_estop").success:
            break
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_IDLE)
    cleared = ros.collect(Bool, "/step_executor/estop_state", qos=LATCHED)
    assert cleared.wait_for(lambda m: m.data is False).data is False


def test_an_estop_published_before_the_node_started_latches_it(ros, start_node):
    estop = ros.publisher(Bool, "/step_executor/estop", qos=LATCHED)
    estop.publish(Bool(data=True))
    start_node("step_executor")
    ros.wait_for_nodes("/step_executor")
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_ESTOPPED)
