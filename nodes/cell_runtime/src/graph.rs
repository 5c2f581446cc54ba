//! Who is who in the ROS graph, from `ros_discovery_info`.
//!
//! Every ROS 2 participant announces its nodes on `ros_discovery_info` (rmw_dds_common's
//! ParticipantEntitiesInfo), each with the GIDs of its readers and writers. That is how
//! `ros2 node info` knows which node a publisher belongs to, and how the cell decides whether
//! a flow-control acknowledgement really comes from the consumer node it names: only a
//! writer that its *own* participant announced as that node's is believed. A participant can
//! still lie about its own nodes — without DDS Security nothing on the wire is authenticated
//! (see docs/design/threat-model.md) — but it can no longer speak for another participant's
//! node, and a plain DDS application that announces nothing cannot speak for any.

use ros2_client::{entities_info::NodeEntitiesInfo, Gid};

/// The first 12 bytes of an RTPS GUID name its participant.
const PREFIX_LEN: usize = 12;

/// The process a writer belongs to, as a number: its participant (the first 12 bytes of its
/// GUID). A restarted node comes back as another one.
pub fn process_of(gid: &Gid) -> u128 {
    prefix(gid)
        .iter()
        .fold(0u128, |acc, b| (acc << 8) | u128::from(*b))
}

fn prefix(gid: &Gid) -> [u8; PREFIX_LEN] {
    gid.as_bytes()[..PREFIX_LEN]
        .try_into()
        .expect("a GUID is 16 bytes")
}

/// Whether `writer` was announced as a writer of the node `node_name` (fully qualified, e.g.
/// `/bag_recorder`) by the participant `writer` belongs to. `announced` is what the
/// participants announced, by participant GID ([`ros2_client::Node::external_nodes`]).
pub fn is_writer_of(
    announced: &[(Gid, Vec<NodeEntitiesInfo>)],
    node_name: &str,
    writer: &Gid,
) -> bool {
    announced
        .iter()
        .filter(|(participant, _)| prefix(participant) == prefix(writer))
        .flat_map(|(_, nodes)| nodes)
        .any(|node| node.fully_qualified_name() == node_name && node.writer_gids().contains(writer))
}

/// The readers the node `node_name` (fully qualified) announced, from every participant that
/// announced a node of that name.
pub fn readers_of(announced: &[(Gid, Vec<NodeEntitiesInfo>)], node_name: &str) -> Vec<Gid> {
    announced
        .iter()
        .flat_map(|(_, nodes)| nodes)
        .filter(|node| node.fully_qualified_name() == node_name)
        .flat_map(|node| node.reader_gids().iter().copied())
        .collect()
}

/// The node (fully qualified) that announced `reader` among its readers: what to call a
/// subscriber in a log line.
pub fn node_of_reader(announced: &[(Gid, Vec<NodeEntitiesInfo>)], reader: &Gid) -> Option<String> {
    announced
        .iter()
        .flat_map(|(_, nodes)| nodes)
        .find(|node| node.reader_gids().contains(reader))
        .map(|node| node.fully_qualified_name())
}

/// The nodes (fully qualified) that announced `writer` among their writers, from its own
/// participant's announcement: what to call a sender in a log line.
pub fn nodes_of_writer(announced: &[(Gid, Vec<NodeEntitiesInfo>)], writer: &Gid) -> Vec<String> {
    announced
        .iter()
        .filter(|(participant, _)| prefix(participant) == prefix(writer))
        .flat_map(|(_, nodes)| nodes)
        .filter(|node| node.writer_gids().contains(writer))
        .map(|node| node.fully_qualified_name())
        .collect()
}

/// The writers a node believes on a flow-controlled link, by the node each must speak for
/// (an acknowledgement in the name of a consumer, a move from the producer): writers that
/// their own participant announced as that node's ([`is_writer_of`]). A writer once found is
/// remembered; for one not (yet) announced, the graph is looked up again at most every
/// [`Sources::LOOKUP_PERIOD`], so a flood of forged messages costs no more than that.
#[derive(Debug, Default)]
pub struct Sources {
    /// Writers found, each with the nodes it was found to speak for (looked up without
    /// allocating: this runs for every message).
    verified: std::collections::BTreeMap<Gid, Vec<String>>,
    snapshot: Vec<(Gid, Vec<NodeEntitiesInfo>)>,
    looked_up: Option<std::time::Duration>,
}

