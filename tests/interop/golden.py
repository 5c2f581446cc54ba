"""Golden replays: a recorded /gcode/moves bag is played into a planner node (plan time 0 =
stamp 0, acknowledgements off) and its /polar/trajectory is recorded; both are played into a
screw driver and its /screw/command is recorded. For the machining head, `polar-cell mechanism
cl` post-processes a generated bowl into a bag of /mechanism/tool_pose and the joint states
that answer them; the poses are played into the mechanism_kin node and its
/mechanism/joint_states recorded.

    python tests/interop/golden.py   # regenerate tests/golden/ (run in a network namespace)
"""

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from conftest import BIN_DIR, FIXTURES, run  # noqa: E402

GOLDEN = HERE.parent / "golden"
MOVES_BAG = GOLDEN / "polartest_moves.mcap"
TRAJECTORY_BAG = GOLDEN / "polartest_trajectory.mcap"
SCREW_BAG = GOLDEN / "polartest_screw.mcap"
BOWL_CL_BAG = GOLDEN / "bowl_cl.mcap"


def hemisphere_cl(path):
    """An independent CL generator: a concave bowl of radius 50 mm, tool along the normal."""
    lines = ["Px,Py,Pz,Vx,Vy,Vz,flag"]
    centre_z = 300.0
    for x in np.arange(-12.0, 12.01, 6.0):
        ys = np.linspace(-12.0, 12.0, 7)
        for k, y in enumerate(ys):
            z = centre_z - math.sqrt(50.0**2 - x * x - y * y)
            v = np.array([x, y, z - centre_z]) / 50.0
            flag = "s" if k == 0 else ("e" if k == len(ys) - 1 else "w")
            lines.append(",".join(repr(float(c)) for c in (x, y, z, *v)) + f",{flag}")
    path.write_text("\n".join(lines) + "\n")
    return len(lines) - 1



def post_process_bowl(cl: Path, out: Path):
    """The CLI's bag of the bowl: tool poses and the joint states that answer them."""
    hemisphere_cl(cl)
    run([BIN_DIR / "polar-cell", "mechanism", "cl", cl, "--bag", out])


def replay_mechanism(cl_bag: Path, out: Path):
    """Play the tool poses of `cl_bag` into a mechanism_kin node; record its joint states."""
    node = [BIN_DIR / "mechanism_kin", "--ros-args", "-p", "publish_home:=false"]
    from test_mechanism import JointState
    replay(node, [(cl_bag, "/mechanism/tool_pose")], out, "/mechanism/joint_states", JointState, 1.0)


def record_moves(out: Path):
    """The input: /gcode/moves of polartest.gcode, as `polar-cell print` records it."""
    run([BIN_DIR / "polar-cell", "print", FIXTURES / "polartest.gcode", "--bag", out, "--no-progress", "--dry-run",
         "--ros-args", "-p", "bag_recorder:topics:=[/gcode/moves]"])


def replay(node: list, plays: list, out: Path, topic: str, kind, settle_s: float):
    """Start `node` (a command whose node is `node[0]`'s name) and a recorder of `topic` into
    `out`, play each `(bag, topic)` of `plays` as fast as subscribers take it once the node
    itself subscribes (a reader left over from an earlier test must not start the play before
    the node has matched), wait until the node's output
    (`kind` messages, watched by a Cyclone DDS reader beside the recorder) has been quiet for
    `settle_s`, then stop both with SIGINT (which finishes the bag). A fixed wait instead
    could stop a node still computing on a loaded machine."""
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from test_dds import ros_qos

    participant = DomainParticipant(0)
    watcher = DataReader(participant, Topic(participant, "rt" + topic, kind), qos=ros_qos(100_000))
    processes = [
        subprocess.Popen([str(a) for a in node], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True),
        subprocess.Popen(
            [str(BIN_DIR / "bag_recorder"), "--ros-args", "-p", f"output:={out}",
             "-p", f"topics:=[{topic}]", "-p", "acknowledge_moves:=false"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        ),
    ]
    try:
        time.sleep(1.0)  # both subscribed before anything is played
        for bag, played in plays:
            run([BIN_DIR / "polar-cell", "bag", "play", bag, "--fast", "--wait-subscribers-s", "15",
                 "--wait-for-node", "/" + Path(node[0]).name, "--topics", played])
        received, last = 0, time.monotonic()
        deadline = last + 120
        while time.monotonic() < deadline:
            taken = len(watcher.take(N=10_000))
            now = time.monotonic()
            if taken:
                received, last = received + taken, now
            elif received and now - last >= settle_s:
                break
            time.sleep(0.05)
    finally:
        for proc in processes:
            proc.send_signal(signal.SIGINT)
        errors = [proc.communicate(timeout=30)[1] for proc in processes]
    if processes[1].returncode != 0:
        raise RuntimeError(f"bag_recorder failed: {errors[1]}")


def replay_plan(moves_bag: Path, out: Path):
    """Play `moves_bag` into a planner node and record its /polar/trajectory to `out`; the
    planner flushes its lookahead when input stops."""
    # The golden plan pins the planner without the screw's limits (which slow polartest's
    # primes); those are tested in Rust (polar_planner/tests/plan.rs) and by test_screw.py.
    # Without flow control a pause in input is taken for the end of the file: 1 s, not the
    # default 50 ms, so that a lost datagram's repair is not planned as a stop mid-file.
    planner = [BIN_DIR / "polar_planner", "--ros-args", "-p", "plan_epoch_ns:=0",
               "-p", "acknowledge_moves:=false", "-p", "publish_steps:=false",
               "-p", "joint_state_period_s:=0.0", "-p", "screw_max_rpm:=0.0",
               "-p", "idle_flush_s:=1.0"]
    from test_outside_reader import JointTrajectory
    replay(planner, [(moves_bag, "/gcode/moves")], out, "/polar/trajectory", JointTrajectory, 2.5)


def replay_screw(moves_bag: Path, trajectory_bag: Path, out: Path):
    """Play recorded moves and trajectories into a screw driver; record /screw/command (it
    computes commands when input stops)."""
    # Breakpoints as the instant-flow law gives them (flow compensation, tested in Rust and by
    # test_screw.py, would make this bag a held 2 ms grid).
    screw = [BIN_DIR / "screw_driver", "--ros-args", "-p", "acknowledge_moves:=false",
             "-p", "idle_flush_s:=1.0", "-p", "flow_compensation:=false"]
    plays = [(moves_bag, "/gcode/moves"), (trajectory_bag, "/polar/trajectory")]
    from test_outside_reader import ScrewCommand
    replay(screw, plays, out, "/screw/command", ScrewCommand, 2.5)


if __name__ == "__main__":
    GOLDEN.mkdir(exist_ok=True)
    record_moves(MOVES_BAG)
    replay_plan(MOVES_BAG, TRAJECTORY_BAG)
    replay_screw(MOVES_BAG, TRAJECTORY_BAG, SCREW_BAG)
    post_process_bowl(GOLDEN / "bowl.cl", BOWL_CL_BAG)
    (GOLDEN / "bowl.cl").unlink()
    print(f"wrote {MOVES_BAG}, {TRAJECTORY_BAG}, {SCREW_BAG} and {BOWL_CL_BAG}")
