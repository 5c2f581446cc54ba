//! `polar-cell print`: every node of the cell in one process, each its own DDS participant,
//! talking over loopback DDS (so `ros2 topic echo` on the same domain sees everything).

use std::io::BufRead;
use std::path::Path;
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
) -> anyhow::Result<StreamSummary> {
    match finished {
        Ok((_, Err(e))) => Err(e.context(name.to_string())),
        Ok((_, Ok(()))) => Err(anyhow::anyhow!("{name} stopped")),
        Err(e) => Err(anyhow::anyhow!("{name} task: {e}")),
    }
}

/// Every global `-p` must be declared by at least one node (unknown parameters are errors).
fn check_global_params(ros_args: &RosArgs, all_specs: &[&[ParamSpec]]) -> anyhow::Result<()> {
    for p in ros_args.params.iter().filter(|p| p.node.is_none()) {
        if !all_specs
            .iter()
            .any(|specs| specs.iter().any(|s| s.name == p.name))
        {
            bail!(
                "-p {}:={}: no node of this process declares `{}`",
                p.name,
                p.value_yaml,
                p.name
            );
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

pub async fn print(
    file: &str,
    bag: &Path,
    bag_dir: bool,
    show_progress: bool,
    run_preflight: bool,
    ros_args: &RosArgs,
) -> anyhow::Result<()> {
    let recorder_specs = cell_bag::node::param_specs();
    let streamer_specs = gcode_streamer::node::param_specs();
    let planner_specs = polar_planner::node::param_specs();
    let screw_specs = screw_driver::node::param_specs();
    check_global_params(
        ros_args,
        &[
            &recorder_specs,
            &streamer_specs,
            &planner_specs,
            &screw_specs,
        ],
    )?;
    // The nodes of one process share its command line: an unprefixed node rename would give
    // them all one name (and the print would wait for consumers that never appear).
    if let Some(rename) = ros_args
        .remaps
        .iter()
        .find(|r| r.node.is_none() && r.from == "__node")
    {
        bail!(
            "-r __node:={0} would give every node of this print the name {0:?}; rename one \
             with -r NODE:__node:={0} (NODE: {1}, {2}, {3} or {4})",
            rename.to,
            gcode_streamer::node::NODE_NAME,
            polar_planner::node::NODE_NAME,
            screw_driver::node::NODE_NAME,
            cell_bag::node::NODE_NAME,
        );
    }
    // Before any node starts (no DDS, no bag): the whole file with the parameters the nodes
    // will get.
    if run_preflight && file != "-" {
        let (streamer, planner) = preflight_params(ros_args)?;
        let started = std::time::Instant::now();
        let report = preflight(file, &streamer, &planner)?;
        eprintln!(
            "{file}: pre-flight passed: {}",
            describe(&report, started.elapsed())
        );
    }
    let (input, total) = open_input(file)?;

    let recorder_node = start_node(
        cell_bag::node::NODE_NAME,
        &recorder_specs,
        ros_args,
        vec![
            param("output", format!("{:?}", bag.display().to_string())),
            param("bag_directory", bag_dir.to_string()),
        ],
    )?;
    let recorder = Recorder::start(recorder_node)?;
    let mut screw_node = start_node(
        screw_driver::node::NODE_NAME,
        &screw_specs,
        ros_args,
        vec![],
    )?;
    let mut planner_node = start_node(
        polar_planner::node::NODE_NAME,
        &planner_specs,
        ros_args,
        planner_overrides(&screw_node.params),
    )?;
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
        vec![param("consumers", consumers)],
    )?;
    let mut screw = tokio::spawn(async move {
        let result = screw_driver::node::run(&mut screw_node).await;
        (screw_node, result)
    });
    let mut planner = tokio::spawn(async move {
        let result = polar_planner::node::run(&mut planner_node).await;
        (planner_node, result)
    });

    let bar = if show_progress {
        let bar = ProgressBar::new(total.max(1));
        bar.set_style(
            ProgressStyle::with_template("{spinner} {bar:40} {percent:>3}% {msg}")
                .expect("static template"),
        );
        bar
    } else {
        ProgressBar::hidden()
    };
    let outcome = tokio::select! {
        finished = &mut planner => Some(stopped(polar_planner::node::NODE_NAME, finished)),
        finished = &mut screw => Some(stopped(screw_driver::node::NODE_NAME, finished)),
        r = gcode_streamer::node::stream(&mut streamer, input, file, total, |p| {
            bar.set_position(p.bytes_read);
            bar.set_message(format!(
                "line {} · {} moves sent · {} acknowledged",
                p.lines_read, p.moves_published, p.moves_acknowledged
            ));
        }) => Some(r),
        _ = cell_runtime::shutdown_signal() => None,
    };
    bar.finish_and_clear();
    if matches!(outcome, Some(Ok(_))) {
        if !recorder.wait_stream_finished(Duration::from_secs(10)).await {
            eprintln!("warning: the bag did not receive the final /gcode/progress within 10 s");
        }
        // The planner and screw driver flush what they buffered once input stops, and the
        // streamer's closing diagnostics follow its final progress: record until all is quiet.
        let quiet = Duration::from_millis(500);
        if !recorder.wait_quiet(quiet, Duration::from_secs(60)).await {
            eprintln!("warning: messages were still arriving 60 s after the stream finished");
        }
    }
    planner.abort();
    screw.abort();
    let recorded = recorder.stop().await.context("finishing the bag")?;
    match outcome {
        None => {
            print_summary(&recorded);
            bail!("interrupted before the end of {file}; the bag was finished")
        }
        Some(Err(e)) => {
            print_summary(&recorded);
            Err(e)
        }
        Some(Ok(s)) => {
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
            print_summary(&recorded);
            Ok(())
        }
    }
}

/// The streamer's and the planner's parameters exactly as `print` gives them to its nodes
/// (global `-p` only where a node declares it, the planner told of the screw), without DDS.
fn preflight_params(
    ros_args: &RosArgs,
) -> anyhow::Result<(cell_runtime::Params, cell_runtime::Params)> {
    let resolve = |name: &str, specs: &[ParamSpec], ours| {
        cell_runtime::resolve_node(name, specs, &args_for(ros_args, name, specs, ours))
            .map(|(_, params)| params)
    };
    let screw = resolve(
        screw_driver::node::NODE_NAME,
        &screw_driver::node::param_specs(),
        vec![],
    )?;
    let planner = resolve(
        polar_planner::node::NODE_NAME,
        &polar_planner::node::param_specs(),
        planner_overrides(&screw),
    )?;
    let streamer = resolve(
        gcode_streamer::node::NODE_NAME,
        &gcode_streamer::node::param_specs(),
        vec![],
    )?;
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
) -> anyhow::Result<polar_planner::PreflightReport> {
    let (options, steps) = polar_planner::node::options_from_params(planner)?;
    let interpreter = gcode_streamer::node::interpreter_options(streamer)?;
    let (input, _) = open_input(file)?;
    let mut reader = GcodeReader::new(input, file, interpreter);
    let mut check = polar_planner::Preflight::new(options, steps)?;
    for event in reader.by_ref() {
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
    let t = report.plan_time_s;
    format!(
        "{} moves, {:.0}:{:02.0}:{:04.1} of machine time, {} step segments; checked in {:.2} s",
        report.moves,
        (t / 3600.0).floor(),
        (t % 3600.0 / 60.0).floor(),
        t % 60.0,
        report.segments,
        took.as_secs_f64()
    )
}

/// `polar-cell check FILE`: the parser, then (unless `parse_only`) the pre-flight with the
/// parameters the print's nodes would get from the same ROS arguments.
pub fn check(file: &str, parse_only: bool, ros_args: &RosArgs) -> anyhow::Result<()> {
    let (input, _) = open_input(file)?;
    let (streamer, planner) = preflight_params(ros_args)?;
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
        let report = preflight(file, &streamer, &planner)?;
        println!(
            "{file}: pre-flight passed: {}",
            describe(&report, started.elapsed())
        );
    }
    Ok(())
}
