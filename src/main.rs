//! `polar-cell`: run the printing cell's nodes, and inspect or replay its bags.
//!
//! Everything after `--ros-args` is the ROS command line (`-p`, `--params-file`, `-r`), applied
//! to every node this process starts; a global `-p name:=value` goes to the nodes that declare
//! `name`, a node-prefixed one (`-p gcode_streamer:window:=64`) to that node only.

mod bag_cmd;
mod demo;
mod mechanism_cmd;
mod plot_cmd;
mod print_cmd;
mod screw_cmd;
mod serve_cmd;

use std::ops::RangeInclusive;
use std::path::PathBuf;

use anyhow::bail;
use cell_runtime::RosArgs;
use clap::{Parser, Subcommand};

#[derive(Parser, Debug)]
#[command(
    name = "polar-cell",
    version,
    about = "The polar printing cell: print, record, replay."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// The hybrid machining head (3-RPS + XY table): ik, fk, cl, urdf, calibrate, simulate.
    Mechanism {
        #[command(subcommand)]
        command: mechanism_cmd::MechanismCommand,
    },
    /// Print a G-code file through the cell's nodes over DDS, recording every topic.
    Print {
        /// The G-code file (`-` for stdin; none: the built-in demo, a spiral vase and a star
        /// through the bed's centre).
        file: Option<String>,
        /// Where to record the bag (a bare MCAP file, or a directory with --bag-dir).
        #[arg(long, default_value = "print.mcap")]
        bag: PathBuf,
        /// Write a rosbag2 directory (MCAP + metadata.yaml) instead of a bare file.
        #[arg(long)]
        bag_dir: bool,
        /// No progress bar (for logs and CI).
        #[arg(long)]
        no_progress: bool,
        /// Skip the pre-flight (planning the whole file before anything moves).
        #[arg(long)]
        no_preflight: bool,
        /// Machine seconds per wall second: a K× faster simulation of the same timeline.
        #[arg(long, default_value_t = 1.0, value_parser = parse_speed)]
        speed: f64,
        /// Plan as fast as the CPU allows, with no executor (tests, benchmarks): the bag has
        /// the plan, not its execution.
        #[arg(long, conflicts_with = "speed")]
        dry_run: bool,
        /// Print on a microcontroller instead of the virtual executor: its serial line (a
        /// tty such as /dev/ttyACM0, a pseudo-terminal's path, unix:/path), or `emulator` to
        /// start mcu_emulator on a pseudo-terminal at the same --speed.
        #[arg(long, conflicts_with = "dry_run")]
        device: Option<String>,
        /// Where the machine stands: BED_RAD,ARM_M,Z_M (default home, 0,0,0). The plan's first
        /// move starts there; a microcontroller standing elsewhere is refused.
        #[arg(long, value_parser = parse_joints, allow_hyphen_values = true)]
        start_joints: Option<[f64; 3]>,
    },
    /// Serve the ROS 2 action /print (polar_cell_msgs/action/Print): each goal prints its file
    /// through the node graph at machine pace, recorded to a bag.
    Serve {
        /// Machine seconds per wall second, for goals that give 0.
        #[arg(long, default_value_t = 1.0, value_parser = parse_speed)]
        speed: f64,
        /// Where each goal's bag goes (print-N.mcap).
        #[arg(long, default_value = ".")]
        bag_dir: PathBuf,
        /// Request/reply format of the action's services: cyclone (rmw_cyclonedds clients),
        /// enhanced (rmw_fastrtps) or basic.
        #[arg(long, default_value = "cyclone")]
        service_mapping: String,
        /// Print on a microcontroller (as for print).
        #[arg(long)]
        device: Option<String>,
        /// Seconds a finished goal stays in the status list and its result can be asked for
        /// (rcl's result_timeout; Humble's default, 15 min).
        #[arg(long, default_value_t = 900.0, value_parser = parse_nonnegative_s)]
        result_timeout_s: f64,
    },
    /// Check a G-code file without DDS: parse it (counts, warnings, the first error), then
    /// plan it whole as a print would (pre-flight: reach, limits, steps).
    Check {
        file: String,
        /// Parse only.
        #[arg(long)]
        parse_only: bool,
        /// Plan from this position (BED_RAD,ARM_M,Z_M), as `print --start-joints`.
        #[arg(long, value_parser = parse_joints, allow_hyphen_values = true)]
        start_joints: Option<[f64; 3]>,
    },
    /// Ask a microcontroller where it stands (a short session of its own, as `print --device`
    /// does first) and print, one per line, the parameters that start a plan there:
    /// `initial_joints:=[…]` (the planner and the machine) and `start_position_mm:=[…]` (the
    /// streamer). For graphs started node by node: `launch-scripts/cell.sh` uses it, and
    /// `ros2 launch launch-scripts/cell_mcu.launch.xml … $(polar-cell mcu-position --device
    /// DEV)` takes them as launch arguments.
    McuPosition {
        /// The MCU's serial line: a tty such as /dev/ttyACM0, a pseudo-terminal's path, or
        /// unix:/path. The bridge's parameters (`baud`, steps per unit, …) come from
        /// `--ros-args`.
        #[arg(long)]
        device: String,
    },
    /// Plot r, θ, tool speed and screw rpm against time from a recorded print.
    Plot {
        /// The bag (file or directory).
        bag: PathBuf,
        /// The PNG to write.
        #[arg(long, default_value = "print.png")]
        out: PathBuf,
    },
    /// The screw's flow response: Navier–Stokes channel, step responses, reduced models.
    Screw {
        #[command(subcommand)]
        command: screw_cmd::ScrewCommand,
    },
    /// Bag tools.
    Bag {
        #[command(subcommand)]
        command: BagCommand,
    },
}

