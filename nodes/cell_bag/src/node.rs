//! The `bag_recorder` node: subscribes to a list of topics and writes a rosbag2 MCAP bag.
//!
//! Each topic gets a typed subscription (so the recorder shows up in the ROS graph with its
//! readers, like `ros2 bag record`), and re-encodes what it takes to CDR: our types mirror the
//! `.msg` files field by field, so the bytes are those on the wire. On `/gcode/moves` the
//! recorder is also a flow-control consumer: it acknowledges only what it has written, so the
//! bag holds every move exactly once and in order.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Context as _};
use cell_runtime::flow::{AckTracker, Verdict};

use crate::credit::PlanEnd;
use crate::gaps::SequenceGaps;
use crate::repeats::Repeats;
use cell_runtime::replay::Admit;
use cell_runtime::topics::{publisher_qos, DEFAULT_MOVE_WINDOW};
use cell_runtime::{
    now_ns, reliable_qos, transient_local_qos, CellNode, LogLevel, ParamSpec, ParamValue,
};
use polar_cell_msgs::{
    cdr, Clock, DiagnosticArray, GcodeAck, GcodeMove, GcodeProgress, JointState, JointTrajectory,
    Log, PlanCredit, PoseStamped, RosMessage, ScrewCommand, StepSegment, StringMsg, TFMessage,
};
use ros2_client::{QosProfile, Subscription};
use tokio::sync::{mpsc, watch};

use crate::{metadata_yaml, BagWriter, ChannelId, Compression, QosRecord, WriterOptions};

/// Default depth of the recorder's readers: what a dry run needs (planning as fast as the
/// CPU allows, the recorder falls behind by tens of thousands of samples; at 4096 a
/// million-move dry run lost 1.4M). RustDDS keeps the last `depth` samples of a topic in its
/// participant's cache even after the reader took them, so the depth is also memory held for
/// the whole print: a print at machine pace sets it by its rate ([`executed_reader_depth`]).
/// A recorder that falls further behind loses samples, and says so
/// ([`RecordSummary::losses`]).
pub const DEFAULT_READER_DEPTH: usize = 100_000;

/// The reader depth when the recorder grants the plan credit (a dry run through
/// `polar-cell print`): producers then run at most `credit_horizon_s` (2 s) of plan ahead of
/// what the bag has taken, and the screw driver cuts its chunks at a quarter of that, so what
/// is in flight to the bag on any topic is a few thousand samples (2 s of plan: 1,000 screw
/// commands at 2 ms, a few hundred moves and their segments on a slicer file). Twice the
/// machine's queue, it leaves room for files of far shorter moves; a recorder that still
/// falls behind it says so ([`RecordSummary::losses`]). At 100,000 a 200,000-move dry run
/// peaked at 294 MB; at this depth 92 MB.
pub const CREDITED_READER_DEPTH: usize = 8192;

/// The reader depth for a print executed at `speed` times machine pace with producers
/// `horizon_s` of machine time ahead: the busiest topic (`/screw/command`, 500 per second of
/// machine time) for about 8 s of wall time at 1× — far more than a recorder falls behind at
/// a bounded rate — but no more than a credited dry run's lag allowance, plus twice that
/// rate over the horizon, which the producers may publish at once (a bench rig's 8 s horizon
/// lost 191 screw commands without it); never more than a dry run's.
///
/// RustDDS keeps `depth` samples of each topic after they are taken, so the depth is memory:
/// with 8 s of wall time at 10× (40,960) a 1M-move print at `--speed 10` grew to 240 MB
/// in its first minutes.
pub fn executed_reader_depth(speed: f64, horizon_s: f64) -> usize {
    let lag = (WRITER_QUEUE as f64 * speed.max(1.0)).min(CREDITED_READER_DEPTH as f64);
    let burst = 1000.0 * horizon_s.max(0.0);
    ((lag + burst).ceil() as usize).min(DEFAULT_READER_DEPTH)
}

/// Default plan-ahead a recorder grants with `grant_credit`: the machine's own 2 s. A dry run
/// is no slower for it (a million moves streamed in 61.2 s with 8 s, 56.5 s with 2 s here),
/// and what is in flight to the bag stays small.
pub const DEFAULT_CREDIT_HORIZON_S: f64 = 2.0;

/// The topics whose recorded plan a granted credit follows: the planner's. Not the screw
/// driver's commands: they end where the last extruding move ends, so after travel moves
/// their end stays behind the plan and a credit that waited for it held the planner for good
/// (polartest with a window of 3). The screw driver cannot run ahead of the planner anyway.
const CREDIT_TOPICS: [&str; 2] = ["/polar/trajectory", "/polar/steps"];

/// Whether a recorder with these parameters grants the credit: `grant_credit`, and it records
/// one of the plan topics the credit follows.
pub fn grants_credit(params: &cell_runtime::Params) -> bool {
    let follows_a_topic = params.strings("topics").iter().any(|entry| {
        let name = entry
            .split_once(':')
            .map_or(entry.as_str(), |(name, _)| name);
        CREDIT_TOPICS.contains(&name)
    });
    params.bool("grant_credit") && follows_a_topic
}

/// What a message says of the plan's timeline, for the credit a recorder grants: the plan
/// stamp (ns) a plan message starts at and how long it lasts, nothing for the rest.
///
/// Plan messages also have a key that never decreases along their stream, by which a
/// restarted planner's repeats are left out of the bag ([`cell_runtime::replay`]): the bag
/// holds the plan once, as the machine executed it.
trait Recordable: RosMessage {
    fn plan_span_ns(&self) -> Option<(i64, i64)> {
        None
    }
    fn replay_key(&self) -> Option<(i64, i64)> {
        None
    }
    /// Streams side by side on one topic, each with keys of its own.
    fn replay_lane(&self) -> &[String] {
        &[]
    }
}

macro_rules! recordable_without_plan_stamp {
    ($($ty:ty),*) => { $(impl Recordable for $ty {})* };
}
recordable_without_plan_stamp!(
    GcodeMove,
    GcodeProgress,
    GcodeAck,
    PoseStamped,
    StringMsg,
    DiagnosticArray,
    Log,
    Clock,
    TFMessage,
    PlanCredit
);

/// Joint states by their stamps, one lane per set of joints (the planner's stage joints and
/// the screw driver's screw share `/polar/planned_joint_states`). Only the planned states are
/// judged so ([`judges_repeats`]): the executed ones come from the one machine.
impl Recordable for JointState {
    fn replay_key(&self) -> Option<(i64, i64)> {
        Some((self.header.stamp.as_nanos(), 0))
    }
    fn replay_lane(&self) -> &[String] {
        &self.name
    }
}

/// Whether a tap on `topic` leaves a restarted producer's repeats of `T` out: plan messages
/// anywhere, joint states only where the planner and screw driver publish them (executed and
/// mechanism joint states may come with any stamps, and are never repeated by a restart).
fn judges_repeats<T: Recordable>(topic: &str) -> bool {
    T::TYPE.full_name() != JointState::TYPE.full_name() || topic == "/polar/planned_joint_states"
}

