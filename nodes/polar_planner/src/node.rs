//! The `polar_planner` node: `/gcode/moves` in (as a flow-control consumer), `/polar/trajectory`,
//! `/polar/steps` and `/polar/planned_joint_states` out.
//!
//! With `follow_execution`, the planner plans no further ahead of execution than the
//! executor's `/cell/plan_credit` allows: moves wait, unacknowledged (so the streamer's window
//! stops the stream), until the plan published so far ends before the credit. Waiting for
//! credit is not idle input, so it never flushes the lookahead queue to a stop; only a stream
//! that really stalls does, and the plan handed to the executor then ends at rest.
//!
//! A move is acknowledged only once its plan is published, so a restarted planner resumes
//! with nothing lost; the acknowledgement carries the planner's [`Checkpoint`] there, so it
//! also resumes on the same timeline (plan clock, joints, path speed, step position) and the
//! machine receives the moves after it as if the planner had never stopped. The lookahead queue is flushed (planned to a stop) when no move arrived
//! for `idle_flush_s` — as firmware planners do — which also ends a stream.
//!
//! Times: plan time `t` (s) maps to stamps `plan_epoch_ns + t`; the epoch is the wall clock at
//! the first move unless `plan_epoch_ns` is set (replays and golden files use 0). Joint
//! states are samples of the plan every `joint_state_period_s` of plan time, published as the
//! plan is made (the machine itself would run them later). The Cartesian tool speed is exact
//! from the published joint velocities: `v = √(ṙ² + r²θ̇² + ż²)`.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context as _};
use cell_runtime::flow::{Intake, LOOK_PERIOD};
use cell_runtime::topics::publisher_qos;
use cell_runtime::{
    now_ns, publish, reliable_qos, CellNode, LogLevel, ParamSpec, ParamValue, Params,
    PUBLISH_PATIENCE,
};
use polar_cell_msgs::{
    DiagnosticStatus, GcodeAck, GcodeMove, GcodeProgress, Header, JointState, JointTrajectory,
    PlanCredit, StepSegment, StringMsg, Time,
};

use crate::resume::{options_digest, Checkpoint};
use crate::steps::{StepGenerator, StepOptions};
use crate::{PlannedMove, Planner, PlannerOptions, JOINT_NAMES};

/// Default node name.
pub const NODE_NAME: &str = "polar_planner";

/// How long a restarted planner that cannot continue the plan stays before it exits.
const RESTART_FAILURE_LINGER: Duration = Duration::from_secs(2);

