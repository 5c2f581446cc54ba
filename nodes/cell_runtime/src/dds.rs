//! A ROS 2 node on DDS, set up the way every node of the cell needs it.
//!
//! What ros2-client leaves to the application and this module does:
//! * `ROS_DOMAIN_ID` is read here (ros2-client's `Context::new` ignores it);
//! * DDS traffic stays on loopback unless `POLAR_CELL_NETWORK` says otherwise;
//! * QoS is the ROS default (reliable, volatile, keep-last 10) — ros2-client's subscriber
//!   default is best-effort, depth 1;
//! * topic names are expanded and remapped per the ROS command line;
//! * parameters are declared so `ros2 param list/get` shows them; they are read-only at run
//!   time (changing one means restarting the node);
//! * `/diagnostics` and `/rosout` publishing.

use std::net::{IpAddr, Ipv4Addr};

use polar_cell_msgs::{DiagnosticArray, DiagnosticStatus, Header, KeyValue, RosMessage, Time};
use ros2_client::{
    ros2::LogLevel, Context, MessageTypeName, Name, Node, NodeName, NodeOptions, ParameterValue,
    Publisher, QosProfile, Subscription,
};

use crate::args::RosArgs;
use crate::delivery::{PublishedTopic, Undelivered};
use crate::names::NameResolver;
use crate::params::{ParamSpec, ParamValue, Params};
use crate::RuntimeError;

/// Which network interfaces DDS may use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Network {
    /// 127.0.0.1 only (the default).
    Loopback,
    /// Every interface.
    All,
    /// These addresses' interfaces.
    Only(Vec<IpAddr>),
}

impl Network {
    /// From `POLAR_CELL_NETWORK`: unset or `loopback`, `all`, or comma-separated addresses.
    pub fn from_env() -> Result<Network, RuntimeError> {
        match std::env::var("POLAR_CELL_NETWORK") {
            Err(_) => Ok(Network::Loopback),
            Ok(v) => Network::parse(&v),
        }
    }

    pub fn parse(text: &str) -> Result<Network, RuntimeError> {
        match text.trim() {
            "" | "loopback" => Ok(Network::Loopback),
            "all" => Ok(Network::All),
            list => list
                .split(',')
                .map(|a| {
                    a.trim()
                        .parse::<IpAddr>()
                        .map_err(|_| RuntimeError::Environment {
                            variable: "POLAR_CELL_NETWORK",
                            problem: format!("`{a}` is not an IP address (or `loopback`, `all`)"),
                        })
                })
                .collect::<Result<Vec<_>, _>>()
                .map(Network::Only),
        }
    }
}

/// `ROS_DOMAIN_ID` (0 when unset), validated to ROS's 0–232.
pub fn domain_id_from_env() -> Result<u16, RuntimeError> {
    match std::env::var("ROS_DOMAIN_ID") {
        Err(_) => Ok(0),
        Ok(v) if v.trim().is_empty() => Ok(0),
        Ok(v) => {
            v.trim()
                .parse::<u16>()
                .ok()
                .filter(|&d| d <= 232)
                .ok_or(RuntimeError::Environment {
                    variable: "ROS_DOMAIN_ID",
                    problem: format!("`{v}` is not a domain id in 0..=232"),
                })
        }
    }
}

/// The ROS 2 default QoS: reliable, volatile, keep-last 10.
pub fn ros_default_qos() -> QosProfile {
    reliable_qos(10)
}

/// Reliable, volatile, keep-last `depth`.
pub fn reliable_qos(depth: usize) -> QosProfile {
    use ros2_client::qos::{Durability, History, Reliability, WhenFull};
    QosProfile::publisher_default()
        .reliability(Reliability::Reliable {
            when_full: WhenFull::DEFAULT,
        })
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth })
}

/// Best effort, volatile, keep-last `depth` (a reader for best-effort writers: a reliable
/// reader matches none of them).
pub fn best_effort_qos(depth: usize) -> QosProfile {
    use ros2_client::qos::{Durability, History, Reliability};
    QosProfile::publisher_default()
        .reliability(Reliability::BestEffort)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth })
}

/// What one discovered writer of a topic offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Offered {
    pub reliable: bool,
    pub transient_local: bool,
}

