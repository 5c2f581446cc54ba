//! Did the pins do what the plan says? Reads a print's bag (its `/polar/steps`) and the pin
//! edges an MCU produced (recorded by `tests/firmware/harness.mjs` under rp2040js, or by a
//! logic analyser exported as `time_ns,pin,level` lines), reconstructs every step of every
//! joint from the pins, and compares with the planner's own decoder:
//!
//! * step counts and directions exact, per joint;
//! * every step's time within `--tolerance-us` (default 1.5 µs) of the decoded time, after
//!   one constant offset (the MCU clock's origin and the output's latency): the middle of the
//!   extreme differences, so the figure is the worst distance from the best constant. An
//!   edge on the decoder's tick is within ½ tick plus the output's jitter inside the tick
//!   (up to 0.9 µs under rp2040js); a few go out on the next tick (the step interrupt entered
//!   late, or waited out a direction's set-up time), counted on the `ticks:` line. The
//!   tolerance is one tick beyond the ½ tick of rounding, and each edge must be within one
//!   tick of its own (1 µs failed a loaded run here at 1.050 µs: three edges of 170,000 a
//!   tick late).
//!
//! The decoded time of a step is its segment's start on the MCU clock, as `mcu_bridge`'s
//! [`Schedule`] sends it (a whole tick: the plan's time rounded), plus the time the
//! planner's decoder gives it inside the segment; the MCU rounds that to its tick, so an
//! exact firmware is within ½ tick plus its output jitter.
//!
//! Pins are the firmware's profiles (`firmware/src/profile.rs`): step/dir on GP0/1, GP4/5,
//! GP8/9 for the cell; with `--bench-rig`, four coils per axis on GP0–3, GP4–7, GP8–11,
//! decoded through seed 001's two-phase sequence.
//!
//!     cargo run --release --example firmware_edges -- print.mcap edges.csv [--bench-rig]
//!
//! The screw's outputs too: the pin (GP12) and the speed as PWM duty (GP13, 300 rpm full
//! scale) against `/screw/command` — every PWM period's duty, converted to rpm, within
//! 0.05 rpm of what the commands ask at some instant of the millisecond before it (the
//! firmware writes a command's duty on its tick and a ramp's every generator chunk, 0.5 ms
//! at most; a new duty begins with the next PWM period), every pin change within that
//! millisecond after its command. Either may show up to `--tolerance-us` early: the constant
//! fitted to the steps places the pins within their tolerance, so a period that begins on a
//! command's own tick (the duty written just before the PWM wraps) may seem to begin before
//! it.
//! `--screw-hold first_order` when the print ran the screw with a first-order hold.
//!
//! Stops: with `--uart-in FILE` (the bytes the harness fed to UART0, with their times), the
//! host's frames are decoded by `cell_protocol`. From the first hold or stop frame on (a
//! hold's after the generator's lead, an emergency stop's at once), the plan's timing no
//! longer applies (σ slows the plan clock): steps are then checked for order and direction
//! only, and the pins may stop short of the plan. After an emergency stop
//! frame, no step, pin opening or PWM pulse may begin later than one control period
//! ([`CONTROL_PERIOD_NS`]), and by then the pin is closed, the PWM low and the drivers
//! disabled (GP14 high). From power-up the motors are free (GP14 high, coils released)
//! until the host's CONFIGURE reaches the MCU, and held when the first step goes out.
//!
//! Exits 0 when every check holds; prints its figures either way.

use std::collections::BTreeMap;

use anyhow::{bail, Context, Result};
use cell_bag::read_bag;
use cell_firmware_core::outputs::coil_phase;
use cell_protocol::message::{host_messages, HostMessage};
use cell_protocol::FrameDecoder;
use mcu_bridge::Schedule;
use polar_cell_msgs::{cdr, Hold, ScrewCommand, StepSegment};
use polar_planner::steps::{decode, Pulse};

const STEP_DIR: [(u8, u8); 3] = [(0, 1), (4, 5), (8, 9)];
const SCREW_PIN: u8 = 12;
const SCREW_PWM_PIN: u8 = 13;
const SCREW_FULL_SCALE_RPM: f64 = 300.0;
/// How long after a command the outputs may still show the previous one (ns).
const SCREW_SETTLE_NS: f64 = 1e6;
const SCREW_TOLERANCE_RPM: f64 = 0.05;
const ENABLE_PIN: u8 = 14;
/// Coil pins of the bench rig (GP0–11).
const COIL_PINS: u8 = 12;
/// The firmware's main-loop period (`LOOP_PERIOD_TICKS`): an e-stop acts within it.
const CONTROL_PERIOD_NS: f64 = 250e3;
/// How far ahead of the pins the firmware generates (`LEAD_TICKS`): a hold changes the
/// steps from this long after its frame.
const GENERATOR_LEAD_NS: f64 = 2e6;

