"""The cell's services from outside, as `ros2 service call` on rmw_cyclonedds makes them.

The client here is written from rmw_cyclonedds's sources (docs/design/actions-and-services.md
§1): request topic `rq/cell/<name>Request`, reply topic `rr/cell/<name>Reply`, types
`std_srvs::srv::dds_::Trigger_Request_` / `_Response_`, and before the body the 16-byte
header `{uint64 guid; int64 seq}` that the server must echo. The print runs at machine pace; we
watch its `/joint_states` (the executed joints) to see each service take effect.
"""

import math
import os
import random
import subprocess
import time
from dataclasses import dataclass

import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as t
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from conftest import binary
from test_dds import Header, ros_qos

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


@dataclass
@annotate.final
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header
    name: t.sequence[str]
    position: t.sequence[float]
    velocity: t.sequence[float]
    effort: t.sequence[float]


class TriggerClient:
    """One `std_srvs/srv/Trigger` client in rmw_cyclonedds's wire format."""

    def __init__(self, participant, service):
        qos = ros_qos(depth=10)
        self.writer = DataWriter(
            participant, Topic(participant, f"rq{service}Request", TriggerRequest), qos=qos
        )
        self.reader = DataReader(
            participant, Topic(participant, f"rr{service}Reply", TriggerResponse), qos=qos
        )
        self.guid = random.getrandbits(63) | 1
        self.seq = 0
        self.service = service

    def call(self, timeout_s=10.0):
        deadline = time.monotonic() + timeout_s
        # A volatile request written before the server's reader matched would be lost.
        while not (
            self.writer.get_matched_subscriptions() and self.reader.get_matched_publications()
        ):
            assert time.monotonic() < deadline, f"{self.service}: no server"
            time.sleep(0.05)
        self.seq += 1
        self.writer.write(TriggerRequest(self.guid, self.seq, 0))
        while time.monotonic() < deadline:
            for reply in self.reader.take(N=10):
                if isinstance(reply, TriggerResponse) and (reply.guid, reply.seq) == (
                    self.guid,
                    self.seq,
                ):
                    return reply
            time.sleep(0.01)
        raise AssertionError(f"{self.service}: no reply to request {self.seq}")


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


def test_pause_resume_estop_from_a_cyclone_client(tmp_path):
    gcode = tmp_path / "circle.gcode"
    circle_gcode(gcode)
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN))
    proc = subprocess.Popen(
        [str(binary("polar-cell")), "print", str(gcode), "--bag", str(tmp_path / "s.mcap"),
         "--no-progress"],
        env=env, stderr=subprocess.PIPE, text=True,
    )
    try:
        participant = DomainParticipant(DOMAIN)
        states = DataReader(
            participant, Topic(participant, "rt/joint_states", JointState), qos=ros_qos(1000)
        )
        pause, resume, estop, reset = (
            TriggerClient(participant, f"/cell/{name}")
            for name in ("pause", "resume", "estop", "reset")
        )
        moving = recent_states(states, 4.0)
        assert moving and moving[-1].name == ["bed_theta", "arm_r", "z", "screw"]
        assert any(abs(v) > 0 for s in moving[-10:] for v in s.velocity[:3]), "moving"

        # Nothing to resume or reset yet: refused, with the reason.
        reply = resume.call()
        assert (reply.success, reply.message) == (False, "not paused")
        assert reset.call().success is False

        reply = pause.call()
        assert reply.success, reply.message
        held = recent_states(states, 1.5)[-25:]  # the last half second, well after the stop
        assert held and all(v == 0.0 for s in held for v in s.velocity)
        assert len({tuple(s.position) for s in held}) == 1, "held in place"

        assert resume.call().success
        resumed = recent_states(states, 1.5)
        assert any(abs(v) > 0 for s in resumed[-10:] for v in s.velocity[:3]), "moving again"
        # It continued from where it held: the first new position is next to the held one.
        assert abs(resumed[0].position[0] - held[-1].position[0]) < 0.05

        reply = estop.call()
        assert reply.success and "emergency stop" in reply.message
        _, stderr = proc.communicate(timeout=20)
        assert proc.returncode == 1, stderr
        assert "emergency stop (/cell/estop) during the print" in stderr, stderr
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