#[derive(Subcommand, Debug)]
enum BagCommand {
    /// Topics, types, message counts and duration of a bag (file or directory).
    Info { bag: PathBuf },
    /// Salvage a bag whose recorder was killed: every message of every complete chunk and
    /// what is intact of the last, into a new, finished bag.
    Recover {
        /// The unfinished bag (file, or rosbag2 directory).
        input: PathBuf,
        /// The new bag (an MCAP file).
        output: PathBuf,
    },
    /// Republish a bag's messages over DDS with their original timing.
    Play {
        bag: PathBuf,
        /// Speed factor on the original timing.
        #[arg(long, default_value_t = 1.0, value_parser = parse_rate)]
        rate: f64,
        /// As fast as possible (ignores --rate).
        #[arg(long)]
        fast: bool,
        /// Only these topics (default: all).
        #[arg(long, value_delimiter = ',')]
        topics: Vec<String>,
        /// Wait up to this many seconds for every topic to have a subscriber before playing.
        #[arg(long, default_value_t = 0.0, value_parser = parse_nonnegative_s)]
        wait_subscribers_s: f64,
        /// Before playing, wait (up to --wait-subscribers-s) until every topic played has a
        /// subscription of this node (fully qualified, e.g. /screw_driver; repeatable): any
        /// other subscriber, a viewer left over say, does not count.
        #[arg(long = "wait-for-node")]
        wait_for_nodes: Vec<String>,
        /// At the end, wait up to this many seconds for every subscriber to acknowledge the
        /// last messages (a lost one is repaired only while the player runs).
        #[arg(long, default_value_t = 10.0, value_parser = parse_nonnegative_s)]
        deliver_timeout_s: f64,
    },
}

fn split_ros_args() -> anyhow::Result<(Vec<String>, RosArgs)> {
    let argv: Vec<String> = std::env::args().collect();
    match argv.iter().position(|a| a == "--ros-args") {
        Some(i) => {
            let (ros, rest) = RosArgs::parse(&argv[i..])?;
            if !rest.is_empty() {
                bail!("unexpected arguments after --ros-args ... --: {rest:?}");
            }
            Ok((argv[..i].to_vec(), ros))
        }
        None => Ok((argv, RosArgs::default())),
    }
}

/// The bag reader turns a panic of the `mcap` crate on a malformed file into an error that
/// says what happened (`cell_bag::BagError::Malformed`); the default hook would also print
/// the panic. Every other panic is printed as usual.
fn quiet_mcap_panics() {
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let in_mcap = info.location().is_some_and(|l| l.file().contains("/mcap-"));
        if !in_mcap {
            default_hook(info);
        }
    }));
}

/// Output piped into a reader that stops early (`polar-cell bag info X | head`) ends the
/// process quietly, as it does any Unix tool, instead of panicking on the failed write: Rust
/// ignores SIGPIPE by default. DDS uses UDP, which never raises it.
fn default_sigpipe() {
    // SAFETY: `signal` with SIG_DFL has no memory-safety preconditions; it is set before any
    // output is written.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// A number within `range`, or what it is not (`what`) for clap's message.
fn parse_within(text: &str, range: RangeInclusive<f64>, what: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(x) if range.contains(&x) => Ok(x),
        _ => Err(format!("`{text}` is not {what}")),
    }
}

