//! `polar-cell serve`: the cell waiting for work. It serves the ROS 2 action `/print`
//! (`polar_cell_msgs/action/Print`): each accepted goal runs one print job — the whole node
//! graph for its file, executed at machine pace and recorded to a bag — with feedback from the
//! executor, cancel as a controlled stop on the path, and a result that says how it ended
//! and where the machine stands. While a job runs, the executor's services
//! (`/cell/pause`, `/cell/resume`, `/cell/estop`, …) work as in `print`.
//!
//! An emergency stop outlives the job it ended: until `/cell/reset`, every new goal is
//! aborted with the reason (a new job's MCU session would otherwise reset the MCU, and the
//! cell would print again with nobody having reset it). While no job runs, the server answers
//! the `/cell` services itself: `/cell/estop` latches that stop, `/cell/reset` clears it, and
//! the others say that no print runs (a `ros2 service call` no longer waits for ever). While
//! a job's machine node is up the server hands the calls to it and sends its answers (the
//! machine serves no `/cell` service of its own: with two servers of one service, a call
//! that matched only the server's reader was lost to the machine); before (pre-flight,
//! start-up) and after it (the job closing its bag) the server answers, and an e-stop then
//! stops the job before it moves and latches all the same.
//!
//! One goal at a time: a goal sent while another runs is rejected. The endpoints are
//! ros2-client's synchronous `ActionServer` (its async wrapper needs `Copy` goals and has the
//! pitfalls listed in docs/design/actions-and-services.md); the goal states follow rcl's table.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context as _;
use cell_machine::node::{Command, TriggerServer};
use cell_runtime::{reliable_qos, transient_local_qos, CellNode, RosArgs, Wire};
use polar_cell_msgs::{PrintFeedback, PrintGoal, PrintResult, TriggerRequest, TriggerResponse};
use ros2_client::action::{GetResultResponse, SendGoalResponse};
use ros2_client::action_msgs::{
    CancelGoalResponse, CancelGoalResponseEnum, GoalInfo, GoalStatus, GoalStatusArray,
    GoalStatusEnum,
};
use ros2_client::{ActionTypeName, Gid, RmwRequestId};

use crate::print_cmd::{self, Ending, JobIo, JobReport, PrintOptions};

/// Default node name of the action server.
pub const NODE_NAME: &str = "print_server";

type Server = ros2_client::ActionServer<Wire<PrintGoal>, Wire<PrintResult>, Wire<PrintFeedback>>;
type GoalId = ros2_client::action_msgs::GoalId;

/// How `serve` runs its jobs.
pub struct ServeOptions {
    /// Machine seconds per wall second for goals that do not say.
    pub speed: f64,
    /// Where each goal's bag goes (`print-<n>.mcap`).
    pub bag_dir: PathBuf,
    pub mapping: cell_runtime::ServiceMapping,
    /// The MCU to print on (None: the virtual executor).
    pub device: Option<String>,
    /// How long a finished goal's status and result are kept (rcl's `result_timeout`).
    pub result_timeout: Duration,
}

/// A cancel request's goal and stamp, read from its wire form (ros2-client keeps the field
/// private).
#[derive(serde::Deserialize)]
struct CancelWire {
    goal_info: GoalInfo,
}

struct Running {
    goal_id: GoalId,
    accepted: GoalInfo,
    interrupts: tokio::sync::watch::Sender<u32>,
    status: tokio::sync::watch::Receiver<cell_machine::node::Status>,
    /// The pre-flight's machine time, once the job has run it.
    planned: tokio::sync::watch::Receiver<Option<f64>>,
    cancelling: bool,
    /// Cancelled because the server is shutting down.
    shutdown: bool,
    /// `/cell/estop` came while the job's machine was not up (pre-flight, start-up).
    estopped_before_motion: bool,
    /// `/cell` calls handed to the job's machine (it serves none itself: one server per
    /// service for the server's whole life, so a call cannot reach a server that leaves it
    /// to another whose reader has not yet matched the caller).
    cell_requests: tokio::sync::mpsc::UnboundedSender<cell_machine::node::Request>,
    job: Job,
}

