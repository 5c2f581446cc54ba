//! The machine node loop: one ROS face for every machine backend.
//!
//! In: `/polar/steps` and `/screw/command` (the plan, ahead of time), `/gcode/progress` (to
//! learn that the plan is complete). Out, from *execution* and not from the plan:
//! `/joint_states` (the four joints of `urdf/polar_cell.urdf`) and `/tf` at `rate_hz` of machine
//! time, `/tf_static` and `/robot_description` (transient local) once, `/diagnostics` every
//! second, and `/cell/plan_credit`: how far ahead of execution the producers may plan
//! (`horizon_s`), which bounds the whole pipeline's plan-ahead in time. Services (std_srvs
//! Trigger): `/cell/pause`, `/cell/resume`, `/cell/cancel`, `/cell/estop`, `/cell/reset`.
//!
//! The clock is the process's monotonic clock times `speed` (a `speed`× faster simulation of
//! the same timeline); stamps are the wall clock at start plus machine time, so at speed 1
//! they are the wall clock. The [`Machine`] decides everything; this loop only feeds it
//! messages and the time, and publishes what it says.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context as _};
use cell_runtime::flow::consumer_state;
use cell_runtime::graph::Producer;
use cell_runtime::replay::{Joined, Numbered};
use cell_runtime::topics::{publisher_qos, suite_topic};
use cell_runtime::{
    now_ns, parse_service_mapping, reliable_qos, CellNode, LogLevel, ParamSpec, ParamValue, Params,
    ShutdownSignal, Wire,
};
use polar_cell_msgs::checkpoint::{reach, PlannerReach, ScrewReach};
use polar_cell_msgs::{
    DiagnosticStatus, GcodeProgress, Header, Hold, JointState, PlanCredit, ScrewCommand,
    StepSegment, StringMsg, TFMessage, Time, TriggerRequest, TriggerResponse,
    TIMELINE_TOLERANCE_NS,
};
use step_core::StepOptions;
use tokio::sync::{mpsc, watch};

use crate::{HoldReason, Machine, PlayerState};
use cell_runtime::tf::TfTree;

/// The most plan (s) the screw commands must reach ahead of the machine: it holds on the path
/// before that (a quarter of the horizon when that is less).
const SCREW_HOLD_MARGIN_MAX_S: f64 = 0.5;

/// Machine seconds per wall second a machine runs at (its `speed`; `print --speed` and a
/// print goal's speed are held to it too).
pub const SPEED_RANGE: std::ops::RangeInclusive<f64> = 0.01..=1000.0;

/// How long after the stream finished the last segments and screw commands the producers
/// acknowledged may still be on their way.
const END_OF_INPUT_PATIENCE: Duration = Duration::from_secs(10);

/// What the producers acknowledged having published that has not arrived yet (nothing:
/// the input is complete), one line per link.
fn input_missing<W: PartialEq>(
    planner: &Option<PlannerReach>,
    steps: &cell_runtime::replay::StepsJoin<W>,
    screw: &Option<ScrewReach>,
    commands: &cell_runtime::replay::SequenceJoin,
) -> Vec<String> {
    let mut lost = Vec::new();
    if let Some(r) = planner {
        // (A plan of no time has no segment: its end is its epoch.)
        let taken_ns = steps.end_ns().unwrap_or(r.plan_epoch_ns);
        if taken_ns < r.end_ns() - TIMELINE_TOLERANCE_NS {
            lost.push(format!(
                "/polar/steps ends {:.6} s into the plan, the planner published {:.6} s",
                (taken_ns - r.plan_epoch_ns) as f64 * 1e-9,
                r.t_s
            ));
        }
    }
    if let Some(r) = screw {
        if commands.next() < r.next_command {
            lost.push(format!(
                "/screw/command has {} commands, the screw driver published {}",
                commands.next(),
                r.next_command
            ));
        }
    }
    lost
}

/// The cell's URDF (the default of `urdf_file`).
pub const POLAR_CELL_URDF: &str = include_str!("../../../urdf/polar_cell.urdf");

/// The joints of `/joint_states`, in the order of [`crate::MachineState::positions`].
pub const JOINT_NAMES: [&str; 4] = ["bed_theta", "arm_r", "z", "screw"];

/// The pin's opening delay the screw driver assumes by default (its `pin_open_delay_s`).
pub const DEFAULT_PIN_OPEN_DELAY_S: f64 = 0.25;

/// The joint acceleration limits the planner plans within by default (its
/// `joint_accelerations`): a hold keeps to them.
pub const DEFAULT_JOINT_ACCELERATIONS: [f64; 3] = [40.0, 3.0, 0.5];

/// The parameters every machine node has (a backend adds its own); `tick_period_s` is the
/// backend's default look period (a bridge polls its line on it, the virtual executor does
/// not need to).
pub fn param_specs(tick_period_s: f64) -> Vec<ParamSpec> {
    let s = StepOptions::default();
    vec![
        ParamSpec::new("urdf_file", ParamValue::String(String::new()), "URDF of the cell for /tf and /robot_description (empty: the shipped urdf/polar_cell.urdf)"),
        ParamSpec::new("rate_hz", ParamValue::Double(50.0), "/joint_states and /tf per second of machine time").range(0.1, 1000.0),
        ParamSpec::new("horizon_s", ParamValue::Double(2.0), "plan time the producers may run ahead of execution").range(0.05, 3600.0),
        ParamSpec::new("speed", ParamValue::Double(1.0), "machine seconds per wall second (a faster simulation of the same timeline)").range(*SPEED_RANGE.start(), *SPEED_RANGE.end()),
        ParamSpec::new("tick_period_s", ParamValue::Double(tick_period_s), "wall time between the node's looks at the clock when nothing arrives").range(1e-4, 0.1),
        Producer::named_param_spec("producer", "gcode_streamer", "the node whose /gcode/progress this machine takes (relative: in its namespace; empty: any writer's); other writers are ignored"),
        Producer::named_param_spec("steps_producer", "polar_planner", "the node whose /polar/steps this machine executes (relative: in its namespace; empty: any writer's, e.g. a replayed bag); other writers are ignored"),
        Producer::named_param_spec("screw_producer", "screw_driver", "the node whose /screw/command this machine executes (relative: in its namespace; empty: any writer's); other writers are ignored"),
        ParamSpec::new("steps_per_unit", ParamValue::DoubleArray(s.steps_per_unit.to_vec()), "steps per rad (bed), per m (arm), per m (z): the planner's"),
        ParamSpec::new("step_timer_hz", ParamValue::Double(s.timer_hz), "step timer frequency: the planner's").range(1.0, 1e9),
        ParamSpec::new("joint_accelerations", ParamValue::DoubleArray(DEFAULT_JOINT_ACCELERATIONS.to_vec()), "bed (rad/s²), arm, z (m/s²) limits a pause or cancel keeps to: the planner's"),
        ParamSpec::new("initial_joints", ParamValue::DoubleArray(vec![0.0; 3]), "where the machine stands when the plan starts: bed (rad), arm (m), z (m): the planner's (a microcontroller that reports another position is refused)"),
        ParamSpec::new("pin_open_delay_s", ParamValue::Double(DEFAULT_PIN_OPEN_DELAY_S), "a resume waits this long at rest with the pin open: the screw driver's").range(0.0, 60.0),
        ParamSpec::new("screw_hold", ParamValue::String("zero_order".into()), "how rpm runs between screw commands: zero_order (compensated, smoothed or resampled commands) or first_order (raw breakpoints)"),
        ParamSpec::new("queue_capacity", ParamValue::Integer(4096), "step segments and screw commands held ahead of execution at most").range(16.0, 1e7),
        ParamSpec::new("planner_resume_timeout_s", ParamValue::Double(10.0), "a planner restarted mid-print must continue the plan within this long of the machine running out of plan (wall s; it holds on the path meanwhile) or the print stops and fails (0: never resume, stop at once)").range(0.0, 3600.0),
        ParamSpec::new("screw_resume_timeout_s", ParamValue::Double(10.0), "a screw driver restarted mid-print must continue its commands within this long of the machine holding for them (wall s; it holds on the path before the commands it has run out) or the print stops and fails (0: never resume, stop at once)").range(0.0, 3600.0),
        ParamSpec::new("exit_when_done", ParamValue::Bool(false), "end the node once a complete plan (its stream finished) has been executed (for scripts)"),
        ParamSpec::new("cell_services", ParamValue::Bool(true), "serve /cell/pause, /cell/resume, /cell/cancel, /cell/estop and /cell/reset (false: the process that runs this node serves them and hands their calls over, as polar-cell serve does for its jobs: one server per service for the server's whole life)"),
        ParamSpec::new("service_mapping", ParamValue::String("cyclone".into()), "request/reply wire format of the services: cyclone (rmw_cyclonedds clients), enhanced (rmw_fastrtps) or basic"),
        ParamSpec::new("await_subscribers", ParamValue::StringArray(vec![]), "nodes (relative: in this node's namespace) that must subscribe to /joint_states and /tf before the first state is published: a volatile sample reaches only readers matched by then, and a recorder matched late misses the first ones"),
        ParamSpec::new("await_subscribers_s", ParamValue::Double(5.0), "wait at most this long (wall s) for await_subscribers, then start without them, with a warning").range(0.0, 600.0),
    ]
}

