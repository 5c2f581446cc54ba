"""The /print action from outside, as `ros2 action send_goal` on rmw_cyclonedds makes it.

Written from rcl's and rmw_cyclonedds's sources (docs/design/actions-and-services.md §2, §4):
three services (`<action>/_action/send_goal`, `cancel_goal`, `get_result`) in rmw_cyclonedds's
request/reply format (the `{guid, seq}` header before the body), the feedback topic, and the
transient-local status topic. `polar-cell serve` runs each goal as a print at machine pace.
"""

import math
import os
import random
import signal
import subprocess
import time
from dataclasses import dataclass

import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as t
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
import pytest

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import binary
from rmw_cyclone import ServiceClient
from test_dds import Time, ros_qos
from test_services import TriggerRequest, TriggerResponse, trigger

DOMAIN = 78
PKG = "polar_cell_msgs::action::dds_::"


@dataclass
@annotate.final
class UUID(IdlStruct, typename="unique_identifier_msgs::msg::dds_::UUID_"):
    uuid: t.array[t.uint8, 16]


@dataclass
@annotate.final
class GoalInfo(IdlStruct, typename="action_msgs::msg::dds_::GoalInfo_"):
    goal_id: UUID
    stamp: Time


@dataclass
@annotate.final
class GoalStatus(IdlStruct, typename="action_msgs::msg::dds_::GoalStatus_"):
    goal_info: GoalInfo
    status: t.int8


@dataclass
@annotate.final
class GoalStatusArray(IdlStruct, typename="action_msgs::msg::dds_::GoalStatusArray_"):
    status_list: t.sequence[GoalStatus]


@dataclass
@annotate.final
class PrintGoal(IdlStruct, typename=PKG + "Print_Goal_"):
    gcode_file: str
    speed: float


@dataclass
@annotate.final
class PrintResult(IdlStruct, typename=PKG + "Print_Result_"):
    ended: str
    message: str
    moves_executed: t.uint64
    machine_time_s: float
    stop_position: t.sequence[float]
    bag: str


@dataclass
@annotate.final
class PrintFeedback(IdlStruct, typename=PKG + "Print_Feedback_"):
    line: t.uint32
    move_sequence: t.uint64
    percent: t.float32
    elapsed_s: float
    remaining_s: float
    state: str


@dataclass
@annotate.final
class SendGoalRequest(IdlStruct, typename=PKG + "Print_SendGoal_Request_"):
    guid: t.uint64
    seq: t.int64
    goal_id: UUID
    goal: PrintGoal


@dataclass
@annotate.final
class SendGoalResponse(IdlStruct, typename=PKG + "Print_SendGoal_Response_"):
    guid: t.uint64
    seq: t.int64
    accepted: bool
    stamp: Time


@dataclass
@annotate.final
class GetResultRequest(IdlStruct, typename=PKG + "Print_GetResult_Request_"):
    guid: t.uint64
    seq: t.int64
    goal_id: UUID


@dataclass
@annotate.final
class GetResultResponse(IdlStruct, typename=PKG + "Print_GetResult_Response_"):
    guid: t.uint64
    seq: t.int64
    status: t.int8
    result: PrintResult


@dataclass
@annotate.final
class CancelRequest(IdlStruct, typename="action_msgs::srv::dds_::CancelGoal_Request_"):
    guid: t.uint64
    seq: t.int64
    goal_info: GoalInfo


@dataclass
@annotate.final
class CancelResponse(IdlStruct, typename="action_msgs::srv::dds_::CancelGoal_Response_"):
    guid: t.uint64
    seq: t.int64
    return_code: t.int8
    goals_canceling: t.sequence[GoalInfo]


@dataclass
@annotate.final
class FeedbackMessage(IdlStruct, typename=PKG + "Print_FeedbackMessage_"):
    goal_id: UUID
    feedback: PrintFeedback


SUCCEEDED, CANCELED = 4, 5


def same(a, b):
    """Goal ids compare by their 16 bytes (Cyclone hands the array back as bytes)."""
    return bytes(a.uuid) == bytes(b.uuid)


def circle(path, turns):
    lines = ["G1 X50 Y0 F3000"]
    for i in range(1, 200 * turns + 1):
        a = i * 2 * math.pi / 200
        lines.append(f"G1 X{50 * math.cos(a):.3f} Y{50 * math.sin(a):.3f} F3000")
    path.write_text("\n".join(lines) + "\n")
    return len(lines)