/// Screw commands are numbered by the screw driver across its restarts.
impl Recordable for ScrewCommand {
    fn replay_key(&self) -> Option<(i64, i64)> {
        Some((self.sequence as i64, 0))
    }
}

/// A move's plan: from its stamp to its last point.
impl Recordable for JointTrajectory {
    fn plan_span_ns(&self) -> Option<(i64, i64)> {
        let (start_ns, end_ns) = self.span_ns();
        Some((start_ns, end_ns - start_ns))
    }
    fn replay_key(&self) -> Option<(i64, i64)> {
        Some(self.span_ns())
    }
}

/// One piece of a move's steps: every segment of a move carries the move's start stamp, and
/// they follow each other ([`PlanEnd`] adds them up).
impl Recordable for StepSegment {
    fn plan_span_ns(&self) -> Option<(i64, i64)> {
        Some((
            self.header.stamp.as_nanos(),
            (self.duration_s * 1e9).round() as i64,
        ))
    }
    fn replay_key(&self) -> Option<(i64, i64)> {
        Some((self.move_sequence as i64, 0))
    }
}

/// A followed topic's frontier: where the plan taken on it ends (ns; `i64::MIN`: nothing yet).
type Frontier = std::sync::Arc<std::sync::atomic::AtomicI64>;

/// Default node name.
pub const NODE_NAME: &str = "bag_recorder";

/// The node's parameters.
pub fn param_specs() -> Vec<ParamSpec> {
    vec![
        ParamSpec::new(
            "output",
            ParamValue::String("cell.mcap".into()),
            "bag file (or directory when bag_directory is true)",
        ),
        ParamSpec::new(
            "bag_directory",
            ParamValue::Bool(false),
            "write a rosbag2 directory (MCAP file + metadata.yaml) instead of a bare file",
        ),
        ParamSpec::new(
            "topics",
            ParamValue::StringArray(
                cell_runtime::topics::SUITE_TOPICS
                    .iter()
                    .map(|t| t.name.to_string())
                    .collect(),
            ),
            "topics to record: a suite topic name, or `name:package/msg/Type`",
        ),
        ParamSpec::new(
            "compression",
            ParamValue::String("zstd".into()),
            "chunk compression: zstd or lz4",
        ),
        ParamSpec::new(
            "chunk_size_bytes",
            ParamValue::Integer(4 << 20),
            "uncompressed bytes per chunk",
        )
        .range(1024.0, 1e9),
        ParamSpec::new(
            "flush_period_s",
            ParamValue::Double(1.0),
            "close the chunk and flush the file at least this often (doubled after every 1,000 chunks, whose indexes stay in memory): a killed recorder loses at most this much (and what its queue holds)",
        )
        .range(0.01, 3600.0),
        ParamSpec::new(
            "reader_depth",
            ParamValue::Integer(DEFAULT_READER_DEPTH as i64),
            "keep-last depth of the readers of volatile topics: samples the recorder may fall behind by before it loses some (and reports them); RustDDS keeps this many after they are taken, so it is the recorder's memory",
        )
        .range(16.0, 1e7),
        ParamSpec::new(
            "qos_wait_s",
            ParamValue::Double(1.0),
            "for a topic the suite does not define: how long to wait at start for its publishers, whose QoS the reader takes (best effort unless all are reliable, transient local only if all are, as rosbag2 does)",
        )
        .range(0.0, 60.0),
        ParamSpec::new(
            "grant_credit",
            ParamValue::Bool(false),
            "publish /cell/plan_credit from what is recorded of the plan (/polar/trajectory, /polar/steps): with no machine (a dry run), producers plan no further ahead of the bag than credit_horizon_s",
        ),
        ParamSpec::new(
            "credit_horizon_s",
            ParamValue::Double(DEFAULT_CREDIT_HORIZON_S),
            "with grant_credit: how far ahead of the recorded plan producers may plan (s of plan time)",
        )
        .range(0.1, 3600.0),
        ParamSpec::new(
            "acknowledge_moves",
            ParamValue::Bool(true),
            "act as a flow-control consumer of /gcode/moves",
        ),
        cell_runtime::graph::Producer::param_spec(),
    ]
}

/// What was recorded.
#[derive(Debug, Clone)]
pub struct RecordSummary {
    pub path: PathBuf,
    pub topics: Vec<(String, String, u64)>,
    pub messages: u64,
    /// Topics with samples the bag lacks: numbered by their writers and never taken (empty:
    /// nothing was lost on the way in).
    pub losses: Vec<TopicLoss>,
}

/// The flow-controlled topic: a loss there has its own cause.
const MOVES_TOPIC: &str = "/gcode/moves";

/// What a tap tells when it ends, for each topic it records: the samples it never took
/// (see [`crate::gaps`]; for the flow-controlled moves, those it was never told where to
/// start taking). Empty: nothing recorded. (Samples a reader could not decode are only
/// warned about: RustDDS hands one up now and then, a trajectory cut short, while the bag
/// still has every sample its writer numbered.)
type TapReport = Vec<TopicLoss>;

/// Samples of one topic a tap did not record.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicLoss {
    pub topic: String,
    /// Published and never taken.
    pub missed: u64,
}

/// What the bag writer thread is handed.
enum Item {
    /// A message: its channel, log and publish times (ns), CDR.
    Message(ChannelId, u64, u64, Vec<u8>),
    /// Close the chunk and flush the file: what was written survives a kill.
    Flush,
}

/// Messages queued for the bag writer thread at most.
const WRITER_QUEUE: usize = 4096;

/// A running recorder; [`Recorder::stop`] drains, finishes the bag, and returns its summary.
pub struct Recorder {
    stop: watch::Sender<bool>,
    stream_finished: watch::Receiver<bool>,
    /// Why the bag could not be written, once it could not (the writer thread has ended).
    failed: watch::Receiver<Option<String>>,
    taps: Vec<tokio::task::JoinHandle<TapReport>>,
    writer: std::thread::JoinHandle<anyhow::Result<RecordSummary>>,
    /// Messages written so far (by the writer thread), `/gcode/ack` and `/cell/plan_credit` not
    /// counted (repeated while idle).
    written: std::sync::Arc<std::sync::atomic::AtomicU64>,
    _node: CellNode,
}

/// The reader's profile for `topic`, and what its publishers offer (for the bag's metadata):
/// the suite's table for a suite topic, ROS's default for another.
fn qos_for(topic: &str, reader_depth: usize) -> (QosProfile, QosRecord) {
    let offered = cell_runtime::topics::suite_topic(topic)
        .map_or(cell_runtime::topics::TopicQos::reliable(10), |t| t.qos);
    let record = QosRecord {
        reliability: crate::Reliability::Reliable,
        durability: if offered.transient_local {
            crate::Durability::TransientLocal
        } else {
            crate::Durability::Volatile
        },
        depth: offered.depth as u32,
    };
    if offered.transient_local {
        // Its writers offer late joiners their last `depth`; live samples come as fast as on
        // any topic (a burst of /rosout lines, depth 1), so the reader keeps as many as others.
        return (transient_local_qos(offered.depth.max(reader_depth)), record);
    }
    (reliable_qos(reader_depth), record)
}