impl Sources {
    /// How often the announcements are read again for a writer not yet found in them.
    pub const LOOKUP_PERIOD: std::time::Duration = std::time::Duration::from_millis(50);

    pub fn new() -> Sources {
        Sources::default()
    }

    /// Whether `writer` speaks for `node_name` at `now` (any monotonic clock), `announced`
    /// giving the graph's announcements when they need reading.
    pub fn admits(
        &mut self,
        node_name: &str,
        writer: Gid,
        now: std::time::Duration,
        announced: impl FnOnce() -> Vec<(Gid, Vec<NodeEntitiesInfo>)>,
    ) -> bool {
        if self
            .verified
            .get(&writer)
            .is_some_and(|nodes| nodes.iter().any(|n| n == node_name))
        {
            return true;
        }
        if self
            .looked_up
            .is_none_or(|at| now.saturating_sub(at) >= Self::LOOKUP_PERIOD)
        {
            self.snapshot = announced();
            self.looked_up = Some(now);
        }
        let admitted = is_writer_of(&self.snapshot, node_name, &writer);
        if admitted {
            (self.verified.entry(writer).or_default()).push(node_name.to_string());
        }
        admitted
    }
}

/// Which process a producer's messages come from, by the participant (the first 12 bytes of
/// every writer's GUID): a node restarted mid-stream comes back as a new participant, and
/// what it sends then does not continue what its first run sent (a planner's clock starts
/// again, a screw driver pairs moves anew). The consumer notices it here and says so.
///
/// A restarted node that sends nothing (a screw driver that cannot pair what it receives)
/// is noticed by its announcement: [`ProducerProcess::announced_elsewhere`]. Kept by each
/// [`Producer`].
#[derive(Debug, Default)]
struct ProducerProcess {
    first: Option<[u8; PREFIX_LEN]>,
    /// Other participants that announced the producer's name when first looked at (a
    /// previous print's node not yet gone from discovery): not a restart.
    baseline: Option<Vec<[u8; PREFIX_LEN]>>,
}

impl ProducerProcess {
    fn new() -> ProducerProcess {
        ProducerProcess::default()
    }

    /// Note a message `writer` sent for the producer: false when it comes from another
    /// participant than the producer's first message did.
    fn same(&mut self, writer: &Gid) -> bool {
        let participant = prefix(writer);
        *self.first.get_or_insert(participant) == participant
    }

    /// Whether the producer's first message came and the announcements were not looked at
    /// since: look at once, so that a quick restart is not taken for the baseline.
    fn needs_baseline(&self) -> bool {
        self.first.is_some() && self.baseline.is_none()
    }

    /// Whether, since the first look after the producer's first message, a participant
    /// other than that message's has announced a node named `name` (fully qualified): the
    /// producer restarted, or a second one started. `announced` as in [`is_writer_of`].
    fn announced_elsewhere(
        &mut self,
        announced: &[(Gid, Vec<NodeEntitiesInfo>)],
        name: &str,
    ) -> bool {
        let Some(first) = self.first else {
            return false;
        };
        let others: Vec<[u8; PREFIX_LEN]> = announced
            .iter()
            .filter(|(participant, nodes)| {
                prefix(participant) != first
                    && nodes.iter().any(|n| n.fully_qualified_name() == name)
            })
            .map(|(participant, _)| prefix(participant))
            .collect();
        let baseline = self.baseline.get_or_insert_with(|| others.clone());
        others.iter().any(|p| !baseline.contains(p))
    }
}

/// A consumer's view of its link's producer: it takes moves and progress reports only from
/// writers of the producer node (`producer`, by default `gcode_streamer` in the consumer's
/// namespace). Without acknowledgements (replaying a bag) there is no producer to check.
pub struct Producer {
    name: String,
    check: bool,
    sources: Sources,
    /// The graph as the consumer's node sees it, and the clock of [`Sources`]' lookups.
    announced: ros2_client::ExternalNodes,
    started: std::time::Instant,
    process: ProducerProcess,
}

impl Producer {
    /// The `producer` parameter every consumer of `/gcode/moves` declares.
    pub fn param_spec() -> crate::ParamSpec {
        crate::ParamSpec::new(
            "producer",
            crate::ParamValue::String("gcode_streamer".into()),
            "the node whose /gcode/moves and /gcode/progress this consumer takes (relative: in \
             its namespace); other writers are ignored",
        )
    }

