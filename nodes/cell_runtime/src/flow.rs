//! Lossless flow control over a pipeline link, without I/O: one implementation for every
//! link (today `/gcode/moves`; any message type with a sequence number, [`Sequenced`]).
//!
//! Go-back-N over a reliable-but-volatile DDS topic. The producer ([`SendWindow`]) keeps at
//! most `window` messages that some consumer has not acknowledged. Each consumer ([`AckTracker`])
//! processes moves strictly in sequence order, drops duplicates, and on a gap (a move lost
//! before the DDS reader matched, say) keeps acknowledging the first missing sequence number.
//! When acknowledgements stop advancing for `resend_after`, the streamer goes back to the
//! oldest move some consumer has not *received* and sends again. A consumer acknowledges two
//! points: what it has finished (`next_expected`: a restart resumes there) and what it has
//! received in order (`received_until`: beyond it a move may be lost). A consumer that holds
//! moves on purpose (a planner paced by the machine) has received them, so the streamer waits
//! instead of sending them again; one that lost a move is stuck below what was sent, and gets
//! everything from the loss again. A consumer that (re)starts announces itself
//! with `resume = true` and learns its resume point from the per-consumer acknowledgements in
//! `/gcode/progress` ([`SendWindow::consumer_acks`]), then confirms it with a plain
//! acknowledgement; only then does the streamer send (again) everything after that point, so a
//! restarted consumer loses and repeats nothing.
//!
//! A consumer whose output depends on more than the moves after its resume point (a planner's
//! plan clock, joints and path speed) puts that state in its acknowledgements
//! ([`Intake::note_resume_state`]); the streamer keeps each consumer's latest, opaque, and hands
//! it back in `/gcode/progress` with the resume point ([`Intake::resume_state`]), so the two
//! always belong together and a restarted consumer continues the same output.

use std::collections::VecDeque;
use std::time::Duration;

use polar_cell_msgs::{GcodeAck, GcodeMove, GcodeProgress};

/// A message that travels a flow-controlled link: numbered 0, 1, 2, … by its producer.
pub trait Sequenced {
    fn sequence(&self) -> u64;
}

impl Sequenced for GcodeMove {
    fn sequence(&self) -> u64 {
        self.sequence
    }
}

/// A consumer's acknowledgement: everything before `next_expected` is done, everything
/// before `received_until` has arrived; `resume` announces a (re)started consumer that wants
/// to learn its resume point.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Ack {
    /// The consumer's fully qualified node name.
    pub consumer: String,
    pub next_expected: u64,
    pub resume: bool,
    /// Every move before it has arrived (in order), finished or not; never below
    /// `next_expected` in effect (a peer that does not fill it in sends 0).
    pub received_until: u64,
    /// The consumer's state after every move before `next_expected` (empty: none kept).
    pub resume_state: Vec<u8>,
}

impl From<&GcodeAck> for Ack {
    fn from(ack: &GcodeAck) -> Ack {
        Ack {
            consumer: ack.consumer.clone(),
            next_expected: ack.next_expected,
            resume: ack.resume,
            received_until: ack.received_until,
            resume_state: ack.resume_state.clone(),
        }
    }
}

impl From<Ack> for GcodeAck {
    fn from(ack: Ack) -> GcodeAck {
        GcodeAck {
            consumer: ack.consumer,
            next_expected: ack.next_expected,
            resume: ack.resume,
            received_until: ack.received_until,
            resume_state: ack.resume_state,
        }
    }
}

/// What became of an acknowledgement ([`SendWindow::on_ack`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum AckOutcome {
    Applied,
    /// From a node that is not one of the consumers: ignored, so a stray node can neither
    /// stall the stream nor speed it up.
    UnknownConsumer,
    /// It acknowledges messages never sent (`next_expected` beyond `sent`): ignored. Taken
    /// at its word, one forged acknowledgement would drain the window and end the stream
    /// "finished" with messages no consumer ever received.
    Impossible {
        next_expected: u64,
        sent: u64,
    },
}

/// Options of a producer's window.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowOptions {
    /// Most messages in flight (sent or queued, not acknowledged by every consumer).
    pub window: usize,
    /// Go back to the oldest move not received by every consumer when no acknowledgement
    /// advanced for this long.
    pub resend_after: Duration,
}

impl Default for WindowOptions {
    fn default() -> Self {
        WindowOptions {
            window: 4096,
            resend_after: Duration::from_millis(500),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Eq)]
struct ConsumerState {
    name: String,
    next_expected: u64,
    /// Everything before it has arrived there; never below `next_expected` (an announcement
    /// sets it there, and an acknowledgement raises it to at least its `next_expected`).
    received_until: u64,
    /// Has announced itself (a `resume` acknowledgement) since the streamer started.
    present: bool,
    /// Has confirmed its resume point (a plain acknowledgement after its announcement); moves
    /// sent before that could reach it before it knows which ones to keep.
    ready: bool,
    /// The state that came with the acknowledgement of `next_expected` (empty: none).
    resume_state: Vec<u8>,
    /// The process its acknowledgements last came from ([`SendWindow::on_ack_from`]).
    process: Option<u128>,
}

/// The producer's side: a bounded buffer of unacknowledged messages.
#[derive(Debug)]
pub struct SendWindow<T> {
    options: WindowOptions,
    buffer: VecDeque<T>,
    /// Sequence number of `buffer[0]`.
    base: u64,
    next_to_send: u64,
    /// One past the highest sequence number ever published (going back does not lower it).
    sent_end: u64,
    consumers: Vec<ConsumerState>,
    last_progress: Duration,
    resends: u64,
    /// Resends since acknowledgements last advanced.
    stalled_resends: u32,
}

impl<T: Sequenced + Clone> SendWindow<T> {
    /// A window gated by the named consumers (fully qualified node names).
    pub fn new(options: WindowOptions, consumers: &[String]) -> Self {
        SendWindow {
            options,
            buffer: VecDeque::new(),
            base: 0,
            next_to_send: 0,
            sent_end: 0,
            consumers: consumers
                .iter()
                .map(|name| ConsumerState {
                    name: name.clone(),
                    next_expected: 0,
                    received_until: 0,
                    present: false,
                    ready: false,
                    resume_state: Vec::new(),
                    process: None,
                })
                .collect(),
            last_progress: Duration::ZERO,
            resends: 0,
            stalled_resends: 0,
        }
    }

