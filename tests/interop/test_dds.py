"""Our nodes against Cyclone DDS (PyPI cyclonedds): wire types, QoS, flow control, ROS graph.

The Python peer here is a second, independent implementation of the flow-control consumer
(announce, learn the resume point from /gcode/progress, confirm, acknowledge in order), so
`polar-cell print` only finishes if Cyclone's acknowledgements reach our subscriber.
"""

import signal
import subprocess
import time
from dataclasses import dataclass, field

import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as t
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import FIXTURES, assert_readable_by_independent_readers, binary, gcode_motion_lines


@dataclass
@annotate.final
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32
    nanosec: t.uint32


@dataclass
@annotate.final
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
@annotate.final
class GcodeMove(IdlStruct, typename="polar_cell_msgs::msg::dds_::GcodeMove_"):
    sequence: t.uint64
    source_line: t.uint32
    kind: t.uint8
    segment_index: t.uint32
    segment_count: t.uint32
    x_m: t.float64
    y_m: t.float64
    z_m: t.float64
    e_m: t.float64
    delta_e_m: t.float64
    feedrate_m_per_s: t.float64
    extrude: bool
    dwell_s: t.float64
    axes: t.uint8
    tool: t.uint8


@dataclass
@annotate.final
class GcodeAck(IdlStruct, typename="polar_cell_msgs::msg::dds_::GcodeAck_"):
    consumer: str
    next_expected: t.uint64
    resume: bool
    # What has arrived at the consumer; 0 = not told (the streamer then goes by next_expected).
    received_until: t.uint64 = 0
    resume_state: t.sequence[t.uint8] = field(default_factory=list)


@dataclass
@annotate.final
class GcodeProgress(IdlStruct, typename="polar_cell_msgs::msg::dds_::GcodeProgress_"):
    header: Header
    file: str
    bytes_read: t.uint64
    bytes_total: t.uint64
    lines_read: t.uint32
    moves_published: t.uint64
    moves_acknowledged: t.uint64
    warnings: t.uint32
    consumers: t.sequence[str]
    consumer_next_expected: t.sequence[t.uint64]
    finished: bool
    consumer_resume_states: t.sequence[t.uint8] = field(default_factory=list)
    consumer_resume_state_ends: t.sequence[t.uint32] = field(default_factory=list)
    end_of_file: bool = False
    moves_waiting: bool = False


@dataclass
@annotate.final
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str


@dataclass
@annotate.final
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: t.uint8
    name: str
    message: str
    hardware_id: str
    values: t.sequence[KeyValue]


@dataclass
@annotate.final
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: t.sequence[DiagnosticStatus]


@dataclass
@annotate.final
class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data: t.array[t.uint8, 16]


@dataclass
@annotate.final
class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace: str
    node_name: str
    reader_gid_seq: t.sequence[Gid]
    writer_gid_seq: t.sequence[Gid]


@dataclass
@annotate.final
class ParticipantEntitiesInfo(
    IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"
):
    gid: Gid
    node_entities_info_seq: t.sequence[NodeEntitiesInfo]


def ros_qos(depth=1000, transient_local=False):
    """ROS 2 default QoS (reliable, volatile unless latched), XCDR1 as ROS 2 uses."""
    return Qos(
        Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.Durability.TransientLocal if transient_local else Policy.Durability.Volatile,
        Policy.History.KeepLast(depth),
        Policy.DataRepresentation(use_cdrv0_representation=True),
    )


CONSUMER = "/cyclone_listener"


def announce_node(participant, fully_qualified_name, readers=(), writers=()):
    """Announce a ROS node on ros_discovery_info as rmw_cyclonedds does for rclcpp: this
    participant's GID and the node's readers and writers by theirs. The streamer takes a
    consumer's acknowledgements only from a writer so announced; a consumer takes moves only
    from the streamer's. Returns the writer (the announcement lasts as long as it does)."""
    namespace, _, name = fully_qualified_name.rpartition("/")
    gid = lambda entity: Gid(list(entity.guid.bytes))  # noqa: E731
    writer = DataWriter(
        participant,
        Topic(participant, "ros_discovery_info", ParticipantEntitiesInfo),
        qos=ros_qos(1, transient_local=True),
    )
    writer.write(ParticipantEntitiesInfo(gid(participant), [NodeEntitiesInfo(
        namespace or "/", name, [gid(r) for r in readers], [gid(w) for w in writers])]))
    return writer


