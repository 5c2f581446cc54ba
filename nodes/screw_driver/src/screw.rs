//! Screw rpm and pin commands from moves and their planned timing.
//!
//! * Pin: open while a move feeds material (ΔE > 0), closed otherwise (travel, retraction).
//!   The pin needs `pin_open_delay_s` before material flows (seed 000 §5.3):
//!   - [`PinStrategy::Stop`]: the planner rests the stage for the delay at the start of each
//!     extruding move that follows a non-extruding one; the pin opens when that rest begins;
//!   - [`PinStrategy::Lookahead`]: the pin opens the delay before the extruding move starts to
//!     move, from the planned timeline, so the stage never stops.
//! * rpm, [`RpmModel::Radius`]: seed 000 eq. (9), `SNW = γ·F·r·ΔE/√(Δx²+Δy²)` in the seed's
//!   units (F mm/min, r mm at the middle of the move, ΔE and Δx, Δy mm), constant while the
//!   move moves.
//! * rpm, [`RpmModel::PolarSpeed`]: eq. (8) done right: `rpm(t) = 60·v(t)·(ΔE/ΔS)/e_rev` with
//!   the planner's exact tool speed `v(t)` (linear in time between trajectory points, as the
//!   plan accelerates uniformly along the path), `ΔS` the move's length and `e_rev` the
//!   filament length one screw revolution feeds. Integrated over a move this feeds exactly
//!   the move's ΔE.
//!
//! Commands are breakpoints with linear interpolation of rpm between them (first-order hold),
//! which reproduces the linear speed profile exactly. With smoothing, rpm is first averaged
//! exactly over a uniform grid, filtered without delay, and held per grid interval.

use crate::compensation::{CompensatorState, FlowModel};
use crate::fir::filter_zero_phase;
use crate::joint::Hold;

/// How rpm follows the plan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RpmModel {
    /// Seed eq. (9) with its calibration constant γ.
    Radius { gamma: f64 },
    /// Exact tool speed; `e_per_rev_m` of filament-equivalent per revolution.
    PolarSpeed { e_per_rev_m: f64 },
}

/// How the pin's opening delay is absorbed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PinStrategy {
    Stop,
    Lookahead,
}

#[derive(Clone, Debug, PartialEq)]
pub struct ScrewOptions {
    pub model: RpmModel,
    pub pin_open_delay_s: f64,
    pub strategy: PinStrategy,
    pub max_rpm: f64,
    /// Largest rpm change per second; 0: unlimited. Where it would be exceeded the command is
    /// lowered, so rpm steps (between moves of different ΔE/ΔS) become ramps that feed less.
    pub max_rpm_per_s: f64,
    /// Zero-phase FIR taps applied on a uniform grid of `smoothing_period_s`; `None`: off.
    pub smoothing: Option<Vec<f64>>,
    pub smoothing_period_s: f64,
    /// Shape rpm so the lagging flow delivers each move's material ([`crate::compensation`]);
    /// `None`: rpm as if flow followed at once.
    pub compensation: Option<FlowModel>,
    /// Grid of the compensated commands (each held over its interval).
    pub compensation_period_s: f64,
}

impl Default for ScrewOptions {
    fn default() -> Self {
        ScrewOptions {
            model: RpmModel::PolarSpeed { e_per_rev_m: 0.002 },
            pin_open_delay_s: 0.25,
            strategy: PinStrategy::Lookahead,
            max_rpm: 300.0,
            max_rpm_per_s: 0.0,
            smoothing: None,
            smoothing_period_s: 0.001,
            compensation: None,
            compensation_period_s: 0.002,
        }
    }
}

/// A move with its planned timing, as the screw needs it.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct TimedMove {
    pub sequence: u64,
    pub source_line: u32,
    pub extrude: bool,
    pub delta_e_m: f64,
    /// 3-D length and xy length of the commanded segment (m).
    pub length_m: f64,
    pub length_xy_m: f64,
    pub feedrate_m_per_s: f64,
    /// Distance from the centre of the segment's midpoint (m).
    pub mid_radius_m: f64,
    /// Planned times (s) and tool speeds (m/s) at the trajectory points.
    pub t: Vec<f64>,
    pub speed: Vec<f64>,
    /// When the stage starts moving for this move (after a pin rest, say).
    pub motion_start_s: f64,
}