/// A topic the suite does not define: the reader takes what its writers offer, as rosbag2
/// does — reliable only if every writer is (a reliable reader matches no best-effort writer,
/// and records nothing of it), transient local only if every writer is. It waits up to
/// `wait` for a writer to be discovered, then 0.2 s more for others; with none, ROS's
/// default (reliable, volatile), said in the log. (A blocking wait: only a recorder of
/// topics outside the suite makes it, at its start.) The record keeps ROS's default depth: discovery does not tell a writer's.
fn offered_qos(
    node: &CellNode,
    topic: &str,
    reader_depth: usize,
    wait: Duration,
) -> anyhow::Result<(QosProfile, QosRecord)> {
    let mut deadline = std::time::Instant::now() + wait;
    let mut settling = false;
    let offered = loop {
        let offered = node.offered(topic)?;
        let now = std::time::Instant::now();
        if !offered.is_empty() && !settling {
            // Its other publishers are announced about when the first is: a moment more,
            // so that a best-effort one seen a little later still counts.
            settling = true;
            deadline = deadline.min(now + Duration::from_millis(200));
        }
        if now >= deadline {
            break offered;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    if offered.is_empty() {
        cell_runtime::cell_log!(
            node,
            LogLevel::Warn,
            "{topic}: no publisher seen within {} s: recorded reliable and volatile (ROS's default), so a best-effort publisher that comes later is not recorded",
            wait.as_secs_f64()
        );
        return Ok(qos_for(topic, reader_depth));
    }
    let reliable = offered.iter().all(|o| o.reliable);
    let transient_local = offered.iter().all(|o| o.transient_local);
    let qos = match (reliable, transient_local) {
        (false, _) => cell_runtime::best_effort_qos(reader_depth),
        (true, true) => transient_local_qos(reader_depth),
        (true, false) => reliable_qos(reader_depth),
    };
    let record = QosRecord {
        reliability: if reliable {
            crate::Reliability::Reliable
        } else {
            crate::Reliability::BestEffort
        },
        durability: if transient_local && reliable {
            crate::Durability::TransientLocal
        } else {
            crate::Durability::Volatile
        },
        depth: 10,
    };
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "{topic}: {} publisher(s) offer {}: recorded {}",
        offered.len(),
        if reliable { "reliable" } else { "best effort" },
        match (reliable, transient_local) {
            (false, _) => "best effort",
            (true, true) => "reliable, transient local",
            (true, false) => "reliable",
        }
    );
    Ok((qos, record))
}

fn parse_topic(entry: &str) -> anyhow::Result<(String, String)> {
    if let Some((name, type_name)) = entry.split_once(':') {
        return Ok((name.to_string(), type_name.to_string()));
    }
    cell_runtime::topics::suite_topic(entry)
        .map(|t| (t.name.to_string(), t.type_name.to_string()))
        .ok_or_else(|| {
            anyhow!("topic {entry}: not a suite topic; give its type as `{entry}:package/msg/Type`")
        })
}

/// The topics to record, each once (as `ros2 bag record` takes a topic named twice): one
/// subscription per topic, so no sample is written twice. A topic given two types is refused.
fn unique_topics(topics: Vec<(String, String)>) -> anyhow::Result<Vec<(String, String)>> {
    let mut unique: Vec<(String, String)> = Vec::with_capacity(topics.len());
    for (name, type_name) in topics {
        match unique.iter().find(|(n, _)| *n == name) {
            Some((_, known)) if *known == type_name => {}
            Some((_, known)) => {
                bail!("topic {name} is given twice, as {known} and as {type_name}")
            }
            None => unique.push((name, type_name)),
        }
    }
    Ok(unique)
}

macro_rules! with_message_type {
    ($type_name:expr, $f:ident ( $($arg:expr),* )) => {
        match $type_name {
            "polar_cell_msgs/msg/GcodeMove" => $f::<GcodeMove>($($arg),*),
            "polar_cell_msgs/msg/GcodeProgress" => $f::<GcodeProgress>($($arg),*),
            "polar_cell_msgs/msg/GcodeAck" => $f::<GcodeAck>($($arg),*),
            "polar_cell_msgs/msg/StepSegment" => $f::<StepSegment>($($arg),*),
            "polar_cell_msgs/msg/ScrewCommand" => $f::<ScrewCommand>($($arg),*),
            "trajectory_msgs/msg/JointTrajectory" => $f::<JointTrajectory>($($arg),*),
            "sensor_msgs/msg/JointState" => $f::<JointState>($($arg),*),
            "geometry_msgs/msg/PoseStamped" => $f::<PoseStamped>($($arg),*),
            "std_msgs/msg/String" => $f::<StringMsg>($($arg),*),
            "diagnostic_msgs/msg/DiagnosticArray" => $f::<DiagnosticArray>($($arg),*),
            "rcl_interfaces/msg/Log" => $f::<Log>($($arg),*),
            "rosgraph_msgs/msg/Clock" => $f::<Clock>($($arg),*),
            "tf2_msgs/msg/TFMessage" => $f::<TFMessage>($($arg),*),
            "polar_cell_msgs/msg/PlanCredit" => $f::<PlanCredit>($($arg),*),
            other => Err(anyhow!("type {other} is not one of the suite's message types (polar-cell records and plays only those)")),
        }
    };
}

/// A type the taps can record (used through [`with_message_type`]): its Rust type.
fn recordable<T: RosMessage>() -> anyhow::Result<&'static str> {
    Ok(std::any::type_name::<T>())
}

/// A move of the streamer's into the bag, in sequence. Moves before the resume point is
/// known are not taken (the streamer sends them again once it is): counted in `unrecorded`,
/// in case it never will be. False once the bag writer is gone.
async fn record_move(
    tracker: &mut AckTracker,
    unrecorded: &mut u64,
    tx: &mpsc::Sender<Item>,
    channel: ChannelId,
    m: &GcodeMove,
    info: &ros2_client::MessageInfo,
) -> bool {
    *unrecorded += u64::from(tracker.needs_hello());
    tracker.accept(m.sequence) != Verdict::Process || forward(tx, channel, m, info).await
}

fn publish_time(info: &ros2_client::MessageInfo, fallback: u64) -> u64 {
    info.source_timestamp()
        .map(|t| t.to_nanos().max(0) as u64)
        .unwrap_or(fallback)
}

/// Hand a message to the bag writer, waiting while its queue is full: the back-pressure
/// reaches the DDS readers and, on `/gcode/moves`, the streamer's window.
async fn forward<T: RosMessage>(
    tx: &mpsc::Sender<Item>,
    channel: ChannelId,
    message: &T,
    info: &ros2_client::MessageInfo,
) -> bool {
    let log_time = now_ns();
    match cdr::encode(message) {
        Ok(bytes) => tx
            .send(Item::Message(
                channel,
                log_time,
                publish_time(info, log_time),
                bytes,
            ))
            .await
            .is_ok(),
        Err(e) => {
            tracing::error!("re-encoding a {}: {e}", T::TYPE.full_name());
            true
        }
    }
}

