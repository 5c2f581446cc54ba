//! `polar-cell bag info|recover|play`.

use std::collections::HashMap;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{bail, Context as _};
use cell_bag::node::{cdr_publisher, mcap_file_of, CdrPublisher};
use cell_bag::{read_bag, Durability};
use cell_runtime::{reliable_qos, transient_local_qos, CellNode, RosArgs};

fn map_bag(path: &Path) -> anyhow::Result<(std::path::PathBuf, memmap2::Mmap)> {
    let file_path = mcap_file_of(path)?;
    let file = std::fs::File::open(&file_path)
        .with_context(|| format!("opening {}", file_path.display()))?;
    // Safety: the bag is opened read-only and not modified while mapped by this process.
    let map = unsafe { memmap2::Mmap::map(&file) }
        .with_context(|| format!("mapping {}", file_path.display()))?;
    Ok((file_path, map))
}

pub fn info(path: &Path) -> anyhow::Result<()> {
    let (file_path, bytes) = map_bag(path)?;
    let bag = read_bag(&bytes).with_context(|| format!("reading {}", file_path.display()))?;
    let i = &bag.info;
    println!("Files:             {}", file_path.display());
    println!("Bag size:          {} bytes", bytes.len());
    println!("Storage id:        mcap (profile {})", i.profile);
    println!("Duration:          {:.9} s", i.duration_s());
    println!("Start:             {} ns", i.start_ns);
    println!("End:               {} ns", i.end_ns);
    println!("Messages:          {}", i.message_count);
    println!(
        "Chunks:            {} ({})",
        i.chunk_count,
        i.compression.join(", ")
    );
    println!("Topic information:");
    for t in &i.topics {
        let qos = t
            .qos
            .map(|q| format!("{:?}/{:?}/depth {}", q.reliability, q.durability, q.depth))
            .unwrap_or_else(|| "no QoS".into());
        println!(
            "  Topic: {} | Type: {} | Count: {} | Serialization Format: cdr | QoS: {}",
            t.name, t.type_name, t.message_count, qos
        );
    }
    Ok(())
}

pub fn recover(input: &Path, output: &Path) -> anyhow::Result<()> {
    let (file_path, bytes) = map_bag(input)?;
    if output.exists() {
        bail!("{} exists already: give a new path", output.display());
    }
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(output)
        .with_context(|| format!("creating {}", output.display()))?;
    let mut sink = std::io::BufWriter::new(file);
    let recovered = cell_bag::recover(&bytes, &mut sink, &cell_bag::WriterOptions::default())
        .with_context(|| format!("recovering {}", file_path.display()))
        .and_then(|r| {
            use std::io::Write as _;
            sink.flush()
                .with_context(|| format!("writing {}", output.display()))?;
            Ok(r)
        });
    let r = match recovered {
        Ok(r) => r,
        Err(e) => {
            // Not a bag: a half-written output would only be refused by the next try.
            drop(sink);
            let _ = std::fs::remove_file(output);
            return Err(e);
        }
    };
    let end = match &r.end {
        cell_bag::RecoveryEnd::Complete => "the data section was complete".to_string(),
        cell_bag::RecoveryEnd::Truncated { at } => format!(
            "the file stops inside the record at byte {at}; {} bytes after it were not usable",
            bytes.len() as u64 - at
        ),
        cell_bag::RecoveryEnd::Damaged { at, what } => {
            format!("the record at byte {at} is damaged ({what}); nothing after it was read")
        }
    };
    eprintln!(
        "{}: {} messages recovered into {} ({} whole chunks, {} messages from a chunk cut \
         short{}); {end}",
        file_path.display(),
        r.messages,
        output.display(),
        r.complete_chunks,
        r.partial_chunk_messages,
        if r.orphan_messages > 0 {
            format!(
                ", {} messages of channels never declared dropped",
                r.orphan_messages
            )
        } else {
            String::new()
        }
    );
    Ok(())
}

/// How `bag play` plays.
pub struct PlayOptions {
    /// Speed factor on the recorded timing.
    pub rate: f64,
    /// As fast as subscribers take it (ignores `rate`).
    pub fast: bool,
    /// Only these topics (empty: all).
    pub only_topics: Vec<String>,
    /// Wait up to this long for every topic to have a subscriber before playing.
    pub wait_subscribers_s: f64,
    /// ... and, when named, a subscription of each of these nodes.
    pub wait_for_nodes: Vec<String>,
    /// At the end, wait up to this long for every subscriber to acknowledge everything.
    pub deliver_timeout_s: f64,
}

/// The speed factors a replay takes on the recorded timing.
pub const RATE_RANGE: std::ops::RangeInclusive<f64> = 1e-3..=1e6;

