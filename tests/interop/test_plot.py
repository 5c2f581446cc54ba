"""`polar-cell plot` renders r, θ, tool speed and rpm panels from a recorded print."""

from PIL import Image

from conftest import run

SERIES_COLOURS = [(0, 0, 255), (255, 0, 0), (0, 255, 0), (255, 0, 255)]  # top to bottom


def test_plot_draws_four_panels_with_their_series(polar_cell, printed_bags, tmp_path):
    bag, _ = printed_bags["polartest.gcode"]
    out = tmp_path / "print.png"
    run([polar_cell, "plot", bag, "--out", out])
    image = Image.open(out).convert("RGB")
    assert image.size == (1400, 1200)
    for panel, colour in enumerate(SERIES_COLOURS):
        box = (0, panel * 300, 1400, (panel + 1) * 300)
        pixels = image.crop(box).getdata()
        drawn = sum(1 for p in pixels if p == colour)
        assert drawn > 500, f"panel {panel}: {drawn} pixels of its series"


def test_plot_of_a_bag_without_trajectory_is_an_error(polar_cell, tmp_path):
    import subprocess

    from golden import MOVES_BAG

    proc = subprocess.run([str(polar_cell), "plot", str(MOVES_BAG), "--out", str(tmp_path / "x.png")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "no /polar/trajectory to plot" in proc.stderr