/// Whether a plan message is a restarted producer's repeat of one already recorded.
fn is_repeat<T: Recordable>(
    repeats: &mut Option<Repeats<cell_runtime::Gid>>,
    message: &T,
    info: &ros2_client::MessageInfo,
) -> bool {
    match (repeats, message.replay_key()) {
        (Some(repeats), Some(key)) => {
            repeats.admit(message.replay_lane(), key, info.publisher_gid()) == Admit::Repeat
        }
        _ => false,
    }
}

/// Samples a reader could not decode (any participant can write one; the reader has moved
/// past it): said once per topic, then counted, not once per sample.
#[derive(Debug, Default)]
struct Unreadable {
    count: u64,
}

impl Unreadable {
    /// The next sample `sub` holds now, past undecodable ones (noted), or `None`: what a
    /// drain at stop takes.
    fn take_next<M: 'static + serde::de::DeserializeOwned>(
        &mut self,
        sub: &Subscription<M>,
        topic: &str,
    ) -> Option<(M, ros2_client::MessageInfo)> {
        loop {
            match sub.take() {
                Ok(taken) => return taken,
                Err(e) => self.note(topic, &e),
            }
        }
    }

    fn note(&mut self, topic: &str, error: &ros2_client::ReadError) {
        self.count += 1;
        if self.count == 1 {
            tracing::warn!(
                "recorder: {topic}: a sample that cannot be read ({error}); any more are counted"
            );
        }
    }

    fn report(&self, topic: &str) {
        if self.count > 1 {
            tracing::warn!(
                "recorder: {topic}: {} samples could not be read",
                self.count
            );
        }
    }
}

fn spawn_tap<T: Recordable>(
    node: &mut CellNode,
    topic: &str,
    qos: &QosProfile,
    channel: ChannelId,
    tx: mpsc::Sender<Item>,
    mut stop: watch::Receiver<bool>,
    frontier: Option<Frontier>,
) -> anyhow::Result<tokio::task::JoinHandle<TapReport>> {
    let sub: Subscription<T> = node.subscription(topic, qos)?;
    let topic = topic.to_string();
    Ok(tokio::spawn(async move {
        let mut gaps = SequenceGaps::default();
        let mut plan_end = PlanEnd::default();
        let mut replayed = judges_repeats::<T>(&topic).then(Repeats::default);
        let mut unreadable = Unreadable::default();
        loop {
            tokio::select! {
                taken = sub.async_take() => match taken {
                    Ok((m, info)) => {
                        gaps.observe(info.publisher_gid(), info.sequence_number());
                        if is_repeat(&mut replayed, &m, &info) {
                            continue;
                        }
                        if !forward(&tx, channel, &m, &info).await { break }
                        if let (Some(frontier), Some(span)) = (&frontier, m.plan_span_ns()) {
                            let end_ns = plan_end.after(span);
                            frontier.fetch_max(end_ns, std::sync::atomic::Ordering::Relaxed);
                        }
                    }
                    Err(e) => unreadable.note(&topic, &e),
                },
                _ = stop.changed() => {
                    while let Some((m, info)) = unreadable.take_next(&sub, &topic) {
                        gaps.observe(info.publisher_gid(), info.sequence_number());
                        if is_repeat(&mut replayed, &m, &info) {
                            continue;
                        }
                        forward(&tx, channel, &m, &info).await;
                    }
                    break;
                }
            }
        }
        let repeats = replayed.as_ref().map_or(0, Repeats::repeats);
        if repeats > 0 {
            tracing::info!("recorder: {topic}: {repeats} repeats of a restarted producer left out");
        }
        unreadable.report(&topic);
        if gaps.out_of_order() > 0 {
            tracing::warn!(
                "recorder: {topic}: {} samples arrived again or out of order",
                gaps.out_of_order()
            );
        }
        vec![TopicLoss {
            topic,
            missed: gaps.missed(),
        }]
    }))
}

/// Publishes the credit of the recorded plan ([`crate::credit`]) until stopped.
fn spawn_credit_grant(
    node: &mut CellNode,
    frontiers: Vec<Frontier>,
    horizon_s: f64,
    mut stop: watch::Receiver<bool>,
) -> anyhow::Result<tokio::task::JoinHandle<TapReport>> {
    use crate::credit::{credit_due, credit_for, Credit};
    let credit_pub =
        node.publisher::<PlanCredit>("/cell/plan_credit", &publisher_qos("/cell/plan_credit"))?;
    let name = node.fully_qualified_name();
    Ok(tokio::spawn(async move {
        // As often as a tap can move a frontier by a twentieth of the horizon at a dry run's
        // pace (about 150 s of plan per second), so producers rarely wait.
        let mut tick = tokio::time::interval(Duration::from_millis(2));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut last: Option<(Credit, tokio::time::Instant)> = None;
        loop {
            tokio::select! {
                _ = tick.tick() => {
                    let recorded: Vec<Option<i64>> = frontiers
                        .iter()
                        .map(|f| f.load(std::sync::atomic::Ordering::Relaxed))
                        .map(|ns| (ns != i64::MIN).then_some(ns))
                        .collect();
                    let credit = credit_for(&recorded, horizon_s);
                    let since_s = last.map_or(f64::INFINITY, |(_, at)| at.elapsed().as_secs_f64());
                    if credit_due(last.map(|(c, _)| c), credit, since_s, horizon_s, 0.1) {
                        last = Some((credit, tokio::time::Instant::now()));
                        let _ = credit_pub.publish(PlanCredit {
                            header: polar_cell_msgs::Header {
                                stamp: polar_cell_msgs::Time::now(),
                                frame_id: String::new(),
                            },
                            executor: name.clone(),
                            executed_until: credit.executed_until,
                            accept_until: credit.accept_until,
                            horizon_s,
                            closed: false,
                        });
                    }
                }
                _ = stop.changed() => return Vec::new(),
            }
        }
    }))
}