    /// True when another move may be queued.
    pub fn has_room(&self) -> bool {
        self.buffer.len() < self.options.window
    }

    /// Queue the next message; its sequence number must follow the previous one.
    pub fn push(&mut self, message: T) {
        debug_assert_eq!(message.sequence(), self.base + self.buffer.len() as u64);
        self.buffer.push_back(message);
    }

    /// The next move to put on the wire, if any, without consuming it: call
    /// [`Self::mark_sent`] once it is actually published. Sending only starts once every
    /// consumer has announced itself, so nothing is published into a reader not yet matched.
    pub fn peek_next(&self) -> Option<&T> {
        if !self.all_present() {
            return None;
        }
        let index = self.next_to_send.checked_sub(self.base)? as usize;
        self.buffer.get(index)
    }

    /// The move returned by [`Self::peek_next`] went out.
    pub fn mark_sent(&mut self) {
        if self.peek_next().is_some() {
            self.next_to_send += 1;
            self.sent_end = self.sent_end.max(self.next_to_send);
        }
    }

    /// Peek and mark sent in one step (for callers whose send cannot fail).
    pub fn next_to_send(&mut self) -> Option<T> {
        let m = self.peek_next()?.clone();
        self.next_to_send += 1;
        self.sent_end = self.sent_end.max(self.next_to_send);
        Some(m)
    }

    /// Moves published and not yet acknowledged by every consumer.
    pub fn in_flight(&self) -> u64 {
        self.next_to_send - self.base
    }

    /// [`Self::on_ack`] for an acknowledgement from `process` (`graph::process_of` its
    /// writer). A consumer's first acknowledgement from another process than before is its
    /// restart, even when it is not an announcement: a restarted consumer can learn its resume
    /// point from a report that still lists its previous process, and confirm it, before any
    /// announcement of its own got here. Taken as announced, it is sent everything after that
    /// point again; otherwise it would wait for moves its previous process had received.
    pub fn on_ack_from(&mut self, ack: &Ack, process: u128, now: Duration) -> AckOutcome {
        let Some(c) = self.consumers.iter_mut().find(|c| c.name == ack.consumer) else {
            return AckOutcome::UnknownConsumer;
        };
        let restarted = c.process.replace(process).is_some_and(|p| p != process);
        if restarted && !ack.resume {
            let announcement = Ack {
                consumer: ack.consumer.clone(),
                next_expected: 0,
                resume: true,
                received_until: 0,
                resume_state: Vec::new(),
            };
            self.on_ack(&announcement, now);
        }
        self.on_ack(ack, now)
    }

    /// Apply an acknowledgement received at monotonic time `now`; one from an unknown
    /// consumer or for messages never sent is ignored (and said so).
    pub fn on_ack(&mut self, ack: &Ack, now: Duration) -> AckOutcome {
        let Some(c) = self.consumers.iter_mut().find(|c| c.name == ack.consumer) else {
            return AckOutcome::UnknownConsumer;
        };
        if !ack.resume && ack.next_expected > self.sent_end {
            return AckOutcome::Impossible {
                next_expected: ack.next_expected,
                sent: self.sent_end,
            };
        }
        if ack.resume {
            c.present = true;
            c.ready = false;
            // Everything after this consumer's last acknowledgement goes again.
            c.received_until = c.next_expected;
            self.next_to_send = self.next_to_send.min(c.next_expected.max(self.base));
            self.last_progress = now;
        } else {
            c.ready |= c.present;
            if ack.next_expected > c.next_expected {
                c.next_expected = ack.next_expected;
                // The old state belongs to the old point: never hand it out with the new one.
                c.resume_state.clone_from(&ack.resume_state);
                self.last_progress = now;
                self.stalled_resends = 0;
            } else if ack.next_expected == c.next_expected && !ack.resume_state.is_empty() {
                c.resume_state.clone_from(&ack.resume_state);
            }
            // What arrived, never beyond what was sent (a claim beyond is not believed).
            let received_until = ack.received_until.min(self.sent_end).max(c.next_expected);
            if received_until > c.received_until {
                c.received_until = received_until;
                self.last_progress = now;
                self.stalled_resends = 0;
            }
        }
        let new_base = self
            .consumers
            .iter()
            .map(|c| c.next_expected)
            .min()
            .unwrap_or(self.next_to_send);
        while self.base < new_base && !self.buffer.is_empty() {
            self.buffer.pop_front();
            self.base += 1;
        }
        self.next_to_send = self.next_to_send.max(self.base);
        AckOutcome::Applied
    }

    /// Call periodically: goes back to the oldest move some consumer has not received when
    /// acknowledgements stalled for `resend_after`. Returns true when it did.
    ///
    /// A consumer that has received everything sent is not sent anything again, however
    /// long it takes to finish (a planner waiting for the executor's credit): going back over
    /// the whole unacknowledged window there cost 108 go-backs and a fifth of the graph's CPU
    /// on finger.gcode at 1×. Each further resend without progress waits twice as long (up to
    /// 16 × `resend_after`).
    pub fn on_tick(&mut self, now: Duration) -> bool {
        let resend_from = self
            .consumers
            .iter()
            .map(|c| c.received_until)
            .min()
            .unwrap_or(self.next_to_send)
            .max(self.base);
        let outstanding = self.next_to_send > resend_from;
        let wait = self.options.resend_after * (1u32 << self.stalled_resends.min(4));
        if outstanding && now.saturating_sub(self.last_progress) >= wait {
            self.next_to_send = resend_from;
            self.last_progress = now;
            self.resends += 1;
            self.stalled_resends += 1;
            return true;
        }
        false
    }

