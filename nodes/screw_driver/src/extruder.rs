//! Why the screw's output lags its rpm, and by how much (seed 000, "resin output delay").
//!
//! Seed 000 says the screw's rpm follows its command in real time, and sets up the
//! incompressible Navier–Stokes equations to study how the outlet flow follows the screw.
//! Solving them for the melt channel of the screw unrolled (the channel between the moving
//! barrel and the screw root, [`channel_from_navier_stokes`]) answers the first half: the
//! channel flow settles in about `H²/(π²ν)` after a change of wall speed — 5·10⁻⁸ s for a
//! polymer melt (ν = μ/ρ ≈ 1.8 m²/s), a million times faster than anything a printer sees. An
//! incompressible melt would follow the screw at once. The lag a printer shows comes from the
//! melt's compressibility: the melt between the screw and the nozzle exit is a spring
//! (capacitance `C = V/K`, K the bulk modulus), charged by the screw's net flow and discharged
//! through the nozzle:
//!
//! ```text
//! C dP/dt = α·N − β·P − Q_die(P)          (pin open; Q_die = 0 with the pin closed)
//! ```
//!
//! with α the drag flow per revolution and β the pressure back-flow conductance of the
//! metering channel (the flat-channel flows with the standard shape factors for the flight
//! walls; the flat-channel parts are what the Navier–Stokes solver reproduces), and
//! `Q_die` the power-law flow through the nozzle bore. Linearised at an operating point the
//! outlet flow is first order with `τ = C / (β + dQ_die/dP)`; a shear-thinning melt
//! (n < 1) makes the nozzle's conductance grow with the flow, so τ falls as the flow rises.
//!
//! [`step_response`] integrates this model for rpm steps and ramps, and [`fit`] reduces each
//! response to first order plus dead time or second order, whichever fits better.

use crate::flow::{Flow, FlowError, FlowOptions, SidesX};

/// The screw, nozzle and melt. Units SI; N in revolutions per second inside the model.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtruderParams {
    pub barrel_diameter_m: f64,
    /// Axial advance of the flight per revolution (square pitch: the diameter).
    pub screw_lead_m: f64,
    pub flight_width_m: f64,
    /// Depth of the metering channel.
    pub channel_depth_m: f64,
    /// Axial length of the metering section (the melt-filled channel).
    pub metering_length_m: f64,
    pub nozzle_diameter_m: f64,
    pub nozzle_length_m: f64,
    /// Melt held under pressure besides the metering channel (screw tip, nozzle chamber).
    pub chamber_volume_m3: f64,
    pub melt_density_kg_per_m3: f64,
    /// Viscosity in the metering channel (apparent, at the channel's shear rate).
    pub melt_viscosity_pa_s: f64,
    /// Power-law consistency K and index n of the melt in the nozzle: τ_w = K γ̇ⁿ.
    pub melt_consistency_pa_sn: f64,
    pub melt_flow_index: f64,
    pub melt_bulk_modulus_pa: f64,
}

impl Default for ExtruderParams {
    /// A small pellet screw (16 mm, square pitch) with a 0.8 mm nozzle and PLA-like melt at
    /// about 200 °C; the README ("Screw flow response and compensation") says where each
    /// value comes from.
    fn default() -> Self {
        ExtruderParams {
            barrel_diameter_m: 0.016,
            screw_lead_m: 0.016,
            flight_width_m: 0.0016,
            channel_depth_m: 0.001,
            metering_length_m: 0.040,
            nozzle_diameter_m: 0.0008,
            nozzle_length_m: 0.002,
            chamber_volume_m3: 0.3e-6,
            melt_density_kg_per_m3: 1100.0,
            melt_viscosity_pa_s: 1945.0,
            melt_consistency_pa_sn: 6000.0,
            melt_flow_index: 0.35,
            melt_bulk_modulus_pa: 0.71e9,
        }
    }
}

/// Why a model cannot be built or fitted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ExtruderError {
    #[error("extruder parameter {name} is {value}: {why}")]
    Parameter {
        name: &'static str,
        value: f64,
        why: &'static str,
    },
    #[error("flow solver: {0}")]
    Flow(#[from] FlowError),
    #[error("a response to fit needs at least 8 samples and a change of output; got {samples} samples, change {change}")]
    NothingToFit { samples: usize, change: f64 },
}

