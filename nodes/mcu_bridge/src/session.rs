//! The host's session with one MCU: start the link, identify, keep the clocks in step, and
//! feed the plan to the MCU within its queue and the execution horizon.
//!
//! Sans-I/O, like every core here: the caller hands in the bytes it read and the host time
//! (`now_us`, a monotonic microsecond count), writes out what [`McuSession::poll_transmit`]
//! gives, and calls [`McuSession::tick`] periodically.
//!
//! # Flow
//!
//! The planner's segments are converted at once ([`Schedule`]) and wait here. One goes to the
//! MCU when its queue has room (its last reported `queue_free`, less what was sent since) and
//! it starts within `horizon_s` of the MCU's plan clock now — so the MCU holds at most a
//! horizon of motion, as the virtual executor does. The first segment fixes the schedule's
//! anchor: the MCU's plan clock now plus `lead_s`, time enough for the first frames to
//! arrive.
//!
//! # Keeping in step
//!
//! A clock query every `clock_query_period_s` feeds [`ClockSync`] until it holds
//! [`CLOCK_SETTLE_SAMPLES`], then one every `clock_query_settled_period_s` keeps it (the
//! window of the fit then spans minutes, and each query costs its frame and the reply's
//! acknowledgement on the line: 1,680 queries were an eighth of finger's bytes). The query
//! doubles as the keep-alive the MCU's watchdog expects, so it comes at least four times per
//! `host_timeout_s`; the MCU reports its state every
//! `state_period_s`. The MCU's plan clock now is its last state's plan clock plus the time
//! since, at the synchronised rate (exact while no hold is in progress).

use std::collections::VecDeque;

use cell_protocol::message::{
    FaultCode, HostMessage, Identity, McuMessage, McuState, Mode, NextSegment, QueuedSegment,
    ScrewNext, ScrewRamp, ScrewReference, SEGMENT_ENDS_AT_REST,
};
use cell_protocol::{LinkError, MAX_WIRE_FRAME, PROTOCOL_VERSION};
use polar_cell_msgs::{Hold, ScrewCommand, StepSegment};

use crate::clock::ClockSync;
use crate::host::{FromMcu, HostEndpoint};
use crate::schedule::{Schedule, ScheduleError};

/// How the session runs.
#[derive(Clone, Debug, PartialEq)]
pub struct SessionOptions {
    /// Most motion queued on the MCU ahead of its plan clock (s).
    pub horizon_s: f64,
    /// Time between the first segment's conversion and its start on the MCU (s).
    pub lead_s: f64,
    /// Time between clock queries while the clock fit settles (s).
    pub clock_query_period_s: f64,
    /// Time between clock queries once it has (s; at most a quarter of `host_timeout_s`).
    pub clock_query_settled_period_s: f64,
    /// The MCU faults when it hears nothing for this long (s).
    pub host_timeout_s: f64,
    /// How often the MCU reports its state (s).
    pub state_period_s: f64,
    /// The host gives up on an MCU silent this long (and at least ten state periods) (s).
    pub silence_s: f64,
    /// The host gives up on an MCU not ready (linked, identified, clock fitted, reporting)
    /// this long after the session's first tick (s): a wrong device or baud rate otherwise
    /// waits for ever with nothing said.
    pub answer_timeout_s: f64,
    pub retransmit_timeout_s: f64,
    /// How long continuing segments and screw commands may wait for more to fill their frame
    /// (machine s): they go a horizon ahead, and each frame costs 8 bytes of framing. A
    /// schedule's first segment, clock queries and holds never wait (a hold takes the
    /// waiting messages along in its frame).
    pub pack_s: f64,
    /// How rpm runs between screw commands (the screw driver's hold).
    pub screw_hold: Hold,
    /// Steps per rad of `bed_theta`, per m of `arm_r` and `z`.
    pub steps_per_unit: [f64; 3],
    /// Joint acceleration limits a feed hold and resume keep to (rad/s², m/s², m/s²).
    pub joint_accelerations: [f64; 3],
    /// Time at rest with the pin reopened before a resume moves (s).
    pub pin_open_delay_s: f64,
}

impl SessionOptions {
    /// The machine's step resolution, joint acceleration limits and pin delay (the planner's
    /// and screw driver's: no default can know them); the rest as the virtual executor runs.
    pub fn new(
        steps_per_unit: [f64; 3],
        joint_accelerations: [f64; 3],
        pin_open_delay_s: f64,
    ) -> SessionOptions {
        SessionOptions {
            horizon_s: 2.0,
            lead_s: 0.25,
            clock_query_period_s: 0.1,
            clock_query_settled_period_s: 0.5,
            host_timeout_s: 1.0,
            state_period_s: 0.02,
            silence_s: 0.25,
            answer_timeout_s: 5.0,
            retransmit_timeout_s: 0.05,
            pack_s: 0.1,
            screw_hold: Hold::ZeroOrder,
            steps_per_unit,
            joint_accelerations,
            pin_open_delay_s,
        }
    }
}