/// Reliable, transient-local, keep-last `depth` (latched, e.g. `/robot_description`).
pub fn transient_local_qos(depth: usize) -> QosProfile {
    use ros2_client::qos::Durability;
    reliable_qos(depth).durability(Durability::TransientLocal)
}

/// One DDS participant per process-level context.
pub fn make_context(domain_id: u16, network: &Network) -> Result<Context, RuntimeError> {
    let mut builder = rustdds::DomainParticipantBuilder::new(domain_id);
    match network {
        Network::Loopback => {
            builder = builder.with_only_networks([IpAddr::V4(Ipv4Addr::LOCALHOST)]);
        }
        Network::All => {}
        Network::Only(addresses) => builder = builder.with_only_networks(addresses.clone()),
    }
    let participant = builder
        .build()
        .map_err(|e| RuntimeError::Dds(e.to_string()))?;
    Context::from_domain_participant(participant).map_err(|e| RuntimeError::Dds(e.to_string()))
}

/// A running node: ros2-client node, resolved names and parameters, diagnostics publisher.
pub struct CellNode {
    // Fields drop in order: endpoints before the node and its participant.
    /// Endpoints that must outlive the code that made them: a writer dropped right after its
    /// last sample cannot repair that sample's loss.
    kept: Vec<Box<dyn std::any::Any + Send>>,
    /// Every writer this node made, for [`CellNode::wait_delivered`].
    published: Vec<PublishedTopic>,
    diagnostics: Publisher<DiagnosticArray>,
    pub node: Node,
    /// Dropped after `node` (whose drop tells the spinner to stop) and before `_context`.
    _spinner: SpinnerExit,
    pub names: NameResolver,
    pub params: Params,
    _context: Context,
}

/// Waits, when dropped, for the node's spinner thread to end. The spinner holds the node's
/// parameter services and its own handle on the participant, which it drops first; without
/// the wait, the participant can close before those endpoints and RustDDS logs an error for
/// each ("Cannot remove Reader/Writer").
struct SpinnerExit(std::sync::mpsc::Receiver<()>);

impl Drop for SpinnerExit {
    fn drop(&mut self) {
        let _ = self.0.recv_timeout(std::time::Duration::from_secs(2));
    }
}

/// The names and parameters the node `default_name` gets from the ROS command line (remaps,
/// parameter files, `-p`), without DDS: what [`CellNode::start`] resolves, for tools that
/// need a node's configuration without running it (pre-flight).
pub fn resolve_node(
    default_name: &str,
    specs: &[ParamSpec],
    ros_args: &RosArgs,
) -> Result<(NameResolver, Params), RuntimeError> {
    let node_name = ros_args.node_name(default_name);
    let namespace = ros_args.namespace(&node_name, "/");
    let names = NameResolver::new(&node_name, &namespace, &ros_args.remaps)?;
    let mut files = Vec::new();
    for path in &ros_args.params_files {
        let text = std::fs::read_to_string(path).map_err(|e| RuntimeError::ParamsFile {
            path: path.clone(),
            problem: e.to_string(),
        })?;
        files.push((path.clone(), text));
    }
    let params = Params::resolve(
        specs,
        &names.fully_qualified_node_name(),
        &files,
        &ros_args.params,
    )?;
    Ok((names, params))
}

impl CellNode {
    /// Start a node that takes nothing but ROS arguments from its command line `argv`
    /// (without the program name): anything else is an error.
    pub fn start_from_argv(
        default_name: &str,
        specs: &[ParamSpec],
        argv: &[String],
    ) -> Result<CellNode, RuntimeError> {
        let (ros_args, rest) = RosArgs::parse(argv)?;
        if !rest.is_empty() {
            return Err(crate::args::ArgsError::Unexpected(rest).into());
        }
        Self::start(default_name, specs, &ros_args)
    }

    /// Create the node `default_name` (subject to `__node`/`__ns` remaps) with its declared
    /// parameters resolved from the ROS command line, on its own DDS participant.
    pub fn start(
        default_name: &str,
        specs: &[ParamSpec],
        ros_args: &RosArgs,
    ) -> Result<CellNode, RuntimeError> {
        let domain_id = domain_id_from_env()?;
        let network = Network::from_env()?;
        let context = make_context(domain_id, &network)?;
        Self::start_in(context, default_name, specs, ros_args)
    }