    /// A parameter `param` naming the node whose writes a node takes, as `description`
    /// says (an empty name takes every writer's, e.g. a bag replayed into the node).
    pub fn named_param_spec(
        param: &'static str,
        default: &str,
        description: &'static str,
    ) -> crate::ParamSpec {
        crate::ParamSpec::new(
            param,
            crate::ParamValue::String(default.into()),
            description,
        )
    }

    /// The producer that `node`'s `producer` parameter names; `check` false takes every
    /// writer (no flow control).
    pub fn of(node: &crate::CellNode, check: bool) -> Result<Producer, crate::RuntimeError> {
        Self::named(node, "producer", check)
    }

    /// The producer that `node`'s parameter `param` names; `check` false, or an empty name,
    /// takes every writer.
    pub fn named(
        node: &crate::CellNode,
        param: &str,
        check: bool,
    ) -> Result<Producer, crate::RuntimeError> {
        let name = node.params.string(param);
        Ok(Producer {
            check: check && !name.is_empty(),
            name: match name.is_empty() {
                true => String::new(),
                false => node.names.resolve(name)?,
            },
            sources: Sources::new(),
            announced: node.node.external_nodes_view(),
            started: std::time::Instant::now(),
            process: ProducerProcess::new(),
        })
    }

    /// The producer's fully qualified name (empty: any writer is taken).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Whether a message it admitted (that came with `info`) comes from another process
    /// than the producer's first message did: the producer restarted. Never for a producer
    /// not checked (no name given).
    pub fn restarted(&mut self, info: &ros2_client::MessageInfo) -> bool {
        self.check && !self.process.same(&info.publisher_gid())
    }

    /// Take the process of the message that came with `info` as the producer's from now on: a
    /// restarted producer that continues what its first process began (a resumed planner).
    /// The announcements are looked at afresh, with the old process among what was there.
    pub fn adopt(&mut self, info: &ros2_client::MessageInfo) {
        self.process = ProducerProcess::new();
        self.process.same(&info.publisher_gid());
    }

    /// Whether the producer's first message came and the graph was not looked at since
    /// ([`Producer::announced_elsewhere`] at once, so that a quick restart is not taken for
    /// what was there before).
    pub fn needs_look(&self) -> bool {
        self.check && self.process.needs_baseline()
    }

    /// Whether, since the first look after its first message, another participant than that
    /// message's has announced the producer's node: it restarted without sending anything
    /// yet (or a second one started). Never for a producer not checked.
    pub fn announced_elsewhere(&mut self) -> bool {
        self.check
            && self
                .process
                .announced_elsewhere(&self.announced.get(), &self.name)
    }

