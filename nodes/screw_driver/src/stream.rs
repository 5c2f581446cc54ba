//! The screw driver's work as a stream, without I/O: moves and their planned trajectories in,
//! chunks of numbered screw commands out, and after every chunk a [`Checkpoint`] from which a
//! restarted driver continues the very same commands.
//!
//! # Pairing
//!
//! The planner publishes exactly one trajectory per move, in order, so the k-th trajectory is
//! the plan of the k-th move; they are paired whichever arrives first. Every trajectory must
//! start where the one before it ended: a lost one would shift every later pairing, so it is
//! refused ([`StreamError::Discontinuous`]).
//!
//! # Chunks
//!
//! Commands are computed per chunk of paired moves ([`Stream::cut`]): when the buffer holds
//! more than `max_buffer_s` of plan or `max_buffer_moves` moves, when input pauses (at a
//! closed-pin gap of at least the pin's opening delay, so no opening reaches back before the
//! cut), or everything at the end. Each published command carries the next number of the
//! stream (`ScrewCommand::sequence`), so a consumer sees a lost command as a gap and a
//! restarted driver's repeats by their numbers.
//!
//! # Restart
//!
//! What a chunk leaves behind for the next — the pin and the modelled flow, the repeat filter,
//! the screw angle, the last stamp and command number, where the tool is — is the
//! [`Checkpoint`]; it belongs to the first move not yet commanded
//! ([`Stream::commanded_until`]), which is what the node acknowledges. A stream resumed from
//! it ([`Stream::resume`]) is given the moves from there on again (the streamer resends them)
//! and trajectories from somewhat earlier (the planner's transient-local history): it drops
//! those up to where its last chunk ended, counting zero-time plans at that instant, and then
//! produces the commands an uninterrupted stream would have.

use std::collections::VecDeque;

use polar_cell_msgs::checkpoint::{self, CheckpointHeader, ResumeStateError};
use polar_cell_msgs::{
    GcodeMove, Header, JointState, JointTrajectory, ScrewCommand, Time, TIMELINE_TOLERANCE_NS,
};
use serde::{Deserialize, Serialize};

use crate::compensation::CompensatorState;
use crate::joint::{Hold, ScrewAngle, ScrewSample, ScrewSamples};
use crate::screw::{
    chunk_commands, position_after, Command, PinState, RepeatFilter, RpmModel, ScrewOptions,
    TimedMove,
};

/// The screw's joint in `urdf/polar_cell.urdf`.
pub const SCREW_JOINT: &str = "screw";

/// How the stream is set up.
#[derive(Clone, Debug, PartialEq)]
pub struct StreamOptions {
    pub screw: ScrewOptions,
    /// Without smoothing: 0 publishes the exact breakpoints; > 0 resamples onto this grid.
    pub command_period_s: f64,
    /// Plan-time period of the screw joint's planned samples (0: none).
    pub joint_state_period_s: f64,
    /// A chunk is cut once this much plan (s) is buffered…
    pub max_buffer_s: f64,
    /// …or this many moves. It must stay below the streamer's window: moves are acknowledged
    /// only once commanded, so a chunk that needs more than the window would wait for ever.
    pub max_buffer_moves: usize,
}

/// How the published commands run between each other: raw breakpoints are linear, smoothed
/// or resampled commands are held.
pub fn command_hold(options: &ScrewOptions, command_period_s: f64) -> Hold {
    if options.smoothing.is_some() || command_period_s > 0.0 || options.compensation.is_some() {
        Hold::ZeroOrder
    } else {
        Hold::FirstOrder
    }
}

/// The rpm model's name, as commands carry it.
pub fn model_name(options: &ScrewOptions) -> &'static str {
    match options.model {
        RpmModel::PolarSpeed { .. } => "polar_speed",
        RpmModel::Radius { .. } => "radius",
    }
}

