//! The `screw_driver` node: `/gcode/moves` (as a flow-control consumer) and `/polar/trajectory`
//! in, `/screw/command` out, stamped on the planned timeline, and the `screw` joint's planned
//! angle on `/polar/planned_joint_states` (beside the planner's stage joints; the executed
//! joints are the executor's `/joint_states`).
//!
//! The k-th trajectory is the plan of the k-th move (the planner publishes exactly one per
//! move, in order); they are paired whichever arrives first. A restarted planner publishes
//! again what it had published after its last acknowledgement: those repeats are told by
//! their times and dropped ([`cell_runtime::replay`]), and every trajectory kept must start
//! where the one before ended, so a lost one stops this node instead of shifting every later
//! pairing. Commands are computed per chunk of moves: a chunk ends when input goes
//! idle (`idle_flush_s`), or when it holds more than `max_buffer_s` of plan — cut at a pin
//! closed for at least `pin_open_delay_s`, so no opening reaches back before the cut. A move
//! is acknowledged once it is paired with its trajectory: the node then holds all it needs
//! (a restart loses the commands of the chunk being buffered).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context as _};
use cell_runtime::flow::{Intake, LOOK_PERIOD};
use cell_runtime::replay::{Admit, TIMELINE_TOLERANCE_NS};
use cell_runtime::topics::{publisher_qos, DEFAULT_MOVE_WINDOW};
use cell_runtime::{
    publish, reliable_qos, CellNode, LogLevel, ParamSpec, ParamValue, Params, PUBLISH_PATIENCE,
};
use polar_cell_msgs::{
    DiagnosticStatus, GcodeAck, GcodeMove, GcodeProgress, Header, JointState, JointTrajectory,
    ScrewCommand, Time,
};

use crate::compensation::FlowModel;
use crate::fir::{FILTER_1, FILTER_2, FILTER_2_60DB};
use crate::joint::{Hold, ScrewAngle, ScrewSample};
use crate::screw::{
    chunk_commands, position_after, Command, PinState, PinStrategy, RepeatFilter, RpmModel,
    ScrewOptions, TimedMove,
};

/// Default node name.
pub const NODE_NAME: &str = "screw_driver";

/// The screw's joint in `urdf/polar_cell.urdf`.
pub const SCREW_JOINT: &str = "screw";

pub fn param_specs() -> Vec<ParamSpec> {
    let d = ScrewOptions::default();
    let flow = FlowModel::default_extruder();
    vec![
        ParamSpec::new("model", ParamValue::String("polar_speed".into()), "rpm model: polar_speed (exact tool speed) or radius (seed eq. 9)"),
        ParamSpec::new("e_per_rev_m", ParamValue::Double(0.002), "filament-equivalent length one screw revolution feeds (polar_speed)").range(1e-9, 1.0),
        ParamSpec::new("gamma", ParamValue::Double(1.0), "calibration constant γ of seed eq. 9 (radius)").range(0.0, 1e6),
        ParamSpec::new("pin_open_delay_s", ParamValue::Double(d.pin_open_delay_s), "time from opening the pin to material flowing").range(0.0, 60.0),
        ParamSpec::new("pin_strategy", ParamValue::String("lookahead".into()), "lookahead (open early from the plan) or stop (the planner rests; set its pin_open_dwell_s)"),
        ParamSpec::new("max_rpm", ParamValue::Double(d.max_rpm), "largest screw speed").range(0.0, 1e5),
        ParamSpec::new("max_rpm_per_s", ParamValue::Double(d.max_rpm_per_s), "largest rpm change per second (0: unlimited)").range(0.0, 1e9),
        ParamSpec::new("smoothing", ParamValue::String("none".into()), "none, fir1, fir2 (the seed's 1521 taps) or fir2_60db (1525 taps)"),
        ParamSpec::new("smoothing_period_s", ParamValue::Double(d.smoothing_period_s), "grid of the smoothed commands").range(1e-5, 10.0),
        ParamSpec::new("command_period_s", ParamValue::Double(0.0), "without smoothing: 0 publishes the exact breakpoints (rpm linear between them); > 0 resamples onto this grid, each command the exact average over its interval").range(0.0, 10.0),
        ParamSpec::new("flow_compensation", ParamValue::Bool(true), "shape rpm so the lagging flow delivers each move's material (needs the reduced model below)"),
        ParamSpec::new("flow_tau_s", ParamValue::Double(flow.tau_s), "time constant of the delivered flow (default: the extruder model of `polar-cell screw response` at 100 rpm; override with a measured value)").range(0.0, 100.0),
        ParamSpec::new("flow_dead_time_s", ParamValue::Double(flow.dead_time_s), "dead time of the delivered flow").range(0.0, 100.0),
        ParamSpec::new("flow_tau_closed_s", ParamValue::Double(flow.tau_closed_s), "decay of the held pressure with the pin closed (back flow through the screw)").range(0.0, 1e4),
        ParamSpec::new("compensation_period_s", ParamValue::Double(d.compensation_period_s), "grid of the compensated commands when command_period_s is 0").range(1e-5, 10.0),
        ParamSpec::new("idle_flush_s", ParamValue::Double(0.1), "compute commands when no trajectory came for this long").range(0.001, 60.0),
        ParamSpec::new("stall_flush_s", ParamValue::Double(2.0), "with flow compensation: when input pauses before the file is all read, commands are computed up to a closed-pin gap; after this long without input, for everything (the pin closes)").range(0.001, 3600.0),
        ParamSpec::new("max_buffer_s", ParamValue::Double(60.0), "compute commands once this much plan is buffered").range(0.1, 1e6),
        ParamSpec::new("acknowledge_moves", ParamValue::Bool(true), "be a flow-control consumer of /gcode/moves"),
        cell_runtime::graph::Producer::param_spec(),
        ParamSpec::new("joint_state_period_s", ParamValue::Double(0.02), "plan-time period of the screw joint's /polar/planned_joint_states samples (0: none)").range(0.0, 10.0),
    ]
}