def valid(samples, kind):
    """Drop Cyclone's InvalidSample entries (disposals when a writer goes away)."""
    return [s for s in samples if isinstance(s, kind)]


def consume_moves(participant, deadline_s=90):
    """Be a flow-control consumer until the stream is finished; return moves and diagnostics."""
    moves_r = DataReader(participant, Topic(participant, "rt/gcode/moves", GcodeMove), qos=ros_qos(10000))
    progress_r = DataReader(participant, Topic(participant, "rt/gcode/progress", GcodeProgress), qos=ros_qos())
    diag_r = DataReader(participant, Topic(participant, "rt/diagnostics", DiagnosticArray), qos=ros_qos())
    ack_w = DataWriter(participant, Topic(participant, "rt/gcode/ack", GcodeAck), qos=ros_qos())
    announcement = announce_node(participant, CONSUMER, [moves_r, progress_r, diag_r], [ack_w])
    next_expected = None
    received, diagnostics = [], []
    finished = False
    last_ack = 0.0
    deadline = time.monotonic() + deadline_s
    while not finished and time.monotonic() < deadline:
        for p in valid(progress_r.take(N=100), GcodeProgress):
            if next_expected is None and CONSUMER in p.consumers:
                next_expected = p.consumer_next_expected[p.consumers.index(CONSUMER)]
                ack_w.write(GcodeAck(CONSUMER, next_expected, False))
            finished |= p.finished
        for m in valid(moves_r.take(N=1000), GcodeMove):
            if next_expected is not None and m.sequence == next_expected:
                received.append(m)
                next_expected += 1
        diagnostics.extend(valid(diag_r.take(N=100), DiagnosticArray))
        now = time.monotonic()
        if now - last_ack > 0.02:
            last_ack = now
            if next_expected is None:
                ack_w.write(GcodeAck(CONSUMER, 0, True))
            else:
                ack_w.write(GcodeAck(CONSUMER, next_expected, False))
        time.sleep(0.001)
    time.sleep(0.3)
    diagnostics.extend(valid(diag_r.take(N=100), DiagnosticArray))
    del announcement
    return received, diagnostics, finished