/// A command as its message, stamped on the plan timeline starting at `base_ns` (its
/// `sequence` is the stream's to fill in).
pub fn command_message(c: &Command, options: &ScrewOptions, base_ns: i64) -> ScrewCommand {
    ScrewCommand {
        header: Header {
            stamp: Time::after(base_ns, c.t),
            frame_id: String::new(),
        },
        rpm: c.rpm,
        pin_open: c.pin_open,
        source_line: c.source_line,
        model: model_name(options).to_string(),
        sequence: 0,
    }
}

/// The `screw` joint's state (the planner publishes the stage's joints on the same topic).
pub fn joint_state_message(s: &ScrewSample, base_ns: i64) -> JointState {
    JointState {
        header: Header {
            stamp: Time::after(base_ns, s.t),
            frame_id: String::new(),
        },
        name: vec![SCREW_JOINT.to_string()],
        position: vec![s.angle_rad],
        velocity: vec![s.velocity_rad_per_s],
        effort: vec![],
    }
}

/// Which chunk to cut ([`Stream::cut`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cut {
    /// Only a full buffer: at its last closed-pin gap, or (a long run without one) all of it.
    IfFull,
    /// Input paused: at the last closed-pin gap (or all of a full buffer).
    AtGap,
    /// Everything buffered, the pin left as the plan has it, for a file that goes on: the
    /// producer waits for this driver's acknowledgement before it sends more (its window is
    /// full), or input paused (without flow compensation) or stalled.
    Now,
    /// Everything buffered, the pin closed after the last move: the input is finished.
    All,
}

/// One chunk's output, in publishing order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Chunk {
    pub commands: Vec<ScrewCommand>,
    pub joint_states: JointStates,
}

/// A chunk's screw joint states, made one at a time as they are taken: a long dwell has
/// millions of them (a 10-hour `G4` held 1.8 million here, 0.7 GB with the planner's).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JointStates {
    samples: Option<ScrewSamples>,
    base_ns: i64,
}

impl Iterator for JointStates {
    type Item = JointState;

    fn next(&mut self) -> Option<JointState> {
        let sample = self.samples.as_mut()?.next()?;
        Some(joint_state_message(&sample, self.base_ns))
    }
}

/// What became of a trajectory ([`Stream::on_trajectory`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Taken {
    /// Buffered for its move.
    Kept,
    /// The plan of a move commanded before the checkpoint this stream resumed from.
    BeforeResume,
}

/// Why the stream cannot go on.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum StreamError {
    #[error(
        "/polar/trajectory is not continuous: a plan starts at {start_ns} ns, the one before \
         ended at {previous_end_ns} ns ({:+.6} s): a plan was lost, and pairing the moves after \
         it would misplace every one",
        (*start_ns - *previous_end_ns) as f64 * 1e-9
    )]
    Discontinuous { start_ns: i64, previous_end_ns: i64 },
}

/// A paired move waiting for its chunk.
#[derive(Clone, Debug)]
struct Buffered {
    timed: TimedMove,
    /// Where the tool was before it.
    from_m: [f64; 3],
    /// Its trajectory's place on the timeline (ns).
    span_ns: (i64, i64),
}

/// What one chunk leaves for the next: the checkpoint's content.
#[derive(Clone, Debug, PartialEq)]
struct Carried {
    /// The first move not commanded yet.
    next_sequence: u64,
    /// Where the tool is before it.
    from_m: [f64; 3],
    pin: PinState,
    /// Stamp of plan time 0 of the commands (the first trajectory's stamp).
    base_ns: Option<i64>,
    /// Stamp of the last command published: stamps never go back.
    last_stamp_ns: i64,
    next_command: u64,
    repeats: RepeatFilter,
    angle: Option<ScrewAngle>,
    /// End of the last commanded move's trajectory, and how many zero-time plans end there
    /// after the last one that takes time.
    commanded_end_ns: Option<i64>,
    zero_time_at_end: u32,
}

/// Trajectories to drop after a resume: those of moves already commanded.
#[derive(Clone, Copy, Debug)]
struct Skip {
    end_ns: i64,
    zero_time_left: u32,
}