/// The host's messages as they reached UART0 (`time_ns,byte` lines from the harness): each
/// message of each decoded frame with the time of the frame's last byte, and how many frames
/// were damaged.
fn read_host_messages(text: &str) -> Result<(Vec<(f64, HostMessage)>, u32)> {
    let mut decoder = FrameDecoder::new();
    let mut messages = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let (t, byte) = line
            .split_once(',')
            .and_then(|(t, b)| Some((t.parse::<u64>().ok()?, b.trim().parse::<u8>().ok()?)))
            .with_context(|| format!("uart line {}: `{line}` is not time_ns,byte", n + 1))?;
        // Every message of the payload: the bridge packs several into a frame (a hold joins
        // the segments waiting to fill theirs), and each takes effect at the frame's end.
        if let Some(Ok(frame)) = decoder.push(byte) {
            for message in host_messages(frame.payload).map_while(Result::ok) {
                messages.push((t as f64, message));
            }
        }
    }
    let c = decoder.counters();
    Ok((messages, c.crc_errors + c.framing_errors))
}

/// After an emergency stop at `estop_ns` (recorded time): nothing starts later than one
/// control period, and everything is off by then. Prints its figures; true when they hold.
fn check_emergency_stop(edges: &[(u64, u8, bool)], estop_ns: f64, bench_rig: bool) -> bool {
    let steps: &[u8] = if bench_rig {
        &[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]
    } else {
        &[0, 4, 8]
    };
    let after: Vec<&(u64, u8, bool)> = edges.iter().filter(|e| e.0 as f64 > estop_ns).collect();
    // Anything switched on (a step pulse, a coil, the pin, a PWM period) after the stop.
    let last_start = after
        .iter()
        .filter(|e| e.2 && (steps.contains(&e.1) || e.1 == SCREW_PIN || e.1 == SCREW_PWM_PIN))
        .map(|e| e.0 as f64 - estop_ns)
        .fold(0.0, f64::max);
    let level_at = |pin: u8, t: f64| {
        edges
            .iter()
            .rfind(|e| e.1 == pin && e.0 as f64 <= t)
            .is_some_and(|e| e.2)
    };
    let settled = estop_ns + CONTROL_PERIOD_NS;
    let off = !level_at(SCREW_PIN, settled)
        && !level_at(SCREW_PWM_PIN, settled)
        && (bench_rig || level_at(ENABLE_PIN, settled))
        && steps.iter().all(|&p| !level_at(p, settled));
    // When the outputs went off: the last change after the stop within the period.
    let off_after_ns = after
        .iter()
        .map(|e| e.0 as f64 - estop_ns)
        .filter(|&d| d <= CONTROL_PERIOD_NS)
        .fold(0.0, f64::max);
    // Moving when it came: step pulses in the 10 ms before.
    let steps_before = edges
        .iter()
        .filter(|e| e.2 && steps.contains(&e.1))
        .filter(|e| (estop_ns - 10e6..=estop_ns).contains(&(e.0 as f64)))
        .count();
    // A stop that came while nothing moved would prove nothing of stopping within a period.
    let good = last_start <= CONTROL_PERIOD_NS && off && steps_before > 0;
    println!(
        "emergency stop: {steps_before} steps in the 10 ms before it; outputs off {:.1} µs after \
         its frame reached the MCU (bound {:.0} µs), nothing started after {:.1} µs{}",
        off_after_ns * 1e-3,
        CONTROL_PERIOD_NS * 1e-3,
        last_start * 1e-3,
        if good { "" } else { "  <-- FAILED" }
    );
    good
}
const COILS: [[u8; 4]; 3] = [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]];

/// One step of one joint: when (ns) and which way.
#[derive(Clone, Copy, Debug)]
struct Step {
    t_ns: f64,
    sign: i8,
}

