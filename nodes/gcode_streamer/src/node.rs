//! The `gcode_streamer` node: reads a G-code file, publishes `/gcode/moves` under lossless flow
//! control and `/gcode/progress`, listens on `/gcode/ack`.
//!
//! Parsing runs on its own thread and hands moves over a bounded channel, so a slow consumer
//! back-pressures the parser (and memory stays bounded) through the send window.

use std::io::BufRead;
use std::sync::mpsc::{sync_channel, Receiver, TryRecvError};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _};
use cell_runtime::topics::publisher_qos;
use cell_runtime::{
    now_ns, publish, reliable_qos, CellNode, LogLevel, ParamSpec, ParamValue, Params, RosArgs,
    PUBLISH_PATIENCE,
};
use polar_cell_msgs::{DiagnosticStatus, GcodeAck, GcodeMove, GcodeProgress, Header, Time};

use crate::{Event, GcodeError, GcodeReader, InterpreterOptions};
use cell_runtime::flow::{AckOutcome, SendWindow, WindowOptions};
use cell_runtime::throttle::LogThrottle;

/// Default node name.
pub const NODE_NAME: &str = "gcode_streamer";

/// How many more times the finished `/gcode/progress` is published, 50 ms apart.
const FINAL_REPORT_REPEATS: usize = 4;

/// The node's parameters.
pub fn param_specs() -> Vec<ParamSpec> {
    vec![
        ParamSpec::new(
            "gcode_file",
            ParamValue::String(String::new()),
            "G-code file to stream (`-` for stdin)",
        ),
        ParamSpec::new(
            "window",
            ParamValue::Integer(4096),
            "moves in flight before waiting for acknowledgements (keep it above the planner's \
             lookahead_blocks: a smaller window starves the planner, which then plans to a stop \
             after each window)",
        )
        .range(1.0, 1e6),
        ParamSpec::new(
            "resend_after_s",
            ParamValue::Double(0.5),
            "resend from the oldest unacknowledged move after this long without progress",
        )
        .range(0.001, 3600.0),
        ParamSpec::new(
            "consumers",
            ParamValue::StringArray(vec!["/polar_planner".into()]),
            "fully qualified names of the nodes whose acknowledgements gate the stream",
        ),
        ParamSpec::new(
            "progress_period_s",
            ParamValue::Double(0.1),
            "period of /gcode/progress",
        )
        .range(0.001, 60.0),
        ParamSpec::new(
            "consumer_timeout_s",
            ParamValue::Double(30.0),
            "give up when a consumer has not announced itself after this long (0: wait forever)",
        )
        .range(0.0, 1e6),
        ParamSpec::new(
            "arc_tolerance_mm",
            ParamValue::Double(0.002),
            "largest distance between an arc and its chords",
        )
        .range(1e-6, 10.0),
        ParamSpec::new(
            "default_feedrate_mm_per_min",
            ParamValue::Double(1500.0),
            "feedrate before the file sets F",
        )
        .range(1e-3, 1e6),
        ParamSpec::new(
            "home_position_mm",
            ParamValue::DoubleArray(vec![0.0, 0.0, 0.0]),
            "machine position G28 homes to (x, y, z)",
        ),
        ParamSpec::new(
            "start_position_mm",
            ParamValue::DoubleArray(vec![0.0, 0.0, 0.0]),
            "where the tool stands before the first line (x, y, z): axes a first move leaves out stay there, relative moves count from there",
        ),
    ]
}

/// What a finished stream reports.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamSummary {
    pub moves: u64,
    pub lines: u32,
    pub bytes: u64,
    pub warnings: u32,
    pub resends: u64,
    pub elapsed: Duration,
}

/// Interpreter options from the node's parameters.
pub fn interpreter_options(params: &Params) -> anyhow::Result<InterpreterOptions> {
    let home = params.f64s("home_position_mm");
    if home.len() != 3 {
        bail!(
            "parameter home_position_mm needs 3 values (x, y, z), got {}",
            home.len()
        );
    }
    let start = params.finite3("start_position_mm", "x, y, z")?;
    Ok(InterpreterOptions {
        arc_tolerance_mm: params.f64("arc_tolerance_mm"),
        default_feedrate_mm_per_min: params.f64("default_feedrate_mm_per_min"),
        home_position_mm: [home[0], home[1], home[2]],
        start_position_mm: start,
        ..InterpreterOptions::default()
    })
}

enum Parsed {
    /// An event and how far the reader got (lines, bytes).
    Event(Event, u32, u64),
    Error(GcodeError),
    Done {
        lines: u32,
        bytes: u64,
    },
}

