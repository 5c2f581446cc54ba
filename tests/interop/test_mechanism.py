"""The hybrid machining head against independent truth.

- urdfdom's check_urdf (Debian liburdfdom-tools) parses urdf/hybrid_pkm.urdf as the tree we say;
- Pinocchio (PyPI `pin`) computes forward kinematics of that tree from the joint values our CLI
  and node publish: the loops close (chains 2 and 3 end on the platform's sphere points) and
  the tool tip lands on the target;
- the leg lengths are recomputed here from the spec's formulas (Rodrigues, X_u, Y_u);
- the node talks to Cyclone DDS: PoseStamped in, JointState and the URDF (transient local) out;
- CL bags are read by mcap-ros2-support and rosbags.
"""

import json
import math
import subprocess
import time
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import pytest

import cyclonedds.idl.annotations as annotate
import cyclonedds.idl.types as t
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from conftest import ROOT, assert_readable_by_independent_readers, binary, run
from golden import hemisphere_cl
from test_dds import DiagnosticArray, Header, Time, ros_qos, valid

URDF = ROOT / "urdf" / "hybrid_pkm.urdf"
R_IN, R_OUT, TOOL = 330.0, 316.0, 100.0
CHAIN_DEG = (270.0, 30.0, 150.0)


def spec_legs(z, theta1, theta2):
    """SPEC §5 written out independently: Rodrigues about (cos θ1, sin θ1, 0), eq. 3.11/3.13."""
    c1, s1, c2, s2 = math.cos(theta1), math.sin(theta1), math.cos(theta2), math.sin(theta2)
    w = np.array([c1, s1, 0.0])
    x_u = R_OUT * (c1 * s1 - c1 * s1 * c2)
    y_u = 0.5 * R_OUT * (1 - c2) * math.cos(2 * theta1)
    legs = []
    for deg in CHAIN_DEG:
        u = np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg)), 0.0])
        p = R_OUT * u
        rotated = (p @ w) * w + c2 * (p - (p @ w) * w) + s2 * np.cross(w, p)
        c = rotated + np.array([x_u, y_u, z])
        legs.append(float(np.linalg.norm(c - R_IN * u)))
    return legs


def pinocchio_frames(joints):
    model = pin.buildModelFromUrdf(str(URDF))
    data = model.createData()
    q = pin.neutral(model)
    for name, value in joints.items():
        jid = model.getJointId(name)
        assert jid < model.njoints, name
        q[model.joints[jid].idx_q] = value
    pin.forwardKinematics(model, data, q)
    pin.updateFramePlacements(model, data)
    return lambda frame: data.oMf[model.getFrameId(frame)]


def assert_closed_and_on_target(joints, tip_mm, axis):
    frame = pinocchio_frames(joints)
    platform = frame("platform")
    for i, deg in enumerate(CHAIN_DEG):
        a = math.radians(deg)
        sphere = platform.act(np.array([math.cos(a), math.sin(a), 0.0]) * R_OUT * 1e-3)
        ball = frame(f"chain{i + 1}_ball")
        assert np.linalg.norm(ball.translation - sphere) < 1e-9, (i, ball.translation, sphere)
        # the ball's outer race turns with the platform
        assert np.abs(ball.rotation - platform.rotation).max() < 1e-12
    tip = frame("tool_tip").translation - frame("table").translation
    assert np.linalg.norm(tip * 1e3 - np.array(tip_mm)) < 1e-9
    assert np.abs(platform.rotation[:, 2] - np.array(axis)).max() < 1e-12


def test_hybrid_urdf_passes_check_urdf():
    out = run(["check_urdf", URDF]).stdout
    assert "Successfully Parsed XML" in out
    assert "root Link: base_link has 4 child(ren)" in out
    for link in ("chain1_ball", "chain2_ball", "chain3_ball", "platform", "tool_tip", "table"):
        assert link in out


@pytest.mark.parametrize("z,t1,t2", [(393, 30, 10), (300, 120, -15), (450, 75, 20), (393, 45, 0)])
def test_cli_ik_matches_spec_formulas_and_pinocchio_closes_the_loops(polar_cell, z, t1, t2):
    out = json.loads(run([polar_cell, "mechanism", "ik", "--z", z, "--theta1-deg", t1,
                          "--theta2-deg", t2, "--json"]).stdout)
    expected = spec_legs(z, math.radians(t1), math.radians(t2))
    assert np.abs(np.array(out["leg_lengths_mm"]) - expected).max() < 1e-9
    assert abs(out["pose"]["z_mm"] - z) < 1e-9
    axis = [math.sin(math.radians(t1)) * math.sin(math.radians(t2)),
            -math.cos(math.radians(t1)) * math.sin(math.radians(t2)),
            math.cos(math.radians(t2))]
    tip = [0.0, 0.0, z - TOOL * axis[2]]
    assert_closed_and_on_target(out["joints"], tip, axis)
    assert out["checks"]["loop_closure_residual_m"] < 1e-9
    # FK of the legs returns the pose
    fk = json.loads(run([polar_cell, "mechanism", "fk", "--legs-mm",
                         ",".join(repr(x) for x in out["leg_lengths_mm"]), "--json"]).stdout)
    assert abs(fk["pose"]["z_mm"] - z) < 1e-9
    if t2:
        assert abs(fk["pose"]["theta1_deg"] - t1) < 1e-7 and abs(fk["pose"]["theta2_deg"] - t2) < 1e-7


