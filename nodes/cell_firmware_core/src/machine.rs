//! The machine: segments on the plan clock, played through the shared step core, with feed
//! hold and resume, positions, the screw, faults and the host watchdog.
//!
//! # Two clocks
//!
//! The *MCU clock* counts timer ticks. The *plan clock* is the schedule's: segment and screw
//! start clocks are on it. It runs at the feed scale σ per tick (Q32, 1 = 2³²): equal to the
//! MCU clock until a feed hold slows it to a stop, behind it by the time lost afterwards. A
//! pulse the step core times at plan instant `P` goes out at the first MCU tick whose plan
//! clock, plus half a tick, is beyond `P` — at σ = 1 exactly the tick nearest `P`, so the
//! edges equal the host decoder's to the tick.
//!
//! When the queue runs dry at the end of a segment that ends at rest (the host had nothing
//! more yet), the plan clock stands at that end until the next segment arrives: the schedule
//! continues there, and plan time stays the plan's time however long the gap. Only a drop,
//! a reset or a fault ends a schedule; a new one may start at any clock not yet passed.
//!
//! # Running ahead
//!
//! [`Machine::advance`] generates everything up to an MCU clock and hands each step edge to a
//! sink with its tick. A firmware runs it a little ahead of real time into an edge buffer
//! that its timer drains at the exact ticks; the emulator and the tests run it to "now".
//! Checks on arrival (late segment, screw) are against the generated clock: what is already
//! generated cannot change.
//!
//! At σ = 1 it jumps from event to event (pulses, segment ends, the watchdog); during a hold
//! or resume it walks tick by tick (additions only), which costs a few instructions per tick
//! for the fraction of a second a ramp lasts.

use cell_protocol::message::{
    FaultCode, HostMessage, Identity, McuMessage, McuState, Mode, QueuedSegment, ScrewRamp,
    ScrewReference, SEGMENT_ENDS_AT_REST,
};
use cell_protocol::PROTOCOL_VERSION;
use heapless::Deque;
use step_core::{PulseTrain, MAX_AXES, ONE_TICK_Q32};

use crate::screw::{Screw, ScrewRefusal};

const ONE: u64 = ONE_TICK_Q32;
const HALF: u128 = (ONE / 2) as u128;

/// How the machine is built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MachineConfig {
    /// MCU clock and step timer frequency.
    pub timer_hz: u32,
    /// Steppers driven (1..=3).
    pub axis_count: u8,
    /// Step position of each axis at power-up.
    pub initial_steps: [i32; MAX_AXES],
}

/// One step edge: the axes in `axes` step at MCU tick `clock`, those in `negative` backwards.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StepEdge {
    pub clock: u64,
    pub axes: u8,
    pub negative: u8,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ramp {
    /// σ constant (1 running, 0 held).
    Steady,
    /// σ falls by `rate` per tick to 0.
    Hold { rate: u64 },
    /// At rest, pin open again, until MCU tick `until`; then [`Ramp::Resume`].
    ResumeWait { rate: u64, until: u64 },
    /// σ rises by `rate` per tick to 1.
    Resume { rate: u64 },
}

/// The segment being played.
#[derive(Clone, Debug)]
struct Playing {
    queued: QueuedSegment,
    train: PulseTrain,
}

impl Playing {
    fn start_q32(&self) -> u128 {
        (self.queued.start_clock as u128) << 32
    }
    fn end_q32(&self) -> u128 {
        ((self.queued.start_clock + self.queued.duration_ticks as u64) as u128) << 32
    }
}

/// Counters the MCU reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MachineCounters {
    pub underruns: u32,
    pub late_segments: u32,
}

