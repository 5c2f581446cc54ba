"""Bags written by `polar-cell print`, read by mcap-ros2-support and rosbags."""

from collections import Counter
import time

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

from conftest import FIXTURES, ROOT, gcode_motion_lines, run

MSG_DIR = ROOT / "nodes" / "polar_cell_msgs" / "msg"


def mcap_file(bag):
    return bag if bag.is_file() else next(bag.glob("*.mcap"))


def read_with_mcap_ros2(path):
    """Decoded messages per topic, and the bag's statistics, via mcap-ros2-support."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert reader.get_header().profile == "ros2"
        stats = {
            summary.channels[cid].topic: count
            for cid, count in summary.statistics.channel_message_counts.items()
        }
        decoded = {}
        for schema, channel, message, ros_msg in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            assert message.data[:4] == b"\x00\x01\x00\x00"
            decoded.setdefault(channel.topic, []).append(ros_msg)
        return decoded, stats, summary


def rosbags_typestore():
    """Jazzy's standard types plus ours, registered from our .msg files."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for msg in sorted(MSG_DIR.glob("*.msg")):
        types.update(get_types_from_msg(msg.read_text(), f"polar_cell_msgs/msg/{msg.stem}"))
    store.register(types)
    return store


def read_with_rosbags(path):
    store = rosbags_typestore()
    decoded = {}
    with AnyReader([path], default_typestore=store) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        for connection, _timestamp, raw in reader.messages():
            decoded.setdefault(connection.topic, []).append(
                reader.deserialize(raw, connection.msgtype)
            )
    return decoded, counts


@pytest.mark.parametrize("name", ["finger.gcode", "polartest.gcode"])
def test_mcap_ros2_support_reads_every_message_with_expected_values(printed_bags, name):
    for bag in printed_bags[name]:
        decoded, stats, summary = read_with_mcap_ros2(mcap_file(bag))
        for topic, count in stats.items():
            assert len(decoded.get(topic, [])) == count, topic
        assert sum(stats.values()) == summary.statistics.message_count
        assert summary.chunk_indexes, "chunk indexes are written"
        lines = gcode_motion_lines(FIXTURES / name)
        moves = decoded["/gcode/moves"]
        assert len(moves) == len(lines)
        assert [m.sequence for m in moves] == list(range(len(lines)))
        assert [m.source_line for m in moves] == [n for n, _, _ in lines]
        kinds = {"G0": 0, "G1": 1, "G28": 5, "G92": 6}
        assert [m.kind for m in moves] == [kinds[c] for _, c, _ in lines]
        # X words are absolute mm (no G92 X in these files): x_m is X / 1000 exactly.
        checked = 0
        for m, (_, code, words) in zip(moves, lines):
            if code in ("G0", "G1") and "X" in words:
                assert m.x_m == words["X"] / 1000.0
                checked += 1
            if code in ("G0", "G1") and "F" in words:
                assert m.feedrate_m_per_s == pytest.approx(words["F"] / 60000.0, rel=1e-15)
        assert checked > 1000
        progress = decoded["/gcode/progress"]
        assert progress[-1].finished
        assert progress[-1].moves_acknowledged == len(lines)
        diag = [d.status[0] for d in decoded["/diagnostics"] if d.status[0].name == "/gcode_streamer"][-1]
        assert diag.message == "stream finished"
        assert {kv.key: kv.value for kv in diag.values}["moves"] == str(len(lines))


@pytest.mark.parametrize("name", ["finger.gcode", "polartest.gcode"])
def test_rosbags_reads_bare_file_and_directory_identically(printed_bags, name):
    bare, directory = printed_bags[name]
    per_form = []
    for bag in (bare, directory):
        decoded, counts = read_with_rosbags(bag)
        for topic, count in counts.items():
            assert len(decoded.get(topic, [])) == count, (bag, topic)
        reference, stats, summary = read_with_mcap_ros2(mcap_file(bag))
        # Statistics omit channels without messages; rosbags lists every channel.
        assert set(counts) == {c.topic for c in summary.channels.values()}
        assert counts == {t: stats.get(t, 0) for t in counts}
        moves = decoded["/gcode/moves"]
        assert [m.sequence for m in moves] == [m.sequence for m in reference["/gcode/moves"]]
        assert [m.x_m for m in moves] == [m.x_m for m in reference["/gcode/moves"]]
        per_form.append(Counter({t: len(v) for t, v in decoded.items()}))
    assert per_form[0]["/gcode/moves"] == per_form[1]["/gcode/moves"]


