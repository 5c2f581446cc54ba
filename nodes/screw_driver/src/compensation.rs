//! Flow compensation: shape the rpm command so the *delivered* flow, which lags the screw
//! (see [`crate::extruder`]), delivers each move's material.
//!
//! The reduced model is first order in rpm-equivalent units (the flow the nozzle passes,
//! expressed as the rpm that would feed it at steady state): `τ ẏ = u(t − L) − y` with the pin
//! open; with the pin closed nothing leaves and the held pressure leaks back through the screw
//! with `τ_closed`. Because the whole timeline is planned ahead, the command is the model's
//! inverse evaluated ahead of time:
//!
//! * on a grid of `period_s` (split at every pin change), each interval's command is the
//!   exact zero-order-hold inverse that brings the modelled flow to the desired profile at the
//!   interval's end, `u_k = (y*(t_{k+1} + L) − a·y_k)/(1 − a)`, `a = exp(−h/τ)` (this is
//!   pressure advance made exact for a held command: `u ≈ y* + τ ẏ*`);
//! * the command is clamped to `[0, max_rpm]` and to the rpm rate; the material a clamp costs
//!   (and the material that leaked or oozed) is counted and added back to the target over
//!   the next `max(τ, 10·h)`, so each pin-open run delivers what it should wherever the
//!   limits allow.
//!
//! Pure: commands in, commands out; the state carries between chunks like [`PinState`].
//!
//! [`PinState`]: crate::screw::PinState

use crate::screw::{integral, Command};

/// The reduced response the compensation inverts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlowModel {
    /// Time constant of the delivered flow with the pin open.
    pub tau_s: f64,
    /// Dead time before the flow starts to respond.
    pub dead_time_s: f64,
    /// Decay of the held pressure with the pin closed and the screw stopped (back flow).
    pub tau_closed_s: f64,
}

impl FlowModel {
    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [
            ("tau_s", self.tau_s),
            ("dead_time_s", self.dead_time_s),
            ("tau_closed_s", self.tau_closed_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("flow model {name} is {v}: must be finite and >= 0"));
            }
        }
        Ok(())
    }
}

/// The modelled delivery between chunks.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct CompensatorState {
    /// Modelled outlet flow (rpm-equivalent) at `t_s`.
    pub flow_rpm: f64,
    pub t_s: f64,
    /// The last command.
    pub command_rpm: f64,
    /// Desired minus modelled material of the current pin-open run (rpm·s).
    pub owed_rpm_s: f64,
    pub pin_open: bool,
}

/// Limits the command must keep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CommandLimits {
    pub max_rpm: f64,
    /// 0: unlimited.
    pub max_rpm_per_s: f64,
}

/// The exact response of the model over one held interval: returns (flow at the end,
/// material delivered in it).
pub fn hold_interval(
    model: &FlowModel,
    flow: f64,
    command: f64,
    pin_open: bool,
    h: f64,
) -> (f64, f64) {
    if h <= 0.0 {
        return (flow, 0.0);
    }
    if !pin_open {
        let a = if model.tau_closed_s > 0.0 {
            (-h / model.tau_closed_s).exp()
        } else {
            0.0
        };
        return (flow * a, 0.0);
    }
    if model.tau_s <= 0.0 {
        return (command, command * h);
    }
    let a = (-h / model.tau_s).exp();
    let end = command + (flow - command) * a;
    let delivered = command * h + (flow - command) * model.tau_s * (1.0 - a);
    (end, delivered)
}

/// rpm of the linear breakpoint profile at `t` (the later value at a jump).
fn profile_at(profile: &[Command], t: f64) -> f64 {
    let k = profile.partition_point(|c| c.t <= t);
    if k == 0 {
        return profile.first().map_or(0.0, |c| c.rpm);
    }
    if k >= profile.len() {
        return profile.last().map_or(0.0, |c| c.rpm);
    }
    let (a, b) = (&profile[k - 1], &profile[k]);
    if b.t <= a.t {
        return b.rpm;
    }
    a.rpm + (b.rpm - a.rpm) * (t - a.t) / (b.t - a.t)
}