@pytest.mark.parametrize("device", [None, "emulator"], ids=["executor", "mcu"])
def test_print_action_feedback_cancel_and_success_from_a_cyclone_client(tmp_path, device):
    """The action whatever the machine: the virtual executor, or per goal the MCU emulator
    behind the bridge (`serve --device emulator`)."""
    long_file, short_file = tmp_path / "long.gcode", tmp_path / "short.gcode"
    circle(long_file, 3)
    short_moves = circle(short_file, 1)
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN))
    on_device = ["--device", device] if device else []
    server = subprocess.Popen(
        [str(binary("polar-cell")), "serve", "--bag-dir", str(tmp_path / "bags"), *on_device],
        env=env, stderr=subprocess.PIPE, text=True,
    )
    try:
        p = DomainParticipant(DOMAIN)
        send_goal = ServiceClient(p, "/print/_action/send_goal", SendGoalRequest, SendGoalResponse)
        get_result = ServiceClient(p, "/print/_action/get_result", GetResultRequest, GetResultResponse)
        cancel = ServiceClient(p, "/print/_action/cancel_goal", CancelRequest, CancelResponse)
        feedback = DataReader(p, Topic(p, "rt/print/_action/feedback", FeedbackMessage), qos=ros_qos(100))
        status = DataReader(p, Topic(p, "rt/print/_action/status", GoalStatusArray),
                            qos=ros_qos(1, transient_local=True))
        deadline = time.monotonic() + 20
        for client in (send_goal, get_result, cancel):
            client.wait_for_server(deadline)

        def goal(path, speed):
            goal_id = UUID([random.randrange(256) for _ in range(16)])
            seq = send_goal.send(lambda g, s: SendGoalRequest(g, s, goal_id, PrintGoal(str(path), speed)))
            return goal_id, send_goal.reply(seq, 10)

        # A long print at machine pace; its result is asked for at once, as send_goal does.
        goal_id, accepted = goal(long_file, 1.0)
        assert accepted.accepted
        result_seq = get_result.send(lambda g, s: GetResultRequest(g, s, goal_id))

        # Feedback at ≥ 2 Hz while it prints, its progress rising.
        time.sleep(3.0)
        ours = [m.feedback for m in feedback.take(N=1000)
                if isinstance(m, FeedbackMessage) and same(m.goal_id, goal_id)]
        assert len(ours) >= 6, len(ours)
        assert ours[-1].state == "printing" and ours[-1].line > 1
        assert ours[-1].percent > ours[0].percent and ours[-1].remaining_s > 0

        # Busy: another goal is rejected.
        _, refused = goal(short_file, 1.0)
        assert not refused.accepted

        # Cancel: accepted for exactly our goal; the result says where it stopped.
        seq = cancel.send(lambda g, s: CancelRequest(g, s, GoalInfo(goal_id, Time(0, 0))))
        reply = cancel.reply(seq, 10)
        assert reply.return_code == 0
        assert len(reply.goals_canceling) == 1 and same(reply.goals_canceling[0].goal_id, goal_id)
        result = get_result.reply(result_seq, 30)
        assert result.status == CANCELED, result
        assert result.result.ended == "cancelled"
        assert "stopped on the path" in result.result.message
        assert len(result.result.stop_position) == 4
        assert 0 < result.result.moves_executed < 601
        statuses = [s for a in status.take(N=100) if isinstance(a, GoalStatusArray) for s in a.status_list
                    if same(s.goal_info.goal_id, goal_id)]
        assert statuses and statuses[-1].status == CANCELED
        stop = list(result.result.stop_position[:3])
        assert stop[1] > 0.04, stop  # mid-circle, far from home

        # A short print to its end, 20× faster.
        goal_id, accepted = goal(short_file, 20.0)
        assert accepted.accepted
        seq = get_result.send(lambda g, s: GetResultRequest(g, s, goal_id))
        result = get_result.reply(seq, 120)
        assert result.status == SUCCEEDED, result
        assert result.result.ended == "succeeded"
        assert result.result.moves_executed == short_moves
        # The virtual machine keeps its position between goals, so the second print starts
        # where the cancel stopped it (its first executed joint state, no jump home); an
        # emulator started per goal powers up at home.
        start = stop if device is None else [0.0, 0.0, 0.0]
        with open(result.result.bag, "rb") as f:
            first = next(m.decoded_message for m in make_reader(f, decoder_factories=[DecoderFactory()])
                         .iter_decoded_messages(topics=["/joint_states"]))
        assert all(abs(a - b) < 1e-12 for a, b in zip(first.position[:3], start)), (first.position, start)
        # Executed in the plan's time (the pre-flight's figure from `polar-cell check`, from
        # the same start), and ended where the file ends: once round the bed at r = 50 mm
        # (from the nearest turn of the bed to the start).
        check = subprocess.run([str(binary("polar-cell")), "check", str(short_file),
                                "--start-joints", ",".join(repr(q) for q in start)],
                               capture_output=True, text=True, check=True).stdout
        m, s = check.split("of machine time")[0].split()[-1].split(":")[-2:]
        # Start and end placed by the plan clock (the MCU's through clock sync), not by when
        # the server noticed them.
        assert abs(result.result.machine_time_s - (60 * int(m) + float(s))) < 0.05, check
        bed, arm, z, _ = result.result.stop_position
        turns = bed / (2 * math.pi)
        assert abs(turns - round(turns)) < 1e-3 / (2 * math.pi), (bed, start)
        # At most half a turn to the first point (a chord), then one turn round.
        assert math.pi - 1e-3 <= bed - start[0] <= 3 * math.pi + 1e-3, (bed, start)
        assert abs(arm - 0.05) < 2e-5 and z == 0.0
        assert os.path.exists(result.result.bag)
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()