/// From power-up the motors are free — the drivers disabled (GP14 high from its first
/// level) or the coils released — until the host's CONFIGURE reached the MCU (when the UART
/// log has it), and held when the first step goes out. Prints its figures; true when they
/// hold.
fn check_power_up(
    edges: &[(u64, u8, bool)],
    configure_ns: Option<f64>,
    first_step_ns: Option<f64>,
    bench_rig: bool,
) -> bool {
    let held_from_ns = edges
        .iter()
        .find(|&&(_, pin, level)| {
            if bench_rig {
                level && pin < COIL_PINS
            } else {
                pin == ENABLE_PIN && !level
            }
        })
        .map(|e| e.0 as f64);
    let free_at_power_up = bench_rig
        || edges
            .iter()
            .find(|e| e.1 == ENABLE_PIN)
            .is_some_and(|e| e.2);
    let before_host = matches!((held_from_ns, configure_ns), (Some(h), Some(c)) if h < c);
    let after_first_step = match (held_from_ns, first_step_ns) {
        (Some(h), Some(s)) => h > s,
        (None, Some(_)) => true,
        _ => false,
    };
    let ok = free_at_power_up && !before_host && !after_first_step;
    let at = |t: Option<f64>| t.map_or("never".to_string(), |t| format!("{:.6} s", t * 1e-9));
    println!(
        "power-up: motors {} at first; held from {}, the host's CONFIGURE at {}, the first step at {}{}",
        if free_at_power_up { "free" } else { "HELD" },
        at(held_from_ns),
        at(configure_ns),
        at(first_step_ns),
        if ok { "" } else { "  <-- FAILED" }
    );
    ok
}

/// The highest step rate the pins kept up over [`PEAK_STEPS`] consecutive steps (steps per
/// second); 0 with fewer steps.
fn peak_rate(steps: &[Step]) -> f64 {
    steps
        .windows(PEAK_STEPS + 1)
        .map(|w| PEAK_STEPS as f64 / ((w[PEAK_STEPS].t_ns - w[0].t_ns) * 1e-9))
        .fold(0.0, f64::max)
}

/// The window of [`peak_rate`]: enough steps that one step's rounding to the tick is a small
/// part of it at the cell's top rates (20 steps at 30k/s span 667 ticks).
const PEAK_STEPS: usize = 20;

fn planned_steps(segments: &[StepSegment]) -> Result<[Vec<Step>; 3]> {
    let mut steps: [Vec<Step>; 3] = Default::default();
    let mut pulses: Vec<Pulse> = Vec::new();
    let timer_hz = segments.first().map_or(1e6, |s| s.timer_frequency_hz);
    let mut schedule = Schedule::new(timer_hz, Hold::ZeroOrder, 0);
    for seg in segments {
        let start_s = schedule.segment(seg)?.start_clock as f64 / timer_hz;
        pulses.clear();
        decode(seg, &mut pulses)?;
        for p in &pulses {
            steps[p.axis].push(Step {
                t_ns: (start_s + p.t) * 1e9,
                sign: seg.directions[p.axis].signum(),
            });
        }
    }
    Ok(steps)
}

/// Pin changes `(time_ns, pin, level)` in time order, as recorded.
fn read_edges(text: &str) -> Result<Vec<(u64, u8, bool)>> {
    let mut edges = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let fields: Vec<&str> = line.trim().split(',').collect();
        if fields.len() != 3 || fields[0].parse::<u64>().is_err() {
            if n == 0 {
                continue; // a header
            }
            bail!("edges line {}: `{line}` is not time_ns,pin,level", n + 1);
        }
        let t = fields[0].parse()?;
        let pin = fields[1]
            .parse()
            .with_context(|| format!("edges line {}: pin", n + 1))?;
        let level = match fields[2] {
            "1" => true,
            "0" => false,
            other => bail!("edges line {}: level `{other}`", n + 1),
        };
        edges.push((t, pin, level));
    }
    Ok(edges)
}

fn executed_steps(edges: &[(u64, u8, bool)], bench_rig: bool) -> Result<[Vec<Step>; 3]> {
    let mut steps: [Vec<Step>; 3] = Default::default();
    let mut levels = 0u32;
    // All changes at one instant first (a coil step changes two pins in one register write).
    let mut by_time: BTreeMap<u64, Vec<(u8, bool)>> = BTreeMap::new();
    for &(t, pin, level) in edges {
        by_time.entry(t).or_default().push((pin, level));
    }
    let mut phases: [Option<u8>; 3] = [None; 3];
    for (t, changes) in by_time {
        let before = levels;
        for (pin, level) in changes {
            if level {
                levels |= 1 << pin;
            } else {
                levels &= !(1 << pin);
            }
        }
        for axis in 0..3 {
            if bench_rig {
                let Some(phase) = coil_phase(levels, COILS[axis]) else {
                    continue; // coils released or mid-change: not a position
                };
                if let Some(from) = phases[axis] {
                    let sign = match (phase + 4 - from) % 4 {
                        0 => continue,
                        1 => 1,
                        3 => -1,
                        _ => bail!("axis {axis} skipped a phase at {t} ns"),
                    };
                    steps[axis].push(Step {
                        t_ns: t as f64,
                        sign,
                    });
                }
                phases[axis] = Some(phase);
            } else {
                let (step, dir) = STEP_DIR[axis];
                if levels >> step & 1 == 1 && before >> step & 1 == 0 {
                    let sign = if levels >> dir & 1 == 1 { 1 } else { -1 };
                    steps[axis].push(Step {
                        t_ns: t as f64,
                        sign,
                    });
                }
            }
        }
    }
    Ok(steps)
}