impl TimedMove {
    /// From a move, where it starts (the previous move's target), and its planned
    /// `JointTrajectory` (joints `bed_theta`, `arm_r`, `z`): the tool speed at each point is
    /// exact from the joint velocities, `√(ṙ² + r²θ̇² + ż²)`. Times are seconds after
    /// `base_ns` (a stamp in ns): wall-clock epochs as f64 seconds would resolve only ~0.2 µs.
    pub fn from_trajectory(
        m: &polar_cell_msgs::GcodeMove,
        from: [f64; 3],
        trajectory: &polar_cell_msgs::JointTrajectory,
        base_ns: i64,
    ) -> TimedMove {
        let t0 = (trajectory.header.stamp.as_nanos() - base_ns) as f64 * 1e-9;
        let mut t = Vec::with_capacity(trajectory.points.len());
        let mut speed = Vec::with_capacity(trajectory.points.len());
        let mut motion_start_s = f64::NAN;
        for p in &trajectory.points {
            let time = t0 + p.time_from_start.as_secs_f64();
            let (q, qd) = (&p.positions, &p.velocities);
            let v = if q.len() == 3 && qd.len() == 3 {
                (qd[1] * qd[1] + (q[1] * qd[0]).powi(2) + qd[2] * qd[2]).sqrt()
            } else {
                0.0
            };
            t.push(time);
            speed.push(v);
        }
        // Motion starts at the last point before the joints first move.
        let moved = |a: &[f64], b: &[f64]| a.iter().zip(b).any(|(x, y)| (x - y).abs() > 1e-15);
        for (k, w) in trajectory.points.windows(2).enumerate() {
            if moved(&w[0].positions, &w[1].positions) {
                motion_start_s = t[k];
                break;
            }
        }
        if motion_start_s.is_nan() {
            motion_start_s = t.first().copied().unwrap_or(0.0);
        }
        let to = [m.x_m, m.y_m, m.z_m];
        let d = [to[0] - from[0], to[1] - from[1], to[2] - from[2]];
        let mid = [(to[0] + from[0]) / 2.0, (to[1] + from[1]) / 2.0];
        // (As the planner has it: closer than NO_PATH_M is no path, and feeds in place.)
        let path = |length_m: f64| {
            if length_m < polar_cell_msgs::GcodeMove::NO_PATH_M {
                0.0
            } else {
                length_m
            }
        };
        TimedMove {
            sequence: m.sequence,
            source_line: m.source_line,
            // Feeding needs both: a move flagged as extruding that takes material back (any
            // publisher can send one) must not run the screw backwards with the pin open.
            extrude: m.extrude && m.delta_e_m > 0.0,
            delta_e_m: m.delta_e_m,
            length_m: path((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()),
            length_xy_m: path(d[0].hypot(d[1])),
            feedrate_m_per_s: m.feedrate_m_per_s,
            mid_radius_m: mid[0].hypot(mid[1]),
            t,
            speed,
            motion_start_s,
        }
    }
}

/// Where the tool is after `m`, from `from`: the target of a move that goes somewhere (a
/// line, an arc chord, a home); dwells and G92 leave it where it was.
pub fn position_after(m: &polar_cell_msgs::GcodeMove, from: [f64; 3]) -> [f64; 3] {
    use polar_cell_msgs::GcodeMove as M;
    match m.kind {
        M::KIND_RAPID | M::KIND_LINEAR | M::KIND_ARC_CW | M::KIND_ARC_CCW | M::KIND_HOME => {
            [m.x_m, m.y_m, m.z_m]
        }
        _ => from,
    }
}

/// One command breakpoint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Command {
    pub t: f64,
    pub rpm: f64,
    pub pin_open: bool,
    pub source_line: u32,
    /// The move the command belongs to (orders commands at the same instant).
    pub sequence: u64,
}

/// rpm of move `m` at tool speed `speed` (the radius model ignores the speed).
fn rpm_at(m: &TimedMove, speed: f64, options: &ScrewOptions) -> f64 {
    if !m.extrude {
        return 0.0;
    }
    if m.length_m <= 0.0 {
        // Feeding in place (a prime): ΔE over the planned duration of the move.
        let duration = m.t.last().unwrap_or(&0.0) - m.motion_start_s;
        return match options.model {
            RpmModel::PolarSpeed { e_per_rev_m } if duration > 0.0 => {
                60.0 * m.delta_e_m / duration / e_per_rev_m
            }
            _ => 0.0,
        };
    }
    match options.model {
        RpmModel::PolarSpeed { e_per_rev_m } => {
            60.0 * speed * (m.delta_e_m / m.length_m) / e_per_rev_m
        }
        RpmModel::Radius { gamma } => {
            if m.length_xy_m <= 0.0 {
                return 0.0;
            }
            // The seed's units: mm/min, mm.
            gamma
                * (m.feedrate_m_per_s * 60_000.0)
                * (m.mid_radius_m * 1000.0)
                * (m.delta_e_m * 1000.0)
                / (m.length_xy_m * 1000.0)
        }
    }
}

/// The pin's state between chunks of moves processed separately.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinState {
    /// The last move with a duration fed material (the pin is open).
    pub extruding: bool,
    /// When the pin last closed.
    pub closed_at: f64,
    /// The modelled delivery, for flow compensation across chunks.
    pub delivery: CompensatorState,
    /// Filament the G-code has retracted and not yet pushed back (m of E, ≥ 0): see
    /// [`fed_after_retractions`].
    pub retracted_m: f64,
    /// The last breakpoint (s, rpm) of the rate-limited profile so far: the next chunk's
    /// rpm rises from it no faster than `max_rpm_per_s`, as in one piece.
    pub last_breakpoint: Option<(f64, f64)>,
}

impl Default for PinState {
    fn default() -> Self {
        PinState {
            extruding: false,
            closed_at: f64::NEG_INFINITY,
            delivery: CompensatorState::default(),
            retracted_m: 0.0,
            last_breakpoint: None,
        }
    }
}

/// Less than this of E left to feed after a retraction is repaid is nothing: the rounding of
/// E from millimetres (a retraction and its exact undoing cancel to about 1e-19 m).
const FED_NOTHING_M: f64 = 1e-12;

/// Most retracted E carried (m): any G-code's retractions stay far below; a sum of absurd
/// ones must not reach infinity, which no checkpoint could carry.
const MAX_RETRACTED_M: f64 = 1e3;

/// `moves` (a print's, from its start) as the screw feeds them: see [`fed_after_retractions`].
pub fn as_fed(moves: &[TimedMove]) -> Vec<TimedMove> {
    let mut retracted_m = 0.0;
    moves
        .iter()
        .map(|m| fed_after_retractions(m, &mut retracted_m).unwrap_or_else(|| m.clone()))
        .collect()
}

