"""The recorded /polar/trajectory, checked independently from the bag (numpy-free Python):
path deviation from every commanded line, joint limits from the URDF, continuous θ."""

import math
import xml.etree.ElementTree as ET

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import ROOT

TOLERANCE_M = 5e-6
ACCELERATION_LIMITS = {"bed_theta": 40.0, "arm_r": 3.0, "z": 0.5}  # planner defaults


def urdf_limits():
    root = ET.parse(ROOT / "urdf" / "polar_cell.urdf").getroot()
    limits = {}
    for joint in root.iter("joint"):
        limit = joint.find("limit")
        if limit is not None:
            limits[joint.get("name")] = (
                float(limit.get("lower", "-inf")) if joint.get("type") == "prismatic" else -math.inf,
                float(limit.get("upper", "inf")) if joint.get("type") == "prismatic" else math.inf,
                float(limit.get("velocity")),
            )
    return limits


def decoded(bag, topic):
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [m for _, _, _, m in reader.iter_decoded_messages(topics=[topic])]


def distance_to_segment(p, a, b):
    ab = [b[i] - a[i] for i in range(3)]
    ap = [p[i] - a[i] for i in range(3)]
    den = sum(x * x for x in ab)
    t = 0.0 if den == 0 else max(0.0, min(1.0, sum(ap[i] * ab[i] for i in range(3)) / den))
    return math.dist(p, [a[i] + ab[i] * t for i in range(3)])


def cartesian(q):
    theta, r, z = q
    return [r * math.cos(theta), r * math.sin(theta), z]


@pytest.mark.parametrize("name", ["finger.gcode", "polartest.gcode"])
def test_recorded_trajectory_follows_commanded_lines_within_limits(printed_bags, name):
    bag, _ = printed_bags[name]
    moves = decoded(bag, "/gcode/moves")
    trajectories = decoded(bag, "/polar/trajectory")
    assert len(trajectories) == len(moves)
    limits = urdf_limits()
    start = [0.0, 0.0, 0.0]
    worst = 0.0
    previous = None  # (t, positions, velocities)
    base_ns = trajectories[0].header.stamp.sec * 10**9 + trajectories[0].header.stamp.nanosec
    for move, traj in zip(moves, trajectories):
        assert traj.joint_names == ["bed_theta", "arm_r", "z"]
        end = [move.x_m, move.y_m, move.z_m]
        # Integer nanoseconds: a float of epoch seconds resolves only ~0.2 µs.
        t0 = traj.header.stamp.sec * 10**9 + traj.header.stamp.nanosec
        points = [
            ((t0 - base_ns + p.time_from_start.sec * 10**9 + p.time_from_start.nanosec) * 1e-9,
             p.positions, p.velocities, p.accelerations)
            for p in traj.points
        ]
        for (ta, qa, _, _), (tb, qb, _, _) in zip(points, points[1:]):
            for k in range(21):
                f = k / 20
                q = [qa[j] + (qb[j] - qa[j]) * f for j in range(3)]
                worst = max(worst, distance_to_segment(cartesian(q), start, end))
        for t, q, qd, qdd in points:
            for j, joint in enumerate(("bed_theta", "arm_r", "z")):
                lower, upper, velocity = limits[joint]
                assert lower - 1e-12 <= q[j] <= upper + 1e-12, (joint, q[j])
                assert abs(qd[j]) <= velocity * (1 + 1e-9), (joint, qd[j], move.source_line)
                assert abs(qdd[j]) <= ACCELERATION_LIMITS[joint] * (1 + 1e-9), (joint, qdd[j])
            if previous is not None:
                dt = t - previous[0]
                assert dt >= -2e-9, "time runs forwards (stamps round to 1 ns)"
                if dt > 1e-6:
                    # Continuity: no joint moves faster on average than its velocity limit.
                    for j, joint in enumerate(("bed_theta", "arm_r", "z")):
                        assert abs(q[j] - previous[1][j]) <= limits[joint][2] * dt * (1 + 1e-6) + 1e-12
                else:
                    assert abs(q[0] - previous[1][0]) < 1e-9, "θ continuous: never re-based"
            previous = (t, q, qd)
        start = end
    assert worst <= TOLERANCE_M, worst


def test_joint_states_and_steps_are_recorded(printed_bags):
    bag, _ = printed_bags["polartest.gcode"]
    # The screw driver publishes the screw joint on the same topic (tests/interop/test_screw.py).
    states = [s for s in decoded(bag, "/polar/planned_joint_states") if s.name != ["screw"]]
    steps = decoded(bag, "/polar/steps")
    trajectories = decoded(bag, "/polar/trajectory")
    last = trajectories[-1]
    plan_end = (last.header.stamp.sec + last.header.stamp.nanosec * 1e-9
                + last.points[-1].time_from_start.sec + last.points[-1].time_from_start.nanosec * 1e-9)
    first = trajectories[0].header.stamp
    duration = plan_end - (first.sec + first.nanosec * 1e-9)
    # One sample every 20 ms of plan time.
    assert abs(len(states) - duration / 0.02) <= 2
    assert all(s.name == ["bed_theta", "arm_r", "z"] for s in states)
    assert abs(sum(s.duration_s for s in steps) - duration) < 1e-6 * duration
    for s in steps:
        n = s.accelerate_steps + s.cruise_steps + s.decelerate_steps
        assert n == s.step_counts[s.dominant_axis]
        assert all(c <= n for c in s.step_counts)