/// The machine, with room for `Q` queued segments and `S` screw commands.
#[derive(Clone, Debug)]
pub struct Machine<const Q: usize, const S: usize> {
    config: MachineConfig,
    /// MCU tick generated up to (inclusive).
    clock: u64,
    /// Plan clock at `clock`, Q32.
    plan_q32: u128,
    sigma_q32: u64,
    ramp: Ramp,
    playing: Option<Playing>,
    queue: Deque<QueuedSegment, Q>,
    /// Plan tick where the last accepted segment ends (the next must start there).
    schedule_end: Option<u64>,
    /// Tag of the last accepted segment: a compact next segment's tag counts on from it.
    schedule_tag: u32,
    /// The last accepted screw command as sent (its start before a late arrival moved it):
    /// a compact one is told relative to it.
    screw_reference: Option<ScrewReference>,
    positions: [i32; MAX_AXES],
    /// The tick of the last step edge: a pin takes one edge per tick, so a second pulse due
    /// in the same tick is a fault, never an edge lost downstream.
    last_edge_clock: Option<u64>,
    done_tag: u32,
    screw: Screw<S>,
    fault: FaultCode,
    /// A latched fault not yet reported to the host.
    unreported_fault: Option<McuMessage>,
    host_timeout_ticks: u32,
    state_period_ticks: u32,
    last_host_frame: u64,
    counters: MachineCounters,
}

impl<const Q: usize, const S: usize> Machine<Q, S> {
    pub fn new(config: MachineConfig) -> Machine<Q, S> {
        Machine {
            config,
            clock: 0,
            plan_q32: 0,
            sigma_q32: ONE,
            ramp: Ramp::Steady,
            playing: None,
            queue: Deque::new(),
            schedule_end: None,
            schedule_tag: 0,
            screw_reference: None,
            positions: config.initial_steps,
            last_edge_clock: None,
            done_tag: 0,
            screw: Screw::new(),
            fault: FaultCode::None,
            unreported_fault: None,
            host_timeout_ticks: 0,
            state_period_ticks: 0,
            last_host_frame: 0,
            counters: MachineCounters::default(),
        }
    }

    pub fn config(&self) -> &MachineConfig {
        &self.config
    }

    /// MCU tick generated up to.
    pub fn clock(&self) -> u64 {
        self.clock
    }

    /// Plan clock (whole ticks) at [`Machine::clock`].
    pub fn plan_clock(&self) -> u64 {
        (self.plan_q32 >> 32) as u64
    }

    pub fn positions(&self) -> [i32; MAX_AXES] {
        self.positions
    }

    pub fn counters(&self) -> MachineCounters {
        self.counters
    }

    pub fn fault(&self) -> FaultCode {
        self.fault
    }

    /// Whether a host has configured the machine since power-up (its watchdog or state
    /// reports): from then on the host owns it, and the start switch is ignored.
    pub fn host_configured(&self) -> bool {
        self.host_timeout_ticks != 0 || self.state_period_ticks != 0
    }

    /// How often the host wants a state message (0: only on query).
    pub fn state_period_ticks(&self) -> u32 {
        self.state_period_ticks
    }

    /// Free places in the segment queue.
    pub fn queue_free(&self) -> usize {
        Q - self.queue.len()
    }

    pub fn mode(&self) -> Mode {
        if self.fault != FaultCode::None {
            Mode::Fault
        } else if self.sigma_q32 == 0 && matches!(self.ramp, Ramp::Steady) {
            Mode::Held
        } else if !matches!(self.ramp, Ramp::Steady) {
            Mode::Ramping
        } else if self.playing.is_some() || !self.queue.is_empty() {
            Mode::Running
        } else {
            Mode::Idle
        }
    }

    /// Screw speed to output now: the schedule's, scaled by σ (material follows the path's
    /// speed), 0 in a fault.
    pub fn screw_millirpm(&self) -> i32 {
        ((self.screw.millirpm() as i64 * self.sigma_q32 as i64) >> 32) as i32
    }