/// `m` as the screw feeds it. A retraction (ΔE < 0) takes nothing back here: the pin closes
/// and keeps the melt where it is. So the ΔE that later pushes the filament back (a
/// slicer's unretract, `G1 E0.1` after `G1 E-1`) is first set against what was retracted,
/// and only the rest is fed: the screw delivers the G-code's net E, not the unretract's
/// length on top (polartest.gcode: 51.34 mm of positive ΔE for a net 44.34 mm). The move
/// stays an extruding one for the pin, as the planner has it (its pin rest under `stop`
/// comes before it, and none before the line after it), even when it feeds nothing.
/// `None`: the move as it is.
fn fed_after_retractions(m: &TimedMove, retracted_m: &mut f64) -> Option<TimedMove> {
    if m.delta_e_m < 0.0 {
        *retracted_m = (*retracted_m - m.delta_e_m).min(MAX_RETRACTED_M);
        return None;
    }
    if !m.extrude || *retracted_m <= 0.0 {
        return None;
    }
    let repaid_m = retracted_m.min(m.delta_e_m);
    *retracted_m -= repaid_m;
    let fed_m = m.delta_e_m - repaid_m;
    Some(TimedMove {
        delta_e_m: if fed_m > FED_NOTHING_M { fed_m } else { 0.0 },
        ..m.clone()
    })
}

/// The command breakpoints for consecutive moves (in plan order), before smoothing.
pub fn breakpoints(moves: &[TimedMove], options: &ScrewOptions) -> Vec<Command> {
    breakpoints_from(moves, options, &mut PinState::default(), true)
}

/// [`breakpoints`] for one chunk of a longer run: starts from `state` and leaves it for the
/// next chunk; the pin is closed after the last move only at `end_of_input`.
pub fn breakpoints_from(
    moves: &[TimedMove],
    options: &ScrewOptions,
    state: &mut PinState,
    end_of_input: bool,
) -> Vec<Command> {
    let mut out: Vec<Command> = Vec::new();
    // Look-ahead openings fall inside earlier moves: merged in by time at the end.
    let mut openings: Vec<Command> = Vec::new();
    let mut previous_extruding = state.extruding;
    let mut pin_closed_at = state.closed_at;
    let mut retracted_m = state.retracted_m;
    // Where the chunk's last move ends: the close at the end of the input goes there when
    // the moves after the last run are only instants (a trailing `G92 E0`).
    let mut last_instant = None;
    for m in moves {
        let fed = fed_after_retractions(m, &mut retracted_m);
        let mut m = fed.as_ref().unwrap_or(m);
        let (Some(&t0), Some(&t1)) = (m.t.first(), m.t.last()) else {
            continue;
        };
        last_instant = Some(Command {
            t: t1,
            rpm: 0.0,
            pin_open: true,
            source_line: m.source_line,
            sequence: m.sequence,
        });
        // A prime after a non-extruding move under `Stop` opens with the planner's pin rest
        // (the delay at rest, in the same trajectory as the prime's own): it feeds after it,
        // when the melt can pass, not from the rest's start. Only where that rest is.
        let primed;
        let rest_end = m.t.get(1).copied().unwrap_or(t0);
        if options.strategy == PinStrategy::Stop
            && m.extrude
            && !previous_extruding
            && m.length_m <= 0.0
            && m.t.len() > 2
            && (rest_end - t0 - options.pin_open_delay_s).abs() < 1e-6
        {
            primed = TimedMove {
                motion_start_s: rest_end,
                ..m.clone()
            };
            m = &primed;
        }
        if t1 <= t0 && !m.extrude {
            continue; // an instant without material (G92, a feedrate-only line): no pin change
        }
        if m.extrude {
            if !previous_extruding {
                let open = Command {
                    t: match options.strategy {
                        PinStrategy::Stop => t0,
                        PinStrategy::Lookahead => {
                            (m.motion_start_s - options.pin_open_delay_s).max(pin_closed_at)
                        }
                    },
                    rpm: 0.0,
                    pin_open: true,
                    source_line: m.source_line,
                    sequence: m.sequence,
                };
                match options.strategy {
                    PinStrategy::Stop => out.push(open),
                    PinStrategy::Lookahead => openings.push(open),
                }
                // Nothing turns before the move starts moving.
                out.push(Command {
                    t: m.motion_start_s,
                    rpm: 0.0,
                    pin_open: true,
                    source_line: m.source_line,
                    sequence: m.sequence,
                });
            }
            for (&t, &v) in m.t.iter().zip(&m.speed) {
                let rpm = match options.model {
                    // Constant while the move moves, nothing during a pin rest before it.
                    RpmModel::Radius { .. } if t < m.motion_start_s || t1 <= t0 => 0.0,
                    RpmModel::Radius { .. } => rpm_at(m, 0.0, options),
                    RpmModel::PolarSpeed { .. } => rpm_at(m, v, options),
                };
                out.push(Command {
                    t,
                    rpm: rpm.min(options.max_rpm),
                    pin_open: true,
                    source_line: m.source_line,
                    sequence: m.sequence,
                });
            }
        } else if previous_extruding {
            // Close at the start of the first non-extruding move.
            out.push(Command {
                t: t0,
                rpm: 0.0,
                pin_open: false,
                source_line: m.source_line,
                sequence: m.sequence,
            });
            pin_closed_at = t0;
        }
        previous_extruding = m.extrude;
    }
    if previous_extruding && end_of_input {
        if let Some(last) = out.last().copied().or(last_instant) {
            out.push(Command {
                rpm: 0.0,
                pin_open: false,
                ..last
            });
            pin_closed_at = last.t;
            previous_extruding = false;
        }
    }
    *state = PinState {
        extruding: previous_extruding,
        closed_at: pin_closed_at,
        delivery: state.delivery,
        retracted_m,
        last_breakpoint: state.last_breakpoint,
    };
    // Plan order is time order, up to the nanosecond rounding of trajectory stamps.
    for i in 1..out.len() {
        out[i].t = out[i].t.max(out[i - 1].t);
    }
    let mut merged = Vec::with_capacity(out.len() + openings.len());
    let mut rest = out.into_iter().peekable();
    for open in openings {
        // Before the opening: everything earlier, and earlier moves' breakpoints at its time
        // (times agree to the nanosecond of the trajectory stamps).
        const SAME_INSTANT_S: f64 = 1e-9;
        while rest.peek().is_some_and(|c| {
            c.t < open.t - SAME_INSTANT_S
                || c.t <= open.t + SAME_INSTANT_S && c.sequence < open.sequence
        }) {
            merged.extend(rest.next());
        }
        merged.push(open);
    }
    merged.extend(rest);
    for i in 1..merged.len() {
        merged[i].t = merged[i].t.max(merged[i - 1].t);
    }
    limit_rate(&mut merged, options.max_rpm_per_s, state.last_breakpoint);
    if let Some(last) = merged.last() {
        state.last_breakpoint = Some((last.t, last.rpm));
    }
    merged
}

