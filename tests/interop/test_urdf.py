"""The URDFs pass urdfdom's check_urdf (Debian liburdfdom-tools) and have the expected tree."""

from conftest import ROOT, run


def test_polar_cell_urdf_passes_check_urdf():
    out = run(["check_urdf", ROOT / "urdf" / "polar_cell.urdf"]).stdout
    assert "Successfully Parsed XML" in out
    assert "root Link: base_link has 2 child(ren)" in out
    for link in ("bed_link", "gantry_link", "carriage_link", "screw_link", "nozzle_link"):
        assert link in out
