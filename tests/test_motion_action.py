"""The PlayMotion action (/step_executor/play_motion, patchwalk_msgs/action/PlayMotion) against the
simulated servo chain: feedback while a trained motion plays and the COMPLETED result; cancel holds
the pose without latching the e-stop; goals are refused (with the reason) while e-stopped or while
a motion plays; a bus fault ends the goal FAULTED with the servo."""

from __future__ import annotations

import threading
import time

from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from std_srvs.srv import Trigger
from patchwalk_msgs.action import PlayMotion
from patchwalk_msgs.msg import ExecutorStatus

from test_step_executor_sim_bus import executor_on_sim_bus, sim_bus, train_rock1  # noqa: F401  (fixtures)

ACTION = "/step_executor/play_motion"


def _wait(future, timeout: float = 10.0):
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    assert done.wait(timeout), "no answer"
    return future.result()


class Goal:
    """One goal sent through an rclpy ActionClient, with its feedback."""

    def __init__(self, client: ActionClient, name: str):
        self.feedback: list = []
        self.handle = _wait(client.send_goal_async(PlayMotion.Goal(name=name),
                                                   feedback_callback=lambda m: self.feedback.append(m.feedback)))
        assert self.handle.accepted
        self._result = self.handle.get_result_async()

    def result(self, timeout: float = 10.0):
        return _wait(self._result, timeout)


def _client(ros) -> ActionClient:
    with ros._lock:
        client = ActionClient(ros.node, PlayMotion, ACTION)
    assert client.wait_for_server(timeout_sec=10.0), f"action server {ACTION} not available"
    return client


def test_goal_plays_with_feedback_and_completes(ros, sim_bus, executor_on_sim_bus):
    train_rock1(ros, sim_bus)
    client = _client(ros)
    goal = Goal(client, "rock1")
    done = goal.result()
    assert done.status == GoalStatus.STATUS_SUCCEEDED, done.result.message
    assert done.result.outcome == PlayMotion.Result.OUTCOME_COMPLETED and "completed" in done.result.message
    assert len(goal.feedback) >= 5, "feedback at least every 100 ms over the 1.4 s motion"
    assert all(f.keyframe_count == 2 for f in goal.feedback)
    fractions = [f.fraction_done for f in goal.feedback]
    assert fractions == sorted(fractions) and 0.0 <= fractions[0] and fractions[-1] <= 1.0
    keyframes = [f.keyframe_index for f in goal.feedback]
    assert keyframes == sorted(keyframes) and keyframes[-1] == 1, keyframes


def test_cancel_holds_without_latching_the_estop(ros, sim_bus, executor_on_sim_bus):
    train_rock1(ros, sim_bus)
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    client = _client(ros)
    goal = Goal(client, "rock1")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_PLAYING)
    time.sleep(0.2)
    cancel = _wait(goal.handle.cancel_goal_async())
    assert len(cancel.goals_canceling) == 1
    status.clear()
    done = goal.result()
    assert done.status == GoalStatus.STATUS_CANCELED, done.result.message
    assert done.result.outcome == PlayMotion.Result.OUTCOME_CANCELLED and "not latched" in done.result.message
    after = status.wait_for(lambda s: s.state != ExecutorStatus.STATE_PLAYING)
    assert after.state == ExecutorStatus.STATE_IDLE, "cancel does not latch the e-stop"
    # The next goal starts at once and completes.
    again = Goal(client, "rock1").result()
    assert again.status == GoalStatus.STATUS_SUCCEEDED, again.result.message


def test_goals_are_refused_with_the_reason_while_playing_or_estopped(ros, sim_bus, executor_on_sim_bus):
    train_rock1(ros, sim_bus)
    client = _client(ros)
    first = Goal(client, "rock1")
    second = Goal(client, "rock1").result()
    assert second.status == GoalStatus.STATUS_ABORTED
    assert second.result.outcome == PlayMotion.Result.OUTCOME_REFUSED and "running" in second.result.message, second.result.message
    assert first.result().status == GoalStatus.STATUS_SUCCEEDED
    unknown = Goal(client, "no such motion").result()
    assert unknown.result.outcome == PlayMotion.Result.OUTCOME_REFUSED and "no such motion" in unknown.result.message
    assert ros.call(Trigger, "/step_executor/stop").success
    refused = Goal(client, "rock1").result()
    assert refused.status == GoalStatus.STATUS_ABORTED
    assert refused.result.outcome == PlayMotion.Result.OUTCOME_REFUSED and "e-stop" in refused.result.message, refused.result.message


def test_an_estop_during_a_goal_ends_it(ros, sim_bus, executor_on_sim_bus):
    train_rock1(ros, sim_bus)
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    client = _client(ros)
    goal = Goal(client, "rock1")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_PLAYING)
    assert ros.call(Trigger, "/step_executor/stop").success
    done = goal.result()
    assert done.status == GoalStatus.STATUS_ABORTED
    assert done.result.outcome == PlayMotion.Result.OUTCOME_CANCELLED and "e-stop" in done.result.message


def test_a_bus_fault_ends_the_goal_faulted_with_the_servo(ros, sim_bus, executor_on_sim_bus):
    train_rock1(ros, sim_bus)
    status = ros.collect(ExecutorStatus, "/step_executor/status")
    client = _client(ros)
    goal = Goal(client, "rock1")
    status.wait_for(lambda s: s.state == ExecutorStatus.STATE_PLAYING)
    time.sleep(0.2)
    sim_bus.command("silence 3")
    done = goal.result()
    assert done.status == GoalStatus.STATUS_ABORTED
    assert done.result.outcome == PlayMotion.Result.OUTCOME_FAULTED
    assert done.result.fault_servo_id == 3 and "r_hip_roll" in done.result.message, done.result.message
