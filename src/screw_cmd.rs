//! `polar-cell screw`: the screw's flow response (seed 000's output delay) and what flow
//! compensation buys on a real file.
//!
//! * `response`: the Navier–Stokes solution of the unrolled channel, then step responses of
//!   the extruder model at several operating points, each reduced to first order plus dead
//!   time and to second order; prints the constants and plots simulated against fitted.
//! * `material FILE`: plans the file, computes the screw commands with and without flow
//!   compensation, and reports the material each extruding move gets through the reduced
//!   model.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context as _};
use clap::Subcommand;
use plotters::prelude::*;
use screw_driver::compensation::FlowModel;
use screw_driver::extruder::{self, ExtruderParams};
use screw_driver::reduced::{self, Fits};

#[derive(Subcommand, Debug)]
pub enum ScrewCommand {
    /// Step responses of the extruder model, their reduced models, and a plot.
    Response {
        /// Operating points as screw-driver rpm (rpm-equivalent flow).
        #[arg(long, value_delimiter = ',', default_values_t = [30.0, 60.0, 120.0, 240.0])]
        rpm: Vec<f64>,
        /// Each step goes from the operating point to this multiple of it.
        #[arg(long, default_value_t = 1.5)]
        step: f64,
        /// The screw driver's calibration: filament-equivalent length per revolution (m).
        #[arg(long, default_value_t = 0.002)]
        e_per_rev_m: f64,
        /// Filament diameter the G-code's E is counted in (mm).
        #[arg(long, default_value_t = 1.75)]
        filament_diameter_mm: f64,
        /// Override an extruder parameter: NAME=VALUE (SI units, names as in `ExtruderParams`).
        #[arg(long = "set", value_name = "NAME=VALUE")]
        set: Vec<String>,
        /// Cells across the channel for the Navier–Stokes solution.
        #[arg(long, default_value_t = 48)]
        cells: usize,
        /// The plot to write.
        #[arg(long, default_value = "screw_response.png")]
        out: PathBuf,
    },
    /// Material per extruding move through the reduced flow model, uncompensated and
    /// compensated (the planner and screw driver with their default parameters).
    Material {
        /// The G-code file.
        file: PathBuf,
        /// Reduced model: time constant, dead time, closed-pin leak (s); default: the
        /// screw driver's defaults (the extruder model at 100 rpm).
        #[arg(long)]
        tau_s: Option<f64>,
        #[arg(long)]
        dead_time_s: Option<f64>,
        #[arg(long)]
        tau_closed_s: Option<f64>,
        /// Command grid (s).
        #[arg(long, default_value_t = 0.002)]
        period_s: f64,
        /// List at most this many moves that miss 1 % when compensated.
        #[arg(long, default_value_t = 20)]
        list: usize,
    },
}

pub fn run(command: ScrewCommand) -> anyhow::Result<()> {
    match command {
        ScrewCommand::Response {
            rpm,
            step,
            e_per_rev_m,
            filament_diameter_mm,
            set,
            cells,
            out,
        } => response(
            &rpm,
            step,
            e_per_rev_m,
            filament_diameter_mm,
            &set,
            cells,
            &out,
        ),
        ScrewCommand::Material {
            file,
            tau_s,
            dead_time_s,
            tau_closed_s,
            period_s,
            list,
        } => {
            let d = FlowModel::default_extruder();
            let model = FlowModel {
                tau_s: tau_s.unwrap_or(d.tau_s),
                dead_time_s: dead_time_s.unwrap_or(d.dead_time_s),
                tau_closed_s: tau_closed_s.unwrap_or(d.tau_closed_s),
            };
            model.check().map_err(anyhow::Error::msg)?;
            if !(period_s.is_finite() && period_s > 0.0) {
                bail!("--period-s {period_s}: must be > 0");
            }
            material(&file, &model, period_s, list)
        }
    }
}