EXECUTING, ABORTED, UNKNOWN = 2, 6, 0
ERROR_NONE, ERROR_UNKNOWN_GOAL_ID, ERROR_GOAL_TERMINATED = 0, 2, 3


def test_cancel_rules_goal_ids_result_timeout_and_shutdown_as_rcl_has_them(tmp_path):
    """What an rcl action server does beyond the happy path (rcl's action_server.c and
    goal_state_machine.c): cancel by stamp, cancel return codes, a goal id used twice, results
    kept for `result_timeout` after the goal ended, the stop position of a goal that never
    moved the machine, and a server stopped with a goal running still ending that goal."""
    long_file = tmp_path / "long.gcode"
    circle(long_file, 3)
    # A bag of an earlier server in the directory: not overwritten.
    (tmp_path / "bags").mkdir()
    earlier = tmp_path / "bags" / "print-1.mcap"
    earlier.write_bytes(b"an earlier server's bag")
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN + 2))
    server = subprocess.Popen(
        [str(binary("polar-cell")), "serve", "--bag-dir", str(tmp_path / "bags"),
         "--result-timeout-s", "4"],
        env=env, stderr=subprocess.PIPE, text=True,
    )
    try:
        p = DomainParticipant(DOMAIN + 2)
        send_goal = ServiceClient(p, "/print/_action/send_goal", SendGoalRequest, SendGoalResponse)
        get_result = ServiceClient(p, "/print/_action/get_result", GetResultRequest, GetResultResponse)
        cancel = ServiceClient(p, "/print/_action/cancel_goal", CancelRequest, CancelResponse)
        status = DataReader(p, Topic(p, "rt/print/_action/status", GoalStatusArray),
                            qos=ros_qos(1, transient_local=True))
        deadline = time.monotonic() + 20
        for client in (send_goal, get_result, cancel):
            client.wait_for_server(deadline)
        zero = UUID([0] * 16)

        def new_id():
            return UUID([random.randrange(256) for _ in range(16)])

        def goal(goal_id, path):
            seq = send_goal.send(lambda g, s: SendGoalRequest(g, s, goal_id, PrintGoal(str(path), 1.0)))
            return send_goal.reply(seq, 10)

        def cancel_goal(goal_id, stamp):
            seq = cancel.send(lambda g, s: CancelRequest(g, s, GoalInfo(goal_id, stamp)))
            return cancel.reply(seq, 10)

        def result_of(goal_id, timeout):
            seq = get_result.send(lambda g, s: GetResultRequest(g, s, goal_id))
            return get_result.reply(seq, timeout)

        def latest_statuses():
            arrays = [a for a in status.read(N=10) if isinstance(a, GoalStatusArray)]
            return {bytes(s.goal_info.goal_id.uuid): s.status for s in arrays[-1].status_list} if arrays else {}

        # Idle: cancelling every goal is no error, naming an unknown one is.
        reply = cancel_goal(zero, Time(0, 0))
        assert (reply.return_code, len(reply.goals_canceling)) == (ERROR_NONE, 0)
        assert cancel_goal(new_id(), Time(0, 0)).return_code == ERROR_UNKNOWN_GOAL_ID

        # A goal at a speed no machine runs at: accepted to say why, aborted before any bag.
        too_fast = new_id()
        seq = send_goal.send(lambda g, s: SendGoalRequest(g, s, too_fast, PrintGoal(str(long_file), -1.0)))
        assert send_goal.reply(seq, 10).accepted
        refused = result_of(too_fast, 10)
        assert refused.status == ABORTED, refused
        assert "speed -1: a print runs at 0.01 to 1000" in refused.result.message, refused.result.message

        first = new_id()
        accepted = goal(first, long_file)
        assert accepted.accepted
        time.sleep(2.0)
        # "Every goal accepted at or before 1970-01-01T00:00:01": not this one.
        reply = cancel_goal(zero, Time(1, 0))
        assert (reply.return_code, len(reply.goals_canceling)) == (ERROR_NONE, 0)
        time.sleep(0.5)
        assert latest_statuses().get(bytes(first.uuid)) == EXECUTING
        # "At or before its acceptance": this one; again while it stops: already terminating.
        reply = cancel_goal(zero, accepted.stamp)
        assert reply.return_code == ERROR_NONE and len(reply.goals_canceling) == 1
        assert same(reply.goals_canceling[0].goal_id, first)
        assert cancel_goal(first, Time(0, 0)).return_code == ERROR_GOAL_TERMINATED
        result = result_of(first, 30)
        assert result.status == CANCELED, result
        assert result.result.bag == str(tmp_path / "bags" / "print-2.mcap"), result.result.bag
        stop = list(result.result.stop_position[:3])
        assert stop[1] > 0.04, stop
        assert cancel_goal(first, Time(0, 0)).return_code == ERROR_GOAL_TERMINATED

        # A goal id that exists is refused, as rcl refuses it.
        assert not goal(first, long_file).accepted

        # A goal that fails before the machine runs: where the machine stands is where the
        # cancel left it, not home.
        missing = new_id()
        assert goal(missing, tmp_path / "no-such.gcode").accepted
        result = result_of(missing, 30)
        assert result.status == ABORTED, result
        assert list(result.result.stop_position[:3]) == stop, (result.result.stop_position, stop)
        # It recorded nothing, so it names no bag (print-3.mcap was never written).
        assert result.result.bag == "", result.result.bag
        assert not os.path.exists(tmp_path / "bags" / "print-3.mcap")
        # "-" would read the server's own standard input: refused, saying why.
        stdin_goal = new_id()
        assert goal(stdin_goal, "-").accepted
        result = result_of(stdin_goal, 30)
        assert result.status == ABORTED, result
        assert "standard input" in result.result.message, result.result.message

        # Kept for the result timeout after they ended (4 s here), then unknown.
        assert bytes(first.uuid) in latest_statuses()
        time.sleep(5.0)
        assert result_of(first, 10).status == UNKNOWN
        assert bytes(first.uuid) not in latest_statuses()

        # Stopped with a goal running: the goal is cancelled on the path and its result
        # given to the client waiting for it before the server ends.
        last = new_id()
        assert goal(last, long_file).accepted
        waiting = get_result.send(lambda g, s: GetResultRequest(g, s, last))
        time.sleep(3.0)
        server.send_signal(signal.SIGINT)
        result = get_result.reply(waiting, 30)
        assert result.status == CANCELED, result
        assert result.result.message.startswith("the server shut down: cancelled"), result.result.message
        _, stderr = server.communicate(timeout=20)
        assert server.returncode == 0, stderr
        assert earlier.read_bytes() == b"an earlier server's bag"
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()


