"""An outside ROS 2 subscriber on rmw_cyclonedds misses nothing the bag records (issue 14 item 1).

A Cyclone DDS participant stands in for `ros2 topic echo` started before the print: reliable,
volatile, keep-last 100,000 readers on every data topic of a dry run (the fastest our writers
ever publish). After the print, each reader must hold exactly the samples the bag holds.

What this caught: RustDDS announced in its HEARTBEATs samples it had admitted but not yet
sent. Cyclone starts a reliable session with a writer of another vendor at the first HEARTBEAT
it accepts and treats every sample up to that HEARTBEAT's lastSN it has not received as a GAP.
When that HEARTBEAT rode on the first datagram of a burst, the rest of the burst was never
delivered ("495 of 1,778 moves, then nothing"): about one print in five. The fix is the patch
in `patches/rustdds/` (see its PATCH.md).
"""

import os
import subprocess
import time
from collections import Counter
from dataclasses import dataclass

import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as t
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import CYCLONE_LOOPBACK, FIXTURES
from test_dds import GcodeAck, GcodeMove, GcodeProgress, Header, ros_qos, valid
from test_mechanism import JointState

# Prints per run of the suite; the README's figure is 20 (POLAR_CELL_OUTSIDE_READER_RUNS=20).
RUNS = int(os.environ.get("POLAR_CELL_OUTSIDE_READER_RUNS", "8"))


@dataclass
@annotate.final
class Duration(IdlStruct, typename="builtin_interfaces::msg::dds_::Duration_"):
    sec: t.int32
    nanosec: t.uint32


@dataclass
@annotate.final
class JointTrajectoryPoint(IdlStruct, typename="trajectory_msgs::msg::dds_::JointTrajectoryPoint_"):
    positions: t.sequence[t.float64]
    velocities: t.sequence[t.float64]
    accelerations: t.sequence[t.float64]
    effort: t.sequence[t.float64]
    time_from_start: Duration


@dataclass
@annotate.final
class JointTrajectory(IdlStruct, typename="trajectory_msgs::msg::dds_::JointTrajectory_"):
    header: Header
    joint_names: t.sequence[str]
    points: t.sequence[JointTrajectoryPoint]


@dataclass
@annotate.final
class StepSegment(IdlStruct, typename="polar_cell_msgs::msg::dds_::StepSegment_"):
    header: Header
    move_sequence: t.uint64
    source_line: t.uint32
    axis_names: t.sequence[str]
    step_counts: t.sequence[t.uint32]
    directions: t.sequence[t.int8]
    dominant_axis: t.uint8
    timer_frequency_hz: t.float64
    first_period_ticks: t.float64
    ramp_r: t.float64
    cruise_period_ticks: t.float64
    accelerate_steps: t.uint32
    cruise_steps: t.uint32
    decelerate_steps: t.uint32
    duration_s: t.float64
    ends_at_rest: bool


@dataclass
@annotate.final
class ScrewCommand(IdlStruct, typename="polar_cell_msgs::msg::dds_::ScrewCommand_"):
    header: Header
    rpm: t.float64
    pin_open: bool
    source_line: t.uint32
    model: str
    sequence: t.uint64


def stamp(m):
    return (m.header.stamp.sec, m.header.stamp.nanosec)


# What identifies a sample of each topic, read the same way from Cyclone's and the bag's
# decoding (both give the .msg field names).
TOPICS = {
    "/gcode/moves": (GcodeMove, lambda m: (m.sequence, m.source_line, m.x_m, m.y_m, m.z_m)),
    "/gcode/progress": (GcodeProgress, lambda m: (stamp(m), m.lines_read, m.moves_published)),
    "/gcode/ack": (GcodeAck, lambda m: (m.consumer, m.next_expected, m.resume, m.received_until)),
    "/polar/trajectory": (
        JointTrajectory,
        lambda m: (stamp(m), len(m.points), tuple(m.points[-1].positions) if m.points else ()),
    ),
    "/polar/steps": (
        StepSegment,
        lambda m: (stamp(m), m.move_sequence, tuple(m.step_counts), m.duration_s),
    ),
    "/polar/planned_joint_states": (JointState, lambda m: (stamp(m), tuple(m.name), tuple(m.position))),
    "/screw/command": (ScrewCommand, lambda m: (stamp(m), m.rpm, m.pin_open, m.source_line)),
}


def bag_samples(path):
    """Every recorded sample's identity, per topic (mcap-ros2-support decoding)."""
    found = {topic: Counter() for topic in TOPICS}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, msg in reader.iter_decoded_messages(topics=list(TOPICS)):
            found[channel.topic][TOPICS[channel.topic][1](msg)] += 1
    return found