/// Apply `NAME=VALUE` overrides to the extruder parameters.
pub fn apply_overrides(params: &mut ExtruderParams, set: &[String]) -> anyhow::Result<()> {
    for item in set {
        let Some((name, value)) = item.split_once('=') else {
            bail!("--set {item}: expected NAME=VALUE");
        };
        let value: f64 = value
            .trim()
            .parse()
            .with_context(|| format!("--set {item}: `{value}` is not a number"))?;
        let field = match name.trim() {
            "barrel_diameter_m" => &mut params.barrel_diameter_m,
            "screw_lead_m" => &mut params.screw_lead_m,
            "flight_width_m" => &mut params.flight_width_m,
            "channel_depth_m" => &mut params.channel_depth_m,
            "metering_length_m" => &mut params.metering_length_m,
            "nozzle_diameter_m" => &mut params.nozzle_diameter_m,
            "nozzle_length_m" => &mut params.nozzle_length_m,
            "chamber_volume_m3" => &mut params.chamber_volume_m3,
            "melt_density_kg_per_m3" => &mut params.melt_density_kg_per_m3,
            "melt_viscosity_pa_s" => &mut params.melt_viscosity_pa_s,
            "melt_consistency_pa_sn" => &mut params.melt_consistency_pa_sn,
            "melt_flow_index" => &mut params.melt_flow_index,
            "melt_bulk_modulus_pa" => &mut params.melt_bulk_modulus_pa,
            other => bail!("--set {item}: no extruder parameter `{other}`"),
        };
        *field = value;
    }
    params.channel()?;
    Ok(())
}

/// One operating point's study.
struct Study {
    rpm: f64,
    op: extruder::OperatingPoint,
    samples: Vec<(f64, f64)>,
    fits: Fits,
    /// The same change as a ramp over `ramp_s`: simulated (normalised) and as the chosen
    /// reduced model predicts it.
    ramp_s: f64,
    ramp: Vec<(f64, f64)>,
    ramp_predicted: Vec<f64>,
}

/// A reduced model's response to a unit ramp over `ramp_s`: its step response averaged over
/// the ramp (superposition of the ramp's steps).
fn ramp_prediction(model: &reduced::Reduced, ramp_s: f64, t: f64) -> f64 {
    const PIECES: usize = 400;
    (0..PIECES)
        .map(|k| {
            let a = (k as f64 + 0.5) / PIECES as f64 * ramp_s;
            model.step(t - a)
        })
        .sum::<f64>()
        / PIECES as f64
}