/// The commands published for `chunk`, continuing from `pin` (and updating it): with flow
/// compensation, held commands shaped by [`crate::compensation::compensate`]; with smoothing,
/// the filtered grid; with `command_period_s > 0`, exact interval averages held per interval;
/// otherwise the breakpoints themselves (rpm linear between them).
pub fn chunk_commands(
    chunk: &[TimedMove],
    options: &ScrewOptions,
    pin: &mut PinState,
    end_of_input: bool,
    command_period_s: f64,
) -> Vec<Command> {
    let raw = breakpoints_from(chunk, options, pin, end_of_input);
    let profile = match (&options.smoothing, command_period_s) {
        (Some(taps), _) => smooth(&raw, taps, options.smoothing_period_s),
        // A fixed rate: exact interval averages (an identity filter), held per interval.
        (None, period) if period > 0.0 && options.compensation.is_none() => {
            smooth(&raw, &[1.0], period)
        }
        (None, _) => raw,
    };
    match &options.compensation {
        None => profile,
        Some(model) => {
            // Smoothed commands are held: as a profile, each holds until the next.
            let profile = if options.smoothing.is_some() {
                held_as_breakpoints(&profile)
            } else {
                profile
            };
            let period = if command_period_s > 0.0 {
                command_period_s
            } else {
                options.compensation_period_s
            };
            crate::compensation::compensate(
                &profile,
                period,
                model,
                &crate::compensation::CommandLimits {
                    max_rpm: options.max_rpm,
                    max_rpm_per_s: options.max_rpm_per_s,
                },
                options.pin_open_delay_s,
                &mut pin.delivery,
            )
        }
    }
}

/// Held commands as linear breakpoints: each value held to the next command, then a jump.
fn held_as_breakpoints(held: &[Command]) -> Vec<Command> {
    let mut out = Vec::with_capacity(2 * held.len());
    for w in held.windows(2) {
        out.push(w[0]);
        out.push(Command { t: w[1].t, ..w[0] });
    }
    out.extend(held.last().copied());
    out
}

/// Lower rpm where it would change faster than `max_rpm_per_s` (forward and backward), so
/// the command never exceeds the plan and never jumps; forward from `previous` (the last
/// breakpoint of the chunk before, s and rpm), as if in one piece with it. (Backward, a
/// chunk cannot see the next: a fall at its start is met only from there on.)
fn limit_rate(commands: &mut [Command], max_rpm_per_s: f64, previous: Option<(f64, f64)>) {
    if max_rpm_per_s <= 0.0 {
        return;
    }
    if let (Some((t, rpm)), Some(first)) = (previous, commands.first_mut()) {
        first.rpm = first.rpm.min(rpm + max_rpm_per_s * (first.t - t).max(0.0));
    }
    for i in 1..commands.len() {
        let allowed = commands[i - 1].rpm + max_rpm_per_s * (commands[i].t - commands[i - 1].t);
        commands[i].rpm = commands[i].rpm.min(allowed);
    }
    for i in (0..commands.len().saturating_sub(1)).rev() {
        let allowed = commands[i + 1].rpm + max_rpm_per_s * (commands[i + 1].t - commands[i].t);
        commands[i].rpm = commands[i].rpm.min(allowed);
    }
}

/// rpm·s fed between `a` and `b` by breakpoints with linear interpolation (exact trapezoids).
///
/// `commands` are in time order (as every profile here is), so only the breakpoints around
/// `[a, b]` are visited: a binary search finds the first. Scanning them all made the screw
/// driver quadratic in a chunk's length (57 % of a million-move dry run's CPU went here).
pub fn integral(commands: &[Command], a: f64, b: f64) -> f64 {
    let mut sum = 0.0;
    for w in windows_over(commands, a, b) {
        let (t0, t1) = (w[0].t, w[1].t);
        if t1 <= t0 || t1 <= a || t0 >= b {
            continue;
        }
        let at = |t: f64| w[0].rpm + (w[1].rpm - w[0].rpm) * (t - t0) / (t1 - t0);
        let (lo, hi) = (t0.max(a), t1.min(b));
        sum += 0.5 * (at(lo) + at(hi)) * (hi - lo);
    }
    sum
}

/// The consecutive pairs of time-ordered `commands` that can overlap `[a, b]`: from the last
/// breakpoint at or before `a` to the first at or after `b`.
fn windows_over(commands: &[Command], a: f64, b: f64) -> impl Iterator<Item = &[Command]> {
    debug_assert!(
        commands.windows(2).all(|w| w[0].t <= w[1].t),
        "commands out of time order"
    );
    let first = commands.partition_point(|c| c.t <= a).saturating_sub(1);
    commands[first..].windows(2).take_while(move |w| w[0].t < b)
}