/// What went wrong with the MCU; the machine is (or is being put) in its safe state.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SessionError {
    #[error("the MCU speaks protocol version {mcu}, this host {PROTOCOL_VERSION}")]
    Version { mcu: u16 },
    #[error(
        "the MCU cannot run a plan from this host: its timer runs at {timer_hz} Hz, it queues \
         {queue_capacity} segments and {screw_queue_capacity} screw commands (needed: a \
         running timer, a segment queue, and 2 screw places, one kept free for a command \
         not yet taken up)"
    )]
    Unusable {
        timer_hz: u32,
        queue_capacity: u16,
        screw_queue_capacity: u16,
    },
    #[error("the MCU reported fault {code:?} at its clock {clock} (segment tag {tag})")]
    Fault {
        code: FaultCode,
        clock: u64,
        tag: u32,
    },
    #[error("the MCU restarted (power cycle or reset): its queue and position are gone; {lost} messages were lost")]
    Restarted { lost: usize },
    #[error("the MCU has been silent for {silent_s:.3} s (no state since)")]
    Silent { silent_s: f64 },
    #[error("the MCU was not ready {waited_s:.1} s after the session began: {missing}")]
    NoAnswer {
        waited_s: f64,
        missing: &'static str,
    },
    #[error(
        "the MCU's fault {code:?} did not clear: it still reports it {waited_s:.3} s after RESET"
    )]
    FaultNotCleared { code: FaultCode, waited_s: f64 },
    #[error(transparent)]
    Schedule(#[from] ScheduleError),
}

/// Whether an MCU so identified can run a plan from this host: a running timer, a segment
/// queue, and 2 screw places (one is kept free for a command not yet taken up).
fn can_run_a_plan(identity: &Identity) -> bool {
    identity.timer_hz > 0 && identity.queue_capacity > 0 && identity.screw_queue_capacity >= 2
}

/// A session's RESET of the MCU: faults count only once the MCU has acted on it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ResetProgress {
    /// Not sent yet (the session is starting): whatever the MCU reports is from before.
    NotSent,
    /// Sent at this host time.
    Sent { at_us: u64 },
    /// Acted on (a state without a fault came after it), or a fault outlasted it.
    Done,
}

/// The host's session with one MCU.
pub struct McuSession {
    options: SessionOptions,
    endpoint: HostEndpoint,
    clock: ClockSync,
    identity: Option<Identity>,
    configured: bool,
    /// The session's first tick, and whether it has been ready since.
    first_tick_us: Option<u64>,
    was_ready: bool,
    /// Outstanding clock queries: token and send time.
    queries: VecDeque<(u32, u64)>,
    next_token: u32,
    next_query_us: u64,
    schedule: Option<Schedule>,
    segments: VecDeque<QueuedSegment>,
    screw: VecDeque<ScrewRamp>,
    /// The last state and the host time it arrived.
    state: Option<(McuState, u64)>,
    /// Segments sent since that state was taken (the MCU's `queue_free` does not know them).
    sent_since_state: usize,
    /// Segments on the MCU not yet played: where each ends and how fast σ may change in it.
    on_mcu: VecDeque<(u64, f64)>,
    /// Start clocks of the screw commands sent that the MCU may still hold queued.
    screw_on_mcu: VecDeque<u64>,
    /// The last feed left segments waiting for the MCU's queue or the horizon.
    held_back: bool,
    /// Screw commands that reached the line too late for their start, and were sent to start
    /// as soon as the MCU could take them ([`SCREW_MARGIN_S`] ahead); the worst lateness.
    pub screw_late: u64,
    pub screw_late_worst_ticks: u64,
    /// States received since [`McuSession::take_reports`] was last called.
    reports: Vec<McuState>,
    /// Holds, resumes, drops and resets waiting for room in the link's window: they go
    /// ahead of any segment or screw command.
    controls: VecDeque<HostMessage>,
    /// Where the last segment sent ends on the plan clock, and whether it ends at rest.
    sent_end: Option<(u64, bool)>,
    /// Tag and start clock of the last segment sent.
    last_sent_tag: Option<u32>,
    last_sent_start: Option<u64>,
    /// The last screw command sent (as sent): a compact one is told relative to it.
    last_screw_sent: Option<ScrewReference>,
    error: Option<SessionError>,
    /// Where the session's RESET is: until the MCU reports a state without a fault after
    /// it, a fault it reports may be one the RESET clears (latched before this session, told
    /// in states that waited in the line or were on their way), and does not count unless it
    /// outlasts [`McuSession::reset_clear_bound_s`].
    reset: ResetProgress,
    /// An emergency stop was asked for, and when it last went out.
    emergency: bool,
    emergency_sent_us: Option<u64>,
}