    /// Lowest sequence number not yet acknowledged by every consumer.
    pub fn acknowledged(&self) -> u64 {
        self.base
    }

    /// True when every queued move has been published at least once (before every consumer
    /// announced itself nothing is, whatever [`Self::peek_next`] says).
    pub fn all_sent(&self) -> bool {
        self.sent_end >= self.base + self.buffer.len() as u64
    }

    /// True when every queued move is acknowledged by every consumer.
    pub fn is_drained(&self) -> bool {
        self.buffer.is_empty()
    }

    /// How many times the window went back to resend.
    pub fn resends(&self) -> u64 {
        self.resends
    }

    fn all_present(&self) -> bool {
        self.consumers.iter().all(|c| c.ready)
    }

    /// Each announced consumer's name and next expected sequence number, for
    /// `/gcode/progress`. A consumer is listed only once its announcement arrived, so it never
    /// learns (and confirms) a resume point before the streamer knows it is there.
    pub fn consumer_acks(&self) -> (Vec<String>, Vec<u64>) {
        self.consumers
            .iter()
            .filter(|c| c.present)
            .map(|c| (c.name.clone(), c.next_expected))
            .unzip()
    }

    /// The resume states of the consumers [`Self::consumer_acks`] lists, in its order, as
    /// `/gcode/progress` carries them: concatenated, and where each one ends.
    pub fn consumer_resume_states(&self) -> (Vec<u8>, Vec<u32>) {
        let (mut bytes, mut ends) = (Vec::new(), Vec::new());
        for c in self.consumers.iter().filter(|c| c.present) {
            bytes.extend_from_slice(&c.resume_state);
            ends.push(u32::try_from(bytes.len()).unwrap_or(u32::MAX));
        }
        (bytes, ends)
    }

    /// Names of consumers that have not announced themselves and confirmed their resume point.
    pub fn missing_consumers(&self) -> Vec<&str> {
        self.consumers
            .iter()
            .filter(|c| !c.ready)
            .map(|c| c.name.as_str())
            .collect()
    }
}

/// What a consumer should do with a received move.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// The next move in order: process it.
    Process,
    /// Already processed: drop it.
    Duplicate,
    /// A move before it is missing: drop it and wait for the resend.
    Gap,
}

/// The consumer's side: in-order acceptance and cumulative acknowledgements.
///
/// A new tracker does not know where it stands: it announces itself with [`Self::hello`] and
/// drops every move until [`Self::on_progress`] tells it its resume point.
#[derive(Debug, Clone)]
pub struct AckTracker {
    consumer: String,
    next_expected: u64,
    ack_every: u64,
    last_acked: u64,
    /// The `received_until` last published.
    last_received_acked: u64,
    /// When [`Self::ack_processed`] last published (the caller's monotonic clock).
    last_published: Option<Duration>,
    resume_point_known: bool,
    /// The consumer's state after every move before `resume_state_until`, sent with
    /// acknowledgements of exactly that point; learnt back with the resume point.
    resume_state: Vec<u8>,
    resume_state_until: u64,
}

/// How often a consumer repeats an acknowledgement that has not changed. A repeat only
/// recovers a lost one. (It does not tell a restarted streamer anything: that streamer has
/// sent nothing, refuses an acknowledgement beyond it, and waits for its consumers'
/// announcements, which they made once. A streamer is not restartable mid-print.) The
/// planner and the screw driver used to repeat theirs on every 10 ms tick, 42,354
/// acknowledgements for finger.gcode's 1,778 moves at 1×, each a DDS sample to the streamer
/// and the recorder.
pub const UNCHANGED_ACK_REPEAT: Duration = Duration::from_millis(250);

/// How often a consumer with nothing arriving looks whether an announcement or a repeated
/// acknowledgement is due: a fifth of [`UNCHANGED_ACK_REPEAT`]. A consumer's other deadlines
/// (an idle flush) get timers of their own, so an idle node wakes 20 times a second, not 100.
pub const LOOK_PERIOD: Duration = Duration::from_millis(50);

impl AckTracker {
    /// A tracker for `consumer` (its fully qualified node name) that acknowledges at least
    /// every `ack_every` processed moves.
    pub fn new(consumer: impl Into<String>, ack_every: u64) -> Self {
        AckTracker {
            consumer: consumer.into(),
            next_expected: 0,
            ack_every: ack_every.max(1),
            last_acked: 0,
            last_received_acked: 0,
            last_published: None,
            resume_point_known: false,
            resume_state: Vec::new(),
            resume_state_until: 0,
        }
    }

    /// The state to acknowledge with, once everything before `until` is finished.
    pub fn note_resume_state(&mut self, until: u64, state: Vec<u8>) {
        self.resume_state_until = until;
        self.resume_state = state;
    }

    /// The state learnt with the resume point (empty before, or when there was none).
    pub fn resume_state(&self) -> &[u8] {
        &self.resume_state
    }

    fn state_for(&self, next_expected: u64) -> Vec<u8> {
        if next_expected == self.resume_state_until {
            self.resume_state.clone()
        } else {
            Vec::new()
        }
    }

    /// The announcement to publish (repeatedly) until the resume point is known.
    pub fn hello(&self) -> Ack {
        Ack {
            consumer: self.consumer.clone(),
            next_expected: self.next_expected,
            resume: true,
            received_until: self.next_expected,
            resume_state: Vec::new(),
        }
    }

    /// True until the resume point is known (keep sending [`Self::hello`] until then).
    pub fn needs_hello(&self) -> bool {
        !self.resume_point_known
    }

