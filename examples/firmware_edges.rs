//! Did the pins do what the plan says? Reads a print's bag (its `/polar/steps`) and the pin
//! edges an MCU produced (recorded by `tests/firmware/harness.mjs` under rp2040js, or by a
//! logic analyser exported as `time_ns,pin,level` lines), reconstructs every step of every
//! joint from the pins, and compares with the planner's own decoder:
//!
//! * step counts and directions exact, per joint;
//! * every step's time within `--tolerance-us` (default 1 µs, one timer tick) of the decoded
//!   time, after one constant offset (the MCU clock's origin and the output's latency): the
//!   middle of the extreme differences, so the figure is the worst distance from the best
//!   constant.
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
//! Exits 0 when every check holds; prints its figures either way.

use std::collections::BTreeMap;

use anyhow::{bail, Context, Result};
use cell_bag::read_bag;
use cell_firmware_core::outputs::coil_phase;
use mcu_bridge::Schedule;
use polar_cell_msgs::{cdr, Hold, StepSegment};
use polar_planner::steps::{decode, Pulse};

const STEP_DIR: [(u8, u8); 3] = [(0, 1), (4, 5), (8, 9)];
const COILS: [[u8; 4]; 3] = [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11]];

/// One step of one joint: when (ns) and which way.
#[derive(Clone, Copy, Debug)]
struct Step {
    t_ns: f64,
    sign: i8,
}

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

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let bench_rig = args.iter().any(|a| a == "--bench-rig");
    let tolerance_us: f64 = args
        .iter()
        .position(|a| a == "--tolerance-us")
        .and_then(|i| args.get(i + 1))
        .map_or(Ok(1.0), |v| v.parse())?;
    let files: Vec<&String> = args.iter().filter(|a| !a.starts_with("--")).collect();
    let [bag, edges, ..] = files[..] else {
        bail!("usage: firmware_edges BAG EDGES.csv [--bench-rig] [--tolerance-us US]");
    };
    let bytes = std::fs::read(bag).with_context(|| format!("reading {bag}"))?;
    let contents = read_bag(&bytes).with_context(|| bag.to_string())?;
    let mut segments = Vec::new();
    for message in contents.messages()? {
        let message = message?;
        if message.topic == "/polar/steps" {
            segments.push(cdr::decode::<StepSegment>(&message.data)?);
        }
    }
    let planned = planned_steps(&segments)?;
    let text = std::fs::read_to_string(edges).with_context(|| format!("reading {edges}"))?;
    let executed = executed_steps(&read_edges(&text)?, bench_rig)?;

    // The constant: the middle of the extreme differences over the steps that pair up.
    let (lowest, highest) = (0..3)
        .flat_map(|k| planned[k].iter().zip(&executed[k]))
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
            axis_worst = axis_worst.max((e.t_ns - offset_ns - p.t_ns).abs());
            wrong_way += (p.sign != e.sign) as usize;
        }
        worst_ns = worst_ns.max(axis_worst);
        // Where the pins first leave the plan, with the steps around it.
        if let Some(i) = p.iter().zip(e).position(|(p, e)| {
            p.sign != e.sign || (e.t_ns - offset_ns - p.t_ns).abs() > tolerance_us * 1e3
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
        let good = p.len() == e.len()
            && net(p) == net(e)
            && wrong_way == 0
            && axis_worst <= tolerance_us * 1e3;
        ok &= good;
        println!(
            "joint {k}: {} steps planned, {} on the pins, net {} vs {}, {wrong_way} the wrong way, \
             worst {:.3} µs from the decoder{}",
            p.len(),
            e.len(),
            net(p),
            net(e),
            axis_worst * 1e-3,
            if good { "" } else { "  <-- FAILED" }
        );
    }
    // To the tick: each step's tick (its recorded time, floored) against the decoder's time
    // rounded to a tick, the difference constant but for the MCU's own rounding.
    let mut tick_differences: BTreeMap<i64, usize> = BTreeMap::new();
    for k in 0..3 {
        for (p, e) in planned[k].iter().zip(&executed[k]) {
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
    println!(
        "ticks: {} steps on the decoder's tick{}",
        tick_differences.get(&usual).copied().unwrap_or(0),
        if off_tick.is_empty() {
            String::new()
        } else {
            format!(", {}", off_tick.join(", "))
        }
    );
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