/// How far ahead of the MCU's plan clock (as the host estimates it) a screw command must
/// start: the MCU's generator runs ahead of its timer (2 ms on the RP2040) and a frame takes
/// a few ms to arrive, more when it is resent. A command that would start sooner — the
/// screw driver's, say, for a pin opening before the plan's first move — starts this far
/// ahead instead: late material, reported. One that still arrives late (resent on a damaged
/// line) the MCU starts at arrival (PROTOCOL.md, SCREW). While the plan clock stands (held,
/// or waiting at rest for the next segment) there is no margin: the MCU takes a command up
/// where it stands, whenever it arrives.
pub const SCREW_MARGIN_S: f64 = 0.02;

/// Plan time sent at once: nothing is sent until something lies within the horizon less
/// this (a quarter of the horizon if that is less), and then everything within the horizon
/// goes. Sent as it came (a segment or two per millisecond tick), the messages filled frames
/// a third; in bursts they fill them.
pub const FEED_BATCH_S: f64 = 0.25;

/// Clock samples the fit keeps: 51 s of them at the default query period. A long window
/// averages the round trips' jitter out of the rate (over 3 s, ±120 ppm on a pty at 1×; the
/// crystal's drift is far slower than the window).
const CLOCK_SAMPLES: usize = 512;

/// Clock samples taken at `clock_query_period_s` before queries slow down: 10 s at 0.1 s, the
/// time the fit takes to come within about 10 ppm of a crystal's rate on a pty.
pub const CLOCK_SETTLE_SAMPLES: usize = 100;

fn ticks(seconds: f64, hz: f64) -> u32 {
    (seconds * hz).round().clamp(0.0, u32::MAX as f64) as u32
}

impl McuSession {
    /// `nonce`: random per host session.
    pub fn new(options: SessionOptions, nonce: u32) -> McuSession {
        let endpoint = HostEndpoint::new((options.retransmit_timeout_s * 1e6) as u64, nonce)
            .pack_for((options.pack_s * 1e6) as u64);
        McuSession {
            options,
            endpoint,
            clock: ClockSync::new(1e6, CLOCK_SAMPLES),
            identity: None,
            configured: false,
            first_tick_us: None,
            was_ready: false,
            queries: VecDeque::new(),
            next_token: 1,
            next_query_us: 0,
            schedule: None,
            segments: VecDeque::new(),
            screw: VecDeque::new(),
            state: None,
            sent_since_state: 0,
            on_mcu: VecDeque::new(),
            screw_on_mcu: VecDeque::new(),
            held_back: false,
            screw_late: 0,
            screw_late_worst_ticks: 0,
            controls: VecDeque::new(),
            reports: Vec::new(),
            sent_end: None,
            last_sent_tag: None,
            last_sent_start: None,
            last_screw_sent: None,
            error: None,
            reset: ResetProgress::NotSent,
            emergency: false,
            emergency_sent_us: None,
        }
    }

    /// How long a fault may still be reported after a RESET before it is taken as one the
    /// RESET could not clear: the silence bound, four times over (a RESET resent on a
    /// damaged line, and the state after it).
    fn reset_clear_bound_s(&self) -> f64 {
        4.0 * (10.0 * self.options.state_period_s).max(self.options.silence_s)
    }

    pub fn options(&self) -> &SessionOptions {
        &self.options
    }

    pub fn identity(&self) -> Option<&Identity> {
        self.identity.as_ref()
    }

    pub fn clock_sync(&self) -> &ClockSync {
        &self.clock
    }

    /// The MCU's last state.
    pub fn state(&self) -> Option<&McuState> {
        self.state.as_ref().map(|(s, _)| s)
    }

    /// Every state the MCU reported since the last call, oldest first (the positions at
    /// each report, for a caller that publishes them all).
    pub fn take_reports(&mut self) -> Vec<McuState> {
        std::mem::take(&mut self.reports)
    }

    pub fn error(&self) -> Option<&SessionError> {
        self.error.as_ref()
    }

    pub fn endpoint(&self) -> &HostEndpoint {
        &self.endpoint
    }

    /// The MCU has acted on this session's RESET: a fault it reports is a fault now (before,
    /// it may be one the RESET clears).
    pub fn faults_count(&self) -> bool {
        self.reset == ResetProgress::Done
    }

    /// Identified, configured and clock-synchronised: ready to take a plan.
    pub fn is_ready(&self) -> bool {
        // (Asked of the identity, not of the error: an operator's reset clears that.)
        self.identity
            .is_some_and(|i| i.protocol_version == PROTOCOL_VERSION && can_run_a_plan(&i))
            && self.configured
            && self.clock.fit().is_some()
            && self.state.is_some()
            && self.reset == ResetProgress::Done
    }