/// What a caller in the same process asks of the machine (the services ask the same).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command {
    Pause,
    Resume,
    /// Stop on the path, then drop the rest of the plan.
    Cancel,
    EmergencyStop,
    Reset,
}

/// The machine's state for a caller in the same process (a print's progress and its end).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Status {
    pub state: Option<PlayerState>,
    pub hold: Option<HoldReason>,
    pub machine_time_s: f64,
    pub plan_time_s: f64,
    /// Plan queued ahead of execution (s).
    pub plan_ahead_s: f64,
    /// The move and G-code line executing now (or last).
    pub current: Option<(u64, u32)>,
    pub segments_received: u64,
    pub segments_completed: u64,
    pub underruns: u64,
    /// The plan is complete (the stream finished) and all of it has been executed.
    pub done: bool,
    /// A cancel was taken: the plan is being, or has been, dropped (at rest once `state` is
    /// not Running).
    pub cancelled: bool,
    pub positions: [f64; 4],
    pub fault: Option<String>,
    /// Machine time at which the first segment started (s).
    pub first_motion_s: Option<f64>,
    /// Machine time at which the whole plan had been executed (s).
    pub done_at_s: Option<f64>,
}

impl Status {
    /// Machine time from the first step to the end of the plan (or to now, while it runs);
    /// 0 before anything moved (s).
    pub fn executed_s(&self) -> f64 {
        self.first_motion_s
            .map_or(0.0, |t0| self.done_at_s.unwrap_or(self.machine_time_s) - t0)
    }

    /// The machine's state in one word: `printing`, `paused`, `cancelling`, `underrun`,
    /// `emergency_stop` or `waiting` (the action's feedback, the progress bar).
    pub fn state_label(&self) -> &'static str {
        match (self.state, self.hold) {
            (Some(PlayerState::Stopped), _) => "emergency_stop",
            (_, Some(HoldReason::Pause)) => "paused",
            (_, Some(HoldReason::Cancel)) => "cancelling",
            (_, Some(HoldReason::Underrun)) => "underrun",
            (Some(PlayerState::Running), None) => "printing",
            _ => "waiting",
        }
    }

    /// A cancel was taken and nothing runs any more: the stop on the path is over.
    pub fn cancelled_at_rest(&self) -> bool {
        self.cancelled && self.state != Some(PlayerState::Running)
    }
}

/// What every machine node is told by its parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineParams {
    /// The planner's step resolution and timer.
    pub steps: StepOptions,
    /// The planner's joint acceleration limits (a hold keeps to them).
    pub joint_accelerations: [f64; 3],
    /// The planner's start position (bed rad, arm m, z m).
    pub initial_joints: [f64; 3],
    /// The screw driver's pin opening delay.
    pub pin_open_delay_s: f64,
    /// How rpm runs between screw commands.
    pub screw_hold: Hold,
    pub queue_capacity: usize,
    pub rate_hz: f64,
    pub horizon_s: f64,
    pub speed: f64,
    /// The URDF's text.
    pub urdf: String,
}

impl MachineParams {
    pub fn from_params(p: &Params) -> anyhow::Result<MachineParams> {
        let three = |name: &str| -> anyhow::Result<[f64; 3]> {
            let v = p.f64s(name);
            match *v {
                [a, b, c] if v.iter().all(|x| x.is_finite() && *x > 0.0) => Ok([a, b, c]),
                _ => anyhow::bail!(
                    "parameter {name} needs 3 positive values (bed, arm, z), got {v:?}"
                ),
            }
        };
        let screw_hold = match p.string("screw_hold") {
            "zero_order" => Hold::ZeroOrder,
            "first_order" => Hold::FirstOrder,
            other => {
                anyhow::bail!("parameter screw_hold: `{other}` is not zero_order or first_order")
            }
        };
        let urdf = match p.string("urdf_file") {
            "" => POLAR_CELL_URDF.to_string(),
            path => {
                std::fs::read_to_string(path).with_context(|| format!("reading URDF {path}"))?
            }
        };
        Ok(MachineParams {
            steps: StepOptions {
                steps_per_unit: three("steps_per_unit")?,
                timer_hz: p.f64("step_timer_hz"),
            },
            joint_accelerations: three("joint_accelerations")?,
            initial_joints: p.finite3("initial_joints", "bed rad, arm m, z m")?,
            pin_open_delay_s: p.f64("pin_open_delay_s"),
            screw_hold,
            queue_capacity: p.i64("queue_capacity") as usize,
            rate_hz: p.f64("rate_hz"),
            horizon_s: p.f64("horizon_s"),
            speed: p.f64("speed"),
            urdf,
        })
    }

    /// The step counts of [`MachineParams::initial_joints`], rounded as the planner's step
    /// generator rounds its start, so the machine's counts and the plan's agree.
    pub fn initial_steps(&self) -> [i64; 3] {
        std::array::from_fn(|j| {
            (self.initial_joints[j] * self.steps.steps_per_unit[j]).round() as i64
        })
    }
}

/// The `/cell` services (`std_srvs/srv/Trigger`) and what each asks.
pub const SERVICES: [(&str, Command); 5] = [
    ("/cell/pause", Command::Pause),
    ("/cell/resume", Command::Resume),
    ("/cell/cancel", Command::Cancel),
    ("/cell/estop", Command::EmergencyStop),
    ("/cell/reset", Command::Reset),
];

/// A command from the machine node's own process, and where its answer goes if somebody
/// waits for it (a `polar-cell serve` handing over a `/cell` service call it took).
#[derive(Debug)]
pub struct Request {
    pub command: Command,
    pub answer: Option<tokio::sync::oneshot::Sender<(bool, String)>>,
}

impl From<Command> for Request {
    fn from(command: Command) -> Request {
        Request {
            command,
            answer: None,
        }
    }
}

/// What the operator's commands have made of the plan: every decision of the node loop that
/// depends on them, apart from DDS (so it is tested without it).
///
/// A plan that was cancelled or emergency-stopped is *dropped*, for good: a reset makes the
/// machine ready again, but the rest of that plan is not executed. Its producers still send
/// what they planned before they saw the credit close, and taken after a reset it would play
/// from wherever the stop left the machine, displaced by all that was dropped. A new plan
/// comes with a new print (a new graph).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
struct Control {
    /// A cancel was accepted (it may come to rest within the same tick, from a rest in the
    /// plan, so it is known from the command, not from watching the hold).
    cancelled: bool,
    /// The plan in hand is dropped: cancelled, or the machine was stopped (e-stop or fault).
    plan_dropped: bool,
    /// Paused by the operator (not by the node holding for screw commands).
    operator_paused: bool,
}

impl Control {
    /// Apply `command` to the machine; the reply a service caller gets.
    fn apply<M: Machine>(&mut self, executor: &mut M, command: Command) -> (bool, String) {
        const STOPPED: &str = "emergency stop in force: /cell/reset first";
        let now = executor.state();
        let stopped = now.state == PlayerState::Stopped;
        let reply = match command {
            Command::Pause | Command::Resume | Command::Cancel if stopped => {
                (false, STOPPED.into())
            }
            Command::Pause if now.hold == Some(HoldReason::Cancel) => (
                false,
                "cancelling: already stopping on the path, then dropping the plan".into(),
            ),
            Command::Pause if self.plan_dropped => (false, "no plan: it was dropped".into()),
            Command::Pause if self.operator_paused => (
                true,
                "already paused: holding on the path until /cell/resume".into(),
            ),
            Command::Pause => {
                executor.pause();
                self.operator_paused = true;
                (true, "pausing: decelerating along the path to rest".into())
            }
            // The node's own hold (screw commands ending too soon) is not the operator's to
            // end: it would start again at once, and brake again.
            Command::Resume if now.hold == Some(HoldReason::Pause) && !self.operator_paused => (
                false,
                "not paused: holding until the screw commands continue, then resuming by itself"
                    .into(),
            ),
            Command::Resume if now.hold == Some(HoldReason::Pause) => {
                executor.resume();
                self.operator_paused = false;
                (true, "resuming after the pin's opening delay".into())
            }
            Command::Resume => (false, "not paused".into()),
            Command::Cancel => {
                executor.cancel();
                self.cancelled = true;
                self.plan_dropped = true;
                self.operator_paused = false;
                (
                    true,
                    "cancelling: stopping along the path, then dropping the plan".into(),
                )
            }
            Command::EmergencyStop => {
                executor.emergency_stop();
                self.plan_dropped = true;
                (
                    true,
                    "emergency stop: stepping stopped, pin closed, screw stopped".into(),
                )
            }
            Command::Reset if stopped => {
                executor.reset();
                self.operator_paused = false;
                (
                    true,
                    "reset: the machine is ready; the stopped plan stays dropped (a new print starts a new one)".into(),
                )
            }
            Command::Reset => (false, "not stopped".into()),
        };
        self.observe(executor.state().state);
        reply
    }