    /// MCU ticks at least until the next queued screw command takes effect (0: at the next
    /// advance), if one is queued and the plan clock moves. The plan clock runs at most as
    /// fast as the MCU's (σ ≤ 1), and through a hold's ramp at most σ as fast (σ only falls
    /// there), so a generator that advances no further than this and then samples the screw
    /// puts each command on its own tick, not wherever a generator pass happens to end.
    /// While the plan clock stands (held, waiting to resume, or run dry) no command can take
    /// effect: `None`, or a generator bounded by it would crawl a tick at a time through the
    /// whole rest.
    pub fn ticks_to_next_screw_command(&self) -> Option<u64> {
        let start = self.screw.next_start()?;
        if self.sigma_q32 == 0 || self.waiting_in_schedule() {
            return None;
        }
        Some(match self.ramp {
            Ramp::Hold { .. } => {
                // The exact plan time left (the plan clock has a fraction here), at σ now.
                let left_q32 = ((start as u128) << 32).saturating_sub(self.plan_q32);
                let ticks = left_q32.div_ceil(self.sigma_q32 as u128);
                u64::try_from(ticks).unwrap_or(u64::MAX)
            }
            _ => start.saturating_sub(self.plan_clock()),
        })
    }

    /// Pin output now: the schedule's, but closed while held at rest. While a hold slows
    /// the machine the screw turns at σ·rpm through the open pin, so every length of path
    /// gets its material, as in the virtual executor; a resume from rest opens it at once,
    /// for its delay before motion.
    pub fn pin_open(&self) -> bool {
        self.screw.pin_open() && !self.held_at_rest() && self.fault == FaultCode::None
    }

    /// σ = 0 by a hold, and staying there (not waiting out a resume's pin delay, nor just
    /// past it with σ about to rise): only a hold brings σ to 0.
    fn held_at_rest(&self) -> bool {
        self.sigma_q32 == 0 && self.ramp == Ramp::Steady
    }

    /// The state message, taken at the clock the machine has advanced to: positions, plan
    /// clock and screw are all of that instant. A firmware that generates edges ahead of its
    /// pins (`advance` to a later clock than the one its link runs on) thus reports where
    /// the generator is and when, not a position stamped with an earlier time.
    pub fn state(&self) -> McuState {
        McuState {
            clock: self.clock,
            plan_clock: self.plan_clock(),
            position_steps: self.positions,
            screw_millirpm: self.screw_millirpm(),
            screw_angle_millirev: self.screw.angle_millirev(self.config.timer_hz),
            pin_open: self.pin_open(),
            queue_free: self.queue_free().min(u16::MAX as usize) as u16,
            done_tag: self.done_tag,
            feed_scale_q16: (self.sigma_q32 >> 16).min(u16::MAX as u64) as u16,
            mode: self.mode(),
            fault: self.fault,
        }
    }

    /// A fault latched since the last call, as the message that reports it.
    pub fn take_fault_report(&mut self) -> Option<McuMessage> {
        self.unreported_fault.take()
    }

    /// A valid frame arrived at MCU clock `now`: the host is alive.
    pub fn host_frame(&mut self, now: u64) {
        self.last_host_frame = now;
    }