    /// The first thing [`McuSession::is_ready`] still waits for, as a user would look for it.
    fn missing_for_ready(&self) -> &'static str {
        if !self.endpoint.link().is_synced() {
            "its link never synchronised (no answer to SYNC_REQUEST: is this the MCU, at this baud rate?)"
        } else if self.identity.is_none() {
            "no answer to IDENTIFY"
        } else if !self.configured {
            "not configured (its protocol version is not ours, or it cannot run a plan)"
        } else if self.clock.fit().is_none() {
            "too few answers to clock queries for a clock fit"
        } else if self.state.is_none() {
            "no state report"
        } else {
            "its RESET was not acted on"
        }
    }

    /// Whether the last feed left segments waiting because the MCU's queue or the horizon
    /// had no room for them: the plan is not short, however little the MCU holds.
    pub fn plan_held_back(&self) -> bool {
        self.held_back
    }

    /// Segments and screw ramps converted and not yet sent.
    pub fn waiting(&self) -> (usize, usize) {
        (self.segments.len(), self.screw.len())
    }

    /// Everything converted has been sent and played: the MCU is idle after the last one.
    pub fn is_drained(&self) -> bool {
        // A screw command past the plan's end would never take effect (the plan clock
        // stands there); every other one must be out.
        let end = self.schedule.as_ref().map_or(0, Schedule::end_clock);
        self.segments.is_empty()
            && self.screw.iter().all(|ramp| ramp.start_clock > end)
            && self.state().is_some_and(|s| {
                self.idle_after_last_sent(s) && self.last_sent_tag.is_none_or(|t| s.done_tag == t)
            })
    }

    /// Whether `state` shows the MCU idle with the last segment sent taken up and played,
    /// not idle from before it arrived: a state can be a period old, and an MCU keeps its
    /// done tag across runs (the same file printed twice ends on the same tag). Its plan
    /// clock tells: idle, it stands where the schedule ends, which is the last segment's end
    /// once that was played. (Not its start: an MCU that ran dry at rest stands exactly
    /// there, where the plan goes on, and its state from before the segment arrived passed
    /// for one after it.) A segment without duration ends where it starts: its tag tells.
    pub fn idle_after_last_sent(&self, state: &McuState) -> bool {
        state.mode == Mode::Idle
            && match (self.last_sent_start, self.sent_end) {
                (Some(start), Some((end, _))) => {
                    state.plan_clock >= end
                        && (end > start || self.last_sent_tag.is_none_or(|t| state.done_tag == t))
                }
                _ => true,
            }
    }

    /// MCU plan clock at which the last segment sent starts.
    pub fn sent_until_clock(&self) -> Option<u64> {
        self.last_sent_start
    }

    /// MCU plan clock of plan time 0, once the first segment fixed it.
    pub fn anchor_clock(&self) -> Option<u64> {
        self.schedule.as_ref().map(|s| s.clock_at(0.0))
    }

    /// The MCU's plan clock at host time `now_us` (estimated), once known.
    pub fn mcu_plan_clock_at(&self, now_us: u64) -> Option<u64> {
        let (state, _) = self.state?;
        let mcu_now = self.clock.mcu_at(now_us as i64 * 1000)?;
        let lag = state.clock.saturating_sub(state.plan_clock);
        if self.plan_clock_stands(&state) {
            return Some(state.plan_clock);
        }
        Some(mcu_now.saturating_sub(lag))
    }

    /// Held, or idle inside the schedule (ran dry at rest, waiting for the next segment):
    /// the plan clock stands. (Faulted, the MCU moves it on, but nothing is scheduled any
    /// more: taken as standing.)
    fn plan_clock_stands(&self, state: &McuState) -> bool {
        let waiting = state.mode == Mode::Idle && self.last_sent_tag.is_some();
        state.mode == Mode::Held || state.mode == Mode::Fault || waiting
    }

    /// A planned segment: converted now, sent when the horizon and the MCU's queue allow.
    /// Where it ends on the MCU's plan clock.
    pub fn on_segment(&mut self, seg: &StepSegment, now_us: u64) -> Result<u64, SessionError> {
        let hz = self.timer_hz();
        if self.schedule.is_none() {
            let anchor =
                self.mcu_plan_clock_at(now_us).unwrap_or(0) + ticks(self.options.lead_s, hz) as u64;
            self.schedule = Some(Schedule::new(hz, self.options.screw_hold, anchor));
        }
        let schedule = self.schedule.as_mut().expect("anchored above");
        let queued = schedule.segment(seg)?;
        self.segments.push_back(queued);
        Ok(queued.start_clock + queued.duration_ticks as u64)
    }

    /// The plan's input ended: what the screw's hold still owes goes out.
    pub fn finish_input(&mut self) {
        if let Some(ramp) = self.schedule.as_mut().and_then(Schedule::finish_screw) {
            self.screw.push_back(ramp);
        }
    }

    /// Where the last segment sent to the MCU ends on its plan clock, and whether it ends at
    /// rest: what the MCU can play before it runs dry (lost frames are sent again).
    pub fn sent_end(&self) -> Option<(u64, bool)> {
        self.sent_end
    }

    /// MCU plan clock where the segments converted so far end.
    pub fn schedule_end_clock(&self) -> Option<u64> {
        self.schedule.as_ref().map(Schedule::end_clock)
    }

    /// Plan time (s) at MCU plan clock `clock`, once the schedule is anchored.
    pub fn plan_s_at(&self, clock: u64) -> Option<f64> {
        self.schedule.as_ref().map(|s| s.plan_s_at(clock))
    }

    /// Forget the plan here and on the MCU (at rest: a cancel after its hold). The next
    /// segment starts a new schedule.
    pub fn drop_plan(&mut self) -> Result<(), LinkError> {
        self.forget_plan();
        self.control(HostMessage::DropQueue)
    }

    /// Leave a fault or an emergency stop: the MCU clears it and its queues, and so does the
    /// host; the next segment starts a new schedule.
    pub fn reset(&mut self) -> Result<(), LinkError> {
        self.forget_plan();
        self.error = None;
        self.emergency = false;
        // A hold or drop still waiting is moot after a reset.
        self.controls.clear();
        // A RESET only to an MCU configured by this session: one not yet configured gets its
        // RESET with CONFIGURE, and one speaking another version (or unable to run a plan)
        // none, since it may read it as anything.
        if self.configured {
            self.control(HostMessage::Reset)?;
            // The last state's arrival stands for now; the bound is generous against it.
            self.reset = ResetProgress::Sent {
                at_us: self.state.map_or(0, |(_, at)| at),
            };
        }
        Ok(())
    }

    fn forget_plan(&mut self) {
        self.segments.clear();
        self.screw.clear();
        self.schedule = None;
        self.on_mcu.clear();
        self.screw_on_mcu.clear();
        self.sent_end = None;
        self.last_sent_tag = None;
        self.last_sent_start = None;
        self.last_screw_sent = None;
    }

    /// A screw command in force from plan time `plan_s` (needs the first segment's anchor).
    pub fn on_screw(
        &mut self,
        cmd: &ScrewCommand,
        plan_s: f64,
        now_us: u64,
    ) -> Result<(), SessionError> {
        let earliest = self.mcu_plan_clock_at(now_us).unwrap_or(0);
        if let Some(schedule) = self.schedule.as_mut() {
            if let Some(ramp) = schedule.screw(cmd, plan_s, earliest)? {
                self.screw.push_back(ramp);
            }
        }
        Ok(())
    }

    /// The fastest change of the feed scale σ (per second) that keeps every joint within its
    /// acceleration limit anywhere in `q`.
    ///
    /// Under σ, joint `j` (a share `c = T_j/N` of the dominant axis, whose plan-time rate is
    /// `R` and acceleration `a`) accelerates at `c·(σ²·a + σ̇·R)`; with `|σ²·a| ≤ |a|` that
    /// stays within `A_j` when `|σ̇| ≤ (A_j/c − |a|)/R` at the segment's highest rate `R`.
    fn sigma_rate_bound(&self, q: &QueuedSegment) -> f64 {
        let hz = self.timer_hz();
        let seg = &q.segment;
        let n = seg.dominant_steps() as f64;
        if n == 0.0 {
            return f64::INFINITY;
        }
        let q32 = step_core::ONE_TICK_Q32 as f64;
        let first_period_ticks = seg.first_period_q32 as f64 / q32;
        let v0 = hz / first_period_ticks;
        // r·p² at the first step gives r; the dominant acceleration is r·hz² (steps/s²).
        let r = seg.first_ramp_q62 as f64
            / (1u64 << 62) as f64
            / (first_period_ticks * first_period_ticks);
        let a = r * hz * hz;
        let v_peak = (v0 * v0 + 2.0 * a * seg.accelerate_steps as f64).sqrt();
        let rate = v0.max(v_peak);
        (0..3)
            .filter(|&j| seg.step_counts[j] > 0)
            .map(|j| {
                let share = seg.step_counts[j] as f64 / n;
                let limit = self.options.joint_accelerations[j] * self.options.steps_per_unit[j];
                // The planner plans within 90 % of each limit (its acceleration_safety); a
                // ramp that says more is a one- or two-step ramp whose nominal rate never
                // lasts, and the hold keeps that margin there.
                ((limit / share - a).max(0.1 * limit / share)) / rate
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// The rate (per second) at which a hold or resume changes σ now: the slowest that
    /// every segment on the MCU allows.
    pub fn sigma_rate_per_s(&self) -> f64 {
        let rho = self
            .on_mcu
            .iter()
            .map(|&(_, bound)| bound)
            .fold(f64::INFINITY, f64::min);
        // Nothing moving: stop (and start) within a millisecond.
        if rho.is_finite() {
            rho
        } else {
            1000.0
        }
    }

    fn sigma_rate_q32(&self) -> u32 {
        (self.sigma_rate_per_s() / self.timer_hz() * step_core::ONE_TICK_Q32 as f64)
            .clamp(1.0, u32::MAX as f64) as u32
    }

    /// Feed hold: the MCU slows along the path to rest, every joint within its limits.
    pub fn pause(&mut self) -> Result<(), LinkError> {
        let rate_q32 = self.sigma_rate_q32();
        self.control(HostMessage::FeedHold { rate_q32 })
    }

    /// Leave a hold: the pin reopens, after its delay the MCU speeds back up along the path.
    pub fn resume(&mut self) -> Result<(), LinkError> {
        let rate_q32 = self.sigma_rate_q32();
        let delay_ticks = ticks(self.options.pin_open_delay_s, self.timer_hz());
        self.control(HostMessage::FeedResume {
            rate_q32,
            delay_ticks,
        })
    }

    /// Stop at once: the MCU stops every output on the first frame that reaches it; sent at
    /// once, then every retransmit timeout until the MCU reports a fault.
    pub fn emergency_stop(&mut self) {
        self.emergency = true;
        self.emergency_sent_us = None;
        self.controls.clear(); // nothing held back may follow the stop (a resume least)
        self.segments.clear();
        self.screw.clear();
    }

    /// The MCU's timer frequency (Hz; 1 MHz until it identified itself).
    pub fn timer_hz(&self) -> f64 {
        self.identity.map_or(1e6, |i| i.timer_hz as f64)
    }

    /// Bytes read from the MCU at `now_us`.
    pub fn receive(&mut self, bytes: &[u8], now_us: u64) {
        let mut arrived = Vec::new();
        self.endpoint
            .receive(bytes, now_us, &mut |m| arrived.push(m));
        for message in arrived {
            match message {
                FromMcu::Message(McuMessage::Identity(identity)) => {
                    if identity.protocol_version != PROTOCOL_VERSION {
                        self.fail(SessionError::Version {
                            mcu: identity.protocol_version,
                        });
                    } else if !can_run_a_plan(&identity) {
                        self.fail(SessionError::Unusable {
                            timer_hz: identity.timer_hz,
                            queue_capacity: identity.queue_capacity,
                            screw_queue_capacity: identity.screw_queue_capacity,
                        });
                    }
                    self.clock = ClockSync::new(identity.timer_hz.max(1) as f64, CLOCK_SAMPLES);
                    self.identity = Some(identity);
                }
                FromMcu::Message(McuMessage::Clock { token, clock }) => {
                    while let Some(&(t, sent_us)) = self.queries.front() {
                        if t == token {
                            self.clock
                                .add(sent_us as i64 * 1000, now_us as i64 * 1000, clock);
                        }
                        self.queries.pop_front();
                        if t == token {
                            break;
                        }
                    }
                }
                FromMcu::Message(McuMessage::State(state)) => {
                    let newer = self.state.is_none_or(|(s, _)| state.clock >= s.clock);
                    if newer {
                        self.state = Some((state, now_us));
                        if self.reports.len() < 1024 {
                            self.reports.push(state);
                        }
                        self.sent_since_state = 0;
                        while self
                            .on_mcu
                            .front()
                            .is_some_and(|&(end, _)| end <= state.plan_clock)
                        {
                            self.on_mcu.pop_front();
                        }
                        // Taken up by the plan clock: out of the MCU's screw queue.
                        while self
                            .screw_on_mcu
                            .front()
                            .is_some_and(|&start| start <= state.plan_clock)
                        {
                            self.screw_on_mcu.pop_front();
                        }
                    }
                    if state.mode != Mode::Fault {
                        if let ResetProgress::Sent { .. } = self.reset {
                            self.reset = ResetProgress::Done; // the RESET has been acted on
                        }
                    } else if self.error.is_none() && self.reset == ResetProgress::Done {
                        self.fail(SessionError::Fault {
                            code: state.fault,
                            clock: state.clock,
                            tag: 0,
                        });
                    }
                }
                // A fault told before the RESET it awaits was acted on: the RESET clears it
                // (and a fault that outlasts it shows in the states).
                FromMcu::Message(McuMessage::Fault { .. }) if self.reset != ResetProgress::Done => {
                }
                FromMcu::Message(McuMessage::Fault { code, clock, tag }) => {
                    self.fail(SessionError::Fault { code, clock, tag });
                }
                FromMcu::Message(McuMessage::Counters(_)) | FromMcu::Undecodable => {}
                FromMcu::Restarted { lost } => {
                    self.fail(SessionError::Restarted { lost });
                    // A new MCU session: its clock began again, it knows no configuration,
                    // it may even run other firmware. Learn it all again (the error stays
                    // until the operator's reset), or a reset could never bring it back.
                    self.identity = None;
                    self.configured = false;
                    self.state = None;
                    self.queries.clear();
                    self.clock.reset();
                    self.reset = ResetProgress::NotSent;
                    self.forget_plan();
                }
            }
        }
    }

    fn fail(&mut self, error: SessionError) {
        // The first error explains; a fault report after an emergency stop is its echo.
        if self.error.is_none() {
            self.error = Some(error);
        }
        self.segments.clear();
        self.screw.clear();
    }

    /// Periodic work at `now_us`: identify and configure, clock queries, feed the plan.
    pub fn tick(&mut self, now_us: u64) -> Result<(), LinkError> {
        let first_tick_us = *self.first_tick_us.get_or_insert(now_us);
        if self.is_ready() {
            self.was_ready = true;
        } else if !self.was_ready && self.error.is_none() {
            let waited_s = now_us.saturating_sub(first_tick_us) as f64 * 1e-6;
            if waited_s > self.options.answer_timeout_s {
                let missing = self.missing_for_ready();
                self.fail(SessionError::NoAnswer { waited_s, missing });
            }
        }
        // An MCU that stops reporting (hung, unplugged) cannot be trusted to be moving as
        // planned: after ten state periods (at least `silence_s`), it is a fault.
        if let Some((_, at)) = self.state {
            let silent_s = now_us.saturating_sub(at) as f64 * 1e-6;
            let bound_s = (10.0 * self.options.state_period_s).max(self.options.silence_s);
            if self.configured && silent_s > bound_s && self.error.is_none() {
                self.fail(SessionError::Silent { silent_s });
                // Unheard is not stopped: an MCU whose reports no longer arrive (its TX
                // wire, its USB endpoint) may still hear us and play its queue; our clock
                // queries would feed its watchdog while it runs dry at speed. Stop it, as
                // often as the stop goes unconfirmed.
                self.emergency_stop();
            }
        }
        if !self.endpoint.link().is_synced() {
            return Ok(()); // the link is still starting; poll_transmit sends its requests
        }
        if self.identity.is_none() && self.endpoint.unacknowledged() == 0 {
            self.endpoint.send(&HostMessage::Identify)?;
            return Ok(());
        }
        let Some(identity) = self.identity else {
            return Ok(());
        };
        let hz = identity.timer_hz as f64;
        // An MCU speaking another version may read CONFIGURE and RESET as anything (asked
        // of its identity, not of the error: a reset clears that, and an earlier one hides it).
        if !self.configured
            && identity.protocol_version == PROTOCOL_VERSION
            && can_run_a_plan(&identity)
        {
            self.endpoint.send(&HostMessage::Configure {
                host_timeout_ticks: ticks(self.options.host_timeout_s, hz),
                state_period_ticks: ticks(self.options.state_period_s, hz),
            })?;
            // A clean slate: no fault and no schedule left from an earlier host session (a
            // host that went away leaves the MCU latched in HOST_SILENT, still reporting it).
            self.endpoint.send(&HostMessage::Reset)?;
            self.reset = ResetProgress::Sent { at_us: now_us };
            self.configured = true;
        }
        if let ResetProgress::Sent { at_us } = self.reset {
            let waited_s = now_us.saturating_sub(at_us) as f64 * 1e-6;
            let latched = self.state.filter(|(s, _)| s.mode == Mode::Fault);
            if let Some((state, _)) = latched.filter(|_| waited_s > self.reset_clear_bound_s()) {
                self.reset = ResetProgress::Done;
                self.fail(SessionError::FaultNotCleared {
                    code: state.fault,
                    waited_s,
                });
            }
        }
        if now_us >= self.next_query_us && self.endpoint.can_send() {
            // Queries are the idle host's keep-alive: four per host timeout at least.
            let period_s = if self.clock.sample_count() >= CLOCK_SETTLE_SAMPLES {
                self.options.clock_query_settled_period_s
            } else {
                self.options.clock_query_period_s
            }
            .min(self.options.host_timeout_s / 4.0);
            self.next_query_us = now_us + (period_s * 1e6) as u64;
            let token = self.next_token;
            self.next_token = self.next_token.wrapping_add(1);
            self.endpoint.send(&HostMessage::ClockQuery { token })?;
            self.queries.push_back((token, now_us));
            if self.queries.len() > 64 {
                self.queries.pop_front(); // answers lost with a restarted MCU
            }
        }
        self.feed(now_us)
    }

    /// Send `message` now, or as soon as the window has room (before anything else).
    fn control(&mut self, message: HostMessage) -> Result<(), LinkError> {
        self.controls.push_back(message);
        self.send_controls()
    }

    fn send_controls(&mut self) -> Result<(), LinkError> {
        while let Some(message) = self.controls.front() {
            if !self.endpoint.can_send() {
                break;
            }
            self.endpoint.send(message)?;
            self.controls.pop_front();
        }
        Ok(())
    }

    fn feed(&mut self, now_us: u64) -> Result<(), LinkError> {
        self.held_back = false;
        self.send_controls()?;
        if !self.controls.is_empty() {
            return Ok(()); // the window is full: controls first
        }
        let Some(plan_now) = self.mcu_plan_clock_at(now_us) else {
            return Ok(());
        };
        let Some((state, _)) = self.state else {
            return Ok(());
        };
        let horizon = ticks(self.options.horizon_s, self.timer_hz()) as u64;
        let batch = ticks(
            FEED_BATCH_S.min(self.options.horizon_s / 4.0),
            self.timer_hz(),
        ) as u64;
        let due_line = plan_now + horizon - batch;
        let due = self
            .segments
            .front()
            .is_some_and(|s| s.start_clock <= due_line)
            || self
                .screw
                .front()
                .is_some_and(|r| r.start_clock <= due_line);
        if !due {
            self.held_back = !self.segments.is_empty();
            return Ok(());
        }
        // Room in the MCU's queue: what its last state reported less what was sent since,
        // and never more than its capacity less every segment sent that its plan clock has
        // not yet passed — a state taken while segments were still on the line does not
        // count them, and clearing `sent_since_state` on it alone overfilled the queue
        // (QUEUE_OVERFLOW on the emulated RP2040, short segments at the cell's top rates).
        let capacity = self.identity.map_or(0, |i| i.queue_capacity as usize);
        let mut room = (state.queue_free as usize)
            .saturating_sub(self.sent_since_state)
            .min(capacity.saturating_sub(self.on_mcu.len()));
        while let Some(next) = self.segments.front() {
            if room == 0 || next.start_clock > plan_now + horizon {
                self.held_back = true;
                break;
            }
            if !self.endpoint.can_send() {
                break;
            }
            let next = *next;
            // Continuing the schedule, the compact form (if the segment has one) leaves out
            // the start and the tag: the MCU knows both.
            let compact = match (self.sent_end, self.last_sent_tag) {
                (Some((end, _)), Some(tag)) => NextSegment::after(end, tag, &next),
                _ => None,
            };
            self.endpoint.send(&match compact {
                Some(compact) => HostMessage::NextSegment(compact),
                None => HostMessage::QueueSegment(next),
            })?;
            if next.start_clock < plan_now + horizon / 2 {
                self.endpoint.flush_soon(); // the plan runs short: no waiting to pack
            }
            self.segments.pop_front();
            let end = next.start_clock + next.duration_ticks as u64;
            self.on_mcu.push_back((end, self.sigma_rate_bound(&next)));
            self.sent_since_state += 1;
            self.last_sent_tag = Some(next.tag);
            self.last_sent_start = Some(next.start_clock);
            self.sent_end = Some((end, next.flags & SEGMENT_ENDS_AT_REST != 0));
            room -= 1;
        }
        let screw_capacity = self.identity.map_or(0, |i| i.screw_queue_capacity as usize);
        while let Some(ramp) = self.screw.front() {
            // One place kept free: a command due exactly at the state's plan clock may not
            // have been taken up yet.
            let full = self.screw_on_mcu.len() + 1 >= screw_capacity;
            if full || ramp.start_clock > plan_now + horizon || !self.endpoint.can_send() {
                break;
            }
            let mut ramp = *ramp;
            // A standing plan clock is where the MCU will take the command up, however long
            // the line takes (a margin past it would wait for the next segment, or for ever).
            let margin = if self.plan_clock_stands(&state) {
                0
            } else {
                ticks(SCREW_MARGIN_S, self.timer_hz()) as u64
            };
            let earliest = (plan_now + margin).max(self.screw_on_mcu.back().copied().unwrap_or(0));
            if ramp.start_clock < earliest {
                // Keep where a ramp ends; start it when the MCU can take it.
                let end = ramp.start_clock + ramp.ramp_ticks as u64;
                self.screw_late += 1;
                self.screw_late_worst_ticks =
                    self.screw_late_worst_ticks.max(earliest - ramp.start_clock);
                ramp.ramp_ticks = end.saturating_sub(earliest).min(u32::MAX as u64) as u32;
                ramp.start_clock = earliest;
            }
            let compact = self
                .last_screw_sent
                .and_then(|last| Some((ScrewNext::after(&last, &ramp)?, last)));
            self.last_screw_sent = Some(match compact {
                Some((compact, last)) => {
                    self.endpoint.send(&HostMessage::ScrewNext(compact))?;
                    compact.reference_after(&last)
                }
                None => {
                    self.endpoint.send(&HostMessage::Screw(ramp))?;
                    ScrewReference::of_screw(&ramp)
                }
            });
            if ramp.start_clock < plan_now + horizon / 2 {
                self.endpoint.flush_soon();
            }
            self.screw.pop_front();
            self.screw_on_mcu.push_back(ramp.start_clock);
        }
        Ok(())
    }

    /// The next bytes to write at `now_us`; call until `None`.
    pub fn poll_transmit(&mut self, now_us: u64, out: &mut [u8; MAX_WIRE_FRAME]) -> Option<usize> {
        if self.emergency {
            // Any latched fault has stopped the outputs; an MCU already faulted keeps its
            // first fault, so waiting for EMERGENCY_STOP itself would repeat it for ever. (A
            // report from after the stop went out: the one before may be a fault a reset
            // has just cleared.)
            let stopped = self.state.as_ref().is_some_and(|(s, received_us)| {
                s.fault != FaultCode::None
                    && self
                        .emergency_sent_us
                        .is_some_and(|sent| *received_us > sent)
            });
            let due = self.emergency_sent_us.is_none_or(|at| {
                now_us.saturating_sub(at) >= (self.options.retransmit_timeout_s * 1e6) as u64
            });
            if stopped {
                self.emergency = false;
            } else if due {
                // Unsequenced: it acts even behind a lost frame; repeated until reported.
                self.emergency_sent_us = Some(now_us);
                return self
                    .endpoint
                    .encode_now(&HostMessage::EmergencyStop, out)
                    .ok();
            }
        }
        self.endpoint.poll_transmit(now_us, out)
    }
}

#[cfg(test)]
mod tests;