def test_metadata_yaml_matches_channels(printed_bags):
    import yaml

    _, directory = printed_bags["finger.gcode"]
    info = yaml.safe_load((directory / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    _, stats, summary = read_with_mcap_ros2(mcap_file(directory))
    listed = {
        t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]
    }
    channels = {c.topic for c in summary.channels.values()}
    assert set(listed) == channels
    for topic in channels:
        assert listed[topic] == stats.get(topic, 0)
    assert info["message_count"] == summary.statistics.message_count
    assert info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == [mcap_file(directory).name]


def test_bag_info_reports_the_statistics(polar_cell, printed_bags):
    bare, _ = printed_bags["polartest.gcode"]
    out = run([polar_cell, "bag", "info", bare]).stdout
    _, stats, _ = read_with_mcap_ros2(bare)
    assert f"Topic: /gcode/moves | Type: polar_cell_msgs/msg/GcodeMove | Count: {stats['/gcode/moves']}" in out


def test_malformed_gcode_is_a_precise_error_not_a_crash(polar_cell, tmp_path):
    bad = tmp_path / "bad.gcode"
    bad.write_text("G1 X1 Y1\nG1 X2 Y\n")
    import subprocess

    proc = subprocess.run(
        [str(polar_cell), "print", str(bad), "--bag", str(tmp_path / "b.mcap"), "--no-progress", "--dry-run"],
        capture_output=True, text=True, timeout=60,
    )
    assert proc.returncode == 1
    assert "bad.gcode:2:8: expected a number after `Y`" in proc.stderr
    assert "panicked" not in proc.stderr


def test_the_bag_says_the_qos_its_publishers_offer(printed_bags):
    """metadata.yaml and the MCAP channels carry the QoS the nodes publish with (README,
    Topics), not ROS's default depth 10 — read here with PyYAML and the mcap library."""
    import yaml

    _, directory = printed_bags["finger.gcode"]
    info = yaml.safe_load((directory / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    offered = {
        t["topic_metadata"]["name"]: yaml.safe_load(t["topic_metadata"]["offered_qos_profiles"])
        for t in info["topics_with_message_count"]
    }
    _, _, summary = read_with_mcap_ros2(mcap_file(directory))
    for channel in summary.channels.values():
        assert yaml.safe_load(channel.metadata["offered_qos_profiles"]) == offered[channel.topic]
    # rosbag2's enums: reliability 1 reliable; durability 1 transient local, 2 volatile.
    expected = {
        "/gcode/moves": (4096, 2),
        "/gcode/ack": (1000, 2),
        "/polar/steps": (10_000, 2),
        # Transient-local: a restarted screw driver gets the plans again.
        "/polar/trajectory": (5120, 1),
        "/screw/command": (10_000, 2),
        "/joint_states": (1000, 2),
        "/tf": (1000, 2),
        "/diagnostics": (10, 2),
        "/robot_description": (1, 1),
        "/tf_static": (1, 1),
        "/rosout": (1, 1),
    }
    for topic, (depth, durability) in expected.items():
        [profile] = offered[topic]
        assert (profile["depth"], profile["durability"], profile["reliability"]) == (
            depth,
            durability,
            1,
        ), topic


def test_a_recorder_the_streamer_does_not_wait_for_says_its_bag_lacks_the_moves(tmp_path):
    """A standalone recorder that is not among the streamer's `consumers` is never told where
    the moves start, so it takes none of them. It used to exit 0 with an empty /gcode/moves;
    it must say what its bag lacks and why, and exit non-zero. The recorder that is named
    records every move."""
    import signal
    import subprocess
    from conftest import BIN_DIR

    gcode = FIXTURES / "polartest.gcode"
    named, unnamed = tmp_path / "named.mcap", tmp_path / "unnamed.mcap"

    def recorder(out, *rename):
        return subprocess.Popen(
            [str(BIN_DIR / "bag_recorder"), "--ros-args", *rename, "-p", f"output:={out}",
             "-p", "topics:=[/gcode/moves]"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    recorders = [recorder(named, "-r", "__node:=first"), recorder(unnamed)]
    try:
        time.sleep(1.0)  # both subscribed before the stream starts
        run([BIN_DIR / "gcode_streamer", gcode, "--ros-args", "-p", "consumers:=[/first]"])
        time.sleep(1.0)
    finally:
        for proc in recorders:
            proc.send_signal(signal.SIGINT)
        errors = [proc.communicate(timeout=30)[1] for proc in recorders]
    assert recorders[0].returncode == 0, errors[0]
    with open(named, "rb") as f:
        summary = make_reader(f).get_summary()
    counts = {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}
    assert counts["/gcode/moves"] == len(gcode_motion_lines(gcode))
    assert recorders[1].returncode != 0, errors[1]
    assert "the bag lacks" in errors[1] and "/gcode/moves" in errors[1], errors[1]
    assert "does not count this recorder among its consumers" in errors[1], errors[1]


def test_bag_play_skips_a_type_it_does_not_know_and_names_what_is_wrong(polar_cell, tmp_path):
    """A bag from another ROS 2 tool may hold types the suite does not know: `bag play`
    plays the rest and says what it skips (as `ros2 bag play` does), refuses the topic when
    asked for it by name, and names the file and message of a corrupt chunk."""
    import subprocess
    from mcap.writer import CompressionType
    from mcap_ros2.writer import Writer

    bag = tmp_path / "foreign.mcap"
    with open(bag, "wb") as f:
        # Uncompressed chunks with CRCs: the damage below lands in a message's bytes.
        writer = Writer(f, compression=CompressionType.NONE)
        int32 = writer.register_msgdef("std_msgs/msg/Int32", "int32 data")
        string = writer.register_msgdef("std_msgs/msg/String", "string data")
        for i in range(5):
            writer.write_message(topic="/chatter", schema=int32, message={"data": i},
                                 log_time=1_000 + i, publish_time=1_000 + i)
            writer.write_message(topic="/note", schema=string, message={"data": f"n{i}"},
                                 log_time=1_000 + i, publish_time=1_000 + i)
        writer.finish()

    def play(*extra):
        return subprocess.run([str(polar_cell), "bag", "play", str(bag), "--fast", *extra],
                              capture_output=True, text=True, timeout=60)

    played = play()
    assert played.returncode == 0, played.stderr
    assert f"warning: {bag}: not playing /chatter (5 messages)" in played.stderr, played.stderr
    assert "std_msgs/msg/Int32 is not one of the suite's message types" in played.stderr
    asked = play("--topics", "/chatter")
    assert asked.returncode != 0
    assert f"{bag}: topic /chatter" in asked.stderr, asked.stderr

    # A damaged chunk (its CRC no longer matches): the file and the message are named.
    data = bytearray(bag.read_bytes())
    at = data.find(b"n2")
    assert at > 0
    data[at:at + 2] = b"\xff\xff"
    bag.write_bytes(bytes(data))
    broken = play("--topics", "/note")
    assert broken.returncode != 0 and "panicked" not in broken.stderr, broken.stderr
    assert str(bag) in broken.stderr, broken.stderr


def test_a_best_effort_topic_is_recorded_with_the_qos_its_publisher_offers(tmp_path):
    """A topic the suite does not define, published best effort (as sensor drivers do): the
    recorder takes the QoS its publisher offers, as rosbag2 does. Its reader was reliable,
    which matches no best-effort writer: the bag held none of it, and said nothing."""
    import os
    import signal
    import subprocess
    import yaml
    from dataclasses import dataclass
    import cyclonedds.idl.annotations as annotate
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.pub import DataWriter
    from cyclonedds.topic import Topic
    from conftest import BIN_DIR

    @dataclass
    @annotate.final
    class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
        data: str

    domain = 91
    participant = DomainParticipant(domain)
    best_effort = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile,
                      Policy.History.KeepLast(10),
                      Policy.DataRepresentation(use_cdrv0_representation=True))
    writer = DataWriter(participant, Topic(participant, "rt/chatter", String), qos=best_effort)
    out = tmp_path / "chatter"
    recorder = subprocess.Popen(
        [str(BIN_DIR / "bag_recorder"), "--ros-args", "-p", f"output:={out}",
         "-p", "bag_directory:=true", "-p", "topics:=[/chatter:std_msgs/msg/String]",
         "-p", "acknowledge_moves:=false", "-p", "qos_wait_s:=5.0"],
        env=dict(os.environ, ROS_DOMAIN_ID=str(domain)),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 15
        while not writer.get_matched_subscriptions():
            assert time.monotonic() < deadline, "the recorder's reader never matched"
            time.sleep(0.05)
        for k in range(100):
            writer.write(String(f"hello {k}"))
            time.sleep(0.01)
        time.sleep(1.0)
    finally:
        recorder.send_signal(signal.SIGINT)
        _, stderr = recorder.communicate(timeout=30)
    with open(out / "chatter_0.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        texts = [m.data for _, _, _, m in reader.iter_decoded_messages(topics=["/chatter"])]
    # Best effort on loopback: all of it here, but not promised.
    assert len(texts) >= 90 and texts[0] == "hello 0", (len(texts), stderr)
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    [chatter] = [t["topic_metadata"] for t in info["topics_with_message_count"]
                 if t["topic_metadata"]["name"] == "/chatter"]
    [offered] = yaml.safe_load(chatter["offered_qos_profiles"])
    assert (offered["reliability"], offered["durability"]) == (2, 2), offered


def test_a_recorder_stopped_while_it_starts_leaves_a_finished_bag(tmp_path):
    """SIGINT while the recorder still waits for the QoS an outside topic's publisher offers
    (its bag file already created): the default action used to kill it there, leaving an
    MCAP without its end where the bag was asked for. Caught from the start, the signal
    ends the recording as any other stop does: a bag every reader opens."""
    import os
    import signal
    import subprocess
    from mcap.reader import make_reader as plain_reader
    from conftest import BIN_DIR

    out = tmp_path / "early.mcap"
    recorder = subprocess.Popen(
        [str(BIN_DIR / "bag_recorder"), "--ros-args", "-p", f"output:={out}",
         "-p", "topics:=[/chatter:std_msgs/msg/String]",
         "-p", "acknowledge_moves:=false", "-p", "qos_wait_s:=5.0"],
        env=dict(os.environ, ROS_DOMAIN_ID="92"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(2.0)
    assert recorder.poll() is None, recorder.communicate()
    assert out.exists(), "the bag is created before the QoS wait"
    recorder.send_signal(signal.SIGINT)
    _, stderr = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, (recorder.returncode, stderr)
    with open(out, "rb") as f:
        summary = plain_reader(f).get_summary()
    assert summary is not None, "no summary: the bag was not finished"