/// Held commands on a grid of `period_s` that make the model deliver `profile` (breakpoints
/// with linear interpolation, as [`crate::screw::breakpoints_from`] returns them).
pub fn compensate(
    profile: &[Command],
    period_s: f64,
    model: &FlowModel,
    limits: &CommandLimits,
    state: &mut CompensatorState,
) -> Vec<Command> {
    let (Some(first), Some(last)) = (profile.first(), profile.last()) else {
        return Vec::new();
    };
    // Grid times: uniform, plus every change of the pin, so the pin is never quantised.
    let mut times: Vec<f64> = Vec::new();
    let n = ((last.t - first.t) / period_s).ceil().max(0.0) as usize;
    times.extend((0..=n).map(|k| first.t + k as f64 * period_s));
    for w in profile.windows(2) {
        if w[0].pin_open != w[1].pin_open {
            times.push(w[1].t);
        }
    }
    times.sort_by(f64::total_cmp);
    times.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
    let recover_s = model.tau_s.max(10.0 * period_s);
    if state.t_s < first.t {
        // The model's state ages to this chunk's start (pin closed between chunks).
        let (flow, _) = hold_interval(model, state.flow_rpm, 0.0, false, first.t - state.t_s);
        state.flow_rpm = flow;
    }
    let mut out = Vec::with_capacity(times.len());
    for w in times.windows(2) {
        let (t0, t1) = (w[0], w[1]);
        let h = t1 - t0;
        if h <= 0.0 {
            continue;
        }
        // The breakpoint in force just after t0 decides the pin and the labels.
        let k = profile.partition_point(|c| c.t <= t0).max(1) - 1;
        let in_force = profile[k];
        let pin_open = in_force.pin_open;
        if pin_open && !state.pin_open {
            state.owed_rpm_s = 0.0;
        }
        let wanted = integral(profile, t0, t1);
        let command = if pin_open {
            let target = profile_at(profile, t1 + model.dead_time_s) + state.owed_rpm_s / recover_s;
            let ideal = if model.tau_s > 0.0 {
                let a = (-h / model.tau_s).exp();
                (target - a * state.flow_rpm) / (1.0 - a)
            } else {
                target
            };
            let mut u = ideal.clamp(0.0, limits.max_rpm);
            if limits.max_rpm_per_s > 0.0 {
                let step = limits.max_rpm_per_s * h;
                u = u
                    .clamp(state.command_rpm - step, state.command_rpm + step)
                    .max(0.0);
            }
            u
        } else {
            0.0
        };
        let (flow, delivered) = hold_interval(model, state.flow_rpm, command, pin_open, h);
        if pin_open {
            state.owed_rpm_s += wanted - delivered;
        }
        state.flow_rpm = flow;
        state.command_rpm = command;
        state.pin_open = pin_open;
        state.t_s = t1;
        out.push(Command {
            t: t0,
            rpm: command,
            pin_open,
            ..in_force
        });
    }
    // The last command holds the final pin state at rest.
    out.push(Command {
        t: times.last().copied().unwrap_or(last.t),
        rpm: 0.0,
        ..*last
    });
    if let Some(c) = out.last() {
        state.command_rpm = c.rpm;
    }
    out
}

