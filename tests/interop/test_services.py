"""The cell's services from outside, as `ros2 service call` on rmw_cyclonedds makes them.

The client here is written from rmw_cyclonedds's sources (docs/design/actions-and-services.md
§1): request topic `rq/cell/<name>Request`, reply topic `rr/cell/<name>Reply`, types
`std_srvs::srv::dds_::Trigger_Request_` / `_Response_`, and before the body the 16-byte
header `{uint64 guid; int64 seq}` that the server must echo. The print runs at machine pace; we
watch its `/joint_states` (the executed joints) to see each service take effect.
"""

import math
import os
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

from conftest import BIN_DIR, ROOT, binary
from rmw_cyclone import ServiceClient
from test_dds import ros_qos
from test_mechanism import JointState

DOMAIN = 77


@dataclass
@annotate.final
class TriggerRequest(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    guid: t.uint64
    seq: t.int64
    structure_needs_at_least_one_member: t.uint8


@dataclass
@annotate.final
class TriggerResponse(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    guid: t.uint64
    seq: t.int64
    success: bool
    message: str


def trigger(client):
    """`ros2 service call <service> std_srvs/srv/Trigger`: the response."""
    return client.call(lambda guid, seq: TriggerRequest(guid, seq, 0))


def circle_gcode(path):
    """Out along the arm, then three times round the bed: in motion for many seconds."""
    lines = ["G1 X50 Y0 F3000"]
    for i in range(1, 601):
        a = i * 2 * math.pi / 200
        lines.append(f"G1 X{50 * math.cos(a):.3f} Y{50 * math.sin(a):.3f} F3000")
    path.write_text("\n".join(lines) + "\n")


def recent_states(reader, seconds):
    """The executed joint states that arrive within `seconds`."""
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        out += [s for s in reader.take(N=1000) if isinstance(s, JointState)]
        time.sleep(0.02)
    return out


def start_circle_print(tmp_path, device):
    """`polar-cell print` of a circling file at machine pace (on `device`, if any), and a
    Cyclone participant reading its executed `/joint_states`."""
    gcode = tmp_path / "circle.gcode"
    circle_gcode(gcode)
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN))
    on_device = ["--device", device] if device else []
    proc = subprocess.Popen(
        [str(binary("polar-cell")), "print", str(gcode), "--bag", str(tmp_path / "s.mcap"), "--no-progress", *on_device],
        env=env, stderr=subprocess.PIPE, text=True,
    )
    participant = DomainParticipant(DOMAIN)
    states = DataReader(
        participant, Topic(participant, "rt/joint_states", JointState), qos=ros_qos(1000)
    )
    return proc, participant, states