/// The flow-controlled tap on `/gcode/moves` (with `/gcode/progress`, which carries the
/// resume point): writes each move once, in order, then acknowledges it.
#[allow(clippy::too_many_arguments)]
fn spawn_moves_consumer(
    node: &mut CellNode,
    moves_channel: ChannelId,
    progress_channel: Option<ChannelId>,
    tx: mpsc::Sender<Item>,
    mut stop: watch::Receiver<bool>,
    stream_finished: watch::Sender<bool>,
) -> anyhow::Result<tokio::task::JoinHandle<TapReport>> {
    // The streamer sends at most its window beyond the slowest consumer: the move depth.
    let (moves_qos, _) = qos_for("/gcode/moves", DEFAULT_MOVE_WINDOW);
    let moves: Subscription<GcodeMove> = node.subscription("/gcode/moves", &moves_qos)?;
    let progress: Subscription<GcodeProgress> =
        node.subscription("/gcode/progress", &reliable_qos(1000))?;
    let acks = node.publisher::<GcodeAck>("/gcode/ack", &publisher_qos("/gcode/ack"))?;
    let mut tracker = AckTracker::new(node.fully_qualified_name(), 64);
    // Moves and progress only from the streamer: the bag holds the print's moves, once each.
    let mut producer = cell_runtime::graph::Producer::of(node, true)?;
    Ok(tokio::spawn(async move {
        const TICK: Duration = cell_runtime::flow::LOOK_PERIOD;
        // An unchanged acknowledgement is repeated every `UNCHANGED_ACK_REPEAT` (every
        // other tick, it was 25 samples a second of an idle print).
        const IDLE_ACK_EVERY_TICKS: u32 =
            (cell_runtime::flow::UNCHANGED_ACK_REPEAT.as_millis() / TICK.as_millis()) as u32;
        let mut tick = tokio::time::interval(TICK);
        let mut idle_ticks = 0u32;
        let mut unrecorded = 0u64;
        // What the streamer says it published: a recorder that matched its writer too late
        // for any move still learns from a progress report that its bag lacks them.
        let mut streamer_published = 0u64;
        let mut unreadable = Unreadable::default();
        let mut unreadable_progress = Unreadable::default();
        // Progress is not flow-controlled: numbered by its writer like any other topic.
        let mut progress_gaps = SequenceGaps::default();
        loop {
            tokio::select! {
                taken = moves.async_take() => match taken {
                    Ok((m, info)) => {
                        idle_ticks = 0;
                        if !producer.admits(&info) {
                            continue;
                        }
                        if !record_move(&mut tracker, &mut unrecorded, &tx, moves_channel, &m, &info).await {
                            return Vec::new();
                        }
                        if let Some(ack) = tracker.ack_due(false) {
                            let _ = acks.publish(GcodeAck::from(ack));
                        }
                    }
                    Err(e) => unreadable.note("/gcode/moves", &e),
                },
                taken = progress.async_take() => {
                    let (p, info) = match taken {
                        Ok(taken) => taken,
                        Err(e) => {
                            unreadable_progress.note("/gcode/progress", &e);
                            continue;
                        }
                    };
                    if !producer.admits(&info) {
                        continue;
                    }
                    progress_gaps.observe(info.publisher_gid(), info.sequence_number());
                    streamer_published = streamer_published.max(p.moves_published);
                    if tracker.on_progress(&p.consumers, &p.consumer_next_expected) {
                        // Confirm the resume point: the streamer starts sending on this.
                        if let Some(ack) = tracker.ack_due(true) {
                            let _ = acks.publish(GcodeAck::from(ack));
                        }
                    }
                    if let Some(channel) = progress_channel {
                        forward(&tx, channel, &p, &info).await;
                    }
                    if p.finished {
                        let _ = stream_finished.send(true);
                    }
                },
                _ = tick.tick() => {
                    idle_ticks += 1;
                    if tracker.needs_hello() {
                        let _ = acks.publish(GcodeAck::from(tracker.hello()));
                    } else if idle_ticks >= 2 && (idle_ticks - 2).is_multiple_of(IDLE_ACK_EVERY_TICKS) {
                        // Idle: repeat the acknowledgement (recovers a lost one, reports gaps),
                        // at once and then as often as any consumer repeats one.
                        if let Some(ack) = tracker.ack_due(true) {
                            let _ = acks.publish(GcodeAck::from(ack));
                        }
                    }
                },
                _ = stop.changed() => {
                    // What the readers hold goes in too: the moves first (the bag would
                    // otherwise have trajectories and progress for moves it lacks), then
                    // the progress, each only from the streamer, as while recording.
                    while let Some((m, info)) = unreadable.take_next(&moves, "/gcode/moves") {
                        if !producer.admits(&info) {
                            continue;
                        }
                        if !record_move(&mut tracker, &mut unrecorded, &tx, moves_channel, &m, &info).await {
                            return Vec::new();
                        }
                    }
                    while let Some((p, info)) = unreadable_progress.take_next(&progress, "/gcode/progress") {
                        if !producer.admits(&info) {
                            continue;
                        }
                        progress_gaps.observe(info.publisher_gid(), info.sequence_number());
                        streamer_published = streamer_published.max(p.moves_published);
                        if let Some(channel) = progress_channel {
                            forward(&tx, channel, &p, &info).await;
                        }
                    }
                    // Moves came but the streamer never named this recorder among its
                    // consumers (so never told it where to start, nor waited for it): the
                    // bag lacks them. Said, not an empty topic and a success.
                    let lacking = unrecorded.max(streamer_published);
                    unreadable.report("/gcode/moves");
                    unreadable_progress.report("/gcode/progress");
                    let mut losses = vec![TopicLoss {
                        topic: MOVES_TOPIC.to_string(),
                        missed: if tracker.needs_hello() { lacking } else { 0 },
                    }];
                    if progress_channel.is_some() {
                        losses.push(TopicLoss {
                            topic: "/gcode/progress".to_string(),
                            missed: progress_gaps.missed(),
                        });
                    }
                    return losses;
                }
            }
        }
    }))
}

