"""The machine's input ends where its producers say their output ends, not where the
streamer's `finished` says the file ended: that flag travels on another topic and can
overtake the plan's last segments. A Cyclone peer plays the streamer and the planner for
the machine alone, with a real plan recorded by a dry run, and sends `finished` (with the
planner's acknowledged checkpoint, as the streamer hands it on) before the last segments."""

import math
import os
import subprocess
import time

from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import binary, run
from test_dds import (Gid, GcodeProgress, Header, NodeEntitiesInfo, ParticipantEntitiesInfo,
                      Time, ros_qos)
from test_mechanism import JointState
from test_outside_reader import StepSegment

DOMAIN = 74
HELD_BACK = 6
# The planner's default steps per unit: 32,000 a turn of the bed, 80 a mm of arm, 400 of z.
STEPS_PER_UNIT = (32_000 / (2 * math.pi), 80_000.0, 400_000.0)


def header(h):
    return Header(Time(h.stamp.sec, h.stamp.nanosec), h.frame_id)


def segment(m):
    return StepSegment(header(m.header), m.move_sequence, m.source_line, list(m.axis_names),
                       list(m.step_counts), list(m.directions), m.dominant_axis,
                       m.timer_frequency_hz, m.first_period_ticks, m.ramp_r,
                       m.cruise_period_ticks, m.accelerate_steps, m.cruise_steps,
                       m.decelerate_steps, m.duration_s, m.ends_at_rest)


def progress(m):
    return GcodeProgress(header(m.header), m.file, m.bytes_read, m.bytes_total, m.lines_read,
                         m.moves_published, m.moves_acknowledged, m.warnings, list(m.consumers),
                         list(m.consumer_next_expected), m.finished,
                         list(m.consumer_resume_states), list(m.consumer_resume_state_ends),
                         m.end_of_file, m.moves_waiting)


def test_a_finished_stream_waits_for_the_segments_its_planner_published(polar_cell, tmp_path):
    gcode = tmp_path / "square.gcode"
    gcode.write_text("G1 X20 Y0 F3000\nG1 X20 Y20\nG1 X0 Y20\nG1 X0 Y30\nG1 X30 Y30\nG1 X30 Y5\n")
    bag = tmp_path / "plan.mcap"
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN))
    run([polar_cell, "print", gcode, "--dry-run", "--no-progress", "--bag", bag], env=env)
    with open(bag, "rb") as f:
        recorded = [(c.topic, m) for _, c, _, m in make_reader(f, decoder_factories=[DecoderFactory()])
                    .iter_decoded_messages(topics=["/polar/steps", "/gcode/progress"])]
    steps = [segment(m) for t, m in recorded if t == "/polar/steps"]
    finished = [progress(m) for t, m in recorded if t == "/gcode/progress" and m.finished][-1]
    assert "/polar_planner" in finished.consumers, finished.consumers
    assert len(steps) > 3 * HELD_BACK, len(steps)

    machine = subprocess.Popen(
        [str(binary("cell_executor")), "--ros-args", "-p", "speed:=10.0", "-p", "exit_when_done:=true"],
        env=env, stderr=subprocess.PIPE, text=True)
    try:
        p = DomainParticipant(DOMAIN)
        states = DataReader(p, Topic(p, "rt/joint_states", JointState), qos=ros_qos(100_000))
        steps_writer = DataWriter(p, Topic(p, "rt/polar/steps", StepSegment), qos=ros_qos(10_000))
        progress_writer = DataWriter(p, Topic(p, "rt/gcode/progress", GcodeProgress), qos=ros_qos(10))
        gid = lambda entity: Gid(list(entity.guid.bytes))  # noqa: E731
        announcement = DataWriter(p, Topic(p, "ros_discovery_info", ParticipantEntitiesInfo),
                                  qos=ros_qos(1, transient_local=True))
        announcement.write(ParticipantEntitiesInfo(gid(p), [
            NodeEntitiesInfo("/", "polar_planner", [], [gid(steps_writer)]),
            NodeEntitiesInfo("/", "gcode_streamer", [], [gid(progress_writer)]),
        ]))
        deadline = time.monotonic() + 20
        while not (steps_writer.get_matched_subscriptions() and progress_writer.get_matched_subscriptions()):
            assert time.monotonic() < deadline, "the machine's readers never matched"
            time.sleep(0.05)
        time.sleep(1.0)  # the machine reads the announcement (every half second)
        for s in steps[:-HELD_BACK]:
            steps_writer.write(s)
        time.sleep(0.3)
        # The file is finished and the planner acknowledged every move: the flag comes first.
        progress_writer.write(finished)
        # The machine plays what it has (well under a second at 10×) and waits.
        time.sleep(2.0)
        assert machine.poll() is None, machine.communicate(timeout=5)[1]
        for s in steps[-HELD_BACK:]:
            steps_writer.write(s)
        _, stderr = machine.communicate(timeout=30)
    finally:
        if machine.poll() is None:
            machine.kill()
            machine.wait()
    assert machine.returncode == 0, stderr
    # It ended where the whole plan ends: every segment's steps, the last six included.
    last = [s for s in states.take(N=100_000) if isinstance(s, JointState)][-1]
    end = [sum(s.step_counts[k] * s.directions[k] for s in steps) for k in range(3)]
    assert any(end[k] != sum(s.step_counts[k] * s.directions[k] for s in steps[:-HELD_BACK])
               for k in range(3)), "the held-back segments move the machine"
    assert [round(last.position[k] * STEPS_PER_UNIT[k]) for k in range(3)] == end, (last.position, end)