fn response(
    rpm: &[f64],
    step: f64,
    e_per_rev_m: f64,
    filament_diameter_mm: f64,
    set: &[String],
    cells: usize,
    out: &Path,
) -> anyhow::Result<()> {
    if !(step.is_finite() && step > 0.0 && step != 1.0) {
        bail!("--step {step}: must be a positive factor other than 1");
    }
    if rpm.iter().any(|r| !(r.is_finite() && *r > 0.0)) {
        bail!("--rpm {rpm:?}: operating points must be > 0");
    }
    let mut params = ExtruderParams::default();
    apply_overrides(&mut params, set)?;
    let channel = params.channel()?;
    let ns = extruder::channel_from_navier_stokes(&params, cells)?;
    let filament_area_m2 = std::f64::consts::PI * (filament_diameter_mm * 1e-3 / 2.0).powi(2);
    let flow_per_rpm = e_per_rev_m * filament_area_m2 / 60.0; // m³/s per driver rpm
    println!("Extruder model (SI): {params:?}");
    println!(
        "Metering channel: helix {:.2}°, width {:.2} mm, down-channel length {:.1} mm, depth {:.2} mm, F_d {:.4}, F_p {:.4}",
        channel.helix_angle_rad.to_degrees(),
        channel.width_m * 1e3,
        channel.length_m * 1e3,
        channel.depth_m * 1e3,
        channel.drag_shape_factor,
        channel.pressure_shape_factor
    );
    println!(
        "  drag flow α = {:.1} mm³/rev, back-flow conductance β = {:.3e} m³/(s·Pa), melt under pressure {:.0} mm³, C = V/K = {:.3e} m³/Pa",
        channel.drag_m3_per_rev * 1e9,
        channel.back_flow_m3_per_s_pa,
        channel.volume_m3 * 1e9,
        channel.capacitance_m3_per_pa
    );
    println!(
        "Navier–Stokes, unrolled channel ({cells} cells across): drag flow {:.6} and pressure flow {:.6} of the closed forms; the channel flow settles (63 %) in {:.3e} s (analytic {:.3e} s)",
        ns.drag_ratio, ns.pressure_ratio, ns.settle_time_s, ns.settle_time_exact_s
    );
    let tau_closed = channel.capacitance_m3_per_pa / channel.back_flow_m3_per_s_pa;
    println!(
        "  → the melt follows the screw within a microsecond; the lag is the melt's compressibility. Pin closed, screw stopped: pressure leaks back through the screw with τ_closed = {:.1} ms",
        tau_closed * 1e3
    );
    println!();
    println!("  rpm   flow mm³/s  screw rev/s  pressure bar  τ_lin ms | FOPDT τ ms  L ms    rms    | SOPDT τ1 ms τ2 ms  L ms   rms     | chosen");
    let mut studies = Vec::new();
    for &r in rpm {
        let q_from = r * flow_per_rpm;
        let op_from = extruder::operating_point(&params, q_from)?;
        let op_to = extruder::operating_point(&params, q_from * step)?;
        let op = extruder::operating_point(&params, q_from * step.sqrt())?;
        let duration = 8.0 * op_from.tau_s.max(op_to.tau_s);
        let samples = extruder::step_response(
            &params,
            op_from.screw_rev_per_s,
            op_to.screw_rev_per_s,
            duration,
            duration / 400.0,
        )?;
        let fits = reduced::fit(&reduced::normalise(&samples)?);
        let (fo_tau, fo_dead) = fits.first_order.model.first_order();
        let (so_t1, so_t2, so_dead) = match fits.second_order.model {
            reduced::Reduced::SecondOrder {
                tau1_s,
                tau2_s,
                dead_time_s,
            } => (tau1_s, tau2_s, dead_time_s),
            reduced::Reduced::FirstOrder { tau_s, dead_time_s } => (tau_s, 0.0, dead_time_s),
        };
        println!(
            "{r:>6.0} {:>11.2} {:>12.3} {:>13.1} {:>9.2} | {:>10.2} {:>5.2} {:>8.1e} | {:>10.2} {:>6.2} {:>5.2} {:>8.1e} | {}",
            q_from * 1e9,
            op_from.screw_rev_per_s,
            op_from.pressure_pa / 1e5,
            op.tau_s * 1e3,
            fo_tau * 1e3,
            fo_dead * 1e3,
            fits.first_order.rms,
            so_t1 * 1e3,
            so_t2 * 1e3,
            so_dead * 1e3,
            fits.second_order.rms,
            match fits.chosen.model {
                reduced::Reduced::FirstOrder { .. } => "first order + dead time",
                reduced::Reduced::SecondOrder { .. } => "second order",
            }
        );
        // The same change as a ramp over two linearised time constants.
        let ramp_s = 2.0 * op.tau_s;
        let (from_rev, to_rev) = (op_from.screw_rev_per_s, op_to.screw_rev_per_s);
        let ramp_raw = extruder::response(
            &params,
            |t| from_rev + (to_rev - from_rev) * (t / ramp_s).clamp(0.0, 1.0),
            duration + ramp_s,
            (duration + ramp_s) / 400.0,
        )?;
        let (q0, q1) = (
            ramp_raw[0].1,
            params.die_flow(extruder::steady_pressure(&params, &channel, to_rev)),
        );
        let ramp: Vec<(f64, f64)> = ramp_raw
            .iter()
            .map(|&(t, q)| (t, (q - q0) / (q1 - q0)))
            .collect();
        let ramp_predicted: Vec<f64> = ramp
            .iter()
            .map(|&(t, _)| ramp_prediction(&fits.chosen.model, ramp_s, t))
            .collect();
        let ramp_rms = (ramp
            .iter()
            .zip(&ramp_predicted)
            .map(|(a, b)| (a.1 - b).powi(2))
            .sum::<f64>()
            / ramp.len() as f64)
            .sqrt();
        println!(
            "       ramp over {:.1} ms: the chosen model predicts it with rms {:.1e}",
            ramp_s * 1e3,
            ramp_rms
        );
        studies.push(Study {
            rpm: r,
            op,
            samples,
            fits,
            ramp_s,
            ramp,
            ramp_predicted,
        });
    }
    let middle = &studies[studies.len() / 2];
    let (tau, dead) = middle.fits.chosen.model.first_order();
    let model = FlowModel {
        tau_s: tau,
        dead_time_s: dead,
        tau_closed_s: tau_closed,
    };
    println!();
    println!(
        "Compensation constants at {:.0} rpm (screw_driver parameters): flow_tau_s:={:.5} flow_dead_time_s:={:.5} flow_tau_closed_s:={:.5}",
        middle.rpm, model.tau_s, model.dead_time_s, model.tau_closed_s
    );
    if set.is_empty()
        && (e_per_rev_m - 0.002).abs() < 1e-12
        && (filament_diameter_mm - 1.75).abs() < 1e-12
    {
        let d = FlowModel::default_extruder();
        println!(
            "The screw driver's defaults: this model linearised at 100 rpm: flow_tau_s {:.5}, flow_dead_time_s {:.5}, flow_tau_closed_s {:.5}",
            d.tau_s, d.dead_time_s, d.tau_closed_s
        );
    }
    plot(&studies, step, out)?;
    println!("Plot: {}", out.display());
    Ok(())
}