/// Smoothing: average the breakpoint profile exactly over a uniform grid, filter it without
/// delay, and return one command per grid interval (held until the next one). Each run of
/// open pin is filtered on its own and rescaled to feed exactly what it fed before: the filter
/// only moves material within a run, never into a closed pin. rpm is zero while the pin is
/// closed.
pub fn smooth(commands: &[Command], taps: &[f64], period_s: f64) -> Vec<Command> {
    let (Some(first), Some(last)) = (commands.first(), commands.last()) else {
        return Vec::new();
    };
    let n = ((last.t - first.t) / period_s).ceil().max(1.0) as usize;
    let start = first.t;
    // The breakpoint in force at the start of each interval, and whether the pin is open
    // anywhere in it: an interval that opens the pin carries the flow after the opening (a
    // period longer than the pin's delay), which a closed interval would drop.
    let mut in_force = Vec::with_capacity(n);
    let mut open = Vec::with_capacity(n);
    let mut j = 0;
    for k in 0..n {
        let t = start + k as f64 * period_s;
        while j + 1 < commands.len() && commands[j + 1].t <= t {
            j += 1;
        }
        in_force.push(j);
        open.push(
            commands[j..]
                .iter()
                .take_while(|c| c.t < t + period_s)
                .any(|c| c.pin_open),
        );
    }
    let averages: Vec<f64> = (0..n)
        .map(|k| {
            let a = start + k as f64 * period_s;
            integral(commands, a, a + period_s) / period_s
        })
        .collect();
    let mut rpm = vec![0.0; n];
    let mut k = 0;
    while k < n {
        if !open[k] {
            k += 1;
            continue;
        }
        let run_start = k;
        while k < n && open[k] {
            k += 1;
        }
        let raw = &averages[run_start..k];
        let filtered = filter_zero_phase(raw, taps);
        let (want, got): (f64, f64) = (raw.iter().sum(), filtered.iter().map(|v| v.max(0.0)).sum());
        let scale = if got > 0.0 { want / got } else { 1.0 };
        for (i, v) in filtered.iter().enumerate() {
            rpm[run_start + i] = v.max(0.0) * scale;
        }
    }
    (0..n)
        .map(|k| {
            let c = &commands[in_force[k]];
            Command {
                t: start + k as f64 * period_s,
                rpm: rpm[k],
                pin_open: open[k],
                source_line: c.source_line,
                sequence: c.sequence,
            }
        })
        .chain(std::iter::once(Command {
            t: start + n as f64 * period_s,
            rpm: 0.0,
            pin_open: last.pin_open,
            source_line: last.source_line,
            sequence: last.sequence,
        }))
        .collect()
}

/// How far a held command's rpm may be from the last one kept and still count as a repeat:
/// the compensation's filters leave values that differ from the plateau they settle on by
/// float rounding (finger.gcode: 48,576 consecutive commands less than 1e-9 rpm apart). A
/// thousandth of the MCU's resolution (1e-3 rpm); over a 10-minute plateau it is 1e-5 of a
/// revolution.
pub const REPEAT_TOLERANCE_RPM: f64 = 1e-6;

/// Drops held commands that change nothing. A flow-compensated or resampled stream puts a
/// command on every period (500 a second at 2 ms) and most of them repeat the one before
/// (finger.gcode: 81,402 commands, 7,185 changes of at least 1e-3 rpm); each is a DDS sample
/// to every consumer and a record in the bag. Under [`Hold::ZeroOrder`] a command with the
/// same pin and source line as the last one kept, and its rpm within
/// [`REPEAT_TOLERANCE_RPM`], holds what was already held, so leaving it out changes the
/// profile by at most that tolerance. Linear (first-order) commands are all kept: a repeat
/// there ends a ramp. A chunk's last command is kept too: it marks how far the commanded
/// timeline reaches (the planned screw angle and whoever integrates a flow after the screw
/// run to it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RepeatFilter {
    last_kept: Option<(f64, bool, u32)>,
}

impl RepeatFilter {
    /// A filter that last kept a command with (rpm, pin open, source line): a restored one.
    pub fn with_last_kept(last_kept: Option<(f64, bool, u32)>) -> RepeatFilter {
        RepeatFilter { last_kept }
    }

    /// The last command kept: (rpm, pin open, source line).
    pub fn last_kept(&self) -> Option<(f64, bool, u32)> {
        self.last_kept
    }

    /// Whether `command` (the next in time order) must be published; `ends_chunk` for the
    /// last command of a chunk.
    pub fn keep(&mut self, command: &Command, hold: Hold, ends_chunk: bool) -> bool {
        let repeat = hold == Hold::ZeroOrder
            && !ends_chunk
            && self.last_kept.is_some_and(|(rpm, pin_open, source_line)| {
                pin_open == command.pin_open
                    && source_line == command.source_line
                    && (rpm - command.rpm).abs() <= REPEAT_TOLERANCE_RPM
            });
        if !repeat {
            self.last_kept = Some((command.rpm, command.pin_open, command.source_line));
        }
        !repeat
    }

    /// The commands of a chunk that must be published, in order.
    pub fn chunk<'a>(
        &'a mut self,
        commands: &'a [Command],
        hold: Hold,
    ) -> impl Iterator<Item = &'a Command> + 'a {
        let last = commands.len().saturating_sub(1);
        commands
            .iter()
            .enumerate()
            .filter(move |&(k, c)| self.keep(c, hold, k == last))
            .map(|(_, c)| c)
    }
}