def test_an_emergency_stop_outlives_its_goal_until_a_reset(tmp_path):
    """`/cell/estop` during a goal: that goal ends in an emergency stop, and every goal after
    it is aborted, saying why, until `/cell/reset` (a new job's MCU session resets the MCU, so
    the cell would otherwise print again with nobody having reset it). With no goal running
    the server answers the /cell services itself: a call does not wait for ever, and an e-stop
    then latches the same way."""
    long_file = tmp_path / "long.gcode"
    circle(long_file, 3)
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN + 3))
    server = subprocess.Popen(
        [str(binary("polar-cell")), "serve", "--bag-dir", str(tmp_path / "bags")],
        env=env, stderr=subprocess.PIPE, text=True,
    )
    try:
        p = DomainParticipant(DOMAIN + 3)
        send_goal = ServiceClient(p, "/print/_action/send_goal", SendGoalRequest, SendGoalResponse)
        get_result = ServiceClient(p, "/print/_action/get_result", GetResultRequest, GetResultResponse)
        cancel = ServiceClient(p, "/print/_action/cancel_goal", CancelRequest, CancelResponse)
        deadline = time.monotonic() + 20
        for client in (send_goal, get_result, cancel):
            client.wait_for_server(deadline)

        def cell(name):
            return ServiceClient(p, f"/cell/{name}", TriggerRequest, TriggerResponse)

        def goal(path):
            goal_id = UUID([random.randrange(256) for _ in range(16)])
            seq = send_goal.send(lambda g, s: SendGoalRequest(g, s, goal_id, PrintGoal(str(path), 1.0)))
            assert send_goal.reply(seq, 10).accepted
            return goal_id

        def result_of(goal_id, timeout=30):
            seq = get_result.send(lambda g, s: GetResultRequest(g, s, goal_id))
            return get_result.reply(seq, timeout)

        # Idle: answered by the server, also to clients made just before their call, as
        # `ros2 service call` makes its client (their answers wait until the server has
        # seen the client's response reader).
        for _ in range(5):
            # Its own participant, as a new process has (the server waits for that
            # participant's response reader).
            fresh = DomainParticipant(DOMAIN + 3)
            reply = trigger(ServiceClient(fresh, "/cell/pause", TriggerRequest, TriggerResponse))
            assert (reply.success, reply.message) == (False, "no print runs"), reply
        assert trigger(cell("reset")).message == "not stopped"

        # An e-stop of the running print (served by its machine).
        running = goal(long_file)
        time.sleep(3.0)
        # Goals from new clients, as `ros2 action send_goal` sends them: each is answered
        # (rejected: one goal at a time).
        for _ in range(5):
            fresh = ServiceClient(DomainParticipant(DOMAIN + 3), "/print/_action/send_goal",
                                  SendGoalRequest, SendGoalResponse)
            goal_id = UUID([random.randrange(256) for _ in range(16)])
            reply = fresh.call(lambda g, s: SendGoalRequest(g, s, goal_id, PrintGoal(str(long_file), 1.0)))
            assert not reply.accepted
        reply = trigger(cell("estop"))
        assert reply.success, reply
        result = result_of(running)
        assert result.result.ended == "emergency_stop", result.result
        time.sleep(1.0)

        # The next goal ends at once, saying why; after a reset one runs.
        refused = goal(long_file)
        result = result_of(refused)
        assert result.status == ABORTED, result
        assert "call /cell/reset before a new print" in result.result.message, result.result.message
        reply = trigger(cell("reset"))
        assert (reply.success, reply.message) == (True, "reset: the cell takes new prints again")
        running = goal(long_file)
        time.sleep(2.0)
        seq = cancel.send(lambda g, s: CancelRequest(g, s, GoalInfo(running, Time(0, 0))))
        assert cancel.reply(seq, 10).return_code == ERROR_NONE
        result = result_of(running)
        assert result.status == CANCELED, result
        assert result.result.machine_time_s > 0.5, result.result
        time.sleep(1.0)

        # An e-stop with no print running latches too.
        assert trigger(cell("estop")).success
        result = result_of(goal(long_file))
        assert result.status == ABORTED and "while no print ran" in result.result.message, result
        assert trigger(cell("reset")).success

        # An e-stop during a goal's pre-flight (800,000 moves: seconds of checking,
        # no machine node yet) is answered by the server, stops the job before it moves,
        # and latches.
        big = tmp_path / "big.gcode"
        with open(big, "w") as f:
            for i in range(800_000):
                a = i * 0.01
                f.write(f"G1 X{30 * math.cos(a):.3f} Y{30 * math.sin(a):.3f} F3000\n")
        checking = goal(big)
        reply = trigger(cell("estop"))
        assert reply.success and "stops before it moves" in reply.message, reply
        result = result_of(checking, 60)
        assert (result.status, result.result.ended) == (ABORTED, "emergency_stop"), result
        assert result.result.machine_time_s == 0.0, result.result
        result = result_of(goal(long_file))
        assert result.status == ABORTED and "/cell/reset" in result.result.message, result
        assert trigger(cell("reset")).success
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
