"""The launch scripts start the same nodes with the same parameters as `polar-cell print`."""

import os
import re
import signal
import subprocess
import time
import xml.etree.ElementTree as ET

import pytest

from mcap.reader import make_reader
from test_bags import read_with_mcap_ros2

from conftest import BIN_DIR, FIXTURES, ROOT, assert_readable_by_independent_readers, gcode_motion_lines, run

LAUNCH = ROOT / "launch-scripts"


def printed_counts(bag):
    """Messages per topic of a print's bag, which the independent readers must read."""
    assert_readable_by_independent_readers(bag)
    with open(bag, "rb") as f:
        summary = make_reader(f).get_summary()
    return {
        summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
    }


def test_cell_sh_prints_a_fixture_with_one_process_per_node(tmp_path):
    bag = tmp_path / "cell.mcap"
    run([LAUNCH / "cell.sh", FIXTURES / "polartest.gcode", bag], env={
        "POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "25",
    })
    counts = printed_counts(bag)
    expected = len(gcode_motion_lines(FIXTURES / "polartest.gcode"))
    assert counts["/gcode/moves"] == expected
    assert counts["/polar/trajectory"] == expected, "the planner ran as its own process"
    # The executor ran as its own process, to the end of the plan (125 s at 25×).
    assert counts["/joint_states"] >= 124.9 / 0.02, counts["/joint_states"]