/// A screw command on the MCU's plan clock (ns from the schedule's anchor).
#[derive(Clone, Copy, Debug)]
struct Commanded {
    t_ns: f64,
    rpm: f64,
    pin_open: bool,
}

/// What the commands ask for at `t_ns`: rpm (clamped to the output's full scale).
fn commanded_rpm(commands: &[Commanded], hold: Hold, t_ns: f64) -> f64 {
    let after = commands.partition_point(|c| c.t_ns <= t_ns);
    let rpm = match (
        after.checked_sub(1).map(|i| commands[i]),
        commands.get(after),
    ) {
        (None, _) => 0.0,
        (Some(c), None) => c.rpm,
        (Some(c), Some(_)) if hold == Hold::ZeroOrder => c.rpm,
        (Some(c), Some(n)) => c.rpm + (n.rpm - c.rpm) * (t_ns - c.t_ns) / (n.t_ns - c.t_ns),
    };
    rpm.clamp(0.0, SCREW_FULL_SCALE_RPM)
}

/// The range of rpm the commands ask for over `[from_ns, to_ns]`.
fn commanded_range(commands: &[Commanded], hold: Hold, from_ns: f64, to_ns: f64) -> (f64, f64) {
    let inside = commands
        .iter()
        .filter(|c| c.t_ns > from_ns && c.t_ns <= to_ns)
        .map(|c| commanded_rpm(commands, hold, c.t_ns));
    [from_ns, to_ns]
        .into_iter()
        .map(|t| commanded_rpm(commands, hold, t))
        .chain(inside)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), r| {
            (lo.min(r), hi.max(r))
        })
}

