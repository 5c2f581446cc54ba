//! The `screw_driver` node: `/gcode/moves` (as a flow-control consumer) and `/polar/trajectory`
//! in, `/screw/command` out, stamped on the planned timeline, and the `screw` joint's planned
//! angle on `/polar/planned_joint_states` (beside the planner's stage joints; the executed
//! joints are the executor's `/joint_states`).
//!
//! The work itself is [`crate::stream`]: moves paired with their plans, commands computed per
//! chunk and numbered. This node feeds it: a chunk is cut when the buffer is full, when input
//! goes idle (`idle_flush_s`; the pin closed after the last move only once the streamer says
//! the file is all here, or, with no streamer reporting (a played bag), at the pause; with
//! flow compensation only at a closed-pin gap until input stalls for `stall_flush_s`), and
//! when the streamer holds moves for our acknowledgement (`GcodeProgress.moves_waiting`). A
//! move is acknowledged once its commands are published, with the stream's checkpoint there,
//! so a restarted driver continues the same commands with the same numbers: the streamer
//! sends its moves again, and the planner's transient-local `/polar/trajectory` their plans. A restarted planner publishes again what
//! it had published after its last acknowledgement: those repeats are told by their times and
//! dropped ([`cell_runtime::replay`]).

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context as _};
use cell_runtime::flow::{Intake, LOOK_PERIOD};
use cell_runtime::replay::Admit;
use cell_runtime::topics::{publisher_qos, DEFAULT_MOVE_WINDOW};
use cell_runtime::{
    publish, reliable_qos, CellNode, LogLevel, ParamSpec, ParamValue, Params, PUBLISH_PATIENCE,
};
use polar_cell_msgs::{
    DiagnosticStatus, GcodeAck, GcodeMove, GcodeProgress, JointState, JointTrajectory, ScrewCommand,
};

use crate::compensation::FlowModel;
use crate::fir::{FILTER_1, FILTER_2, FILTER_2_60DB};
use crate::screw::{PinStrategy, RpmModel, ScrewOptions};
pub use crate::stream::{command_hold, command_message, joint_state_message, SCREW_JOINT};
use crate::stream::{model_name, Checkpoint, Cut, Stream, StreamOptions};

/// How long a driver that cannot continue a print stays in the graph (so the machine sees
/// the restart) before it exits.
const RESTART_FAILURE_LINGER: Duration = Duration::from_secs(2);

/// Default node name.
pub const NODE_NAME: &str = "screw_driver";

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
        ParamSpec::new("stall_flush_s", ParamValue::Double(2.0), "with flow compensation: when input pauses before the file is all read, commands are computed up to a closed-pin gap; after this long without input, for everything (the pin as planned while a streamer reports: a machine whose commands run out holds with its pin closed; without one, the pin closes, taken for the end of the input)").range(0.001, 3600.0),
        ParamSpec::new("max_buffer_s", ParamValue::Double(60.0), "compute commands once this much plan is buffered").range(0.1, 1e6),
        ParamSpec::new("max_buffer_moves", ParamValue::Integer(1024), "compute commands once this many moves are buffered (moves are acknowledged once commanded: keep it below the streamer's window)").range(1.0, 1e7),
        ParamSpec::new("acknowledge_moves", ParamValue::Bool(true), "be a flow-control consumer of /gcode/moves"),
        cell_runtime::graph::Producer::param_spec(),
        ParamSpec::new("joint_state_period_s", ParamValue::Double(0.02), "plan-time period of the screw joint's /polar/planned_joint_states samples (0: none)").range(0.0, 10.0),
    ]
}