@pytest.mark.parametrize("device", [None, "emulator"], ids=["executor", "mcu"])
def test_pause_resume_estop_from_a_cyclone_client(tmp_path, device):
    """The same services whatever the machine: the virtual executor, or the MCU emulator
    behind the bridge (`--device emulator`)."""
    proc, participant, states = start_circle_print(tmp_path, device)
    try:
        pause, resume, estop, reset = (
            ServiceClient(participant, f"/cell/{name}", TriggerRequest, TriggerResponse)
            for name in ("pause", "resume", "estop", "reset")
        )
        moving = recent_states(states, 4.0)
        assert moving and moving[-1].name == ["bed_theta", "arm_r", "z", "screw"]
        assert any(abs(v) > 0 for s in moving[-10:] for v in s.velocity[:3]), "moving"

        # Nothing to resume or reset yet: refused, with the reason.
        reply = trigger(resume)
        assert (reply.success, reply.message) == (False, "not paused")
        assert trigger(reset).success is False

        reply = trigger(pause)
        assert reply.success, reply.message
        held = recent_states(states, 1.5)[-25:]  # the last half second, well after the stop
        assert held and all(v == 0.0 for s in held for v in s.velocity)
        assert len({tuple(s.position) for s in held}) == 1, "held in place"

        assert trigger(resume).success
        resumed = recent_states(states, 1.5)
        assert any(abs(v) > 0 for s in resumed[-10:] for v in s.velocity[:3]), "moving again"
        # It continued from where it held: the first new position is next to the held one.
        assert abs(resumed[0].position[0] - held[-1].position[0]) < 0.05

        reply = trigger(estop)
        assert reply.success and "emergency stop" in reply.message
        _, stderr = proc.communicate(timeout=20)
        assert proc.returncode == 1, stderr
        assert "emergency stop (/cell/estop) during the print" in stderr, stderr
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("device", [None, "emulator"], ids=["executor", "mcu"])
def test_a_cancel_from_a_cyclone_client_ends_the_print_at_rest(tmp_path, device):
    """`ros2 service call /cell/cancel` during `print`: the machine stops on the path, and the
    print ends there, non-zero, saying so (it used to wait for ever for moves the stopped
    planner never sent, or, in the last two seconds, to report the print as succeeded)."""
    proc, participant, states = start_circle_print(tmp_path, device)
    try:
        pause, cancel = (
            ServiceClient(participant, f"/cell/{name}", TriggerRequest, TriggerResponse)
            for name in ("pause", "cancel")
        )
        moving = recent_states(states, 4.0)
        assert any(abs(v) > 0 for s in moving[-10:] for v in s.velocity[:3]), "moving"
        reply = trigger(cancel)
        assert reply.success and reply.message.startswith("cancelling"), reply.message
        # A pause while the cancel slows down would make it a pause: refused (as it is once
        # the cancel came to rest and dropped the plan).
        reply = trigger(pause)
        assert not reply.success, reply.message
        assert reply.message.startswith(("cancelling", "no plan")), reply.message
        _, stderr = proc.communicate(timeout=20)
        assert proc.returncode == 1, stderr
        assert "cancelled (/cell/cancel): stopped on the path at line" in stderr, stderr
        last = recent_states(states, 0.5)[-5:] or moving[-1:]
        assert last and all(v == 0.0 for s in last for v in s.velocity), "at rest"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_reset_after_an_estop_does_not_bring_the_stopped_plan_back(tmp_path):
    """A graph whose machine outlives an e-stop (`exit_when_done` off, as under `ros2
    launch`): after `/cell/reset` the producers still hold the stopped plan, and taken then
    it would play from where the e-stop left the machine, displaced by all that was dropped.
    The machine stays where it stopped, and says the plan stays dropped."""
    gcode = tmp_path / "circle.gcode"
    circle_gcode(gcode)
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), POLAR_CELL_BIN_DIR=str(BIN_DIR),
               POLAR_CELL_ROS_ARGS="-p cell_executor:exit_when_done:=false")
    proc = subprocess.Popen(
        [str(ROOT / "launch-scripts" / "cell.sh"), str(gcode), str(tmp_path / "r.mcap")],
        env=env, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        participant = DomainParticipant(DOMAIN)
        states = DataReader(
            participant, Topic(participant, "rt/joint_states", JointState), qos=ros_qos(1000)
        )
        pause, estop, reset = (
            ServiceClient(participant, f"/cell/{name}", TriggerRequest, TriggerResponse)
            for name in ("pause", "estop", "reset")
        )
        moving = recent_states(states, 5.0)
        assert any(abs(v) > 0 for s in moving[-10:] for v in s.velocity[:3]), "moving"
        assert trigger(estop).success
        stopped = recent_states(states, 1.0)
        reply = trigger(reset)
        assert reply.success and "stays dropped" in reply.message, reply.message
        after = recent_states(states, 4.0)
        assert len(after) > 100, "the machine publishes its state after the reset"
        assert all(v == 0.0 for s in after for v in s.velocity), "nothing moves"
        assert {tuple(s.position[:3]) for s in after} == {tuple(stopped[-1].position[:3])}
        reply = trigger(pause)
        assert (reply.success, reply.message) == (False, "no plan: it was dropped")
        assert proc.poll() is None, "the machine outlives the e-stop"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