    /// Learn the resume point from the streamer's progress report (consumer names and their
    /// next expected sequence numbers). Returns true when it was learnt now: then publish
    /// `ack_due(true)` at once, which tells the streamer to start sending.
    pub fn on_progress(&mut self, consumers: &[String], next_expected: &[u64]) -> bool {
        self.on_progress_with_states(consumers, next_expected, &[], &[])
    }

    /// [`Self::on_progress`], also learning this consumer's resume state from the concatenated
    /// `states` and their `ends` (see `GcodeProgress.msg`; malformed ends give no state).
    pub fn on_progress_with_states(
        &mut self,
        consumers: &[String],
        next_expected: &[u64],
        states: &[u8],
        ends: &[u32],
    ) -> bool {
        if self.resume_point_known {
            return false;
        }
        let Some((n, state)) =
            consumer_entry(consumers, next_expected, states, ends, &self.consumer)
        else {
            return false;
        };
        self.resume_state = state.to_vec();
        self.resume_state_until = n;
        self.next_expected = n;
        self.last_acked = n;
        self.last_received_acked = n;
        self.resume_point_known = true;
        true
    }

    /// Classify a received move by its sequence number.
    pub fn accept(&mut self, sequence: u64) -> Verdict {
        if !self.resume_point_known {
            return Verdict::Gap;
        }
        match sequence.cmp(&self.next_expected) {
            std::cmp::Ordering::Equal => {
                self.next_expected += 1;
                Verdict::Process
            }
            std::cmp::Ordering::Less => Verdict::Duplicate,
            std::cmp::Ordering::Greater => Verdict::Gap,
        }
    }

    /// The acknowledgement to publish now, if one is due: after `ack_every` new moves, or any
    /// time `force` is set (idle timer; repeating an unchanged acknowledgement is harmless and
    /// recovers a lost one).
    pub fn ack_due(&mut self, force: bool) -> Option<Ack> {
        if !self.resume_point_known {
            return None;
        }
        let since = self.next_expected - self.last_acked;
        if since < self.ack_every && !force {
            return None;
        }
        self.last_acked = self.next_expected;
        self.last_received_acked = self.next_expected;
        Some(Ack {
            consumer: self.consumer.clone(),
            next_expected: self.next_expected,
            resume: false,
            received_until: self.next_expected,
            resume_state: self.state_for(self.next_expected),
        })
    }

    /// Acknowledge everything before `processed_until` — for consumers that finish a move
    /// later than they receive it (a planner's lookahead): only finished moves are
    /// acknowledged, so a restart resumes with the unfinished ones. Never beyond what was
    /// received. Published at `now` (a monotonic clock) when it advanced, or unchanged once
    /// [`UNCHANGED_ACK_REPEAT`] has passed since the last one.
    pub fn ack_processed(&mut self, processed_until: u64, now: Duration) -> Option<Ack> {
        if !self.resume_point_known {
            return None;
        }
        let next_expected = processed_until.min(self.next_expected).max(self.last_acked);
        let repeat_due = self
            .last_published
            .is_none_or(|at| now.saturating_sub(at) >= UNCHANGED_ACK_REPEAT);
        // What arrived is news only once it is not far ahead of what was said: a burst of
        // moves taken in is one acknowledgement, not one per move.
        let received_news = self.next_expected >= self.last_received_acked + self.ack_every
            || (self.next_expected > self.last_received_acked && next_expected > self.last_acked);
        if next_expected == self.last_acked && !received_news && !repeat_due {
            return None;
        }
        self.last_acked = next_expected;
        self.last_received_acked = self.next_expected;
        self.last_published = Some(now);
        Some(Ack {
            consumer: self.consumer.clone(),
            next_expected,
            resume: false,
            received_until: self.next_expected,
            resume_state: self.state_for(next_expected),
        })
    }

    /// Sequence number of the next move this consumer will process.
    pub fn next_expected(&self) -> u64 {
        self.next_expected
    }
}

/// `consumer`'s acknowledged point and resume state in a progress report's per-consumer
/// lists (see `GcodeProgress.msg`; malformed ends give an empty state).
fn consumer_entry<'a>(
    consumers: &[String],
    next_expected: &[u64],
    states: &'a [u8],
    ends: &[u32],
    consumer: &str,
) -> Option<(u64, &'a [u8])> {
    let i = consumers.iter().position(|c| c == consumer)?;
    let n = *next_expected.get(i)?;
    let start = if i == 0 {
        Some(0)
    } else {
        ends.get(i - 1).copied()
    };
    let state = match (start, ends.get(i)) {
        (Some(a), Some(&b)) if a <= b => states.get(a as usize..b as usize).unwrap_or(&[]),
        _ => &[],
    };
    Some((n, state))
}

/// What `progress` says of `consumer` (fully qualified): the point it acknowledged and the
/// state it acknowledged with. A node downstream of that consumer reads there how far the
/// consumer's own output reaches (`polar_cell_msgs::checkpoint::reach`).
pub fn consumer_state<'a>(progress: &'a GcodeProgress, consumer: &str) -> Option<(u64, &'a [u8])> {
    consumer_entry(
        &progress.consumers,
        &progress.consumer_next_expected,
        &progress.consumer_resume_states,
        &progress.consumer_resume_state_ends,
        consumer,
    )
}

/// How a node takes in a link: as a flow-control consumer ([`AckTracker`]), or —
/// replaying a bag, with no streamer to acknowledge — simply in sequence order from 0.
#[derive(Debug, Clone)]
pub struct Intake {
    tracker: Option<AckTracker>,
    next_without_acks: u64,
}

impl Intake {
    /// `consumer` is the node's fully qualified name.
    pub fn new(consumer: impl Into<String>, acknowledge: bool) -> Self {
        Intake {
            tracker: acknowledge.then(|| AckTracker::new(consumer, 64)),
            next_without_acks: 0,
        }
    }