fn spawn_parser(
    input: Box<dyn BufRead + Send>,
    file_label: String,
    options: InterpreterOptions,
) -> Receiver<Parsed> {
    let (tx, rx) = sync_channel(8192);
    std::thread::Builder::new()
        .name("gcode parser".into())
        .spawn(move || {
            let mut reader = GcodeReader::new(input, file_label, options);
            while let Some(item) = reader.next() {
                let message = match item {
                    Ok(event) => Parsed::Event(event, reader.lines_read(), reader.bytes_read()),
                    Err(e) => Parsed::Error(e),
                };
                let stop = matches!(message, Parsed::Error(_));
                if tx.send(message).is_err() || stop {
                    return;
                }
            }
            let _ = tx.send(Parsed::Done {
                lines: reader.lines_read(),
                bytes: reader.bytes_read(),
            });
        })
        .expect("spawning a thread");
    rx
}

/// Stream `input` (labelled `file_label`, `bytes_total` long if known) until every move is
/// acknowledged by every consumer. `on_progress` sees each progress report (for a UI).
pub async fn stream(
    node: &mut CellNode,
    input: Box<dyn BufRead + Send>,
    file_label: &str,
    bytes_total: u64,
    mut on_progress: impl FnMut(&GcodeProgress),
) -> anyhow::Result<StreamSummary> {
    let params = node.params.clone();
    let window_size = params.i64("window") as usize;
    let options = WindowOptions {
        window: window_size,
        resend_after: Duration::from_secs_f64(params.f64("resend_after_s")),
    };
    let consumers = params.strings("consumers").to_vec();
    let progress_period = Duration::from_secs_f64(params.f64("progress_period_s"));
    let consumer_timeout = params.f64("consumer_timeout_s");
    let moves_pub =
        Arc::new(node.publisher::<GcodeMove>("/gcode/moves", &reliable_qos(window_size.max(10)))?);
    let progress_pub = Arc::new(
        node.publisher::<GcodeProgress>("/gcode/progress", &publisher_qos("/gcode/progress"))?,
    );
    // The writers outlive the stream with the node: a last progress lost on the way to a
    // reader is repaired only while its writer exists (a caller that keeps the node, as
    // `print` does until its bag is closed, lets every reader have it).
    node.keep(moves_pub.clone());
    node.keep(progress_pub.clone());
    let acks = node.subscription::<GcodeAck>("/gcode/ack", &reliable_qos(1000))?;
    let parsed = spawn_parser(input, file_label.to_string(), interpreter_options(&params)?);
    let mut window = SendWindow::new(options, &consumers);
    let start = Instant::now();
    let mut progress = GcodeProgress {
        file: file_label.to_string(),
        bytes_total,
        ..Default::default()
    };
    let mut eof = false;
    // A move taken from the parser while the window had no room for it.
    let mut held: Option<Parsed> = None;
    let mut last_progress = Instant::now() - progress_period;
    let mut consumers_announced = consumers.is_empty();
    // A consumer that (re)announces itself needs its resume point from /gcode/progress now.
    let mut progress_due = false;
    let mut ack_checks = AckChecks::new();
    let mut undecodable = cell_runtime::Undecodable::default();
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "streaming {file_label} to {consumers:?} (window {window_size})"
    );
    loop {
        let now = start.elapsed();
        // Acknowledgements.
        loop {
            match undecodable.take(node, "/gcode/ack", acks.take())? {
                Some(Some((ack, info))) => {
                    progress_due |= apply_ack(node, &mut window, &mut ack_checks, &ack, &info, now);
                }
                Some(None) => break,
                None => {} // counted; the next one may be good
            }
        }
        // Parser output into the window. With the window full, one move is taken ahead and
        // held: the end of the file is then known as soon as the parser reaches it, and a
        // held move tells the consumers that more waits for their acknowledgements.
        while !eof {
            let next = match held.take() {
                Some(next) => next,
                None => match parsed.try_recv() {
                    Ok(next) => next,
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => {
                        bail!("G-code parser stopped unexpectedly")
                    }
                },
            };
            if !window.has_room() && matches!(next, Parsed::Event(Event::Move(_), ..)) {
                held = Some(next);
                break;
            }
            match next {
                Parsed::Event(event, lines, bytes) => {
                    progress.lines_read = lines;
                    progress.bytes_read = bytes;
                    match event {
                        Event::Move(m) => window.push(m),
                        Event::Warning(w) => {
                            progress.warnings += 1;
                            cell_runtime::cell_log!(node, LogLevel::Warn, "{file_label}: {w}");
                        }
                    }
                }
                Parsed::Error(e) => {
                    node.diagnose(DiagnosticStatus::ERROR, &e.to_string(), &[]);
                    return Err(e.into());
                }
                Parsed::Done { lines, bytes } => {
                    progress.lines_read = lines;
                    progress.bytes_read = bytes;
                    eof = true;
                }
            }
        }
        if progress.moves_waiting != held.is_some() {
            progress.moves_waiting = held.is_some();
            progress_due = true;
        }
        // Publish what the window allows.
        let mut sent_any = false;
        while let Some(m) = window.peek_next() {
            match moves_pub.publish(m.clone()) {
                Ok(()) => {
                    window.mark_sent();
                    sent_any = true;
                }
                Err(_) => break, // the DDS send window is full: come back after acks
            }
            if !consumers_announced {
                consumers_announced = true;
                cell_runtime::cell_log!(node, LogLevel::Info, "every consumer announced itself");
            }
        }
        progress.moves_published = progress
            .moves_published
            .max(window.acknowledged() + window.in_flight());
        window.on_tick(start.elapsed());
        // Every move of the file published once: consumers that have them all know their
        // input is complete (a screw driver then computes its last chunk).
        if eof && window.all_sent() && !progress.end_of_file {
            progress.end_of_file = true;
            progress_due = true;
        }
        let finished = eof && window.is_drained();
        if progress_due || finished || last_progress.elapsed() >= progress_period {
            progress_due = false;
            last_progress = Instant::now();
            progress.header = Header {
                stamp: Time::from_nanos(now_ns() as i64),
                frame_id: String::new(),
            };
            progress.moves_acknowledged = window.acknowledged();
            let (names, next) = window.consumer_acks();
            progress.consumers = names;
            progress.consumer_next_expected = next;
            (
                progress.consumer_resume_states,
                progress.consumer_resume_state_ends,
            ) = window.consumer_resume_states();
            progress.finished = finished;
            on_progress(&progress);
            publish(&progress_pub, progress.clone(), PUBLISH_PATIENCE)
                .await
                .context("/gcode/progress")?;
        }
        if finished {
            // The final report is repeated: a subscriber that lost one still gets it (a
            // reliable writer does not always repair a loss in a burst).
            for _ in 0..FINAL_REPORT_REPEATS {
                tokio::time::sleep(Duration::from_millis(50)).await;
                publish(&progress_pub, progress.clone(), PUBLISH_PATIENCE)
                    .await
                    .context("/gcode/progress")?;
            }
            let summary = StreamSummary {
                moves: window.acknowledged(),
                lines: progress.lines_read,
                bytes: progress.bytes_read,
                warnings: progress.warnings,
                resends: window.resends(),
                elapsed: start.elapsed(),
            };
            node.diagnose(
                DiagnosticStatus::OK,
                "stream finished",
                &[
                    ("moves", summary.moves.to_string()),
                    ("warnings", summary.warnings.to_string()),
                    ("resends", summary.resends.to_string()),
                    // Acknowledgements from writers not of the consumer they name, and of
                    // moves never sent: ignored (a forger, or a consumer still unannounced).
                    ("acks_ignored_foreign", ack_checks.foreign_count.to_string()),
                    (
                        "acks_ignored_impossible",
                        ack_checks.impossible_count.to_string(),
                    ),
                ],
            );
            return Ok(summary);
        }
        if !consumers_announced
            && consumer_timeout > 0.0
            && start.elapsed().as_secs_f64() > consumer_timeout
        {
            bail!(
                "no announcement from consumer(s) {:?} within {consumer_timeout} s",
                window.missing_consumers()
            );
        }
        if !sent_any {
            // Nothing to do until an acknowledgement arrives (or the parser catches up: with
            // room in the window, look again soon; a full window waits for acknowledgements,
            // which wake this at once, and looks again only for the resend timer and the
            // progress report).
            let patience = if window.has_room() && !eof {
                Duration::from_millis(2)
            } else {
                cell_runtime::flow::LOOK_PERIOD
            };
            let wait = tokio::time::timeout(patience, acks.async_take()).await;
            if let Ok(taken) = wait {
                if let Some((ack, info)) = undecodable.take(node, "/gcode/ack", taken)? {
                    let now = start.elapsed();
                    progress_due |= apply_ack(node, &mut window, &mut ack_checks, &ack, &info, now);
                }
            }
        } else {
            tokio::task::yield_now().await;
        }
    }
}