/// Moves and trajectories in, commands out.
#[derive(Debug)]
pub struct Stream {
    options: StreamOptions,
    hold: Hold,
    digest: u64,
    moves: VecDeque<GcodeMove>,
    plans: VecDeque<JointTrajectory>,
    timed: VecDeque<Buffered>,
    /// Where the tool is after the last paired move, and the move after it.
    paired_from_m: [f64; 3],
    paired_until: u64,
    /// End of the last trajectory kept (ns).
    last_end_ns: Option<i64>,
    skip: Option<Skip>,
    carried: Carried,
}

impl Stream {
    /// A stream from the start of a print.
    pub fn new(options: StreamOptions) -> Stream {
        let hold = command_hold(&options.screw, options.command_period_s);
        let angle = (options.joint_state_period_s > 0.0)
            .then(|| ScrewAngle::new(options.joint_state_period_s, hold));
        Stream {
            digest: options_digest(&options),
            hold,
            moves: VecDeque::new(),
            plans: VecDeque::new(),
            timed: VecDeque::new(),
            paired_from_m: [0.0; 3],
            paired_until: 0,
            last_end_ns: None,
            skip: None,
            carried: Carried {
                next_sequence: 0,
                from_m: [0.0; 3],
                pin: PinState::default(),
                base_ns: None,
                last_stamp_ns: i64::MIN,
                next_command: 0,
                repeats: RepeatFilter::default(),
                angle,
                commanded_end_ns: None,
                zero_time_at_end: 0,
            },
            options,
        }
    }

    /// A stream that continues from `checkpoint` (read with [`Checkpoint::from_bytes`]
    /// against this stream's [`Stream::options_digest`]).
    pub fn resume(options: StreamOptions, checkpoint: &Checkpoint) -> Stream {
        let mut stream = Stream::new(options);
        let c = checkpoint;
        let angle = stream.carried.angle.take().map(|mut a| {
            a.restore(
                c.angle_has_last.then_some((
                    Command {
                        t: c.angle_last_t_s,
                        rpm: c.angle_last_rpm,
                        pin_open: c.angle_last_pin_open,
                        source_line: c.angle_last_source_line,
                        sequence: c.angle_last_sequence,
                    },
                    c.angle_last_rad,
                )),
                c.angle_origin_t_s,
                c.angle_next_index,
            );
            a
        });
        stream.carried = Carried {
            next_sequence: c.header.next_sequence,
            from_m: c.from_m,
            pin: PinState {
                extruding: c.pin_extruding,
                closed_at: c.pin_closed_at_s,
                retracted_m: c.retracted_m,
                last_breakpoint: c
                    .has_last_breakpoint
                    .then_some((c.last_breakpoint_t_s, c.last_breakpoint_rpm)),
                delivery: CompensatorState {
                    flow_rpm: c.flow_rpm,
                    t_s: c.flow_t_s,
                    command_rpm: c.flow_command_rpm,
                    owed_rpm_s: c.flow_owed_rpm_s,
                    pin_open: c.flow_pin_open,
                    valve_open: c.flow_valve_open,
                    opened_at_s: c.flow_opened_at_s,
                },
            },
            base_ns: c.has_base.then_some(c.base_ns),
            last_stamp_ns: c.last_stamp_ns,
            next_command: c.next_command,
            repeats: RepeatFilter::with_last_kept(c.repeat_has_last.then_some((
                c.repeat_rpm,
                c.repeat_pin_open,
                c.repeat_source_line,
            ))),
            angle,
            commanded_end_ns: c.has_commanded_end.then_some(c.commanded_end_ns),
            zero_time_at_end: c.zero_time_at_end,
        };
        stream.paired_from_m = c.from_m;
        stream.paired_until = c.header.next_sequence;
        stream.last_end_ns = stream.carried.commanded_end_ns;
        stream.skip = stream.carried.commanded_end_ns.map(|end_ns| Skip {
            end_ns,
            zero_time_left: c.zero_time_at_end,
        });
        stream
    }

    /// The digest a checkpoint of this stream carries (see [`options_digest`]).
    pub fn options_digest(&self) -> u64 {
        self.digest
    }

