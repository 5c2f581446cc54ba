"""Material per unit length, computed from the recorded bag alone (polar_speed, defaults):
each path move is fed its G-code ΔE within 1 %."""

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

E_PER_REV_M = 0.002  # screw_driver's default e_per_rev_m


def decoded(bag, topic):
    with open(bag, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [m for _, _, _, m in reader.iter_decoded_messages(topics=[topic])]


def ns(stamp):
    return stamp.sec * 10**9 + stamp.nanosec


@pytest.mark.parametrize("name", ["finger.gcode", "polartest.gcode"])
def test_screw_commands_feed_each_move_its_material(printed_bags, name):
    bag, _ = printed_bags[name]
    moves = decoded(bag, "/gcode/moves")
    trajectories = decoded(bag, "/polar/trajectory")
    commands = decoded(bag, "/screw/command")
    assert commands and all(c.model == "polar_speed" for c in commands)
    base = ns(commands[0].header.stamp)
    # rpm is linear between commands (first-order hold).
    points = [((ns(c.header.stamp) - base) * 1e-9, c.rpm, c.pin_open) for c in commands]
    assert all(b[0] >= a[0] for a, b in zip(points, points[1:])), "commands in time order"
    assert all(rpm == 0.0 for _, rpm, pin in points if not pin), "no rpm with the pin closed"

    def fed(a, b):
        total = 0.0
        for (t0, r0, _), (t1, r1, _) in zip(points, points[1:]):
            lo, hi = max(t0, a), min(t1, b)
            if t1 > t0 and hi > lo:
                at = lambda t: r0 + (r1 - r0) * (t - t0) / (t1 - t0)
                total += 0.5 * (at(lo) + at(hi)) * (hi - lo)
        return total / 60.0 * E_PER_REV_M

    start = [0.0, 0.0, 0.0]
    checked, worst, worst_line = 0, 0.0, None
    for move, traj in zip(moves, trajectories):
        end = [move.x_m, move.y_m, move.z_m]
        length = sum((e - s) ** 2 for e, s in zip(end, start)) ** 0.5
        t0 = (ns(traj.header.stamp) - base) * 1e-9
        times = [t0 + p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in traj.points]
        if move.extrude and length > 0 and move.delta_e_m > 1e-7:
            error = abs(fed(times[0], times[-1]) - move.delta_e_m) / move.delta_e_m
            if error > worst:
                worst, worst_line = error, move.source_line
            checked += 1
        if move.kind in (0, 1, 2, 3, 5):
            start = end
    assert checked > 1500
    assert worst < 0.01, (worst, worst_line)