/// A print job as a future polled by the serve loop itself (the node graph's handles are
/// not `Sync`, so the job cannot be a spawned task).
type Job =
    std::pin::Pin<Box<dyn std::future::Future<Output = (anyhow::Result<JobReport>, String)>>>;

/// A `/cell` call handed to the running job's machine: the service's index in
/// [`cell_machine::node::SERVICES`], the request to answer, its command, and the machine's
/// answer to come.
type HandedCall = (
    usize,
    cell_runtime::service::Request,
    Command,
    tokio::sync::oneshot::Receiver<(bool, String)>,
);

struct Finished {
    info: GoalInfo,
    status: GoalStatusEnum,
    result: PrintResult,
    ended_at: std::time::Instant,
}

pub async fn serve(options: ServeOptions, ros_args: &RosArgs) -> anyhow::Result<()> {
    let mut node = CellNode::start(NODE_NAME, &[], ros_args)?;
    let service_qos = reliable_qos(10);
    let qos = ros2_client::action::ActionServerQosPolicies {
        goal_service: service_qos.clone(),
        result_service: service_qos.clone(),
        cancel_service: service_qos.clone(),
        feedback_publisher: service_qos,
        status_publisher: transient_local_qos(1),
    };
    let name = node.ros_name("/print")?;
    let server: Server = node
        .node
        .create_action_server(
            options.mapping,
            &name,
            &ActionTypeName::new("polar_cell_msgs", "Print"),
            qos,
        )
        .map_err(|e| anyhow::anyhow!("action /print: {e:?}"))?;
    std::fs::create_dir_all(&options.bag_dir)
        .with_context(|| format!("creating {}", options.bag_dir.display()))?;
    eprintln!(
        "serving the action /print (polar_cell_msgs/action/Print); bags go to {}",
        options.bag_dir.display()
    );
    let mut running: Option<Running> = None;
    // Why the cell is stopped at once, until `/cell/reset`.
    let mut latched: Option<String> = None;
    // The `/cell` services, answered here while no job's machine is up and handed to the
    // machine while one is. They live as long as the server: a reader made
    // again on this participant would be handed the requests its predecessor had taken
    // (RustDDS keeps a topic's samples for the participant), an old /cell/reset among them.
    let mut idle: Vec<(TriggerServer, Command)> = Vec::new();
    let mut replies = cell_runtime::service::Replies::default();
    // Calls handed to a job's machine, waiting for its answer.
    let mut to_machine: Vec<HandedCall> = Vec::new();
    for (name, command) in cell_machine::node::SERVICES {
        let server = node.service::<TriggerRequest, TriggerResponse>(
            name,
            ("std_srvs", "Trigger"),
            options.mapping,
        )?;
        idle.push((server, command));
    }
    let mut finished: Vec<Finished> = Vec::new();
    let mut result_requests: Vec<(RmwRequestId, GoalId, Gid)> = Vec::new();
    // Answers waiting until their client's response reader is matched.
    let mut answers = Answers::default();
    let mut jobs = 0u32;
    // Where the virtual machine stands after the last job, for the next plan to start there
    // (a cancelled print leaves it mid-part). A real MCU is asked where it stands at each
    // job's start; an emulator started per goal powers up at home.
    let machine_persists = options.device.is_none();
    let mut machine_at: Option<[f64; 3]> = None;
    // One listener for the whole life of the server: a listener made afresh at each turn of
    // the loop would miss a signal that comes between two (tokio delivers a signal only to
    // the listeners that exist when it comes).
    let mut signals = cell_runtime::ShutdownSignals::new().context("signal handlers")?;
    let mut signals_seen = 0u32;
    // Shutting down: the running goal is cancelled (a second signal: emergency stop), its
    // result published and given to whoever asks for a while, then the server ends.
    let mut leave_at: Option<std::time::Instant> = None;
    let mut poll = tokio::time::interval(Duration::from_millis(10));
    let mut last_feedback = std::time::Instant::now();
    let publish_statuses = |server: &Server, running: &Option<Running>, finished: &[Finished]| {
        let mut list: Vec<GoalStatus> = finished
            .iter()
            .map(|f| GoalStatus {
                goal_info: f.info.clone(),
                status: f.status,
            })
            .collect();
        if let Some(r) = running {
            list.push(GoalStatus {
                goal_info: r.accepted.clone(),
                status: if r.cancelling {
                    GoalStatusEnum::Canceling
                } else {
                    GoalStatusEnum::Executing
                },
            });
        }
        let _ = server.send_goal_statuses(GoalStatusArray { status_list: list });
    };
    loop {
        let ended = tokio::select! {
            _ = poll.tick() => None,
            (index, request) = cell_machine::node::next_request(&idle) => {
                let command = idle[index].1;
                let answer = match (running.as_mut(), request) {
                    (None, Some(request)) => Some((request, idle_reply(command, &mut latched))),
                    (Some(r), Some(request)) => {
                        // The job's machine answers while its node is up. Before (pre-flight,
                        // start-up) and after (the job closing its bag) the server does: an
                        // e-stop then stops the job before it moves, and holds the cell
                        // either way.
                        let up = r.status.has_changed().is_ok() && r.status.borrow().state.is_some();
                        if command == Command::EmergencyStop {
                            latched.get_or_insert_with(|| "emergency stop (/cell/estop) during a print".into());
                        }
                        let (answer, answered) = tokio::sync::oneshot::channel();
                        let handed = up && r
                            .cell_requests
                            .send(cell_machine::node::Request { command, answer: Some(answer) })
                            .is_ok();
                        if handed {
                            to_machine.push((index, request, command, answered));
                            None
                        } else if command == Command::EmergencyStop && r.status.borrow().state.is_none() {
                            r.estopped_before_motion = true;
                            raise_interrupt(&r.interrupts, 2);
                            Some((request, (true, "emergency stop: the print stops before it moves; new prints are refused until /cell/reset".to_string())))
                        } else {
                            Some((request, without_machine_reply(command)))
                        }
                    }
                    (_, None) => None,
                };
                if let Some((request, (success, message))) = answer {
                    eprintln!("serve: {}: {message}", cell_machine::node::SERVICES[index].0);
                    replies.push(index, request, Wire(TriggerResponse { success, message }));
                }
                None
            }
            ended = async {
                match running.as_mut() {
                    Some(r) => (&mut r.job).await,
                    None => std::future::pending().await,
                }
            } => Some(ended),
            _ = signals.next() => {
                signals_seen += 1;
                if let Some(r) = running.as_mut() {
                    // The first: a cancel (stop on the path); a second: emergency stop.
                    raise_interrupt(&r.interrupts, signals_seen.min(2));
                    // (A goal its client cancelled already ends as that cancel.)
                    r.shutdown |= !r.cancelling;
                    r.cancelling = true;
                    eprintln!("serve: shutting down: stopping the running print first (again: emergency stop)");
                    publish_statuses(&server, &running, &finished);
                } else if signals_seen > 1 {
                    return Ok(());
                }
                None
            }
        };
        // The machine's answers to the calls handed to it; a machine that ended first
        // dropped the call, and the server answers it.
        for (index, request, command, mut answered) in std::mem::take(&mut to_machine) {
            let reply = match answered.try_recv() {
                Ok(reply) => reply,
                Err(tokio::sync::oneshot::error::TryRecvError::Empty) => {
                    to_machine.push((index, request, command, answered));
                    continue;
                }
                Err(tokio::sync::oneshot::error::TryRecvError::Closed) => {
                    let reply = without_machine_reply(command);
                    eprintln!(
                        "serve: {}: {}",
                        cell_machine::node::SERVICES[index].0,
                        reply.1
                    );
                    reply
                }
            };
            let (success, message) = reply;
            replies.push(index, request, Wire(TriggerResponse { success, message }));
        }
        for (index, problem) in replies.send_ready(|index| &idle[index].0) {
            eprintln!(
                "serve: {}: {problem}",
                cell_machine::node::SERVICES[index].0
            );
        }
        // The job's end first: a goal that comes in the same pass finds the server free.
        // (Only a running goal's job can end, and then the goal is no longer running.)
        if let Some(((report, bag), r)) = ended.and_then(|e| running.take().map(|r| (e, r))) {
            let status = r.status.borrow().clone();
            if machine_persists && status.state.is_some() {
                let [bed, arm, z, _] = status.positions;
                machine_at = Some([bed, arm, z]);
            }
            let (mut goal_status, mut result) = outcome(report, &status, bag);
            if result.ended == "emergency_stop"
                || status.state == Some(cell_executor::PlayerState::Stopped)
            {
                latched = Some(result.message.clone());
            }
            if status.state.is_none() {
                // The machine never ran for this goal: it stands where it stood.
                result.stop_position = standing_position(&options.device, machine_at);
            }
            if r.shutdown {
                result.message = format!("the server shut down: {}", result.message);
            }
            // Stopped from outside the action, as a `/cell/estop` to the machine would be.
            if r.estopped_before_motion {
                result.ended = "emergency_stop".into();
                if status.state.is_none() {
                    result.message = "emergency stop (/cell/estop) before the print moved".into();
                }
                goal_status = GoalStatusEnum::Aborted;
            }
            keep_finished(&mut finished, r.accepted.clone(), goal_status, result);
            publish_statuses(&server, &running, &finished);
        }
        if signals_seen > 0 && running.is_none() && leave_at.is_none() {
            leave_at = Some(std::time::Instant::now() + SHUTDOWN_LINGER);
        }
        // New goals: accept one when idle, reject while busy, shutting down, or when its id
        // is already known (rcl refuses a goal id that exists).
        while let Ok(Some((request_id, request, client))) = server.receive_goal_with_info() {
            let stamp = ros2_client::builtin_interfaces::Time::now();
            let known = running
                .as_ref()
                .is_some_and(|r| r.goal_id == request.goal_id)
                || finished.iter().any(|f| f.info.goal_id == request.goal_id);
            if running.is_some() || signals_seen > 0 || known {
                answers.push(client, goal_answer(request_id, false, stamp));
                continue;
            }
            let asked_speed = request.goal.0.speed;
            let refusal = if let Some(why) = &latched {
                Some(format!(
                    "the cell is stopped ({why}): call /cell/reset before a new print"
                ))
            } else if !(asked_speed == 0.0
                || cell_machine::node::SPEED_RANGE.contains(&asked_speed))
            {
                Some(format!(
                    "speed {asked_speed}: a print runs at 0.01 to 1000 machine seconds per wall second (0: the server's --speed {})",
                    options.speed
                ))
            } else {
                None
            };
            if let Some(message) = refusal {
                // Accepted, to say why it ends at once (a rejection carries no reason),
                // before a bag or a node exists for it.
                let info = GoalInfo {
                    goal_id: request.goal_id,
                    stamp,
                };
                let result = PrintResult {
                    ended: "aborted".into(),
                    message,
                    stop_position: standing_position(&options.device, machine_at),
                    ..PrintResult::default()
                };
                keep_finished(&mut finished, info, GoalStatusEnum::Aborted, result);
                publish_statuses(&server, &running, &finished);
                answers.push(client, goal_answer(request_id, true, stamp));
                continue;
            }
            // The next number no bag in the directory has yet: a restarted server does not
            // overwrite the last one's bags.
            let bag = loop {
                jobs += 1;
                let bag = options.bag_dir.join(format!("print-{jobs}.mcap"));
                if !bag.exists() {
                    break bag;
                }
            };
            let goal = request.goal.0;
            let speed = if goal.speed == 0.0 {
                options.speed
            } else {
                goal.speed
            };
            let (interrupts, interrupts_rx) = tokio::sync::watch::channel(0u32);
            let (status_tx, status) =
                tokio::sync::watch::channel(cell_machine::node::Status::default());
            let (planned_tx, planned) = tokio::sync::watch::channel(None);
            let (cell_requests, cell_requests_rx) = tokio::sync::mpsc::unbounded_channel();
            let job_options = PrintOptions {
                bag: bag.clone(),
                bag_dir: false,
                show_progress: false,
                run_preflight: true,
                execution: Some(speed),
                device: options.device.clone(),
                start_joints: machine_at,
            };
            let file = goal.gcode_file.clone();
            let args = ros_args.clone();
            let job: Job = Box::pin(async move {
                let io = JobIo {
                    interrupts: interrupts_rx,
                    status: status_tx,
                    planned: planned_tx,
                    cell_requests: Some(cell_requests_rx),
                };
                // `print -` reads its own standard input; the server's is not the client's.
                let report = if file == "-" {
                    Err(anyhow::anyhow!(
                        "gcode_file \"-\" would read the server's standard input: send a \
                         file's path on the machine that serves /print"
                    ))
                } else {
                    print_cmd::run_job(&file, &job_options, &args, io).await
                };
                // A goal that ended before its recorder started names no bag.
                let recorded = if bag.exists() {
                    bag.display().to_string()
                } else {
                    String::new()
                };
                (report, recorded)
            });
            let accepted = GoalInfo {
                goal_id: request.goal_id,
                stamp,
            };
            running = Some(Running {
                goal_id: request.goal_id,
                accepted: accepted.clone(),
                interrupts,
                status,
                planned,
                cancelling: false,
                shutdown: false,
                estopped_before_motion: false,
                cell_requests,
                job,
            });
            publish_statuses(&server, &running, &finished);
            answers.push(client, goal_answer(request_id, true, stamp));
        }
        // Cancel requests, as rcl judges them (the goal by its id, and/or every goal accepted
        // at or before the stamp; both zero: every goal).
        while let Ok(Some((request_id, request, client))) =
            server.receive_cancel_request_with_info()
        {
            let target = serde_json::to_value(&request)
                .ok()
                .and_then(|v| serde_json::from_value::<CancelWire>(v).ok())
                .map(|c| c.goal_info);
            let response = match target {
                Some(target) => {
                    let verdict = judge_cancel(
                        &target,
                        running.as_ref().map(|r| (&r.accepted, r.cancelling)),
                        finished.iter().map(|f| &f.info.goal_id),
                    );
                    if !verdict.goals_canceling.is_empty() {
                        if let Some(r) = running.as_mut() {
                            raise_interrupt(&r.interrupts, 1);
                            r.cancelling = true;
                        }
                    }
                    verdict
                }
                None => CancelGoalResponse {
                    return_code: CancelGoalResponseEnum::Rejected,
                    goals_canceling: vec![],
                },
            };
            publish_statuses(&server, &running, &finished);
            answers.push(client, Answer::Cancel(request_id, response));
        }
        while let Ok(Some((request_id, request, client))) =
            server.receive_result_request_with_info()
        {
            result_requests.push((request_id, request.goal_id, client));
        }
        // Feedback at 4 Hz.
        if let Some(r) = &running {
            if last_feedback.elapsed() >= Duration::from_millis(250) {
                last_feedback = std::time::Instant::now();
                let s = r.status.borrow().clone();
                let planned_s = *r.planned.borrow();
                let _ = server.send_feedback(r.goal_id, Wire(feedback(&s, planned_s)));
            }
        }
        result_requests.retain(|(request_id, goal_id, client)| {
            let Some(f) = finished.iter().find(|f| f.info.goal_id == *goal_id) else {
                // Unknown and not running: answer at once (rcl answers UNKNOWN).
                if running.as_ref().is_some_and(|r| r.goal_id == *goal_id) {
                    return true;
                }
                answers.push(
                    *client,
                    Answer::Result(
                        *request_id,
                        GetResultResponse {
                            status: GoalStatusEnum::Unknown,
                            result: Wire(PrintResult::default()),
                        },
                    ),
                );
                return false;
            };
            answers.push(
                *client,
                Answer::Result(
                    *request_id,
                    GetResultResponse {
                        status: f.status,
                        result: Wire(f.result.clone()),
                    },
                ),
            );
            false
        });
        send_ready(&mut answers, &server);
        // A finished goal is kept (in the status list, its result for get_result) for the
        // result timeout after it ended, as rcl keeps it; then it is unknown. (After the
        // answers above: a request waiting when the goal ended gets its result whatever the
        // timeout.)
        let before = finished.len();
        finished.retain(|f| f.ended_at.elapsed() < options.result_timeout);
        if finished.len() != before {
            publish_statuses(&server, &running, &finished);
        }
        if leave_at.is_some_and(|at| std::time::Instant::now() >= at) {
            return Ok(());
        }
    }
}