    /// Act on a host message at MCU clock `now`; the reply, if the message asks for one.
    pub fn handle(&mut self, message: &HostMessage, now: u64) -> Option<McuMessage> {
        match *message {
            HostMessage::Identify => {
                return Some(McuMessage::Identity(Identity {
                    protocol_version: PROTOCOL_VERSION,
                    timer_hz: self.config.timer_hz,
                    queue_capacity: Q.min(u16::MAX as usize) as u16,
                    axis_count: self.config.axis_count,
                    screw_queue_capacity: S.min(u16::MAX as usize) as u16,
                }))
            }
            HostMessage::ClockQuery { token } => {
                return Some(McuMessage::Clock { token, clock: now })
            }
            HostMessage::Configure {
                host_timeout_ticks,
                state_period_ticks,
            } => {
                self.host_timeout_ticks = host_timeout_ticks;
                self.state_period_ticks = state_period_ticks;
                self.last_host_frame = now;
            }
            HostMessage::QueueSegment(queued) => self.queue_segment(queued),
            // Without a schedule or a screw command to continue (none begun, or dropped by a
            // fault or the host), a compact form is a bad segment (a no-op once faulted).
            HostMessage::NextSegment(next) => match self.schedule_end {
                Some(end) => self.queue_segment(next.queued_after(end, self.schedule_tag)),
                None => self.latch(FaultCode::BadSegment, 0),
            },
            HostMessage::Screw(command) => {
                self.queue_screw(command, ScrewReference::of_screw(&command))
            }
            HostMessage::ScrewNext(next) => match self.screw_reference {
                Some(reference) => self.queue_screw(
                    next.ramp_after(&reference),
                    next.reference_after(&reference),
                ),
                None => self.latch(FaultCode::BadSegment, 0),
            },
            HostMessage::FeedHold { rate_q32 } => {
                if self.fault == FaultCode::None {
                    self.ramp = if self.sigma_q32 > 0 {
                        Ramp::Hold {
                            rate: (rate_q32 as u64).max(1),
                        }
                    } else {
                        Ramp::Steady // already at rest (perhaps waiting to resume): stay
                    };
                }
            }
            HostMessage::FeedResume {
                rate_q32,
                delay_ticks,
            } => {
                let holding = self.ramp != Ramp::Steady || self.sigma_q32 < ONE;
                if self.fault == FaultCode::None && holding {
                    let rate = (rate_q32 as u64).max(1);
                    self.ramp = if self.sigma_q32 == 0 {
                        Ramp::ResumeWait {
                            rate,
                            until: self.clock + delay_ticks as u64,
                        }
                    } else {
                        Ramp::Resume { rate } // never came to rest: no pin delay to wait
                    };
                }
            }
            HostMessage::DropQueue => {
                let moving = self.sigma_q32 > 0 && self.playing.is_some();
                if moving {
                    let tag = self.playing.as_ref().map_or(0, |p| p.queued.tag);
                    self.latch(FaultCode::DropWhileMoving, tag);
                } else {
                    self.clear_schedule();
                }
            }
            HostMessage::EmergencyStop => self.emergency_stop(),
            HostMessage::Reset => {
                self.clear_schedule();
                self.fault = FaultCode::None;
                self.unreported_fault = None;
                self.last_host_frame = now;
            }
            HostMessage::QueryState => return Some(McuMessage::State(self.state())),
            HostMessage::QueryCounters => {} // answered by the endpoint, which has the link's
        }
        None
    }

    /// Stop every output at once and latch the fault.
    pub fn emergency_stop(&mut self) {
        self.latch(FaultCode::EmergencyStop, 0);
    }

    /// A host message that does not decode, in a frame that passed its checks: a host that
    /// speaks another protocol, or a bug. What it was (a segment, a screw command) is lost,
    /// and the segments after a lost NEXT_* would continue from the wrong one: stop.
    pub fn bad_message(&mut self) {
        self.latch(FaultCode::BadSegment, 0);
    }

    /// Take back edges that were generated but never reached the pins: an output stage that
    /// generates ahead of its pins (the RP2040's, by its lead) drops what it still held when
    /// a fault stopped it, and the positions must say where the motors are, not where they
    /// were going. Only while stopped by a fault: in motion the edges are owed to the plan.
    pub fn discard_edges(&mut self, edges: impl IntoIterator<Item = StepEdge>) {
        if self.fault == FaultCode::None {
            return;
        }
        for edge in edges {
            move_positions(&mut self.positions, &edge, -1);
        }
    }

    /// Queue `command`; accepted, it leaves `reference` for the next compact one.
    fn queue_screw(&mut self, command: ScrewRamp, reference: ScrewReference) {
        if self.fault != FaultCode::None {
            return;
        }
        match self.screw.push(command, self.plan_clock()) {
            Ok(late) => {
                // Started at arrival (see `Screw::push`), counted with the late.
                self.counters.late_segments += u32::from(late);
                self.screw_reference = Some(reference);
            }
            Err(ScrewRefusal::OutOfOrder) => self.latch(FaultCode::BadSegment, 0),
            Err(ScrewRefusal::Full) => self.latch(FaultCode::QueueOverflow, 0),
        }
    }