    /// A machine seen stopped (an e-stop or a fault) has dropped its plan.
    fn observe(&mut self, state: PlayerState) {
        self.plan_dropped |= state == PlayerState::Stopped;
    }

    /// A cancel has come to rest: the machine no longer moves for it.
    fn cancelled_at_rest(&self, state: PlayerState) -> bool {
        self.cancelled && state != PlayerState::Running
    }
}

/// Run the executor on `node` until an error. `commands` come from the same process (a
/// print's Ctrl-C); `status` tells it how the machine is doing.
pub async fn run<M: Machine>(
    node: &mut CellNode,
    executor: &mut M,
    options: &MachineParams,
    mut commands: mpsc::UnboundedReceiver<Request>,
    status: watch::Sender<Status>,
) -> anyhow::Result<()> {
    let mapping = parse_service_mapping(node.params.string("service_mapping"))?;
    let serves_cell_services = node.params.bool("cell_services");
    let exit_when_done = node.params.bool("exit_when_done");
    let tree = TfTree::from_urdf(&options.urdf).context("URDF")?;
    tree.check_joints(&JOINT_NAMES)
        .context("parameter urdf_file")?;
    let capacity = options.queue_capacity;

    // Only the pipeline's own nodes drive the machine: a segment or a screw command from any
    // other writer on the domain would move it.
    let mut steps_from = Producer::named(node, "steps_producer", true)?;
    let mut screw_from = Producer::named(node, "screw_producer", true)?;
    let mut progress_from = Producer::named(node, "producer", true)?;
    // A restarted planner resumes the plan where it acknowledged (polar_planner::resume):
    // its repeats are dropped, and its first new segment must start where the plan taken so
    // far ends. A restarted screw driver resumes its numbered commands (screw_driver::stream):
    // repeats are dropped by number, and its first new command must be the next one. Until
    // it continues, the machine holds on the path before the commands it has run out. One
    // that does not continue within its timeout stops the machine on the path and fails the
    // print, saying why, instead of waiting for input that never fits. A segment or a command
    // lost anywhere (a gap) does the same.
    let mut stopping_for: Option<String> = None;
    let mut steps_join = cell_runtime::replay::StepsJoin::new();
    let resume_timeout = Duration::from_secs_f64(node.params.f64("planner_resume_timeout_s"));
    // Whether the planner was seen restarted and has not continued the plan yet, and since
    // when the machine has been starving for plan since then.
    let mut awaiting_planner = false;
    let mut planner_starved_since: Option<Instant> = None;
    let mut screw_join = cell_runtime::replay::SequenceJoin::new();
    let screw_resume_timeout = Duration::from_secs_f64(node.params.f64("screw_resume_timeout_s"));
    // The same for the screw driver; the stamp of the last command taken (how far the screw
    // is commanded); whether the machine holds for commands, and since when.
    let mut awaiting_screw = false;
    let mut screw_covered_ns: Option<i64> = None;
    let mut held_for_screw = false;
    let mut screw_starved_since: Option<Instant> = None;
    let mut screw_holds = 0u64;
    // Enough plan to stop in (a hold from full speed takes well under 0.1 s of plan) and to
    // notice in time at a high --speed; never more than the quarter of the horizon the
    // commands are normally short of it.
    let screw_margin_ns = (options.horizon_s / 4.0).min(SCREW_HOLD_MARGIN_MAX_S) * 1e9;
    let screw_margin_ns = screw_margin_ns as i64;
    // Screw commands that came after the machine passed their time, and how late one may
    // come before the print stops: the screw hold's margin, or 50 ms of wall time at the
    // machine's pace (a loop's pass at a high --speed), whichever is longer.
    let mut late_screw_commands = 0u64;
    let late_screw_tolerance_ns = screw_margin_ns.max((0.05e9 * options.speed) as i64);
    // The least the screw commands were ahead of the running machine (a measure of the
    // margin a lost screw driver leaves).
    let mut screw_ahead_min_ns = i64::MAX;
    let mut stop_issued = false;
    // Segments and screw commands that came for a dropped plan (in flight at the stop, or
    // sent by its producers since).
    let mut dropped_after_stop = 0u64;
    let mut operator_stop_at_ns: Option<i64> = None;
    let mut last_graph_look = Instant::now();
    let mut fault_at_ns: Option<i64> = None;
    let mut finished_at_ns: Option<i64> = None;
    let mut ignored = IgnoredWriters::default();
    let mut undecodable = cell_runtime::Undecodable::default();
    // A reader keeps at most its depth of samples not taken yet and drops the oldest beyond
    // it. A move is handed over whole, so one credit can bring thousands of screw commands
    // at once (seed 001's bench rig: all 5,944 of its file within 100 ms), more than the
    // loop takes meanwhile on a loaded machine: with a depth of 4,096, CI's RP2040 run lost
    // 237 of them. As deep as the writer, the reader drops nothing the writer has let go.
    let depth = |topic: &str| capacity.max(suite_topic(topic).map_or(0, |t| t.qos.depth));
    let steps_sub =
        node.subscription::<StepSegment>("/polar/steps", &reliable_qos(depth("/polar/steps")))?;
    let screw_sub = node
        .subscription::<ScrewCommand>("/screw/command", &reliable_qos(depth("/screw/command")))?;
    let progress_sub =
        node.subscription::<GcodeProgress>("/gcode/progress", &reliable_qos(1000))?;
    let joint_states =
        Arc::new(node.publisher::<JointState>("/joint_states", &publisher_qos("/joint_states"))?);
    let tf = Arc::new(node.publisher::<TFMessage>("/tf", &publisher_qos("/tf"))?);
    let tf_static = node.publisher::<TFMessage>("/tf_static", &publisher_qos("/tf_static"))?;
    let description =
        node.publisher::<StringMsg>("/robot_description", &publisher_qos("/robot_description"))?;
    let credit_pub = Arc::new(
        node.publisher::<PlanCredit>("/cell/plan_credit", &publisher_qos("/cell/plan_credit"))?,
    );
    // The node outlives this function's writers' last samples: a caller that ends the machine
    // and keeps its node (a print closing its bag) still has them repaired if lost.
    node.keep(joint_states.clone());
    node.keep(tf.clone());
    node.keep(credit_pub.clone());
    let mut servers = Vec::new();
    for (name, command) in SERVICES.into_iter().filter(|_| serves_cell_services) {
        let server = node.service::<TriggerRequest, TriggerResponse>(
            name,
            ("std_srvs", "Trigger"),
            mapping,
        )?;
        servers.push((server, command));
    }

    let awaited = node
        .params
        .strings("await_subscribers")
        .iter()
        .map(|name| node.names.resolve(name))
        .collect::<Result<Vec<_>, _>>()?;
    if !awaited.is_empty() {
        let max_wait = Duration::from_secs_f64(node.params.f64("await_subscribers_s"));
        let lacking = node
            .wait_subscribed(&["/joint_states", "/tf"], &awaited, max_wait)
            .await;
        if !lacking.is_empty() {
            cell_runtime::cell_log!(
                node,
                LogLevel::Warn,
                "after {} s still no subscription on {}: starting without it (what it records misses the first states)",
                max_wait.as_secs_f64(),
                lacking.join(", ")
            );
        }
    }
    let wall_start_ns = now_ns() as i64;
    let started = Instant::now();
    let speed = options.speed;
    let machine_ns = |at: Instant| ((at - started).as_nanos() as f64 * speed) as i64;
    executor.clock_started(started, speed);
    let stamp_at = |machine_ns: i64| Time::from_nanos(wall_start_ns + machine_ns);
    tf_static
        .publish(TFMessage {
            transforms: tree.static_transforms(stamp_at(0)),
        })
        .map_err(|e| anyhow!("/tf_static: {e:?}"))?;
    description
        .publish(StringMsg {
            data: options.urdf.clone(),
        })
        .map_err(|e| anyhow!("/robot_description: {e:?}"))?;
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "executing /polar/steps and /screw/command at {speed}× machine pace, horizon {} s",
        options.horizon_s
    );

    let sample_ns = (1e9 / options.rate_hz) as i64;
    let mut next_sample_ns = 0i64;
    let mut last_measured_ns: Option<i64> = None;
    let mut first_motion_s: Option<f64> = None;
    let mut start_wait: Option<Instant> = None;
    let mut done_at_s: Option<f64> = None;
    // The last two ticks at which plan time advanced, (machine s, plan s): the plan's end is
    // placed between them rather than at the tick that noticed it.
    let mut advancing: [Option<(f64, f64)>; 2] = [None, None];
    let mut pending_steps: VecDeque<StepSegment> = VecDeque::new();
    let mut pending_screw: VecDeque<ScrewCommand> = VecDeque::new();
    let mut received = 0u64;
    // The input ends when the streamer says the file is done AND what the planner and the
    // screw driver acknowledged having published (their checkpoints' reach, in the same
    // progress report) has all arrived: the `finished` flag travels on another topic and
    // can overtake the last segments and commands.
    let mut input_finished = false;
    let mut stream_finished = false;
    let mut stream_finished_at: Option<Instant> = None;
    let mut planner_reach: Option<PlannerReach> = None;
    let mut screw_reach: Option<ScrewReach> = None;
    let mut start_checked = false;
    let mut control = Control::default();
    let mut fault: Option<String> = None;
    let mut last_credit = (Instant::now() - Duration::from_secs(1), f64::NAN);
    let mut last_diagnostics = Instant::now();
    let mut last_status = Instant::now();
    let mut reported_underruns = 0u64;
    // The loop's own period (wall time). The core steps σ every control period whatever
    // the loop's period (it advances period by period to "now"), and commands and messages
    // wake the loop at once: the period only bounds how stale the published credit and
    // status may be. The loop also wakes at each instant of the sample grid, so a sample
    // goes out when it is due rather than up to a period late. 1 ms cost a fifth of a core
    // in timer wake-ups.
    let period = Duration::from_secs_f64(node.params.f64("tick_period_s"));
    let mut wake = Instant::now();
    // Service replies waiting for their clients' response readers.
    let mut replies = cell_runtime::service::Replies::default();
    loop {
        // A command, and who asked for it.
        let mut requested: Option<(Command, Caller)> = None;
        tokio::select! {
            taken = steps_sub.async_take() => { 'steps: {
                let Some((s, info)) = undecodable.take(node, "/polar/steps", taken)? else {
                    break 'steps;
                };
                let over = input_finished && executor.is_drained();
                let admitted = steps_from.admits(&info);
                // From another process than the planner's first (or adopted) one.
                let from_restarted = admitted && steps_from.restarted(&info);
                if !admitted {
                    ignored.note(node, "/polar/steps", "ignored_foreign_steps", steps_from.name());
                } else if control.plan_dropped {
                    dropped_after_stop += 1;
                } else if from_restarted && !over && resume_timeout.is_zero() {
                    stopping_for.get_or_insert_with(|| restarted(steps_from.name(), "/polar/steps"));
                } else {
                    match steps_join.take(&s, info.publisher_gid()) {
                        Joined::Repeat => {}
                        Joined::Gap { move_sequence, expected_ns, found_ns } => {
                            let after = if from_restarted {
                                format!(" after {} restarted", steps_from.name())
                            } else {
                                String::new()
                            };
                            stopping_for.get_or_insert_with(|| format!(
                                "/polar/steps lost part of the plan{after}: move {move_sequence} (line {}) starts {:.6} s after the plan taken so far ends",
                                s.source_line,
                                (found_ns - expected_ns) as f64 * 1e-9
                            ));
                        }
                        Joined::New => {
                            if from_restarted {
                                steps_from.adopt(&info);
                                awaiting_planner = false;
                                planner_starved_since = None;
                                cell_runtime::cell_log!(
                                    node,
                                    LogLevel::Info,
                                    "{} restarted and continues the plan at move {} (line {}); {} repeated segments dropped",
                                    steps_from.name(),
                                    s.move_sequence,
                                    s.source_line,
                                    steps_join.repeats()
                                );
                            }
                            received += 1;
                            pending_steps.push_back(s);
                        }
                    }
                }
            }}
            taken = screw_sub.async_take() => { 'screw: {
                let Some((c, info)) = undecodable.take(node, "/screw/command", taken)? else {
                    break 'screw;
                };
                if !screw_from.admits(&info) {
                    ignored.note(
                        node,
                        "/screw/command",
                        "ignored_foreign_screw_commands",
                        screw_from.name(),
                    );
                } else if control.plan_dropped {
                    dropped_after_stop += 1;
                } else {
                    let from_restarted = screw_from.restarted(&info);
                    let over = input_finished && executor.is_drained();
                    if from_restarted && !over && screw_resume_timeout.is_zero() {
                        stopping_for
                            .get_or_insert_with(|| restarted(screw_from.name(), "/screw/command"));
                    } else {
                        match screw_join.take(c.sequence) {
                            Numbered::Repeat => {}
                            Numbered::Gap { expected, found } => {
                                let after = if from_restarted {
                                    format!(" after {} restarted", screw_from.name())
                                } else {
                                    String::new()
                                };
                                stopping_for.get_or_insert_with(|| format!(
                                    "/screw/command lost {} commands{after}: command {found} (line {}) came after command {}",
                                    found - expected,
                                    c.source_line,
                                    expected.saturating_sub(1),
                                ));
                            }
                            Numbered::New => {
                                if from_restarted {
                                    screw_from.adopt(&info);
                                    awaiting_screw = false;
                                    screw_starved_since = None;
                                    cell_runtime::cell_log!(
                                        node,
                                        LogLevel::Info,
                                        "{} restarted and continues the screw commands at command {} (line {}); {} repeated commands dropped",
                                        screw_from.name(),
                                        c.sequence,
                                        c.source_line,
                                        screw_join.repeats()
                                    );
                                }
                                screw_covered_ns = Some(c.header.stamp.as_nanos());
                                pending_screw.push_back(c);
                            }
                        }
                    }
                }
            }}
            taken = progress_sub.async_take() => {
                if let Ok((p, info)) = taken {
                    if progress_from.admits(&info) {
                        stream_finished |= p.finished;
                        let reach_of = |producer: &Producer| {
                            consumer_state(&p, producer.name()).map(|(_, state)| state)
                        };
                        if let Some((_, r)) = reach_of(&steps_from).and_then(reach::<PlannerReach>) {
                            planner_reach = Some(r);
                        }
                        if let Some((_, r)) = reach_of(&screw_from).and_then(reach::<ScrewReach>) {
                            screw_reach = Some(r);
                        }
                    } else {
                        ignored.note(
                            node,
                            "/gcode/progress",
                            "ignored_foreign_progress",
                            progress_from.name(),
                        );
                    }
                }
            }
            Some(request) = commands.recv() => {
                requested = Some((request.command, Caller::Process(request.answer)));
            }
            (index, request) = next_request(&servers), if !servers.is_empty() => {
                if let Some(request) = request {
                    requested = Some((servers[index].1, Caller::Service(index, request)));
                }
            }
            _ = tokio::time::sleep_until(wake.into()) => {}
        }
        if stream_finished && !input_finished {
            let missing = input_missing(&planner_reach, &steps_join, &screw_reach, &screw_join);
            let since = *stream_finished_at.get_or_insert_with(Instant::now);
            if missing.is_empty() {
                input_finished = true;
            } else if since.elapsed() >= END_OF_INPUT_PATIENCE && !control.plan_dropped {
                // Reliable delivery repairs a lost sample within a heartbeat or two: this
                // much later, the end of the plan is lost, and the print did not end as planned.
                stopping_for.get_or_insert_with(|| {
                    format!(
                        "the end of the plan was lost: {} s after the stream finished, {}",
                        END_OF_INPUT_PATIENCE.as_secs(),
                        missing.join("; ")
                    )
                });
            }
        }
        // The first segment taken must be the plan's start: a plan whose first segments
        // were dropped (from a writer not yet announced, say) would play displaced.
        if let (false, Some(r), Some(first_ns)) =
            (start_checked, planner_reach, steps_join.first_start_ns())
        {
            start_checked = true;
            if first_ns - r.plan_epoch_ns > TIMELINE_TOLERANCE_NS && !control.plan_dropped {
                stopping_for.get_or_insert_with(|| format!(
                    "/polar/steps lost the plan's start: the first segment taken starts {:.6} s after plan time 0",
                    (first_ns - r.plan_epoch_ns) as f64 * 1e-9
                ));
            }
        }
        if let Some((command, caller)) = requested {
            let (success, message) = control.apply(executor, command);
            if command == Command::Reset && success {
                // What stopped the machine is over with the plan it stopped: a fault kept
                // would stop it again at once.
                fault = None;
                fault_at_ns = None;
                stopping_for = None;
                stop_issued = false;
                held_for_screw = false;
            }
            match caller {
                Caller::Process(answer) => {
                    cell_runtime::cell_log!(node, LogLevel::Info, "{command:?}: {message}");
                    if let Some(answer) = answer {
                        let _ = answer.send((success, message));
                    }
                }
                Caller::Service(index, request) => {
                    let service = SERVICES[index].0;
                    cell_runtime::cell_log!(node, LogLevel::Info, "{service}: {message}");
                    replies.push(index, request, Wire(TriggerResponse { success, message }));
                }
            }
        }
        for (index, problem) in replies.send_ready(|index| &servers[index].0) {
            let service = SERVICES[index].0;
            cell_runtime::cell_log!(node, LogLevel::Warn, "{service}: {problem}");
        }
        control.observe(executor.state().state);
        // A restarted producer that sends nothing is seen in the graph's announcements
        // (looked at every half second, and at once after a producer's first message, which
        // fixes who announced it before), while the print lasts.
        let graph_look_due = last_graph_look.elapsed() >= Duration::from_millis(500)
            || steps_from.needs_look()
            || screw_from.needs_look();
        if stopping_for.is_none()
            && !control.plan_dropped
            && graph_look_due
            && !(input_finished && executor.is_drained())
        {
            last_graph_look = Instant::now();
            if screw_from.announced_elsewhere() {
                if screw_resume_timeout.is_zero() {
                    stopping_for
                        .get_or_insert_with(|| restarted(screw_from.name(), "/screw/command"));
                } else if !awaiting_screw {
                    awaiting_screw = true;
                    cell_runtime::cell_log!(
                        node,
                        LogLevel::Warn,
                        "{} restarted mid-print: waiting up to {} s for it to continue the screw commands (the machine holds on the path before the commands it has run out)",
                        screw_from.name(),
                        screw_resume_timeout.as_secs_f64()
                    );
                }
            }
            if steps_from.announced_elsewhere() {
                if resume_timeout.is_zero() {
                    stopping_for
                        .get_or_insert_with(|| restarted(steps_from.name(), "/polar/steps"));
                } else if !awaiting_planner {
                    awaiting_planner = true;
                    cell_runtime::cell_log!(
                        node,
                        LogLevel::Warn,
                        "{} restarted mid-print: waiting up to {} s for it to continue the plan (the machine holds on the path if the plan runs out)",
                        steps_from.name(),
                        resume_timeout.as_secs_f64()
                    );
                }
            }
        }
        // The wait counts only while the machine starves: paused by the operator with plan in
        // hand, a resumed planner has nothing new to send until the machine moves again.
        let state_now = executor.state();
        // Held for screw commands counts too: with the planner away, the screw driver has no
        // plans to command, and its commands end before the plan does.
        let starving = state_now.hold == Some(HoldReason::Underrun)
            || held_for_screw
            || (state_now.state == PlayerState::Idle && !input_finished);
        if awaiting_planner {
            planner_starved_since = match (starving, planner_starved_since) {
                (true, None) => Some(Instant::now()),
                (true, since) => since,
                (false, _) => None,
            };
        }
        if let Some(at) = planner_starved_since {
            if at.elapsed() >= resume_timeout
                && !(input_finished && executor.is_drained())
                && !control.plan_dropped
            {
                stopping_for.get_or_insert_with(|| {
                    format!(
                        "{} restarted mid-print and did not continue the plan within {} s of the machine running out of it",
                        steps_from.name(),
                        resume_timeout.as_secs_f64()
                    )
                });
            }
        }
        // Screw commands must cover the plan the machine runs: when they reach less than the
        // margin ahead (0.5 s, or a quarter of a shorter horizon; the driver cuts its chunks
        // at a quarter, so they normally reach three quarters ahead: 1.45 s at least in a
        // 2 s-horizon print of finger), hold on the path, and go on once they reach twice
        // the margin again and no restarted driver is awaited. Once the file is all acknowledged, every command
        // is published.
        let plan_now_ns = executor
            .epoch_ns()
            .map(|epoch| epoch + (state_now.plan_time_s * 1e9) as i64);
        let screw_ahead_ns = plan_now_ns
            .zip(screw_covered_ns)
            .map(|(now, covered)| covered - now);
        if let Some(ahead) = screw_ahead_ns.filter(|_| {
            !input_finished && state_now.state == PlayerState::Running && !awaiting_screw
        }) {
            screw_ahead_min_ns = screw_ahead_min_ns.min(ahead);
        }
        let must_hold = !input_finished
            && stopping_for.is_none()
            && !control.plan_dropped
            && screw_ahead_ns.is_some_and(|ahead| ahead < screw_margin_ns);
        if must_hold && state_now.state == PlayerState::Running && state_now.hold.is_none() {
            // (Again after an operator's resume meanwhile: the commands still end.)
            if !held_for_screw {
                held_for_screw = true;
                screw_holds += 1;
                cell_runtime::cell_log!(
                    node,
                    LogLevel::Warn,
                    "screw commands end {:.3} s of plan ahead: holding on the path until {} continues them",
                    screw_ahead_ns.unwrap_or(0) as f64 * 1e-9,
                    screw_from.name()
                );
            }
            executor.pause();
        } else if held_for_screw
            && (input_finished
                || stopping_for.is_some()
                || control.plan_dropped
                || screw_ahead_ns
                    .is_some_and(|ahead| !awaiting_screw && ahead >= 2 * screw_margin_ns))
        {
            held_for_screw = false;
            screw_starved_since = None;
            if !control.operator_paused && !control.plan_dropped && stopping_for.is_none() {
                executor.resume();
                cell_runtime::cell_log!(node, LogLevel::Info, "screw commands continue: resuming");
            }
        }
        // Only the screw driver's own wait: without plans it has nothing to command.
        if held_for_screw && !awaiting_planner && !control.plan_dropped {
            let since = *screw_starved_since.get_or_insert_with(Instant::now);
            if since.elapsed() >= screw_resume_timeout && !screw_resume_timeout.is_zero() {
                stopping_for.get_or_insert_with(|| {
                    format!(
                        "{} did not continue the screw commands within {} s of the machine holding for them",
                        screw_from.name(),
                        screw_resume_timeout.as_secs_f64()
                    )
                });
            }
        }
        // A producer restarted: stop on the path as a cancel does; at rest, the print fails.
        if let Some(reason) = &stopping_for {
            if executor.is_drained() || executor.state().state == PlayerState::Stopped {
                fault.get_or_insert_with(|| reason.clone());
            } else if !stop_issued {
                stop_issued = true;
                cell_runtime::cell_log!(node, LogLevel::Error, "{reason}: stopping on the path");
                executor.cancel();
            }
        }
        // Once cancelled or stopped, what is still in flight for the dropped plan is dropped
        // too: a stopped machine would refuse it, and that refusal is no fault of the print.
        // (Here, after every check of this pass that may decide a stop: a stop decided above
        // must not queue more plan into the machine it is stopping.)
        if control.plan_dropped || stopping_for.is_some() {
            pending_steps.clear();
            pending_screw.clear();
        }
        // Queue what the core has room for; the rest waits (the credit bounds how much).
        let (mut free_steps, free_screw) = executor.free_slots();
        for _ in 0..free_screw.min(pending_screw.len()) {
            let c = pending_screw.pop_front().expect("counted");
            // Where the machine plays it: a pin opening stamped before the plan's start
            // (its delay reaches back) plays at the start.
            let due_ns = executor
                .epoch_ns()
                .map_or(c.header.stamp.as_nanos(), |epoch| {
                    c.header.stamp.as_nanos().max(epoch)
                });
            let late_ns = plan_now_ns.map_or(0, |now| now - due_ns);
            if late_ns > TIMELINE_TOLERANCE_NS {
                // The machine has passed its time: played now, it feeds from here, and what
                // it should have fed since is missing. A little late (within the screw hold's
                // own reach: its margin, or a loop's pass at a high --speed) is counted; far
                // beyond that the screw driver is not keeping up, and the print stops on
                // the path.
                late_screw_commands += 1;
                if late_ns > late_screw_tolerance_ns {
                    stopping_for.get_or_insert_with(|| format!(
                        "screw command {} (line {}) for plan time {:.3} s came {:.3} s after the machine passed it",
                        c.sequence,
                        c.source_line,
                        executor
                            .epoch_ns()
                            .map_or(0.0, |epoch| (due_ns - epoch) as f64 * 1e-9),
                        late_ns as f64 * 1e-9
                    ));
                    pending_screw.clear();
                    pending_steps.clear();
                    break;
                }
            }
            if let Err(e) = executor.on_screw(&c) {
                fault.get_or_insert(format!("screw command at line {}: {e}", c.source_line));
            }
        }
        // From rest, start only with half a horizon of plan in hand (or the whole plan, or
        // after half a second): a start on the first segment alone would underrun at once.
        // Nor before the screw driver's first command, within the same half second: one
        // that came after the machine passed its time would stop the print. (A print that
        // extrudes only later, or never, has none yet, and starts after the half second.)
        let starting = executor.is_drained() && !input_finished;
        if starting && !pending_steps.is_empty() {
            let waiting_since = *start_wait.get_or_insert_with(Instant::now);
            let in_hand_s: f64 = pending_steps.iter().map(|s| s.duration_s).sum();
            if (in_hand_s < options.horizon_s / 2.0 || screw_covered_ns.is_none())
                && waiting_since.elapsed() < Duration::from_millis(500)
            {
                free_steps = 0;
            }
        }
        if !starting {
            start_wait = None;
        }
        for _ in 0..free_steps.min(pending_steps.len()) {
            let s = pending_steps.pop_front().expect("counted");
            if let Err(e) = executor.on_segment(&s) {
                fault.get_or_insert(format!(
                    "step segment of move {} (line {}): {e}",
                    s.move_sequence, s.source_line
                ));
            }
        }
        if input_finished && pending_steps.is_empty() {
            executor.finish_input();
        }
        let now = Instant::now();
        let machine_now = machine_ns(now);
        // Samples on a regular grid of machine time: execute to each grid instant, sample
        // there (a late tick publishes late, but what it publishes is exact for its stamp).
        // Catch up after a late tick; after a real stall of the process (a quarter second
        // of wall time), skip to now rather than publish a burst.
        if machine_now - next_sample_ns > (10 * sample_ns).max((0.25e9 * speed) as i64) {
            next_sample_ns = machine_now - machine_now % sample_ns; // fell far behind: skip
        }
        while next_sample_ns <= machine_now {
            if let Err(e) = executor.on_tick(next_sample_ns) {
                fault.get_or_insert(e.to_string());
            }
            let state = executor.state();
            let measured_ns = state.measured_ns.unwrap_or(next_sample_ns);
            next_sample_ns += sample_ns;
            // A measurement already published (no newer one since) is not published again.
            if last_measured_ns.is_some_and(|last| measured_ns <= last) {
                continue;
            }
            last_measured_ns = Some(measured_ns);
            let stamp = stamp_at(measured_ns);
            let _ = joint_states.publish(JointState {
                header: Header {
                    stamp,
                    frame_id: String::new(),
                },
                name: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
                position: state.positions.to_vec(),
                velocity: state.velocities.to_vec(),
                effort: vec![],
            });
            let _ = tf.publish(TFMessage {
                transforms: tree.moving_transforms(stamp, |joint| {
                    JOINT_NAMES
                        .iter()
                        .position(|n| *n == joint)
                        .map(|i| state.positions[i])
                }),
            });
        }
        if let Err(e) = executor.on_tick(machine_now) {
            fault.get_or_insert(e.to_string());
        }
        let to_next_sample = Duration::from_nanos(
            ((next_sample_ns - machine_now).max(0) as f64 / speed).ceil() as u64,
        );
        wake = now + period.min(to_next_sample);
        if fault.is_some() && executor.state().state != PlayerState::Stopped {
            executor.emergency_stop();
        }
        let state = executor.state();
        // Start and end of the motion as the plan clock places them, not when this loop saw
        // them: a microcontroller's report reaches us a line latency and a loop period late
        // (0.1 s of machine time at 20x). Plan time runs at machine pace outside holds.
        if first_motion_s.is_none() && state.state == PlayerState::Running {
            first_motion_s = Some((state.machine_time_s - state.plan_time_s).max(0.0));
        }
        if advancing[1].is_none_or(|(_, plan_s)| state.plan_time_s > plan_s) {
            advancing = [
                advancing[1],
                Some((state.machine_time_s, state.plan_time_s)),
            ];
        }
        // Credit: as far as the producers may plan; repeated so a late joiner learns it.
        let credit_due = now - last_credit.0 >= Duration::from_millis(100)
            || (state.plan_time_s - last_credit.1).abs() >= options.horizon_s / 20.0;
        if credit_due {
            last_credit = (now, state.plan_time_s);
            let (executed_until, accept_until) = match executor.epoch_ns() {
                Some(epoch) => (
                    Time::after(epoch, state.plan_time_s),
                    Time::after(epoch, state.plan_time_s + options.horizon_s),
                ),
                None => (Time::default(), Time::default()),
            };
            let _ = credit_pub.publish(PlanCredit {
                header: Header {
                    stamp: stamp_at(machine_now),
                    frame_id: String::new(),
                },
                executor: node.fully_qualified_name(),
                executed_until,
                accept_until,
                horizon_s: options.horizon_s,
                closed: control.plan_dropped,
            });
        }
        let (completed, last_completed) = executor.completed();
        let underruns = executor.underruns();
        let done = input_finished
            && pending_steps.is_empty()
            && executor.is_drained()
            && fault.is_none()
            && stopping_for.is_none()
            // (A plan executed to its end stays done whatever comes after.)
            && (!control.plan_dropped || done_at_s.is_some());
        if done && done_at_s.is_none() {
            let end_s = state.plan_time_s;
            done_at_s = Some(match advancing {
                [Some((machine_s, plan_s)), Some((_, last_plan_s))] if last_plan_s >= end_s => {
                    machine_s + (end_s - plan_s)
                }
                _ => state.machine_time_s,
            });
        }
        // The status watch wakes whoever watches it (a print's progress, its end): at once
        // when the state changes, else at most every 50 ms of wall time.
        let next = Status {
            state: Some(state.state),
            // Holding for screw commands is an underrun of the plan's input, not a pause.
            hold: match state.hold {
                Some(HoldReason::Pause) if held_for_screw && !control.operator_paused => {
                    Some(HoldReason::Underrun)
                }
                hold => hold,
            },
            machine_time_s: state.machine_time_s,
            plan_time_s: state.plan_time_s,
            plan_ahead_s: executor.plan_ahead_s(),
            current: state.current.or(last_completed),
            segments_received: received,
            segments_completed: completed,
            underruns,
            done,
            cancelled: control.cancelled,
            positions: state.positions,
            fault: fault.clone(),
            first_motion_s,
            done_at_s,
        };
        let changed = {
            let last = status.borrow();
            (
                last.state,
                last.hold,
                last.done,
                last.cancelled,
                &last.fault,
                last.first_motion_s,
            ) != (
                next.state,
                next.hold,
                next.done,
                next.cancelled,
                &next.fault,
                next.first_motion_s,
            )
        };
        let executed_s = next.executed_s();
        if changed || last_status.elapsed() >= Duration::from_millis(50) {
            last_status = Instant::now();
            status.send_replace(next);
        }
        // A script's machine ends at a fault once the sample grid has passed it, so the
        // last sample (if the machine had one to give) shows it standing where it stopped.
        if let (Some(f), true) = (&fault, exit_when_done) {
            let since_ns = *fault_at_ns.get_or_insert(machine_now);
            // (Not before the service replies have gone: a caller would wait for ever.)
            if state.state == PlayerState::Stopped
                && next_sample_ns > since_ns + sample_ns
                && replies.is_empty()
            {
                cell_runtime::cell_log!(node, LogLevel::Error, "the machine stopped: {f}");
                anyhow::bail!("the machine stopped: {f}");
            }
        }
        // A script's machine ends when the operator stopped its plan as well (nothing more of
        // it will run), once at rest and the grid has passed the stop.
        let operator_stop = if state.state == PlayerState::Stopped {
            Some("emergency stop (/cell/estop)")
        } else if control.cancelled_at_rest(state.state) {
            Some("cancelled (/cell/cancel): stopped on the path")
        } else {
            None
        };
        if let (Some(how), true, None, None) = (operator_stop, exit_when_done, &fault, done_at_s) {
            let since_ns = *operator_stop_at_ns.get_or_insert(machine_now);
            if next_sample_ns > since_ns + sample_ns && replies.is_empty() {
                cell_runtime::cell_log!(node, LogLevel::Warn, "the plan was dropped: {how}");
                anyhow::bail!("the plan was dropped: {how}");
            }
        }
        // And at the end once the grid has passed it too: the last sample shows the machine
        // at rest where the plan ends (it used to be up to a sample period short of it).
        let done_at_ns = done.then(|| *finished_at_ns.get_or_insert(machine_now));
        if done_at_ns.is_some_and(|at| next_sample_ns > at + sample_ns)
            && exit_when_done
            && replies.is_empty()
        {
            cell_runtime::cell_log!(
                node,
                LogLevel::Info,
                "plan executed: {completed} segments, {executed_s:.3} s of machine time"
            );
            return Ok(());
        }
        if last_diagnostics.elapsed() >= Duration::from_secs(1) || underruns > reported_underruns {
            last_diagnostics = Instant::now();
            let (level, message) = match (&fault, state.state, state.hold) {
                (Some(f), _, _) => (DiagnosticStatus::ERROR, format!("fault: {f}")),
                (None, PlayerState::Stopped, _) => (
                    DiagnosticStatus::ERROR,
                    "emergency stop: /cell/reset to leave".into(),
                ),
                (None, _, Some(HoldReason::Underrun)) => (
                    DiagnosticStatus::WARN,
                    "underrun: the plan ran short, holding at rest on the path".into(),
                ),
                (None, _, Some(HoldReason::Pause))
                    if held_for_screw && !control.operator_paused =>
                {
                    (
                        DiagnosticStatus::WARN,
                        "holding on the path until the screw commands continue".into(),
                    )
                }
                (None, _, Some(HoldReason::Pause)) => (DiagnosticStatus::OK, "paused".into()),
                (None, _, Some(HoldReason::Cancel)) => (DiagnosticStatus::OK, "cancelling".into()),
                (None, PlayerState::Idle, None) => (DiagnosticStatus::OK, "idle".into()),
                (None, _, None) => (DiagnosticStatus::OK, "executing".into()),
            };
            reported_underruns = underruns;
            let mut values = vec![
                ("machine_time_s", format!("{:.3}", state.machine_time_s)),
                ("plan_time_s", format!("{:.3}", state.plan_time_s)),
                ("plan_ahead_s", format!("{:.3}", executor.plan_ahead_s())),
                ("feed", format!("{:.3}", state.feed)),
                ("segments_received", received.to_string()),
                ("segments_repeated", steps_join.repeats().to_string()),
                ("screw_commands_repeated", screw_join.repeats().to_string()),
                ("screw_holds", screw_holds.to_string()),
                ("late_screw_commands", late_screw_commands.to_string()),
                ("dropped_after_stop", dropped_after_stop.to_string()),
                (
                    "screw_ahead_min_s",
                    match screw_ahead_min_ns {
                        i64::MAX => "none".to_string(),
                        ns => format!("{:.3}", ns as f64 * 1e-9),
                    },
                ),
                ("segments_completed", completed.to_string()),
                ("underruns", underruns.to_string()),
                ("screw_rpm", format!("{:.2}", state.screw_rpm)),
                ("pin_open", state.pin_open.to_string()),
            ];
            values.extend(executor.diagnostics());
            for (&key, count) in &ignored.counts {
                values.push((key, count.to_string()));
            }
            values.push(("undecodable_samples", undecodable.total().to_string()));
            node.diagnose(level, &message, &values);
        }
    }
}