/// What the streamer checks an acknowledgement by, and how often it says so.
struct AckChecks {
    sources: cell_runtime::graph::Sources,
    /// Acknowledgements from a writer not (yet) known as the consumer's: logged only once
    /// that lasts 2 s (a consumer's first ones may come before its announcement).
    foreign: LogThrottle<cell_runtime::Gid>,
    impossible: LogThrottle<cell_runtime::Gid>,
    /// Acknowledgements ignored as not from their consumer, and as impossible.
    foreign_count: u64,
    impossible_count: u64,
}

impl AckChecks {
    fn new() -> AckChecks {
        AckChecks {
            sources: cell_runtime::graph::Sources::new(),
            foreign: LogThrottle::with_grace(Duration::from_secs(1), Duration::from_secs(2)),
            impossible: LogThrottle::new(Duration::from_secs(1)),
            foreign_count: 0,
            impossible_count: 0,
        }
    }
}

/// Apply an acknowledgement to the window; `true` when it announces a consumer (which needs
/// its resume point from /gcode/progress now). One of moves never sent is not applied (a
/// forged or corrupted one would end the stream "finished"): say so, naming its sender, at
/// most once a second per sender (a sender repeating it must not flood /rosout).
fn apply_ack(
    node: &CellNode,
    window: &mut SendWindow<GcodeMove>,
    checks: &mut AckChecks,
    ack: &GcodeAck,
    info: &cell_runtime::MessageInfo,
    now: Duration,
) -> bool {
    let sender = info.publisher_gid();
    // Only the consumer itself may acknowledge for it (see cell_runtime::graph): anyone else
    // on the domain could otherwise make the streamer drop moves the consumer never had.
    if !checks
        .sources
        .admits(&ack.consumer, sender, now, || node.node.external_nodes())
    {
        checks.foreign_count += 1;
        if let Some(held_back) = checks.foreign.admit(sender, now) {
            let speaker =
                match cell_runtime::graph::nodes_of_writer(&node.node.external_nodes(), &sender) {
                    nodes if nodes.is_empty() => "not a ROS node".to_string(),
                    nodes => format!("a writer of {}", nodes.join(", ")),
                };
            cell_runtime::cell_log!(
                node,
                LogLevel::Warn,
                "ignored /gcode/ack in the name of {} from publisher {sender:?} ({speaker}): \
                 it is not a writer of {} in ros_discovery_info{}",
                ack.consumer,
                ack.consumer,
                match held_back {
                    0 => String::new(),
                    n => format!(" ({n} more from it since the last report)"),
                }
            );
        }
        return false;
    }
    let impossible_acks = &mut checks.impossible;
    if let AckOutcome::Impossible {
        next_expected,
        sent,
    } = window.on_ack_from(
        &ack.into(),
        cell_runtime::graph::process_of(&info.publisher_gid()),
        now,
    ) {
        checks.impossible_count += 1;
        let sender = info.publisher_gid();
        if let Some(held_back) = impossible_acks.admit(sender, now) {
            let more = match held_back {
                0 => String::new(),
                n => format!(" ({n} more from it since the last report)"),
            };
            cell_runtime::cell_log!(
                node,
                LogLevel::Error,
                "ignored an impossible /gcode/ack from publisher {sender:?} in the name of {}: \
                 next expected {next_expected}, but only {sent} moves were sent{more}",
                ack.consumer
            );
        }
    }
    ack.resume
}