    /// True when the move with this sequence number is the next one to process.
    pub fn accept(&mut self, sequence: u64) -> bool {
        match &mut self.tracker {
            Some(t) => t.accept(sequence) == Verdict::Process,
            None if sequence == self.next_without_acks => {
                self.next_without_acks += 1;
                true
            }
            None => false,
        }
    }

    /// A progress report arrived: the confirmation to publish when it told the resume point
    /// (and, with it, this consumer's resume state: [`Self::resume_state`]).
    pub fn on_progress(&mut self, progress: &GcodeProgress) -> Option<Ack> {
        let t = self.tracker.as_mut()?;
        if t.on_progress_with_states(
            &progress.consumers,
            &progress.consumer_next_expected,
            &progress.consumer_resume_states,
            &progress.consumer_resume_state_ends,
        ) {
            t.ack_due(true)
        } else {
            None
        }
    }

    /// The resume point and the state learnt with it, once known (`None` before, and without
    /// acknowledgements).
    pub fn resume_state(&self) -> Option<(u64, &[u8])> {
        let t = self.tracker.as_ref().filter(|t| !t.needs_hello())?;
        Some((t.resume_state_until, t.resume_state()))
    }

    /// Acknowledge with `state` once everything before `until` is finished (see
    /// [`AckTracker::note_resume_state`]).
    pub fn note_resume_state(&mut self, until: u64, state: Vec<u8>) {
        if let Some(t) = self.tracker.as_mut() {
            t.note_resume_state(until, state);
        }
    }