/// Why the machine stops when a plan producer's messages come from a new process (a screw
/// driver, or a planner when resuming is off).
fn restarted(producer: &str, topic: &str) -> String {
    format!(
        "{producer} restarted mid-print ({topic} now comes from another process): what it \
         sends no longer continues the plan, and a restarted planner or screw driver cannot \
         resume a print"
    )
}

/// How a machine node runs: the node, commands from its own process, its status out.
pub type RunFn = for<'a> fn(
    &'a mut CellNode,
    mpsc::UnboundedReceiver<Request>,
    watch::Sender<Status>,
) -> std::pin::Pin<
    Box<dyn std::future::Future<Output = anyhow::Result<()>> + 'a>,
>;

/// Whether the machine has a plan under way: it moves, or holds on the path with more to
/// run. Stopping such a machine is a stop on the path, not letting go of it.
fn plan_under_way(s: &Status) -> bool {
    s.first_motion_s.is_some()
        && !s.done
        && !s.cancelled_at_rest()
        && s.fault.is_none()
        && s.state != Some(PlayerState::Stopped)
}

/// A machine node as its own process: started from its command line, run until an error or
/// SIGINT/SIGTERM (nobody else in the process sends commands or watches the status).
///
/// A signal while a plan is under way (`ros2 launch`'s Ctrl-C, a script's `kill`) stops the
/// machine on the path first, as `/cell/cancel` does, and ends the node once at rest: a
/// machine let go mid-move would stop at once (an MCU's bridge dropped sends its emergency
/// stop). A second signal is the emergency stop (Ctrl-C twice), except SIGTERM after SIGINT
/// (a launcher escalating, or a script stopping its nodes after a terminal's Ctrl-C reached
/// them as well): the stop on the path goes on.
pub async fn main_with_args(
    name: &str,
    specs: &[ParamSpec],
    argv: Vec<String>,
    run: RunFn,
) -> anyhow::Result<()> {
    /// How long the last samples at rest get to go out, and an emergency stop to act.
    const LINGER: Duration = Duration::from_millis(150);
    let mut signals = cell_runtime::ShutdownSignals::new().context("signal handlers")?;
    let mut node = CellNode::start_from_argv(name, specs, &argv)?;
    let (commands, receiver) = mpsc::unbounded_channel();
    let (status_tx, status) = watch::channel(Status::default());
    let running = run(&mut node, receiver, status_tx);
    tokio::pin!(running);
    let mut stopping: Option<ShutdownSignal> = None;
    // When the node ends: once a stop has come to rest (and its samples are out).
    let mut end_at: Option<tokio::time::Instant> = None;
    let mut look = tokio::time::interval(Duration::from_millis(10));
    loop {
        tokio::select! {
            result = &mut running => {
                // The stop asked for here ended the plan: no error of the node's.
                // (A fault during that stop is the node's error all the same.)
                let asked = stopping.is_some() && {
                    let s = status.borrow();
                    !plan_under_way(&s) && s.fault.is_none()
                };
                return match result {
                    Err(_) if asked => Ok(()),
                    other => other,
                };
            }
            signal = signals.next_kind() => {
                let under_way = plan_under_way(&status.borrow());
                match stopping {
                    None if under_way => {
                        eprintln!(
                            "{name}: stopping on the path (Ctrl-C again: emergency stop)"
                        );
                        let _ = commands.send(Command::Cancel.into());
                        stopping = Some(signal);
                    }
                    None => return Ok(()),
                    // SIGTERM after SIGINT: a launcher escalating, or a script stopping its
                    // nodes after a terminal's Ctrl-C reached them too. Not a second stop.
                    Some(ShutdownSignal::Interrupt) if signal == ShutdownSignal::Terminate => {}
                    Some(_) if under_way && end_at.is_none() => {
                        eprintln!("{name}: emergency stop");
                        let _ = commands.send(Command::EmergencyStop.into());
                        end_at = Some(tokio::time::Instant::now() + LINGER);
                    }
                    Some(_) if !under_way => return Ok(()),
                    Some(_) => {}
                }
            }
            _ = look.tick(), if stopping.is_some() => {
                if end_at.is_none() && !plan_under_way(&status.borrow()) {
                    end_at = Some(tokio::time::Instant::now() + LINGER);
                }
                if end_at.is_some_and(|at| tokio::time::Instant::now() >= at) {
                    return Ok(());
                }
            }
        }
    }
}

