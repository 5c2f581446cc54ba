//! `polar-cell plot BAG --out FILE.png`: r, θ, tool speed and screw rpm against time, one
//! panel each (the layout of seed 000's Figure 1), from a recorded print.

use std::path::Path;

use anyhow::{bail, Context as _};
use cell_bag::node::mcap_file_of;
use cell_bag::read_bag;
use plotters::prelude::*;
use polar_cell_msgs::{cdr, JointTrajectory, ScrewCommand};

/// Where DejaVu Sans usually is (Debian's fonts-dejavu-core); `POLAR_CELL_FONT` overrides.
const FONT_PATHS: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

pub fn register_font() -> anyhow::Result<()> {
    let candidates: Vec<String> = std::env::var("POLAR_CELL_FONT")
        .into_iter()
        .chain(FONT_PATHS.iter().map(|s| s.to_string()))
        .collect();
    for path in &candidates {
        if let Ok(bytes) = std::fs::read(path) {
            // The font registry wants 'static bytes; the process plots once and exits.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            plotters::style::register_font("sans-serif", FontStyle::Normal, bytes)
                .map_err(|_| anyhow::anyhow!("{path} is not a usable TrueType font"))?;
            return Ok(());
        }
    }
    bail!("no font found (tried {candidates:?}): install fonts-dejavu-core or set POLAR_CELL_FONT")
}

/// One time series per panel.
struct Series {
    title: &'static str,
    unit: &'static str,
    points: Vec<(f64, f64)>,
}

pub fn plot(bag_path: &Path, out: &Path) -> anyhow::Result<()> {
    let file = mcap_file_of(bag_path)?;
    let bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
    let bag = read_bag(&bytes).with_context(|| format!("reading {}", file.display()))?;
    let mut r = Vec::new();
    let mut theta = Vec::new();
    let mut speed = Vec::new();
    let mut rpm = Vec::new();
    let mut base: Option<i64> = None;
    let mut seconds = |stamp_ns: i64| (stamp_ns - *base.get_or_insert(stamp_ns)) as f64 * 1e-9;
    for message in bag.messages()? {
        let message = message?;
        match message.topic.as_str() {
            "/polar/trajectory" => {
                let t: JointTrajectory = cdr::decode(&message.data)?;
                let t0 = seconds(t.header.stamp.as_nanos());
                for p in &t.points {
                    let (q, qd) = (&p.positions, &p.velocities);
                    if q.len() < 3 || qd.len() < 3 {
                        continue;
                    }
                    let time = t0 + p.time_from_start.as_secs_f64();
                    r.push((time, q[1] * 1000.0));
                    theta.push((time, q[0]));
                    let v = (qd[1] * qd[1] + (q[1] * qd[0]).powi(2) + qd[2] * qd[2]).sqrt();
                    speed.push((time, v * 1000.0));
                }
            }
            "/screw/command" => {
                let c: ScrewCommand = cdr::decode(&message.data)?;
                rpm.push((seconds(c.header.stamp.as_nanos()), c.rpm));
            }
            _ => {}
        }
    }
    if r.is_empty() {
        bail!("{}: no /polar/trajectory to plot", file.display());
    }
    register_font()?;
    let panels = [
        Series {
            title: "radius r",
            unit: "mm",
            points: r,
        },
        Series {
            title: "bed angle θ",
            unit: "rad",
            points: theta,
        },
        Series {
            title: "tool speed",
            unit: "mm/s",
            points: speed,
        },
        Series {
            title: "screw",
            unit: "rpm",
            points: rpm,
        },
    ];
    let t_max = panels
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.0))
        .fold(0.0f64, f64::max)
        .max(1e-3);
    let root = BitMapBackend::new(out, (1400, 1200)).into_drawing_area();
    root.fill(&WHITE)?;
    let colours = [BLUE, RED, GREEN, MAGENTA];
    for ((area, series), colour) in root.split_evenly((4, 1)).iter().zip(&panels).zip(colours) {
        let (lo, hi) = series
            .points
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                (lo.min(p.1), hi.max(p.1))
            });
        let (lo, hi) = if lo > hi { (0.0, 1.0) } else { (lo, hi) };
        let pad = ((hi - lo) * 0.05).max(1e-9);
        let mut chart = ChartBuilder::on(area)
            .caption(
                format!("{} ({})", series.title, series.unit),
                ("sans-serif", 22),
            )
            .margin(8)
            // Room for the tick labels and, below them, the axis description (30 px put
            // one on top of the other).
            .x_label_area_size(46)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..t_max, (lo - pad)..(hi + pad))?;
        chart
            .configure_mesh()
            .x_desc("time (s)")
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 14))
            .draw()?;
        chart.draw_series(LineSeries::new(series.points.iter().copied(), colour))?;
    }
    root.present()
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}
