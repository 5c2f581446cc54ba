//! `polar-cell print`: every node of the cell in one process, each its own DDS participant,
//! talking over loopback DDS (so `ros2 topic echo` on the same domain sees everything).

use std::io::BufRead;
use std::time::Duration;

use anyhow::{bail, Context as _};
use cell_bag::node::{print_summary, Recorder};
use cell_runtime::args::ParamOverride;
use cell_runtime::{CellNode, ParamSpec, RosArgs};
use gcode_streamer::node::StreamSummary;
use gcode_streamer::{Event, GcodeReader};
use indicatif::{ProgressBar, ProgressStyle};

/// The ROS arguments for one node: global `-p` only where the node declares the parameter.
fn args_for(
    ros_args: &RosArgs,
    node_name: &str,
    specs: &[ParamSpec],
    ours: Vec<ParamOverride>,
) -> RosArgs {
    let mut args = ros_args.clone();
    let mut params = ours;
    params.extend(
        ros_args
            .params
            .iter()
            .filter(|p| match &p.node {
                Some(n) => n == node_name,
                None => specs.iter().any(|s| s.name == p.name),
            })
            .cloned(),
    );
    args.params = params;
    args
}

/// Start node `name` with its parameter `specs`, our `ours` overrides first (the user's win).
fn start_node(
    name: &str,
    specs: &[ParamSpec],
    ros_args: &RosArgs,
    ours: Vec<ParamOverride>,
) -> anyhow::Result<CellNode> {
    Ok(CellNode::start(
        name,
        specs,
        &args_for(ros_args, name, specs, ours),
    )?)
}

/// What the planner must know of the screw driver it plans for: the pin's rest (its `stop`
/// strategy), the screw's top speed and calibration, and its flow time constant when the
/// driver compensates the flow.
fn planner_overrides(screw: &cell_runtime::Params) -> Vec<ParamOverride> {
    let pin_dwell = match screw.string("pin_strategy") {
        "stop" => screw.f64("pin_open_delay_s"),
        _ => 0.0,
    };
    let flow_tau = if screw.bool("flow_compensation") {
        screw.f64("flow_tau_s")
    } else {
        0.0
    };
    vec![
        param("pin_open_dwell_s", pin_dwell.to_string()),
        param("screw_max_rpm", format!("{:?}", screw.f64("max_rpm"))),
        param(
            "screw_e_per_rev_m",
            format!("{:?}", screw.f64("e_per_rev_m")),
        ),
        param("screw_flow_tau_s", format!("{flow_tau:?}")),
    ]
}

/// What a node task that should run until the print ends means when it ends first.
fn stopped(
    name: &str,
    finished: Result<(CellNode, anyhow::Result<()>), tokio::task::JoinError>,
) -> anyhow::Error {
    match finished {
        Ok((_, Err(e))) => e.context(name.to_string()),
        Ok((_, Ok(()))) => anyhow::anyhow!("{name} stopped"),
        Err(e) => anyhow::anyhow!("{name} task: {e}"),
    }
}