pub async fn play(path: &Path, options: &PlayOptions, ros_args: &RosArgs) -> anyhow::Result<()> {
    let PlayOptions {
        rate,
        fast,
        ref only_topics,
        wait_subscribers_s,
        ref wait_for_nodes,
        deliver_timeout_s,
    } = *options;
    if !RATE_RANGE.contains(&rate) {
        bail!("--rate must lie in [0.001, 1e6], got {rate}");
    }
    for (name, s) in [
        ("--deliver-timeout-s", deliver_timeout_s),
        ("--wait-subscribers-s", wait_subscribers_s),
    ] {
        if !crate::SECONDS_RANGE.contains(&s) {
            bail!("{name} must lie in [0, 3.2e7] s, got {s}");
        }
    }
    let (file_path, bytes) = map_bag(path)?;
    let bag = read_bag(&bytes).with_context(|| format!("reading {}", file_path.display()))?;
    // A topic asked for by name that the bag lacks is a typo more often than not.
    let absent: Vec<&str> = only_topics
        .iter()
        .filter(|name| !bag.info.topics.iter().any(|t| &t.name == *name))
        .map(String::as_str)
        .collect();
    if !absent.is_empty() {
        bail!(
            "{}: no topic {} in the bag (it has {})",
            file_path.display(),
            absent.join(", "),
            bag.info
                .topics
                .iter()
                .map(|t| t.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let mut node = CellNode::start("bag_player", &[], ros_args)?;
    let mut publishers: HashMap<String, Box<dyn CdrPublisher>> = HashMap::new();
    for t in &bag.info.topics {
        if !only_topics.is_empty() && !only_topics.contains(&t.name) {
            continue;
        }
        // A deep history so a fast replay is not thinned by keep-last on the writer side.
        // A suite topic that is transient-local now is offered so whatever the bag says: a
        // bag recorded when it was volatile (`/polar/trajectory` before the screw driver's
        // restart) would not match today's transient-local readers.
        let latched_now = cell_runtime::topics::suite_topic(&t.name)
            .is_some_and(|suite| suite.qos.transient_local);
        let qos = match t.qos.map(|q| q.durability) {
            Some(Durability::TransientLocal) => {
                transient_local_qos(t.qos.map_or(1, |q| q.latched_depth(t.message_count)))
            }
            _ if latched_now => transient_local_qos(10_000),
            _ => reliable_qos(10_000),
        };
        let publisher = match cdr_publisher(&mut node, &t.name, &t.type_name, &qos) {
            Ok(publisher) => publisher,
            // A type we do not know: asked for by name, an error; otherwise skipped and
            // said, as `ros2 bag play` skips a type it cannot load.
            Err(e) if only_topics.is_empty() && polar_cell_msgs::find(&t.type_name).is_none() => {
                eprintln!(
                    "warning: {}: not playing {} ({} messages): {e:#}",
                    file_path.display(),
                    t.name,
                    t.message_count
                );
                continue;
            }
            Err(e) => return Err(e.context(format!("{}: topic {}", file_path.display(), t.name))),
        };
        publishers.insert(t.name.clone(), publisher);
    }
    if wait_subscribers_s > 0.0 {
        // What a topic still lacks: any subscriber, or one of each node named.
        let lacking = |topic: &String, publisher: &dyn CdrPublisher| -> Option<String> {
            if publisher.subscription_count(&node) == 0 {
                return Some(format!("{topic} (no subscriber)"));
            }
            let absent: Vec<&str> = wait_for_nodes
                .iter()
                .filter(|n| !node.subscribed_by(topic, n))
                .map(String::as_str)
                .collect();
            (!absent.is_empty()).then(|| format!("{topic} (not {})", absent.join(", ")))
        };
        let deadline = Instant::now() + Duration::from_secs_f64(wait_subscribers_s);
        loop {
            let missing: Vec<String> = publishers
                .iter()
                .filter_map(|(t, p)| lacking(t, p.as_ref()))
                .collect();
            if missing.is_empty() {
                break;
            }
            if Instant::now() > deadline {
                eprintln!(
                    "after {wait_subscribers_s} s, still no subscription on {}; playing anyway",
                    missing.join(", ")
                );
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
    let start = Instant::now();
    let mut first_log_time = None;
    let mut count = 0u64;
    for (index, message) in bag.messages()?.enumerate() {
        let message = message
            .with_context(|| format!("{}: message {index} of the bag", file_path.display()))?;
        let Some(publisher) = publishers.get(&message.topic) else {
            continue;
        };
        let t0 = *first_log_time.get_or_insert(message.log_time_ns);
        if !fast {
            let offset = Duration::from_nanos(message.log_time_ns.saturating_sub(t0)).div_f64(rate);
            let due = start + offset;
            let now = Instant::now();
            if due > now {
                tokio::time::sleep(due - now).await;
            }
        }
        publisher.publish_cdr(&message.data).with_context(|| {
            format!(
                "{}: message {index} of the bag ({}, {count} played before it)",
                file_path.display(),
                message.topic
            )
        })?;
        count += 1;
    }
    let played_s = start.elapsed().as_secs_f64();
    // A message lost on the way is resent only while its writer exists: stay until every
    // subscriber has acknowledged everything (bounded), and name those that have not.
    let undelivered = node
        .wait_delivered(Duration::from_secs_f64(deliver_timeout_s))
        .await;
    for u in &undelivered {
        eprintln!("warning: after {deliver_timeout_s} s, {u}");
    }
    eprintln!(
        "played {count} messages from {} in {played_s:.3} s; {}",
        file_path.display(),
        if undelivered.is_empty() {
            "every subscriber acknowledged them all".to_string()
        } else {
            format!(
                "{} subscriptions had not acknowledged all",
                undelivered.len()
            )
        }
    );
    Ok(())
}
