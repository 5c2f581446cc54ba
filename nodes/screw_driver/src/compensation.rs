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
    /// The reduced model of an extruder linearised at outlet flow `flow_m3_per_s`: the
    /// first-order τ there (its fitted dead time is below a microsecond: none), and the
    /// closed pin's leak through the screw, C/β.
    pub fn from_extruder(
        params: &crate::extruder::ExtruderParams,
        flow_m3_per_s: f64,
    ) -> Result<FlowModel, crate::extruder::ExtruderError> {
        let channel = params.channel()?;
        let op = crate::extruder::operating_point(params, flow_m3_per_s)?;
        Ok(FlowModel {
            tau_s: op.tau_s,
            dead_time_s: 0.0,
            tau_closed_s: channel.capacitance_m3_per_pa / channel.back_flow_m3_per_s_pa,
        })
    }

    /// The default model: the default extruder at 100 rpm of the screw driver's default
    /// calibration (e_per_rev 2 mm of 1.75 mm filament: 8.0 mm³/s).
    pub fn default_extruder() -> FlowModel {
        let area = std::f64::consts::PI * (1.75e-3f64 / 2.0).powi(2);
        FlowModel::from_extruder(
            &crate::extruder::ExtruderParams::default(),
            100.0 * 0.002 * area / 60.0,
        )
        .expect("the default extruder parameters are valid")
    }

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
    /// Desired minus modelled material of the current move (rpm·s).
    pub owed_rpm_s: f64,
    /// Whether material flowed in the last interval.
    pub pin_open: bool,
    /// The pin's state at the end of the last chunk, and when it last opened.
    pub valve_open: bool,
    pub opened_at_s: f64,
}