/// Who asked for a command: the node's own process (maybe waiting for the answer), or a
/// caller of one of its `/cell` services (by index in [`SERVICES`]).
enum Caller {
    Process(Option<tokio::sync::oneshot::Sender<(bool, String)>>),
    Service(usize, cell_runtime::service::Request),
}

/// A `/cell` service's server.
pub type TriggerServer = ros2_client::Server<Wire<TriggerRequest>, Wire<TriggerResponse>>;

/// The first service with a request waiting, and the request.
pub async fn next_request(
    servers: &[(TriggerServer, Command)],
) -> (usize, Option<cell_runtime::service::Request>) {
    let futures = servers.iter().enumerate().map(|(i, (s, _))| {
        Box::pin(async move { (i, cell_runtime::service::receive(s).await.map(|(r, _)| r)) })
    });
    futures::future::select_all(futures).await.0
}

/// Messages taken from writers that are not the named producer's: counted, and logged the
/// first time per topic (a flood of forgeries must not flood the log) — but not in the first
/// seconds: the producer's own first messages can arrive before its announcement (the
/// streamer's first progress report did in most prints, and its warning alarmed for nothing).
struct IgnoredWriters {
    /// By diagnostics key, one per topic.
    counts: std::collections::BTreeMap<&'static str, u64>,
    logged: std::collections::BTreeSet<&'static str>,
    started: Instant,
}

