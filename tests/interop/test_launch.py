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


@pytest.mark.parametrize("restarted", ["screw_driver", "polar_planner"])
def test_cell_sh_stops_on_the_path_when_a_planner_or_screw_driver_restarts(tmp_path, restarted):
    """A plan producer killed and started again mid-print cannot continue the plan it began
    (a restarted screw driver used to hang the print for good, a restarted planner to start
    its plan clock again): the executor sees the new process, stops on the path (as a cancel
    does, not an emergency stop) and ends the print with the reason, non-zero, and the bag is
    finalised."""
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
        time.sleep(8)  # well into the print (finger's first 30 s of machine time)
        pid = subprocess.run(
            ["pgrep", "-P", str(cell.pid), "-x", restarted], capture_output=True, text=True
        ).stdout.split()
        assert pid, f"no {restarted} under cell.sh"
        os.kill(int(pid[0]), signal.SIGKILL)
        time.sleep(0.5)
        again = subprocess.Popen(
            [str(BIN_DIR / restarted), "--ros-args", "--params-file",
             str(LAUNCH / "params" / "cell.yaml")],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        output, _ = cell.communicate(timeout=30)
    finally:
        for proc in (again, cell):
            if proc is not None:
                try:
                    os.killpg(proc.pid, signal.SIGINT if proc is again else signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait(timeout=10)
    assert cell.returncode != 0, output
    assert f"/{restarted} restarted mid-print" in output, output
    # It was moving: the machine stopped on the path (a cancel's hold), and only then, at
    # rest, took the fault (an emergency stop of a machine standing still).
    assert "stopping on the path" in output, output
    messages, _, _ = read_with_mcap_ros2(bag)
    states = messages["/joint_states"]
    assert len(states) > 8 / 0.02, len(states)  # it had been running
    assert all(abs(v) < 1e-9 for v in states[-1].velocity), states[-1].velocity