    /// Like [`CellNode::start`] on a given context.
    pub fn start_in(
        context: Context,
        default_name: &str,
        specs: &[ParamSpec],
        ros_args: &RosArgs,
    ) -> Result<CellNode, RuntimeError> {
        let node_name = ros_args.node_name(default_name);
        let namespace = ros_args.namespace(&node_name, "/");
        let (names, params) = resolve_node(default_name, specs, ros_args)?;
        // Parameters are read at start-up; the validator (which ros2-client also runs on the
        // declarations) accepts exactly the resolved values and refuses any later change.
        let declared: std::collections::BTreeMap<String, ParameterValue> = params
            .iter()
            .map(|(name, value)| (name.clone(), to_ros_parameter(value)))
            .collect();
        let mut options = NodeOptions::new()
            .enable_rosout(ros_args.rosout_logs.unwrap_or(true))
            .allow_undeclared_parameters(false)
            .parameter_validator(Box::new(move |name, value| {
                if declared.get(name) == Some(value) {
                    Ok(())
                } else {
                    Err(format!(
                        "{name} is read at start-up: restart the node with --ros-args -p {name}:=..."
                    ))
                }
            }));
        for (name, value) in params.iter() {
            options = options.declare_parameter(name, to_ros_parameter(value));
        }
        let ros_node_name = NodeName::new(&namespace, &node_name)
            .map_err(|e| RuntimeError::Dds(format!("{e:?}")))?;
        let mut node = context
            .new_node(ros_node_name, options)
            .map_err(|e| RuntimeError::Dds(format!("{e:?}")))?;
        let spinner = node
            .spinner()
            .map_err(|e| RuntimeError::Dds(format!("{e:?}")))?;
        let (exited, exit) = std::sync::mpsc::sync_channel(1);
        std::thread::Builder::new()
            .name(format!("spin {node_name}"))
            .spawn(move || {
                // `spin` consumes the spinner: its endpoints are gone when this is sent.
                let _ = futures::executor::block_on(spinner.spin());
                let _ = exited.send(());
            })
            .map_err(|e| RuntimeError::Dds(e.to_string()))?;
        let diagnostics_topic =
            create_topic::<DiagnosticArray>(&mut node, &names, "/diagnostics", &ros_default_qos())?;
        let diagnostics = node
            .create_publisher(&diagnostics_topic, Some(ros_default_qos()))
            .map_err(|e| RuntimeError::Dds(format!("{e:?}")))?;
        let published = vec![PublishedTopic::new(
            names.resolve("/diagnostics")?,
            diagnostics.acknowledgments(),
        )];
        Ok(CellNode {
            node,
            names,
            params,
            diagnostics,
            published,
            kept: Vec::new(),
            _spinner: SpinnerExit(exit),
            _context: context,
        })
    }