impl Default for IgnoredWriters {
    fn default() -> Self {
        IgnoredWriters {
            counts: Default::default(),
            logged: Default::default(),
            started: Instant::now(),
        }
    }
}

/// How long after the machine starts an ignored writer is only counted.
const ANNOUNCEMENT_GRACE: Duration = Duration::from_secs(2);

impl IgnoredWriters {
    fn note(&mut self, node: &CellNode, topic: &str, key: &'static str, producer: &str) {
        *self.counts.entry(key).or_default() += 1;
        if self.started.elapsed() >= ANNOUNCEMENT_GRACE && self.logged.insert(key) {
            cell_runtime::cell_log!(
                node,
                LogLevel::Warn,
                "ignored {topic} from a writer that is not {producer}'s (counted in diagnostics)"
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cancel that comes to rest within one tick (the plan was resting) never shows its
    /// hold; the node knows it was cancelled from the accepted command (a print waited
    /// forever for a Ctrl-C during a dwell before).
    #[test]
    fn a_cancel_is_known_from_the_command() {
        let mut control = Control::default();
        let mut executor = Fake::default();
        let (accepted, _) = control.apply(&mut executor, Command::Cancel);
        assert!(accepted && control.cancelled && control.plan_dropped);
        assert!(control.cancelled_at_rest(PlayerState::Idle));
        assert!(!control.cancelled_at_rest(PlayerState::Running));
        let (accepted, message) = control.apply(&mut executor, Command::Resume);
        assert_eq!((accepted, message.as_str()), (false, "not paused"));
        control.apply(&mut executor, Command::EmergencyStop);
        let (accepted, message) = control.apply(&mut executor, Command::Cancel);
        assert_eq!(
            (accepted, message.as_str()),
            (false, "emergency stop in force: /cell/reset first")
        );
        assert!(control.apply(&mut executor, Command::Reset).0);
        assert_eq!(executor.calls, ["cancel", "emergency_stop", "reset"]);
    }

    /// After an e-stop and a reset, the stopped plan does not come back: the node drops what
    /// its producers still send, keeps the credit closed and refuses a pause (the old plan,
    /// taken after the reset, would have played from the stop, displaced).
    #[test]
    fn a_reset_leaves_the_stopped_plan_dropped() {
        let mut control = Control::default();
        let mut executor = Fake::default();
        assert!(control.apply(&mut executor, Command::Pause).0);
        assert!(control.operator_paused && !control.plan_dropped);
        assert!(control.apply(&mut executor, Command::EmergencyStop).0);
        assert!(control.plan_dropped);
        let (accepted, message) = control.apply(&mut executor, Command::Reset);
        assert!(accepted, "{message}");
        assert!(message.contains("stays dropped"), "{message}");
        assert!(control.plan_dropped && !control.operator_paused && !control.cancelled);
        let (accepted, message) = control.apply(&mut executor, Command::Pause);
        assert_eq!(
            (accepted, message.as_str()),
            (false, "no plan: it was dropped")
        );
        assert_eq!(executor.calls, ["pause", "emergency_stop", "reset"]);
    }

    /// A fault stops the machine by itself: seen stopped, the plan is dropped as by an e-stop.
    #[test]
    fn a_machine_seen_stopped_has_dropped_its_plan() {
        let mut control = Control::default();
        control.observe(PlayerState::Running);
        control.observe(PlayerState::Idle);
        assert!(!control.plan_dropped);
        control.observe(PlayerState::Stopped);
        assert!(control.plan_dropped && !control.cancelled);
    }

    /// A pause while a cancel decelerates would turn the cancel into a pause on a machine
    /// that keeps one hold (the MCU bridge did): it is refused, and the cancel goes on.
    #[test]
    fn a_pause_during_a_cancel_is_refused() {
        let mut control = Control::default();
        let mut executor = Fake {
            cancel_decelerates: true,
            ..Fake::default()
        };
        assert!(control.apply(&mut executor, Command::Cancel).0);
        let (accepted, message) = control.apply(&mut executor, Command::Pause);
        assert!(!accepted && message.starts_with("cancelling"), "{message}");
        assert!(!control.operator_paused);
        assert_eq!(executor.hold, Some(HoldReason::Cancel));
        assert_eq!(executor.calls, ["cancel"]);
    }

    /// A machine stopped while paused (a fault of the MCU keeps its pause) is not resumed:
    /// the reply says the stop is in force, and the machine is not asked.
    #[test]
    fn a_resume_while_stopped_is_refused() {
        let mut control = Control::default();
        let mut executor = Fake {
            stopped: true,
            hold: Some(HoldReason::Pause),
            ..Fake::default()
        };
        let (accepted, message) = control.apply(&mut executor, Command::Resume);
        assert_eq!(
            (accepted, message.as_str()),
            (false, "emergency stop in force: /cell/reset first")
        );
        assert!(executor.calls.is_empty());
        assert!(control.plan_dropped);
    }

    /// The node's own hold for screw commands (a pause the operator did not ask for) is not
    /// ended by /cell/resume: the node would hold again at once, braking twice. A pause asked
    /// twice says it is paused already; the operator's resume then ends it.
    #[test]
    fn resume_ends_only_the_operators_pause() {
        let mut control = Control::default();
        let mut executor = Fake {
            hold: Some(HoldReason::Pause), // the node held for the screw
            ..Fake::default()
        };
        let (accepted, message) = control.apply(&mut executor, Command::Resume);
        assert!(
            !accepted && message.starts_with("not paused: holding until the screw"),
            "{message}"
        );
        assert!(executor.calls.is_empty());
        assert!(control.apply(&mut executor, Command::Pause).0);
        let (accepted, message) = control.apply(&mut executor, Command::Pause);
        assert!(
            accepted && message.starts_with("already paused"),
            "{message}"
        );
        assert_eq!(executor.calls, ["pause"]);
        assert!(control.apply(&mut executor, Command::Resume).0);
        assert_eq!(executor.calls, ["pause", "resume"]);
    }

    /// A machine that only remembers what it was asked (its state follows the asks).
    #[derive(Default)]
    struct Fake {
        stopped: bool,
        hold: Option<HoldReason>,
        /// A cancel holds (decelerates) rather than coming to rest at once.
        cancel_decelerates: bool,
        calls: Vec<&'static str>,
    }

    impl Machine for Fake {
        type Error = String;
        fn on_segment(&mut self, _: &StepSegment) -> Result<(), String> {
            Ok(())
        }
        fn on_screw(&mut self, _: &ScrewCommand) -> Result<(), String> {
            Ok(())
        }
        fn free_slots(&self) -> (usize, usize) {
            (1, 1)
        }
        fn finish_input(&mut self) {}
        fn on_tick(&mut self, _: i64) -> Result<(), String> {
            Ok(())
        }
        fn state(&self) -> crate::MachineState {
            crate::MachineState {
                positions: [0.0; 4],
                velocities: [0.0; 4],
                screw_rpm: 0.0,
                pin_open: false,
                state: if self.stopped {
                    PlayerState::Stopped
                } else {
                    PlayerState::Idle
                },
                hold: self.hold,
                feed: 1.0,
                machine_time_s: 0.0,
                plan_time_s: 0.0,
                current: None,
                measured_ns: None,
            }
        }
        fn epoch_ns(&self) -> Option<i64> {
            None
        }
        fn is_drained(&self) -> bool {
            true
        }
        fn plan_ahead_s(&self) -> f64 {
            0.0
        }
        fn completed(&self) -> (u64, Option<(u64, u32)>) {
            (0, None)
        }
        fn underruns(&self) -> u64 {
            0
        }
        fn pause(&mut self) {
            self.calls.push("pause");
            self.hold = Some(HoldReason::Pause);
        }
        fn resume(&mut self) {
            self.calls.push("resume");
            self.hold = None;
        }
        fn cancel(&mut self) {
            self.calls.push("cancel");
            // Decelerating, or come to rest at once (the plan was resting).
            self.hold = self.cancel_decelerates.then_some(HoldReason::Cancel);
        }
        fn emergency_stop(&mut self) {
            self.calls.push("emergency_stop");
            self.stopped = true;
        }
        fn reset(&mut self) {
            self.calls.push("reset");
            self.stopped = false;
        }
    }
}