/// The metering channel as the model uses it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Channel {
    /// Helix angle of the flight at the barrel.
    pub helix_angle_rad: f64,
    /// Width perpendicular to the flight and length along the channel (down-channel).
    pub width_m: f64,
    pub length_m: f64,
    pub depth_m: f64,
    /// Shape factors of the flight walls (1 for an infinitely wide channel).
    pub drag_shape_factor: f64,
    pub pressure_shape_factor: f64,
    /// Drag flow per revolution α (m³).
    pub drag_m3_per_rev: f64,
    /// Back-flow conductance β (m³/(s·Pa)).
    pub back_flow_m3_per_s_pa: f64,
    /// Melt under pressure (m³) and the capacitance C = V/K (m³/Pa).
    pub volume_m3: f64,
    pub capacitance_m3_per_pa: f64,
}

/// Drag-flow shape factor of a rectangular channel of depth h and width w (flights at rest,
/// barrel moving): `F_d = 16w/(π³h) Σ_{i odd} tanh(iπh/(2w))/i³`.
pub fn drag_shape_factor(h: f64, w: f64) -> f64 {
    // Enough terms for shallow channels, where tanh stays linear for i up to ~w/h.
    let terms = (20.0 * w / h).clamp(2000.0, 1e6) as usize;
    let sum: f64 = (0..terms)
        .map(|k| {
            let i = (2 * k + 1) as f64;
            (i * std::f64::consts::PI * h / (2.0 * w)).tanh() / i.powi(3)
        })
        .sum();
    16.0 * w / (std::f64::consts::PI.powi(3) * h) * sum
}

/// Pressure-flow shape factor: `F_p = 1 − 192h/(π⁵w) Σ_{i odd} tanh(iπw/(2h))/i⁵`.
pub fn pressure_shape_factor(h: f64, w: f64) -> f64 {
    let sum: f64 = (0..200)
        .map(|k| {
            let i = (2 * k + 1) as f64;
            (i * std::f64::consts::PI * w / (2.0 * h)).tanh() / i.powi(5)
        })
        .sum();
    1.0 - 192.0 * h / (std::f64::consts::PI.powi(5) * w) * sum
}

impl ExtruderParams {
    fn check(&self) -> Result<(), ExtruderError> {
        let positive = [
            ("barrel_diameter_m", self.barrel_diameter_m),
            ("screw_lead_m", self.screw_lead_m),
            ("channel_depth_m", self.channel_depth_m),
            ("metering_length_m", self.metering_length_m),
            ("nozzle_diameter_m", self.nozzle_diameter_m),
            ("nozzle_length_m", self.nozzle_length_m),
            ("melt_density_kg_per_m3", self.melt_density_kg_per_m3),
            ("melt_viscosity_pa_s", self.melt_viscosity_pa_s),
            ("melt_consistency_pa_sn", self.melt_consistency_pa_sn),
            ("melt_flow_index", self.melt_flow_index),
            ("melt_bulk_modulus_pa", self.melt_bulk_modulus_pa),
        ];
        for (name, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(ExtruderError::Parameter {
                    name,
                    value,
                    why: "must be finite and > 0",
                });
            }
        }
        for (name, value) in [
            ("flight_width_m", self.flight_width_m),
            ("chamber_volume_m3", self.chamber_volume_m3),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(ExtruderError::Parameter {
                    name,
                    value,
                    why: "must be finite and >= 0",
                });
            }
        }
        if self.channel_depth_m * 2.0 >= self.barrel_diameter_m {
            return Err(ExtruderError::Parameter {
                name: "channel_depth_m",
                value: self.channel_depth_m,
                why: "must be less than the barrel's radius",
            });
        }
        Ok(())
    }

    /// The metering channel: geometry, drag and back flow, capacitance.
    pub fn channel(&self) -> Result<Channel, ExtruderError> {
        self.check()?;
        let d = self.barrel_diameter_m;
        let phi = (self.screw_lead_m / (std::f64::consts::PI * d)).atan();
        let width = self.screw_lead_m * phi.cos() - self.flight_width_m;
        if width.is_nan() || width <= 0.0 {
            return Err(ExtruderError::Parameter {
                name: "flight_width_m",
                value: self.flight_width_m,
                why: "leaves no channel between the flights",
            });
        }
        let h = self.channel_depth_m;
        let length = self.metering_length_m / phi.sin();
        let fd = drag_shape_factor(h, width);
        let fp = pressure_shape_factor(h, width);
        // Barrel speed along the channel per rev/s: π D cos φ.
        let drag = 0.5 * fd * width * h * std::f64::consts::PI * d * phi.cos();
        let back = fp * width * h.powi(3) / (12.0 * self.melt_viscosity_pa_s * length);
        let volume = width * h * length + self.chamber_volume_m3;
        Ok(Channel {
            helix_angle_rad: phi,
            width_m: width,
            length_m: length,
            depth_m: h,
            drag_shape_factor: fd,
            pressure_shape_factor: fp,
            drag_m3_per_rev: drag,
            back_flow_m3_per_s_pa: back,
            volume_m3: volume,
            capacitance_m3_per_pa: volume / self.melt_bulk_modulus_pa,
        })
    }

    /// Flow through the nozzle bore at pressure drop `p` (power-law melt in a tube):
    /// `Q = nπR³/(3n+1) · (R p / (2 K L))^(1/n)`.
    pub fn die_flow(&self, p: f64) -> f64 {
        if p <= 0.0 {
            return 0.0;
        }
        let n = self.melt_flow_index;
        let r = 0.5 * self.nozzle_diameter_m;
        let wall_stress = r * p / (2.0 * self.nozzle_length_m);
        n * std::f64::consts::PI * r.powi(3) / (3.0 * n + 1.0)
            * (wall_stress / self.melt_consistency_pa_sn).powf(1.0 / n)
    }

    /// Pressure that drives `q` through the nozzle (the inverse of [`Self::die_flow`]).
    pub fn die_pressure(&self, q: f64) -> f64 {
        if q <= 0.0 {
            return 0.0;
        }
        let n = self.melt_flow_index;
        let r = 0.5 * self.nozzle_diameter_m;
        let shear = q * (3.0 * n + 1.0) / (n * std::f64::consts::PI * r.powi(3));
        2.0 * self.nozzle_length_m / r * self.melt_consistency_pa_sn * shear.powf(n)
    }
}

