"""step_executor over ROS 2: status, arm/stop/reset_estop, the motion list, and clear failures from
the services that are not connected yet."""

import threading
import time

from std_srvs.srv import SetBool, Trigger
from patchwalk_msgs.msg import ExecutorStatus, Patch, PatchArray
from patchwalk_msgs.srv import ListMotions, PlayMotion, RecordKeyframe, SelectTarget

import patchwalk_testing as pw


def _status(ros):
    return ros.collect(ExecutorStatus, "/step_executor/status")


def test_status_is_idle_and_disarmed_at_start(ros, step_executor):
    status = _status(ros).latest()
    assert status.state == ExecutorStatus.STATE_IDLE
    assert not status.armed and not status.torque_enabled
    assert status.library_size == 0


def test_list_motions_is_empty(ros, step_executor):
    response = ros.call(ListMotions, "/step_executor/list_motions")
    assert response.success
    assert list(response.motions) == []


def _heartbeat(ros):
    """Heartbeats running and seen by the executor (arming needs them)."""
    heartbeat = ros.heartbeat()
    heartbeat.wait_for_executor()
    time.sleep(0.3)
    return heartbeat


def test_arm_is_refused_without_a_heartbeat(ros, step_executor):
    response = ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True))
    assert not response.success and "heartbeat" in response.message, response.message
    assert not _status(ros).latest().armed


def test_arm_then_stop_latches_estop(ros, step_executor):
    status = _status(ros)
    heartbeat = _heartbeat(ros)
    # The executor's reader may match the heartbeat writer after rclpy's side did: arm once it has one.
    pw.wait_until(lambda: ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True)).success,
                  "arm accepted (the executor has seen a heartbeat)", timeout=pw.DEFAULT_TIMEOUT_S, period=0.2)
    status.wait_for(lambda s: s.armed)
    response = ros.call(Trigger, "/step_executor/stop")
    assert response.success
    got = status.wait_for(lambda s: s.state == ExecutorStatus.STATE_ESTOPPED)
    assert not got.armed
    # Arming does not clear the latch; reset_estop does, and leaves the executor disarmed.
    response = ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True))
    assert not response.success and "reset_estop" in response.message
    assert ros.call(Trigger, "/step_executor/reset_estop").success
    got = _status(ros).wait_for(lambda s: s.state == ExecutorStatus.STATE_IDLE)  # a fresh collector: after the reset
    assert not got.armed
    heartbeat.stop()


def _clients(ros, srv_type, name, count):
    clients = [ros.client(srv_type, name) for _ in range(count)]
    for client in clients:
        assert client.wait_for_service(timeout_sec=10.0), name
    return clients


def _send(client, request):
    """call_async without waiting; returns an Event set when the answer is in."""
    done = threading.Event()
    future = client.call_async(request)
    future.add_done_callback(lambda _: done.set())
    return future, done


def _answer(pending, timeout=10.0):
    future, done = pending
    assert done.wait(timeout), "no answer"
    return future.result()


def _reset_until_accepted(reset_client):
    # A reset that arrives together with a stop is refused (the stop stays in force): send it again.
    for _ in range(50):
        if _answer(_send(reset_client, Trigger.Request())).success:
            return
    raise AssertionError("reset_estop never accepted")


def test_an_acknowledged_stop_is_not_undone_by_an_arm_sent_just_before_it(ros, step_executor):
    """arm immediately followed by stop, from one client and from two: every time, both are answered
    and the executor ends e-stopped and disarmed (arming then refused) until an explicit reset."""
    (arm_a, arm_b), (stop_a,), (reset,) = (_clients(ros, SetBool, "/step_executor/arm", 2),
                                           _clients(ros, Trigger, "/step_executor/stop", 1),
                                           _clients(ros, Trigger, "/step_executor/reset_estop", 1))
    heartbeat = _heartbeat(ros)
    for trial in range(40):
        arm_client = arm_a if trial % 2 == 0 else arm_b
        armed = _send(arm_client, SetBool.Request(data=True))
        stopped = _send(stop_a, Trigger.Request())
        _answer(armed)
        assert _answer(stopped).success
        probe = _answer(_send(arm_a, SetBool.Request(data=True)))
        assert not probe.success and "reset_estop" in probe.message, f"trial {trial}: armed after an acknowledged stop"
        _reset_until_accepted(reset)
    # A burst of alternating arm/stop ending with a stop ends stopped.
    assert _answer(_send(arm_a, SetBool.Request(data=True))).success
    pending = [_send(arm_a if i % 2 == 0 else stop_a, SetBool.Request(data=True) if i % 2 == 0 else Trigger.Request())
               for i in range(10)]
    for p in pending:
        _answer(p)
    probe = _answer(_send(arm_b, SetBool.Request(data=True)))
    assert not probe.success and "reset_estop" in probe.message
    got = _status(ros).wait_for(lambda s: s.state == ExecutorStatus.STATE_ESTOPPED)
    assert not got.armed
    heartbeat.stop()


def test_a_reset_racing_a_stop_never_clears_it(ros, step_executor):
    """reset_estop sent just before a stop: either the reset was refused or it was taken first; in
    both cases the stop, acknowledged afterwards, is in force."""
    (stop_a,), (reset,), (arm,) = (_clients(ros, Trigger, "/step_executor/stop", 1),
                                   _clients(ros, Trigger, "/step_executor/reset_estop", 1),
                                   _clients(ros, SetBool, "/step_executor/arm", 1))
    assert _answer(_send(stop_a, Trigger.Request())).success
    for trial in range(40):
        resetting = _send(reset, Trigger.Request())
        stopped = _send(stop_a, Trigger.Request())
        _answer(resetting)
        assert _answer(stopped).success
        probe = _answer(_send(arm, SetBool.Request(data=True)))
        assert not probe.success, f"trial {trial}: armed after an acknowledged stop"


def test_unconnected_services_fail_with_a_reason(ros, step_executor):
    response = ros.call(PlayMotion, "/step_executor/play_motion", PlayMotion.Request(name="rock_1"))
    assert not response.success and "not available" in response.message
    response = ros.call(RecordKeyframe, "/step_executor/record_keyframe",
                        RecordKeyframe.Request(duration=1.0, pause=0.5))
    assert not response.success and response.message
    request = SelectTarget.Request(mode=SelectTarget.Request.MODE_NEAREST_POINT, radius=0.05)
    request.point.x = 0.1
    response = ros.call(SelectTarget, "/step_executor/select_target", request)
    assert not response.success and response.message


def test_patch_array_is_accepted(ros, step_executor):
    """A PatchArray with a fully populated patch reaches the node (it stays alive and keeps serving)."""
    patch = Patch(id=7, surface=Patch.ELLIPTIC_PARABOLOID, boundary=Patch.ELLIPSE)
    patch.curvatures = [3.0, -1.5]
    patch.boundary_params = [0.03, 0.02]
    patch.rotation = [0.1, -0.2, 0.0]
    patch.center = [0.2, 0.0, -0.3]
    patch.covariance = [0.0] * 100
    patch.residual = 0.001
    patch.num_points = 321
    msg = PatchArray(patches=[patch] * 50)
    msg.header.frame_id = "map"
    pub = ros.publisher(PatchArray, "/patch_mapper/patches", qos=10)
    ros.wait_for_subscriber(pub)
    for _ in range(5):
        pub.publish(msg)
    assert ros.call(ListMotions, "/step_executor/list_motions").success
    assert step_executor.alive()