    fn queue_segment(&mut self, queued: QueuedSegment) {
        if self.fault != FaultCode::None {
            return; // refused silently: the host already has the fault report
        }
        let tag = queued.tag;
        if queued.segment.check().is_err() || queued.flags & !SEGMENT_ENDS_AT_REST != 0 {
            return self.latch(FaultCode::BadSegment, tag);
        }
        match self.schedule_end {
            Some(end) if queued.start_clock != end => {
                return self.latch(FaultCode::BadSegment, tag);
            }
            None if (queued.start_clock as u128) << 32 < self.plan_q32 => {
                self.counters.late_segments += 1;
                return self.latch(FaultCode::LateSegment, tag);
            }
            _ => {}
        }
        // A start clock from the wire so late that the segment would end past the clock's
        // range: no schedule can follow it (and the sum would wrap).
        let Some(end) = queued.start_clock.checked_add(queued.duration_ticks as u64) else {
            return self.latch(FaultCode::BadSegment, tag);
        };
        if self.queue.push_back(queued).is_err() {
            return self.latch(FaultCode::QueueOverflow, tag);
        }
        self.schedule_end = Some(end);
        self.schedule_tag = tag;
    }

    /// Drop everything scheduled and stop the screw: what a fault and a drop have in common.
    fn drop_schedule(&mut self) {
        self.playing = None;
        self.queue.clear();
        self.schedule_end = None;
        self.screw_reference = None;
        self.screw.stop();
        self.ramp = Ramp::Steady;
    }

    /// Drop the schedule and be ready for a new one at full feed.
    fn clear_schedule(&mut self) {
        self.drop_schedule();
        self.sigma_q32 = ONE;
    }

    fn latch(&mut self, code: FaultCode, tag: u32) {
        if self.fault == FaultCode::None {
            self.fault = code;
            self.unreported_fault = Some(McuMessage::Fault {
                code,
                clock: self.clock,
                tag,
            });
        }
        self.drop_schedule();
    }

    /// Generate everything up to MCU tick `until`, handing each step edge to `sink`.
    pub fn advance(&mut self, until: u64, sink: &mut impl FnMut(StepEdge)) {
        while self.clock < until {
            if self.fault != FaultCode::None {
                self.plan_q32 += ((until - self.clock) as u128) << 32;
                self.clock = until;
                break;
            }
            let at_rest =
                self.sigma_q32 == 0 && matches!(self.ramp, Ramp::Steady | Ramp::ResumeWait { .. });
            if self.waiting_in_schedule() {
                // Ran dry at rest: the plan clock stands where the schedule ends, so the
                // host's next segment starts there whenever it comes (plan time = the
                // plan's time, as the virtual executor keeps it).
                // A hold or resume asked for meanwhile still ramps σ at its rate per tick
                // (applied for the whole stretch at once), so the machine is held at the same
                // tick however its caller chunks the time.
                let from = self.clock;
                self.clock = self.next_rest_event(until);
                self.ramp_over(self.clock - from);
            } else if self.sigma_q32 == ONE && self.ramp == Ramp::Steady {
                // The pulses in a tight loop up to the last one due (the pass's end then
                // handles that tick: a segment ending there, the next taken up); with none
                // due, on to the next event.
                let from = self.clock;
                self.emit_steady(until.min(self.watchdog_deadline() - 1), sink);
                if self.clock == from {
                    let next = self.next_event_tick().min(until);
                    self.plan_q32 += ((next - self.clock) as u128) << 32;
                    self.clock = next;
                }
            } else if at_rest {
                // Held: the plan clock stands; only the watchdog or the end of a resume's
                // wait can happen.
                self.clock = self.next_rest_event(until);
                self.step_ramp();
            } else {
                // Ramping: σ changes every tick, so the plan clock is stepped tick by tick,
                // in a tight loop up to whatever needs the full pass (the next pulse or
                // segment end on the plan clock, the ramp's end, the watchdog, `until`).
                // The same ticks as one tick per pass, at a few dozen cycles each: an RP2040
                // keeps up with real time through a hold.
                let target = self.next_plan_event_q32();
                let stop_at = until.min(self.watchdog_deadline());
                match self.ramp {
                    Ramp::Hold { rate } => self.walk_ramp(target, stop_at, rate, false),
                    Ramp::Resume { rate } => self.walk_ramp(target, stop_at, rate, true),
                    _ => {
                        let ramp = core::mem::discriminant(&self.ramp);
                        loop {
                            self.clock += 1;
                            self.step_ramp();
                            self.plan_q32 += self.sigma_q32 as u128;
                            if self.plan_q32 >= target
                                || self.clock >= stop_at
                                || core::mem::discriminant(&self.ramp) != ramp
                            {
                                break;
                            }
                        }
                    }
                }
            }
            self.screw.advance_to(self.plan_clock());
            self.check_watchdog();
            self.emit_due(sink);
        }
    }