    /// Keep `endpoint` (a publisher, say) alive as long as the node.
    pub fn keep<T: Send + 'static>(&mut self, endpoint: T) {
        self.kept.push(Box::new(endpoint));
    }

    /// What the writers discovered so far on `topic` (resolved as this node's topics are)
    /// offer, one entry per writer. A writer that does not say offers reliable and volatile,
    /// DDS's defaults for a writer.
    pub fn offered(&self, topic: &str) -> Result<Vec<Offered>, RuntimeError> {
        use rustdds::policy::{Durability, Reliability};
        let dds_name = format!("rt{}", self.names.resolve(topic)?);
        Ok(self
            ._context
            .domain_participant()
            .discovered_writers()
            .into_iter()
            .filter(|w| w.publication_topic_data.topic_name == dds_name)
            .map(|w| Offered {
                reliable: !matches!(
                    w.publication_topic_data.reliability,
                    Some(Reliability::BestEffort)
                ),
                transient_local: matches!(
                    w.publication_topic_data.durability,
                    Some(Durability::TransientLocal)
                ),
            })
            .collect())
    }

    /// Fully qualified node name, e.g. `/gcode_streamer`.
    pub fn fully_qualified_name(&self) -> String {
        self.names.fully_qualified_node_name()
    }

    /// A publisher on `topic` (expanded and remapped) with the given QoS.
    pub fn publisher<T: RosMessage>(
        &mut self,
        topic: &str,
        qos: &QosProfile,
    ) -> Result<Publisher<T>, RuntimeError> {
        let t = create_topic::<T>(&mut self.node, &self.names, topic, qos)?;
        let publisher = self
            .node
            .create_publisher(&t, Some(qos.clone()))
            .map_err(|e| RuntimeError::Dds(format!("publisher on {topic}: {e:?}")))?;
        self.published.push(PublishedTopic::new(
            self.names.resolve(topic)?,
            publisher.acknowledgments(),
        ));
        Ok(publisher)
    }

    /// Whether this node's publisher on `topic` (as given to [`CellNode::publisher`]) has
    /// matched a subscription of the node `node_name` (fully qualified), as that node announced
    /// its readers on `ros_discovery_info`.
    pub fn subscribed_by(&self, topic: &str, node_name: &str) -> bool {
        let Ok(resolved) = self.names.resolve(topic) else {
            return false;
        };
        let readers = crate::graph::readers_of(&self.node.external_nodes(), node_name);
        self.published
            .iter()
            .filter(|p| p.topic == resolved)
            .flat_map(|p| p.matched_readers())
            .any(|guid| readers.contains(&ros2_client::Gid::from(guid)))
    }

    /// Waits, at most `max_wait`, until each of `nodes` (fully qualified) subscribes to each
    /// of `topics` this node publishes; returns what is still lacking then, as `topic (node)`.
    /// A volatile writer offers a sample only to the readers it has matched when it writes,
    /// so a node whose first samples must reach a recorder waits for it first.
    pub async fn wait_subscribed(
        // `&mut`: a future holding `&CellNode` across its sleeps would need the node `Sync`.
        &mut self,
        topics: &[&str],
        nodes: &[String],
        max_wait: std::time::Duration,
    ) -> Vec<String> {
        let deadline = std::time::Instant::now() + max_wait;
        loop {
            let lacking: Vec<String> = topics
                .iter()
                .flat_map(|topic| {
                    nodes
                        .iter()
                        .filter(|n| !self.subscribed_by(topic, n))
                        .map(move |n| format!("{topic} ({n})"))
                })
                .collect();
            if lacking.is_empty() || std::time::Instant::now() >= deadline {
                return lacking;
            }
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
    }

    /// Waits, at most `max_wait`, until the matched reliable subscribers of every topic this
    /// node publishes have acknowledged everything it published so far; returns the readers
    /// that had not, named (see [`crate::delivery`]). Call it before the node goes away.
    pub async fn wait_delivered(&self, max_wait: std::time::Duration) -> Vec<Undelivered> {
        wait_delivered(&[self], max_wait).await
    }

    /// A subscription on `topic` (expanded and remapped) with the given QoS.
    pub fn subscription<T: RosMessage>(
        &mut self,
        topic: &str,
        qos: &QosProfile,
    ) -> Result<Subscription<T>, RuntimeError> {
        let t = create_topic::<T>(&mut self.node, &self.names, topic, qos)?;
        self.node
            .create_subscription(&t, Some(qos.clone()))
            .map_err(|e| RuntimeError::Dds(format!("subscription on {topic}: {e:?}")))
    }

    /// `name` (a topic, service or action) expanded and remapped for this node.
    pub fn ros_name(&self, name: &str) -> Result<Name, RuntimeError> {
        ros_name(&self.names, name).map(|(_, parsed)| parsed)
    }

    /// A service server on `service` (expanded and remapped) of type `package/srv/Type`, with
    /// ROS's service QoS (reliable, volatile, keep-last 10) and the given request/reply
    /// mapping: `Cyclone` for rmw_cyclonedds clients, `Enhanced` for rmw_fastrtps ones.
    pub fn service<Req, Resp>(
        &mut self,
        service: &str,
        type_name: (&str, &str),
        mapping: ServiceMapping,
    ) -> Result<ros2_client::Server<Wire<Req>, Wire<Resp>>, RuntimeError>
    where
        Req: serde::Serialize + serde::de::DeserializeOwned + Clone + 'static,
        Resp: serde::Serialize + serde::de::DeserializeOwned + 'static,
    {
        let (resolved, name) = ros_name(&self.names, service)?;
        let qos = ros_default_qos();
        self.node
            .create_server(
                mapping,
                &name,
                &ros2_client::ServiceTypeName::new(type_name.0, type_name.1),
                qos.clone(),
                qos,
            )
            .map_err(|e| RuntimeError::Dds(format!("service {resolved}: {e:?}")))
    }

    /// Publish one diagnostic status for this node on `/diagnostics`.
    pub fn diagnose(&self, level: u8, message: &str, values: &[(&str, String)]) {
        let status = DiagnosticStatus {
            level,
            name: self.fully_qualified_name(),
            message: message.to_string(),
            hardware_id: "polar_cell".to_string(),
            values: values
                .iter()
                .map(|(k, v)| KeyValue {
                    key: k.to_string(),
                    value: v.clone(),
                })
                .collect(),
        };
        let array = DiagnosticArray {
            header: Header {
                stamp: Time::now(),
                frame_id: String::new(),
            },
            status: vec![status],
        };
        if let Err(e) = self.diagnostics.publish(array) {
            tracing::warn!(
                "{}: /diagnostics publish failed: {e:?}",
                self.fully_qualified_name()
            );
        }
    }

    /// Log to `/rosout` (and through `tracing` to stderr) as rclcpp does: under the node's
    /// logger name (`bar.gcode_streamer`), with the source of the call. Use [`crate::cell_log!`],
    /// which fills `site` in where it is written.
    pub fn log_at(&self, level: LogLevel, message: &str, site: LogSite) {
        ros2_client::rosout::RosoutRaw::rosout_raw(
            &self.node,
            ros2_client::builtin_interfaces::Time::now(),
            level,
            &logger_name(&self.fully_qualified_name()),
            message,
            site.file,
            site.function,
            site.line,
        );
    }
}