/// The node's parameters (defaults: the shipped URDF and [`PlannerOptions::default`]).
pub fn param_specs() -> Vec<ParamSpec> {
    let d = PlannerOptions::default();
    let s = StepOptions::default();
    vec![
        ParamSpec::new("urdf_file", ParamValue::String(String::new()), "URDF with the joint limits (empty: the shipped urdf/polar_cell.urdf)"),
        ParamSpec::new("path_tolerance_m", ParamValue::Double(d.path_tolerance_m), "largest distance of the executed path from the commanded lines").range(1e-9, 1e-2),
        ParamSpec::new("center_radius_m", ParamValue::Double(d.center_radius_m), "lines passing closer to the centre go through it").range(0.0, 1e-2),
        ParamSpec::new("allow_negative_r", ParamValue::Bool(d.allow_negative_r), "cross the centre with a negative radius instead of turning the bed"),
        ParamSpec::new("joint_accelerations", ParamValue::DoubleArray(d.joints.iter().map(|j| j.acceleration).collect()), "bed (rad/s²), arm (m/s²), z (m/s²) acceleration limits"),
        ParamSpec::new("velocity_jumps", ParamValue::DoubleArray(d.joints.iter().map(|j| j.velocity_jump).collect()), "largest velocity change at a corner: bed (rad/s), arm, z (m/s)"),
        ParamSpec::new("max_tool_acceleration_m_per_s2", ParamValue::Double(d.max_tool_acceleration_m_per_s2), "tangential tool acceleration").range(1e-6, 1e3),
        ParamSpec::new("max_node_spacing_m", ParamValue::Double(d.max_node_spacing_m), "trajectory points at least this close along a line").range(1e-6, 1.0),
        ParamSpec::new("lookahead_blocks", ParamValue::Integer(d.lookahead_blocks as i64), "path blocks planned together").range(2.0, 1e5),
        ParamSpec::new("homing_speed_m_per_s", ParamValue::Double(d.homing_speed_m_per_s), "speed of G28 moves").range(1e-6, 10.0),
        ParamSpec::new("acceleration_safety", ParamValue::Double(d.acceleration_safety), "fraction of the acceleration limits planned with").range(0.01, 1.0),
        ParamSpec::new("steps_per_unit", ParamValue::DoubleArray(s.steps_per_unit.to_vec()), "steps per rad (bed), per m (arm), per m (z)"),
        ParamSpec::new("step_timer_hz", ParamValue::Double(s.timer_hz), "step timer frequency").range(1.0, 1e9),
        ParamSpec::new("publish_steps", ParamValue::Bool(true), "publish /polar/steps"),
        ParamSpec::new("publish_robot_description", ParamValue::Bool(false), "publish the URDF planned with on /robot_description (transient local), for a graph without a machine node to publish it (a dry run's bag)"),
        ParamSpec::new("joint_state_period_s", ParamValue::Double(0.02), "plan-time period of /polar/planned_joint_states samples (0: none)").range(0.0, 10.0),
        ParamSpec::new("follow_execution", ParamValue::Bool(false), "plan no further ahead of execution than the executor's /cell/plan_credit allows"),
        ParamSpec::new("plan_epoch_ns", ParamValue::Integer(-1), "stamp of plan time 0 (-1: wall clock at the first move)"),
        ParamSpec::new("idle_flush_s", ParamValue::Double(0.05), "plan the queue to a stop when no move came for this long").range(0.001, 60.0),
        ParamSpec::new("acknowledge_moves", ParamValue::Bool(true), "be a flow-control consumer of /gcode/moves (false: accept moves in sequence order, e.g. from a bag)"),
        cell_runtime::graph::Producer::param_spec(),
        cell_runtime::graph::Producer::named_param_spec("credit_producer", "cell_executor", "the machine node whose /cell/plan_credit this planner follows (relative: in its namespace; empty: any writer's); other writers are ignored"),
        ParamSpec::new("initial_joints", ParamValue::DoubleArray(d.initial_joints.to_vec()), "where the machine stands when the plan starts: bed (rad), arm (m), z (m); the first move goes from there"),
        ParamSpec::new("pin_open_dwell_s", ParamValue::Double(0.0), "rest before each extruding move after a non-extruding one, for the extruder pin (screw_driver's stop strategy; 0: none)").range(0.0, 60.0),
        ParamSpec::new("screw_max_rpm", ParamValue::Double(300.0), "the screw's top speed (screw_driver's max_rpm); extruding moves are slowed so they never need more (0: ignore the screw)").range(0.0, 1e5),
        ParamSpec::new("screw_e_per_rev_m", ParamValue::Double(0.002), "filament-equivalent length one screw revolution feeds (screw_driver's e_per_rev_m)").range(1e-9, 1.0),
        ParamSpec::new("screw_flow_tau_s", ParamValue::Double(0.049), "time constant of the screw's delivered flow (screw_driver's flow_tau_s when its flow_compensation is on, else 0): primes get five of it to rise and drain").range(0.0, 100.0),
        ParamSpec::new("screw_rpm_headroom", ParamValue::Double(0.1), "fraction of screw_max_rpm the plan leaves free for the screw's flow compensation").range(0.0, 0.99),
    ]
}

fn three(params: &Params, name: &str) -> anyhow::Result<[f64; 3]> {
    let v = params.f64s(name);
    if v.len() != 3 || v.iter().any(|x| !x.is_finite() || *x < 0.0) {
        anyhow::bail!(
            "parameter {name} needs 3 finite non-negative values (bed, arm, z), got {v:?}"
        );
    }
    Ok([v[0], v[1], v[2]])
}

/// Most steps per unit taken: a window of the plan then holds at most about 2³¹ steps of
/// any axis, as a segment's counts (u32) and a machine's position need.
const MAX_STEPS_PER_UNIT: f64 = 1e8;

fn steps_per_unit(params: &Params) -> anyhow::Result<[f64; 3]> {
    let v = three(params, "steps_per_unit")?;
    if v.iter().any(|x| !(*x > 0.0 && *x <= MAX_STEPS_PER_UNIT)) {
        anyhow::bail!(
            "parameter steps_per_unit needs 3 values in (0, {MAX_STEPS_PER_UNIT:e}] (bed per rad, arm and z per m), got {v:?}: an axis of 0 steps would never move"
        );
    }
    Ok(v)
}