/// One interval of the command grid.
#[derive(Clone, Copy, Debug)]
struct Interval {
    t0: f64,
    t1: f64,
    /// The breakpoint in force at its start: pin command, labels.
    in_force: Command,
    /// The pin open and past its opening delay: material can leave.
    flowing: bool,
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

/// rpm of the linear breakpoint profile arriving at `t` (the earlier value at a jump: where
/// the pin closes, the flow the pin cuts).
fn profile_at(profile: &[Command], t: f64) -> f64 {
    let k = profile.partition_point(|c| c.t < t);
    if k == 0 {
        return profile.first().map_or(0.0, |c| c.rpm);
    }
    if k >= profile.len() {
        return profile.last().map_or(0.0, |c| c.rpm);
    }
    let (a, b) = (&profile[k - 1], &profile[k]);
    if b.t <= t || b.t <= a.t {
        return b.rpm;
    }
    a.rpm + (b.rpm - a.rpm) * (t - a.t) / (b.t - a.t)
}

/// Held commands on a grid of `period_s` that make the model deliver `profile` (breakpoints
/// with linear interpolation, as [`crate::screw::breakpoints_from`] returns them).
///
/// The modelled flow can fall no faster than it drains with the screw stopped, so before the
/// forward pass the target flow at each grid point is capped from behind (`y*_k ≤
/// y*_{k+1}/a`): the flow starts to fall early enough to meet a lower flow ahead (a prime
/// followed by a fine line). What a cap takes from a move is added back to the same move's
/// earlier, uncapped points; what still cannot be placed is owed to the rest of the run.
pub fn compensate(
    profile: &[Command],
    period_s: f64,
    model: &FlowModel,
    limits: &CommandLimits,
    pin_open_delay_s: f64,
    state: &mut CompensatorState,
) -> Vec<Command> {
    let (Some(first), Some(last)) = (profile.first(), profile.last()) else {
        return Vec::new();
    };
    // Grid times: every change of the pin (never quantised), the moment material can flow
    // after an opening, and a uniform grid while the pin is open (a closed pin, however long,
    // is one interval).
    let mut times: Vec<f64> = vec![first.t, last.t];
    let mut open_since = first.pin_open.then_some(first.t);
    let grid = |from: f64, to: f64, times: &mut Vec<f64>| {
        let n = ((to - from) / period_s).ceil().max(0.0) as usize;
        times.extend((0..n).map(|k| from + k as f64 * period_s));
    };
    for w in profile.windows(2) {
        if w[0].pin_open != w[1].pin_open {
            times.push(w[1].t);
            if w[1].pin_open {
                times.push(w[1].t + pin_open_delay_s);
                open_since = Some(w[1].t);
            } else if let Some(from) = open_since.take() {
                grid(from, w[1].t, &mut times);
            }
        }
    }
    if let Some(from) = open_since {
        grid(from, last.t, &mut times);
    }
    times.sort_by(f64::total_cmp);
    times.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
    let recover_s = model.tau_s.max(10.0 * period_s);
    if state.t_s < first.t {
        // The model's state ages to this chunk's start (pin closed between chunks).
        let (flow, _) = hold_interval(model, state.flow_rpm, 0.0, false, first.t - state.t_s);
        state.flow_rpm = flow;
    }
    // The intervals, each with the breakpoint in force just after its start (pin, labels),
    // and whether material can flow (the pin open for its delay).
    let mut opened_at = state.opened_at_s;
    let mut was_open = state.valve_open;
    let intervals: Vec<Interval> = times
        .windows(2)
        .filter(|w| w[1] > w[0])
        .map(|w| {
            let k = profile.partition_point(|c| c.t <= w[0]).max(1) - 1;
            let c = profile[k];
            if c.pin_open && !was_open {
                opened_at = w[0];
            }
            was_open = c.pin_open;
            Interval {
                t0: w[0],
                t1: w[1],
                in_force: c,
                flowing: c.pin_open && w[0] >= opened_at + pin_open_delay_s - 1e-12,
            }
        })
        .collect();
    state.opened_at_s = opened_at;
    let (targets, capped, planned) =
        shaped_targets(profile, &intervals, model, limits, state.flow_rpm);
    let mut sequence = None;
    let mut out = Vec::with_capacity(intervals.len() + 1);
    for (k, iv) in intervals.iter().enumerate() {
        let (t0, t1, in_force) = (iv.t0, iv.t1, iv.in_force);
        let h = t1 - t0;
        let pin_open = iv.flowing;
        // Material is owed within a move, never shifted into the next one.
        if pin_open && !state.pin_open || sequence != Some(in_force.sequence) {
            state.owed_rpm_s = 0.0;
            sequence = Some(in_force.sequence);
        }
        // The shaped plan's material in this interval: what is owed is the shortfall against
        // the plan (rate limits, a state that differs), not against the unshaped profile.
        let wanted = planned[k];
        let command = if pin_open {
            // Where the target is capped (the flow must fall), owing changes nothing.
            let owed = if capped[k] {
                0.0
            } else {
                state.owed_rpm_s / recover_s
            };
            let target = targets[k] + owed;
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
            ..in_force
        });
    }
    // The last command holds the final pin state at rest.
    out.push(Command {
        t: times.last().copied().unwrap_or(last.t),
        rpm: 0.0,
        ..*last
    });
    // A chunk cut inside a run (a full buffer, a stall) is continued by the next chunk at
    // this same instant: the rate limit goes on from the last command the run played, not
    // from the rest command above, which is in force for no time unless input stops.
    if !last.pin_open {
        state.command_rpm = 0.0;
    }
    state.valve_open = last.pin_open;
    state.pin_open = state.pin_open && last.pin_open;
    out
}