fn parse_speed(text: &str) -> Result<f64, String> {
    parse_within(
        text,
        cell_machine::node::SPEED_RANGE,
        "a speed factor in [0.01, 1000]",
    )
}

/// A replay's speed factor on the recorded timing.
fn parse_rate(text: &str) -> Result<f64, String> {
    parse_within(text, bag_cmd::RATE_RANGE, "a rate in [0.001, 1e6]")
}

/// A duration in seconds, 0 or more (at most a year: `Duration` takes it).
pub(crate) const SECONDS_RANGE: RangeInclusive<f64> = 0.0..=3.2e7;

fn parse_nonnegative_s(text: &str) -> Result<f64, String> {
    parse_within(text, SECONDS_RANGE, "a number of seconds in [0, 3.2e7]")
}

/// `BED_RAD,ARM_M,Z_M`: a joint position (its limits are the planner's to check).
fn parse_joints(text: &str) -> Result<[f64; 3], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{text}`: {e}"))?;
    match values[..] {
        [bed, arm, z] if values.iter().all(|v| v.is_finite()) => Ok([bed, arm, z]),
        _ => Err(format!(
            "`{text}` is not three finite numbers BED_RAD,ARM_M,Z_M"
        )),
    }
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    default_sigpipe();
    cell_runtime::init_logging("warn,polar_cell=info");
    quiet_mcap_panics();
    let (argv, ros_args) = split_ros_args()?;
    let cli = Cli::parse_from(argv);
    match cli.command {
        Command::Print {
            file,
            bag,
            bag_dir,
            no_progress,
            no_preflight,
            speed,
            dry_run,
            device,
            start_joints,
        } => {
            let options = print_cmd::PrintOptions {
                start_joints,
                bag,
                bag_dir,
                show_progress: !no_progress,
                run_preflight: !no_preflight,
                execution: (!dry_run).then_some(speed),
                device,
            };
            match file {
                Some(file) => print_cmd::print(&file, &options, &ros_args).await,
                None => {
                    let dir = std::env::temp_dir()
                        .join(format!("polar-cell-demo-{}", std::process::id()));
                    std::fs::create_dir_all(&dir)?;
                    let path = dir.join(demo::DEMO_NAME);
                    std::fs::write(&path, demo::demo_gcode())?;
                    let result =
                        print_cmd::print(&path.display().to_string(), &options, &ros_args).await;
                    let _ = std::fs::remove_dir_all(&dir);
                    result
                }
            }
        }
        Command::Serve {
            speed,
            bag_dir,
            service_mapping,
            device,
            result_timeout_s,
        } => {
            let options = serve_cmd::ServeOptions {
                device,
                result_timeout: std::time::Duration::from_secs_f64(result_timeout_s),
                speed,
                bag_dir,
                mapping: cell_runtime::parse_service_mapping(&service_mapping)?,
            };
            serve_cmd::serve(options, &ros_args).await
        }
        Command::Check {
            file,
            parse_only,
            start_joints,
        } => print_cmd::check(&file, parse_only, start_joints, &ros_args),
        Command::McuPosition { device } => {
            let joints =
                tokio::task::spawn_blocking(move || print_cmd::mcu_position(&device, &ros_args))
                    .await??;
            println!(
                "initial_joints:={}",
                print_cmd::initial_joints_value(joints)
            );
            println!(
                "start_position_mm:={}",
                print_cmd::start_position_value(joints)
            );
            Ok(())
        }
        Command::Plot { bag, out } => plot_cmd::plot(&bag, &out),
        Command::Mechanism { command } => mechanism_cmd::run(command),
        Command::Screw { command } => screw_cmd::run(command),
        Command::Bag { command } => match command {
            BagCommand::Info { bag } => bag_cmd::info(&bag),
            BagCommand::Recover { input, output } => bag_cmd::recover(&input, &output),
            BagCommand::Play {
                bag,
                rate,
                fast,
                topics,
                wait_subscribers_s,
                wait_for_nodes,
                deliver_timeout_s,
            } => {
                let options = bag_cmd::PlayOptions {
                    rate,
                    fast,
                    only_topics: topics,
                    wait_subscribers_s,
                    wait_for_nodes,
                    deliver_timeout_s,
                };
                bag_cmd::play(&bag, &options, &ros_args).await
            }
        },
    }
}