    /// What to publish at `now` (a monotonic clock), given that every move before
    /// `processed_until` is finished: the announcement until the resume point is known, then
    /// the acknowledgement when it advanced or a repeat is due.
    pub fn ack(&mut self, processed_until: u64, now: Duration) -> Option<Ack> {
        let t = self.tracker.as_mut()?;
        if t.needs_hello() {
            Some(t.hello())
        } else {
            t.ack_processed(processed_until, now)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mv(sequence: u64) -> GcodeMove {
        GcodeMove {
            sequence,
            ..Default::default()
        }
    }

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Simulates a lossy channel; the consumer's effect log must end up as 0..n exactly once,
    /// in order. With `restart_at`, the consumer crashes after that many processed moves,
    /// losing what it processed since its last acknowledgement, and a fresh one takes over.
    fn run(n: u64, window: usize, drop_every: u64, restart_at: Option<usize>) -> (Vec<u64>, u64) {
        let options = WindowOptions {
            window,
            resend_after: ms(10),
        };
        let mut w = SendWindow::new(options, &["/c".to_string()]);
        let mut c = AckTracker::new("/c", 8);
        let mut processed = Vec::new();
        let mut queued = 0u64;
        let mut now = Duration::ZERO;
        let mut wire_count = 0u64;
        let mut restart_at = restart_at;
        for _step in 0..1_000_000 {
            now += ms(1);
            if c.needs_hello() {
                w.on_ack(&c.hello(), now);
                assert!(
                    w.peek_next().is_none(),
                    "nothing is sent before the confirmation"
                );
                let (names, acks) = w.consumer_acks();
                if c.on_progress(&names, &acks) {
                    w.on_ack(&c.ack_due(true).unwrap(), now);
                }
            }
            while w.has_room() && queued < n {
                w.push(mv(queued));
                queued += 1;
            }
            let mut batch = Vec::new();
            while let Some(m) = w.next_to_send() {
                batch.push(m.sequence);
            }
            for seq in batch {
                wire_count += 1;
                if drop_every > 0 && wire_count.is_multiple_of(drop_every) {
                    continue; // lost on the wire
                }
                if c.accept(seq) == Verdict::Process {
                    processed.push(seq);
                }
                if let Some(ack) = c.ack_due(false) {
                    w.on_ack(&ack, now);
                }
                if restart_at == Some(processed.len()) {
                    restart_at = None;
                    // Crash: the effects after the last acknowledgement are not committed.
                    processed.truncate(w.consumer_acks().1[0] as usize);
                    c = AckTracker::new("/c", 8);
                    break;
                }
            }
            if let Some(ack) = c.ack_due(true) {
                w.on_ack(&ack, now);
            }
            w.on_tick(now);
            if queued == n && w.is_drained() {
                break;
            }
        }
        (processed, w.resends())
    }

    #[test]
    fn lossless_channel_delivers_in_order_without_resends() {
        let (p, resends) = run(10_000, 64, 0, None);
        assert_eq!(p, (0..10_000).collect::<Vec<_>>());
        assert_eq!(resends, 0);
    }

    #[test]
    fn lossy_channel_still_delivers_everything_once_in_order() {
        let (p, resends) = run(5_000, 32, 7, None);
        assert_eq!(p, (0..5_000).collect::<Vec<_>>());
        assert!(resends > 0);
    }

    #[test]
    fn restarted_consumer_resumes_after_its_last_acknowledgement() {
        let (p, _) = run(3_000, 50, 0, Some(1_234));
        assert_eq!(p, (0..3_000).collect::<Vec<_>>());
    }

    /// A window with one announced, confirmed consumer "/c" and moves 0..n sent.
    fn sent_window(n: u64) -> SendWindow<GcodeMove> {
        let options = WindowOptions {
            window: 64,
            resend_after: ms(100),
        };
        let mut w = SendWindow::new(options, &["/c".to_string()]);
        let mut c = AckTracker::new("/c", 8);
        w.on_ack(&c.hello(), ms(0));
        let (names, acks) = w.consumer_acks();
        assert!(c.on_progress(&names, &acks));
        w.on_ack(&c.ack_due(true).unwrap(), ms(0));
        for k in 0..n {
            w.push(mv(k));
            w.next_to_send().unwrap();
        }
        w
    }

    /// A consumer that has received everything and finishes slowly on purpose (a planner
    /// paced by the machine) is sent nothing again, however long it takes.
    #[test]
    fn a_consumer_holding_what_it_received_is_not_sent_it_again() {
        let mut w = sent_window(20);
        let mut c = AckTracker::new("/c", 8);
        c.on_progress(&["/c".to_string()], &[0]);
        for k in 0..20 {
            assert_eq!(c.accept(k), Verdict::Process);
        }
        // Finished 3 of them; the acknowledgement says all 20 arrived.
        let ack = c.ack_processed(3, ms(1)).unwrap();
        assert_eq!((ack.next_expected, ack.received_until), (3, 20));
        w.on_ack(&ack, ms(1));
        for t in (0..60_000).step_by(10) {
            assert!(!w.on_tick(ms(t)), "went back at {t} ms");
            if let Some(ack) = c.ack_processed(3, ms(t)) {
                w.on_ack(&ack, ms(t));
            }
        }
        assert_eq!(w.resends(), 0);
        assert_eq!(w.peek_next().map(|m| m.sequence), None);
        assert_eq!(w.acknowledged(), 3);
    }

    /// A consumer that lost a move in the middle gets everything from the lost one again,
    /// not what it had already received; one that does not say what it received (0, an older
    /// peer) gets everything from its acknowledgement, as before.
    #[test]
    fn going_back_starts_at_the_first_move_a_consumer_did_not_receive() {
        let mut w = sent_window(20);
        let told = |received_until| Ack {
            consumer: "/c".into(),
            next_expected: 3,
            resume: false,
            received_until,
            resume_state: Vec::new(),
        };
        w.on_ack(&told(12), ms(1));
        assert!(!w.on_tick(ms(50)));
        assert!(w.on_tick(ms(101)));
        assert_eq!(w.peek_next().map(|m| m.sequence), Some(12));

        let mut w = sent_window(20);
        w.on_ack(&told(0), ms(1));
        assert!(w.on_tick(ms(101)));
        assert_eq!(w.peek_next().map(|m| m.sequence), Some(3));

        // A claim beyond what was sent is not believed beyond it.
        let mut w = sent_window(20);
        w.on_ack(&told(1_000), ms(1));
        assert!(!w.on_tick(ms(10_000)));
        w.push(mv(20));
        w.next_to_send().unwrap();
        assert!(w.on_tick(ms(20_000)));
        assert_eq!(w.peek_next().map(|m| m.sequence), Some(20));
    }

    /// Moves taken in but not finished are told once a batch has arrived, and with every
    /// repeat; not one acknowledgement per move.
    #[test]
    fn what_arrived_is_told_in_batches_and_with_repeats() {
        let mut c = AckTracker::new("/c", 8);
        c.on_progress(&["/c".to_string()], &[0]);
        let mut published = Vec::new();
        for k in 0..20 {
            c.accept(k);
            if let Some(ack) = c.ack_processed(0, ms(k)) {
                published.push((k, ack.next_expected, ack.received_until));
            }
        }
        // The first (nothing published yet), then one once 8 more had arrived, and so on.
        assert_eq!(published, vec![(0, 0, 1), (8, 0, 9), (16, 0, 17)]);
        assert_eq!(c.ack_processed(0, ms(100)), None);
        let repeat = c.ack_processed(0, ms(300)).unwrap();
        assert_eq!((repeat.next_expected, repeat.received_until), (0, 20));
    }

    #[test]
    fn window_bounds_unacknowledged_moves_and_slowest_consumer_gates() {
        let consumers = ["/a".to_string(), "/b".to_string()];
        let mut w = SendWindow::new(
            WindowOptions {
                window: 4,
                resend_after: ms(100),
            },
            &consumers,
        );
        for s in 0..4 {
            w.push(mv(s));
        }
        assert!(!w.has_room());
        let ack = |name: &str, n| Ack {
            consumer: name.into(),
            next_expected: n,
            resume: false,
            received_until: 0,
            resume_state: Vec::new(),
        };
        assert_eq!(
            w.consumer_acks().0,
            Vec::<String>::new(),
            "nobody announced yet"
        );
        w.on_ack(&AckTracker::new("/a", 1).hello(), ms(0));
        assert_eq!(w.consumer_acks(), (vec!["/a".to_string()], vec![0]));
        w.on_ack(&ack("/a", 0), ms(0));
        assert!(w.next_to_send().is_none(), "/b has not announced itself");
        assert!(w.peek_next().is_none());
        assert!(
            !w.all_sent(),
            "nothing is published before /b announces itself"
        );
        assert_eq!(w.missing_consumers(), ["/b"]);
        w.on_ack(&AckTracker::new("/b", 1).hello(), ms(0));
        assert!(
            w.next_to_send().is_none(),
            "/b has not confirmed its resume point"
        );
        w.on_ack(&ack("/b", 0), ms(0));
        let sent: Vec<u64> = std::iter::from_fn(|| w.next_to_send().map(|m| m.sequence)).collect();
        assert_eq!(sent, [0, 1, 2, 3]);
        assert!(w.all_sent());
        w.on_ack(&ack("/a", 4), ms(1));
        assert_eq!(w.acknowledged(), 0, "/b still holds the window");
        w.on_ack(&ack("/b", 2), ms(2));
        assert_eq!(w.acknowledged(), 2);
        assert!(w.has_room());
        assert_eq!(
            w.on_ack(&ack("/stranger", 4), ms(3)),
            AckOutcome::UnknownConsumer
        );
        assert_eq!(w.acknowledged(), 2);
        // No progress for resend_after: go back to 2.
        assert!(!w.on_tick(ms(50)));
        assert!(w.on_tick(ms(102)));
        assert_eq!(w.next_to_send().map(|m| m.sequence), Some(2));
        // Still no progress: the next go-backs wait 200, 400, 800 ms, then 1.6 s each.
        let _ = std::iter::from_fn(|| w.next_to_send()).count();
        assert!(!w.on_tick(ms(301)) && w.on_tick(ms(302)));
        let _ = std::iter::from_fn(|| w.next_to_send()).count();
        assert!(!w.on_tick(ms(701)) && w.on_tick(ms(702)));
        let _ = std::iter::from_fn(|| w.next_to_send()).count();
        assert!(!w.on_tick(ms(1501)) && w.on_tick(ms(1502)));
        let _ = std::iter::from_fn(|| w.next_to_send()).count();
        assert!(!w.on_tick(ms(3101)) && w.on_tick(ms(3102)));
        let _ = std::iter::from_fn(|| w.next_to_send()).count();
        assert!(!w.on_tick(ms(4701)) && w.on_tick(ms(4702)), "capped at 16×");
        // Progress resets the wait to resend_after.
        let _ = std::iter::from_fn(|| w.next_to_send()).count();
        w.on_ack(&ack("/a", 3), ms(4710));
        w.on_ack(&ack("/b", 3), ms(4710));
        assert!(!w.on_tick(ms(4809)) && w.on_tick(ms(4810)));
    }

    #[test]
    fn intake_with_and_without_acknowledgements() {
        let mut replay = Intake::new("/p", false);
        assert!(replay.accept(0) && !replay.accept(2) && replay.accept(1));
        assert_eq!(
            replay.ack(2, ms(0)),
            None,
            "no acknowledgements when replaying"
        );
        let mut live = Intake::new("/p", true);
        assert!(live.ack(0, ms(0)).unwrap().resume, "announces itself first");
        assert!(!live.accept(0), "resume point unknown");
        let told = GcodeProgress {
            consumers: vec!["/p".into()],
            consumer_next_expected: vec![3],
            ..GcodeProgress::default()
        };
        let confirm = live.on_progress(&told).unwrap();
        assert_eq!((confirm.next_expected, confirm.resume), (3, false));
        assert!(live.accept(3) && live.accept(4));
        assert_eq!(live.ack(4, ms(10)).unwrap().next_expected, 4);
        // Nothing new: repeated only after UNCHANGED_ACK_REPEAT.
        assert_eq!(live.ack(4, ms(20)), None);
        assert_eq!(live.ack(4, ms(259)), None);
        assert_eq!(live.ack(4, ms(260)).unwrap().next_expected, 4);
        assert!(live.accept(5));
        assert_eq!(
            live.ack(5, ms(270)).unwrap().next_expected,
            5,
            "an advance goes at once"
        );
    }

    #[test]
    fn tracker_classifies_and_acknowledges() {
        let mut t = AckTracker::new("/c", 3);
        assert!(t.needs_hello());
        assert_eq!(t.accept(0), Verdict::Gap, "resume point unknown yet");
        assert!(!t.on_progress(&["/other".into()], &[5]));
        assert!(t.on_progress(&["/other".into(), "/c".into()], &[5, 0]));
        assert!(!t.needs_hello());
        assert_eq!(t.accept(0), Verdict::Process);
        assert_eq!(t.accept(0), Verdict::Duplicate);
        assert_eq!(t.accept(2), Verdict::Gap);
        assert_eq!(t.ack_due(false), None);
        assert_eq!(t.ack_due(true).unwrap().next_expected, 1);
        assert_eq!(t.accept(1), Verdict::Process);
        assert_eq!(t.accept(2), Verdict::Process);
        assert_eq!(t.accept(3), Verdict::Process);
        assert_eq!(t.ack_due(false).unwrap().next_expected, 4);
        // A consumer that finished only two of them acknowledges two; never more than received.
        let mut t = AckTracker::new("/p", 8);
        assert_eq!(t.ack_processed(5, ms(0)), None, "resume point unknown");
        t.on_progress(&["/p".into()], &[10]);
        for s in 10..15 {
            assert_eq!(t.accept(s), Verdict::Process);
        }
        assert_eq!(t.ack_processed(12, ms(1)).unwrap().next_expected, 12);
        assert_eq!(t.ack_processed(99, ms(2)).unwrap().next_expected, 15);
        assert_eq!(
            t.ack_processed(11, ms(3)),
            None,
            "unchanged, not yet repeated"
        );
        assert_eq!(
            t.ack_processed(11, ms(300)).unwrap().next_expected,
            15,
            "never goes back"
        );
    }

    /// A forged acknowledgement (next_expected 10⁹ for a real consumer) acknowledges nothing:
    /// the window keeps every message until the consumer itself has them.
    #[test]
    fn an_acknowledgement_of_messages_never_sent_is_refused() {
        let ack = |name: &str, n| Ack {
            consumer: name.into(),
            next_expected: n,
            resume: false,
            received_until: 0,
            resume_state: Vec::new(),
        };
        let mut w: SendWindow<GcodeMove> =
            SendWindow::new(WindowOptions::default(), &["/a".to_string()]);
        w.on_ack(&AckTracker::new("/a", 1).hello(), ms(0));
        w.on_ack(&ack("/a", 0), ms(0));
        for k in 0..10 {
            w.push(mv(k));
        }
        for _ in 0..4 {
            w.next_to_send().unwrap();
        }
        assert_eq!(
            w.on_ack(&ack("/a", 1_000_000_000), ms(1)),
            AckOutcome::Impossible {
                next_expected: 1_000_000_000,
                sent: 4
            }
        );
        assert_eq!(w.acknowledged(), 0);
        assert!(!w.is_drained());
        // What was sent can be acknowledged; a go-back does not lower what counts as sent.
        assert_eq!(w.on_ack(&ack("/a", 4), ms(2)), AckOutcome::Applied);
        assert_eq!(w.acknowledged(), 4);
        assert_eq!(w.on_ack(&ack("/b", 4), ms(2)), AckOutcome::UnknownConsumer);
    }

    /// The state a consumer acknowledges with comes back to it, restarted, with exactly the
    /// resume point it belongs to: the streamer drops an old state when the point advances
    /// without one, and a consumer that keeps none gets none.
    #[test]
    fn a_restarted_consumer_gets_back_the_state_of_its_resume_point() {
        let names = ["/planner".to_string(), "/recorder".to_string()];
        let mut w: SendWindow<GcodeMove> = SendWindow::new(WindowOptions::default(), &names);
        let mut planner = Intake::new("/planner", true);
        let mut recorder = Intake::new("/recorder", true);
        let progress = |w: &SendWindow<GcodeMove>| {
            let (consumers, consumer_next_expected) = w.consumer_acks();
            let (consumer_resume_states, consumer_resume_state_ends) = w.consumer_resume_states();
            GcodeProgress {
                consumers,
                consumer_next_expected,
                consumer_resume_states,
                consumer_resume_state_ends,
                ..GcodeProgress::default()
            }
        };
        for intake in [&mut planner, &mut recorder] {
            w.on_ack(&intake.ack(0, ms(0)).unwrap(), ms(0));
        }
        for intake in [&mut recorder, &mut planner] {
            let confirm = intake.on_progress(&progress(&w)).unwrap();
            assert_eq!(intake.resume_state(), Some((0, &[][..])));
            w.on_ack(&confirm, ms(0));
        }
        for k in 0..10 {
            w.push(mv(k));
        }
        while let Some(m) = w.next_to_send() {
            assert!(planner.accept(m.sequence) && recorder.accept(m.sequence));
        }
        planner.note_resume_state(4, b"after 4".to_vec());
        let ack = planner.ack(4, ms(1)).unwrap();
        assert_eq!(ack.resume_state, b"after 4");
        w.on_ack(&ack, ms(1));
        w.on_ack(&recorder.ack(10, ms(1)).unwrap(), ms(1));
        // Not yet at the noted point: acknowledged without a state (it would not match).
        planner.note_resume_state(7, b"after 7".to_vec());
        assert!(planner.ack(6, ms(300)).unwrap().resume_state.is_empty());

        // The planner restarts: it announces itself and learns point and state together.
        let mut restarted = Intake::new("/planner", true);
        w.on_ack(&restarted.ack(0, ms(400)).unwrap(), ms(400));
        let p = progress(&w);
        assert_eq!(
            p.consumer_resume_state_ends,
            vec![7, 7],
            "the recorder keeps none"
        );
        // What a node downstream of the planner reads there.
        assert_eq!(consumer_state(&p, "/planner"), Some((4, &b"after 4"[..])));
        assert_eq!(consumer_state(&p, "/recorder"), Some((10, &b""[..])));
        assert_eq!(consumer_state(&p, "/other"), None);
        restarted.on_progress(&p).unwrap();
        assert_eq!(restarted.resume_state(), Some((4, &b"after 4"[..])));
        assert_eq!(
            w.peek_next().map(|m| m.sequence),
            None,
            "not before it confirms"
        );

        // An advance without a state drops the old one.
        let mut w2: SendWindow<GcodeMove> = SendWindow::new(WindowOptions::default(), &names[..1]);
        w2.on_ack(&AckTracker::new("/planner", 1).hello(), ms(0));
        for k in 0..5 {
            w2.push(mv(k));
        }
        let with = |n: u64, state: &[u8]| Ack {
            consumer: "/planner".into(),
            next_expected: n,
            resume: false,
            received_until: n,
            resume_state: state.to_vec(),
        };
        w2.on_ack(&with(0, b""), ms(0));
        while w2.next_to_send().is_some() {}
        w2.on_ack(&with(2, b"s2"), ms(1));
        assert_eq!(w2.consumer_resume_states(), (b"s2".to_vec(), vec![2]));
        w2.on_ack(&with(1, b"old"), ms(2));
        assert_eq!(
            w2.consumer_resume_states(),
            (b"s2".to_vec(), vec![2]),
            "a late one is not taken"
        );
        w2.on_ack(&with(3, b""), ms(3));
        assert_eq!(w2.consumer_resume_states(), (vec![], vec![0]));
    }

    /// A restarted consumer that learnt its resume point from a report still listing its
    /// previous process, and confirmed it without announcing itself, is sent everything after
    /// that point again (it used to wait for ever: the window held that its previous process
    /// had received them all).
    #[test]
    fn a_consumer_confirming_from_a_new_process_is_sent_its_moves_again() {
        let mut w: SendWindow<GcodeMove> =
            SendWindow::new(WindowOptions::default(), &["/p".to_string()]);
        let mut first = Intake::new("/p", true);
        w.on_ack_from(&first.ack(0, ms(0)).unwrap(), 1, ms(0));
        let told = |w: &SendWindow<GcodeMove>| {
            let (consumers, consumer_next_expected) = w.consumer_acks();
            GcodeProgress {
                consumers,
                consumer_next_expected,
                ..GcodeProgress::default()
            }
        };
        w.on_ack_from(&first.on_progress(&told(&w)).unwrap(), 1, ms(0));
        for k in 0..10 {
            w.push(mv(k));
        }
        while let Some(m) = w.next_to_send() {
            assert!(first.accept(m.sequence));
        }
        // It finished 4 and received all 10, then died.
        w.on_ack_from(&first.ack(4, ms(1)).unwrap(), 1, ms(1));
        // Its successor reads a report before announcing itself, and confirms at once.
        let mut second = Intake::new("/p", true);
        let confirm = second.on_progress(&told(&w)).unwrap();
        assert_eq!(confirm.next_expected, 4);
        assert!(!confirm.resume);
        w.on_ack_from(&confirm, 2, ms(2));
        let again: Vec<u64> = std::iter::from_fn(|| w.next_to_send().map(|m| m.sequence)).collect();
        assert_eq!(again, (4..10).collect::<Vec<_>>());
        assert!(again.iter().all(|&k| second.accept(k)));
    }
}