def test_unreachable_pose_is_an_error(polar_cell):
    proc = subprocess.run([str(polar_cell), "mechanism", "ik", "--z", "393", "--theta1-deg", "30",
                           "--theta2-deg", "35"], capture_output=True, text=True)
    assert proc.returncode != 0 and "tilt" in proc.stderr, proc.stderr
    proc = subprocess.run([str(polar_cell), "mechanism", "fk", "--legs-mm", "100,400,400"],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and "chain 1" in proc.stderr, proc.stderr


def test_cl_bag_is_readable_and_every_state_puts_the_tool_on_its_point(polar_cell, tmp_path):
    cl = tmp_path / "bowl.cl"
    points = hemisphere_cl(cl)
    bag = tmp_path / "bowl.mcap"
    out = json.loads(run([polar_cell, "mechanism", "cl", cl, "--bag", bag, "--json"]).stdout)
    commands = out["commands"]
    assert out["paths"] == 5 and len(commands) == points + 2 * 5
    decoded = assert_readable_by_independent_readers(bag)
    states = decoded["/mechanism/joint_states"]
    assert len(states) == len(commands) == len(decoded["/mechanism/tool_pose"])
    assert "hybrid_pkm" in decoded["/robot_description"][0].data
    for state, command in zip(states, commands):
        joints = dict(zip(state.name, state.position))
        assert_closed_and_on_target(joints, command["tip_mm"], command["axis"])
        if command["kind"] != "work":
            # approach/retract: 10 mm up the tool axis from the surface point
            assert command["kind"] in ("approach", "retract")


def test_malformed_cl_names_file_and_line(polar_cell, tmp_path):
    cl = tmp_path / "bad.cl"
    cl.write_text("Px,Py,Pz,Vx,Vy,Vz,flag\n0,0,250,0,0,-1,s\n0,0,250,0,0.5,-1,e\n")
    proc = subprocess.run([str(polar_cell), "mechanism", "cl", str(cl)], capture_output=True, text=True)
    assert proc.returncode != 0
    assert f"{cl}:3: tool vector" in proc.stderr, proc.stderr


def test_calibration_cli_round_trip(polar_cell, tmp_path):
    meas, cal = tmp_path / "m.csv", tmp_path / "cal.json"
    run([polar_cell, "mechanism", "simulate", "--seed", "3", "--out", meas])
    summary = json.loads(run([polar_cell, "mechanism", "calibrate", "--measurements", meas,
                              "--out", cal, "--json"]).stdout)
    assert summary["method"] == "geometric" and summary["measurements"] == 20
    assert summary["rms_tip_residual_um"] < 3.0
    out = json.loads(run([polar_cell, "mechanism", "ik", "--tip-mm", "0,0,250", "--json",
                          "--calibration", cal]).stdout)
    nominal, corrected = out["leg_lengths_mm"], out["calibrated"]["leg_lengths_mm"]
    # the machine is off by tenths of a millimetre: the correction is that large, not zero
    assert 0.01 < max(abs(a - b) for a, b in zip(nominal, corrected)) < 5.0
    bad = tmp_path / "bad.csv"
    bad.write_text(meas.read_text().splitlines()[0] + "\n1,2,3,4\n")
    proc = subprocess.run([str(polar_cell), "mechanism", "calibrate", "--measurements", str(bad),
                           "--out", str(tmp_path / "x.json")], capture_output=True, text=True)
    assert proc.returncode != 0 and f"{bad}:2: expected 9 fields" in proc.stderr, proc.stderr


# ---------------------------------------------------------------- the node over Cyclone DDS


@dataclass
@annotate.final
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float
    y: float
    z: float


@dataclass
@annotate.final
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float
    y: float
    z: float
    w: float


@dataclass
@annotate.final
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
@annotate.final
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header
    pose: Pose


@dataclass
@annotate.final
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header
    name: t.sequence[str]
    position: t.sequence[float]
    velocity: t.sequence[float]
    effort: t.sequence[float]


@dataclass
@annotate.final
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str


@dataclass
@annotate.final
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float
    y: float
    z: float


@dataclass
@annotate.final
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion


@dataclass
@annotate.final
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
@annotate.final
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped]


def homogeneous(transform):
    """The 4×4 matrix of a geometry_msgs Transform (unit quaternion x, y, z, w)."""
    q, v = transform.rotation, transform.translation
    x, y, z, w = q.x, q.y, q.z, q.w
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = [v.x, v.y, v.z]
    return m