/// [`CellNode::wait_delivered`] for several nodes at once, under one deadline.
pub async fn wait_delivered(
    nodes: &[&CellNode],
    max_wait: std::time::Duration,
) -> Vec<Undelivered> {
    let Some(first) = nodes.first() else {
        return Vec::new();
    };
    let published: Vec<PublishedTopic> = nodes
        .iter()
        .flat_map(|n| n.published.iter().cloned())
        .collect();
    let lagging = match tokio::task::spawn_blocking(move || {
        crate::delivery::wait_acknowledged(&published, max_wait)
    })
    .await
    {
        Ok(lagging) => lagging,
        Err(e) => {
            tracing::warn!("waiting for acknowledgements failed: {e}");
            return Vec::new();
        }
    };
    crate::delivery::name_readers(&first.node, lagging)
}

/// Where a log call is written: what `/rosout`'s `file`, `line` and `function` carry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LogSite {
    pub file: &'static str,
    pub line: u32,
    pub function: &'static str,
}

/// rclcpp's logger name for a node: its fully qualified name without the leading slash, in
/// dots (`/bar/gcode_streamer` → `bar.gcode_streamer`).
pub fn logger_name(fully_qualified_name: &str) -> String {
    fully_qualified_name
        .trim_start_matches('/')
        .replace('/', ".")
}