/// Screw options from the node's parameters.
pub fn options_from_params(p: &Params) -> anyhow::Result<ScrewOptions> {
    let model = match p.string("model") {
        "polar_speed" => RpmModel::PolarSpeed {
            e_per_rev_m: p.f64("e_per_rev_m"),
        },
        "radius" => RpmModel::Radius {
            gamma: p.f64("gamma"),
        },
        other => bail!("parameter model: `{other}` is not polar_speed or radius"),
    };
    let strategy = match p.string("pin_strategy") {
        "lookahead" => PinStrategy::Lookahead,
        "stop" => PinStrategy::Stop,
        other => bail!("parameter pin_strategy: `{other}` is not lookahead or stop"),
    };
    let smoothing = match p.string("smoothing") {
        "none" => None,
        "fir1" => Some(FILTER_1.taps()),
        "fir2" => Some(FILTER_2.taps()),
        "fir2_60db" => Some(FILTER_2_60DB.taps()),
        other => bail!("parameter smoothing: `{other}` is not none, fir1, fir2 or fir2_60db"),
    };
    Ok(ScrewOptions {
        model,
        pin_open_delay_s: p.f64("pin_open_delay_s"),
        strategy,
        max_rpm: p.f64("max_rpm"),
        max_rpm_per_s: p.f64("max_rpm_per_s"),
        smoothing,
        smoothing_period_s: p.f64("smoothing_period_s"),
        compensation: p.bool("flow_compensation").then(|| FlowModel {
            tau_s: p.f64("flow_tau_s"),
            dead_time_s: p.f64("flow_dead_time_s"),
            tau_closed_s: p.f64("flow_tau_closed_s"),
        }),
        compensation_period_s: p.f64("compensation_period_s"),
    })
}

fn model_name(options: &ScrewOptions) -> &'static str {
    match options.model {
        RpmModel::PolarSpeed { .. } => "polar_speed",
        RpmModel::Radius { .. } => "radius",
    }
}

/// How the published commands run between each other: raw breakpoints are linear, smoothed
/// or resampled commands are held.
pub fn command_hold(options: &ScrewOptions, command_period_s: f64) -> Hold {
    if options.smoothing.is_some() || command_period_s > 0.0 || options.compensation.is_some() {
        Hold::ZeroOrder
    } else {
        Hold::FirstOrder
    }
}

/// A command as its message, stamped on the plan timeline starting at `base_ns`.
pub fn command_message(c: &Command, options: &ScrewOptions, base_ns: i64) -> ScrewCommand {
    ScrewCommand {
        header: Header {
            stamp: Time::after(base_ns, c.t),
            frame_id: String::new(),
        },
        rpm: c.rpm,
        pin_open: c.pin_open,
        source_line: c.source_line,
        model: model_name(options).to_string(),
    }
}

/// The `screw` joint's state (the planner publishes the stage's joints on the same topic).
pub fn joint_state_message(s: &ScrewSample, base_ns: i64) -> JointState {
    JointState {
        header: Header {
            stamp: Time::after(base_ns, s.t),
            frame_id: String::new(),
        },
        name: vec![SCREW_JOINT.to_string()],
        position: vec![s.angle_rad],
        velocity: vec![s.velocity_rad_per_s],
        effort: vec![],
    }
}

/// Where a chunk of buffered moves may end: after the last move that starts a closed-pin gap
/// of at least `delay` (so no later opening reaches back into it).
fn safe_cut(moves: &VecDeque<TimedMove>, delay: f64) -> Option<usize> {
    let mut cut = None;
    let mut gap_start: Option<f64> = None;
    for (i, m) in moves.iter().enumerate() {
        let (Some(&t0), Some(&t1)) = (m.t.first(), m.t.last()) else {
            continue;
        };
        if m.extrude {
            gap_start = None;
        } else if t1 > t0 {
            let start = *gap_start.get_or_insert(t0);
            if t1 - start >= delay {
                cut = Some(i + 1);
            }
        }
    }
    cut
}

