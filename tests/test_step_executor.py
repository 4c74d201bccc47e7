"""step_executor over ROS 2: status, arm/stop, the motion list, and clear failures from the services
that are not connected yet."""

from std_srvs.srv import SetBool, Trigger
from patchwalk_msgs.msg import ExecutorStatus, Patch, PatchArray
from patchwalk_msgs.srv import ListMotions, PlayMotion, RecordKeyframe, SelectTarget


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


def test_arm_then_stop_latches_estop(ros, step_executor):
    status = _status(ros)
    assert ros.call(SetBool, "/step_executor/arm", SetBool.Request(data=True)).success
    status.wait_for(lambda s: s.armed)
    response = ros.call(Trigger, "/step_executor/stop")
    assert response.success
    got = status.wait_for(lambda s: s.state == ExecutorStatus.STATE_ESTOPPED)
    assert not got.armed


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
