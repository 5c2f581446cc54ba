"""A print killed mid-way (SIGKILL: no chance to finish its bag), its bag recovered by
`polar-cell bag recover`, checked against what an independent stream reader (the `mcap`
Python library's StreamReader, reading records from the front until the file breaks off)
salvages from the same file, and read back by mcap-ros2-support and rosbags."""

import os
import signal
import subprocess
import time

from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from conftest import binary
from test_bags import read_with_mcap_ros2, read_with_rosbags

DOMAIN = 79


def stream_salvage(path):
    """(channel topic, log time, data) of every message a stream reader gets before the
    file breaks off."""
    topics, out = {}, []
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, emit_chunks=False).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message):
                    out.append((topics[record.channel_id], record.log_time, bytes(record.data)))
        except Exception:  # the truncated end: what came before stands
            pass
    return out


def test_a_killed_print_s_bag_is_recovered_to_its_last_flush(tmp_path):
    killed = tmp_path / "killed.mcap"
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN))
    proc = subprocess.Popen(
        [str(binary("polar-cell")), "print", "--no-progress", "--speed", "4", "--bag", str(killed)],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(6.0)
    proc.send_signal(signal.SIGKILL)
    killed_ns = time.time_ns()
    proc.wait(timeout=10)

    info = subprocess.run(
        [str(binary("polar-cell")), "bag", "info", str(killed)], capture_output=True, text=True
    )
    assert info.returncode != 0
    assert "not finished" in info.stderr and "bag recover" in info.stderr, info.stderr

    salvaged = stream_salvage(killed)
    assert len(salvaged) > 1000, len(salvaged)

    recovered = tmp_path / "recovered.mcap"
    out = subprocess.run(
        [str(binary("polar-cell")), "bag", "recover", str(killed), str(recovered)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stderr
    mine = stream_salvage(recovered)
    # At least what the independent reader gets, the same messages in the same order.
    assert len(mine) >= len(salvaged), (len(mine), len(salvaged), out.stderr)
    assert mine[: len(salvaged)] == salvaged

    # A finished bag again: both independent readers decode it, statistics and all.
    decoded, stats, _ = read_with_mcap_ros2(recovered)
    assert sum(stats.values()) == len(mine)
    assert sum(len(v) for v in decoded.values()) == len(mine)
    assert len(decoded["/joint_states"]) > 50
    _, counts = read_with_rosbags(recovered)
    assert sum(counts.values()) == len(mine)

    # The recorder closes a chunk every second (flush_period_s): the kill cost at most that,
    # and the time its queue held.
    last_ns = max(t for _, t, _ in mine)
    assert killed_ns - last_ns < 1.6e9, (killed_ns - last_ns) / 1e9