/// Compare the screw pin and PWM with the commands; `pins_offset_ns` maps a recorded time
/// to the plan clock. Prints its figures; true when they hold.
fn check_screw(
    commands: &[Commanded],
    hold: Hold,
    edges: &[(u64, u8, bool)],
    pins_offset_ns: f64,
    until_plan_ns: f64,
    hold_plan_ns: Option<f64>,
    edge_tolerance_ns: f64,
) -> bool {
    let plan_ns = |t: u64| t as f64 - pins_offset_ns;
    let edges: Vec<(u64, u8, bool)> = edges
        .iter()
        .copied()
        .filter(|e| plan_ns(e.0) < until_plan_ns)
        .collect();
    let commands: Vec<Commanded> = commands
        .iter()
        .copied()
        .filter(|c| c.t_ns < until_plan_ns)
        .collect();
    let commands = &commands[..];
    let end_ns = edges.last().map_or(0.0, |e| plan_ns(e.0));
    // Speed: each PWM period (rise to rise) or each stretch without edges (0 % or 100 %).
    let pwm: Vec<(f64, bool)> = edges
        .iter()
        .filter(|e| e.1 == SCREW_PWM_PIN)
        .map(|e| (plan_ns(e.0), e.2))
        .collect();
    let period_ns = 80_000.0;
    let mut measured: Vec<(f64, f64, f64)> = Vec::new(); // (from, to, rpm)
    let mut last_change = (0.0, false);
    for (i, &(t, level)) in pwm.iter().enumerate() {
        if level {
            // A rise: a period from here to the next rise, if it is one.
            if let (Some(&(fall, false)), Some(&(next_rise, true))) =
                (pwm.get(i + 1), pwm.get(i + 2))
            {
                if next_rise - t < 1.5 * period_ns {
                    let duty = (fall - t) / (next_rise - t);
                    measured.push((t, next_rise, duty * SCREW_FULL_SCALE_RPM));
                }
            }
        }
        // Held at one level for longer than a period: 0 % or 100 % duty.
        if t - last_change.0 > 1.5 * period_ns {
            let rpm = if last_change.1 {
                SCREW_FULL_SCALE_RPM
            } else {
                0.0
            };
            measured.push((last_change.0 + period_ns, t - period_ns, rpm));
        }
        last_change = (t, level);
    }
    if end_ns - last_change.0 > 1.5 * period_ns {
        let rpm = if last_change.1 {
            SCREW_FULL_SCALE_RPM
        } else {
            0.0
        };
        measured.push((last_change.0 + period_ns, end_ns, rpm));
    }
    let mut worst_rpm = 0.0f64;
    let mut compared = 0usize;
    for &(from, to, rpm) in &measured {
        // A long stretch is checked every period along it.
        let mut t = from;
        while t <= to {
            // A period that begins on a command's own tick may already carry its duty (the
            // write precedes the wrap by nanoseconds), and the constant fitted to the steps
            // places that tick within the edges' tolerance either side of the rise.
            let (lo, hi) = commanded_range(
                commands,
                hold,
                t - SCREW_SETTLE_NS,
                t.min(to) + edge_tolerance_ns,
            );
            let off = if rpm < lo {
                lo - rpm
            } else if rpm > hi {
                rpm - hi
            } else {
                0.0
            };
            worst_rpm = worst_rpm.max(off);
            compared += 1;
            t += period_ns;
        }
    }
    // The pin: each change after a command that makes it, within the settling time.
    let mut wanted: Vec<(f64, bool)> = Vec::new();
    for c in commands {
        if wanted.last().map_or(c.pin_open, |w| w.1 != c.pin_open) {
            wanted.push((c.t_ns, c.pin_open));
        }
    }
    // Closed from the start: a recording's first "change" may be the pin becoming an output.
    let mut level = false;
    let mut changes: Vec<(f64, bool)> = edges
        .iter()
        .filter(|e| e.1 == SCREW_PIN && std::mem::replace(&mut level, e.2) != e.2)
        .map(|e| (plan_ns(e.0), e.2))
        .collect();
    // A hold closes the pin whatever the commands say, from the moment the MCU takes its
    // frame (its generator is then up to its lead ahead of the pins): one closing after the
    // hold's frame is the hold's, not a command's.
    if let Some(hold_plan_ns) = hold_plan_ns {
        if changes.len() == wanted.len() + 1
            && changes
                .last()
                .is_some_and(|&(t, open)| !open && t >= hold_plan_ns)
        {
            changes.pop();
        }
    }
    // A change the generator reaches exactly at its command's tick goes out on that tick;
    // measured against the steps' best constant it may then show up to the edges' own
    // tolerance early.
    let (mut earliest_pin_ns, mut latest_pin_ns) = (f64::INFINITY, f64::NEG_INFINITY);
    let mut pin_ok = changes.len() == wanted.len();
    for (c, w) in changes.iter().zip(&wanted) {
        let late = c.0 - w.0;
        pin_ok &= c.1 == w.1 && (-edge_tolerance_ns..=SCREW_SETTLE_NS).contains(&late);
        earliest_pin_ns = earliest_pin_ns.min(late);
        latest_pin_ns = latest_pin_ns.max(late);
    }
    if changes.is_empty() {
        (earliest_pin_ns, latest_pin_ns) = (0.0, 0.0);
    }
    let speed_ok = compared > 0 && worst_rpm <= SCREW_TOLERANCE_RPM;
    println!(
        "screw: {} commands; speed: {compared} PWM periods, worst {worst_rpm:.3} rpm from the \
         commands{}; pin: {} changes for {} commanded, {:.3} to {:.3} ms after its command{}",
        commands.len(),
        if speed_ok { "" } else { "  <-- FAILED" },
        changes.len(),
        wanted.len(),
        earliest_pin_ns * 1e-6,
        latest_pin_ns * 1e-6,
        if pin_ok { "" } else { "  <-- FAILED" }
    );
    speed_ok && pin_ok
}