    /// Take the next move (in sequence order).
    pub fn on_move(&mut self, m: GcodeMove) {
        self.moves.push_back(m);
        self.pair();
    }

    /// Take the next trajectory (repeats of a restarted planner already dropped).
    pub fn on_trajectory(&mut self, trajectory: JointTrajectory) -> Result<Taken, StreamError> {
        let (start_ns, end_ns) = trajectory.span_ns();
        let near = |a: i64, b: i64| (a - b).abs() <= TIMELINE_TOLERANCE_NS;
        if let Some(skip) = self.skip.as_mut() {
            let earlier = end_ns < skip.end_ns - TIMELINE_TOLERANCE_NS
                || (near(end_ns, skip.end_ns) && start_ns < skip.end_ns - TIMELINE_TOLERANCE_NS);
            if earlier {
                return Ok(Taken::BeforeResume);
            }
            if near(start_ns, skip.end_ns) && near(end_ns, skip.end_ns) && skip.zero_time_left > 0 {
                skip.zero_time_left -= 1;
                return Ok(Taken::BeforeResume);
            }
            self.skip = None;
        }
        if let Some(previous_end_ns) = self.last_end_ns {
            if !near(start_ns, previous_end_ns) {
                return Err(StreamError::Discontinuous {
                    start_ns,
                    previous_end_ns,
                });
            }
        }
        self.last_end_ns = Some(end_ns);
        self.plans.push_back(trajectory);
        self.pair();
        Ok(Taken::Kept)
    }

    fn pair(&mut self) {
        while !self.moves.is_empty() && !self.plans.is_empty() {
            let (m, trajectory) = (
                self.moves.pop_front().expect("not empty"),
                self.plans.pop_front().expect("not empty"),
            );
            if self.carried.base_ns.is_none() {
                // The print's first move starts where the plan starts, which is not the
                // origin when the machine stood elsewhere (a print after a cancel, an MCU
                // that reports its position): the lengths, and so the rpm, count from there.
                if let Some(start) = plan_start_m(&trajectory) {
                    self.paired_from_m = start;
                }
            }
            let base = *self
                .carried
                .base_ns
                .get_or_insert(trajectory.header.stamp.as_nanos());
            let from_m = self.paired_from_m;
            self.timed.push_back(Buffered {
                timed: TimedMove::from_trajectory(&m, from_m, &trajectory, base),
                from_m,
                span_ns: trajectory.span_ns(),
            });
            self.paired_until = m.sequence + 1;
            self.paired_from_m = position_after(&m, from_m);
        }
    }

    /// Every move before it is paired with its plan.
    pub fn paired_until(&self) -> u64 {
        self.paired_until
    }

    /// Every move before it is commanded: what may be acknowledged, with [`Stream::checkpoint`].
    pub fn commanded_until(&self) -> u64 {
        self.carried.next_sequence
    }

    /// This stream continued from `checkpoint`, learnt after it had taken plans: a driver
    /// restarted mid-print may get the planner's history before it learns where to resume.
    /// The resumed stream takes those plans as if they came now.
    pub fn resumed(self, checkpoint: &Checkpoint) -> Result<Stream, StreamError> {
        let mut resumed = Stream::resume(self.options, checkpoint);
        for trajectory in self.plans {
            resumed.on_trajectory(trajectory)?;
        }
        Ok(resumed)
    }

    /// Moves taken that wait for their plan.
    pub fn unpaired_moves(&self) -> usize {
        self.moves.len()
    }

    /// Paired moves waiting for a chunk.
    pub fn buffered_moves(&self) -> usize {
        self.timed.len()
    }

    /// Plan time (s) the buffered moves span.
    pub fn buffered_s(&self) -> f64 {
        match (
            self.timed.front().and_then(|b| b.timed.t.first()),
            self.timed.back().and_then(|b| b.timed.t.last()),
        ) {
            (Some(a), Some(b)) => b - a,
            _ => 0.0,
        }
    }

