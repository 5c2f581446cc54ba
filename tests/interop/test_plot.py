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


def test_time_axis_label_sits_clear_below_the_tick_labels(polar_cell, printed_bags, tmp_path):
    """Below each panel's x axis the dark rows form two bands, the tick labels and then
    "time (s)", with blank rows between them (they used to overlap)."""
    bag, _ = printed_bags["polartest.gcode"]
    out = tmp_path / "print.png"
    run([polar_cell, "plot", bag, "--out", out])
    image = Image.open(out).convert("L")
    width = image.size[0]
    for panel in range(4):
        top = panel * 300
        dark_rows = [
            y for y in range(top, top + 300)
            if sum(1 for x in range(width) if image.getpixel((x, y)) < 100) > 0
        ]
        axis = max(y for y in range(top, top + 300)
                   if sum(1 for x in range(width) if image.getpixel((x, y)) < 100) > width // 2)
        below = [y for y in dark_rows if y > axis + 6]  # past the tick marks
        bands = [[below[0]]]
        for y in below[1:]:
            if y - bands[-1][-1] > 1:
                bands.append([y])
            else:
                bands[-1].append(y)
        assert len(bands) == 2, f"panel {panel}: rows {below}"
        assert bands[1][0] - bands[0][-1] >= 4, f"panel {panel}: bands {bands}"