def test_cell_sh_stopped_mid_print_stops_the_machine_on_the_path(tmp_path):
    """`kill -INT` (or -TERM) to cell.sh mid-print, as a service manager stops it: every node
    goes, and the machine first stops on the path. It used to be dropped mid-move (a real
    MCU's bridge dropped e-stops it), so the bag ended with the machine at speed."""
    bag = tmp_path / "cell.mcap"
    env = {"POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "4"}
    cell = subprocess.Popen([str(LAUNCH / "cell.sh"), str(FIXTURES / "finger.gcode"), str(bag)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        time.sleep(7.0)
        cell.send_signal(signal.SIGINT)
        output, _ = cell.communicate(timeout=60)
    finally:
        if cell.poll() is None:
            os.killpg(cell.pid, signal.SIGKILL)
            cell.wait(timeout=10)
    leftover = subprocess.run(["pgrep", "-s", str(cell.pid)], capture_output=True, text=True)
    assert leftover.stdout.strip() == "", ("nodes left running", leftover.stdout, output)
    assert "stopping on the path" in output, output
    messages, _, _ = read_with_mcap_ros2(bag)
    states = messages["/joint_states"]
    # It printed for a while, then came to rest: its last state stands still, away from home.
    assert len(states) > 100, len(states)
    assert all(abs(v) < 1e-9 for v in states[-1].velocity), states[-1].velocity
    assert states[-1].position[1] > 0.01, states[-1].position


def test_cell_sh_ends_when_the_planner_refuses_a_move(tmp_path):
    """A move beyond the arm's reach: the planner says so and exits 1. cell.sh used to watch
    only the machine and the streamer, which both wait for the plan for ever: it hung. It
    ends with the planner's status and stops every node."""
    gcode = tmp_path / "far.gcode"
    gcode.write_text("G28\nG1 X10 Y10 F600\nG1 X400 Y0 F600\n")
    env = {"POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "25"}
    proc = subprocess.run([str(LAUNCH / "cell.sh"), str(gcode), str(tmp_path / "far.mcap")],
                          env=env, capture_output=True, text=True, timeout=60,
                          start_new_session=True)
    assert proc.returncode == 1, (proc.returncode, proc.stdout, proc.stderr)
    assert "polar_planner ended with exit status 1" in proc.stderr, proc.stderr


def test_launch_xml_names_existing_binaries_and_parameter_file():
    root = ET.parse(LAUNCH / "cell.launch.xml").getroot()
    args = {a.get("name"): a.get("default") for a in root.iter("arg")}
    assert set(args) == {"gcode_file", "bag", "bin_dir", "params"}
    commands = [e.get("cmd") for e in root.iter("executable")]
    assert len(commands) == 5
    for cmd in commands:
        binary = re.match(r"\$\(var bin_dir\)/(\S+)", cmd).group(1)
        assert (BIN_DIR / binary).exists(), binary
        assert "--params-file $(var params)" in cmd
    assert (LAUNCH / args["params"].replace("$(dirname)/", "")).exists()


def test_mechanism_launch_xml_starts_an_existing_binary_with_the_parameter_file():
    root = ET.parse(LAUNCH / "mechanism.launch.xml").getroot()
    (cmd,) = [e.get("cmd") for e in root.iter("executable")]
    assert re.match(r"\$\(var bin_dir\)/mechanism_kin ", cmd)
    assert (BIN_DIR / "mechanism_kin").exists()
    assert "--params-file $(var params)" in cmd


def test_cell_sh_prints_on_the_mcu_emulator(tmp_path):
    """POLAR_CELL_DEVICE=emulator: the machine is mcu_bridge with mcu_emulator on a socket."""
    bag = tmp_path / "mcu.mcap"
    run([LAUNCH / "cell.sh", FIXTURES / "polartest.gcode", bag], env={
        "POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "10",
        "POLAR_CELL_DEVICE": "emulator",
    })
    counts = printed_counts(bag)
    expected = len(gcode_motion_lines(FIXTURES / "polartest.gcode"))
    assert counts["/gcode/moves"] == expected
    # The MCU's reports over the whole plan (125 s): stamps (when the MCU measured them)
    # span it. At 10x the emulator reports every 1 ms of wall time, its own poll period; on a
    # loaded CI machine it misses some, and a 50 Hz sample with no newer report than the
    # last is not published twice: 44 Hz here, 37 Hz seen in CI. Enough for RViz, not a
    # rate to promise at 10x.
    decoded, _, _ = read_with_mcap_ros2(bag)
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in decoded["/joint_states"]]
    assert stamps[-1] - stamps[0] >= 124.0, stamps[-1] - stamps[0]
    assert counts["/joint_states"] >= 25 * 125, counts["/joint_states"]
    # The diagnostics are the bridge's, with what it learnt of the MCU.
    statuses = [s for d in decoded["/diagnostics"] for s in d.status if s.name == "/mcu_bridge"]
    assert statuses, "no diagnostics from /mcu_bridge"
    values = {v.key: v.value for v in statuses[-1].values}
    assert values["mcu_timer_hz"] == "1000000", values


def test_mcu_launch_xml_names_existing_binaries_and_parameter_file():
    root = ET.parse(LAUNCH / "cell_mcu.launch.xml").getroot()
    commands = [e.get("cmd") for e in root.iter("executable")]
    binaries = [re.match(r"\$\(var bin_dir\)/(\S+)", cmd).group(1) for cmd in commands]
    assert "mcu_bridge" in binaries and "mcu_emulator" in binaries
    assert "cell_executor" not in binaries
    for binary in binaries:
        assert (BIN_DIR / binary).exists(), binary


def run_cell_sh_and_restart(tmp_path, restarted, kill_after_s=8.0, extra_args=(), away_s=0.5):
    """finger.gcode under cell.sh at 4x; `restarted` SIGKILLed after `kill_after_s` (well into
    finger's first 30 s of machine time) and started again `away_s` later. Returns cell.sh's
    return code, its output and the bag."""
    bag = tmp_path / "cell.mcap"
    env = {"POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "4"}
    # Its own process group, so that whatever happens every node of it goes at the end.
    cell = subprocess.Popen(
        [str(LAUNCH / "cell.sh"), str(FIXTURES / "finger.gcode"), str(bag)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )
    again = None
    try:
        time.sleep(kill_after_s)
        pid = subprocess.run(
            ["pgrep", "-P", str(cell.pid), "-x", restarted], capture_output=True, text=True
        ).stdout.split()
        assert pid, f"no {restarted} under cell.sh"
        os.kill(int(pid[0]), signal.SIGKILL)
        time.sleep(away_s)
        again = subprocess.Popen(
            [str(BIN_DIR / restarted), "--ros-args", "--params-file",
             str(LAUNCH / "params" / "cell.yaml"), *extra_args],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True,
        )
        output, _ = cell.communicate(timeout=90)
    finally:
        for proc in (again, cell):
            if proc is not None:
                try:
                    os.killpg(proc.pid, signal.SIGINT if proc is again else signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait(timeout=10)
    if again is not None:
        output += "\n--- restarted " + restarted + " ---\n" + again.stdout.read()
    return cell.returncode, output, bag


def stamp_ns(t):
    return t.sec * 1_000_000_000 + t.nanosec


def assert_planned_states_once(messages):
    """The bag's /polar/planned_joint_states hold each sample once: per set of joints (the
    planner's stage joints, the screw driver's screw) the stamps only increase, though a
    restarted node published again what it had published before its last acknowledgement
    (the recorder leaves those repeats out)."""
    lanes = {}
    for state in messages["/polar/planned_joint_states"]:
        lanes.setdefault(tuple(state.name), []).append(stamp_ns(state.header.stamp))
    assert set(lanes) == {("bed_theta", "arm_r", "z"), ("screw",)}, set(lanes)
    for lane, stamps in lanes.items():
        backwards = sum(1 for a, b in zip(stamps, stamps[1:]) if b <= a)
        assert backwards == 0, (lane, backwards, len(stamps))


def test_a_screw_driver_restarted_mid_print_continues_its_commands(tmp_path):
    """A screw driver killed mid-print and started again resumes from the checkpoint it
    acknowledged (screw_driver::stream): the streamer sends its moves again, the planner's
    transient-local /polar/trajectory their plans, and it publishes the same numbered commands
    again from there. The machine drops the repeats by number, holds on the path if it is
    about to run out of commands, and the print completes: the bag holds every command once,
    numbered without a gap, in time order, and the screw turned as much as in a print that was
    not interrupted."""
    returncode, output, bag = run_cell_sh_and_restart(tmp_path, "screw_driver", 6.0)
    assert returncode == 0, output
    messages, _, _ = read_with_mcap_ros2(bag)
    log = [(entry.name, entry.msg) for entry in messages["/rosout"]]
    assert any(n == "screw_driver" and m.startswith("resumed after move") for n, m in log), log
    assert any("/screw_driver restarted and continues the screw commands at command" in m
               for _, m in log), log
    commands = messages["/screw/command"]
    assert [c.sequence for c in commands] == list(range(len(commands)))
    assert_planned_states_once(messages)
    stamps = [stamp_ns(c.header.stamp) for c in commands]
    assert all(a <= b for a, b in zip(stamps, stamps[1:]))
    final = messages["/joint_states"][-1]
    assert all(abs(v) < 1e-9 for v in final.velocity), final.velocity
    # The screw's executed angle against the same print uninterrupted (held commands: the
    # angle is their exact integral, whatever the chunks).
    reference_bag = tmp_path / "reference.mcap"
    env = {"POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "4"}
    subprocess.run([str(LAUNCH / "cell.sh"), str(FIXTURES / "finger.gcode"), str(reference_bag)],
                   env=env, check=True, capture_output=True, timeout=120)
    reference, _, _ = read_with_mcap_ros2(reference_bag)
    turned, expected = final.position[3], reference["/joint_states"][-1].position[3]
    assert abs(turned - expected) <= 1e-6 * abs(expected), (turned, expected)


def test_a_restarted_screw_driver_that_cannot_continue_stops_the_print(tmp_path):
    """A screw driver restarted with other options (here another pin delay) would command
    another screw: it refuses the checkpoint, says why and exits; the machine holds on the
    path before the commands it has run out, and stops the print screw_resume_timeout_s
    (10 s) later, non-zero, with the reason, at rest."""
    returncode, output, bag = run_cell_sh_and_restart(
        tmp_path, "screw_driver", 6.0, ("-p", "pin_open_delay_s:=0.3"))
    assert returncode != 0, output
    assert "/screw_driver did not continue the screw commands" in output, output
    messages, _, _ = read_with_mcap_ros2(bag)
    log = [(entry.name, entry.msg) for entry in messages["/rosout"]]
    assert any(n == "screw_driver" and "cannot continue the screw commands: resume state was "
               "written by a screw driver with other options" in m for n, m in log), log
    assert all(abs(v) < 1e-9 for v in messages["/joint_states"][-1].velocity)


# One step of bed_theta (rad), arm_r and z (m) at the shipped steps_per_unit.
ONE_STEP = (6.283185307179586 / 32000.0, 1.0 / 80000.0, 1.0 / 400000.0)


@pytest.mark.parametrize("kill_after_s", [6.0, 9.5])
def test_a_planner_restarted_mid_print_continues_the_plan(tmp_path, kill_after_s):
    """A planner killed mid-print and started again resumes where it acknowledged, on the same
    timeline (polar_planner::resume): the print completes, and the bag holds the plan once —
    every move's trajectory and steps exactly once, each move starting where the one before
    ended — and the machine ends where the plan ends."""
    returncode, output, bag = run_cell_sh_and_restart(tmp_path, "polar_planner", kill_after_s)
    assert returncode == 0, output
    messages, _, _ = read_with_mcap_ros2(bag)
    log = [(entry.name, entry.msg) for entry in messages["/rosout"]]
    assert any(n == "polar_planner" and m.startswith("resumed after move") for n, m in log), log
    assert any("/polar_planner restarted and continues the plan at move" in m for _, m in log), log
    assert not any("lost part of the plan" in m for _, m in log), log
    moves = messages["/gcode/moves"]
    trajectories = messages["/polar/trajectory"]
    segments = messages["/polar/steps"]
    assert len(moves) == len(gcode_motion_lines(FIXTURES / "finger.gcode"))
    # One trajectory per move, each starting where the one before ended (1 us: ns rounding).
    assert len(trajectories) == len(moves), (len(trajectories), len(moves))
    assert_planned_states_once(messages)

    def ns(t):
        return t.sec * 1_000_000_000 + t.nanosec

    end = None
    for k, tr in enumerate(trajectories):
        start = ns(tr.header.stamp)
        if end is not None:
            assert abs(start - end) <= 1000, (k, start, end)
        last = tr.points[-1].time_from_start
        end = start + last.sec * 1_000_000_000 + last.nanosec
    # Segments: moves in order, each move's first one where the move before ended.
    move_start, move_end, last_sequence = None, None, -1
    for seg in segments:
        if seg.move_sequence != last_sequence:
            assert seg.move_sequence > last_sequence, (seg.move_sequence, last_sequence)
            if move_end is not None:
                assert abs(ns(seg.header.stamp) - move_end) <= 1000, seg.move_sequence
            last_sequence, move_start, move_end = seg.move_sequence, ns(seg.header.stamp), ns(seg.header.stamp)
        move_end += round(seg.duration_s * 1e9)
    # The machine ends at rest where the plan ends, within a step of each joint (the last
    # sample used to come up to a sample period before the end).
    final = messages["/joint_states"][-1]
    assert all(abs(v) < 1e-9 for v in final.velocity[:3]), final.velocity
    planned = trajectories[-1].points[-1].positions
    for j in range(3):
        assert abs(final.position[j] - planned[j]) <= ONE_STEP[j] * 1.01, (j, final.position, planned)
    # The steps add up to the plan's end: none lost, none doubled.
    totals = [0, 0, 0]
    for seg in segments:
        for j in range(3):
            totals[j] += seg.step_counts[j] * seg.directions[j]
    for j, per_step in enumerate(ONE_STEP):
        assert abs(totals[j] - round(planned[j] / per_step)) <= 1, (j, totals, planned)


def test_a_restarted_planner_that_cannot_continue_stops_the_print(tmp_path):
    """A planner restarted with other options (here a finer path tolerance) would plan another
    timeline: it refuses the checkpoint, says why and exits; the machine, holding on the path
    once its plan runs out, stops the print planner_resume_timeout_s (10 s) later, non-zero,
    with the reason, at rest."""
    returncode, output, bag = run_cell_sh_and_restart(
        tmp_path, "polar_planner", 6.0, ("-p", "path_tolerance_m:=2e-6"))
    assert returncode != 0, output
    assert "/polar_planner restarted mid-print and did not continue the plan" in output, output
    messages, _, _ = read_with_mcap_ros2(bag)
    log = [(entry.name, entry.msg) for entry in messages["/rosout"]]
    assert any(n == "polar_planner" and "cannot continue the plan: resume state was written by a "
               "planner with other options" in m for n, m in log), log
    assert all(abs(v) < 1e-9 for v in messages["/joint_states"][-1].velocity)