def test_cyclone_consumer_decodes_moves_and_its_acks_gate_the_stream(polar_cell, tmp_path):
    name = "finger.gcode"
    bag = tmp_path / "cyclone.mcap"
    participant = DomainParticipant(0)
    proc = subprocess.Popen(
        [str(polar_cell), "print", str(FIXTURES / name), "--bag", str(bag), "--no-progress", "--dry-run",
         "--ros-args", "-p", f"gcode_streamer:consumers:=[/bag_recorder, {CONSUMER}]"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        received, diagnostics, finished = consume_moves(participant)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert finished, (len(received), err)
    lines = gcode_motion_lines(FIXTURES / name)
    assert [m.sequence for m in received] == list(range(len(lines)))
    assert [m.source_line for m in received] == [n for n, _, _ in lines]
    for m, (_, code, words) in zip(received, lines):
        if code in ("G0", "G1") and "X" in words:
            assert m.x_m == words["X"] / 1000.0
        if code in ("G0", "G1") and "E" in words:
            assert m.e_m == words["E"] / 1000.0
    # A standard type decoded by Cyclone: the streamer's closing diagnostics.
    statuses = [s for d in diagnostics for s in d.status if s.name == "/gcode_streamer"]
    assert any(
        s.message == "stream finished"
        and {kv.key: kv.value for kv in s.values}["moves"] == str(len(lines))
        for s in statuses
    ), statuses
    assert_readable_by_independent_readers(bag)
    # Cyclone's acknowledgements reached our nodes (and the recorder recorded them).
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        acks = [
            m for _, _, _, m in reader.iter_decoded_messages(topics=["/gcode/ack"])
            if m.consumer == CONSUMER
        ]
    assert acks and max(a.next_expected for a in acks) == len(lines)


def discovered_nodes(participant, seconds):
    reader = DataReader(
        participant,
        Topic(participant, "ros_discovery_info", ParticipantEntitiesInfo),
        qos=ros_qos(100, transient_local=True),
    )
    nodes = {}
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        for info in valid(reader.take(N=100), ParticipantEntitiesInfo):
            for n in info.node_entities_info_seq:
                nodes[(n.node_namespace, n.node_name)] = n
        time.sleep(0.05)
    return nodes


def test_nodes_appear_in_ros_discovery_info_with_remapped_names(tmp_path):
    streamer = binary("gcode_streamer")
    participant = DomainParticipant(0)
    proc = subprocess.Popen(
        [str(streamer), str(FIXTURES / "finger.gcode"), "--ros-args",
         "-r", "__ns:=/cell", "-r", "__node:=feeder",
         "-p", "consumers:=[/nobody]", "-p", "consumer_timeout_s:=6.0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        nodes = discovered_nodes(participant, 4.0)
    finally:
        proc.kill()
        proc.communicate()
    assert ("/cell", "feeder") in nodes, sorted(nodes)
    feeder = nodes[("/cell", "feeder")]
    assert len(feeder.writer_gid_seq) >= 3  # moves, progress, diagnostics (+ rosout, params)
    assert len(feeder.reader_gid_seq) >= 1  # acks


def test_print_nodes_appear_under_their_default_names(polar_cell, tmp_path):
    participant = DomainParticipant(0)
    proc = subprocess.Popen(
        [str(polar_cell), "print", str(FIXTURES / "finger.gcode"), "--dry-run", "--bag", str(tmp_path / "x.mcap"),
         "--no-progress", "--ros-args", "-p", "gcode_streamer:consumers:=[/bag_recorder, /absent]",
         "-p", "consumer_timeout_s:=60.0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        nodes = discovered_nodes(participant, 4.0)
    finally:
        # SIGINT: the nodes shut down cleanly and the bag is finished.
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    # An interrupted print says so and exits non-zero, with its bag finished.
    assert proc.returncode == 1, err
    assert "interrupted before the end of" in err and "the bag was finished" in err
    assert_readable_by_independent_readers(tmp_path / "x.mcap")
    assert ("/", "gcode_streamer") in nodes, sorted(nodes)
    assert ("/", "bag_recorder") in nodes, sorted(nodes)


def print_beside_a_forger(polar_cell, bag, forge, name="polartest.gcode", pace=("--dry-run",)):
    """A print of `name` (by default a dry run) while `forge()` runs every 5 ms; the print's
    stderr, the bag's message counts and /rosout, and the streamer's closing diagnostics."""
    proc = subprocess.Popen(
        [str(polar_cell), "print", str(FIXTURES / name), "--bag", str(bag), "--no-progress", *pace],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    forged = 0
    try:
        deadline = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < deadline:
            forged += forge()
            time.sleep(0.005)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert forged > 100, forged
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        counts = reader.get_summary().statistics.channel_message_counts
        topics = {c.id: c.topic for c in reader.get_summary().channels.values()}
        by_topic = {topics[k]: v for k, v in counts.items()}
        logs = [m.msg for _, _, _, m in reader.iter_decoded_messages(topics=["/rosout"])]
        closing = [
            {kv.key: kv.value for kv in s.values}
            for _, _, _, d in reader.iter_decoded_messages(topics=["/diagnostics"])
            for s in d.status if s.name == "/gcode_streamer" and s.message == "stream finished"
        ]
    return err, by_topic, logs, closing


def test_forged_acknowledgements_from_a_foreign_participant_change_nothing(polar_cell, tmp_path):
    """A Cyclone participant on the domain acknowledges 10^9 moves in the name of each of the
    print's consumers, every 5 ms, for the whole print. It is not those nodes (it announces
    none), so the streamer ignores every one and counts them in its closing diagnostics; the
    print finishes with every move in the bag."""
    participant = DomainParticipant(0)
    forger = DataWriter(participant, Topic(participant, "rt/gcode/ack", GcodeAck), qos=ros_qos())

    def forge():
        for consumer in ("/bag_recorder", "/polar_planner", "/screw_driver"):
            forger.write(GcodeAck(consumer, 10**9, False))
        return 3

    err, by_topic, logs, closing = print_beside_a_forger(polar_cell, tmp_path / "forged.mcap", forge)
    import re

    moves = int(re.search(r"(\d+) moves from \d+ lines", err).group(1))
    assert moves == 1766, err  # `polar-cell check` on the fixture says 1766
    assert by_topic["/gcode/moves"] == moves, (by_topic["/gcode/moves"], moves)
    assert by_topic["/polar/trajectory"] == by_topic["/gcode/moves"]
    assert not any("impossible" in m for m in logs), logs
    [streamer] = closing
    assert int(streamer["acks_ignored_foreign"]) > 100, streamer
    assert streamer["acks_ignored_impossible"] == "0", streamer


@dataclass
@annotate.final
class PlanCredit(IdlStruct, typename="polar_cell_msgs::msg::dds_::PlanCredit_"):
    header: Header
    executor: str
    executed_until: Time
    accept_until: Time
    horizon_s: t.float64
    closed: bool


def finger_beside_a_forger_plays_exactly(polar_cell, bag, forge):
    """finger at 20x beside `forge()`: the machine plays exactly the plan (4,074 segments,
    168.055 s, no underrun). The bag's /rosout lines and the machine's diagnostics."""
    err, _, logs, _ = print_beside_a_forger(polar_cell, bag, forge, "finger.gcode", ("--speed", "20"))
    executed = next(line for line in err.splitlines() if " executed " in line)
    assert "executed 4074 step segments" in executed, executed
    assert "(168.055 s; planned 168.055 s), 0 underruns" in executed, executed
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        machine = [
            {kv.key: kv.value for kv in s.values}
            for _, _, _, d in reader.iter_decoded_messages(topics=["/diagnostics"])
            for s in d.status if s.name == "/cell_executor"
        ]
    return logs, machine


def test_forged_steps_and_screw_commands_from_a_foreign_participant_move_nothing(polar_cell, tmp_path):
    """While finger prints at 20x, a Cyclone participant publishes, every 5 ms, a step segment
    of 100,000 bed steps, a screw command of 500 rpm with the pin open, a progress report
    saying the stream is finished, and a closed plan credit. The machine executes /polar/steps only
    from the planner, /screw/command only from the screw driver and /gcode/progress only from
    the streamer; the planner follows only the machine's credit. The
    machine plays exactly the plan (4,074 segments, 168.055 s, no underrun), each node logs
    that it ignored each topic, and the machine counts the forgeries in its diagnostics."""
    from test_outside_reader import ScrewCommand, StepSegment

    participant = DomainParticipant(0)
    steps_w = DataWriter(participant, Topic(participant, "rt/polar/steps", StepSegment), qos=ros_qos())
    screw_w = DataWriter(participant, Topic(participant, "rt/screw/command", ScrewCommand), qos=ros_qos())
    progress_w = DataWriter(participant, Topic(participant, "rt/gcode/progress", GcodeProgress), qos=ros_qos())
    credit_w = DataWriter(participant, Topic(participant, "rt/cell/plan_credit", PlanCredit), qos=ros_qos())
    header = Header(Time(0, 0), "")

    def forge():
        steps_w.write(StepSegment(
            header, 5, 1, ["bed", "arm", "z"], [100_000, 0, 0], [1, 1, 1], 0, 1e6,
            100.0, 0.0, 100.0, 0, 100_000, 0, 10.0, True))
        screw_w.write(ScrewCommand(header, 500.0, True, 1, "forged", 0))
        progress_w.write(GcodeProgress(header, "forged", 0, 0, 0, 0, 0, 0, [], [], True))
        # "Closed": a planner that believed it would stop planning, and the print would stall.
        credit_w.write(PlanCredit(header, "forged", Time(0, 0), Time(0, 0), 0.0, True))
        return 4

    logs, machine = finger_beside_a_forger_plays_exactly(polar_cell, tmp_path / "steps.mcap", forge)
    for topic in ("/polar/steps", "/screw/command", "/gcode/progress"):
        assert any(f"ignored {topic} from a writer" in m for m in logs), (topic, logs[-20:])
    assert int(machine[-1]["ignored_foreign_steps"]) > 100, machine[-1]
    assert int(machine[-1]["ignored_foreign_screw_commands"]) > 100, machine[-1]


def test_forged_moves_and_progress_from_a_foreign_participant_change_nothing(polar_cell, tmp_path):
    """A Cyclone participant publishes moves on /gcode/moves (each sequence number a little
    ahead of the real stream, a move far off the bed) and a progress report saying the stream
    is finished, every 5 ms. The consumers take moves and progress only from the streamer
    node's writers: the bag and the plan are the file's, move for move."""
    participant = DomainParticipant(0)
    moves_w = DataWriter(participant, Topic(participant, "rt/gcode/moves", GcodeMove), qos=ros_qos())
    progress_w = DataWriter(participant, Topic(participant, "rt/gcode/progress", GcodeProgress), qos=ros_qos())
    sequence = [0]

    def forge():
        for s in range(sequence[0], sequence[0] + 20):
            moves_w.write(GcodeMove(s, 1, 1, 0, 1, 9.0, 9.0, 0.0, 0.0, 0.0, 0.1, False, 0.0, 0, 0))
        sequence[0] += 5
        progress_w.write(GcodeProgress(Header(Time(0, 0), ""), "forged", 0, 0, 0, 0, 0, 0, [], [], True))
        return 21

    err, by_topic, _, _ = print_beside_a_forger(polar_cell, tmp_path / "moves.mcap", forge, "finger.gcode")
    assert "1778 moves from 2001 lines" in err, err
    assert by_topic["/gcode/moves"] == 1778
    assert by_topic["/polar/trajectory"] == 1778
    with open(tmp_path / "moves.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        recorded = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/gcode/moves"])]
    assert [m.sequence for m in recorded] == list(range(1778))
    assert max(abs(m.x_m) for m in recorded) < 1.0  # no forged 9 m move


def undecodable_type(typename):
    """A type that carries `typename` but one byte: every sample of it is too short for the
    message of that name, as from another build's layout or a truncated forgery."""

    @dataclass
    @annotate.final
    class Short(IdlStruct, typename=typename):
        byte: t.uint8

    return Short


def test_undecodable_samples_on_every_link_are_counted_and_the_print_goes_on(polar_cell, tmp_path):
    """While finger prints at 20x, a Cyclone participant writes, every 5 ms, a sample that
    cannot be decoded on each link of the pipeline: /gcode/moves, /gcode/ack,
    /polar/trajectory, /polar/steps, /screw/command (a one-byte payload under the right type
    name). Each node that reads them skips them, says so once and counts them; the machine
    plays exactly the plan. (One such sample ended the machine node mid-print before, and
    likewise the planner, the screw driver and the streamer.)"""
    participant = DomainParticipant(0)
    writers = []
    for topic, typename in [
        ("gcode/moves", "polar_cell_msgs::msg::dds_::GcodeMove_"),
        ("gcode/ack", "polar_cell_msgs::msg::dds_::GcodeAck_"),
        ("polar/steps", "polar_cell_msgs::msg::dds_::StepSegment_"),
        ("screw/command", "polar_cell_msgs::msg::dds_::ScrewCommand_"),
        ("polar/trajectory", "trajectory_msgs::msg::dds_::JointTrajectory_"),
    ]:
        short = undecodable_type(typename)
        # (The plans are latched: a volatile writer would match none of their readers.)
        qos = ros_qos(transient_local=topic == "polar/trajectory")
        writers.append((DataWriter(participant, Topic(participant, f"rt/{topic}", short), qos=qos), short))

    def forge():
        for writer, short in writers:
            writer.write(short(7))
        return len(writers)

    logs, machine = finger_beside_a_forger_plays_exactly(polar_cell, tmp_path / "undecodable.mcap", forge)
    for topic in ("/gcode/moves", "/gcode/ack", "/polar/trajectory", "/polar/steps", "/screw/command"):
        assert any(f"ignored a {topic} sample that cannot be decoded" in m for m in logs), (topic, logs[-20:])
    assert int(machine[-1]["undecodable_samples"]) > 100, machine[-1]