    /// Where a chunk may end: after the last move that starts a closed-pin gap of at least
    /// the pin's opening delay (so no later opening reaches back into it).
    fn safe_cut(&self) -> Option<usize> {
        let delay = self.options.screw.pin_open_delay_s;
        let mut cut = None;
        let mut gap_start: Option<f64> = None;
        for (i, b) in self.timed.iter().enumerate() {
            let (Some(&t0), Some(&t1)) = (b.timed.t.first(), b.timed.t.last()) else {
                continue;
            };
            if b.timed.extrude {
                gap_start = None;
            } else if t1 > t0 {
                let start = *gap_start.get_or_insert(t0);
                if t1 - start >= delay {
                    cut = Some(i + 1);
                }
            }
        }
        cut
    }

    /// Compute the commands of the chunk `how` asks for, if any; the checkpoint then
    /// belongs to the move after it.
    pub fn cut(&mut self, how: Cut) -> Option<Chunk> {
        if self.timed.is_empty() {
            return if how == Cut::All {
                self.close_at_end()
            } else {
                None
            };
        }
        let full = self.buffered_s() > self.options.max_buffer_s
            || self.timed.len() >= self.options.max_buffer_moves;
        let whole = || Some(self.timed.len());
        let n = match how {
            Cut::All | Cut::Now => whole(),
            Cut::AtGap => self.safe_cut().or(if full { whole() } else { None }),
            Cut::IfFull if full => self.safe_cut().or(whole()),
            Cut::IfFull => None,
        }
        .filter(|&n| n > 0)?;
        let mut moves = Vec::with_capacity(n);
        for b in self.timed.drain(..n) {
            let (start_ns, end_ns) = b.span_ns;
            let c = &mut self.carried;
            if end_ns > start_ns {
                c.commanded_end_ns = Some(end_ns);
                c.zero_time_at_end = 0;
            } else if c.commanded_end_ns == Some(end_ns) {
                c.zero_time_at_end += 1;
            } else {
                c.commanded_end_ns = Some(end_ns);
                c.zero_time_at_end = 1;
            }
            moves.push(b.timed);
        }
        let (next_sequence, from_m) = self
            .timed
            .front()
            .map_or((self.paired_until, self.paired_from_m), |b| {
                (b.timed.sequence, b.from_m)
            });
        let options = &self.options;
        let c = &mut self.carried;
        c.next_sequence = next_sequence;
        c.from_m = from_m;
        let commands = chunk_commands(
            &moves,
            &options.screw,
            &mut c.pin,
            how == Cut::All,
            options.command_period_s,
        );
        Some(self.chunk_of(commands))
    }

    /// Whether the pin is open after the last chunk (a run not yet closed).
    pub fn pin_open(&self) -> bool {
        self.carried.pin.extruding
    }

    /// The input ended inside a run whose moves were all published already (a chunk cut at
    /// a full window or a stall took the last of them): the close the last chunk would have
    /// carried, at the end of what was commanded. Nothing if the pin is closed.
    fn close_at_end(&mut self) -> Option<Chunk> {
        let c = &mut self.carried;
        if !c.pin.extruding {
            return None;
        }
        let end_ns = c.commanded_end_ns?;
        let close = Command {
            t: (end_ns - c.base_ns.unwrap_or(0)) as f64 * 1e-9,
            rpm: 0.0,
            pin_open: false,
            source_line: c.repeats.last_kept().map_or(0, |(_, _, line)| line),
            sequence: c.next_sequence.saturating_sub(1),
        };
        c.pin.extruding = false;
        c.pin.closed_at = close.t;
        c.pin.last_breakpoint = Some((close.t, close.rpm));
        Some(self.chunk_of(vec![close]))
    }