/// The stream's options from the node's parameters.
pub fn stream_options_from_params(p: &Params) -> anyhow::Result<StreamOptions> {
    Ok(StreamOptions {
        screw: options_from_params(p)?,
        command_period_s: p.f64("command_period_s"),
        joint_state_period_s: p.sample_period_s("joint_state_period_s")?,
        max_buffer_s: p.f64("max_buffer_s"),
        max_buffer_moves: p.i64("max_buffer_moves") as usize,
    })
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

/// Run the screw driver on `node` until an error.
pub async fn run(node: &mut CellNode) -> anyhow::Result<()> {
    let params = node.params.clone();
    let stream_options = stream_options_from_params(&params)?;
    let idle_flush = Duration::from_secs_f64(params.f64("idle_flush_s"));
    let compensating = stream_options.screw.compensation.is_some();
    // Neither input runs more than the streamer's window ahead of this node's acknowledgements
    // (the planner plans only moves the streamer sent). RustDDS keeps `depth` samples after
    // they are taken, so a deeper history is memory that grows with the print, not safety.
    let depth = 2 * DEFAULT_MOVE_WINDOW;
    let moves_sub = node.subscription::<GcodeMove>("/gcode/moves", &reliable_qos(depth))?;
    // Transient-local: a restarted driver gets again the plans published since its last
    // acknowledgement (the planner's writer keeps more than a window of them).
    let trajectories = node.subscription::<JointTrajectory>(
        "/polar/trajectory",
        &publisher_qos("/polar/trajectory"),
    )?;
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
    let mut intake = Intake::new(
        node.fully_qualified_name(),
        params.bool("acknowledge_moves"),
    );
    // Moves and progress only from the streamer (a forged move would get material).
    let mut producer = cell_runtime::graph::Producer::of(node, params.bool("acknowledge_moves"))?;
    let mut stream = Stream::new(stream_options.clone());
    let digest = stream.options_digest();
    let mut replayed = cell_runtime::replay::ReplayFilter::new();
    let started = Instant::now();
    let mut last_input = Instant::now();
    // Acknowledgement repeats and announcements are looked at every LOOK_PERIOD; the idle and
    // stall cuts have deadlines of their own, so this loop wakes only when something is due.
    let mut tick = tokio::time::interval(LOOK_PERIOD);
    let mut last_look = Instant::now();
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "screw commands, model {}",
        model_name(&stream_options.screw)
    );
    let stall_flush = Duration::from_secs_f64(params.f64("stall_flush_s"));
    let mut moves_in_file: Option<u64> = None;
    // The streamer's last word on whether more moves wait for our acknowledgement.
    let mut streamer_waits = false;
    // Whether a streamer reports at all (it tells the end of the file; a played bag does not).
    let mut streamer_heard = false;
    // Moves the streamer has published: with all of them paired and more to come, it waits
    // for our acknowledgement (its window is full), which waits for a chunk.
    let mut moves_published = 0u64;
    let mut undecodable = cell_runtime::Undecodable::default();
    loop {
        let mut cut = Cut::IfFull;
        let mut look = false;
        let cut_deadline = [idle_flush, stall_flush]
            .into_iter()
            .map(|after| last_input + after)
            .filter(|&at| at > last_look)
            .min()
            .filter(|_| stream.buffered_moves() > 0);
        tokio::select! {
            taken = moves_sub.async_take() => {
                let Some((m, info)) = undecodable.take(node, "/gcode/moves", taken)? else {
                    continue;
                };
                if producer.admits(&info)
                    && intake.accept(m.sequence)
                {
                    stream.on_move(m);
                }
            }
            taken = trajectories.async_take() => {
                let Some((trajectory, info)) =
                    undecodable.take(node, "/polar/trajectory", taken)?
                else {
                    continue;
                };
                last_input = Instant::now();
                if replayed.admit(trajectory.span_ns(), info.publisher_gid()) == Admit::Repeat {
                    continue;
                }
                if let Err(e) = stream.on_trajectory(trajectory) {
                    node.diagnose(DiagnosticStatus::ERROR, &e.to_string(), &[]);
                    bail!(e);
                }
            }
            taken = progress_sub.async_take() => {
                if let Ok((p, info)) = taken {
                    if !producer.admits(&info) {
                        continue;
                    }
                    // The file's moves all published: once every one is paired, the input
                    // is complete (our own acknowledgements wait for the last chunk).
                    if p.end_of_file || p.finished {
                        moves_in_file = Some(p.moves_published);
                    }
                    moves_published = moves_published.max(p.moves_published);
                    streamer_waits = p.moves_waiting;
                    streamer_heard = true;
                    if let Some(ack) = intake.on_progress(&p) {
                        if let Some((resume_at, state)) = intake
                            .resume_state()
                            .filter(|(n, state)| *n > 0 || !state.is_empty())
                        {
                            // Restarted mid-print: continue the commands acknowledged there.
                            let restored = match state.is_empty() {
                                true => Err("no screw driver state came from the streamer: the pin, the modelled flow and the command numbers cannot be continued".to_string()),
                                false => Checkpoint::from_bytes(state, resume_at, digest).map_err(|e| e.to_string()),
                            };
                            let c = match restored {
                                Ok(c) => c,
                                Err(why) => {
                                    let reason = format!("restarted after move {resume_at}, cannot continue the screw commands: {why}");
                                    node.diagnose(DiagnosticStatus::ERROR, &reason, &[]);
                                    cell_runtime::cell_log!(node, LogLevel::Error, "{reason}");
                                    // Stay in the graph a moment: the machine sees the restart
                                    // and stops the print instead of holding for ever.
                                    tokio::time::sleep(RESTART_FAILURE_LINGER).await;
                                    return Err(anyhow!(reason));
                                }
                            };
                            // Plans that came before the resume point was known (the
                            // planner's history) go to the resumed stream.
                            stream = match stream.resumed(&c) {
                                Ok(resumed) => resumed,
                                Err(e) => {
                                    node.diagnose(DiagnosticStatus::ERROR, &e.to_string(), &[]);
                                    bail!(e);
                                }
                            };
                            cell_runtime::cell_log!(node, LogLevel::Info, "resumed after move {resume_at}: next command {}, plan time {:.6} s", c.next_command, c.commanded_end_ns.saturating_sub(c.base_ns) as f64 * 1e-9);
                        }
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
            let idle = stream.buffered_moves() > 0 && last_input.elapsed() >= idle_flush;
            // Input paused. The pin closes after the last move only when the file is all
            // here: a pause is the machine's pace (its plan-ahead horizon) or a stall
            // upstream, and the file goes on. A run cut there would be closed and reopened
            // at one instant; if commands run out, the machine holds and closes the pin
            // itself. With flow compensation a cut inside a run would starve the next
            // moves' look-ahead, so it waits for a closed-pin gap, unless input stalls.
            let stalled = last_input.elapsed() >= stall_flush;
            let input_complete = moves_in_file.is_some_and(|n| stream.paired_until() >= n);
            if idle {
                cut = if input_complete || (!streamer_heard && (!compensating || stalled)) {
                    // (Without a streamer, as when a bag is played in, nobody tells the end
                    // of the file: a pause, or with compensation a stall, is taken for it.)
                    Cut::All
                } else if compensating && !stalled {
                    Cut::AtGap
                } else {
                    Cut::Now
                };
            }
            // The file ended inside a run whose moves were all published (cut at a full
            // window or a stall): its close, or the pin would stay open after the print.
            if input_complete && stream.buffered_moves() == 0 && stream.pin_open() {
                cut = Cut::All;
            }
            if let Some(ack) = intake.ack(stream.commanded_until(), started.elapsed()) {
                let _ = acks.publish(GcodeAck::from(ack));
            }
        }
        // (Equal, not at least: a report older than the moves taken since says less.)
        // A held move means the file goes on: this is never its last chunk.
        let window_full = streamer_waits
            && stream.buffered_moves() > 0
            && stream.unpaired_moves() == 0
            && stream.paired_until() == moves_published
            && moves_in_file.is_none();
        if window_full && cut != Cut::All {
            cut = Cut::Now;
        }
        if let Some(chunk) = stream.cut(cut) {
            for message in chunk.commands {
                publish(&commands_pub, message, PUBLISH_PATIENCE)
                    .await
                    .context("/screw/command")?;
            }
            for message in chunk.joint_states {
                publish(&joint_states_pub, message, PUBLISH_PATIENCE)
                    .await
                    .context("/polar/planned_joint_states")?;
            }
            // Published: a restart continues after this chunk.
            intake.note_resume_state(stream.commanded_until(), stream.checkpoint().to_bytes());
            if let Some(ack) = intake.ack(stream.commanded_until(), started.elapsed()) {
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