def print_with_an_outside_reader(polar_cell, bag):
    participant = DomainParticipant(0)
    readers = {
        topic: DataReader(participant, Topic(participant, "rt" + topic, kind), qos=ros_qos(100_000))
        for topic, (kind, _) in TOPICS.items()
    }
    received = {topic: Counter() for topic in TOPICS}

    def take_all():
        for topic, reader in readers.items():
            kind, key = TOPICS[topic]
            while True:
                taken = reader.take(N=5000)
                if not taken:
                    break
                for m in valid(taken, kind):
                    received[topic][key(m)] += 1

    proc = subprocess.Popen(
        [str(polar_cell), "print", str(FIXTURES / "finger.gcode"), "--dry-run", "--no-progress",
         "--bag", str(bag)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        take_all()
        time.sleep(0.005)
    if proc.poll() is None:
        proc.kill()
    _, stderr = proc.communicate()
    assert proc.returncode == 0, stderr
    # A clean print logs no error (issue 14 item 5: RustDDS's entity-removal queue overflowed
    # at every print's end, "Cannot remove Reader … TrySendError::Full").
    assert "ERROR" not in stderr, stderr
    # What reached Cyclone before the print's writers went away is in its queues: take it.
    # (The print keeps its writers until its bag is closed, past RustDDS's 1 s heartbeat, so
    # a loss near the end is repaired; it does not wait for outside acknowledgements.)
    take_all()
    return received


def test_an_outside_reliable_reader_receives_every_sample_the_bag_records(polar_cell, tmp_path):
    failures = []
    for run in range(RUNS):
        bag = tmp_path / f"run{run}.mcap"
        received = print_with_an_outside_reader(polar_cell, bag)
        recorded = bag_samples(bag)
        assert sum(recorded["/gcode/moves"].values()) == 1778
        # finger's compensated screw stream: 7,218 commands published.
        assert sum(recorded["/screw/command"].values()) > 7_000
        for topic in TOPICS:
            # A resent move (the streamer's go-back-N) is a second sample with the same
            # content, and a sample published after the recorder stopped is not in the bag:
            # what counts is what the bag has and the reader lacks.
            missing = recorded[topic] - received[topic]
            if topic == "/gcode/moves":
                missing = Counter(set(recorded[topic]) - set(received[topic]))
            if topic == "/gcode/progress":
                # Likewise the streamer's first progress (nothing read yet), published as its
                # writer is created; every later one must arrive.
                missing = Counter({p: n for p, n in missing.items() if p[1] > 0})
            if topic == "/gcode/ack":
                # A consumer announces itself and confirms its resume point (move 0) the moment
                # its writer exists, before a volatile reader elsewhere has matched that
                # writer: DDS offers a sample only to readers matched by then. Every
                # acknowledgement of a move must arrive.
                missing = Counter({ack: n for ack, n in missing.items() if ack[1] > 0})
            if missing:
                failures.append(
                    f"run {run} {topic}: bag {sum(recorded[topic].values())}, reader "
                    f"{sum(received[topic].values())}, {sum(missing.values())} missing, e.g. "
                    f"{sorted(missing)[:3]}"
                )
    assert not failures, "\n".join(failures)


# A subscriber in its own process, so the test can freeze it (SIGSTOP) as a reader whose
# host hung would be: it prints its reader's GUID, then the count of moves it took.
FROZEN_READER = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from test_mechanism import JointState
from test_dds import ros_qos
participant = DomainParticipant(0)
reader = DataReader(participant, Topic(participant, "rt/joint_states", JointState), qos=ros_qos(100_000))
print("guid", reader.guid.bytes.hex(), flush=True)
taken = 0
while True:
    taken += len(reader.take(N=1000))
    print("taken", taken, flush=True)
    time.sleep(0.01)
"""


def bag_joint_states(path):
    with open(path, "rb") as f:
        return sum(1 for _ in make_reader(f).iter_messages(topics=["/joint_states"]))


def cyclone_guid_text(hex_bytes):
    """A GUID as the print names it: four 32-bit words in hex (Cyclone's own notation)."""
    raw = bytes.fromhex(hex_bytes)
    return ":".join(f"{int.from_bytes(raw[i:i + 4], 'big'):x}" for i in range(0, 16, 4))


def test_a_print_waits_for_outside_acknowledgements_and_names_a_reader_that_gives_none(
    polar_cell, tmp_path
):
    """An outside subscriber that stops acknowledging (a `ros2 topic echo` suspended with
    Ctrl-Z) changes nothing in the print: the machine keeps its pace (RustDDS's reliable
    writers used to wait for it: 1,240 s of machine time for 168 s, with an underrun). At
    the end the print does not drop its writers while a subscriber still lacks samples (a
    loss is repaired only while the writer exists): it waits, bounded (5 s), and then names
    the reader that did not acknowledge."""
    import signal
    import sys
    from pathlib import Path

    here = Path(__file__).resolve().parent
    # A participant's lease (Cyclone's default 10 s) would end while it is frozen, and DDS
    # would then rightly count its reader gone, owed nothing: this one's lasts a minute.
    env = dict(os.environ, CYCLONEDDS_URI=CYCLONE_LOOPBACK.replace(
        "</Discovery>", "<LeaseDuration>60 s</LeaseDuration></Discovery>"))
    reader = subprocess.Popen([sys.executable, "-c", FROZEN_READER, str(here)],
                              stdout=subprocess.PIPE, text=True, env=env)
    try:
        kind, guid_hex = reader.stdout.readline().split()
        assert kind == "guid"
        bag = tmp_path / "frozen.mcap"
        started = time.monotonic()
        proc = subprocess.Popen(
            [str(polar_cell), "print", str(FIXTURES / "finger.gcode"), "--speed", "20",
             "--no-progress", "--bag", str(bag)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        # Freeze the reader a second after its first joint states, early in the print: by
        # then it has acknowledged some (a reader acknowledges when a writer's heartbeat asks;
        # frozen at its first sample it may have acknowledged none).
        first_sample = None
        while first_sample is None or time.monotonic() - first_sample < 1.0:
            line = reader.stdout.readline()
            assert line, "the outside reader died"
            if first_sample is None and int(line.split()[1]) > 0:
                first_sample = time.monotonic()
        reader.send_signal(signal.SIGSTOP)
        _, stderr = proc.communicate(timeout=120)
        took_s = time.monotonic() - started
    finally:
        reader.send_signal(signal.SIGCONT)
        reader.kill()
        reader.wait()
    assert proc.returncode == 0, stderr
    guid = cyclone_guid_text(guid_hex)
    named = [line for line in stderr.splitlines() if "not acknowledged by reader" in line]
    assert len(named) == 1 and guid in named[0], stderr
    assert named[0].startswith("warning: after 5 s, /joint_states: ")
    assert named[0].endswith(f"not acknowledged by reader {guid} (not a ROS node)")
    missing = int(named[0].split("/joint_states: ")[1].split()[0])
    recorded = bag_joint_states(bag)
    assert 0 < missing < recorded
    # Bounded: finger at 20x is 8.4 s of machine time; the wait adds at most 5 s.
    assert took_s < 8.4 + 5 + 10, took_s
    # The print is whole all the same: at its planned pace, 50 Hz of its machine time.
    executed = next(line for line in stderr.splitlines() if " executed " in line)
    assert "(168.055 s; planned 168.055 s), 0 underruns" in executed, executed
    assert recorded >= 168 * 50


def executed_states(bag):
    """The bag's executed joint states, by identity (stamp, positions)."""
    found = Counter()
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, m in reader.iter_decoded_messages(topics=["/joint_states"]):
            found[(stamp(m), tuple(m.position))] += 1
    return found


def test_the_bag_and_an_outside_reader_have_the_same_executed_states(polar_cell, tmp_path):
    """Executed at machine pace (4x): a reader started before the print and the print's own
    bag hold the same `/joint_states`, the first included. The machine waits for the recorder
    to subscribe before its first state (`await_subscribers`): a volatile sample goes only to
    the readers matched when it is written, and a recorder matched late lost the first (seen
    once in three prints on a machine whose file cache had been dropped: the outside reader
    had 604 states, the bag 603)."""
    gcode = tmp_path / "square.gcode"
    gcode.write_text("G1 X20 Y0 F3000\nG1 X20 Y20\nG1 X0 Y20\nG1 X0 Y0\n")
    participant = DomainParticipant(0)
    reader = DataReader(participant, Topic(participant, "rt/joint_states", JointState),
                        qos=ros_qos(100_000))
    received = Counter()
    time.sleep(1.0)  # the reader is known before the print starts
    bag = tmp_path / "square.mcap"
    proc = subprocess.Popen(
        [str(polar_cell), "print", str(gcode), "--speed", "4", "--no-progress", "--bag", str(bag)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        for m in reader.take(N=1000):
            if isinstance(m, JointState):
                received[(stamp(m), tuple(m.position))] += 1
        if proc.poll() is not None:
            break
        time.sleep(0.02)
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 0, stderr
    time.sleep(0.5)
    for m in reader.take(N=1000):
        if isinstance(m, JointState):
            received[(stamp(m), tuple(m.position))] += 1
    recorded = executed_states(bag)
    assert len(recorded) > 40, len(recorded)
    assert received == recorded, (
        f"bag {sum(recorded.values())}, reader {sum(received.values())}; only in the reader: "
        f"{sorted(received - recorded)[:3]}; only in the bag: {sorted(recorded - received)[:3]}"
    )


def test_a_machine_waits_for_its_recorder_boundedly_and_says_so(polar_cell, tmp_path):
    """A subscriber it awaits that never comes: the machine starts after the bound, with a
    warning naming what it lacked, and the print completes."""
    gcode = tmp_path / "line.gcode"
    gcode.write_text("G1 X10 Y0 F3000\n")
    proc = subprocess.run(
        [str(polar_cell), "print", str(gcode), "--speed", "4", "--no-progress",
         "--bag", str(tmp_path / "line.mcap"), "--ros-args",
         "-p", "cell_executor:await_subscribers:=[/bag_recorder, /nobody]",
         "-p", "cell_executor:await_subscribers_s:=1.0"],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "line.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        logged = [m.msg for _, _, _, m in reader.iter_decoded_messages(topics=["/rosout"])]
    assert any(line.startswith(
        "after 1 s still no subscription on /joint_states (/nobody), /tf (/nobody): starting "
        "without it") for line in logged), logged
