"""Shared fixtures for the interop tests: our binaries, the fixtures, a Cyclone DDS config.

These tests check our output with independent implementations (Cyclone DDS, mcap-ros2-support,
rosbags). Run them inside a private network namespace (see .ci/run): DDS traffic stays there.
"""

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT.parent / "shared" / "fixtures" / "gcode"
BIN_DIR = Path(os.environ.get("POLAR_CELL_BIN_DIR", ROOT / "target" / "release"))

CYCLONE_LOOPBACK = """<CycloneDDS><Domain id="any">
  <General><Interfaces><NetworkInterface name="lo"/></Interfaces>
    <AllowMulticast>false</AllowMulticast></General>
  <Discovery><Peers><Peer address="127.0.0.1"/></Peers>
    <ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>60</MaxAutoParticipantIndex>
  </Discovery>
</Domain></CycloneDDS>"""

os.environ.setdefault("CYCLONEDDS_URI", CYCLONE_LOOPBACK)


def binary(name: str) -> Path:
    path = BIN_DIR / name
    if not path.exists():
        pytest.fail(f"{path} is missing: build with `cargo build --release` first")
    return path


def run(args, timeout=120, **kwargs):
    """Run a command, failing the test with its output if it fails."""
    proc = subprocess.run(
        [str(a) for a in args], capture_output=True, text=True, timeout=timeout, **kwargs
    )
    if proc.returncode != 0:
        pytest.fail(f"{args} exited {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc


def gcode_motion_lines(path: Path):
    """Independent reading of a fixture: (line number, words) of every G0/G1/G28/G92 line."""
    out = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        code = line.split(";", 1)[0].strip()
        m = re.match(r"^(G0|G1|G28|G92)(\s|$)", code)
        if m:
            words = dict(
                (w[0], float(w[1:])) for w in code.split()[1:] if len(w) > 1
            )
            out.append((number, m.group(1), words))
    return out


@pytest.fixture(scope="session")
def polar_cell():
    return binary("polar-cell")


@pytest.fixture(scope="session")
def printed_bags(polar_cell, tmp_path_factory):
    """Print both fixtures once, as a bare file and as a bag directory."""
    out = tmp_path_factory.mktemp("bags")
    bags = {}
    for name in ("finger.gcode", "polartest.gcode"):
        bare = out / f"{name}.mcap"
        directory = out / f"{name}_dir"
        for args in (["--bag", bare], ["--bag", directory, "--bag-dir"]):
            stderr = run([polar_cell, "print", FIXTURES / name, *args, "--no-progress", "--dry-run"]).stderr
            assert "did not receive the final" not in stderr, stderr
        bags[name] = (bare, directory)
    return bags


def assert_readable_by_independent_readers(bag: Path):
    """mcap-ros2-support and rosbags decode every message; counts equal the bag's statistics."""
    from test_bags import mcap_file, read_with_mcap_ros2, read_with_rosbags

    decoded, stats, summary = read_with_mcap_ros2(mcap_file(bag))
    for topic in {c.topic for c in summary.channels.values()}:
        assert len(decoded.get(topic, [])) == stats.get(topic, 0), (bag, topic)
    by_rosbags, counts = read_with_rosbags(bag)
    assert counts == {t: stats.get(t, 0) for t in counts}, bag
    for topic, count in counts.items():
        assert len(by_rosbags.get(topic, [])) == count, (bag, topic)
    return decoded