/// The flow to reach at the end of each interval, and which intervals are capped.
///
/// The desired flow (ahead by the dead time), except before a move that wants less than the
/// melt would ooze into it: with the screw stopped a move of duration T starting at flow y
/// gets at least `y·τ·(1 − e^{−T/τ})`, so its start must be at most `V/(τ(1 − e^{−T/τ}))`,
/// and at most what drains to the next move's bound in T. Grid points before such a bound
/// are capped by it (grown by e^{Δt/τ} going back), and each move's capped material is
/// moved to its earlier, uncapped points.
fn shaped_targets(
    profile: &[Command],
    intervals: &[Interval],
    model: &FlowModel,
    limits: &CommandLimits,
    start_flow: f64,
) -> (Vec<f64>, Vec<bool>, Vec<f64>) {
    let mut targets: Vec<f64> = intervals
        .iter()
        .map(|iv| profile_at(profile, iv.t1 + model.dead_time_s))
        .collect();
    let mut capped = vec![false; targets.len()];
    let tau = model.tau_s;
    if tau <= 0.0 || intervals.is_empty() {
        let planned = intervals
            .iter()
            .map(|iv| {
                if iv.flowing {
                    integral(profile, iv.t0, iv.t1)
                } else {
                    0.0
                }
            })
            .collect();
        return (targets, capped, planned);
    }
    // Moves on the grid: runs of intervals with one sequence (start, end, wanted, open).
    let mut groups: Vec<(usize, usize, f64, bool)> = Vec::new();
    for (k, iv) in intervals.iter().enumerate() {
        let wanted = if iv.flowing {
            integral(profile, iv.t0, iv.t1)
        } else {
            0.0
        };
        match groups.last_mut() {
            Some(g)
                if intervals[g.0].in_force.sequence == iv.in_force.sequence
                    && g.3 == iv.flowing =>
            {
                g.1 = k + 1;
                g.2 += wanted;
            }
            _ => groups.push((k, k + 1, wanted, iv.flowing)),
        }
    }
    // Backward over moves: the highest flow each may start at.
    let mut bound = vec![f64::INFINITY; groups.len()];
    for j in (0..groups.len()).rev() {
        let (a, b, wanted, open) = groups[j];
        if !open {
            continue;
        }
        let duration = intervals[b - 1].t1 - intervals[a].t0;
        let decay = (-duration / tau).exp();
        let own = wanted.max(0.0) / (tau * (1.0 - decay)).max(f64::MIN_POSITIVE);
        let next = match groups.get(j + 1) {
            Some(g) if g.3 => bound[j + 1] / decay,
            _ => f64::INFINITY,
        };
        bound[j] = own.min(next);
    }
    let apply_caps = |targets: &mut [f64], capped: &mut [bool]| {
        for j in 1..groups.len() {
            let (a, _, _, open) = groups[j];
            let (pa, pb, _, prev_open) = groups[j - 1];
            if !open || !prev_open || !bound[j].is_finite() {
                continue;
            }
            let boundary = intervals[a].t0;
            for k in (pa..pb).rev() {
                let cap = bound[j] * ((boundary - intervals[k].t1) / tau).exp();
                if cap > 1e12 {
                    break; // grown past any flow
                }
                if targets[k] > cap {
                    targets[k] = cap;
                    capped[k] = true;
                }
            }
        }
    };
    let mut saturated = vec![false; targets.len()];
    for _pass in 0..12 {
        apply_caps(&mut targets, &mut capped);
        // Per move: what the targets deliver (the command within its limits) against what
        // it wants, the difference spread over its points that are neither capped nor at
        // the rpm limit.
        let mut flow = start_flow;
        for &(a, b, wanted, open) in &groups {
            let mut got = 0.0;
            let mut free_s = 0.0;
            for k in a..b {
                let h = intervals[k].t1 - intervals[k].t0;
                if open {
                    let decay = (-h / tau).exp();
                    let ideal = (targets[k] - decay * flow) / (1.0 - decay);
                    saturated[k] = ideal > limits.max_rpm;
                    let u = ideal.clamp(0.0, limits.max_rpm);
                    let (end, delivered) = hold_interval(model, flow, u, true, h);
                    got += delivered;
                    flow = end;
                    if !capped[k] && !saturated[k] {
                        free_s += h;
                    }
                } else {
                    flow = hold_interval(model, flow, 0.0, false, h).0;
                }
            }
            if open && free_s > 0.0 && (wanted - got).abs() > 1e-12 * wanted.abs().max(1.0) {
                let add = (wanted - got) / free_s;
                for k in a..b {
                    if !capped[k] && !saturated[k] {
                        targets[k] = (targets[k] + add).max(0.0);
                    }
                }
            }
        }
    }
    apply_caps(&mut targets, &mut capped);
    // The material the final targets deliver, interval by interval.
    let mut planned = vec![0.0; targets.len()];
    let mut flow = start_flow;
    for (k, iv) in intervals.iter().enumerate() {
        let h = iv.t1 - iv.t0;
        if iv.flowing {
            let decay = (-h / tau).exp();
            let u = ((targets[k] - decay * flow) / (1.0 - decay)).clamp(0.0, limits.max_rpm);
            let (end, delivered) = hold_interval(model, flow, u, true, h);
            planned[k] = delivered;
            flow = end;
        } else {
            flow = hold_interval(model, flow, 0.0, false, h).0;
        }
    }
    (targets, capped, planned)
}