    /// The messages of a chunk's `commands`, numbered and stamped after the last chunk's.
    fn chunk_of(&mut self, commands: Vec<Command>) -> Chunk {
        let options = &self.options;
        let c = &mut self.carried;
        let base = c.base_ns.unwrap_or(0);
        let mut chunk = Chunk::default();
        for command in c.repeats.chunk(&commands, self.hold) {
            let mut message = command_message(command, &options.screw, base);
            // A chunk's first command can round to a nanosecond before the previous chunk's
            // last (its time comes from another sum of the same plan): the same instant,
            // kept in order.
            let stamp_ns = message.header.stamp.as_nanos().max(c.last_stamp_ns);
            message.header.stamp = Time::from_nanos(stamp_ns);
            c.last_stamp_ns = stamp_ns;
            message.sequence = c.next_command;
            c.next_command += 1;
            chunk.commands.push(message);
        }
        if let Some(angle) = c.angle.as_mut() {
            chunk.joint_states = JointStates {
                samples: Some(angle.clone().samples(commands.clone())),
                base_ns: base,
            };
            // The stream's own angle is past the chunk at once: its checkpoint.
            angle.advance(&commands);
        }
        chunk
    }

    /// The state after the last chunk, for the move [`Stream::commanded_until`].
    pub fn checkpoint(&self) -> Checkpoint {
        let c = &self.carried;
        let d = &c.pin.delivery;
        let repeat = c.repeats.last_kept();
        let angle = c.angle.as_ref().and_then(|a| a.last());
        let (origin_t_s, next_index) = c.angle.as_ref().map_or((0.0, 0), |a| a.grid());
        let (last_command, last_rad) = angle.unwrap_or((
            Command {
                t: 0.0,
                rpm: 0.0,
                pin_open: false,
                source_line: 0,
                sequence: 0,
            },
            0.0,
        ));
        Checkpoint {
            header: <Checkpoint as checkpoint::Checkpoint>::header_for(
                c.next_sequence,
                self.digest,
            ),
            has_base: c.base_ns.is_some(),
            base_ns: c.base_ns.unwrap_or(0),
            last_stamp_ns: c.last_stamp_ns,
            next_command: c.next_command,
            from_m: c.from_m,
            pin_extruding: c.pin.extruding,
            pin_closed_at_s: c.pin.closed_at,
            retracted_m: c.pin.retracted_m,
            has_last_breakpoint: c.pin.last_breakpoint.is_some(),
            last_breakpoint_t_s: c.pin.last_breakpoint.map_or(0.0, |b| b.0),
            last_breakpoint_rpm: c.pin.last_breakpoint.map_or(0.0, |b| b.1),
            flow_rpm: d.flow_rpm,
            flow_t_s: d.t_s,
            flow_command_rpm: d.command_rpm,
            flow_owed_rpm_s: d.owed_rpm_s,
            flow_pin_open: d.pin_open,
            flow_valve_open: d.valve_open,
            flow_opened_at_s: d.opened_at_s,
            repeat_has_last: repeat.is_some(),
            repeat_rpm: repeat.map_or(0.0, |r| r.0),
            repeat_pin_open: repeat.is_some_and(|r| r.1),
            repeat_source_line: repeat.map_or(0, |r| r.2),
            angle_has_last: angle.is_some(),
            angle_last_t_s: last_command.t,
            angle_last_rpm: last_command.rpm,
            angle_last_pin_open: last_command.pin_open,
            angle_last_source_line: last_command.source_line,
            angle_last_sequence: last_command.sequence,
            angle_last_rad: last_rad,
            angle_origin_t_s: origin_t_s,
            angle_next_index: next_index,
            has_commanded_end: c.commanded_end_ns.is_some(),
            commanded_end_ns: c.commanded_end_ns.unwrap_or(0),
            zero_time_at_end: c.zero_time_at_end,
        }
    }
}

/// The format this build writes and reads.
pub const CHECKPOINT_FORMAT: u32 = 3;

