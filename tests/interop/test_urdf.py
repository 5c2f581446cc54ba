"""The URDFs pass urdfdom's check_urdf (Debian liburdfdom-tools) and have the expected tree."""

from conftest import ROOT, run


def test_polar_cell_urdf_passes_check_urdf():
    out = run(["check_urdf", ROOT / "urdf" / "polar_cell.urdf"]).stdout
    assert "Successfully Parsed XML" in out
    assert "root Link: base_link has 2 child(ren)" in out
    for link in ("bed_link", "gantry_link", "carriage_link", "screw_link", "nozzle_link"):
        assert link in out


def test_bench_rig_urdf_is_the_cells_tree_with_the_28byj48_limits():
    """Seed 001's bench rig: the cell's joints, every velocity limit 500 steps/s (the motor's
    self-start rate) at the steps of launch-scripts/params/bench_rig.yaml."""
    import math
    import xml.etree.ElementTree as ET

    out = run(["check_urdf", ROOT / "urdf" / "bench_rig.urdf"]).stdout
    assert "Successfully Parsed XML" in out
    assert "root Link: base_link has 2 child(ren)" in out
    steps_per_unit = {"bed_theta": 2048 / (2 * math.pi), "arm_r": 2048 / 0.008, "z": 2048 / 0.008}
    joints = {j.get("name"): j for j in ET.parse(ROOT / "urdf" / "bench_rig.urdf").iter("joint")}
    for name, steps in steps_per_unit.items():
        velocity = float(joints[name].find("limit").get("velocity"))
        assert math.isclose(velocity * steps, 500.0, rel_tol=1e-12), name
    params = (ROOT / "launch-scripts" / "params" / "bench_rig.yaml").read_text()
    assert "steps_per_unit: [325.94932345220167, 256000.0, 256000.0]" in params