/// Parse the node's own command line and run it to completion or shutdown.
pub async fn main_with_args(argv: Vec<String>) -> anyhow::Result<()> {
    let (ros_args, rest) = RosArgs::parse(&argv)?;
    let mut node = CellNode::start(NODE_NAME, &param_specs(), &ros_args)?;
    let path = match rest.as_slice() {
        [] => node.params.string("gcode_file").to_string(),
        [one] => one.clone(),
        more => bail!("expected one G-code file, got {more:?}"),
    };
    if path.is_empty() {
        bail!("no G-code file: give a path or -p gcode_file:=PATH (`-` for stdin)");
    }
    let (input, total): (Box<dyn BufRead + Send>, u64) = if path == "-" {
        (Box::new(std::io::BufReader::new(std::io::stdin())), 0)
    } else {
        let file = std::fs::File::open(&path).with_context(|| format!("opening {path}"))?;
        let total = file.metadata().map(|m| m.len()).unwrap_or(0);
        (
            Box::new(std::io::BufReader::with_capacity(1 << 16, file)),
            total,
        )
    };
    tokio::select! {
        result = stream(&mut node, input, &path, total, |_| {}) => {
            let s = result?;
            eprintln!(
                "{path}: {} moves from {} lines in {:.2} s ({} warnings, {} resends)",
                s.moves, s.lines, s.elapsed.as_secs_f64(), s.warnings, s.resends
            );
            Ok(())
        }
        _ = cell_runtime::shutdown_signal() => {
            eprintln!("interrupted");
            Ok(())
        }
    }
}