/// The function a [`crate::cell_log!`] is written in, from the type name of the marker
/// function it declares there (`crate::module::function::{{closure}}::marker`): the path up
/// to the enclosing named function. Rust has no `__func__`; this is its usual stand-in.
pub fn function_of(marker_type_name: &'static str) -> &'static str {
    let mut path = marker_type_name
        .rsplit_once("::")
        .map_or(marker_type_name, |(head, _)| head);
    while let Some(head) = path.strip_suffix("::{{closure}}") {
        path = head;
    }
    path
}

/// Log to `/rosout` from a node with the caller's file, line and function, as rclcpp's
/// `RCLCPP_INFO(logger, ...)` does: `cell_log!(node, LogLevel::Info, "planned {n} moves")`.
#[macro_export]
macro_rules! cell_log {
    ($node:expr, $level:expr, $($arg:tt)+) => {
        $node.log_at(
            $level,
            &::std::format!($($arg)+),
            $crate::dds::LogSite {
                file: ::std::file!(),
                line: ::std::line!(),
                function: $crate::log_site_function!(),
            },
        )
    };
}

/// The function this is written in (see [`function_of`]): what [`cell_log!`] records.
#[doc(hidden)]
#[macro_export]
macro_rules! log_site_function {
    () => {{
        fn cell_log_site() {}
        $crate::dds::function_of(::std::any::type_name_of_val(&cell_log_site))
    }};
}

/// A message or service payload as ros2-client carries it (its `Message` marker trait, which
/// our message crate does not depend on).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(transparent)]
pub struct Wire<T>(pub T);

impl<T: serde::Serialize + serde::de::DeserializeOwned> ros2_client::Message for Wire<T> {}

/// How a service's requests and replies are paired on the wire.
pub use ros2_client::ServiceMapping;

/// `cyclone` (rmw_cyclonedds: a 16-byte header in the payload), `enhanced` (rmw_fastrtps:
/// the RTPS sample identity) or `basic` (DDS-RPC's in-payload header).
pub fn parse_service_mapping(text: &str) -> Result<ServiceMapping, RuntimeError> {
    match text {
        "cyclone" => Ok(ServiceMapping::Cyclone),
        "enhanced" => Ok(ServiceMapping::Enhanced),
        "basic" => Ok(ServiceMapping::Basic),
        other => Err(RuntimeError::Params(crate::ParamError::Invalid {
            name: "service_mapping".into(),
            problem: format!("`{other}` is not cyclone, enhanced or basic"),
        })),
    }
}

/// `name` expanded and remapped, as text and as ros2-client's `Name`.
fn ros_name(names: &NameResolver, name: &str) -> Result<(String, Name), RuntimeError> {
    let resolved = names.resolve(name)?;
    let parsed =
        Name::parse(&resolved).map_err(|e| RuntimeError::Dds(format!("{resolved}: {e:?}")))?;
    Ok((resolved, parsed))
}

fn create_topic<T: RosMessage>(
    node: &mut Node,
    names: &NameResolver,
    topic: &str,
    qos: &QosProfile,
) -> Result<rustdds::Topic, RuntimeError> {
    let (resolved, name) = ros_name(names, topic)?;
    node.create_topic(
        &name,
        MessageTypeName::new(T::TYPE.package, T::TYPE.name),
        qos,
    )
    .map_err(|e| RuntimeError::Dds(format!("topic {resolved}: {e:?}")))
}

fn to_ros_parameter(v: &ParamValue) -> ParameterValue {
    match v {
        ParamValue::Bool(b) => ParameterValue::Boolean(*b),
        ParamValue::Integer(i) => ParameterValue::Integer(*i),
        ParamValue::Double(d) => ParameterValue::Double(*d),
        ParamValue::String(s) => ParameterValue::String(s.clone()),
        ParamValue::BoolArray(a) => ParameterValue::BooleanArray(a.clone()),
        ParamValue::IntegerArray(a) => ParameterValue::IntegerArray(a.clone()),
        ParamValue::DoubleArray(a) => ParameterValue::DoubleArray(a.clone()),
        ParamValue::StringArray(a) => ParameterValue::StringArray(a.clone()),
    }
}

/// How long the nodes' publications wait for a full send window before it is an error: long
/// enough for a recorder catching up after a million moves.
pub const PUBLISH_PATIENCE: std::time::Duration = std::time::Duration::from_secs(30);

/// Samples readers could not decode, by topic: counted, and said once per topic (a flood of
/// them must not flood the log).
#[derive(Debug, Default)]
pub struct Undecodable {
    counts: std::collections::BTreeMap<String, u64>,
}

impl Undecodable {
    /// What a reader took: the sample, or `None` for one it could not decode (another build's
    /// layout, a truncated or forged sample: any participant on the domain can write one),
    /// counted. The reader has moved past it, so one bad sample must not end a node (a
    /// machine ended mid-print); the reader's other errors (its DDS threads failed, it was
    /// closed) remain errors.
    pub fn take<T>(
        &mut self,
        node: &CellNode,
        topic: &str,
        taken: ros2_client::ReadResult<T>,
    ) -> Result<Option<T>, RuntimeError> {
        use ros2_client::ReadError;
        match taken {
            Ok(sample) => Ok(Some(sample)),
            Err(e @ (ReadError::Deserialization { .. } | ReadError::Malformed)) => {
                let count = self.counts.entry(topic.to_string()).or_default();
                *count += 1;
                if *count == 1 {
                    crate::cell_log!(
                        node,
                        LogLevel::Warn,
                        "ignored a {topic} sample that cannot be decoded ({e}); any more are counted in diagnostics"
                    );
                }
                Ok(None)
            }
            Err(e) => Err(RuntimeError::Dds(format!("reading {topic}: {e}"))),
        }
    }

    /// Undecodable samples so far, all topics.
    pub fn total(&self) -> u64 {
        self.counts.values().sum()
    }
}

/// Publish, waiting while the reliable send window is full (back-pressure from a slow
/// subscriber is not an error); gives up after `patience`.
pub async fn publish<T: RosMessage>(
    publisher: &Publisher<T>,
    message: T,
    patience: std::time::Duration,
) -> Result<(), RuntimeError> {
    let deadline = std::time::Instant::now() + patience;
    let mut pending = message;
    loop {
        match publisher.publish(pending) {
            Ok(()) => return Ok(()),
            Err(ros2_client::ros2::WriteError::WouldBlock { data })
                if std::time::Instant::now() < deadline =>
            {
                pending = data;
                tokio::time::sleep(std::time::Duration::from_millis(1)).await;
            }
            Err(ros2_client::ros2::WriteError::WouldBlock { .. }) => {
                return Err(RuntimeError::Dds(format!(
                    "publishing a {}: the send window stayed full for {patience:?} \
                     (a subscriber is not acknowledging)",
                    T::TYPE.full_name()
                )))
            }
            Err(e) => {
                return Err(RuntimeError::Dds(format!(
                    "publishing a {}: {e}",
                    T::TYPE.full_name()
                )))
            }
        }
    }
}

/// Every SIGINT and SIGTERM the process gets, counted from creation on: unlike calling
/// [`shutdown_signal`] in a loop, a second Ctrl-C that comes while the first is being handled
/// is not lost (a job's second Ctrl-C is its emergency stop).
pub struct ShutdownSignals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
}