/// Material (rpm·s) the model delivers inside each window `[start, end)` when the screw
/// follows held `commands` from `flow_rpm` (rpm-equivalent) at the first command.
pub fn delivered_in_windows(
    commands: &[Command],
    model: &FlowModel,
    pin_open_delay_s: f64,
    windows: &[(f64, f64)],
) -> Vec<f64> {
    let mut out = vec![0.0; windows.len()];
    let mut flow = 0.0;
    let mut opened_at = f64::NEG_INFINITY;
    let mut was_open = false;
    for w in commands.windows(2) {
        let (c, t1) = (w[0], w[1].t);
        if c.pin_open && !was_open {
            opened_at = c.t;
        }
        was_open = c.pin_open;
        let flows_from = opened_at + pin_open_delay_s;
        // Split the interval at window edges and where flow starts: the exact response on
        // each piece.
        let mut cuts: Vec<f64> = vec![c.t, t1];
        if c.pin_open && flows_from > c.t && flows_from < t1 {
            cuts.push(flows_from);
        }
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
            let flowing = c.pin_open && a >= flows_from - 1e-12;
            let (end, delivered) = hold_interval(model, flow, c.rpm, flowing, b - a);
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
    /// A prime followed by a fine line: the flow falls before the line starts.
    #[test]
    fn compensation_delivers_each_move_where_uncompensated_lags() {
        // Each move its own sequence, as breakpoints label them.
        let m = |t, rpm, pin_open, sequence| Command {
            sequence,
            ..c(t, rpm, pin_open)
        };
        let profile = vec![
            m(0.0, 0.0, true, 1),
            m(0.0, 100.0, true, 1),
            m(0.1, 100.0, true, 1),
            m(0.1, 250.0, true, 2),
            m(0.2, 250.0, true, 2),
            m(0.2, 200.0, true, 3),
            m(0.3, 200.0, true, 3),
            m(0.3, 0.0, false, 4),
        ];
        let windows = [(0.0, 0.1), (0.1, 0.2), (0.2, 0.3)];
        let want = [10.0, 25.0, 20.0];
        let plain = crate::screw::smooth(&profile, &[1.0], 0.001);
        let got = delivered_in_windows(&plain, &MODEL, 0.0, &windows);
        let worst_plain = got
            .iter()
            .zip(&want)
            .map(|(g, w)| (g / w - 1.0).abs())
            .fold(0.0, f64::max);
        assert!(worst_plain > 0.3, "the lag costs a lot: {got:?}");
        let mut state = CompensatorState::default();
        let commands = compensate(&profile, 0.001, &MODEL, &FREE, 0.0, &mut state);
        let got = delivered_in_windows(&commands, &MODEL, 0.0, &windows);
        for (g, w) in got.iter().zip(&want) {
            assert!((g / w - 1.0).abs() < 0.01, "{got:?}");
        }
        assert!(commands.iter().all(|c| c.rpm >= 0.0));
    }

    /// A run cut into two chunks (a full buffer) with a rate limit: the second chunk goes on
    /// from the first one's last command, as the run in one piece does, instead of ramping up
    /// again from rest (with 200 rpm/s it did: the second move got 94.2 rpm·s where the run in
    /// one piece delivers 108.8).
    #[test]
    fn a_rate_limited_run_continues_across_a_chunk_cut() {
        let limits = CommandLimits {
            max_rpm: 1e9,
            max_rpm_per_s: 200.0,
        };
        // Two moves of 1 s each at 100 rpm; chunks are cut between moves.
        let m = |t, rpm, pin_open, sequence| Command {
            sequence,
            ..c(t, rpm, pin_open)
        };
        let first_half = vec![
            m(0.0, 0.0, true, 1),
            m(0.0, 100.0, true, 1),
            m(1.0, 100.0, true, 1),
        ];
        let second_half = vec![
            m(1.0, 100.0, true, 2),
            m(2.0, 100.0, true, 2),
            m(2.0, 0.0, false, 3),
        ];
        let whole: Vec<Command> = first_half.iter().chain(&second_half).copied().collect();
        let mut state = CompensatorState::default();
        let one_piece = compensate(&whole, 0.002, &MODEL, &limits, 0.0, &mut state);
        let mut state = CompensatorState::default();
        let mut cut = compensate(&first_half, 0.002, &MODEL, &limits, 0.0, &mut state);
        assert!(state.command_rpm > 50.0, "{state:?}");
        cut.extend(compensate(
            &second_half,
            0.002,
            &MODEL,
            &limits,
            0.0,
            &mut state,
        ));
        // The second move's material, and its first half, where the old cut ramped.
        for window in [(1.0, 2.0), (1.0, 1.5)] {
            let want = delivered_in_windows(&one_piece, &MODEL, 0.0, &[window])[0];
            let got = delivered_in_windows(&cut, &MODEL, 0.0, &[window])[0];
            assert!(
                (got / want - 1.0).abs() < 1e-3,
                "{window:?}: cut {got} vs one piece {want} rpm·s"
            );
        }
        // And the limit holds across the cut: the held commands either side of t = 1 s.
        let around: Vec<f64> = cut
            .iter()
            .filter(|k| (k.t - 1.0).abs() < 0.003 && k.rpm > 0.0)
            .map(|k| k.rpm)
            .collect();
        for w in around.windows(2) {
            assert!((w[1] - w[0]).abs() <= 200.0 * 0.002 + 1e-9, "{around:?}");
        }
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
        let commands = compensate(&profile, 0.002, &MODEL, &limits, 0.0, &mut state);
        assert!(commands.iter().all(|c| c.rpm <= 260.0));
        let got = delivered_in_windows(&commands, &MODEL, 0.0, &[(0.0, 1.0)]);
        assert!((got[0] / 200.0 - 1.0).abs() < 0.01, "{got:?}");
    }
}

/// What one extruding move asked for and what the model delivered (rpm·s; × e_rev/60 for
/// filament length).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MoveMaterial {
    pub sequence: u64,
    pub source_line: u32,
    pub wanted_rpm_s: f64,
    pub delivered_rpm_s: f64,
}