    /// At σ = 1, the playing segment's pulses due by MCU tick `limit` (inclusive), in one
    /// tight loop. The plan clock is the MCU clock plus a constant here, so a pulse's tick
    /// follows from its time by a subtraction and a shift in 64 bits, without the full pass
    /// per pulse (next event, screw, watchdog in `u128` plan time), which the caller makes
    /// once after: that pass per pulse was most of the generator's cost at the top step
    /// rates. The ticks are the full pass's (tested: any chunking gives the same edges).
    fn emit_steady(&mut self, limit: u64, sink: &mut impl FnMut(StepEdge)) {
        let Some(playing) = &mut self.playing else {
            return;
        };
        // How far the plan clock (+½ tick) is past the segment's start: a pulse at `t` from
        // the start is due once this exceeds `t`. Under 2⁶³ while the segment plays (it lasts
        // under 2³¹ ticks); a segment not yet begun is left to the full pass.
        let Some(behind) = (self.plan_q32 + HALF).checked_sub(playing.start_q32()) else {
            return;
        };
        let Ok(mut behind) = u64::try_from(behind) else {
            return;
        };
        let mut clock = self.clock;
        let mut fault = None;
        while let Some(t) = playing.train.next_time_q32() {
            if t < behind {
                break; // due now: the full pass's (never, after its last `emit_due`)
            }
            let ticks = ((t - behind) >> 32) + 1;
            if clock + ticks > limit {
                break;
            }
            clock += ticks;
            behind += ticks << 32;
            let pulse = match playing.train.next_pulse() {
                Ok(Some(pulse)) => pulse,
                Ok(None) => break,
                Err(_) => {
                    fault = Some(playing.queued.tag);
                    break;
                }
            };
            let negative_mask = playing.queued.segment.negative_mask;
            self.last_edge_clock = Some(clock);
            sink(step(&mut self.positions, negative_mask, pulse.axes, clock));
        }
        self.plan_q32 += ((clock - self.clock) as u128) << 32;
        self.clock = clock;
        if let Some(tag) = fault {
            self.latch(FaultCode::StepFault, tag);
        }
    }

    /// Idle inside a schedule: the last segment ended at rest and nothing follows yet.
    fn waiting_in_schedule(&self) -> bool {
        self.playing.is_none() && self.queue.is_empty() && self.schedule_end.is_some()
    }

    /// A hold's or resume's σ ramp, tick by tick, until the plan clock reaches `target_q32`,
    /// the MCU clock `stop_at`, or σ its end (0, or 1 rising): the same ticks as
    /// [`Machine::step_ramp`] one at a time, with the loop's state in locals and 64-bit
    /// arithmetic — an RP2040 walks a tick in a few dozen cycles this way, faster than the
    /// 125 a tick lasts (the `u128` plan clock through `self` took 132, and a long hold ramp
    /// fell behind real time).
    fn walk_ramp(&mut self, target_q32: u128, stop_at: u64, rate: u64, rising: bool) {
        // How far the plan clock may move before the target (capped: far enough for any
        // stretch of ticks this call can walk).
        let room = target_q32
            .saturating_sub(self.plan_q32)
            .min(u64::MAX as u128) as u64;
        let ticks = stop_at.saturating_sub(self.clock).max(1);
        let mut sigma = self.sigma_q32;
        let mut walked = 0u64;
        let mut advanced = 0u64;
        loop {
            walked += 1;
            sigma = if rising {
                (sigma + rate).min(ONE)
            } else {
                sigma.saturating_sub(rate)
            };
            advanced = advanced.saturating_add(sigma);
            let ended = if rising { sigma == ONE } else { sigma == 0 };
            if advanced >= room || walked >= ticks || ended {
                break;
            }
        }
        self.clock += walked;
        self.plan_q32 += advanced as u128;
        self.sigma_q32 = sigma;
        if sigma == 0 || sigma == ONE {
            self.ramp = Ramp::Steady;
        }
    }