/// Finished goals kept at most, whatever the result timeout (a client sending goals that
/// fail at once must not grow the server without bound).
const MAX_RESULTS_KEPT: usize = 64;

/// Ask the running job to stop at least as hard as `level` (1: cancel, 2: emergency stop):
/// never lower, so a cancel that comes after an emergency stop cannot undo it.
fn raise_interrupt(interrupts: &tokio::sync::watch::Sender<u32>, level: u32) {
    interrupts.send_if_modified(|current| {
        let raised = level > *current;
        *current = (*current).max(level);
        raised
    });
}

/// Keep a goal that ended (the oldest goes beyond [`MAX_RESULTS_KEPT`]).
fn keep_finished(
    finished: &mut Vec<Finished>,
    info: GoalInfo,
    status: GoalStatusEnum,
    result: PrintResult,
) {
    finished.push(Finished {
        info,
        status,
        result,
        ended_at: std::time::Instant::now(),
    });
    if finished.len() > MAX_RESULTS_KEPT {
        finished.remove(0);
    }
}

/// Where the machine stands for a goal that ended before its machine ran: where the last job
/// left the virtual machine (home before any), home for an emulator (started per goal), and
/// unknown (empty) for a real MCU that was not reached.
fn standing_position(device: &Option<String>, machine_at: Option<[f64; 3]>) -> Vec<f64> {
    match (device, machine_at) {
        (None, Some([bed, arm, z])) => vec![bed, arm, z, 0.0],
        (None, None) => vec![0.0; 4],
        (Some(device), _) if device == "emulator" => vec![0.0; 4],
        (Some(_), _) => vec![],
    }
}