impl MoveMaterial {
    /// Delivered over wanted, minus one.
    pub fn error(&self) -> f64 {
        self.delivered_rpm_s / self.wanted_rpm_s - 1.0
    }
}

/// The material each extruding move gets through `model` when the screw follows the
/// commands `options` produce for `moves` (one chunk, the whole run), on a grid of
/// `period_s`. A move's window runs from its first trajectory point to the next move's.
pub fn material_per_move(
    moves: &[crate::screw::TimedMove],
    options: &crate::screw::ScrewOptions,
    model: &FlowModel,
    period_s: f64,
) -> Vec<MoveMaterial> {
    let commands = crate::screw::chunk_commands(
        moves,
        options,
        &mut crate::screw::PinState::default(),
        true,
        period_s,
    );
    let e_per_rev_m = match options.model {
        crate::screw::RpmModel::PolarSpeed { e_per_rev_m } => e_per_rev_m,
        crate::screw::RpmModel::Radius { .. } => return Vec::new(),
    };
    material_of_commands(
        moves,
        &commands,
        model,
        options.pin_open_delay_s,
        e_per_rev_m,
    )
}

/// What held `commands` (a screw's commands as it received them: each held to the next)
/// deliver through `model` to each extruding move of `moves` (a print's, from its start),
/// against what the move wants: its ΔE as the screw feeds it, net of retractions
/// ([`crate::screw::as_fed`]; `e_per_rev_m` of filament-equivalent per revolution).
pub fn material_of_commands(
    moves: &[crate::screw::TimedMove],
    commands: &[Command],
    model: &FlowModel,
    pin_open_delay_s: f64,
    e_per_rev_m: f64,
) -> Vec<MoveMaterial> {
    let moves = &crate::screw::as_fed(moves)[..];
    let mut windows = Vec::new();
    let mut which = Vec::new();
    for (k, m) in moves.iter().enumerate() {
        let (Some(&t0), Some(&t1)) = (m.t.first(), m.t.last()) else {
            continue;
        };
        // (An unretraction that only repays a retraction wants nothing: no window.)
        if !m.extrude || m.delta_e_m <= 0.0 || t1 <= t0 {
            continue;
        }
        let end = moves[k + 1..]
            .iter()
            .find_map(|n| n.t.first().copied())
            .unwrap_or(f64::INFINITY)
            .max(t1);
        windows.push((t0, end));
        which.push(k);
    }
    let delivered = delivered_in_windows(commands, model, pin_open_delay_s, &windows);
    which
        .iter()
        .zip(delivered)
        .map(|(&k, delivered_rpm_s)| MoveMaterial {
            sequence: moves[k].sequence,
            source_line: moves[k].source_line,
            wanted_rpm_s: moves[k].delta_e_m * 60.0 / e_per_rev_m,
            delivered_rpm_s,
        })
        .collect()
}