/// Run the screw driver on `node` until an error.
pub async fn run(node: &mut CellNode) -> anyhow::Result<()> {
    let params = node.params.clone();
    let options = options_from_params(&params)?;
    let idle_flush = Duration::from_secs_f64(params.f64("idle_flush_s"));
    let max_buffer_s = params.f64("max_buffer_s");
    let command_period_s = params.f64("command_period_s");
    // Neither input runs more than the streamer's window ahead of this node's acknowledgements
    // (the planner plans only moves the streamer sent). RustDDS keeps `depth` samples after
    // they are taken, so a deeper history is memory that grows with the print, not safety.
    let depth = 2 * DEFAULT_MOVE_WINDOW;
    let moves_sub = node.subscription::<GcodeMove>("/gcode/moves", &reliable_qos(depth))?;
    let trajectories =
        node.subscription::<JointTrajectory>("/polar/trajectory", &reliable_qos(depth))?;
    let progress_sub =
        node.subscription::<GcodeProgress>("/gcode/progress", &reliable_qos(1000))?;
    let acks = node.publisher::<GcodeAck>("/gcode/ack", &publisher_qos("/gcode/ack"))?;
    let commands_pub = std::sync::Arc::new(
        node.publisher::<ScrewCommand>("/screw/command", &publisher_qos("/screw/command"))?,
    );
    node.keep(commands_pub.clone());
    let joint_states_pub = std::sync::Arc::new(node.publisher::<JointState>(
        "/polar/planned_joint_states",
        &publisher_qos("/polar/planned_joint_states"),
    )?);
    node.keep(joint_states_pub.clone());
    let joint_state_period_s = params.f64("joint_state_period_s");
    let mut angle = (joint_state_period_s > 0.0).then(|| {
        ScrewAngle::new(
            joint_state_period_s,
            command_hold(&options, command_period_s),
        )
    });
    let mut samples = Vec::new();
    let mut intake = Intake::new(
        node.fully_qualified_name(),
        params.bool("acknowledge_moves"),
    );
    // Moves and progress only from the streamer (a forged move would get material).
    let mut producer = cell_runtime::graph::Producer::of(node, params.bool("acknowledge_moves"))?;
    let mut moves: VecDeque<GcodeMove> = VecDeque::new();
    let mut plans: VecDeque<JointTrajectory> = VecDeque::new();
    let mut replayed = cell_runtime::replay::ReplayFilter::new();
    // End stamp of the last trajectory kept (ns).
    let mut last_end_ns: Option<i64> = None;
    let mut timed: VecDeque<TimedMove> = VecDeque::new();
    let mut from = [0.0f64; 3];
    let mut done_until = 0u64;
    let mut pin = PinState::default();
    let started = Instant::now();
    let mut last_input = Instant::now();
    // Times are kept relative to the first trajectory's stamp (integer ns).
    let mut base_ns: Option<i64> = None;
    // Stamp of the last command published: stamps never go back.
    let mut last_stamp_ns = i64::MIN;
    let hold = command_hold(&options, command_period_s);
    let mut repeats = RepeatFilter::default();
    // Acknowledgement repeats and announcements are looked at every LOOK_PERIOD; the idle and
    // stall cuts have deadlines of their own, so this loop wakes only when something is due.
    let mut tick = tokio::time::interval(LOOK_PERIOD);
    let mut last_look = Instant::now();
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "screw commands, model {}",
        model_name(&options)
    );
    let stall_flush = Duration::from_secs_f64(params.f64("stall_flush_s"));
    let mut stream_finished = false;
    loop {
        let mut flush_all = false;
        let mut idle_cut = false;
        let mut look = false;
        let cut_deadline = [idle_flush, stall_flush]
            .into_iter()
            .map(|after| last_input + after)
            .filter(|&at| at > last_look)
            .min()
            .filter(|_| !timed.is_empty());
        tokio::select! {
            taken = moves_sub.async_take() => {
                let (m, info) = taken.map_err(|e| anyhow!("/gcode/moves: {e:?}"))?;
                if producer.admits(&info)
                    && intake.accept(m.sequence)
                {
                    moves.push_back(m);
                }
            }
            taken = trajectories.async_take() => {
                let (trajectory, info) = taken.map_err(|e| anyhow!("/polar/trajectory: {e:?}"))?;
                last_input = Instant::now();
                let (start_ns, end_ns) = trajectory.span_ns();
                if replayed.admit((start_ns, end_ns), info.publisher_gid()) == Admit::Repeat {
                    continue;
                }
                if let Some(previous_end) = last_end_ns {
                    if (start_ns - previous_end).abs() > TIMELINE_TOLERANCE_NS {
                        let reason = format!(
                            "/polar/trajectory is not continuous: a plan starts at {start_ns} ns, the one before ended at {previous_end} ns ({:+.6} s): a plan was lost, and pairing the moves after it would misplace every one",
                            (start_ns - previous_end) as f64 * 1e-9
                        );
                        node.diagnose(DiagnosticStatus::ERROR, &reason, &[]);
                        bail!(reason);
                    }
                }
                last_end_ns = Some(end_ns);
                plans.push_back(trajectory);
            }
            taken = progress_sub.async_take() => {
                if let Ok((p, info)) = taken {
                    if !producer.admits(&info) {
                        continue;
                    }
                    // Every move of the file acknowledged by every consumer (us included).
                    stream_finished |= p.finished;
                    if let Some(ack) = intake.on_progress(&p) {
                        let _ = acks.publish(GcodeAck::from(ack));
                    }
                }
            }
            _ = tick.tick() => look = true,
            _ = tokio::time::sleep_until(cut_deadline.unwrap_or(last_look).into()), if cut_deadline.is_some() => {
                look = true;
            }
        }
        if look {
            last_look = Instant::now();
            let idle = !timed.is_empty() && last_input.elapsed() >= idle_flush;
            // With flow compensation a cut inside a run would close the pin mid-run (and
            // its reopening delay would starve the next moves): when input pauses, cut
            // at a closed-pin gap and wait for more, unless the file is all here or the
            // pause has become a stall.
            let stalled = last_input.elapsed() >= stall_flush;
            flush_all = idle && (options.compensation.is_none() || stream_finished || stalled);
            idle_cut = idle && !flush_all;
            if let Some(ack) = intake.ack(done_until, started.elapsed()) {
                let _ = acks.publish(GcodeAck::from(ack));
            }
        }
        // The k-th trajectory is the plan of the k-th move, whichever arrives first.
        while !moves.is_empty() && !plans.is_empty() {
            let (m, trajectory) = (moves.pop_front().unwrap(), plans.pop_front().unwrap());
            let base = *base_ns.get_or_insert(trajectory.header.stamp.as_nanos());
            timed.push_back(TimedMove::from_trajectory(&m, from, &trajectory, base));
            done_until = m.sequence + 1;
            from = position_after(&m, from);
        }
        let buffered_s = match (
            timed.front().and_then(|m| m.t.first()),
            timed.back().and_then(|m| m.t.last()),
        ) {
            (Some(a), Some(b)) => b - a,
            _ => 0.0,
        };
        // Full buffer: cut at a safe gap, or (a long print without one) everything.
        let cut = if flush_all {
            Some(timed.len())
        } else if idle_cut {
            safe_cut(&timed, options.pin_open_delay_s)
        } else if buffered_s > max_buffer_s {
            safe_cut(&timed, options.pin_open_delay_s).or(Some(timed.len()))
        } else {
            None
        };
        if let Some(cut) = cut.filter(|&c| c > 0) {
            let chunk: Vec<TimedMove> = timed.drain(..cut).collect();
            let commands = chunk_commands(&chunk, &options, &mut pin, flush_all, command_period_s);
            let base = base_ns.unwrap_or(0);
            for c in repeats.chunk(&commands, hold) {
                let mut message = command_message(c, &options, base);
                // A chunk's first command can round to a nanosecond before the previous
                // chunk's last (its time comes from another sum of the same plan): the
                // same instant, kept in order.
                let stamp_ns = message.header.stamp.as_nanos().max(last_stamp_ns);
                message.header.stamp = Time::from_nanos(stamp_ns);
                last_stamp_ns = stamp_ns;
                publish(&commands_pub, message, PUBLISH_PATIENCE)
                    .await
                    .context("/screw/command")?;
            }
            if let Some(angle) = angle.as_mut() {
                angle.extend(&commands, &mut samples);
                for s in samples.drain(..) {
                    publish(
                        &joint_states_pub,
                        joint_state_message(&s, base),
                        PUBLISH_PATIENCE,
                    )
                    .await
                    .context("/polar/planned_joint_states")?;
                }
            }
            if let Some(ack) = intake.ack(done_until, started.elapsed()) {
                let _ = acks.publish(GcodeAck::from(ack));
            }
        }
    }
}

/// Run the node from its own command line until SIGINT/SIGTERM.
pub async fn main_with_args(argv: Vec<String>) -> anyhow::Result<()> {
    let mut node = CellNode::start_from_argv(NODE_NAME, &param_specs(), &argv)?;
    tokio::select! {
        result = run(&mut node) => result,
        _ = cell_runtime::shutdown_signal() => Ok(()),
    }
}