/// A screw driver's state after every move before `next_sequence` was commanded: the bytes
/// it acknowledges with (CDR, like every message here, led by a format number and a digest of
/// the options that shape the commands). Flat, with flags for what may be absent.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    pub header: CheckpointHeader,
    pub has_base: bool,
    pub base_ns: i64,
    pub last_stamp_ns: i64,
    pub next_command: u64,
    pub from_m: [f64; 3],
    pub pin_extruding: bool,
    pub pin_closed_at_s: f64,
    pub retracted_m: f64,
    pub has_last_breakpoint: bool,
    pub last_breakpoint_t_s: f64,
    pub last_breakpoint_rpm: f64,
    pub flow_rpm: f64,
    pub flow_t_s: f64,
    pub flow_command_rpm: f64,
    pub flow_owed_rpm_s: f64,
    pub flow_pin_open: bool,
    pub flow_valve_open: bool,
    pub flow_opened_at_s: f64,
    pub repeat_has_last: bool,
    pub repeat_rpm: f64,
    pub repeat_pin_open: bool,
    pub repeat_source_line: u32,
    pub angle_has_last: bool,
    pub angle_last_t_s: f64,
    pub angle_last_rpm: f64,
    pub angle_last_pin_open: bool,
    pub angle_last_source_line: u32,
    pub angle_last_sequence: u64,
    pub angle_last_rad: f64,
    pub angle_origin_t_s: f64,
    pub angle_next_index: u64,
    pub has_commanded_end: bool,
    pub commanded_end_ns: i64,
    pub zero_time_at_end: u32,
}

/// Why acknowledged bytes are not a checkpoint this screw driver can continue from.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CheckpointError {
    #[error(transparent)]
    State(#[from] ResumeStateError),
    #[error("resume state holds a value that is not a screw state: {0}")]
    NotAScrewState(String),
}

impl checkpoint::Checkpoint for Checkpoint {
    const FORMAT: u32 = CHECKPOINT_FORMAT;
    const WRITER: &'static str = "screw driver";
    const OTHER_OPTIONS_WOULD: &'static str = "it would command another screw";
    fn header(&self) -> &CheckpointHeader {
        &self.header
    }
}

impl Checkpoint {
    pub fn to_bytes(&self) -> Vec<u8> {
        checkpoint::to_bytes(self)
    }

    /// Read the checkpoint acknowledged at `resume_point` by a screw driver whose options
    /// have `options_digest`, refusing anything else.
    pub fn from_bytes(
        bytes: &[u8],
        resume_point: u64,
        options_digest: u64,
    ) -> Result<Checkpoint, CheckpointError> {
        let c: Checkpoint = checkpoint::from_bytes(bytes, resume_point, options_digest)?;
        // The pin's closing time may be −∞ (never opened); nothing may be NaN, and what is
        // measured must be finite.
        let finite = [
            c.last_breakpoint_t_s,
            c.last_breakpoint_rpm,
            c.flow_rpm,
            c.flow_t_s,
            c.flow_command_rpm,
            c.flow_owed_rpm_s,
            c.repeat_rpm,
            c.angle_last_t_s,
            c.angle_last_rpm,
            c.angle_last_rad,
            c.angle_origin_t_s,
        ]
        .into_iter()
        .chain(c.from_m);
        if let Some(bad) = finite.into_iter().find(|x| !x.is_finite()) {
            return Err(CheckpointError::NotAScrewState(format!("{bad}")));
        }
        if c.pin_closed_at_s.is_nan() || c.flow_opened_at_s.is_nan() {
            return Err(CheckpointError::NotAScrewState("NaN".into()));
        }
        if !(c.retracted_m.is_finite() && c.retracted_m >= 0.0) {
            return Err(CheckpointError::NotAScrewState(format!(
                "retracted {} m",
                c.retracted_m
            )));
        }
        Ok(c)
    }
}

/// A digest of everything that shapes the commands ([`checkpoint::options_digest`]). The cut
/// sizes are not in it: they change where chunks end, not what a chunk left.
/// Where a trajectory starts, Cartesian (m): its first point's joints (bed θ rad, arm r m,
/// z m) through the polar forward kinematics.
fn plan_start_m(trajectory: &JointTrajectory) -> Option<[f64; 3]> {
    match trajectory.points.first()?.positions[..] {
        [theta, r, z] => Some([r * theta.cos(), r * theta.sin(), z]),
        _ => None,
    }
}

pub fn options_digest(options: &StreamOptions) -> u64 {
    checkpoint::options_digest(&format!(
        "{:?} {:?} {:?}",
        options.screw, options.command_period_s, options.joint_state_period_s
    ))
}