/// The answer to a goal request.
fn goal_answer(
    request_id: RmwRequestId,
    accepted: bool,
    stamp: ros2_client::builtin_interfaces::Time,
) -> Answer {
    Answer::Goal(request_id, SendGoalResponse { accepted, stamp })
}

/// An action service's answer to one request.
enum Answer {
    Goal(RmwRequestId, SendGoalResponse),
    Cancel(RmwRequestId, CancelGoalResponse),
    Result(RmwRequestId, GetResultResponse<Wire<PrintResult>>),
}

/// The action's answers waiting until the server has discovered their client's response
/// reader (at most `cell_runtime::service::REPLY_PATIENCE`): `ros2 action send_goal` sends
/// its goal as soon as it sees the server, and an answer sent before the server saw the
/// client's reader was lost (see `cell_runtime::service`).
type Answers = cell_runtime::service::Waiting<Answer>;

/// Send the answers whose clients can hear them now, or that have waited long enough.
fn send_ready(answers: &mut Answers, server: &Server) {
    answers.release(
        |client, answer| match answer {
            Answer::Goal(..) => server.goal_client_matched(client),
            Answer::Cancel(..) => server.cancel_client_matched(client),
            Answer::Result(..) => server.result_client_matched(client),
        },
        |answer, heard| {
            if !heard {
                eprintln!(
                    "serve: an action client's response reader was not seen in {} s: its answer may be lost",
                    cell_runtime::service::REPLY_PATIENCE.as_secs_f64()
                );
            }
            let _ = match answer {
                Answer::Goal(id, response) => server.send_goal_response(id, response),
                Answer::Cancel(id, response) => server.send_cancel_response(id, response),
                Answer::Result(id, response) => server.send_result(id, response),
            };
        },
    );
}