/// Every `-p` must reach a node of this process that declares it: a global one at least one
/// node, a scoped one (`-p NODE:NAME:=V`) that node (unknown parameters are errors; a scoped
/// one for a node this print does not run, `cell_executor` on a print with `--device` say,
/// would otherwise be dropped without a word).
fn check_params(ros_args: &RosArgs, nodes: &[(&str, &[ParamSpec])]) -> anyhow::Result<()> {
    let declares = |specs: &[ParamSpec], name: &str| specs.iter().any(|s| s.name == name);
    // `-p NODE:` names a node as it runs, renamed by `-r NODE:__node:=…` (as the node's own
    // parameters take it).
    let renamed: Vec<(String, &[ParamSpec])> = nodes
        .iter()
        .map(|(name, specs)| (ros_args.node_name(name), *specs))
        .collect();
    let nodes = &renamed;
    for p in &ros_args.params {
        match &p.node {
            None => {
                if !nodes.iter().any(|(_, specs)| declares(specs, &p.name)) {
                    bail!(
                        "-p {}:={}: no node of this process declares `{}`",
                        p.name,
                        p.value_yaml,
                        p.name
                    );
                }
            }
            Some(node) => match nodes.iter().find(|(name, _)| name == node) {
                None => bail!(
                    "-p {node}:{}:={}: this print runs no node `{node}` (its nodes: {})",
                    p.name,
                    p.value_yaml,
                    nodes
                        .iter()
                        .map(|(name, _)| name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
                Some((_, specs)) if !declares(specs, &p.name) => bail!(
                    "-p {node}:{}:={}: node `{node}` declares no parameter `{}`",
                    p.name,
                    p.value_yaml,
                    p.name
                ),
                Some(_) => {}
            },
        }
    }
    Ok(())
}

fn param(name: &str, value_yaml: String) -> ParamOverride {
    ParamOverride {
        node: None,
        name: name.to_string(),
        value_yaml,
    }
}

fn open_input(file: &str) -> anyhow::Result<(Box<dyn BufRead + Send>, u64)> {
    if file == "-" {
        return Ok((Box::new(std::io::BufReader::new(std::io::stdin())), 0));
    }
    let f = std::fs::File::open(file).with_context(|| format!("opening {file}"))?;
    let total = f.metadata().map(|m| m.len()).unwrap_or(0);
    Ok((
        Box::new(std::io::BufReader::with_capacity(1 << 16, f)),
        total,
    ))
}

/// How `print` runs.
#[derive(Clone, Debug)]
pub struct PrintOptions {
    pub bag: std::path::PathBuf,
    pub bag_dir: bool,
    pub show_progress: bool,
    pub run_preflight: bool,
    /// Execute at this speed factor (machine seconds per wall second); `None`: dry run, the
    /// plan as fast as the CPU allows and no executor.
    pub execution: Option<f64>,
    /// Execute on the MCU on this serial line (`emulator`: one started for the job) instead
    /// of the virtual executor.
    pub device: Option<String>,
    /// Where the machine stands when the plan starts (bed rad, arm m, z m); `None`: the
    /// nodes' `initial_joints` parameter (home unless given).
    pub start_joints: Option<[f64; 3]>,
}

/// The planner's and the machine's `initial_joints` (bed rad, arm m, z m) for a start
/// position, as a parameter value (without spaces: one shell word, for `ros2 launch`).
pub fn initial_joints_value([bed, arm, z]: [f64; 3]) -> String {
    format!("[{bed:?},{arm:?},{z:?}]")
}

/// The streamer's `start_position_mm` for a start position, as a parameter value: the
/// G-code starts where the tool stands, as the plan does.
pub fn start_position_value(joints: [f64; 3]) -> String {
    let [x, y, z] = polar_planner::path::forward(joints).map(|v| v * 1e3);
    format!("[{x:?},{y:?},{z:?}]")
}

/// The `initial_joints` parameter of the planner and the machine for a start position.
fn start_override(start: Option<[f64; 3]>) -> Vec<ParamOverride> {
    start
        .map(|joints| param("initial_joints", initial_joints_value(joints)))
        .into_iter()
        .collect()
}

/// The streamer's `start_position_mm` for a start position.
fn streamer_start_override(start: Option<[f64; 3]>) -> Vec<ParamOverride> {
    start
        .map(|joints| param("start_position_mm", start_position_value(joints)))
        .into_iter()
        .collect()
}

/// Where the MCU on `device` stands (bed rad, arm m, z m), asked before the print is planned,
/// with the bridge's parameters from the same ROS arguments.
pub fn mcu_position(device: &str, ros_args: &RosArgs) -> anyhow::Result<[f64; 3]> {
    let specs = mcu_bridge::node::param_specs();
    let name = mcu_bridge::node::NODE_NAME;
    let (_, bridge) =
        cell_runtime::resolve_node(name, &specs, &args_for(ros_args, name, &specs, vec![]))?;
    let params = cell_machine::node::MachineParams::from_params(&bridge)?;
    let mut options = mcu_bridge::SessionOptions::new(
        params.steps.steps_per_unit,
        params.joint_accelerations,
        params.pin_open_delay_s,
    );
    // As the bridge would wait: for the device to appear, then for the MCU to be ready.
    let answer_timeout_s = bridge.f64("answer_timeout_s");
    options.answer_timeout_s = answer_timeout_s;
    let timeout = Duration::from_secs_f64(bridge.f64("open_timeout_s") + answer_timeout_s);
    let steps =
        mcu_bridge::node::probe_position(device, bridge.i64("baud") as u32, options, timeout)?;
    let u = params.steps.steps_per_unit;
    let joints: [f64; 3] = std::array::from_fn(|j| steps[j] as f64 / u[j]);
    eprintln!(
        "MCU on {device} stands at steps {steps:?} (bed {:.6} rad, arm {:.6} m, z {:.6} m)",
        joints[0], joints[1], joints[2]
    );
    Ok(joints)
}

/// `mcu_emulator` started for one job on a pseudo-terminal, stopped when the job ends.
struct Emulator {
    child: std::process::Child,
    /// The pseudo-terminal it serves.
    device: String,
}

impl Emulator {
    /// Start it at `speed`: the binary beside this one (a workspace build puts them
    /// together), else the one on PATH.
    fn start(speed: f64) -> anyhow::Result<Emulator> {
        use std::io::BufRead as _;
        let beside = std::env::current_exe()
            .ok()
            .and_then(|exe| exe.parent().map(|dir| dir.join("mcu_emulator")))
            .filter(|path| path.exists());
        let program = beside.unwrap_or_else(|| "mcu_emulator".into());
        let mut command = std::process::Command::new(&program);
        command
            .args(["--speed", &speed.to_string()])
            .stdout(std::process::Stdio::piped());
        // Its own process group: a Ctrl-C typed in the terminal goes to the foreground group,
        // and an emulator killed by it would turn the print's controlled stop into a lost
        // line. The print stops it when the job ends (and PDEATHSIG if the print dies).
        std::os::unix::process::CommandExt::process_group(&mut command, 0);
        // SAFETY: prctl is async-signal-safe; between fork and exec it only asks the kernel
        // to kill the child when its parent thread dies (here a runtime thread, which lives
        // as long as the process), so no emulator outlives a killed print.
        unsafe {
            use std::os::unix::process::CommandExt as _;
            command.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) == -1 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = command.spawn().with_context(|| {
            format!(
                "starting {} (build it with `cargo build --release --workspace`)",
                program.display()
            )
        })?;
        let stdout = child.stdout.take().expect("piped");
        let mut line = String::new();
        std::io::BufReader::new(stdout)
            .read_line(&mut line)
            .context("reading where mcu_emulator listens")?;
        let Some(device) = line.trim().strip_prefix("pty ") else {
            let _ = child.kill();
            bail!("mcu_emulator said {line:?} instead of `pty PATH`");
        };
        eprintln!("MCU emulator on {device} at {speed}×");
        Ok(Emulator {
            device: device.to_string(),
            child,
        })
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A print the job itself stopped on the path, because its bag could not be written or a
/// node of the pipeline failed (not an operator): `serve` reports it as aborted, not as
/// cancelled.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct StoppedByJob(pub String);

/// How a print ended, when it did not end by itself.
enum Stop {
    Interrupted,
    Failed(anyhow::Error),
    /// The bag could not be written (why): the machine stops on the path, as for Ctrl-C.
    BagFailed(String),
}

/// What a print job is told and tells while it runs: interrupts (the first is a cancel, the
/// second an emergency stop) and the executor's status.
pub struct JobIo {
    pub interrupts: tokio::sync::watch::Receiver<u32>,
    pub status: tokio::sync::watch::Sender<cell_machine::node::Status>,
    /// The pre-flight's machine time of the plan, once known.
    pub planned: tokio::sync::watch::Sender<Option<f64>>,
    /// `/cell` service calls that the caller serves and hands to this job's machine (which
    /// then serves none itself), or `None`: the machine serves them.
    pub cell_requests: Option<tokio::sync::mpsc::UnboundedReceiver<cell_machine::node::Request>>,
}

/// How a print job that did not fail ended.
#[derive(Clone, Debug, PartialEq)]
pub enum Ending {
    Finished,
    /// Interrupted; executing, the machine stopped as said (cancel or emergency stop).
    Interrupted {
        emergency: bool,
        how: Option<String>,
    },
}

/// A print job's end.
pub struct JobReport {
    pub ending: Ending,
    pub summary: Option<StreamSummary>,
}

/// A job interrupted before any node started: nothing moved, nothing to stop.
fn interrupted_before_start() -> JobReport {
    JobReport {
        ending: Ending::Interrupted {
            emergency: false,
            how: None,
        },
        summary: None,
    }
}

/// Resolves once `interrupts` has counted `n`.
async fn interrupted(interrupts: &tokio::sync::watch::Receiver<u32>, n: u32) {
    let mut rx = interrupts.clone();
    if rx.wait_for(|&count| count >= n).await.is_err() {
        std::future::pending::<()>().await;
    }
}

/// `polar-cell print`: a job whose interrupts are SIGINT/SIGTERM, its end said on stderr
/// and in the exit code.
pub async fn print(file: &str, options: &PrintOptions, ros_args: &RosArgs) -> anyhow::Result<()> {
    let (count, interrupts) = tokio::sync::watch::channel(0u32);
    let mut shutdown = cell_runtime::ShutdownSignals::new()?;
    let signals = tokio::spawn(async move {
        loop {
            shutdown.next().await;
            count.send_modify(|n| *n += 1);
        }
    });
    let (status, _) = tokio::sync::watch::channel(cell_machine::node::Status::default());
    let (planned, _) = tokio::sync::watch::channel(None);
    let io = JobIo {
        interrupts,
        status,
        planned,
        cell_requests: None,
    };
    let report = run_job(file, options, ros_args, io).await;
    signals.abort();
    let report = report?;
    match report.ending {
        Ending::Interrupted { how: Some(how), .. } => bail!("{how}; the bag was finished"),
        Ending::Interrupted { how: None, .. } => {
            bail!("interrupted before the end of {file}; the bag was finished")
        }
        Ending::Finished => Ok(()),
    }
}

/// How long a finished job waits for subscribers to acknowledge the nodes' last messages.
const DELIVER_TIMEOUT: Duration = Duration::from_secs(5);

/// Run one print: the whole graph for `file`, until it is printed, interrupted or failed.
pub async fn run_job(
    file: &str,
    options: &PrintOptions,
    ros_args: &RosArgs,
    io: JobIo,
) -> anyhow::Result<JobReport> {
    let recorder_specs = cell_bag::node::param_specs();
    let streamer_specs = gcode_streamer::node::param_specs();
    let planner_specs = polar_planner::node::param_specs();
    let screw_specs = screw_driver::node::param_specs();
    // The machine: the MCU bridge with a device, else the virtual executor.
    let (machine_name, executor_specs) = match options.device {
        Some(_) => (mcu_bridge::node::NODE_NAME, mcu_bridge::node::param_specs()),
        None => (
            cell_executor::node::NODE_NAME,
            cell_executor::node::param_specs(),
        ),
    };
    check_params(
        ros_args,
        &[
            (cell_bag::node::NODE_NAME, &recorder_specs),
            (gcode_streamer::node::NODE_NAME, &streamer_specs),
            (polar_planner::node::NODE_NAME, &planner_specs),
            (screw_driver::node::NODE_NAME, &screw_specs),
            (machine_name, &executor_specs),
        ],
    )?;
    // The nodes of one process share its command line: an unprefixed node rename would give
    // them all one name (and the print would wait for consumers that never appear).
    if let Some(rename) = ros_args
        .remaps
        .iter()
        .find(|r| r.node.is_none() && matches!(r.from.as_str(), "__node" | "__name"))
    {
        bail!(
            "-r {6}:={0} would give every node of this print the name {0:?}; rename one \
             with -r NODE:__node:={0} (NODE: {1}, {2}, {3}, {4} or {5})",
            rename.to,
            gcode_streamer::node::NODE_NAME,
            polar_planner::node::NODE_NAME,
            screw_driver::node::NODE_NAME,
            cell_executor::node::NODE_NAME,
            cell_bag::node::NODE_NAME,
            rename.from,
        );
    }
    if let (Some(device), Some(speed)) = (options.device.as_deref(), options.execution) {
        if speed != 1.0 && is_serial_port(device) {
            bail!(
                "speed {speed} with the serial device {device}: a microcontroller's clock runs \
                 at machine pace, speed 1 (other speeds are for the virtual executor, \
                 `--device emulator` and emulated MCUs behind a pseudo-terminal or a unix: socket)"
            );
        }
    }
    // A real MCU is where the last print left it (a cancel leaves it mid-part): ask it,
    // and plan from there.
    let start_joints = match (options.device.as_deref(), options.execution) {
        (Some(device), Some(_)) if device != "emulator" && options.start_joints.is_none() => {
            // A second or so of serial line: off the runtime's threads (`serve` goes on).
            let (device, args) = (device.to_string(), ros_args.clone());
            let asked = tokio::task::spawn_blocking(move || mcu_position(&device, &args));
            // Waited for even when interrupted (it ends within its timeouts): abandoned, it
            // would hold the line that the next job opens.
            let joints = asked.await.context("asking the MCU where it stands")??;
            if *io.interrupts.borrow() > 0 {
                return Ok(interrupted_before_start());
            }
            eprintln!("The print starts where the MCU stands.");
            Some(joints)
        }
        _ => options.start_joints,
    };
    // Before any node starts (no DDS, no bag): the whole file with the parameters the nodes
    // will get.
    let mut machine_time_s = None;
    let mut total_moves = None;
    if options.run_preflight && file != "-" {
        let (streamer, planner) = preflight_params(ros_args, start_joints)?;
        let started = std::time::Instant::now();
        // Off the runtime's threads: `serve` answers its clients meanwhile (a million moves
        // take seconds).
        let checked = file.to_string();
        let cancel = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let cancelled = cancel.clone();
        let checking = tokio::task::spawn_blocking(move || {
            preflight(&checked, &streamer, &planner, &cancelled)
        });
        // Cancelled while checking: nothing has started, nothing to stop; the check ends
        // at its next move.
        let report = tokio::select! {
            report = checking => report.context("the pre-flight")??,
            _ = interrupted(&io.interrupts, 1) => {
                cancel.store(true, std::sync::atomic::Ordering::Relaxed);
                return Ok(interrupted_before_start());
            }
        };
        eprintln!(
            "{file}: pre-flight passed: {}",
            describe(&report, started.elapsed())
        );
        machine_time_s = Some(report.plan_time_s);
        total_moves = Some(report.moves);
        io.planned.send_replace(machine_time_s);
    }
    let (input, total) = open_input(file)?;
    // The consumers take moves only from the streamer's writers: tell them its name.
    let streamer_name = {
        let args = args_for(
            ros_args,
            gcode_streamer::node::NODE_NAME,
            &streamer_specs,
            vec![],
        );
        let (names, _) =
            cell_runtime::resolve_node(gcode_streamer::node::NODE_NAME, &streamer_specs, &args)?;
        names.fully_qualified_node_name()
    };
    let producer = || param("producer", format!("{streamer_name:?}"));

    let recorder_node = start_node(
        cell_bag::node::NODE_NAME,
        &recorder_specs,
        ros_args,
        [
            vec![
                param("output", format!("{:?}", options.bag.display().to_string())),
                param("bag_directory", options.bag_dir.to_string()),
                producer(),
            ],
            // At machine pace the topics' rates are bounded: a shallower history, less memory.
            match options.execution {
                Some(speed) => {
                    // The horizon of the machine that runs (the bridge's with a device).
                    let args = args_for(ros_args, machine_name, &executor_specs, vec![]);
                    let (_, machine) =
                        cell_runtime::resolve_node(machine_name, &executor_specs, &args)?;
                    let horizon_s = machine.f64("horizon_s");
                    let depth = cell_bag::node::executed_reader_depth(speed, horizon_s);
                    vec![param("reader_depth", depth.to_string())]
                }
                // No machine: the bag is the plan's slowest consumer, and grants the credit;
                // what is in flight to it is then bounded, and so is its history.
                None => {
                    let ours = vec![param("grant_credit", "true".into())];
                    let args = args_for(
                        ros_args,
                        cell_bag::node::NODE_NAME,
                        &recorder_specs,
                        ours.clone(),
                    );
                    let (_, recorder) = cell_runtime::resolve_node(
                        cell_bag::node::NODE_NAME,
                        &recorder_specs,
                        &args,
                    )?;
                    let depth = cell_bag::node::CREDITED_READER_DEPTH;
                    match cell_bag::node::grants_credit(&recorder) {
                        true => [ours, vec![param("reader_depth", depth.to_string())]].concat(),
                        false => ours,
                    }
                }
            },
        ]
        .concat(),
    )?;
    let bag_grants_credit =
        options.execution.is_none() && cell_bag::node::grants_credit(&recorder_node.params);
    let recorder_name = recorder_node.fully_qualified_name();
    let credit_horizon_s = recorder_node.params.f64("credit_horizon_s");
    let recorder = Recorder::start(recorder_node)?;
    let (executor_overrides, planner_extra, screw_extra) =
        match (options.execution, bag_grants_credit) {
            (Some(speed), _) => execution_overrides(ros_args, speed, options.device.is_some())?,
            // The screw driver's chunks are cut at a quarter of the credit's horizon, as at
            // machine pace: a minute of commands at once would outrun the bag's history.
            (None, true) => (
                vec![],
                vec![param("follow_execution", "true".into())],
                vec![screw_chunk_for(credit_horizon_s)],
            ),
            (None, false) => (vec![], vec![], vec![]),
        };
    let mut screw_extra = screw_extra;
    screw_extra.push(producer());
    let mut screw_node = start_node(
        screw_driver::node::NODE_NAME,
        &screw_specs,
        ros_args,
        screw_extra,
    )?;
    let mut ours = planner_overrides(&screw_node.params);
    ours.extend(planner_extra);
    ours.extend(start_override(start_joints));
    if options.execution.is_some() {
        // The planner follows only the machine's credit.
        let args = args_for(ros_args, machine_name, &executor_specs, vec![]);
        let (names, _) = cell_runtime::resolve_node(machine_name, &executor_specs, &args)?;
        let machine = names.fully_qualified_node_name();
        ours.push(param("credit_producer", format!("{machine:?}")));
    } else if bag_grants_credit {
        ours.push(param("credit_producer", format!("{recorder_name:?}")));
    }
    if options.execution.is_none() {
        // No machine node to publish the cell's description: the bag has it all the same.
        ours.push(param("publish_robot_description", "true".into()));
    }
    ours.push(producer());
    let mut planner_node = start_node(
        polar_planner::node::NODE_NAME,
        &planner_specs,
        ros_args,
        ours,
    )?;
    // The machine executes steps and screw commands only from these two nodes.
    let mut executor_overrides = executor_overrides;
    executor_overrides.extend(start_override(start_joints));
    executor_overrides.extend([
        producer(),
        param(
            "steps_producer",
            format!("{:?}", planner_node.fully_qualified_name()),
        ),
        param(
            "screw_producer",
            format!("{:?}", screw_node.fully_qualified_name()),
        ),
        // The bag has the machine's states from the first.
        param("await_subscribers", format!("[{recorder_name:?}]")),
    ]);
    if io.cell_requests.is_some() {
        executor_overrides.push(param("cell_services", "false".into()));
    }
    let (commands, command_rx) = tokio::sync::mpsc::unbounded_channel();
    if let (Some(mut requests), Some(_)) = (io.cell_requests, options.execution) {
        // Handed over as they come; once the machine is gone, a request's answer sender is
        // dropped with it, and so is this receiver: the caller answers for itself.
        let to_machine = commands.clone();
        tokio::spawn(async move {
            while let Some(request) = requests.recv().await {
                if to_machine.send(request).is_err() {
                    break;
                }
            }
        });
    }
    let status_tx = io.status;
    let status = status_tx.subscribe();
    // The MCU emulator of `--device emulator` lives as long as the job.
    let mut _emulator = None;
    // The machine node (`None`: a dry run). Its task ends on `end_machine` and hands the node
    // back, its live-state writers still alive: a sample lost on the way to the recorder is
    // repaired only while its writer exists.
    let (end_machine, machine_ended) = tokio::sync::oneshot::channel::<()>();
    let machine_node = match (options.execution, options.device.as_deref()) {
        (Some(speed), Some(device)) => {
            let device = match device {
                "emulator" => {
                    let emulator = Emulator::start(speed)?;
                    let path = emulator.device.clone();
                    _emulator = Some(emulator);
                    path
                }
                path => path.to_string(),
            };
            let mut overrides = executor_overrides;
            overrides.push(param("device", format!("{device:?}")));
            let node = start_node(
                mcu_bridge::node::NODE_NAME,
                &executor_specs,
                ros_args,
                overrides,
            )?;
            Some((node, true))
        }
        (Some(_), None) => {
            let node = start_node(
                cell_executor::node::NODE_NAME,
                &executor_specs,
                ros_args,
                executor_overrides,
            )?;
            Some((node, false))
        }
        (None, _) => None,
    };
    let mut executor = machine_node.map(|(mut node, on_mcu)| {
        tokio::spawn(async move {
            let run = async {
                match on_mcu {
                    true => mcu_bridge::node::run(&mut node, command_rx, status_tx).await,
                    false => cell_executor::node::run(&mut node, command_rx, status_tx).await,
                }
            };
            let result = tokio::select! {
                result = run => result,
                _ = machine_ended => Ok(()),
            };
            (node, result)
        })
    });
    let consumers = format!(
        "[{:?}, {:?}, {:?}]",
        recorder.node_name(),
        planner_node.fully_qualified_name(),
        screw_node.fully_qualified_name()
    );
    let mut streamer = start_node(
        gcode_streamer::node::NODE_NAME,
        &streamer_specs,
        ros_args,
        [
            vec![param("consumers", consumers)],
            streamer_start_override(start_joints),
        ]
        .concat(),
    )?;
    // The planner and screw driver run until they fail or the job ends them; either way their
    // task hands the node back, writers alive, for the final delivery.
    let (end_pipeline, pipeline_ended) = tokio::sync::watch::channel(false);
    let mut screw = tokio::spawn({
        let mut ended = pipeline_ended.clone();
        async move {
            let result = tokio::select! {
                result = screw_driver::node::run(&mut screw_node) => result,
                _ = ended.wait_for(|&ended| ended) => Ok(()),
            };
            (screw_node, result)
        }
    });
    let mut planner = tokio::spawn({
        let mut ended = pipeline_ended;
        async move {
            let result = tokio::select! {
                result = polar_planner::node::run(&mut planner_node) => result,
                _ = ended.wait_for(|&ended| ended) => Ok(()),
            };
            (planner_node, result)
        }
    });

    let bar = progress_bar(options, total_moves, machine_time_s);
    let executing = options.execution.is_some();
    let executor_failed = async {
        match executor.as_mut() {
            Some(task) => stopped(machine_name, task.await),
            None => std::future::pending().await,
        }
    };
    let streamed = tokio::select! {
        finished = &mut planner => Err(Stop::Failed(stopped(polar_planner::node::NODE_NAME, finished))),
        finished = &mut screw => Err(Stop::Failed(stopped(screw_driver::node::NODE_NAME, finished))),
        e = executor_failed => Err(Stop::Failed(e)),
        r = gcode_streamer::node::stream(&mut streamer, input, file, total, |p| {
            if !executing {
                // Moves every consumer acknowledged: what is done, not what was read.
                bar.set_position(p.moves_acknowledged);
                bar.set_message(format!(
                    "line {} · {} moves sent · {} acknowledged",
                    p.lines_read, p.moves_published, p.moves_acknowledged
                ));
            }
        }) => r.map_err(Stop::Failed),
        e = machine_failed(status.clone()), if executing => Err(Stop::Failed(e)),
        _ = show_execution(&bar, status.clone(), machine_time_s), if executing => unreachable!("the progress display never ends"),
        _ = interrupted(&io.interrupts, 1) => Err(Stop::Interrupted),
        reason = recorder.failed() => Err(Stop::BagFailed(reason)),
    };
    // Executing: the stream is over once every move is planned; the machine runs on until it
    // has executed the plan (or is stopped).
    let outcome = match (streamed, executing) {
        (Ok(summary), true) => {
            tokio::select! {
                // A fault or an e-stop wins over an end seen at the same time.
                biased;
                e = machine_failed(status.clone()) => Err(Stop::Failed(e)),
                r = wait_executed(status.clone()) => r.map(|()| summary).map_err(Stop::Failed),
                finished = &mut planner => Err(Stop::Failed(stopped(polar_planner::node::NODE_NAME, finished))),
                finished = &mut screw => Err(Stop::Failed(stopped(screw_driver::node::NODE_NAME, finished))),
                _ = show_execution(&bar, status.clone(), machine_time_s) => unreachable!("the progress display never ends"),
                _ = interrupted(&io.interrupts, 1) => Err(Stop::Interrupted),
                reason = recorder.failed() => Err(Stop::BagFailed(reason)),
            }
        }
        (other, _) => other,
    };
    // Ctrl-C while the machine moves: a controlled stop on the path; a second: stop at once.
    // The same when the bag cannot be written (nothing more of the print could be recorded,
    // and the recorder's acknowledgements that pace the stream are gone with it).
    // So too when a node of the pipeline failed while the machine runs: dropping the machine
    // would stop a real MCU at once, mid-move.
    // (Not a machine whose node is gone — its status is its last — nor one that never ran.)
    let machine_runs_on = || {
        let alive = status.has_changed().is_ok();
        let s = status.borrow();
        alive
            && s.state.is_some()
            && s.fault.is_none()
            && s.state != Some(cell_executor::PlayerState::Stopped)
            && !s.cancelled
            && !s.done
    };
    let mut ended = None;
    if executing
        && (matches!(outcome, Err(Stop::Interrupted | Stop::BagFailed(_)))
            || (matches!(outcome, Err(Stop::Failed(_))) && machine_runs_on()))
    {
        ended = Some(stop_machine(&commands, &status, &bar, &io.interrupts).await);
    }
    bar.finish_and_clear();
    if outcome.is_ok() {
        if !recorder.wait_stream_finished(Duration::from_secs(10)).await {
            eprintln!("warning: the bag did not receive the final /gcode/progress within 10 s");
        }
        // The planner and screw driver flush what they buffered once input stops, and the
        // streamer's closing diagnostics follow its final progress: record until all is quiet.
        let quiet = Duration::from_millis(500);
        if !executing && !recorder.wait_quiet(quiet, Duration::from_secs(60)).await {
            eprintln!("warning: messages were still arriving 60 s after the stream finished");
        }
    }
    if executing {
        // The executor's last samples (at rest) reach the bag before it closes.
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    // Tasks finished by now ended by themselves and were awaited above (their nodes are
    // gone): not again. The others are told to end and hand their nodes back; the machine
    // stops publishing, and its node stays until the bag is closed. (Checked before the end
    // is sent: a task that ends on it is finished a moment later, its node still to collect.)
    let pipeline_tasks: Vec<_> = [planner, screw]
        .into_iter()
        .filter(|task| !task.is_finished())
        .collect();
    let machine_task = executor.take().filter(|task| !task.is_finished());
    let _ = end_pipeline.send(true);
    let _ = end_machine.send(());
    let mut pipeline_nodes = Vec::new();
    for task in pipeline_tasks {
        pipeline_nodes.extend(task.await.ok().map(|(node, _)| node));
    }
    let mut _machine_node = None;
    if let Some(task) = machine_task {
        _machine_node = task.await.ok().map(|(node, _)| node);
    }
    // What the nodes published last is still on its way to the recorder's readers, and a
    // sample lost on loopback is resent only after the writer's next heartbeat: a bag closed
    // now could hold a /joint_states without its /tf. Quiet for longer than RustDDS's slow
    // heartbeat period (1 s) means no repair is still due.
    recorder
        .wait_quiet(Duration::from_millis(1200), Duration::from_secs(5))
        .await;
    // Subscribers outside this process (a `ros2 topic echo`, RViz, a recorder) get what the
    // nodes published last only while their writers exist: wait for their acknowledgements,
    // bounded, and name the readers that did not give them.
    let nodes: Vec<&CellNode> = std::iter::once(&streamer)
        .chain(&pipeline_nodes)
        .chain(&_machine_node)
        .collect();
    for undelivered in cell_runtime::wait_delivered(&nodes, DELIVER_TIMEOUT).await {
        eprintln!(
            "warning: after {} s, {undelivered}",
            DELIVER_TIMEOUT.as_secs_f64()
        );
    }
    let recorded = recorder.stop().await;
    let recorded = match &outcome {
        // (The recorder's own error is the writer's again: the reason says it.)
        Err(Stop::BagFailed(reason)) => {
            return Err(StoppedByJob(match ended {
                Some((_, how)) => format!("{reason}; {how}"),
                None => reason.clone(),
            })
            .into())
        }
        _ => recorded.context("finishing the bag")?,
    };
    match outcome {
        Err(Stop::BagFailed(_)) => unreachable!("ended above"),
        Err(Stop::Interrupted) => {
            print_summary(&recorded);
            Ok(JobReport {
                ending: Ending::Interrupted {
                    emergency: ended.as_ref().is_some_and(|(emergency, _)| *emergency),
                    how: ended.map(|(_, how)| how),
                },
                summary: None,
            })
        }
        Err(Stop::Failed(e)) => {
            print_summary(&recorded);
            match ended {
                Some((_, how)) => Err(StoppedByJob(format!("{e:#}; {how}")).into()),
                None => Err(e),
            }
        }
        Ok(s) => {
            let secs = s.elapsed.as_secs_f64();
            eprintln!(
                "{file}: {} moves from {} lines ({} bytes) in {:.3} s — {:.0} moves/s, {} warnings, {} resends",
                s.moves,
                s.lines,
                s.bytes,
                secs,
                s.moves as f64 / secs.max(1e-9),
                s.warnings,
                s.resends
            );
            if executing {
                let st = status.borrow().clone();
                let executed_s = st.executed_s();
                eprintln!(
                    "{file}: executed {} step segments in {} of machine time from the first \
                     step ({:.3} s; planned {}), {} underruns",
                    st.segments_completed,
                    clock(executed_s),
                    executed_s,
                    machine_time_s.map_or("-".to_string(), |t| format!("{t:.3} s")),
                    st.underruns
                );
            }
            print_summary(&recorded);
            // A print is a success only with its whole record: every sample, and every move
            // the streamer counts as acknowledged by every consumer, the recorder among them.
            if let Some(loss) = recorded.loss() {
                bail!(loss);
            }
            if let Some((_, _, recorded_moves)) = recorded
                .topics
                .iter()
                .find(|(topic, _, _)| topic == "/gcode/moves")
            {
                if *recorded_moves != s.moves {
                    bail!(
                        "the bag holds {recorded_moves} of the {} moves the stream reports \
                         delivered to every consumer",
                        s.moves
                    );
                }
            }
            Ok(JobReport {
                ending: Ending::Finished,
                summary: Some(s),
            })
        }
    }
}

/// The overrides that make a print execute: the executor gets the planner's step and
/// acceleration settings and the screw driver's pin delay and command hold; the planner
/// follows the executor's credit; the screw driver computes commands in pieces well inside the
/// executor's horizon, and leaves a stall to the executor (it holds at rest on the path).
fn execution_overrides(
    ros_args: &RosArgs,
    speed: f64,
    on_mcu: bool,
) -> anyhow::Result<(Vec<ParamOverride>, Vec<ParamOverride>, Vec<ParamOverride>)> {
    let NodeParams {
        screw,
        planner,
        executor,
        ..
    } = node_params(ros_args, None)?;
    let screw_options = screw_driver::node::options_from_params(&screw)?;
    // The screw on an amplifier's serial line takes a few commands a second: the screw
    // driver puts its commands on that grid, each the exact average over its interval.
    let mut command_period_s = screw.f64("command_period_s");
    let mut screw_extra = vec![];
    // The horizon of the machine that runs: the screw's chunks stay inside it.
    let mut horizon_s = executor.f64("horizon_s");
    if on_mcu {
        let specs = mcu_bridge::node::param_specs();
        let name = mcu_bridge::node::NODE_NAME;
        let (_, bridge) =
            cell_runtime::resolve_node(name, &specs, &args_for(ros_args, name, &specs, vec![]))?;
        horizon_s = bridge.f64("horizon_s");
        let line_period_s = 1.0 / bridge.f64("screw_max_rate_hz");
        if !bridge.string("screw_port").is_empty() && command_period_s < line_period_s {
            command_period_s = line_period_s;
            screw_extra.push(param("command_period_s", format!("{command_period_s:?}")));
        }
    }
    let hold = match screw_driver::node::command_hold(&screw_options, command_period_s) {
        polar_cell_msgs::Hold::ZeroOrder => "zero_order",
        polar_cell_msgs::Hold::FirstOrder => "first_order",
    };
    let list = |v: &[f64]| {
        format!(
            "[{}]",
            v.iter()
                .map(|x| format!("{x:?}"))
                .collect::<Vec<_>>()
                .join(", ")
        )
    };
    let executor_overrides = vec![
        param("speed", format!("{speed:?}")),
        param("steps_per_unit", list(planner.f64s("steps_per_unit"))),
        // The machine shows the joints the planner planned for (a rig profile's URDF).
        param("urdf_file", format!("{:?}", planner.string("urdf_file"))),
        param(
            "step_timer_hz",
            format!("{:?}", planner.f64("step_timer_hz")),
        ),
        param(
            "joint_accelerations",
            list(planner.f64s("joint_accelerations")),
        ),
        param(
            "pin_open_delay_s",
            format!("{:?}", screw.f64("pin_open_delay_s")),
        ),
        param("screw_hold", hold.to_string()),
    ];
    let planner_extra = vec![param("follow_execution", "true".into())];
    screw_extra.extend([
        screw_chunk_for(horizon_s),
        param("stall_flush_s", "3600.0".into()),
    ]);
    Ok((executor_overrides, planner_extra, screw_extra))
}

/// The screw driver's chunk for producers `horizon_s` of plan ahead of their consumer (the
/// machine, or a dry run's bag): a quarter of the horizon, so its commands never outrun
/// what the consumer holds.
fn screw_chunk_for(horizon_s: f64) -> ParamOverride {
    param("max_buffer_s", format!("{:?}", (horizon_s / 4.0).max(0.1)))
}

/// Executing: over the plan's machine time; dry run: over the moves (from the pre-flight;
/// without it, a spinner).
fn progress_bar(
    options: &PrintOptions,
    total_moves: Option<u64>,
    machine_time_s: Option<f64>,
) -> ProgressBar {
    if !options.show_progress {
        return ProgressBar::hidden();
    }
    let bar = match (options.execution, machine_time_s) {
        (Some(_), Some(t)) => ProgressBar::new(((t * 1000.0) as u64).max(1)),
        (Some(_), None) => ProgressBar::new_spinner(),
        (None, _) => match total_moves {
            Some(moves) => ProgressBar::new(moves.max(1)),
            None => ProgressBar::new_spinner(),
        },
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} {bar:40} {percent:>3}% {msg}")
            .expect("static template"),
    );
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}

/// `m:ss.s` (or `h:mm:ss`) of a duration in seconds.
fn clock(seconds: f64) -> String {
    // Rounded to what is shown before splitting, so that 59.96 s reads 1:00.0, not 0:60.0.
    let tenths = (seconds.max(0.0) * 10.0).round() as u64;
    if tenths >= 36_000 {
        let s = tenths / 10;
        format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
    } else {
        format!("{}:{:02}.{}", tenths / 600, tenths / 10 % 60, tenths % 10)
    }
}

fn execution_message(s: &cell_machine::node::Status, machine_time_s: Option<f64>) -> String {
    let state = s.state_label().replace('_', " ");
    let line = s
        .current
        .map(|(_, line)| format!(" · line {line}"))
        .unwrap_or_default();
    let remaining = machine_time_s
        .map(|t| format!(" · {} left", clock(t - s.plan_time_s)))
        .unwrap_or_default();
    format!(
        "{state} · machine {}{remaining}{line}",
        clock(s.machine_time_s)
    )
}

/// Resolves when the machine stops short of the plan's end: a fault, or from outside an
/// emergency stop or a cancel (`/cell/cancel`, once at rest on the path: the plan is dropped,
/// and nothing more of it will run).
async fn machine_failed(
    mut status: tokio::sync::watch::Receiver<cell_machine::node::Status>,
) -> anyhow::Error {
    loop {
        {
            let s = status.borrow_and_update();
            if let Some(fault) = &s.fault {
                return anyhow::anyhow!("the executor stopped the machine: {fault}");
            }
            if s.state == Some(cell_executor::PlayerState::Stopped) {
                return anyhow::anyhow!("emergency stop (/cell/estop) during the print");
            }
            if s.cancelled_at_rest() {
                return anyhow::anyhow!(stop_text(
                    "cancelled (/cell/cancel): stopped on the path",
                    &s
                ));
            }
        }
        if status.changed().await.is_err() {
            return std::future::pending().await;
        }
    }
}

/// Wait until the executor has executed the whole plan.
async fn wait_executed(
    mut status: tokio::sync::watch::Receiver<cell_machine::node::Status>,
) -> anyhow::Result<()> {
    match status.wait_for(|s| s.done).await {
        Ok(_) => Ok(()),
        Err(_) => bail!("the executor ended"),
    }
}

/// The progress bar from the executor's status, at most ten times a second; never ends.
async fn show_execution(
    bar: &ProgressBar,
    mut status: tokio::sync::watch::Receiver<cell_machine::node::Status>,
    machine_time_s: Option<f64>,
) {
    while status.changed().await.is_ok() {
        let s = status.borrow_and_update().clone();
        bar.set_position((s.plan_time_s * 1000.0) as u64);
        bar.set_message(execution_message(&s, machine_time_s));
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    std::future::pending().await
}

/// Ctrl-C while executing: cancel (stop on the path within the acceleration limits, pin
/// closed, screw stopped); a second Ctrl-C during that stop: emergency stop. Says how it ended.
async fn stop_machine(
    commands: &tokio::sync::mpsc::UnboundedSender<cell_machine::node::Request>,
    status: &tokio::sync::watch::Receiver<cell_machine::node::Status>,
    bar: &ProgressBar,
    interrupts: &tokio::sync::watch::Receiver<u32>,
) -> (bool, String) {
    use cell_executor::PlayerState;
    use cell_machine::node::Command;
    let _ = commands.send(Command::Cancel.into());
    // The second interrupt is the emergency stop, whether this stop came from the first (a
    // Ctrl-C, an action's cancel) or from the job itself (a bag that cannot be written, a
    // node that failed): then a cancel asked meanwhile is that stop, not an emergency.
    const EMERGENCY_AT: u32 = 2;
    bar.println(if *interrupts.borrow() == 0 {
        "stopping on the path (Ctrl-C twice: emergency stop)"
    } else {
        "cancelling: stopping on the path (Ctrl-C again: emergency stop)"
    });
    let mut watch = status.clone();
    let at_rest = async {
        loop {
            {
                let s = watch.borrow_and_update();
                if s.cancelled_at_rest()
                    || s.state == Some(PlayerState::Stopped)
                    || s.state.is_none()
                {
                    return s.clone();
                }
            }
            if watch.changed().await.is_err() {
                return watch.borrow().clone();
            }
        }
    };
    let (s, emergency) = tokio::select! {
        s = at_rest => (s, false),
        _ = interrupted(interrupts, EMERGENCY_AT) => {
            let _ = commands.send(Command::EmergencyStop.into());
            let mut watch = status.clone();
            // The machine stops within a control period; a machine that does not say so
            // within seconds is not waited for (nor is a third Ctrl-C ignored meanwhile).
            let confirmed = async {
                loop {
                    if watch.borrow_and_update().state == Some(PlayerState::Stopped) { break; }
                    if watch.changed().await.is_err() { break; }
                }
            };
            tokio::select! {
                _ = tokio::time::timeout(ESTOP_CONFIRM, confirmed) => {}
                _ = interrupted(interrupts, EMERGENCY_AT + 1) => {}
            }
            let s = status.borrow().clone();
            if s.state != Some(PlayerState::Stopped) && s.state.is_some() {
                return (true, format!(
                    "emergency stop sent; the machine did not confirm it within {} s",
                    ESTOP_CONFIRM.as_secs()
                ));
            }
            (s, true)
        }
    };
    // The machine may have stopped at once meanwhile, by a fault or `/cell/estop`: that is
    // how it ended, not on the path.
    let stopped_at_once = emergency || s.state == Some(PlayerState::Stopped);
    let how = match &s.fault {
        Some(fault) if stopped_at_once => format!("the machine stopped at once: {fault}"),
        None if emergency => "emergency stop".to_string(),
        None if stopped_at_once => "emergency stop (/cell/estop) while stopping".to_string(),
        _ => "cancelled: stopped on the path".to_string(),
    };
    (stopped_at_once, stop_text(&how, &s))
}

/// How long an emergency stop's confirmation is waited for.
const ESTOP_CONFIRM: Duration = Duration::from_secs(5);

/// Whether `device` is a serial port, where a real microcontroller keeps real time: not the
/// built-in emulator, a `unix:` socket or a pseudo-terminal (which an emulator serves). A
/// path that does not resolve is left to the bridge to refuse.
fn is_serial_port(device: &str) -> bool {
    if device == "emulator" || device.starts_with("unix:") {
        return false;
    }
    use std::os::unix::fs::FileTypeExt;
    std::fs::canonicalize(device).is_ok_and(|path| {
        let character_device =
            std::fs::metadata(&path).is_ok_and(|m| m.file_type().is_char_device());
        character_device && !(path.starts_with("/dev/pts") || path.ends_with("ptmx"))
    })
}

/// How a print stopped short, where and when: "`how` at line L after T of machine time (bed,
/// arm, z)".
fn stop_text(how: &str, s: &cell_machine::node::Status) -> String {
    let line = s
        .current
        .map(|(_, line)| format!(" at line {line}"))
        .unwrap_or_default();
    let [bed, arm, z, _] = s.positions;
    format!(
        "{how}{line} after {} of machine time (bed {bed:.6} rad, arm {arm:.6} m, z {z:.6} m)",
        clock(s.machine_time_s)
    )
}

/// The nodes' parameters exactly as `print` gives them (global `-p` only where a node
/// declares it, the planner told of the screw), without DDS.
struct NodeParams {
    streamer: cell_runtime::Params,
    planner: cell_runtime::Params,
    screw: cell_runtime::Params,
    executor: cell_runtime::Params,
}

fn node_params(ros_args: &RosArgs, start: Option<[f64; 3]>) -> anyhow::Result<NodeParams> {
    let resolve = |name: &str, specs: &[ParamSpec], ours| {
        cell_runtime::resolve_node(name, specs, &args_for(ros_args, name, specs, ours))
            .map(|(_, params)| params)
    };
    let screw = resolve(
        screw_driver::node::NODE_NAME,
        &screw_driver::node::param_specs(),
        vec![],
    )?;
    Ok(NodeParams {
        planner: resolve(
            polar_planner::node::NODE_NAME,
            &polar_planner::node::param_specs(),
            [planner_overrides(&screw), start_override(start)].concat(),
        )?,
        streamer: resolve(
            gcode_streamer::node::NODE_NAME,
            &gcode_streamer::node::param_specs(),
            streamer_start_override(start),
        )?,
        executor: resolve(
            cell_executor::node::NODE_NAME,
            &cell_executor::node::param_specs(),
            start_override(start),
        )?,
        screw,
    })
}

/// The streamer's and the planner's parameters, for the pre-flight.
fn preflight_params(
    ros_args: &RosArgs,
    start: Option<[f64; 3]>,
) -> anyhow::Result<(cell_runtime::Params, cell_runtime::Params)> {
    let NodeParams {
        streamer, planner, ..
    } = node_params(ros_args, start)?;
    Ok((streamer, planner))
}

/// The whole file through the planner and the step core as the print would run it (the
/// streamer's interpreter options, the planner's options), before anything moves: a file that
/// would fail later — a move beyond the arm's reach at its very end — is refused now, with its
/// line, joint and value. Constant memory; the cost is one planning pass (README).
fn preflight(
    file: &str,
    streamer: &cell_runtime::Params,
    planner: &cell_runtime::Params,
    cancelled: &std::sync::atomic::AtomicBool,
) -> anyhow::Result<polar_planner::PreflightReport> {
    let (options, steps) = polar_planner::node::options_from_params(planner)?;
    let interpreter = gcode_streamer::node::interpreter_options(streamer)?;
    let (input, _) = open_input(file)?;
    let mut reader = GcodeReader::new(input, file, interpreter);
    let mut check = polar_planner::Preflight::new(options, steps)?;
    for event in reader.by_ref() {
        if cancelled.load(std::sync::atomic::Ordering::Relaxed) {
            bail!("{file}: pre-flight cancelled");
        }
        if let Event::Move(m) = event? {
            check
                .push(&m)
                .with_context(|| format!("{file}: pre-flight refuses the print"))?;
        }
    }
    check
        .finish()
        .with_context(|| format!("{file}: pre-flight refuses the print"))
}

fn describe(report: &polar_planner::PreflightReport, took: Duration) -> String {
    // Whole milliseconds first, so that 59.9996 s reads 0:01:00.000, not 0:00:60.000.
    let ms = (report.plan_time_s * 1e3).round() as u64;
    format!(
        "{} moves, {}:{:02}:{:02}.{:03} of machine time, {} step segments; checked in {:.2} s",
        report.moves,
        ms / 3_600_000,
        ms / 60_000 % 60,
        ms / 1000 % 60,
        ms % 1000,
        report.segments,
        took.as_secs_f64()
    )
}

/// `polar-cell check FILE`: the parser, then (unless `parse_only`) the pre-flight with the
/// parameters the print's nodes would get from the same ROS arguments.
pub fn check(
    file: &str,
    parse_only: bool,
    start_joints: Option<[f64; 3]>,
    ros_args: &RosArgs,
) -> anyhow::Result<()> {
    let (input, _) = open_input(file)?;
    let (streamer, planner) = preflight_params(ros_args, start_joints)?;
    let mut reader = GcodeReader::new(
        input,
        file,
        gcode_streamer::node::interpreter_options(&streamer)?,
    );
    let mut moves = 0u64;
    let mut warnings = 0u64;
    for event in reader.by_ref() {
        match event? {
            Event::Move(_) => moves += 1,
            Event::Warning(w) => {
                warnings += 1;
                eprintln!("{file}: warning: {w}");
            }
        }
    }
    println!(
        "{file}: {} lines, {} bytes, {moves} moves, {warnings} warnings",
        reader.lines_read(),
        reader.bytes_read()
    );
    if !parse_only && file != "-" {
        let started = std::time::Instant::now();
        let report = preflight(
            file,
            &streamer,
            &planner,
            &std::sync::atomic::AtomicBool::new(false),
        )?;
        println!(
            "{file}: pre-flight passed: {}",
            describe(&report, started.elapsed())
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_screw_chunks_stay_inside_the_horizon_of_the_machine_that_runs() {
        let args = RosArgs {
            params: vec![ParamOverride {
                node: Some(mcu_bridge::node::NODE_NAME.to_string()),
                name: "horizon_s".to_string(),
                value_yaml: "0.8".to_string(),
            }],
            ..RosArgs::default()
        };
        let chunk = |on_mcu| {
            let (_, _, screw) = execution_overrides(&args, 1.0, on_mcu).unwrap();
            let chunk = screw
                .into_iter()
                .find(|p| p.name == "max_buffer_s")
                .unwrap();
            chunk.value_yaml
        };
        assert_eq!(chunk(true), "0.2");
        assert_eq!(chunk(false), "0.5"); // the executor's default 2 s
    }

    #[test]
    fn the_progress_clock_never_shows_sixty_seconds() {
        assert_eq!(clock(0.0), "0:00.0");
        assert_eq!(clock(-3.0), "0:00.0");
        assert_eq!(clock(7.26), "0:07.3");
        assert_eq!(clock(59.96), "1:00.0");
        assert_eq!(clock(119.97), "2:00.0");
        assert_eq!(clock(166.04), "2:46.0");
        assert_eq!(clock(3599.96), "1:00:00");
        assert_eq!(clock(3725.4), "1:02:05");
    }

    fn scoped(node: Option<&str>, name: &str) -> RosArgs {
        RosArgs {
            params: vec![ParamOverride {
                node: node.map(str::to_string),
                name: name.to_string(),
                value_yaml: "1".to_string(),
            }],
            ..RosArgs::default()
        }
    }

    fn check(args: &RosArgs) -> Result<(), String> {
        let planner = polar_planner::node::param_specs();
        let bridge = mcu_bridge::node::param_specs();
        check_params(
            args,
            &[
                (polar_planner::node::NODE_NAME, &planner),
                (mcu_bridge::node::NODE_NAME, &bridge),
            ],
        )
        .map_err(|e| e.to_string())
    }

    /// A machine that obeys the stop's commands as `obey` says, the status as it then is.
    async fn stopped_with(
        interrupts_during: u32,
        obey: impl Fn(&cell_machine::node::Command, &mut cell_machine::node::Status) + Send + 'static,
    ) -> ((bool, String), Vec<cell_machine::node::Command>) {
        use cell_machine::node::Status;
        let (commands, mut asked) =
            tokio::sync::mpsc::unbounded_channel::<cell_machine::node::Request>();
        let (status_tx, status) = tokio::sync::watch::channel(Status {
            state: Some(cell_executor::PlayerState::Running),
            current: Some((41, 120)),
            ..Status::default()
        });
        let (interrupts_tx, interrupts) = tokio::sync::watch::channel(0u32);
        let machine = tokio::spawn(async move {
            let mut seen = Vec::new();
            while let Some(request) = asked.recv().await {
                let command = request.command;
                if matches!(command, cell_machine::node::Command::Cancel) {
                    interrupts_tx.send_replace(interrupts_during);
                    tokio::task::yield_now().await;
                }
                status_tx.send_modify(|s| obey(&command, s));
                seen.push(command);
            }
            seen
        });
        let ended = stop_machine(&commands, &status, &ProgressBar::hidden(), &interrupts).await;
        drop(commands);
        (ended, machine.await.unwrap())
    }

    /// A controlled stop is reported as what it became: an emergency stop from `/cell/estop`
    /// or a fault meanwhile is not "cancelled: stopped on the path"; the job's own stop (a
    /// bag, a node) takes one interrupt as that stop and only a second as an emergency stop.
    #[tokio::test]
    async fn a_controlled_stop_says_how_it_really_ended() {
        use cell_executor::PlayerState;
        use cell_machine::node::Command;
        // /cell/estop while decelerating
        let (ended, seen) = stopped_with(0, |c, s| {
            if matches!(c, Command::Cancel) {
                s.state = Some(PlayerState::Stopped);
            }
        })
        .await;
        assert_eq!(
            ended,
            (true, "emergency stop (/cell/estop) while stopping at line 120 after 0:00.0 of machine time (bed 0.000000 rad, arm 0.000000 m, z 0.000000 m)".to_string())
        );
        assert!(matches!(seen[..], [Command::Cancel]));
        // a fault of the machine while decelerating
        let (ended, _) = stopped_with(0, |_, s| {
            s.state = Some(PlayerState::Stopped);
            s.fault = Some("late segment".into());
        })
        .await;
        assert!(
            ended.0
                && ended
                    .1
                    .starts_with("the machine stopped at once: late segment at line 120"),
            "{ended:?}"
        );
        // one interrupt (an action's cancel) during the job's own stop: no emergency stop
        let (ended, seen) = stopped_with(1, |c, s| {
            if matches!(c, Command::Cancel) {
                s.cancelled = true;
                s.state = Some(PlayerState::Idle);
            }
        })
        .await;
        assert!(
            !ended.0 && ended.1.starts_with("cancelled: stopped on the path"),
            "{ended:?}"
        );
        assert!(matches!(seen[..], [Command::Cancel]));
        // a second: an emergency stop
        let (ended, seen) = stopped_with(2, |c, s| {
            if matches!(c, Command::EmergencyStop) {
                s.state = Some(PlayerState::Stopped);
            }
        })
        .await;
        assert!(
            ended.0 && ended.1.starts_with("emergency stop at line 120"),
            "{ended:?}"
        );
        assert!(matches!(
            seen[..],
            [Command::Cancel, Command::EmergencyStop]
        ));
    }

    /// Only a character device that is not a pseudo-terminal keeps real time; an emulator's
    /// pty, socket or the built-in emulator may run at any speed.
    #[test]
    fn only_a_serial_port_is_held_to_speed_1() {
        assert!(is_serial_port("/dev/null"));
        assert!(!is_serial_port("emulator"));
        assert!(!is_serial_port("unix:/tmp/uart0.sock"));
        assert!(!is_serial_port("/dev/ptmx"));
        assert!(!is_serial_port("/no/such/device"));
        assert!(!is_serial_port(env!("CARGO_MANIFEST_DIR")));
        // SAFETY: a pseudo-terminal pair of this process; the name is copied out before
        // the master is closed.
        let name = unsafe {
            let master = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY);
            assert!(master >= 0 && libc::grantpt(master) == 0 && libc::unlockpt(master) == 0);
            let mut buf = [0 as libc::c_char; 128];
            assert_eq!(libc::ptsname_r(master, buf.as_mut_ptr(), buf.len()), 0);
            let name = std::ffi::CStr::from_ptr(buf.as_ptr())
                .to_str()
                .unwrap()
                .to_string();
            assert!(!is_serial_port(&name), "{name}");
            libc::close(master);
            name
        };
        assert!(name.starts_with("/dev/pts/"), "{name}");
    }

    #[test]
    fn parameters_reach_a_node_that_declares_them_or_are_refused() {
        assert_eq!(check(&scoped(None, "horizon_s")), Ok(()));
        assert_eq!(check(&scoped(Some("mcu_bridge"), "horizon_s")), Ok(()));
        assert_eq!(
            check(&scoped(None, "windw")),
            Err("-p windw:=1: no node of this process declares `windw`".to_string())
        );
        // A print on an MCU runs no virtual executor: its parameter would be lost.
        assert_eq!(
            check(&scoped(Some("cell_executor"), "service_mapping")),
            Err(
                "-p cell_executor:service_mapping:=1: this print runs no node \
                 `cell_executor` (its nodes: polar_planner, mcu_bridge)"
                    .to_string()
            )
        );
        assert_eq!(
            check(&scoped(Some("polar_planner"), "baud")),
            Err(
                "-p polar_planner:baud:=1: node `polar_planner` declares no parameter `baud`"
                    .to_string()
            )
        );
        // A renamed node is named as it runs (its parameters take only that name).
        let renamed = |node: &str| {
            let mut args = scoped(Some(node), "horizon_s");
            args.remaps = RosArgs::parse(&["--ros-args", "-r", "mcu_bridge:__node:=bridge2"])
                .unwrap()
                .0
                .remaps;
            check(&args)
        };
        assert_eq!(renamed("bridge2"), Ok(()));
        assert_eq!(
            renamed("mcu_bridge"),
            Err(
                "-p mcu_bridge:horizon_s:=1: this print runs no node `mcu_bridge` (its nodes: \
                 polar_planner, bridge2)"
                    .to_string()
            )
        );
    }
}