/// Material (rpm·s) the model delivers inside each window `[start, end)` when the screw
/// follows held `commands` from `flow_rpm` (rpm-equivalent) at the first command.
pub fn delivered_in_windows(
    commands: &[Command],
    model: &FlowModel,
    windows: &[(f64, f64)],
) -> Vec<f64> {
    let mut out = vec![0.0; windows.len()];
    let mut flow = 0.0;
    for w in commands.windows(2) {
        let (c, t1) = (w[0], w[1].t);
        // Split the interval at window edges inside it: the exact response on each piece.
        let mut cuts: Vec<f64> = vec![c.t, t1];
        let from = windows.partition_point(|win| win.1 <= c.t);
        for win in &windows[from..] {
            if win.0 >= t1 {
                break;
            }
            for edge in [win.0, win.1] {
                if edge > c.t && edge < t1 {
                    cuts.push(edge);
                }
            }
        }
        cuts.sort_by(f64::total_cmp);
        for piece in cuts.windows(2) {
            let (a, b) = (piece[0], piece[1]);
            let (end, delivered) = hold_interval(model, flow, c.rpm, c.pin_open, b - a);
            flow = end;
            let mid = 0.5 * (a + b);
            let i = windows.partition_point(|win| win.1 <= mid);
            if let Some(win) = windows.get(i) {
                if win.0 <= mid && mid < win.1 {
                    out[i] += delivered;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn c(t: f64, rpm: f64, pin_open: bool) -> Command {
        Command {
            t,
            rpm,
            pin_open,
            source_line: 0,
            sequence: 0,
        }
    }

    const MODEL: FlowModel = FlowModel {
        tau_s: 0.05,
        dead_time_s: 0.0,
        tau_closed_s: 0.2,
    };
    const FREE: CommandLimits = CommandLimits {
        max_rpm: 1e9,
        max_rpm_per_s: 0.0,
    };

    #[test]
    fn hold_interval_is_the_exact_first_order_response() {
        let (end, delivered) = hold_interval(&MODEL, 10.0, 100.0, true, 0.03);
        let a = (-0.03f64 / 0.05).exp();
        assert!((end - (100.0 - 90.0 * a)).abs() < 1e-12);
        // ∫ (100 − 90 e^{−t/τ}) dt
        assert!((delivered - (3.0 - 90.0 * 0.05 * (1.0 - a))).abs() < 1e-12);
        let (end, delivered) = hold_interval(&MODEL, 10.0, 100.0, false, 0.2);
        assert!((end - 10.0 * (-1.0f64).exp()).abs() < 1e-12 && delivered == 0.0);
    }

    /// Moves of 100, 250 and 200 rpm (steps between them), 0.1 s each, pin open throughout:
    /// uncompensated, each move misses by the lag; compensated each gets its material.
    #[test]
    fn compensation_delivers_each_move_where_uncompensated_lags() {
        let profile = vec![
            c(0.0, 0.0, true),
            c(0.0, 100.0, true),
            c(0.1, 100.0, true),
            c(0.1, 250.0, true),
            c(0.2, 250.0, true),
            c(0.2, 200.0, true),
            c(0.3, 200.0, true),
            c(0.3, 0.0, false),
        ];
        let windows = [(0.0, 0.1), (0.1, 0.2), (0.2, 0.3)];
        let want = [10.0, 25.0, 20.0];
        let plain = crate::screw::smooth(&profile, &[1.0], 0.001);
        let got = delivered_in_windows(&plain, &MODEL, &windows);
        let worst_plain = got
            .iter()
            .zip(&want)
            .map(|(g, w)| (g / w - 1.0).abs())
            .fold(0.0, f64::max);
        assert!(worst_plain > 0.3, "the lag costs a lot: {got:?}");
        let mut state = CompensatorState::default();
        let commands = compensate(&profile, 0.001, &MODEL, &FREE, &mut state);
        let got = delivered_in_windows(&commands, &MODEL, &windows);
        for (g, w) in got.iter().zip(&want) {
            assert!((g / w - 1.0).abs() < 0.01, "{got:?}");
        }
        assert!(commands.iter().all(|c| c.rpm >= 0.0));
    }

    /// With an rpm ceiling the clamp's deficit is paid back later in the run.
    #[test]
    fn a_clamp_is_paid_back_within_the_run() {
        let profile = vec![
            c(0.0, 0.0, true),
            c(0.0, 200.0, true),
            c(1.0, 200.0, true),
            c(1.0, 0.0, false),
        ];
        let limits = CommandLimits {
            max_rpm: 260.0,
            max_rpm_per_s: 0.0,
        };
        let mut state = CompensatorState::default();
        let commands = compensate(&profile, 0.002, &MODEL, &limits, &mut state);
        assert!(commands.iter().all(|c| c.rpm <= 260.0));
        let got = delivered_in_windows(&commands, &MODEL, &[(0.0, 1.0)]);
        assert!((got[0] / 200.0 - 1.0).abs() < 0.01, "{got:?}");
    }
}