    /// The plan clock (Q32) from which `emit_due` has something to do: the next pulse
    /// (emitted once `plan + ½ > its time`), the playing segment's end, or at once when a
    /// queued segment waits to be taken up; `u128::MAX` when nothing is queued.
    fn next_plan_event_q32(&self) -> u128 {
        match &self.playing {
            Some(playing) => match playing.train.next_time_q32() {
                Some(t) => (playing.start_q32() + t as u128 + 1).saturating_sub(HALF),
                None => playing.end_q32(),
            },
            None if !self.queue.is_empty() => 0,
            None => u128::MAX,
        }
    }

    /// At σ = 1: the next MCU tick at which something happens (always after `clock`).
    fn next_event_tick(&self) -> u64 {
        // Ticks from now until the plan clock (+½ for pulses) passes `target_q32`.
        let ticks_until = |target_q32: u128, half: u128| -> u64 {
            let reached = self.plan_q32 + half;
            if reached > target_q32 {
                1
            } else {
                (((target_q32 - reached) >> 32) as u64).saturating_add(1)
            }
        };
        let mut next = u64::MAX;
        if let Some(playing) = &self.playing {
            match playing.train.next_time_q32() {
                Some(t) => next = next.min(ticks_until(playing.start_q32() + t as u128, HALF)),
                // All pulses made: the segment ends when the plan clock reaches its end.
                None => next = next.min(ticks_until(playing.end_q32() - 1, 0)),
            }
        } else if !self.queue.is_empty() {
            next = 1; // taken up at the next tick, then timed
        }
        self.clock
            .saturating_add(next)
            .min(self.watchdog_deadline())
    }

    /// The first MCU tick at which the host has been silent too long (after `clock`).
    fn watchdog_deadline(&self) -> u64 {
        if self.host_timeout_ticks == 0 {
            return u64::MAX;
        }
        (self.last_host_frame + self.host_timeout_ticks as u64 + 1).max(self.clock + 1)
    }

    /// Where a pass that moves nothing on the plan clock ends: `until`, the watchdog, or the
    /// end of a resume's wait (the tick σ starts to rise).
    fn next_rest_event(&self, until: u64) -> u64 {
        let mut next = until.min(self.watchdog_deadline());
        if let Ramp::ResumeWait {
            until: wait_end, ..
        } = self.ramp
        {
            next = next.min(wait_end.max(self.clock + 1));
        }
        next
    }

    /// `ticks` calls of [`Machine::step_ramp`] at once, for a stretch in which the plan clock
    /// stands (a resume's wait ends only at the stretch's last tick: see
    /// [`Machine::next_rest_event`]).
    fn ramp_over(&mut self, ticks: u64) {
        match self.ramp {
            Ramp::Hold { rate } => {
                self.sigma_q32 = self.sigma_q32.saturating_sub(rate.saturating_mul(ticks));
                if self.sigma_q32 == 0 {
                    self.ramp = Ramp::Steady;
                }
            }
            Ramp::Resume { rate } => {
                self.sigma_q32 = self
                    .sigma_q32
                    .saturating_add(rate.saturating_mul(ticks))
                    .min(ONE);
                if self.sigma_q32 == ONE {
                    self.ramp = Ramp::Steady;
                }
            }
            Ramp::Steady | Ramp::ResumeWait { .. } => self.step_ramp(),
        }
    }