/// Seed 001's bench program on the pins (`--seed-program EDGES LINES`): the bench-rig
/// firmware's coils, decoded, make the seed's six moves — every target reached in order, the
/// dominant axis stepping at the seed's rate to the tick, every axis's count exact, home at
/// the end — and the position lines on the second USB port follow the pins.
fn check_seed_program(edges_path: &str, lines_path: &str) -> Result<()> {
    use cell_firmware_core::seed_program::SEED_001_MOVES;
    let text =
        std::fs::read_to_string(edges_path).with_context(|| format!("reading {edges_path}"))?;
    let steps = executed_steps(&read_edges(&text)?, true)?;
    // One timeline: (time, axis, sign), in order.
    let mut timeline: Vec<(f64, usize, i8)> = (0..3)
        .flat_map(|k| steps[k].iter().map(move |s| (s.t_ns, k, s.sign)))
        .collect();
    timeline.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut ok = true;
    let mut position = [0i64; 3];
    let mut path: Vec<(f64, [i64; 3])> = Vec::new();
    let mut at = 0usize;
    let mut from = [0i64; 3];
    let mut move_end_ns = None::<f64>;
    for (n, &(target, rate)) in SEED_001_MOVES.iter().enumerate() {
        let target = target.map(i64::from);
        let counts: Vec<u64> = (0..3).map(|k| target[k].abs_diff(from[k])).collect();
        let dominant = *counts.iter().max().unwrap_or(&0);
        let period_ns = 1e9 / rate as f64;
        // The move's pulse instants (all axes stepping together share one).
        let mut instants: Vec<f64> = Vec::new();
        while position != target && at < timeline.len() {
            let (t, k, sign) = timeline[at];
            position[k] += sign as i64;
            path.push((t, position));
            if instants.last() != Some(&t) {
                instants.push(t);
            }
            at += 1;
        }
        let gaps_ok = instants
            .windows(2)
            .all(|w| (w[1] - w[0] - period_ns).abs() <= 1e3);
        // The first pulse comes one period after the previous move's end (the segment waits,
        // then steps).
        let start_ok = match (move_end_ns, instants.first()) {
            (Some(end), Some(&first)) => (first - end - period_ns).abs() <= 1e3,
            _ => true,
        };
        let good = position == target && instants.len() as u64 == dominant && gaps_ok && start_ok;
        ok &= good;
        println!(
            "seed move {}: to {target:?} at {rate} steps/s: {} pulse instants for {dominant} \
             dominant steps over {:.3} ms{}",
            n + 1,
            instants.len(),
            instants
                .last()
                .zip(instants.first())
                .map_or(0.0, |(l, f)| (l - f) * 1e-6),
            if good { "" } else { "  <-- FAILED" }
        );
        move_end_ns = instants.last().copied();
        from = target;
    }
    if at != timeline.len() {
        println!(
            "{} steps on the pins after the program's end  <-- FAILED",
            timeline.len() - at
        );
        ok = false;
    }
    // Position lines: each is where the pins were at some instant from 20 ms before it
    // (the 10 ms line period, the USB poll) to the generator's 2 ms lead after it.
    let lines =
        std::fs::read_to_string(lines_path).with_context(|| format!("reading {lines_path}"))?;
    let mut parsed = Vec::new();
    for (n, line) in lines.lines().enumerate() {
        let parse = || -> Option<(f64, [i64; 3])> {
            let (t, text) = line.split_once(',')?;
            let mut xyz = [0i64; 3];
            for (k, (field, name)) in text.split(',').zip(["X:", "Y:", "Z:"]).enumerate() {
                xyz[k] = field.strip_prefix(name)?.parse().ok()?;
            }
            Some((t.parse().ok()?, xyz))
        };
        parsed.push(parse().with_context(|| {
            format!(
                "{lines_path} line {}: `{line}` is not time,X:..,Y:..,Z:..",
                n + 1
            )
        })?);
    }
    let position_at = |t: f64| {
        let i = path.partition_point(|p| p.0 <= t);
        if i == 0 {
            [0; 3]
        } else {
            path[i - 1].1
        }
    };
    let unmatched = parsed
        .iter()
        .filter(|(t, xyz)| {
            let lo = path.partition_point(|p| p.0 < t - 20e6);
            let hi = path.partition_point(|p| p.0 <= t + GENERATOR_LEAD_NS);
            position_at(t - 20e6) != *xyz && !path[lo..hi].iter().any(|p| p.1 == *xyz)
        })
        .count();
    let last_ok = parsed.last().map(|l| l.1) == Some([0, 0, 0]);
    let lines_ok = parsed.len() > 100 && unmatched == 0 && last_ok;
    ok &= lines_ok;
    println!(
        "position lines: {}, {unmatched} not where the pins were, the last {:?}{}",
        parsed.len(),
        parsed.last().map(|l| l.1),
        if lines_ok { "" } else { "  <-- FAILED" }
    );
    if !ok {
        bail!("the pins do not play seed 001's program");
    }
    Ok(())
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--seed-program") {
        let [_, edges, lines] = &args[..] else {
            bail!("usage: firmware_edges --seed-program EDGES.csv LINES.csv");
        };
        return check_seed_program(edges, lines);
    }
    let bench_rig = args.iter().any(|a| a == "--bench-rig");
    // The run was stopped by a cancel and an emergency stop: its frame must be found.
    let expect_emergency_stop = args.iter().any(|a| a == "--expect-emergency-stop");
    let tolerance_us: f64 = args
        .iter()
        .position(|a| a == "--tolerance-us")
        .and_then(|i| args.get(i + 1))
        .map_or(Ok(1.5), |v| v.parse())?;
    let screw_hold = match args
        .iter()
        .position(|a| a == "--screw-hold")
        .and_then(|i| args.get(i + 1))
    {
        None => Hold::ZeroOrder,
        Some(h) if h == "zero_order" => Hold::ZeroOrder,
        Some(h) if h == "first_order" => Hold::FirstOrder,
        Some(other) => bail!("--screw-hold `{other}`: zero_order or first_order"),
    };
    let uart_in = args
        .iter()
        .position(|a| a == "--uart-in")
        .and_then(|i| args.get(i + 1));
    let files: Vec<&String> = args
        .iter()
        .enumerate()
        .filter(|(i, a)| {
            !a.starts_with("--")
                && !matches!(
                    args.get(i.wrapping_sub(1)).map(String::as_str),
                    Some("--tolerance-us" | "--screw-hold" | "--uart-in")
                )
        })
        .map(|(_, a)| a)
        .collect();
    let [bag, edges, ..] = files[..] else {
        bail!(
            "usage: firmware_edges BAG EDGES.csv [--bench-rig] [--tolerance-us US] \
             [--screw-hold zero_order|first_order] [--uart-in UART.csv] \
             [--expect-emergency-stop]"
        );
    };
    let bytes = std::fs::read(bag).with_context(|| format!("reading {bag}"))?;
    let contents = read_bag(&bytes).with_context(|| bag.to_string())?;
    let mut segments = Vec::new();
    let mut screw_commands = Vec::new();
    for message in contents.messages()? {
        let message = message?;
        if message.topic == "/polar/steps" {
            segments.push(cdr::decode::<StepSegment>(&message.data)?);
        } else if message.topic == "/screw/command" {
            screw_commands.push(cdr::decode::<ScrewCommand>(&message.data)?);
        }
    }
    let planned = planned_steps(&segments)?;
    let text = std::fs::read_to_string(edges).with_context(|| format!("reading {edges}"))?;
    let edges = read_edges(&text)?;
    let executed = executed_steps(&edges, bench_rig)?;
    let (host_messages, damaged_frames) = match uart_in {
        Some(path) => read_host_messages(
            &std::fs::read_to_string(path).with_context(|| format!("reading {path}"))?,
        )?,
        None => (Vec::new(), 0),
    };
    let stop_ns = host_messages
        .iter()
        .find(|(_, m)| {
            matches!(
                m,
                HostMessage::FeedHold { .. } | HostMessage::EmergencyStop | HostMessage::DropQueue
            )
        })
        .map(|(t, _)| *t);
    let estop_ns = host_messages
        .iter()
        .find(|(_, m)| *m == HostMessage::EmergencyStop)
        .map(|(t, _)| *t);
    // Steps the plan's timing applies to (recorded time): those the generator made before a
    // hold's frame came, up to its lead; none after an emergency stop's frame, which masks
    // the step timer while it takes the pins (edges due then may go out microseconds late,
    // and the stop's own check bounds what follows).
    let exact_until_ns = stop_ns
        .map_or(f64::INFINITY, |t| t + GENERATOR_LEAD_NS)
        .min(estop_ns.unwrap_or(f64::INFINITY));
    if uart_in.is_some() {
        println!(
            "host messages: {} decoded, {damaged_frames} frames damaged on the line{}{}",
            host_messages.len(),
            stop_ns.map_or(String::new(), |t| format!(
                "; first hold or stop at {:.6} s",
                t * 1e-9
            )),
            estop_ns.map_or(String::new(), |t| format!(
                "; emergency stop at {:.6} s",
                t * 1e-9
            )),
        );
    }
    // Screw commands on the plan clock: the first segment's stamp is plan time 0 (as the
    // bridge takes it), rounded to the MCU's tick as its schedule does.
    let epoch_ns = segments.first().map_or(0, |s| s.header.stamp.as_nanos());
    let commanded: Vec<Commanded> = screw_commands
        .iter()
        .map(|c| Commanded {
            t_ns: ((c.header.stamp.as_nanos() - epoch_ns).max(0) as f64 * 1e-3).round() * 1e3,
            rpm: c.rpm,
            pin_open: c.pin_open,
        })
        .collect();

    // The constant: the middle of the extreme differences over the steps that pair up.
    let (lowest, highest) = (0..3)
        .flat_map(|k| planned[k].iter().zip(&executed[k]))
        .filter(|(_, e)| e.t_ns < exact_until_ns)
        .map(|(p, e)| e.t_ns - p.t_ns)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), d| {
            (lo.min(d), hi.max(d))
        });
    if !lowest.is_finite() {
        bail!("no steps planned or none executed");
    }
    let offset_ns = (lowest + highest) / 2.0;
    let mut ok = true;
    let mut worst_ns = 0.0f64;
    for k in 0..3 {
        let (p, e) = (&planned[k], &executed[k]);
        let net = |s: &[Step]| s.iter().map(|s| s.sign as i64).sum::<i64>();
        let mut axis_worst = 0.0f64;
        let mut wrong_way = 0;
        for (p, e) in p.iter().zip(e) {
            if e.t_ns < exact_until_ns {
                axis_worst = axis_worst.max((e.t_ns - offset_ns - p.t_ns).abs());
            }
            wrong_way += (p.sign != e.sign) as usize;
        }
        worst_ns = worst_ns.max(axis_worst);
        // Where the pins first leave the plan, with the steps around it.
        if let Some(i) = p.iter().zip(e).position(|(p, e)| {
            p.sign != e.sign
                || (e.t_ns < exact_until_ns
                    && (e.t_ns - offset_ns - p.t_ns).abs() > tolerance_us * 1e3)
        }) {
            println!("joint {k}: first divergence at step {i}:");
            for j in i.saturating_sub(3)..(i + 4).min(p.len().max(e.len())) {
                let show = |s: Option<&Step>, shift: f64| {
                    s.map_or("-".to_string(), |s| {
                        format!("{:+} at {:.3} µs", s.sign, (s.t_ns - shift) * 1e-3)
                    })
                };
                println!(
                    "  step {j}: plan {}  pins {}",
                    show(p.get(j), 0.0),
                    show(e.get(j), offset_ns)
                );
            }
        }
        // Stopped early, the pins did a prefix of the plan.
        let counts_ok = if stop_ns.is_some() {
            e.len() <= p.len()
        } else {
            p.len() == e.len() && net(p) == net(e)
        };
        let good = counts_ok && wrong_way == 0 && axis_worst <= tolerance_us * 1e3;
        ok &= good;
        println!(
            "joint {k}: {} steps planned, {} on the pins, net {} vs {}, {wrong_way} the wrong way, \
             worst {:.3} µs from the decoder, peak {:.0} steps/s on the pins{}",
            p.len(),
            e.len(),
            net(p),
            net(e),
            axis_worst * 1e-3,
            peak_rate(e),
            if good { "" } else { "  <-- FAILED" }
        );
    }
    // To the tick: each step's tick (its recorded time, floored) against the decoder's time
    // rounded to a tick, the difference constant but for the MCU's own rounding.
    let mut tick_differences: BTreeMap<i64, usize> = BTreeMap::new();
    for k in 0..3 {
        for (p, e) in planned[k].iter().zip(&executed[k]) {
            if e.t_ns >= exact_until_ns {
                continue;
            }
            let d = (e.t_ns / 1e3).floor() as i64 - (p.t_ns / 1e3).round() as i64;
            *tick_differences.entry(d).or_default() += 1;
        }
    }
    let usual = tick_differences
        .iter()
        .max_by_key(|(_, &n)| n)
        .map_or(0, |(&d, _)| d);
    let off_tick: Vec<String> = tick_differences
        .iter()
        .filter(|(&d, _)| d != usual)
        .map(|(&d, n)| format!("{n} at {:+} tick", d - usual))
        .collect();
    // A late interrupt may put an edge on the next tick (and the MCU's fixed point may round
    // a time within hundredths of a tick of a half the other way): none further.
    let ticks_ok = tick_differences.keys().all(|&d| (d - usual).abs() <= 1);
    ok &= ticks_ok;
    println!(
        "ticks: {} steps on the decoder's tick{}{}",
        tick_differences.get(&usual).copied().unwrap_or(0),
        if off_tick.is_empty() {
            String::new()
        } else {
            format!(", {}", off_tick.join(", "))
        },
        if ticks_ok { "" } else { "  <-- FAILED" }
    );
    ok &= check_screw(
        &commanded,
        screw_hold,
        &edges,
        offset_ns,
        exact_until_ns - offset_ns,
        stop_ns.map(|t| t - offset_ns),
        tolerance_us * 1e3,
    );
    let configure_ns = host_messages
        .iter()
        .find(|(_, m)| matches!(m, HostMessage::Configure { .. }))
        .map(|(t, _)| *t);
    let first_step_ns = executed
        .iter()
        .filter_map(|steps| steps.first().map(|s| s.t_ns))
        .reduce(f64::min);
    ok &= check_power_up(&edges, configure_ns, first_step_ns, bench_rig);
    match estop_ns {
        Some(estop_ns) => ok &= check_emergency_stop(&edges, estop_ns, bench_rig),
        None if expect_emergency_stop => {
            println!("emergency stop: no EMERGENCY_STOP frame reached the MCU  <-- FAILED");
            ok = false;
        }
        None => {}
    }
    println!(
        "{} segments; pins {:.3} ms after the plan's clock; worst edge {:.3} µs (tolerance {tolerance_us} µs)",
        segments.len(),
        offset_ns * 1e-6,
        worst_ns * 1e-3
    );
    if !ok {
        bail!("the pins do not follow the plan");
    }
    Ok(())
}
