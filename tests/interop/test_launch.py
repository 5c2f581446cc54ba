"""The launch scripts start the same nodes with the same parameters as `polar-cell print`."""

import re
import xml.etree.ElementTree as ET

from mcap.reader import make_reader

from conftest import BIN_DIR, FIXTURES, ROOT, assert_readable_by_independent_readers, gcode_motion_lines, run

LAUNCH = ROOT / "launch-scripts"


def test_cell_sh_prints_a_fixture_with_one_process_per_node(tmp_path):
    bag = tmp_path / "cell.mcap"
    run([LAUNCH / "cell.sh", FIXTURES / "polartest.gcode", bag], env={
        "POLAR_CELL_BIN_DIR": str(BIN_DIR), "PATH": "/usr/bin:/bin", "POLAR_CELL_SPEED": "25",
    })
    assert_readable_by_independent_readers(bag)
    with open(bag, "rb") as f:
        summary = make_reader(f).get_summary()
    counts = {
        summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()
    }
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