    fn step_ramp(&mut self) {
        match self.ramp {
            Ramp::Steady => {}
            Ramp::Hold { rate } => {
                self.sigma_q32 = self.sigma_q32.saturating_sub(rate);
                if self.sigma_q32 == 0 {
                    self.ramp = Ramp::Steady;
                }
            }
            Ramp::ResumeWait { rate, until } => {
                if self.clock >= until {
                    self.ramp = Ramp::Resume { rate };
                }
            }
            Ramp::Resume { rate } => {
                self.sigma_q32 = (self.sigma_q32 + rate).min(ONE);
                if self.sigma_q32 == ONE {
                    self.ramp = Ramp::Steady;
                }
            }
        }
    }

    fn check_watchdog(&mut self) {
        if self.host_timeout_ticks > 0
            && self.clock - self.last_host_frame.min(self.clock) > self.host_timeout_ticks as u64
        {
            self.latch(FaultCode::HostSilent, 0);
        }
    }

    /// Emit every pulse due at the current tick, finishing and taking up segments on the way.
    fn emit_due(&mut self, sink: &mut impl FnMut(StepEdge)) {
        while self.fault == FaultCode::None {
            let Some(playing) = &mut self.playing else {
                match self.queue.pop_front() {
                    Some(queued) => {
                        self.playing = Some(Playing {
                            train: PulseTrain::new(&queued.segment),
                            queued,
                        });
                        continue;
                    }
                    None => return,
                }
            };
            let start = playing.start_q32();
            match playing.train.next_time_q32() {
                Some(t) if self.plan_q32 + HALF > start + t as u128 => {
                    if self.last_edge_clock == Some(self.clock) {
                        let tag = playing.queued.tag;
                        return self.latch(FaultCode::StepFault, tag);
                    }
                    let pulse = match playing.train.next_pulse() {
                        Ok(Some(pulse)) => pulse,
                        Ok(None) => unreachable!("next_time_q32 said a pulse remains"),
                        Err(_) => {
                            let tag = playing.queued.tag;
                            return self.latch(FaultCode::StepFault, tag);
                        }
                    };
                    let negative_mask = playing.queued.segment.negative_mask;
                    self.last_edge_clock = Some(self.clock);
                    sink(step(
                        &mut self.positions,
                        negative_mask,
                        pulse.axes,
                        self.clock,
                    ));
                }
                Some(_) => return,
                None if self.plan_q32 >= playing.end_q32() => {
                    let finished = self.playing.take().expect("playing").queued;
                    self.done_tag = finished.tag;
                    // Dry at rest the schedule waits (see `waiting_in_schedule`); dry while
                    // moving is an underrun.
                    let moving = finished.flags & SEGMENT_ENDS_AT_REST == 0;
                    if self.queue.is_empty() && moving {
                        self.counters.underruns += 1;
                        return self.latch(FaultCode::Underrun, finished.tag);
                    }
                }
                None => return,
            }
        }
    }
}

/// A pulse on `axes` at MCU tick `clock`, of a segment whose `negative_mask` axes step
/// backwards: the positions moved by it, and its edge.
#[inline(always)]
fn step(positions: &mut [i32; MAX_AXES], negative_mask: u8, axes: u8, clock: u64) -> StepEdge {
    let edge = StepEdge {
        clock,
        axes,
        negative: negative_mask & axes,
    };
    move_positions(positions, &edge, 1);
    edge
}

/// Move `positions` by `edge`'s steps, `sign` 1 to make them, −1 to take them back.
#[inline(always)]
fn move_positions(positions: &mut [i32; MAX_AXES], edge: &StepEdge, sign: i32) {
    for (axis, position) in positions.iter_mut().enumerate() {
        if edge.axes >> axis & 1 == 1 {
            *position += sign
                * if edge.negative >> axis & 1 == 1 {
                    -1
                } else {
                    1
                };
        }
    }
}

#[cfg(test)]
mod tests;