def in_root(transforms, frame, root):
    """`frame`'s pose in `root`, composed parent by parent from tf transforms."""
    by_child = {tr.child_frame_id: tr for tr in transforms}
    pose = np.eye(4)
    while frame != root:
        tr = by_child[frame]
        pose = homogeneous(tr.transform) @ pose
        frame = tr.header.frame_id
    return pose


def test_node_solves_cyclone_poses_and_latches_the_urdf():
    participant = DomainParticipant(0)
    node = subprocess.Popen([str(binary("mechanism_kin")), "--ros-args", "-p",
                             "frame_prefix:=head/"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        tf = DataReader(participant, Topic(participant, "rt/tf", TFMessage), qos=ros_qos(1000))
        poses = DataWriter(participant, Topic(participant, "rt/mechanism/tool_pose", PoseStamped),
                           qos=ros_qos(100))
        states = DataReader(participant, Topic(participant, "rt/mechanism/joint_states", JointState),
                            qos=ros_qos(100))
        diagnostics = DataReader(participant, Topic(participant, "rt/diagnostics", DiagnosticArray),
                                 qos=ros_qos(100))
        half = math.radians(6.0)  # 12° tilt about x
        axis = [0.0, -math.sin(2 * half), math.cos(2 * half)]
        targets = [
            ((0.005, -0.01, 0.24), Quaternion(math.sin(half), 0.0, 0.0, math.cos(half))),
            ((0.0, 0.0, 0.9), Quaternion(0.0, 0.0, 0.0, 1.0)),  # far above the work range
        ]
        got, diags = [], []
        deadline = time.time() + 30
        sent = 0
        while time.time() < deadline and not (len(got) >= 1 and any(
                s.level == 2 for d in diags for s in d.status)):
            if sent < 20:
                # publish until the node has matched (a volatile writer's first samples can
                # precede matching); stamps tell the answers apart
                for k, (p, q) in enumerate(targets):
                    poses.write(PoseStamped(Header(Time(100 + k, 0), "table"),
                                            Pose(Point(*p), q)))
                sent += 1
            time.sleep(0.2)
            got += [s for s in valid(states.take(N=100), JointState) if s.header.stamp.sec == 100]
            diags += valid(diagnostics.take(N=100), DiagnosticArray)
        assert got, "no joint states for the reachable pose"
        joints = dict(zip(got[0].name, got[0].position))
        assert len(joints) == 17
        assert_closed_and_on_target(joints, [5.0, -10.0, 240.0], axis)
        statuses = [s for d in diags for s in d.status if s.name == "/mechanism_kin"]
        ok = [s for s in statuses if s.level == 0]
        assert ok and float({kv.key: kv.value for kv in ok[0].values}["loop_closure_residual_m"]) < 1e-9
        assert any(s.level == 2 and "unreachable" in s.message for s in statuses), statuses
        # A reader that joins late still gets the URDF (transient local).
        description = DataReader(participant, Topic(participant, "rt/robot_description", String),
                                 qos=ros_qos(1, transient_local=True))
        urdf = []
        deadline = time.time() + 15
        while time.time() < deadline and not urdf:
            time.sleep(0.2)
            urdf = valid(description.take(N=1), String)
        assert urdf and urdf[0].data == URDF.read_text()
        # The head's transforms, as RViz would compose them: the fixed joints latched on
        # /tf_static (read late), the held pose repeated on /tf at 10 Hz, stamped now; both
        # put the tool tip on its target in the table frame, under the frame prefix.
        latched = DataReader(participant, Topic(participant, "rt/tf_static", TFMessage),
                             qos=ros_qos(1, transient_local=True))
        fixed = []
        deadline = time.time() + 15
        while time.time() < deadline and not fixed:
            time.sleep(0.2)
            fixed = valid(latched.take(N=1), TFMessage)
        assert fixed and {tr.child_frame_id for tr in fixed[0].transforms} == {
            "head/platform", "head/tool_tip"}
        tf.take(N=1000)
        time.sleep(1.0)
        repeats = valid(tf.take(N=1000), TFMessage)
        assert 5 <= len(repeats) <= 15, len(repeats)
        stamps = [m.transforms[0].header.stamp for m in repeats]
        now = time.time()
        assert all(abs(s.sec + s.nanosec * 1e-9 - now) < 2.0 for s in stamps), (stamps, now)
        last = repeats[-1].transforms + fixed[0].transforms
        assert len(repeats[-1].transforms) == 17
        tip = np.linalg.inv(in_root(last, "head/table", "head/base_link")) @ in_root(
            last, "head/tool_tip", "head/base_link")
        assert np.linalg.norm(tip[:3, 3] * 1e3 - np.array([5.0, -10.0, 240.0])) < 1e-6
        assert np.abs(tip[:3, 2] - np.array(axis)).max() < 1e-9
    finally:
        node.terminate()
        node.wait(timeout=10)