impl Recorder {
    /// Open the bag and subscribe to every topic of the node's `topics` parameter.
    pub fn start(mut node: CellNode) -> anyhow::Result<Recorder> {
        let params = node.params.clone();
        let compression = match params.string("compression") {
            "zstd" => Compression::Zstd,
            "lz4" => Compression::Lz4,
            other => bail!("parameter compression: `{other}` is not zstd or lz4"),
        };
        // Every topic checked before the disk is touched: a mistyped topic must not leave
        // an empty bag in the place of the one the user meant to keep.
        let topics = unique_topics(
            params
                .strings("topics")
                .iter()
                .map(|t| parse_topic(t))
                .collect::<anyhow::Result<_>>()?,
        )?;
        let topics: Vec<(String, String, &'static polar_cell_msgs::MsgType)> = topics
            .into_iter()
            .map(
                |(topic, type_name)| match polar_cell_msgs::find(&type_name) {
                    // As the taps and the bag name it (`std_msgs/String` is
                    // `std_msgs/msg/String`), and one they record: checked before the
                    // output is created, which would empty a bag already there.
                    Some(msg_type) => {
                        let type_name = msg_type.full_name();
                        with_message_type!(type_name.as_str(), recordable())
                            .with_context(|| format!("topic {topic}"))?;
                        Ok((topic, type_name, msg_type))
                    }
                    None => Err(anyhow!("topic {topic}: unknown message type {type_name}")),
                },
            )
            .collect::<anyhow::Result<_>>()?;
        let output = PathBuf::from(params.string("output"));
        let directory = params.bool("bag_directory");
        let file_path = if directory {
            if output.exists() {
                bail!("bag directory {} already exists", output.display());
            }
            std::fs::create_dir_all(&output)
                .with_context(|| format!("creating {}", output.display()))?;
            let stem = output
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "bag".into());
            output.join(format!("{stem}_0.mcap"))
        } else {
            output.clone()
        };
        let file = File::create(&file_path)
            .with_context(|| format!("creating bag {}", file_path.display()))?;
        let options = WriterOptions {
            compression,
            chunk_size_bytes: params.i64("chunk_size_bytes") as u64,
        };
        // What the bag is called in errors: the directory for a bag directory.
        let bag_path = if directory {
            output.clone()
        } else {
            file_path.clone()
        };
        let mut bag = BagWriter::new(BufWriter::with_capacity(1 << 20, file), &options)
            .map_err(|e| cannot_write(&bag_path, e.into()))?;
        // Written through now, so a bag that cannot be written (a full device) is refused
        // before anything moves, not at the first flush a second into the print.
        bag.flush().map_err(|e| cannot_write(&bag_path, e.into()))?;
        let acknowledge_moves = params.bool("acknowledge_moves");
        let reader_depth = params.i64("reader_depth") as usize;
        let qos_wait = Duration::from_secs_f64(params.f64("qos_wait_s"));
        let (tx, rx) = mpsc::channel::<Item>(WRITER_QUEUE);
        let (stop, stop_rx) = watch::channel(false);
        let (finished_tx, stream_finished) = watch::channel(false);
        let mut taps = Vec::new();
        let mut moves_channel = None;
        let mut progress_channel = None;
        // Consumers repeat their acknowledgements while idle: not activity.
        let mut ack_channel = None;
        // Our own repeated credit is not activity either.
        let mut credit_channel = None;
        let grant_credit = params.bool("grant_credit");
        let mut frontiers: Vec<Frontier> = Vec::new();
        for (topic, type_name, msg_type) in &topics {
            let (qos, record) = if cell_runtime::topics::suite_topic(topic).is_some() {
                qos_for(topic, reader_depth)
            } else {
                offered_qos(&node, topic, reader_depth, qos_wait)?
            };
            let channel = bag
                .add_topic(topic, msg_type, record)
                .map_err(|e| cannot_write(&bag_path, e.into()))?;
            if topic == "/gcode/ack" {
                ack_channel = Some(channel);
            }
            if topic == "/cell/plan_credit" {
                credit_channel = Some(channel);
            }
            match (topic.as_str(), acknowledge_moves) {
                ("/gcode/moves", true) => moves_channel = Some(channel),
                ("/gcode/progress", true) => progress_channel = Some(channel),
                _ => {
                    let frontier = (grant_credit && CREDIT_TOPICS.contains(&topic.as_str()))
                        .then(|| Frontier::new(i64::MIN.into()));
                    frontiers.extend(frontier.clone());
                    let tap = with_message_type!(
                        type_name.as_str(),
                        spawn_tap(
                            &mut node,
                            topic,
                            &qos,
                            channel,
                            tx.clone(),
                            stop_rx.clone(),
                            frontier
                        )
                    )?;
                    taps.push(tap);
                }
            }
        }
        if let Some(moves) = moves_channel {
            taps.push(spawn_moves_consumer(
                &mut node,
                moves,
                progress_channel,
                tx.clone(),
                stop_rx.clone(),
                finished_tx,
            )?);
        } else if let Some(progress) = progress_channel {
            taps.push(spawn_tap::<GcodeProgress>(
                &mut node,
                "/gcode/progress",
                &reliable_qos(1000),
                progress,
                tx.clone(),
                stop_rx.clone(),
                None,
            )?);
        }
        if grant_credit && !frontiers.is_empty() {
            taps.push(spawn_credit_grant(
                &mut node,
                frontiers,
                params.f64("credit_horizon_s"),
                stop_rx.clone(),
            )?);
        }
        // A chunk is written only when it is closed: close one every flush period, so a
        // recorder killed mid-print loses at most that much of the print. The period
        // doubles every `CHUNKS_PER_FLUSH_PERIOD` flushes (see `flush_period`).
        let base_flush_period = Duration::from_secs_f64(params.f64("flush_period_s"));
        let flusher = tx.clone();
        let mut flush_stop = stop_rx.clone();
        taps.push(tokio::spawn(async move {
            for flushes in 0u64.. {
                tokio::select! {
                    _ = tokio::time::sleep(flush_period(base_flush_period, flushes)) => {
                        if flusher.send(Item::Flush).await.is_err() {
                            return Vec::new();
                        }
                    }
                    _ = flush_stop.changed() => return Vec::new(),
                }
            }
            Vec::new()
        }));
        drop(tx);
        cell_runtime::cell_log!(
            node,
            LogLevel::Info,
            "recording {} topics to {}",
            topics.len(),
            output.display()
        );
        let directory_path = directory.then(|| output.clone());
        let written = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
        let written_by_writer = written.clone();
        let (failed_tx, failed) = watch::channel(None);
        let writer = std::thread::Builder::new()
            .name("bag writer".into())
            .spawn(move || -> anyhow::Result<RecordSummary> {
                let result = write_bag(
                    rx,
                    bag,
                    ack_channel,
                    credit_channel,
                    &written_by_writer,
                    directory_path,
                    file_path,
                );
                result.map_err(|e| {
                    let e = cannot_write(&bag_path, e);
                    // Said at once: whoever waits on the recording stops the print now,
                    // not when the taps behind the dead writer have starved it.
                    let _ = failed_tx.send(Some(format!(
                        "{e} (what was written before is readable with `polar-cell bag \
                         recover`)"
                    )));
                    e
                })
            })?;
        Ok(Recorder {
            stop,
            stream_finished,
            failed,
            taps,
            writer,
            written,
            _node: node,
        })
    }

    /// Fully qualified name of the recorder node (the flow-control consumer name).
    pub fn node_name(&self) -> String {
        self._node.fully_qualified_name()
    }

    /// Resolves once the recorder has written a `/gcode/progress` that says the stream is
    /// finished (only when it consumes `/gcode/moves`), or after `timeout`.
    pub async fn wait_stream_finished(&self, timeout: Duration) -> bool {
        let mut rx = self.stream_finished.clone();
        tokio::time::timeout(timeout, rx.wait_for(|&done| done))
            .await
            .is_ok_and(|r| r.is_ok())
    }

    /// Resolves (with the reason) once the bag cannot be written any more — a full disk, an
    /// I/O error — so a print stops at once with that reason instead of waiting on taps
    /// whose writer is gone; never resolves while the bag is fine.
    pub async fn failed(&self) -> String {
        let mut rx = self.failed.clone();
        let reason = match rx.wait_for(Option::is_some).await {
            Ok(reason) => reason.clone(),
            Err(_) => None,
        };
        match reason {
            Some(reason) => reason,
            None => std::future::pending().await,
        }
    }

    /// Resolves once no message (but the consumers' repeated acknowledgements) has been
    /// written for `quiet` (true), or after `limit`
    /// (false). After the stream's end the planner and screw driver still flush what they
    /// buffered (after their idle times, 0.05 s and 0.1 s by default): a quiet graph says
    /// they are done.
    pub async fn wait_quiet(&self, quiet: Duration, limit: Duration) -> bool {
        use std::sync::atomic::Ordering;
        let start = tokio::time::Instant::now();
        let mut seen = self.written.load(Ordering::Relaxed);
        let mut since = start;
        while start.elapsed() < limit {
            tokio::time::sleep(Duration::from_millis(10)).await;
            let now = self.written.load(Ordering::Relaxed);
            if now != seen {
                (seen, since) = (now, tokio::time::Instant::now());
            } else if since.elapsed() >= quiet {
                return true;
            }
        }
        false
    }