/// A steady operating point: outlet flow q (m³/s), the screw speed that gives it and the
/// pressure behind the nozzle; `tau_s` the linearised time constant there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OperatingPoint {
    pub flow_m3_per_s: f64,
    pub screw_rev_per_s: f64,
    pub pressure_pa: f64,
    pub tau_s: f64,
}

/// The steady state delivering `q` and its linearised time constant.
pub fn operating_point(params: &ExtruderParams, q: f64) -> Result<OperatingPoint, ExtruderError> {
    let ch = params.channel()?;
    let p = params.die_pressure(q);
    let n_rev = (q + ch.back_flow_m3_per_s_pa * p) / ch.drag_m3_per_rev;
    // dQ_die/dP = Q/(n P) for a power law.
    let die_conductance = if q > 0.0 && p > 0.0 {
        q / (params.melt_flow_index * p)
    } else {
        // Q ∝ P^(1/n): at rest the conductance is 0 for n < 1 and the Newtonian one for n = 1.
        let probe = 1.0;
        params.die_flow(probe) / probe
    };
    Ok(OperatingPoint {
        flow_m3_per_s: q,
        screw_rev_per_s: n_rev,
        pressure_pa: p,
        tau_s: ch.capacitance_m3_per_pa / (ch.back_flow_m3_per_s_pa + die_conductance),
    })
}

/// The lumped model's state: the pressure behind the nozzle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeltState {
    pub pressure_pa: f64,
}

/// Advance the pressure by `dt` at screw speed `rev_per_s` with the pin open or closed;
/// returns the volume that left the nozzle. Integrated by classical Runge–Kutta in substeps
/// no longer than a tenth of the local time constant.
pub fn advance(
    params: &ExtruderParams,
    channel: &Channel,
    state: &mut MeltState,
    rev_per_s: f64,
    pin_open: bool,
    dt: f64,
) -> f64 {
    if dt <= 0.0 {
        return 0.0;
    }
    let c = channel.capacitance_m3_per_pa;
    let rhs = |p: f64| {
        let out = if pin_open { params.die_flow(p) } else { 0.0 };
        (
            (channel.drag_m3_per_rev * rev_per_s - channel.back_flow_m3_per_s_pa * p - out) / c,
            out,
        )
    };
    let mut p = state.pressure_pa;
    let mut volume = 0.0;
    let mut t = 0.0;
    while t < dt {
        // Local stiffness: back flow plus the die's slope (secant near 0).
        let slope = channel.back_flow_m3_per_s_pa
            + if pin_open {
                let q = params.die_flow(p.max(1.0));
                q / (params.melt_flow_index * p.max(1.0))
            } else {
                0.0
            };
        let h = (0.1 * c / slope).min(dt - t).max(dt * 1e-6);
        let (k1, o1) = rhs(p);
        let (k2, o2) = rhs(p + 0.5 * h * k1);
        let (k3, o3) = rhs(p + 0.5 * h * k2);
        let (k4, o4) = rhs(p + h * k3);
        p += h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4);
        volume += h / 6.0 * (o1 + 2.0 * o2 + 2.0 * o3 + o4);
        t += h;
    }
    state.pressure_pa = p.max(0.0);
    volume
}

