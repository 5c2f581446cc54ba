"""Replay: record -> `polar-cell bag play` -> re-record gives identical messages; and a
consumer restarted mid-print resumes with nothing lost or duplicated (Cyclone DDS peer)."""

import signal
import subprocess
import time

from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from mcap.reader import make_reader

from conftest import FIXTURES, assert_readable_by_independent_readers, binary, gcode_motion_lines, run
from test_dds import GcodeAck, GcodeMove, GcodeProgress, announce_node, ros_qos, valid


def raw_messages(path):
    """(topic, data bytes) per message in file order, read with the mcap package."""
    with open(path, "rb") as f:
        return [(c.topic, bytes(m.data)) for _, c, m in make_reader(f).iter_messages()]


def test_record_play_rerecord_is_identical(polar_cell, printed_bags, tmp_path):
    original, _ = printed_bags["polartest.gcode"]
    rerecorded = tmp_path / "replayed.mcap"
    recorder = subprocess.Popen(
        [str(binary("bag_recorder")), "--ros-args",
         "-p", f"output:={rerecorded}", "-p", "acknowledge_moves:=false"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        run([polar_cell, "bag", "play", original, "--fast", "--wait-subscribers-s", "15",
             "--wait-for-node", "/bag_recorder", "--ros-args", "-r", "__node:=player"])
        time.sleep(0.5)
    finally:
        recorder.send_signal(signal.SIGINT)
        _, err = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, err
    assert_readable_by_independent_readers(rerecorded)
    before = raw_messages(original)
    after = raw_messages(rerecorded)

    def per_topic(messages, topic):
        return [data for t, data in messages if t == topic]

    topics = {t for t, _ in before}
    assert "/gcode/moves" in topics
    for topic in sorted(topics - {"/rosout"}):
        assert per_topic(after, topic) == per_topic(before, topic), topic
    # The re-recording may add the recorder's own log line, never lose one.
    replayed_logs = per_topic(after, "/rosout")
    assert all(log in replayed_logs for log in per_topic(before, "/rosout"))


CONSUMER = "/restartable"


class Consumer:
    """A flow-control consumer that commits its output only when it acknowledges."""

    def __init__(self, participant, ack_every=10, crash_after=None):
        self.moves = DataReader(participant, Topic(participant, "rt/gcode/moves", GcodeMove), qos=ros_qos(10000))
        self.progress = DataReader(participant, Topic(participant, "rt/gcode/progress", GcodeProgress), qos=ros_qos())
        self.acks = DataWriter(participant, Topic(participant, "rt/gcode/ack", GcodeAck), qos=ros_qos())
        self.announcement = announce_node(participant, CONSUMER, [self.moves, self.progress], [self.acks])
        self.next_expected = None
        self.ack_every = ack_every
        self.uncommitted = []
        self.committed = []
        self.finished = False
        self.crashed = False
        self.crash_after = crash_after
        self.last_ack_time = 0.0

    def ack(self):
        self.committed.extend(self.uncommitted)
        self.uncommitted = []
        self.acks.write(GcodeAck(CONSUMER, self.next_expected, False))

    def step(self):
        for p in valid(self.progress.take(N=100), GcodeProgress):
            if self.next_expected is None and CONSUMER in p.consumers:
                self.next_expected = p.consumer_next_expected[p.consumers.index(CONSUMER)]
                self.ack()
            self.finished |= p.finished
        for m in valid(self.moves.take(N=1000), GcodeMove):
            if self.next_expected is not None and m.sequence == self.next_expected:
                self.uncommitted.append(m.sequence)
                self.next_expected += 1
                # Dies before acknowledging the move just processed (checked ahead of the
                # periodic acknowledgement, which would otherwise commit it one time in ten).
                if len(self.committed) + len(self.uncommitted) == self.crash_after:
                    self.crashed = True  # dies here: what was not acknowledged is lost
                    return
                if len(self.uncommitted) >= self.ack_every:
                    self.ack()
        now = time.monotonic()
        if now - self.last_ack_time > 0.02:
            self.last_ack_time = now
            if self.next_expected is None:
                self.acks.write(GcodeAck(CONSUMER, 0, True))
            else:
                self.ack()


def test_restarted_consumer_resumes_without_loss_or_duplicates(polar_cell, tmp_path):
    name = "finger.gcode"
    proc = subprocess.Popen(
        [str(polar_cell), "print", str(FIXTURES / name), "--dry-run", "--bag", str(tmp_path / "r.mcap"),
         "--no-progress", "--ros-args",
         "-p", f"gcode_streamer:consumers:=[/bag_recorder, {CONSUMER}]",
         "-p", "window:=64", "-p", "resend_after_s:=0.2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        first_participant = DomainParticipant(0)
        # Crash after 505 moves, some of them processed but not yet acknowledged.
        first = Consumer(first_participant, crash_after=505)
        deadline = time.monotonic() + 60
        while not first.crashed and time.monotonic() < deadline:
            first.step()
            time.sleep(0.001)
        crashed_with_uncommitted = len(first.uncommitted)
        first_committed = first.committed
        del first
        first_participant = None
        time.sleep(0.5)
        second = Consumer(DomainParticipant(0))
        while not second.finished and time.monotonic() < deadline:
            second.step()
            time.sleep(0.001)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert_readable_by_independent_readers(tmp_path / "r.mcap")
    total = len(gcode_motion_lines(FIXTURES / name))
    assert crashed_with_uncommitted >= 1
    acknowledged = len(first_committed)
    assert first_committed == list(range(acknowledged))
    resumed = [*second.committed, *second.uncommitted]
    assert resumed == list(range(acknowledged, total)), "resumes after the last acknowledgement"