/// The answer to a `/cell` service while no job runs.
fn idle_reply(command: Command, latched: &mut Option<String>) -> (bool, String) {
    match command {
        Command::EmergencyStop => {
            *latched = Some("emergency stop (/cell/estop) while no print ran".into());
            (
                true,
                "emergency stop: no print runs; new prints are refused until /cell/reset".into(),
            )
        }
        Command::Reset if latched.take().is_some() => {
            (true, "reset: the cell takes new prints again".into())
        }
        Command::Reset => (false, "not stopped".into()),
        Command::Pause | Command::Resume | Command::Cancel => (false, "no print runs".into()),
    }
}

/// The server's answer while a job runs without its machine up (starting or ending); an
/// e-stop was latched by the caller.
fn without_machine_reply(command: Command) -> (bool, String) {
    match command {
        Command::EmergencyStop => (
            true,
            "emergency stop: the print has ended; new prints are refused until /cell/reset".into(),
        ),
        _ => (
            false,
            "the print is starting or ending: its machine is not up".into(),
        ),
    }
}

/// How long a server that was told to stop still answers result requests once its last goal
/// ended (a client asks for the result when it sees the terminal status).
const SHUTDOWN_LINGER: Duration = Duration::from_secs(2);

/// rcl's answer to a cancel request, given the running goal (with whether it is already
/// being cancelled) and the ids of the finished goals still kept. The goal named by a
/// non-zero id, and every goal accepted at or before a non-zero stamp, are cancelled; both
/// zero, every goal. A goal already CANCELING cannot be cancelled again (rcl's state machine
/// has no such transition), nor can a finished one. Only a request by id alone (stamp 0) is
/// answered with an error when it cancels nothing: rcl judges one with a stamp by the stamp.
fn judge_cancel<'a>(
    target: &GoalInfo,
    running: Option<(&GoalInfo, bool)>,
    mut finished: impl Iterator<Item = &'a GoalId>,
) -> CancelGoalResponse {
    let by_id = target.goal_id != GoalId::ZERO;
    let stamp_ns = target.stamp.to_nanos();
    let mut goals_canceling = Vec::new();
    let mut named_terminal = false;
    if let Some((info, cancelling)) = running {
        let named = by_id && info.goal_id == target.goal_id;
        let wanted = named
            || (!by_id && stamp_ns == 0)
            || (stamp_ns != 0 && info.stamp.to_nanos() <= stamp_ns);
        if wanted && !cancelling {
            goals_canceling.push(info.clone());
        }
        named_terminal = named && cancelling;
    }
    // Something cancelled, or a request by stamp (or for all goals): no error.
    let return_code = if !goals_canceling.is_empty() || !by_id || stamp_ns != 0 {
        CancelGoalResponseEnum::None
    } else if named_terminal || finished.any(|id| *id == target.goal_id) {
        CancelGoalResponseEnum::GoalTerminated
    } else {
        CancelGoalResponseEnum::UnknownGoal
    };
    CancelGoalResponse {
        return_code,
        goals_canceling,
    }
}