    /// Stop recording: take what the readers still hold, finish the bag, report.
    pub async fn stop(self) -> anyhow::Result<RecordSummary> {
        let _ = self.stop.send(true);
        let mut losses = Vec::new();
        let mut failed_taps = Vec::new();
        // Every tap awaited and the writer joined whatever one of them did: returning at a
        // failed tap would leave the bag without its end.
        for tap in self.taps {
            match tap.await {
                Ok(report) => losses.extend(report.into_iter().filter(|loss| loss.missed > 0)),
                Err(e) => failed_taps.push(e.to_string()),
            }
        }
        let mut summary = tokio::task::spawn_blocking(move || self.writer.join())
            .await?
            .map_err(|_| anyhow!("bag writer thread panicked"))??;
        if !failed_taps.is_empty() {
            bail!(
                "recorder: {} of its topic readers failed ({}); the bag {} is finished but may lack what they held",
                failed_taps.len(),
                failed_taps.join("; "),
                summary.path.display()
            );
        }
        summary.losses = losses;
        Ok(summary)
    }
}

/// Flushes at one period before it doubles.
const CHUNKS_PER_FLUSH_PERIOD: u64 = 1000;

/// The wait before flush number `flushes` (from 0): `base` for the first
/// [`CHUNKS_PER_FLUSH_PERIOD`], then twice as long for as many, and so on. Each flush closes
/// a chunk, and the MCAP writer keeps every chunk's index in memory until the summary (0.67
/// KB with 15 channels): at a fixed 1 s, a 10-hour print would hold 36,000 of them, 24 MB
/// more at the end than at the start. Doubling keeps the count logarithmic in the print's
/// length (5,200 chunks in 10 hours, 8,400 in 100) while a print killed in its first quarter
/// hour still loses at most `base`.
fn flush_period(base: Duration, flushes: u64) -> Duration {
    base * (1u32 << (flushes / CHUNKS_PER_FLUSH_PERIOD).min(16))
}

/// The error of a bag that cannot be written, with the bag's path and the cause's chain in
/// one line ("the bag out.mcap could not be written: …: No space left on device").
fn cannot_write(bag: &Path, e: anyhow::Error) -> anyhow::Error {
    anyhow!("the bag {} could not be written: {e:#}", bag.display())
}

/// The writer thread's work: every item into the bag until the taps are done, then the
/// summary, `sync_all` and (for a bag directory) `metadata.yaml`.
fn write_bag(
    mut rx: mpsc::Receiver<Item>,
    mut bag: BagWriter<BufWriter<File>>,
    ack_channel: Option<ChannelId>,
    credit_channel: Option<ChannelId>,
    written: &std::sync::atomic::AtomicU64,
    directory_path: Option<PathBuf>,
    file_path: PathBuf,
) -> anyhow::Result<RecordSummary> {
    while let Some(item) = rx.blocking_recv() {
        let Item::Message(channel, log_time, publish_time, bytes) = item else {
            bag.flush()?;
            continue;
        };
        bag.write(channel, log_time, publish_time, &bytes)?;
        if Some(channel) != ack_channel && Some(channel) != credit_channel {
            written.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
    }
    let messages = bag.message_count();
    let (sink, topics) = bag.finish()?;
    let file = sink
        .into_inner()
        .map_err(|e| anyhow!("flushing the bag: {e}"))?;
    file.sync_all().context("syncing the bag")?;
    if let Some(dir) = &directory_path {
        let name = file_path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        std::fs::write(
            dir.join("metadata.yaml"),
            metadata_yaml(&name, &topics, crate::meta::ROS_DISTRO),
        )
        .context("writing metadata.yaml")?;
    }
    Ok(RecordSummary {
        path: directory_path.unwrap_or(file_path),
        topics: topics
            .into_iter()
            .map(|t| (t.topic, t.type_name, t.stats.message_count))
            .collect(),
        messages,
        losses: Vec::new(),
    })
}

/// Run the recorder from its own command line until SIGINT/SIGTERM.
pub async fn main_with_args(argv: Vec<String>) -> anyhow::Result<()> {
    let (ros_args, rest) = cell_runtime::RosArgs::parse(&argv)?;
    if !rest.is_empty() {
        bail!("unexpected arguments {rest:?}: use --ros-args -p output:=FILE -p topics:=[...]");
    }
    // Caught from the start: a signal while the recorder starts (the bag file is already
    // created, the QoS of outside topics awaited) ends it with a finished bag, where the
    // default action left an MCAP without its end.
    let mut signals = cell_runtime::ShutdownSignals::new().context("catching SIGINT/SIGTERM")?;
    let node = CellNode::start(NODE_NAME, &param_specs(), &ros_args)?;
    let recorder = Recorder::start(node)?;
    tokio::select! {
        _ = signals.next() => {}
        reason = recorder.failed() => bail!(reason),
    }
    let summary = recorder.stop().await?;
    print_summary(&summary);
    if let Some(loss) = summary.loss() {
        bail!(loss);
    }
    Ok(())
}

/// Print a recording summary to stderr.
pub fn print_summary(summary: &RecordSummary) {
    eprintln!(
        "bag {}: {} messages",
        summary.path.display(),
        summary.messages
    );
    for (topic, type_name, count) in &summary.topics {
        eprintln!("  {topic:<28} {type_name:<40} {count}");
    }
    for loss in &summary.losses {
        eprintln!(
            "  {}: {} samples published but never received (the bag lacks them)",
            loss.topic, loss.missed
        );
    }
}

impl RecordSummary {
    /// What the bag lacks, in one line (`None`: nothing was lost on the way in).
    pub fn loss(&self) -> Option<String> {
        if self.losses.is_empty() {
            return None;
        }
        let total: u64 = self.losses.iter().map(|l| l.missed).sum();
        let topics: Vec<String> = (self.losses.iter())
            .map(|l| format!("{} {}", l.topic, l.missed))
            .collect();
        let mut causes = Vec::new();
        if self.losses.iter().any(|l| l.topic == MOVES_TOPIC) {
            causes.push(
                "the streamer does not count this recorder among its consumers (its \
                 `consumers` parameter), so it never said where the moves start",
            );
        }
        if self.losses.iter().any(|l| l.topic != MOVES_TOPIC) {
            causes.push("the recorder fell behind their keep-last history");
        }
        Some(format!(
            "the bag lacks {total} samples its writers published ({}): {}",
            topics.join(", "),
            causes.join("; ")
        ))
    }
}

/// Where a bag's MCAP file is for a path that may be a bag directory.
pub fn mcap_file_of(path: &Path) -> anyhow::Result<PathBuf> {
    if path.is_dir() {
        let mut files: Vec<PathBuf> = std::fs::read_dir(path)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
            .collect();
        files.sort();
        // A bag split by size (`ros2 bag record --max-bag-size`) has several: reading only
        // one of them would drop the rest without a word.
        if files.len() > 1 {
            let names: Vec<String> = files
                .iter()
                .filter_map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned()))
                .collect();
            bail!(
                "{}: a bag split into {} files ({}); give one of them as the bag",
                path.display(),
                files.len(),
                names.join(", ")
            );
        }
        files
            .into_iter()
            .next()
            .ok_or_else(|| anyhow!("{}: no .mcap file in the bag directory", path.display()))
    } else {
        Ok(path.to_path_buf())
    }
}