/// Outlet flow (m³/s) sampled every `sample_s` while the screw speed follows `rev_per_s(t)`
/// from the steady state at `rev_per_s(0)`, pin open, for `duration_s`.
pub fn response(
    params: &ExtruderParams,
    rev_per_s: impl Fn(f64) -> f64,
    duration_s: f64,
    sample_s: f64,
) -> Result<Vec<(f64, f64)>, ExtruderError> {
    let channel = params.channel()?;
    let mut state = MeltState {
        pressure_pa: steady_pressure(params, &channel, rev_per_s(0.0)),
    };
    let samples = (duration_s / sample_s).round() as usize;
    let mut out = Vec::with_capacity(samples + 1);
    out.push((0.0, params.die_flow(state.pressure_pa)));
    for k in 0..samples {
        let t = k as f64 * sample_s;
        // The speed held at the middle of the sample (exact for steps on the grid).
        advance(
            params,
            &channel,
            &mut state,
            rev_per_s(t + 0.5 * sample_s),
            true,
            sample_s,
        );
        out.push((t + sample_s, params.die_flow(state.pressure_pa)));
    }
    Ok(out)
}

/// The pressure at which the screw at `rev_per_s` and the nozzle pass the same flow.
pub fn steady_pressure(params: &ExtruderParams, channel: &Channel, rev_per_s: f64) -> f64 {
    let drag = channel.drag_m3_per_rev * rev_per_s.max(0.0);
    if drag <= 0.0 {
        return 0.0;
    }
    // Net screw flow falls and die flow rises with pressure: bisection on the balance.
    let (mut lo, mut hi) = (0.0, drag / channel.back_flow_m3_per_s_pa);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if drag - channel.back_flow_m3_per_s_pa * mid - params.die_flow(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Step response to the screw going from `from_rev_per_s` to `to_rev_per_s` at t = 0.
pub fn step_response(
    params: &ExtruderParams,
    from_rev_per_s: f64,
    to_rev_per_s: f64,
    duration_s: f64,
    sample_s: f64,
) -> Result<Vec<(f64, f64)>, ExtruderError> {
    response(
        params,
        |t| {
            if t > 0.0 {
                to_rev_per_s
            } else {
                from_rev_per_s
            }
        },
        duration_s,
        sample_s,
    )
}

/// What the Navier–Stokes solver says about the unrolled metering channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChannelFlow {
    /// Drag flow of the flat channel relative to `V H / 2` per unit width (1 exactly).
    pub drag_ratio: f64,
    /// Pressure flow relative to `H³ G / (12 ν)` per unit width (1 exactly).
    pub pressure_ratio: f64,
    /// Time for the channel flow to reach 1 − 1/e of a change of barrel speed, in seconds of
    /// the real melt, and the analytic value of the same (Couette start-up series).
    pub settle_time_s: f64,
    pub settle_time_exact_s: f64,
}

/// Couette start-up: flow rate fraction reached `t` after the wall starts, depth h, ν:
/// `1 − Σ_{n odd} 8/(n²π²) · exp(−n²π²νt/h²)`.
pub fn couette_startup_fraction(t: f64, h: f64, nu: f64) -> f64 {
    let pi2 = std::f64::consts::PI.powi(2);
    1.0 - (0..2000)
        .map(|k| {
            let n = (2 * k + 1) as f64;
            8.0 / (n * n * pi2) * (-n * n * pi2 * nu * t / (h * h)).exp()
        })
        .sum::<f64>()
}

/// Solve the unrolled channel (periodic down the channel, barrel on top, root below) with the
/// Navier–Stokes solver in the melt's own units: drag flow, pressure flow, and how fast the
/// channel flow settles after the barrel speed changes.
pub fn channel_from_navier_stokes(
    params: &ExtruderParams,
    cells_across: usize,
) -> Result<ChannelFlow, ExtruderError> {
    let ch = params.channel()?;
    let h = ch.depth_m;
    let nu = params.melt_viscosity_pa_s / params.melt_density_kg_per_m3;
    let wall = std::f64::consts::PI * params.barrel_diameter_m * ch.helix_angle_rad.cos();
    let base = FlowOptions {
        cells_x: 4,
        cells_y: cells_across,
        length_x: 4.0 * h / cells_across as f64,
        length_y: h,
        kinematic_viscosity: nu,
        sides_x: SidesX::Periodic,
        wall_speed_bottom: 0.0,
        wall_speed_top: wall,
        body_force_x: 0.0,
        ..FlowOptions::default()
    };
    // Start-up after a step of barrel speed, timed on the flow rate.
    let mut flow = Flow::new(base.clone())?;
    let q_steady = wall * h / 2.0;
    let exact = {
        // 1 − 1/e of the analytic start-up, by bisection.
        let target = 1.0 - (-1.0f64).exp();
        let (mut lo, mut hi) = (0.0, h * h / nu);
        for _ in 0..100 {
            let mid = 0.5 * (lo + hi);
            if couette_startup_fraction(mid, h, nu) < target {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        0.5 * (lo + hi)
    };
    let target = (1.0 - (-1.0f64).exp()) * q_steady;
    let mut previous = (0.0, 0.0);
    let mut settle = f64::NAN;
    while flow.time() < 10.0 * exact {
        let dt = flow.stable_dt().min(exact / 200.0);
        flow.step(dt)?;
        let q = flow.flow_rate_x(0);
        if q >= target {
            // Linear between the two samples around the crossing.
            let (t0, q0) = previous;
            settle = t0 + (target - q0) / (q - q0) * (flow.time() - t0);
            break;
        }
        previous = (flow.time(), q);
    }
    flow.run_to_steady(1e-9 * wall / exact, 100.0 * exact)?;
    let drag_ratio = flow.flow_rate_x(0) / q_steady;
    // Pressure flow alone: walls at rest, the gradient as a body force.
    let gradient = 1e6; // Pa/m; the ratio does not depend on it
    let mut pressure = Flow::new(FlowOptions {
        wall_speed_top: 0.0,
        body_force_x: gradient / params.melt_density_kg_per_m3,
        ..base
    })?;
    pressure.run_to_steady(
        1e-9 * gradient * h * h / params.melt_viscosity_pa_s / exact,
        100.0 * exact,
    )?;
    let pressure_ratio =
        pressure.flow_rate_x(0) / (h.powi(3) * gradient / (12.0 * params.melt_viscosity_pa_s));
    Ok(ChannelFlow {
        drag_ratio,
        pressure_ratio,
        settle_time_s: settle,
        settle_time_exact_s: exact,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shape_factors_tend_to_the_flat_channel() {
        assert!((drag_shape_factor(1e-4, 1.0) - 1.0).abs() < 1e-3);
        assert!((pressure_shape_factor(1e-4, 1.0) - 1.0).abs() < 1e-3);
        // Deeper channels lose more to the flight walls, pressure flow faster than drag flow.
        let (fd, fp) = (drag_shape_factor(0.5, 1.0), pressure_shape_factor(0.5, 1.0));
        assert!(fp < fd && fd < 1.0, "{fd} {fp}");
        // A square channel: four copies, each with another wall moving, add up to the whole
        // section moving with the wall, so each carries exactly a quarter: F_d = 1/2.
        assert!((drag_shape_factor(1.0, 1.0) - 0.5).abs() < 1e-7);
        // Poiseuille flow in a square duct, Q = 0.035144 w⁴ G/μ (White, Viscous Fluid Flow).
        assert!((pressure_shape_factor(1.0, 1.0) - 12.0 * 0.035144).abs() < 1e-4);
        // Shallow channels: F_p ≈ 1 − (192/π⁵)·Σ i⁻⁵ · h/w = 1 − 0.6302 h/w.
        let r = 0.02;
        assert!((pressure_shape_factor(r, 1.0) - (1.0 - 0.6302 * r)).abs() < 1e-4);
    }

    #[test]
    fn die_pressure_inverts_die_flow_and_newtonian_is_hagen_poiseuille() {
        let p = ExtruderParams::default();
        for q in [1e-10, 1e-9, 1e-8, 5e-8] {
            assert!((p.die_flow(p.die_pressure(q)) / q - 1.0).abs() < 1e-12);
        }
        let newtonian = ExtruderParams {
            melt_flow_index: 1.0,
            melt_consistency_pa_sn: 800.0,
            ..p
        };
        let r: f64 = 0.0004;
        let hp = std::f64::consts::PI * r.powi(4) / (8.0 * 800.0 * 0.002);
        assert!((newtonian.die_flow(1e6) / (hp * 1e6) - 1.0).abs() < 1e-12);
    }

    /// A Newtonian melt makes the model linear: the step response is exactly first order
    /// with τ = C/(β + k).
    #[test]
    fn newtonian_step_response_is_first_order_with_the_closed_form_tau() {
        let p = ExtruderParams {
            melt_flow_index: 1.0,
            melt_consistency_pa_sn: 800.0,
            ..ExtruderParams::default()
        };
        let ch = p.channel().unwrap();
        let k = p.die_flow(1.0);
        let tau = ch.capacitance_m3_per_pa / (ch.back_flow_m3_per_s_pa + k);
        let response = step_response(&p, 0.5, 1.0, 5.0 * tau, tau / 50.0).unwrap();
        let q0 = response[0].1;
        let q1 = p.die_flow(steady_pressure(&p, &ch, 1.0));
        for &(t, q) in &response {
            let model = q1 + (q0 - q1) * (-t / tau).exp();
            assert!((q - model).abs() < 1e-6 * q1, "t {t}: {q} vs {model}");
        }
        let op = operating_point(&p, q1).unwrap();
        assert!((op.tau_s / tau - 1.0).abs() < 1e-6, "{} vs {tau}", op.tau_s);
        // Steady state: the screw's net flow equals the nozzle's.
        assert!((op.screw_rev_per_s - 1.0).abs() < 1e-3, "{op:?}");
    }

    /// The fitted first-order time constant of a small step matches the linearised τ at that
    /// operating point; a shear-thinning melt responds faster at higher flow.
    #[test]
    fn fitted_tau_matches_the_linearisation() {
        let p = ExtruderParams::default();
        let ch = p.channel().unwrap();
        let mut taus = Vec::new();
        for n in [0.2, 0.8] {
            let q = |rev: f64| p.die_flow(steady_pressure(&p, &ch, rev));
            let op = operating_point(&p, q(n * 1.01)).unwrap();
            let response = step_response(&p, n, n * 1.02, 8.0 * op.tau_s, op.tau_s / 40.0).unwrap();
            let fits = crate::reduced::fit(&crate::reduced::normalise(&response).unwrap());
            let (tau, dead) = fits.first_order.model.first_order();
            assert!(
                (tau / op.tau_s - 1.0).abs() < 0.02,
                "{n}: {tau} vs {}",
                op.tau_s
            );
            assert!(dead < 0.02 * op.tau_s, "{dead}");
            taus.push(tau);
        }
        assert!(taus[1] < taus[0], "{taus:?}");
    }

    /// The unrolled channel by Navier–Stokes: the flat channel's drag and pressure flows, and
    /// its start-up time against the Couette start-up series.
    #[test]
    fn navier_stokes_channel_matches_the_closed_forms() {
        let c = channel_from_navier_stokes(&ExtruderParams::default(), 48).unwrap();
        assert!((c.drag_ratio - 1.0).abs() < 1e-6, "{c:?}");
        assert!((c.pressure_ratio - 1.0).abs() < 1e-3, "{c:?}");
        assert!(
            (c.settle_time_s / c.settle_time_exact_s - 1.0).abs() < 0.01,
            "{c:?}"
        );
        // A melt follows the barrel within a microsecond.
        assert!(c.settle_time_s < 1e-6, "{c:?}");
    }

    #[test]
    fn bad_parameters_are_named() {
        let err = ExtruderParams {
            channel_depth_m: -1.0,
            ..ExtruderParams::default()
        }
        .channel()
        .unwrap_err();
        assert!(err.to_string().contains("channel_depth_m"), "{err}");
        let err = ExtruderParams {
            flight_width_m: 0.1,
            ..ExtruderParams::default()
        }
        .channel()
        .unwrap_err();
        assert!(err.to_string().contains("no channel"), "{err}");
    }
}