fn feedback(s: &cell_machine::node::Status, planned_s: Option<f64>) -> PrintFeedback {
    let (move_sequence, line) = s.current.unwrap_or((0, 0));
    PrintFeedback {
        line,
        move_sequence,
        percent: planned_s
            .map(|t| (100.0 * s.plan_time_s / t.max(1e-9)).min(100.0) as f32)
            .unwrap_or(0.0),
        elapsed_s: s.executed_s(),
        remaining_s: planned_s.map_or(0.0, |t| (t - s.plan_time_s).max(0.0)),
        state: s.state_label().to_string(),
    }
}

/// The goal's end state and result from the job's report.
fn outcome(
    report: anyhow::Result<JobReport>,
    status: &cell_machine::node::Status,
    bag: String,
) -> (GoalStatusEnum, PrintResult) {
    let mut result = PrintResult {
        machine_time_s: status.executed_s(),
        stop_position: status.positions.to_vec(),
        bag,
        ..PrintResult::default()
    };
    let goal_status = match report {
        Ok(JobReport {
            ending: Ending::Finished,
            summary,
            ..
        }) => {
            result.ended = "succeeded".into();
            result.moves_executed = summary.map_or(0, |s| s.moves);
            result.message = "printed".into();
            GoalStatusEnum::Succeeded
        }
        Ok(JobReport {
            ending: Ending::Interrupted { emergency, how },
            ..
        }) => {
            result.ended = if emergency {
                "emergency_stop"
            } else {
                "cancelled"
            }
            .into();
            result.message = how.unwrap_or_else(|| "cancelled before any motion".into());
            // Moves before the one that was executing.
            result.moves_executed = status.current.map_or(0, |(sequence, _)| sequence);
            GoalStatusEnum::Canceled
        }
        Err(e) => {
            let stopped =
                status.state == Some(cell_executor::PlayerState::Stopped) && status.fault.is_none();
            // Stopped from outside the action (`/cell/estop`, `/cell/cancel`): aborted, as
            // the goal was not cancelled through it, but said how.
            // A bag that could not be written or a failed node stopped the machine through a
            // cancel of the job's own: aborted, not an operator's cancel.
            let by_job = e.downcast_ref::<crate::print_cmd::StoppedByJob>().is_some();
            result.ended = if stopped {
                "emergency_stop"
            } else if status.cancelled && !by_job {
                "cancelled"
            } else {
                "aborted"
            }
            .into();
            result.message = format!("{e:#}");
            result.moves_executed = status.current.map_or(0, |(sequence, _)| sequence);
            GoalStatusEnum::Aborted
        }
    };
    (goal_status, result)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::builtin_interfaces::Time;

    fn info(goal_id: GoalId, stamp_ns: i64) -> GoalInfo {
        GoalInfo {
            goal_id,
            stamp: Time::from_nanos(stamp_ns),
        }
    }

    fn verdict(
        target: GoalInfo,
        running: Option<(&GoalInfo, bool)>,
        finished: &[GoalId],
    ) -> (CancelGoalResponseEnum, usize) {
        let r = judge_cancel(&target, running, finished.iter());
        (r.return_code, r.goals_canceling.len())
    }

    /// rcl's rules (action_server.c, rcl_action_process_cancel_request, and the goal state
    /// machine: no cancel from CANCELING or a terminal state).
    #[test]
    fn cancel_requests_are_judged_as_rcl_judges_them() {
        use CancelGoalResponseEnum::{GoalTerminated, None as Ok, UnknownGoal};
        let zero = GoalId::ZERO;
        let (a, done, other) = (
            GoalId::new_random(),
            GoalId::new_random(),
            GoalId::new_random(),
        );
        let running = info(a, 100);
        // Idle: cancelling every goal is no error; an unknown goal is.
        assert_eq!(verdict(info(zero, 0), None, &[]), (Ok, 0));
        assert_eq!(verdict(info(other, 0), None, &[]), (UnknownGoal, 0));
        assert_eq!(verdict(info(done, 0), None, &[done]), (GoalTerminated, 0));
        // Running, accepted at 100 ns.
        let live = Some((&running, false));
        assert_eq!(verdict(info(zero, 0), live, &[]), (Ok, 1), "all goals");
        assert_eq!(verdict(info(a, 0), live, &[]), (Ok, 1), "by id");
        assert_eq!(
            verdict(info(zero, 99), live, &[]),
            (Ok, 0),
            "accepted after"
        );
        assert_eq!(verdict(info(zero, 100), live, &[]), (Ok, 1), "at the stamp");
        assert_eq!(verdict(info(other, 100), live, &[]), (Ok, 1), "by stamp");
        assert_eq!(
            verdict(info(other, 99), live, &[]),
            (Ok, 0),
            "judged by the stamp"
        );
        assert_eq!(verdict(info(other, 0), live, &[]), (UnknownGoal, 0));
        // Already cancelling: no second transition.
        let cancelling = Some((&running, true));
        assert_eq!(verdict(info(a, 0), cancelling, &[]), (GoalTerminated, 0));
        assert_eq!(verdict(info(zero, 0), cancelling, &[]), (Ok, 0));
        assert_eq!(
            verdict(info(a, 100), cancelling, &[]),
            (Ok, 0),
            "judged by the stamp"
        );
    }
}