/// rpm·s fed between `a` and `b` by held (zero-order) commands.
pub fn integral_held(commands: &[Command], a: f64, b: f64) -> f64 {
    windows_over(commands, a, b)
        .map(|w| {
            let (lo, hi) = (w[0].t.max(a), w[1].t.min(b));
            if hi > lo {
                w[0].rpm * (hi - lo)
            } else {
                0.0
            }
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn held(rpm: f64, pin_open: bool, source_line: u32, t: f64) -> Command {
        Command {
            t,
            rpm,
            pin_open,
            source_line,
            sequence: 0,
        }
    }

    #[test]
    fn repeated_held_commands_are_dropped_and_every_change_kept() {
        let stream = [
            held(0.0, false, 1, 0.000),
            held(0.0, false, 1, 0.002), // repeat
            held(0.0, true, 1, 0.004),  // the pin opens
            held(12.5, true, 1, 0.006),
            held(12.5, true, 1, 0.008), // repeat
            held(12.5, true, 2, 0.010), // the next line, same rpm
            held(12.5, true, 2, 0.012), // repeat
            held(12.25, true, 2, 0.014),
            held(12.25 + 0.5e-6, true, 2, 0.015), // within the tolerance of the last kept
            held(12.25 + 1.5e-6, true, 2, 0.0155), // 1.5e-6 from the last kept: a change
            held(12.5, true, 2, 0.016),           // back to an earlier value: a change
            held(12.5, true, 2, 0.018),           // a repeat, but the chunk's last
        ];
        let mut filter = RepeatFilter::default();
        let kept: Vec<f64> = filter
            .chunk(&stream, Hold::ZeroOrder)
            .map(|c| c.t)
            .collect();
        assert_eq!(
            kept,
            [0.000, 0.004, 0.006, 0.010, 0.014, 0.0155, 0.016, 0.018]
        );
        // The next chunk continues from the last kept: its repeat is dropped.
        let next = [held(12.5, true, 2, 0.020), held(0.0, false, 2, 0.022)];
        let kept: Vec<f64> = filter.chunk(&next, Hold::ZeroOrder).map(|c| c.t).collect();
        assert_eq!(kept, [0.022]);
        // Linear commands: a repeat ends a ramp, so all stay.
        let mut filter = RepeatFilter::default();
        assert_eq!(
            filter.chunk(&stream, Hold::FirstOrder).count(),
            stream.len()
        );
    }

    proptest::proptest! {
        /// What the held commands feed over any interval is the same with or without the
        /// repeats, to the tolerance times the interval (the profile is kept, not merely its
        /// total), and the stream still ends where it ended.
        #[test]
        fn dropping_repeats_keeps_the_held_profile(
            values in proptest::collection::vec((0u8..3, 0u8..2, -2i8..3), 1..60),
            a in 0.0f64..0.13,
            length in 0.0f64..0.13,
        ) {
            let commands: Vec<Command> = values
                .iter()
                .enumerate()
                .map(|(k, &(rpm, line, noise))| {
                    let rpm_value = f64::from(rpm) * 5.0 + f64::from(noise) * 0.4e-6;
                    held(rpm_value, rpm > 0, u32::from(line), k as f64 * 0.002)
                })
                .collect();
            let mut filter = RepeatFilter::default();
            let kept: Vec<Command> = filter.chunk(&commands, Hold::ZeroOrder).copied().collect();
            proptest::prop_assert_eq!(kept.last().map(|c| c.t), commands.last().map(|c| c.t));
            let (full, fewer) = (
                integral_held(&commands, a, a + length),
                integral_held(&kept, a, a + length),
            );
            proptest::prop_assert!(
                (full - fewer).abs() <= REPEAT_TOLERANCE_RPM * length + 1e-12,
                "{full} vs {fewer}"
            );
        }
    }

    proptest::proptest! {
        /// The searched integrals equal the sum over every pair of breakpoints (the closed
        /// form per trapezoid or hold), whatever the interval: inside, across or outside
        /// the profile, with jumps (equal times) anywhere.
        #[test]
        fn integrals_over_the_breakpoints_near_the_interval_equal_the_full_sums(
            steps in proptest::collection::vec((0u8..4, -50.0f64..1500.0), 0..40),
            a in -1.0f64..12.0,
            length in 0.0f64..6.0,
        ) {
            let mut t = 0.0;
            let commands: Vec<Command> = steps
                .iter()
                .map(|&(dt, rpm)| {
                    t += f64::from(dt) * 0.25;
                    Command { t, rpm, pin_open: true, source_line: 0, sequence: 0 }
                })
                .collect();
            let b = a + length;
            let (mut linear, mut held) = (0.0, 0.0);
            for w in commands.windows(2) {
                let (lo, hi) = (w[0].t.max(a), w[1].t.min(b));
                if hi > lo {
                    let slope = (w[1].rpm - w[0].rpm) / (w[1].t - w[0].t);
                    let at = |t: f64| w[0].rpm + slope * (t - w[0].t);
                    linear += 0.5 * (at(lo) + at(hi)) * (hi - lo);
                    held += w[0].rpm * (hi - lo);
                }
            }
            let scale = 1e-9 * (1.0 + linear.abs() + held.abs());
            proptest::prop_assert!((integral(&commands, a, b) - linear).abs() <= scale);
            proptest::prop_assert!((integral_held(&commands, a, b) - held).abs() <= scale);
        }
    }

    /// A plan that rests at joints `q` for `duration_s` from its stamp.
    fn resting(q: [f64; 3], duration_s: f64) -> polar_cell_msgs::JointTrajectory {
        use polar_cell_msgs::{Duration, JointTrajectory, JointTrajectoryPoint};
        let point = |t: f64| JointTrajectoryPoint {
            positions: q.to_vec(),
            velocities: vec![0.0; 3],
            time_from_start: Duration::from_secs_f64(t),
            ..Default::default()
        };
        JointTrajectory {
            points: vec![point(0.0), point(duration_s)],
            ..Default::default()
        }
    }

    /// A line `length_m` long fed `delta_e_m` over one second from `t0` (a prime when
    /// `length_m` is 0: no joint moves, so its motion "starts" at `t0`).
    fn one_second(sequence: u64, t0: f64, delta_e_m: f64, length_m: f64) -> TimedMove {
        let speed = if length_m > 0.0 { length_m } else { 0.0 };
        TimedMove {
            sequence,
            source_line: sequence as u32 + 1,
            extrude: delta_e_m > 0.0,
            delta_e_m,
            length_m,
            length_xy_m: length_m,
            feedrate_m_per_s: 0.01,
            mid_radius_m: 0.05,
            t: vec![t0, t0 + 1.0],
            speed: vec![speed, speed],
            motion_start_s: t0,
        }
    }

    /// With `max_rpm_per_s`, a chunk cut inside a run's ramp goes on from where the ramp
    /// was, as the run in one piece does: the next chunk used to start at the plan's full
    /// rpm, a jump the limit exists to prevent.
    #[test]
    fn a_rate_limited_ramp_continues_across_a_chunk_cut() {
        let moves: Vec<TimedMove> = (0..3)
            .map(|i| one_second(i, i as f64, 1e-3, 0.01))
            .collect();
        let full_rpm = breakpoints(&moves, &ScrewOptions::default())
            .iter()
            .map(|c| c.rpm)
            .fold(0.0, f64::max);
        // Up to full speed in 1.5 s: the ramp spans the cut at 1 s.
        let options = ScrewOptions {
            max_rpm_per_s: full_rpm / 1.5,
            ..ScrewOptions::default()
        };
        let one_piece = breakpoints(&moves, &options);
        let mut pin = PinState::default();
        let mut cut = breakpoints_from(&moves[..1], &options, &mut pin, false);
        cut.extend(breakpoints_from(&moves[1..], &options, &mut pin, true));
        assert_eq!(cut, one_piece);
        for w in cut.windows(2) {
            assert!(
                w[1].rpm - w[0].rpm <= options.max_rpm_per_s * (w[1].t - w[0].t) + 1e-9,
                "{w:?}"
            );
        }
        assert!(cut.iter().any(|c| c.t == 1.0 && c.rpm < 0.7 * full_rpm));
    }

    /// A slicer's retraction and unretraction (`G1 E-1`, travel, `G1 E0.1`): the screw takes
    /// nothing back at the retraction (the pin closes), so the unretraction feeds only its
    /// 0.1 mm beyond it, not 1.1 mm; one that just undoes the retraction feeds nothing and
    /// leaves the pin closed. The retracted length carries across chunks.
    #[test]
    fn an_unretraction_feeds_only_what_goes_beyond_the_retraction() {
        let options = ScrewOptions::default();
        let RpmModel::PolarSpeed { e_per_rev_m } = options.model else {
            panic!("the default model")
        };
        let moves = |unretract_m: f64| {
            vec![
                one_second(0, 0.0, 1e-3, 0.01),
                one_second(1, 1.0, -1e-3, 0.0),
                one_second(2, 2.0, 0.0, 0.01), // the travel
                one_second(3, 3.0, unretract_m, 0.0),
                one_second(4, 4.0, 1e-3, 0.01),
            ]
        };
        let revs = |commands: &[Command], a: f64| integral(commands, a, a + 1.0) / 60.0;
        let commands = breakpoints(&moves(1.1e-3), &options);
        for (second, fed_m) in [
            (0.0, 1e-3),
            (1.0, 0.0),
            (2.0, 0.0),
            (3.0, 0.1e-3),
            (4.0, 1e-3),
        ] {
            assert!(
                (revs(&commands, second) - fed_m / e_per_rev_m).abs() < 1e-9,
                "second {second}: {} rev",
                revs(&commands, second)
            );
        }
        // In two chunks, split after the retraction: the same commands.
        let all = moves(1.1e-3);
        let mut pin = PinState::default();
        let mut split = breakpoints_from(&all[..2], &options, &mut pin, false);
        assert_eq!(pin.retracted_m, 1e-3);
        split.extend(breakpoints_from(&all[2..], &options, &mut pin, true));
        assert_eq!(split, commands);
        // Undone exactly: nothing turns, but the pin opens for it as the planner has it
        // (the delay before it) and stays open into the line, which needs no opening (under
        // `stop` the planner rests before the unretraction, not before the line).
        let commands = breakpoints(&moves(1e-3), &options);
        assert!(revs(&commands, 3.0).abs() < 1e-12);
        let opens_at = 3.0 - options.pin_open_delay_s;
        assert!(commands.iter().any(|c| c.t == opens_at && c.pin_open));
        for c in commands.iter().filter(|c| c.t > 1.0 && c.t < 5.0) {
            assert_eq!(c.pin_open, c.t >= opens_at, "{c:?}");
            assert!(c.t >= 4.0 || c.rpm == 0.0, "{c:?}");
        }
        let fed = as_fed(&moves(1e-3));
        assert_eq!((fed[3].delta_e_m, fed[3].extrude), (0.0, true));
        // Under `stop` likewise: open from the unretraction's start (where the planner
        // rests), not from the line's, which moves at once.
        let stop = ScrewOptions {
            strategy: PinStrategy::Stop,
            ..options.clone()
        };
        let commands = breakpoints(&moves(1e-3), &stop);
        for c in commands.iter().filter(|c| c.t > 1.0 && c.t < 5.0) {
            assert_eq!(c.pin_open, c.t >= 3.0, "{c:?}");
        }
    }

    /// Under `Stop`, a prime after a travel rests the pin's delay in its own trajectory
    /// before it feeds: the screw turns after that rest, when the melt can pass, and the
    /// prime still gets its material (it turned from the rest's start, a fifth of the
    /// prime's material against a closed pin).
    #[test]
    fn a_prime_under_stop_feeds_after_the_pin_rest() {
        let options = ScrewOptions {
            strategy: PinStrategy::Stop,
            ..ScrewOptions::default()
        };
        let RpmModel::PolarSpeed { e_per_rev_m } = options.model else {
            panic!("the default model")
        };
        let delay = options.pin_open_delay_s;
        let mut prime = one_second(1, 1.0, 2e-3, 0.0);
        prime.t = vec![1.0, 1.0 + delay, 2.0 + delay];
        prime.speed = vec![0.0; 3];
        let moves = [one_second(0, 0.0, 0.0, 0.01), prime];
        let commands = breakpoints(&moves, &options);
        assert!(
            integral(&commands, 1.0, 1.0 + delay).abs() < 1e-12,
            "{commands:?}"
        );
        let revs = integral(&commands, 1.0, 2.0 + delay) / 60.0;
        assert!((revs - 2e-3 / e_per_rev_m).abs() < 1e-9, "{revs} rev");
        assert!(commands.iter().any(|c| c.t == 1.0 && c.pin_open));
    }

    /// Found by fuzzing (tests/fuzz, target move_stream): a prime flagged `extrude` with a
    /// negative ΔE gave −1500 rpm with the pin open.
    #[test]
    fn a_move_that_takes_material_back_does_not_feed() {
        use polar_cell_msgs::GcodeMove;
        let trajectory = resting([0.0, 0.05, 0.0], 0.2);
        let mut m = GcodeMove {
            x_m: 0.05,
            delta_e_m: -0.01,
            feedrate_m_per_s: 0.05,
            extrude: true,
            ..Default::default()
        };
        let timed = TimedMove::from_trajectory(&m, [0.05, 0.0, 0.0], &trajectory, 0);
        let commands = breakpoints(&[timed], &ScrewOptions::default());
        assert!(
            commands.iter().all(|c| c.rpm == 0.0 && !c.pin_open),
            "{commands:?}"
        );
        // and the same move with material going in does feed
        m.delta_e_m = 0.01;
        let timed = TimedMove::from_trajectory(&m, [0.05, 0.0, 0.0], &trajectory, 0);
        let commands = breakpoints(&[timed], &ScrewOptions::default());
        assert!(
            commands.iter().any(|c| c.rpm > 0.0 && c.pin_open),
            "{commands:?}"
        );
    }

    /// A prime where the tool starts away from home: the move's target (from mm) and the
    /// start (in m) differ in the last bit. It feeds in place, as a prime (it was taken for a
    /// 1e-19 m line the tool rests on, and fed nothing).
    #[test]
    fn a_prime_a_last_bit_away_from_its_start_feeds_in_place() {
        use polar_cell_msgs::GcodeMove;
        let (theta, r) = (0.038f64, 0.05f64);
        let from = [r * theta.cos(), r * theta.sin(), 0.0];
        let target = from.map(|v| (v * 1e3) / 1e3);
        assert_ne!(from, target, "exact conversion: the test shows nothing");
        let trajectory = resting([theta, r, 0.0], 0.2);
        let m = GcodeMove {
            x_m: target[0],
            y_m: target[1],
            delta_e_m: 0.002,
            feedrate_m_per_s: 0.01,
            extrude: true,
            ..Default::default()
        };
        let timed = TimedMove::from_trajectory(&m, from, &trajectory, 0);
        assert_eq!((timed.length_m, timed.length_xy_m), (0.0, 0.0));
        let options = ScrewOptions::default();
        let commands = breakpoints(&[timed], &options);
        let fed = integral(&commands, 0.0, 0.2);
        let RpmModel::PolarSpeed { e_per_rev_m } = options.model else {
            panic!("the default model feeds primes")
        };
        assert!(
            (fed / 60.0 * e_per_rev_m - 0.002).abs() < 1e-9,
            "{commands:?}"
        );
    }

    #[test]
    fn rate_limit_lowers_steps_into_ramps() {
        let c = |t, rpm| Command {
            t,
            rpm,
            pin_open: true,
            source_line: 0,
            sequence: 0,
        };
        let mut commands = vec![
            c(0.0, 0.0),
            c(1.0, 0.0),
            c(1.0, 100.0),
            c(3.0, 100.0),
            c(3.0, 0.0),
        ];
        limit_rate(&mut commands, 50.0, None);
        let rpms: Vec<f64> = commands.iter().map(|c| c.rpm).collect();
        assert_eq!(
            rpms,
            [0.0, 0.0, 0.0, 0.0, 0.0],
            "a step with no time to ramp is lowered"
        );
        let mut commands = vec![c(0.0, 0.0), c(1.0, 100.0), c(4.0, 100.0), c(5.0, 0.0)];
        limit_rate(&mut commands, 50.0, None);
        let rpms: Vec<f64> = commands.iter().map(|c| c.rpm).collect();
        assert_eq!(rpms, [0.0, 50.0, 50.0, 0.0]);
        for w in commands.windows(2) {
            assert!((w[1].rpm - w[0].rpm).abs() <= 50.0 * (w[1].t - w[0].t) + 1e-12);
        }
    }
}