/// The URDF the node plans with: `urdf_file`, or the shipped one.
fn urdf_text(params: &Params) -> anyhow::Result<String> {
    Ok(match params.string("urdf_file") {
        "" => crate::urdf::POLAR_CELL_URDF.to_string(),
        path => std::fs::read_to_string(path).with_context(|| format!("reading URDF {path}"))?,
    })
}

/// Planner and step options from the node's parameters and the URDF.
pub fn options_from_params(params: &Params) -> anyhow::Result<(PlannerOptions, StepOptions)> {
    let urdf_text = urdf_text(params)?;
    let mut joints = crate::urdf::joint_limits(&urdf_text).context("URDF")?;
    let accelerations = three(params, "joint_accelerations")?;
    let jumps = three(params, "velocity_jumps")?;
    for j in 0..3 {
        joints[j].acceleration = accelerations[j];
        joints[j].velocity_jump = jumps[j];
    }
    let options = PlannerOptions {
        path_tolerance_m: params.f64("path_tolerance_m"),
        center_radius_m: params.f64("center_radius_m"),
        allow_negative_r: params.bool("allow_negative_r"),
        joints,
        max_tool_acceleration_m_per_s2: params.f64("max_tool_acceleration_m_per_s2"),
        max_node_spacing_m: params.f64("max_node_spacing_m"),
        lookahead_blocks: params.i64("lookahead_blocks") as usize,
        homing_speed_m_per_s: params.f64("homing_speed_m_per_s"),
        acceleration_safety: params.f64("acceleration_safety"),
        // Checked against the joint limits by the planner.
        initial_joints: params.finite3("initial_joints", "bed rad, arm m, z m")?,
        pin_open_dwell_s: params.f64("pin_open_dwell_s"),
        screw: match params.f64("screw_max_rpm") {
            max_rpm if max_rpm > 0.0 => Some(crate::ScrewLimits {
                usable_rpm: max_rpm * (1.0 - params.f64("screw_rpm_headroom")),
                e_per_rev_m: params.f64("screw_e_per_rev_m"),
                flow_tau_s: params.f64("screw_flow_tau_s"),
            }),
            _ => None,
        },
    };
    // Not an option of the plan, but refused with them, so pre-flight refuses it too.
    params.sample_period_s("joint_state_period_s")?;
    let steps = StepOptions {
        steps_per_unit: steps_per_unit(params)?,
        timer_hz: params.f64("step_timer_hz"),
    };
    Ok((options, steps))
}

use crate::messages::trajectory_message;

/// Joint states sampled from a plan every `period` of plan time, from `next_t` on, made one
/// at a time as they are taken: a long dwell or slow move has millions of them (a 10-hour
/// `G4` held 1.8 million here, 0.7 GB with the screw driver's), and collecting them first
/// would make memory grow with the length of the print.
pub struct PlanSamples<'a> {
    plan: &'a PlannedMove,
    period: f64,
    /// Plan time of the next sample.
    next_t: f64,
    epoch_ns: i64,
    /// The window of `plan.points` the next sample falls in.
    window: usize,
}

impl<'a> PlanSamples<'a> {
    /// Samples of `plan` every `period` (≤ 0: none) from plan time `next_t` on.
    pub fn new(plan: &'a PlannedMove, period: f64, next_t: f64, epoch_ns: i64) -> Self {
        PlanSamples {
            plan,
            period,
            next_t,
            epoch_ns,
            window: 0,
        }
    }

    /// Plan time of the first sample after this plan's (where the next plan's start).
    pub fn next_t(&self) -> f64 {
        self.next_t
    }
}

impl Iterator for PlanSamples<'_> {
    type Item = JointState;

    fn next(&mut self) -> Option<JointState> {
        if self.period <= 0.0 {
            return None;
        }
        while let [a, b] = self.plan.points.get(self.window..self.window + 2)? {
            if self.next_t > b.t || b.t <= a.t {
                self.window += 1;
                continue;
            }
            let t = self.next_t;
            self.next_t += self.period;
            if t < a.t {
                continue;
            }
            let f = (t - a.t) / (b.t - a.t);
            let lerp = |x: [f64; 3], y: [f64; 3]| -> Vec<f64> {
                (0..3).map(|j| x[j] + (y[j] - x[j]) * f).collect()
            };
            return Some(JointState {
                header: Header {
                    stamp: Time::after(self.epoch_ns, t),
                    frame_id: String::new(),
                },
                name: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
                position: lerp(a.q, b.q),
                velocity: lerp(a.qd, b.qd),
                effort: vec![],
            });
        }
        None
    }
}

