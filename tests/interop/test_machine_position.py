"""A machine that stays where a print left it: one MCU emulator, three `polar-cell print`
runs on its pseudo-terminal, as a machine builder with a Pico on /dev/ttyACM0 would run them.

1. a print cancelled with Ctrl-C stops mid-part;
2. a print told to start at home (`--start-joints 0,0,0`) is refused before its first step,
   naming where the MCU stands (the first host left it latched in HOST_SILENT: the new
   session clears that, and does not take the states that waited in the line for a fault
   of its own);
3. the same print without the option asks the MCU where it stands, runs from exactly there
   (its bag's first executed joint state) to where the file ends;
4. `polar-cell mcu-position` tells the parameters that start a plan there, and
   `launch-scripts/cell.sh` (one process per node) uses them: its print starts at the third
   one's end.
"""

import math
import os
import re
import signal
import subprocess
import time

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import BIN_DIR, ROOT, binary

DOMAIN = 71


def joint_states(bag):
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [m.decoded_message for m in reader.iter_decoded_messages(topics=["/joint_states"])]


def test_a_print_starts_where_the_mcu_stands_and_refuses_to_start_elsewhere(tmp_path):
    circle = tmp_path / "circle.gcode"
    lines = ["G1 X50 Y0 F3000"] + [
        f"G1 X{50 * math.cos(a):.3f} Y{50 * math.sin(a):.3f} F3000"
        for a in (i * 2 * math.pi / 200 for i in range(1, 601))
    ]
    circle.write_text("\n".join(lines) + "\n")
    short = tmp_path / "short.gcode"
    short.write_text("G1 X50 Y0 F3000\nG1 X0 Y50\nG1 X-30 Y-30\n")
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN))
    emulator = subprocess.Popen([str(binary("mcu_emulator")), "--speed", "2"],
                                stdout=subprocess.PIPE, text=True)
    try:
        pty = emulator.stdout.readline().split()[1]
        assert pty.startswith("/dev/pts/"), pty

        def print_on_mcu(gcode, bag, *extra):
            return [str(binary("polar-cell")), "print", str(gcode), "--device", pty, "--speed", "2",
                    "--no-progress", "--bag", str(tmp_path / bag), *extra]

        # 1. Cancelled mid-circle.
        first = subprocess.Popen(print_on_mcu(circle, "one.mcap"), env=env,
                                 stderr=subprocess.PIPE, text=True)
        time.sleep(6)
        first.send_signal(signal.SIGINT)
        _, err = first.communicate(timeout=60)
        assert first.returncode == 1, err
        assert "cancelled: stopped on the path" in err, err
        start = list(joint_states(tmp_path / "one.mcap")[-1].position[:3])
        assert abs(start[1] - 0.05) < 2e-5 and start[0] > 0.5, start  # mid-circle

        # 2. Told to start at home: refused before anything moves.
        second = subprocess.run(print_on_mcu(short, "two.mcap", "--start-joints", "0,0,0"), env=env,
                                capture_output=True, text=True, timeout=60)
        assert second.returncode == 1, second.stderr
        assert "the MCU stands at steps" in second.stderr, second.stderr
        assert f"initial_joints [{start[0]!r}, {start[1]!r}, {start[2]!r}]" in second.stderr, second.stderr
        assert "HostSilent" not in second.stderr, second.stderr
        moved = [s.position[:3] for s in joint_states(tmp_path / "two.mcap")]
        assert moved, "the refused print recorded no joint states"
        assert all(list(p) == start for p in moved), "the MCU moved"

        # 3. Asked where it stands: from there to the file's end.
        third = subprocess.run(print_on_mcu(short, "three.mcap"),
                               env=env, capture_output=True, text=True, timeout=120)
        assert third.returncode == 0, third.stderr
        assert re.search(r"MCU on \S+ stands at steps \[-?\d+, \d+, \d+\]", third.stderr), third.stderr
        assert "The print starts where the MCU stands." in third.stderr, third.stderr
        assert "executed" in third.stderr and ", 0 underruns" in third.stderr, third.stderr
        states = joint_states(tmp_path / "three.mcap")
        assert list(states[0].position[:3]) == start
        bed, arm, z = states[-1].position[:3]
        # (-30, -30) mm: 5π/4 on the turn nearest the start, r = 42.43 mm within a step.
        assert abs((bed - 5 * math.pi / 4) / (2 * math.pi) - round((bed - 5 * math.pi / 4) / (2 * math.pi))) < 1e-4
        assert abs(arm - math.hypot(0.03, 0.03)) < 1.3e-5 and z == 0.0

        # 4. Node by node: asked by `mcu-position`, which cell.sh runs before its nodes.
        end = [bed, arm, z]
        asked = subprocess.run([str(binary("polar-cell")), "mcu-position", "--device", pty],
                               env=env, capture_output=True, text=True, timeout=60)
        assert asked.returncode == 0, asked.stderr
        lines = asked.stdout.splitlines()
        assert lines[0] == f"initial_joints:=[{bed!r},{arm!r},{z!r}]", asked.stdout
        x_mm, y_mm, z_mm = (float(v) for v in lines[1].removeprefix("start_position_mm:=[")
                            .removesuffix("]").split(","))
        assert math.hypot(x_mm + 30, y_mm + 30) < 0.02 and z_mm == 0.0, lines[1]
        up = tmp_path / "up.gcode"
        up.write_text("G1 X0 Y40 F3000\n")
        launched = subprocess.run(
            [str(ROOT / "launch-scripts" / "cell.sh"), str(up), str(tmp_path / "four.mcap")],
            env=dict(env, POLAR_CELL_BIN_DIR=str(BIN_DIR), POLAR_CELL_DEVICE=pty,
                     POLAR_CELL_SPEED="2"),
            capture_output=True, text=True, timeout=120)
        assert launched.returncode == 0, launched.stderr
        states = joint_states(tmp_path / "four.mcap")
        assert list(states[0].position[:3]) == end
        bed, arm, z = states[-1].position[:3]
        # (0, 40) mm: π/2 on the turn nearest 5π/4, r = 40 mm within a step.
        assert abs((bed - math.pi / 2) / (2 * math.pi) - round((bed - math.pi / 2) / (2 * math.pi))) < 1e-4
        assert abs(bed - end[0]) < math.pi and abs(arm - 0.04) < 1.3e-5 and z == 0.0
    finally:
        emulator.kill()
        emulator.wait()