#[cfg(test)]
mod prime_tests {
    use super::*;

    /// A prime of 33 rpm·s over 0.42 s, then a fine line wanting 0.14 rpm·s in 70 ms: the
    /// pressure the prime builds would ooze far more than that into the line, so the flow
    /// must fall before the prime ends, and the prime still gets its material.
    #[test]
    fn a_prime_drains_before_a_fine_line() {
        let c = |t, rpm, pin_open, sequence| Command {
            t,
            rpm,
            pin_open,
            source_line: 0,
            sequence,
        };
        let (t, r) = (0.42, 33.0 / 0.42);
        let profile = vec![
            c(-0.25, 0.0, true, 1),
            c(0.0, 0.0, true, 1),
            c(0.0, r, true, 1),
            c(t, r, true, 1),
            c(t, 2.0, true, 2),
            c(t + 0.07, 2.0, true, 2),
            c(t + 0.07, 0.0, false, 3),
        ];
        let model = FlowModel {
            tau_s: 0.03,
            dead_time_s: 0.0,
            tau_closed_s: 0.17,
        };
        let limits = CommandLimits {
            max_rpm: 300.0,
            max_rpm_per_s: 0.0,
        };
        let windows = [(0.0, t), (t, t + 0.07)];
        let plain = crate::screw::smooth(&profile, &[1.0], 0.002);
        let lagging = delivered_in_windows(&plain, &model, 0.25, &windows);
        assert!(
            lagging[1] / 0.14 > 10.0,
            "the ooze swamps the line: {lagging:?}"
        );
        let mut state = CompensatorState::default();
        let out = compensate(&profile, 0.002, &model, &limits, 0.25, &mut state);
        let got = delivered_in_windows(&out, &model, 0.25, &windows);
        assert!((got[0] / 33.0 - 1.0).abs() < 0.01, "{got:?}");
        assert!((got[1] / 0.14 - 1.0).abs() < 0.01, "{got:?}");
        // Nothing turns during the pin's opening delay, nothing beyond the limit.
        assert!(out.iter().filter(|c| c.t < 0.0).all(|c| c.rpm == 0.0));
        assert!(out.iter().all(|c| (0.0..=300.0).contains(&c.rpm)));
    }
}