/// Whether the executor's `credit` lets the planner plan past plan time `plan_time_s` (the
/// end of what it published), on the timeline stamped from `epoch_ns` (< 0: not started).
pub fn credit_allows(credit: Option<&PlanCredit>, epoch_ns: i64, plan_time_s: f64) -> bool {
    let Some(c) = credit.filter(|c| !c.closed) else {
        return false; // no executor heard from yet, or it stopped taking this plan
    };
    if c.accept_until == Time::default() || epoch_ns < 0 {
        // The executor has nothing yet: the first horizon of our own plan.
        return plan_time_s < c.horizon_s;
    }
    Time::after(epoch_ns, plan_time_s).as_nanos() < c.accept_until.as_nanos()
}

/// Run the planner on `node` until an error; the caller decides when to stop it (signals
/// belong to whoever owns the process).
pub async fn run(node: &mut CellNode) -> anyhow::Result<()> {
    let params = node.params.clone();
    let (options, step_options) = options_from_params(&params)?;
    let digest = options_digest(&options, &step_options);
    let mut planner = Planner::new(options.clone()).map_err(|e| anyhow!("{e}"))?;
    let mut steps = StepGenerator::new(step_options.clone(), options.initial_joints);
    let publish_steps = params.bool("publish_steps");
    let js_period = params.sample_period_s("joint_state_period_s")?;
    let idle_flush = Duration::from_secs_f64(params.f64("idle_flush_s"));
    let mut epoch_ns = params.i64("plan_epoch_ns");
    let moves_sub = node.subscription::<GcodeMove>("/gcode/moves", &reliable_qos(10_000))?;
    let progress_sub =
        node.subscription::<GcodeProgress>("/gcode/progress", &reliable_qos(1000))?;
    let acks = node.publisher::<GcodeAck>("/gcode/ack", &publisher_qos("/gcode/ack"))?;
    let trajectory_pub = node
        .publisher::<JointTrajectory>("/polar/trajectory", &publisher_qos("/polar/trajectory"))?;
    let steps_pub =
        node.publisher::<StepSegment>("/polar/steps", &publisher_qos("/polar/steps"))?;
    let joint_states_pub = node.publisher::<JointState>(
        "/polar/planned_joint_states",
        &publisher_qos("/polar/planned_joint_states"),
    )?;
    if params.bool("publish_robot_description") {
        let description = node
            .publisher::<StringMsg>("/robot_description", &publisher_qos("/robot_description"))?;
        description
            .publish(StringMsg {
                data: urdf_text(&params)?,
            })
            .map_err(|e| anyhow!("/robot_description: {e:?}"))?;
        // Latched: the writer lives as long as the node, for late readers.
        node.keep(description);
    }
    let follow_execution = params.bool("follow_execution");
    let credit_sub = node.subscription::<PlanCredit>("/cell/plan_credit", &reliable_qos(10))?;
    let mut credit: Option<PlanCredit> = None;
    // Moves taken in order and not yet given to the planner (waiting for credit).
    let mut held: VecDeque<GcodeMove> = VecDeque::new();
    let mut intake = Intake::new(
        node.fully_qualified_name(),
        params.bool("acknowledge_moves"),
    );
    // Moves and progress only from the streamer (a forged move would be planned).
    let mut producer = cell_runtime::graph::Producer::of(node, params.bool("acknowledge_moves"))?;
    // Credit only from the machine (a forged credit would plan ahead of it, or stall it).
    let mut machine =
        cell_runtime::graph::Producer::named(node, "credit_producer", follow_execution)?;
    let mut undecodable = cell_runtime::Undecodable::default();
    let mut planned = Vec::new();
    let mut segments = Vec::new();
    let mut next_state_t = 0.0;
    // What may be acknowledged: every move before `planned_until` is published, and the
    // checkpoint after each of them. Acknowledged is `published`, except that zero-time moves
    // at its end wait for a move that takes time (or for the planner to go idle): consumers
    // tell a resumed planner's repeats from new moves by their times, and a resume point
    // right after a zero-time move would make a zero-time move after it look repeated.
    let mut published: Option<Checkpoint> = None;
    let mut timed: Option<Checkpoint> = None;
    let mut planned_until = 0u64;
    let mut pending = 0usize;
    let started = Instant::now();
    let mut last_diagnostics = Instant::now();
    let mut last_move = Instant::now();
    // Acknowledgement repeats and announcements are looked at every LOOK_PERIOD; the idle
    // flush has a deadline of its own, so this loop wakes only when something is due.
    let mut tick = tokio::time::interval(LOOK_PERIOD);
    // Whether the queue was planned to a stop since the last move came.
    let mut flushed_since_move = false;
    let (mut moves_planned, mut plan_time) = (0u64, 0.0f64);
    cell_runtime::cell_log!(node, LogLevel::Info, "planning /gcode/moves");
    loop {
        tokio::select! {
            taken = moves_sub.async_take() => {
                let Some((m, info)) = undecodable.take(node, "/gcode/moves", taken)? else {
                    continue;
                };
                if producer.admits(&info)
                    && intake.accept(m.sequence)
                {
                    last_move = Instant::now();
                    flushed_since_move = false;
                    held.push_back(m);
                }
            }
            taken = credit_sub.async_take() => {
                if let Ok((c, info)) = taken {
                    if machine.admits(&info) {
                        credit = Some(c);
                    }
                }
            }
            taken = progress_sub.async_take() => {
                if let Ok((p, info)) = taken {
                    if !producer.admits(&info) {
                        continue;
                    }
                    if let Some(ack) = intake.on_progress(&p) {
                        // Restarted before anything was acknowledged: the state, if any, has
                        // the epoch the killed planner's first plans were stamped with.
                        if let Some((resume_at, state)) = intake
                            .resume_state()
                            .filter(|(n, state)| *n > 0 || !state.is_empty())
                        {
                            // Restarted mid-print: continue the timeline acknowledged there.
                            let restored = match state.is_empty() {
                                true => Err("no planner state came from the streamer: the plan clock and joints cannot be continued".to_string()),
                                false => Checkpoint::from_bytes(state, resume_at, digest)
                                    .map_err(|e| e.to_string())
                                    .and_then(|c| {
                                        let p = Planner::resume(options.clone(), &c.resume_point()).map_err(|e| e.to_string())?;
                                        Ok((c, p))
                                    }),
                            };
                            let (c, resumed) = match restored {
                                Ok(both) => both,
                                Err(why) => {
                                    let reason = format!("restarted after move {resume_at}, cannot continue the plan: {why}");
                                    node.diagnose(DiagnosticStatus::ERROR, &reason, &[]);
                                    cell_runtime::cell_log!(node, LogLevel::Error, "{reason}");
                                    // Stay in the graph a moment: the machine, which looks at it
                                    // every half second, sees the restart and stops the print
                                    // when its plan runs out instead of holding for ever.
                                    tokio::time::sleep(RESTART_FAILURE_LINGER).await;
                                    return Err(anyhow!(reason));
                                }
                            };
                            planner = resumed;
                            steps = StepGenerator::at_position(step_options.clone(), c.step_position);
                            published = Some(c.clone());
                            timed = published.clone();
                            epoch_ns = c.plan_epoch_ns;
                            next_state_t = c.next_sample_t_s;
                            planned_until = resume_at;
                            moves_planned = c.moves_planned;
                            plan_time = c.t_s;
                            cell_runtime::cell_log!(node, LogLevel::Info, "resumed after move {resume_at}: plan time {:.6} s, joints {:?}, path speed {:.6} m/s, steps {:?}", c.t_s, c.q, c.path_speed2.sqrt(), c.step_position);
                        }
                        let _ = acks.publish(GcodeAck::from(ack));
                    }
                }
            }
            _ = tokio::time::sleep_until((last_move + idle_flush).into()),
                if pending > 0 && held.is_empty() && !flushed_since_move =>
            {
                flushed_since_move = true;
                planner.flush(&mut planned);
            }
            _ = tick.tick() => {
                // Announce until the resume point is known; then repeat the acknowledgement
                // (recovers a lost one).
                if let Some(ack) = intake.ack(planned_until, started.elapsed()) {
                    let _ = acks.publish(GcodeAck::from(ack));
                }
            }
        }
        // Feed the planner what the credit allows and publish each plan as it comes, so the
        // credit is judged against the plan actually published.
        let mut any_published = false;
        loop {
            while planned.is_empty()
                && !held.is_empty()
                && (!follow_execution || credit_allows(credit.as_ref(), epoch_ns, plan_time))
            {
                let m = held.pop_front().expect("not empty");
                if epoch_ns < 0 {
                    epoch_ns = now_ns() as i64;
                    // Nothing published yet, but the epoch is chosen: a planner restarted
                    // before its first acknowledgement stamps its plans the same way.
                    let start = Planner::start_point(planner.options());
                    let checkpoint =
                        Checkpoint::new(0, digest, epoch_ns, &start, steps.position(), 0.0, 0);
                    intake.note_resume_state(0, checkpoint.to_bytes());
                }
                pending += 1;
                if let Err(e) = planner.push(&m, &mut planned) {
                    node.diagnose(DiagnosticStatus::ERROR, &e.to_string(), &[]);
                    return Err(anyhow!("{e}"));
                }
            }
            if planned.is_empty() {
                break;
            }
            any_published = true;
            for plan in planned.drain(..) {
                publish(
                    &trajectory_pub,
                    trajectory_message(&plan, epoch_ns),
                    PUBLISH_PATIENCE,
                )
                .await
                .context("/polar/trajectory")?;
                if publish_steps {
                    segments.clear();
                    steps.segments(&plan, &mut segments);
                    for mut s in segments.drain(..) {
                        s.header.stamp = Time::after(epoch_ns, plan.start_time());
                        publish(&steps_pub, s, PUBLISH_PATIENCE)
                            .await
                            .context("/polar/steps")?;
                    }
                }
                let mut samples = PlanSamples::new(&plan, js_period, next_state_t, epoch_ns);
                for s in samples.by_ref() {
                    publish(&joint_states_pub, s, PUBLISH_PATIENCE)
                        .await
                        .context("/polar/planned_joint_states")?;
                }
                next_state_t = samples.next_t();
                moves_planned += 1;
                plan_time = plan.end_time();
                pending = pending.saturating_sub(1);
                let checkpoint = Checkpoint::new(
                    plan.sequence + 1,
                    digest,
                    epoch_ns,
                    &plan.resume,
                    steps.position(),
                    next_state_t,
                    moves_planned,
                );
                published = Some(checkpoint);
                if plan.end_time() > plan.start_time() {
                    timed = published.clone();
                }
            }
        }
        if !any_published {
            continue;
        }
        let idle = pending == 0 && held.is_empty();
        let checkpoint = if idle { &published } else { &timed };
        if let Some(c) = checkpoint
            .as_ref()
            .filter(|c| c.header.next_sequence > planned_until)
        {
            planned_until = c.header.next_sequence;
            intake.note_resume_state(planned_until, c.to_bytes());
        }
        // Acknowledge what is planned and published; the lookahead queue is not.
        if let Some(ack) = intake.ack(planned_until, started.elapsed()) {
            let _ = acks.publish(GcodeAck::from(ack));
        }
        if last_diagnostics.elapsed() >= Duration::from_secs(1) {
            last_diagnostics = Instant::now();
            node.diagnose(
                DiagnosticStatus::OK,
                "planning",
                &[
                    ("moves_planned", moves_planned.to_string()),
                    ("plan_time_s", format!("{plan_time:.3}")),
                ],
            );
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

#[cfg(test)]
mod tests {
    use super::*;

    fn credit(accept_until_ns: i64, closed: bool) -> PlanCredit {
        PlanCredit {
            accept_until: Time::from_nanos(accept_until_ns),
            horizon_s: 2.0,
            closed,
            ..PlanCredit::default()
        }
    }

    fn point(t: f64, r: f64, rd: f64) -> crate::TrajPoint {
        crate::TrajPoint {
            t,
            q: [0.0, r, 0.0],
            qd: [0.0, rd, 0.0],
            ..Default::default()
        }
    }

    fn params_with(name: &str, value: &str) -> Params {
        let set = cell_runtime::args::ParamOverride {
            node: None,
            name: name.into(),
            value_yaml: value.into(),
        };
        Params::resolve(&param_specs(), "/polar_planner", &[], &[set]).unwrap()
    }

    /// An axis of 0 steps per unit would never move (the machine refuses it only when the
    /// print starts, a graph launched node by node not at all): refused with the planner's
    /// options, so `polar-cell check` says so too.
    #[test]
    fn steps_per_unit_and_the_sample_period_are_checked_with_the_options() {
        for bad in ["[0.0, 80000.0, 400000.0]", "[5000.0, 1.0e9, 400000.0]"] {
            let error = options_from_params(&params_with("steps_per_unit", bad))
                .unwrap_err()
                .to_string();
            assert!(
                error.contains("steps_per_unit needs 3 values in (0, 1e8]"),
                "{bad}: {error}"
            );
        }
        // Pre-flight reads the options only: a sample period the node would refuse is
        // refused there too.
        let error = options_from_params(&params_with("joint_state_period_s", "0.0001"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("joint_state_period_s"), "{error}");
        let good = options_from_params(&params_with("steps_per_unit", "[5000.0, 80000.0, 1.0]"));
        assert_eq!(good.unwrap().1.steps_per_unit, [5000.0, 80000.0, 1.0]);
    }

    /// Samples fall on one grid across plans (a plan's first sample continues the last
    /// one's), interpolate between points, skip a corner's repeated instant, and a long plan
    /// with two points yields all of its samples.
    #[test]
    fn samples_follow_one_grid_across_plans() {
        let first = PlannedMove {
            points: vec![
                point(0.0, 0.0, 0.1),
                point(0.5, 0.05, 0.1),
                point(0.5, 0.05, 0.2),
            ],
            ..Default::default()
        };
        let second = PlannedMove {
            points: vec![point(0.5, 0.05, 0.2), point(1.0, 0.15, 0.2)],
            ..Default::default()
        };
        let mut samples = PlanSamples::new(&first, 0.2, 0.0, 1_000);
        let taken: Vec<JointState> = samples.by_ref().collect();
        let next_t = samples.next_t();
        assert!((next_t - 0.6).abs() < 1e-12, "{next_t}");
        let taken_after: Vec<JointState> = PlanSamples::new(&second, 0.2, next_t, 1_000).collect();
        let r: Vec<f64> = taken
            .iter()
            .chain(&taken_after)
            .map(|s| s.position[1])
            .collect();
        let expected = [0.0, 0.02, 0.04, 0.07, 0.11, 0.15];
        assert_eq!(r.len(), expected.len(), "{r:?}");
        for (got, want) in r.iter().zip(expected) {
            assert!((got - want).abs() < 1e-12, "{r:?}");
        }
        let stamps: Vec<i64> = taken
            .iter()
            .chain(&taken_after)
            .map(|s| s.header.stamp.as_nanos())
            .collect();
        assert_eq!(
            stamps,
            [
                1_000,
                200_001_000,
                400_001_000,
                600_001_000,
                800_001_000,
                1_000_001_000
            ]
        );
        assert_eq!(PlanSamples::new(&first, 0.0, 0.0, 0).count(), 0);
        let dwell = PlannedMove {
            points: vec![point(0.0, 0.1, 0.0), point(36_000.0, 0.1, 0.0)],
            ..Default::default()
        };
        let dwell_samples = PlanSamples::new(&dwell, 0.02, 0.0, 0).count();
        assert!(
            (1_800_000..=1_800_001).contains(&dwell_samples),
            "{dwell_samples}"
        );
    }

    /// No executor heard from, or one that closed: nothing. Before the executor has a
    /// segment: the first horizon of the plan. Then: up to the stamp it grants.
    #[test]
    fn the_credit_bounds_the_plan_ahead() {
        assert!(!credit_allows(None, -1, 0.0));
        assert!(!credit_allows(Some(&credit(0, true)), -1, 0.0));
        let fresh = credit(0, false);
        assert!(credit_allows(Some(&fresh), -1, 0.0));
        assert!(credit_allows(Some(&fresh), 1_000, 1.999));
        assert!(!credit_allows(Some(&fresh), 1_000, 2.0));
        let epoch = 5_000_000_000;
        let granted = credit(epoch + 3_500_000_000, false);
        assert!(credit_allows(Some(&granted), epoch, 3.4999));
        assert!(!credit_allows(Some(&granted), epoch, 3.5));
    }
}