fn plot(studies: &[Study], step: f64, out: &Path) -> anyhow::Result<()> {
    crate::plot_cmd::register_font()?;
    let root = BitMapBackend::new(out, (1400, 300 * studies.len() as u32 + 40)).into_drawing_area();
    root.fill(&WHITE)?;
    let (title, body) = root.split_vertically(40);
    title.titled(
        &format!("Outlet flow after a ×{step} step and ramp of screw speed: simulated and reduced models"),
        ("sans-serif", 22),
    )?;
    for (area, study) in body.split_evenly((studies.len(), 1)).iter().zip(studies) {
        let normalised = reduced::normalise(&study.samples)?;
        let t_max = study.ramp.last().map_or(1.0, |p| p.0) * 1e3;
        let mut chart = ChartBuilder::on(area)
            .caption(
                format!(
                    "{:.0} rpm → {:.0} rpm: τ_lin {:.1} ms",
                    study.rpm,
                    study.rpm * step,
                    study.op.tau_s * 1e3
                ),
                ("sans-serif", 18),
            )
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..t_max, -0.05..1.1)?;
        chart
            .configure_mesh()
            .x_desc("time after the change starts (ms)")
            .y_desc("fraction of the change")
            .label_style(("sans-serif", 14))
            .draw()?;
        chart
            .draw_series(LineSeries::new(
                normalised.iter().map(|&(t, s)| (t * 1e3, s)),
                BLUE.stroke_width(3),
            ))?
            .label("simulated (extruder model)")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE));
        for (fit, colour, name) in [
            (&study.fits.first_order, RED, "first order + dead time"),
            (&study.fits.second_order, GREEN, "second order + dead time"),
        ] {
            chart
                .draw_series(LineSeries::new(
                    normalised
                        .iter()
                        .map(|&(t, _)| (t * 1e3, fit.model.step(t))),
                    colour,
                ))?
                .label(format!("{name} (rms {:.1e})", fit.rms))
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
        }
        chart
            .draw_series(LineSeries::new(
                study.ramp.iter().map(|&(t, s)| (t * 1e3, s)),
                CYAN.stroke_width(3),
            ))?
            .label(format!("ramp over {:.0} ms, simulated", study.ramp_s * 1e3))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], CYAN));
        chart
            .draw_series(LineSeries::new(
                study
                    .ramp
                    .iter()
                    .zip(&study.ramp_predicted)
                    .map(|(&(t, _), &p)| (t * 1e3, p)),
                MAGENTA,
            ))?
            .label("ramp, chosen reduced model")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], MAGENTA));
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()?;
    }
    root.present()
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}

/// The file planned as the print plans it, as the screw driver sees the moves.
/// Also how much the planner slowed each move for the screw.
fn timed_moves(
    file: &Path,
    options: &polar_planner::PlannerOptions,
) -> anyhow::Result<(Vec<screw_driver::screw::TimedMove>, Vec<Option<f64>>)> {
    let bytes = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
    let name = file.display().to_string();
    let (moves, _) = gcode_streamer::parse_all(&bytes, &name, Default::default())?;
    let mut planner = polar_planner::Planner::new(options.clone())?;
    let mut plans = Vec::with_capacity(moves.len());
    for m in &moves {
        planner.push(m, &mut plans)?;
    }
    planner.flush(&mut plans);
    let mut from = [0.0; 3];
    let mut out = Vec::with_capacity(moves.len());
    for (m, p) in moves.iter().zip(&plans) {
        let trajectory = polar_planner::messages::trajectory_message(p, 0);
        out.push(screw_driver::screw::TimedMove::from_trajectory(
            m,
            from,
            &trajectory,
            0,
        ));
        from = screw_driver::screw::position_after(m, from);
    }
    Ok((out, plans.iter().map(|p| p.slowed_for_screw).collect()))
}

/// |error| quantiles of a set of moves, in %.
fn quantiles(errors: &mut [f64]) -> String {
    if errors.is_empty() {
        return "no moves".into();
    }
    errors.sort_by(f64::total_cmp);
    let at = |q: f64| errors[((errors.len() - 1) as f64 * q).round() as usize] * 100.0;
    format!(
        "median {:.3} %, p90 {:.3} %, p99 {:.3} %, worst {:.3} %",
        at(0.5),
        at(0.9),
        at(0.99),
        at(1.0)
    )
}