/// A publisher that takes CDR bytes (as stored in a bag) for a type known at run time.
pub trait CdrPublisher: Send {
    /// Decode `cdr` (with its encapsulation header) and publish it.
    fn publish_cdr(&self, cdr: &[u8]) -> anyhow::Result<()>;
    /// Matched subscriptions right now.
    fn subscription_count(&self, node: &CellNode) -> usize;
}

struct TypedPublisher<T: RosMessage>(ros2_client::Publisher<T>);

impl<T: RosMessage> CdrPublisher for TypedPublisher<T> {
    fn publish_cdr(&self, bytes: &[u8]) -> anyhow::Result<()> {
        let message: T =
            cdr::decode(bytes).with_context(|| format!("decoding a {}", T::TYPE.full_name()))?;
        let mut pending = message;
        // A full reliable send window: wait for acknowledgements and try again.
        for _ in 0..1000 {
            match self.0.publish(pending) {
                Ok(()) => return Ok(()),
                Err(ros2_client::ros2::WriteError::WouldBlock { data }) => {
                    pending = data;
                    std::thread::sleep(Duration::from_millis(1));
                }
                Err(e) => bail!("publishing a {}: {e:?}", T::TYPE.full_name()),
            }
        }
        bail!(
            "publishing a {}: no subscriber acknowledged for 1 s",
            T::TYPE.full_name()
        )
    }

    fn subscription_count(&self, node: &CellNode) -> usize {
        self.0.get_subscription_count(&node.node)
    }
}

fn make_typed_publisher<T: RosMessage>(
    node: &mut CellNode,
    topic: &str,
    qos: &QosProfile,
) -> anyhow::Result<Box<dyn CdrPublisher>> {
    Ok(Box::new(TypedPublisher(node.publisher::<T>(topic, qos)?)))
}

/// A [`CdrPublisher`] for `type_name` on `topic`.
pub fn cdr_publisher(
    node: &mut CellNode,
    topic: &str,
    type_name: &str,
    qos: &QosProfile,
) -> anyhow::Result<Box<dyn CdrPublisher>> {
    with_message_type!(type_name, make_typed_publisher(node, topic, qos))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A recording that lost samples says which and why in one line (the recorder then
    /// exits non-zero); one that lost nothing says nothing.
    #[test]
    fn a_loss_names_its_topics_and_causes() {
        let summary = |losses: Vec<TopicLoss>| RecordSummary {
            path: PathBuf::from("out.mcap"),
            topics: Vec::new(),
            messages: 0,
            losses,
        };
        let loss = |topic: &str, missed| TopicLoss {
            topic: topic.into(),
            missed,
        };
        assert_eq!(summary(vec![]).loss(), None);
        let text = summary(vec![loss("/gcode/progress", 3), loss("/tf", 2)])
            .loss()
            .unwrap();
        assert_eq!(
            text,
            "the bag lacks 5 samples its writers published (/gcode/progress 3, /tf 2): the \
             recorder fell behind their keep-last history"
        );
        let text = summary(vec![loss(MOVES_TOPIC, 12)]).loss().unwrap();
        assert!(text.starts_with("the bag lacks 12 samples its writers published (/gcode/moves 12): the streamer does not count this recorder"), "{text}");
    }

    #[test]
    fn a_topic_named_twice_is_recorded_once_and_two_types_are_refused() {
        let t = |n: &str, ty: &str| (n.to_string(), ty.to_string());
        let tf = "tf2_msgs/msg/TFMessage";
        let kept = unique_topics(vec![
            t("/tf", tf),
            t("/a", "std_msgs/msg/String"),
            t("/tf", tf),
        ])
        .unwrap();
        assert_eq!(kept, [t("/tf", tf), t("/a", "std_msgs/msg/String")]);
        let e = unique_topics(vec![t("/tf", tf), t("/tf", "std_msgs/msg/String")]).unwrap_err();
        assert!(e.to_string().contains("given twice"), "{e}");
    }

    #[test]
    fn a_split_bag_directory_is_refused_with_its_files() {
        let dir = std::env::temp_dir().join(format!("cell_bag_split_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("bag_0.mcap"), b"").unwrap();
        assert_eq!(mcap_file_of(&dir).unwrap(), dir.join("bag_0.mcap"));
        std::fs::write(dir.join("bag_1.mcap"), b"").unwrap();
        let e = mcap_file_of(&dir).unwrap_err().to_string();
        assert!(
            e.contains("split into 2 files (bag_0.mcap, bag_1.mcap)"),
            "{e}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Chunks (whose indexes the writer keeps until the end) grow with the logarithm of a
    /// print's length, not with it; the first quarter hour is flushed every second.
    #[test]
    fn chunks_grow_with_the_logarithm_of_the_print() {
        let base = Duration::from_secs(1);
        assert_eq!(flush_period(base, 0), base);
        assert_eq!(flush_period(base, 999), base);
        assert_eq!(flush_period(base, 1000), 2 * base);
        assert_eq!(flush_period(base, 3500), 8 * base);
        let chunks_in = |hours: u64| {
            let (mut t, mut n) = (Duration::ZERO, 0u64);
            while t < Duration::from_secs(hours * 3600) {
                t += flush_period(base, n);
                n += 1;
            }
            n
        };
        assert_eq!(
            chunks_in(1),
            1000 + 1000 + 150,
            "1,000 s at 1 s, 2,000 at 2 s, 600 at 4 s"
        );
        assert!(chunks_in(10) <= 6_000, "{}", chunks_in(10));
        assert!(chunks_in(100) <= 9_000, "{}", chunks_in(100));
    }

    /// At machine pace the depth covers 8 s of 500 screw commands a second of machine time,
    /// scaled with the speed up to a credited dry run's depth, plus a burst of the horizon
    /// at twice that rate.
    #[test]
    fn an_executed_print_keeps_seconds_of_its_busiest_topic() {
        assert_eq!(executed_reader_depth(1.0, 0.0), 4096);
        assert!(executed_reader_depth(1.0, 0.0) as f64 / 500.0 > 8.0);
        assert_eq!(
            executed_reader_depth(0.1, 2.0),
            6096,
            "slower: no shallower"
        );
        assert_eq!(
            executed_reader_depth(1.0, 8.0),
            12_096,
            "the bench rig's horizon"
        );
        assert_eq!(executed_reader_depth(2.0, 2.0), 10_192);
        assert_eq!(executed_reader_depth(10.0, 2.0), 10_192);
        assert_eq!(executed_reader_depth(40.0, 2.0), 10_192);
        assert_eq!(executed_reader_depth(10.0, 200.0), DEFAULT_READER_DEPTH);
    }
}