impl ShutdownSignals {
    pub fn new() -> std::io::Result<ShutdownSignals> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(ShutdownSignals {
            interrupt: signal(SignalKind::interrupt())?,
            terminate: signal(SignalKind::terminate())?,
        })
    }

    /// The next signal (at once if one came since the last call).
    pub async fn next(&mut self) {
        self.next_kind().await;
    }

    /// The next signal and which it was.
    pub async fn next_kind(&mut self) -> ShutdownSignal {
        tokio::select! {
            _ = self.interrupt.recv() => ShutdownSignal::Interrupt,
            _ = self.terminate.recv() => ShutdownSignal::Terminate,
        }
    }
}

/// Which shutdown signal came.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShutdownSignal {
    /// SIGINT: Ctrl-C, or `ros2 launch` stopping its nodes.
    Interrupt,
    /// SIGTERM: a script, a service manager, a launcher escalating after SIGINT.
    Terminate,
}

/// Resolves when the process gets SIGINT or SIGTERM.
pub async fn shutdown_signal() {
    match ShutdownSignals::new() {
        Ok(mut signals) => signals.next().await,
        Err(_) => {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

/// Nanoseconds since the epoch, for bag log times and stamps.
pub fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn planning_step() -> &'static str {
        crate::log_site_function!()
    }

    #[test]
    fn the_function_is_the_enclosing_named_one_even_inside_closures() {
        assert_eq!(planning_step(), "cell_runtime::dds::tests::planning_step");
        let in_closure = || crate::log_site_function!();
        assert_eq!(
            in_closure(),
            "cell_runtime::dds::tests::the_function_is_the_enclosing_named_one_even_inside_closures"
        );
        let in_async = async { crate::log_site_function!() };
        let waker = std::task::Waker::noop();
        let mut cx = std::task::Context::from_waker(waker);
        let mut in_async = std::pin::pin!(in_async);
        assert_eq!(
            std::future::Future::poll(in_async.as_mut(), &mut cx),
            std::task::Poll::Ready(
                "cell_runtime::dds::tests::the_function_is_the_enclosing_named_one_even_inside_closures"
            )
        );
    }

    #[test]
    fn logger_names_are_rclcpp_s() {
        assert_eq!(logger_name("/gcode_streamer"), "gcode_streamer");
        assert_eq!(logger_name("/bar/gcode_streamer"), "bar.gcode_streamer");
        assert_eq!(logger_name("/a/b/planner"), "a.b.planner");
    }
}