    /// Whether a message that came with `info` comes from the producer.
    pub fn admits(&mut self, info: &ros2_client::MessageInfo) -> bool {
        !self.check
            || self.sources.admits(
                &self.name,
                info.publisher_gid(),
                self.started.elapsed(),
                || self.announced.get(),
            )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::NodeName;

    fn gid(participant: u8, entity: u8) -> Gid {
        let mut bytes = [0u8; 16];
        bytes[..12].fill(participant);
        bytes[15] = entity;
        Gid::from(bytes)
    }

    /// The first participant is the producer's; another writer of it is the same process,
    /// another participant a restart (and stays one).
    #[test]
    fn a_producer_from_another_participant_is_a_restart() {
        let mut process = ProducerProcess::new();
        assert!(process.same(&gid(1, 3)));
        assert!(
            process.same(&gid(1, 4)),
            "another writer of the same process"
        );
        assert!(!process.same(&gid(2, 3)), "a new participant");
        assert!(process.same(&gid(1, 3)));
        assert!(!process.same(&gid(2, 3)));
    }

    /// A restart is also seen in the announcements: a participant that was not announcing
    /// the producer when first looked at, and is not the first message's, announces it.
    #[test]
    fn a_producer_announced_by_a_new_participant_is_a_restart() {
        let planner = |participant: u8| {
            (
                gid(participant, 1),
                vec![node("polar_planner", &[gid(participant, 3)])],
            )
        };
        let mut process = ProducerProcess::new();
        // Nothing before the first message.
        assert!(!process.announced_elsewhere(&[planner(1), planner(2)], "/polar_planner"));
        assert!(!process.needs_baseline());
        assert!(process.same(&gid(1, 3)));
        assert!(process.needs_baseline());
        // A stale announcement of a previous run (participant 2) is the baseline.
        assert!(!process.announced_elsewhere(&[planner(1), planner(2)], "/polar_planner"));
        assert!(!process.needs_baseline());
        assert!(!process.announced_elsewhere(&[planner(1)], "/polar_planner"));
        // Another node's name from a new participant is not the producer.
        let streamer = (gid(4, 1), vec![node("gcode_streamer", &[gid(4, 3)])]);
        assert!(!process.announced_elsewhere(&[planner(1), streamer], "/polar_planner"));
        // The producer from a new participant (the first one gone or not) is a restart.
        assert!(process.announced_elsewhere(&[planner(3)], "/polar_planner"));
        assert!(process.announced_elsewhere(&[planner(1), planner(3)], "/polar_planner"));
    }

    fn node(name: &str, writers: &[Gid]) -> NodeEntitiesInfo {
        let mut info = NodeEntitiesInfo::new(NodeName::new("/", name).unwrap());
        for w in writers {
            info.add_writer(*w);
        }
        info
    }

    #[test]
    fn a_writer_belongs_to_a_node_only_by_its_own_participants_word() {
        let recorder_ack = gid(1, 7);
        let foreign_ack = gid(2, 9);
        let announced = vec![
            (gid(1, 0xc1), vec![node("bag_recorder", &[recorder_ack])]),
            // Participant 2 claims participant 1's writer for its own node of the same name,
            // and its own writer for a node it does host.
            (
                gid(2, 0xc1),
                vec![
                    node("bag_recorder", &[recorder_ack]),
                    node("spy", &[foreign_ack]),
                ],
            ),
        ];
        assert!(is_writer_of(&announced, "/bag_recorder", &recorder_ack));
        assert!(!is_writer_of(&announced, "/polar_planner", &recorder_ack));
        assert!(!is_writer_of(&announced, "/bag_recorder", &foreign_ack));
        assert!(is_writer_of(&announced, "/spy", &foreign_ack));
        // Announced by nobody: a plain DDS participant.
        assert!(!is_writer_of(&announced, "/bag_recorder", &gid(3, 7)));
        assert_eq!(
            nodes_of_writer(&announced, &recorder_ack),
            ["/bag_recorder"]
        );
        assert_eq!(nodes_of_writer(&announced, &foreign_ack), ["/spy"]);
        assert!(nodes_of_writer(&announced, &gid(3, 7)).is_empty());
        assert!(!is_writer_of(&[], "/bag_recorder", &recorder_ack));
        let mut planner = node("polar_planner", &[]);
        planner.add_reader(gid(1, 3));
        planner.add_reader(gid(1, 4));
        let announced = vec![(gid(1, 0xc1), vec![planner, node("bag_recorder", &[])])];
        assert_eq!(
            readers_of(&announced, "/polar_planner"),
            [gid(1, 3), gid(1, 4)]
        );
        assert!(readers_of(&announced, "/bag_recorder").is_empty());
        assert!(readers_of(&announced, "/nobody").is_empty());
        assert_eq!(
            node_of_reader(&announced, &gid(1, 4)).as_deref(),
            Some("/polar_planner")
        );
        assert_eq!(node_of_reader(&announced, &gid(3, 4)), None);
    }

    #[test]
    fn sources_believe_announced_writers_and_read_the_graph_at_most_every_50_ms() {
        let ms = std::time::Duration::from_millis;
        let recorder_ack = gid(1, 7);
        let mut announced = vec![];
        let mut lookups = 0;
        let mut sources = Sources::new();
        let ask = |sources: &mut Sources, at: u64, announced: &Vec<_>, lookups: &mut u32| {
            sources.admits("/bag_recorder", recorder_ack, ms(at), || {
                *lookups += 1;
                announced.clone()
            })
        };
        // Not announced yet (discovery is still on its way): refused.
        assert!(!ask(&mut sources, 0, &announced, &mut lookups));
        announced.push((gid(1, 0xc1), vec![node("bag_recorder", &[recorder_ack])]));
        // Within 50 ms of the last look: refused without looking again.
        assert!(!ask(&mut sources, 49, &announced, &mut lookups));
        assert_eq!(lookups, 1);
        assert!(ask(&mut sources, 50, &announced, &mut lookups));
        assert_eq!(lookups, 2);
        // Remembered: no more lookups, even once the announcement is gone.
        announced.clear();
        assert!(ask(&mut sources, 51, &announced, &mut lookups));
        assert_eq!(lookups, 2);
        // The same writer for another node is another question.
        assert!(!sources.admits("/polar_planner", recorder_ack, ms(200), Vec::new));
    }
}