/// rpm the move needs at its fastest (instant flow).
fn peak_rpm(m: &screw_driver::screw::TimedMove, e_per_rev_m: f64) -> f64 {
    let duration = m.t.last().unwrap_or(&0.0) - m.motion_start_s;
    let peak = if m.length_m > 0.0 {
        m.speed.iter().fold(0.0f64, |a, &v| a.max(v)) * m.delta_e_m / m.length_m
    } else if duration > 0.0 {
        m.delta_e_m / duration
    } else {
        0.0
    };
    60.0 * peak / e_per_rev_m
}

fn material(file: &Path, model: &FlowModel, period_s: f64, list: usize) -> anyhow::Result<()> {
    let screw = screw_driver::screw::ScrewOptions::default();
    let e_per_rev_m = 0.002;
    let planner_defaults = polar_planner::PlannerOptions::default();
    let limits = polar_planner::ScrewLimits {
        usable_rpm: screw.max_rpm * 0.9,
        e_per_rev_m,
        flow_tau_s: model.tau_s,
    };
    // Without the screw's limit in the plan: which moves would need more than the screw has.
    let (unlimited, _) = timed_moves(file, &planner_defaults)?;
    let options = polar_planner::PlannerOptions {
        screw: Some(limits),
        ..planner_defaults
    };
    let (moves, slowed) = timed_moves(file, &options)?;
    println!(
        "{}: {} moves; reduced model τ {:.2} ms, dead time {:.2} ms, closed-pin leak {:.1} ms; grid {:.1} ms; screw max {:.0} rpm, the plan uses ≤ {:.0} rpm",
        file.display(),
        moves.len(),
        model.tau_s * 1e3,
        model.dead_time_s * 1e3,
        model.tau_closed_s * 1e3,
        period_s * 1e3,
        screw.max_rpm,
        limits.usable_rpm
    );
    let plan_time = |ms: &[screw_driver::screw::TimedMove]| {
        ms.iter()
            .filter_map(|m| m.t.last().copied())
            .fold(0.0f64, f64::max)
    };
    // Which moves would need more than the screw has, planned without its limit.
    let over = unlimited
        .iter()
        .filter(|m| m.extrude && peak_rpm(m, e_per_rev_m) > limits.usable_rpm * (1.0 + 1e-9))
        .count();
    let mut factors: Vec<(f64, u32, bool)> = slowed
        .iter()
        .zip(&moves)
        .filter_map(|(f, m)| f.map(|f| (f, m.source_line, m.length_m == 0.0)))
        .collect();
    factors.sort_by(|a, b| b.0.total_cmp(&a.0));
    let primes = factors.iter().filter(|f| f.2).count();
    println!(
        "Screw limits in the plan: {over} extruding moves would need more than {:.0} rpm; {} moves slowed ({} moving, {primes} primes lengthened for the rpm and for the flow to rise and drain){}; machine time {:.2} s → {:.2} s",
        limits.usable_rpm,
        factors.len(),
        factors.len() - primes,
        factors.first().map_or(String::new(), |(f, line, _)| format!(
            ", most: line {line} ×{f:.2}"
        )),
        plan_time(&unlimited),
        plan_time(&moves)
    );
    let run = |compensation: Option<FlowModel>| {
        screw_driver::compensation::material_per_move(
            &moves,
            &screw_driver::screw::ScrewOptions {
                compensation,
                compensation_period_s: period_s,
                ..screw.clone()
            },
            model,
            period_s,
        )
    };
    let uncompensated = run(None);
    let compensated = run(Some(*model));
    for (name, result) in [
        ("uncompensated", &uncompensated),
        ("compensated", &compensated),
    ] {
        let mut errors: Vec<f64> = result.iter().map(|m| m.error().abs()).collect();
        let missed = errors.iter().filter(|e| **e > 0.01).count();
        println!(
            "{name:>14}: {} extruding moves; |delivered/wanted − 1|: {}; {missed} beyond 1 %",
            result.len(),
            quantiles(&mut errors)
        );
    }
    let mut missed: Vec<&screw_driver::compensation::MoveMaterial> = compensated
        .iter()
        .filter(|m| m.error().abs() > 0.01)
        .collect();
    missed.sort_by(|a, b| b.error().abs().total_cmp(&a.error().abs()));
    if !missed.is_empty() {
        println!("Compensated moves beyond 1 % (worst first):");
        for m in missed.iter().take(list) {
            println!(
                "  line {}: E {:.4} mm, {:+.2} %",
                m.source_line,
                m.wanted_rpm_s / 60.0 * e_per_rev_m * 1e3,
                m.error() * 100.0
            );
        }
    }
    Ok(())
}
