//! A microcontroller as the cell's [`Machine`]: the same interface the virtual executor has,
//! so the same node loop, services and print action drive it.
//!
//! [`McuMachine`] joins an [`McuSession`] (the protocol, the clocks, the schedule) with what
//! the node loop expects of a machine: the plan's epoch (screw commands are stamped on the
//! producers' clock), the move playing now, hold reasons, cancel as a hold followed by a drop,
//! an emergency stop that is not reported back as a fault, and the executed state converted
//! from the MCU's step counts to joint units. The bytes go through an [`McuLink`]: a serial
//! device in the node, an emulator in the same process in tests.
//!
//! Underrun: the planner hands over plans that end at rest, so a stalled upstream lets the
//! MCU run dry at rest, where its plan clock waits. Should the plan end while moving (a
//! producer died), the machine holds on the path in time — before what is queued runs out —
//! and resumes by itself when enough plan has arrived, as the virtual executor does.

use std::collections::VecDeque;

use cell_machine::{HoldReason, Machine, MachineState, PlayerState};
use cell_protocol::message::Mode;
use cell_protocol::{LinkError, MAX_WIRE_FRAME};
use polar_cell_msgs::{ScrewCommand, StepSegment};

use crate::session::{McuSession, SessionError};

/// The byte line to the MCU, without blocking.
pub trait McuLink {
    type Error: std::fmt::Display + std::fmt::Debug;
    /// Append whatever has arrived by machine time `now_ns` to `into`.
    fn read(&mut self, now_ns: i64, into: &mut Vec<u8>) -> Result<(), Self::Error>;
    /// [`McuLink::read`], with when the bytes came: (end in `into`, machine time) for each
    /// part, in order. A link that cannot tell says `now_ns` (clock sync then counts the
    /// wait for the caller's look into the round trip).
    fn read_arrivals(
        &mut self,
        now_ns: i64,
        into: &mut Vec<u8>,
        arrivals: &mut Vec<(usize, i64)>,
    ) -> Result<(), Self::Error> {
        let result = self.read(now_ns, into);
        arrivals.push((into.len(), now_ns));
        result
    }
    /// Send `bytes` at machine time `now_ns`.
    fn write(&mut self, now_ns: i64, bytes: &[u8]) -> Result<(), Self::Error>;
    /// Machine time 0 is the wall instant `origin`, and it runs `speed` times wall time: a
    /// link that notes when bytes arrive places them on the machine's clock with this.
    fn clock_started(&mut self, _origin: std::time::Instant, _speed: f64) {}
}

/// What goes wrong between the cell and its MCU.
#[derive(Debug, thiserror::Error)]
pub enum McuMachineError<E: std::fmt::Display + std::fmt::Debug> {
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error("the MCU's link: {0}")]
    Link(#[from] LinkError),
    #[error("the serial line: {0}")]
    Line(E),
    #[error(
        "{count} screw commands arrived before any step segment: more than can be held ({capacity})"
    )]
    TooManyEarly { count: usize, capacity: usize },
    #[error(
        "the MCU stands at steps {mcu_steps:?} (bed, arm, z) but the plan starts at {plan_steps:?}: \
         print from where it stands (initial_joints {mcu_joints:?}, `polar-cell print --start-joints`) \
         or bring it to the plan's start first"
    )]
    NotAtStart {
        mcu_steps: [i64; 3],
        plan_steps: [i64; 3],
        /// The MCU's position in joint units (rad, m, m), to start a plan from.
        mcu_joints: [f64; 3],
    },
    #[error(
        "the MCU restarted since this bridge began: its step count began again at 0, so where \
         the machine stands is unknown; home it and print again with a new bridge \
         (`polar-cell print --start-joints`)"
    )]
    PositionLost,
}

/// Reports kept: a second of them at the default 10 ms period.
const REPORTS_KEPT: usize = 100;

/// One state report of the MCU.
#[derive(Clone, Copy, Debug)]
struct Report {
    state: cell_protocol::message::McuState,
    /// Machine time it was measured (once the clocks are synchronised).
    measured_ns: Option<i64>,
    velocity: [f64; 3],
}

/// A planned segment on its way: where it ends on the MCU's plan clock, and what it was.
#[derive(Clone, Copy, Debug)]
struct Tracked {
    end_clock: u64,
    move_sequence: u64,
    source_line: u32,
}

/// The MCU behind `L` as the cell's machine.
pub struct McuMachine<L: McuLink> {
    session: McuSession,
    link: L,
    /// Segments and screw commands held here at most (waiting to go to the MCU).
    capacity: usize,
    steps_per_unit: [f64; 3],
    horizon_s: f64,
    epoch_ns: Option<i64>,
    early_screw: Vec<ScrewCommand>,
    tracked: VecDeque<Tracked>,
    completed: u64,
    last_completed: Option<(u64, u32)>,
    hold: Option<HoldReason>,
    underruns: u64,
    input_finished: bool,
    estop_requested: bool,
    now_ns: i64,
    origin_ns: Option<i64>,
    /// The MCU's latest reports, with when they were measured and the velocities since the
    /// report before.
    reports: VecDeque<Report>,
    incoming: Vec<u8>,
    /// Where each part of `incoming` ends, and when it came (machine time).
    arrivals: Vec<(usize, i64)>,
    /// When the latest bytes came (machine time).
    arrived_ns: i64,
    link_error: Option<String>,
    /// Bytes written to the MCU so far (frames and their retransmissions).
    bytes_sent: u64,
    /// Where the plan's steps start; checked against the MCU's report before the first
    /// segment goes out (steps counted from elsewhere would print the part displaced).
    start_steps: Option<[i64; 3]>,
    /// The MCU restarted: its step count no longer says where the machine stands, and no
    /// plan may play until a new bridge is told (a plan continues from the last one's end).
    position_lost: bool,
}

impl<L: McuLink> McuMachine<L> {
    /// `capacity`: segments (and screw commands) held on the host at most; `horizon_s`: the
    /// plan-ahead the node grants (an underrun's resume waits for half of it).
    pub fn new(session: McuSession, link: L, capacity: usize, horizon_s: f64) -> McuMachine<L> {
        let steps_per_unit = session.options().steps_per_unit;
        McuMachine {
            session,
            link,
            capacity,
            steps_per_unit,
            horizon_s,
            epoch_ns: None,
            early_screw: Vec::new(),
            tracked: VecDeque::new(),
            completed: 0,
            last_completed: None,
            hold: None,
            underruns: 0,
            input_finished: false,
            estop_requested: false,
            now_ns: 0,
            origin_ns: None,
            reports: VecDeque::new(),
            incoming: Vec::new(),
            arrivals: Vec::new(),
            arrived_ns: i64::MIN,
            link_error: None,
            bytes_sent: 0,
            start_steps: Some([0; 3]),
            position_lost: false,
        }
    }

    /// The step counts the plan starts from (the planner's `initial_joints`; home by
    /// default). The first segment is refused unless the MCU reports standing there.
    pub fn with_start_steps(mut self, start_steps: [i64; 3]) -> Self {
        self.start_steps = Some(start_steps);
        self
    }

    /// The report [`Machine::state`] gives the positions of: the newest measured by the
    /// last tick's time.
    fn report_now(&self) -> Option<&Report> {
        self.reports
            .iter()
            .rev()
            .find(|r| r.measured_ns.is_none_or(|at| at <= self.now_ns))
            .or(self.reports.front())
    }

    /// The MCU clock at which the positions [`Machine::state`] gives were measured.
    pub fn reported_clock(&self) -> Option<u64> {
        self.report_now().map(|r| r.state.clock)
    }

    /// Bytes written to the MCU so far (frames and their retransmissions).
    pub fn bytes_sent(&self) -> u64 {
        self.bytes_sent
    }

    pub fn session(&self) -> &McuSession {
        &self.session
    }

    pub fn link(&self) -> &L {
        &self.link
    }

    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    fn now_us(&self) -> u64 {
        (self.now_ns.max(0) / 1000) as u64
    }

    /// The MCU's plan clock now (estimated).
    fn plan_clock_now(&self) -> Option<u64> {
        self.session.mcu_plan_clock_at(self.now_us())
    }

    fn push_screw(&mut self, msg: &ScrewCommand, epoch_ns: i64) -> Result<(), SessionError> {
        let plan_s = (msg.header.stamp.as_nanos() - epoch_ns) as f64 * 1e-9;
        self.session.on_screw(msg, plan_s.max(0.0), self.now_us())
    }

    /// The session's error, unless it is the echo of an emergency stop asked for here (by
    /// the node, or after a line error).
    fn session_error(&self) -> Option<&SessionError> {
        match self.session.error() {
            Some(SessionError::Fault {
                code: cell_protocol::message::FaultCode::EmergencyStop,
                ..
            }) if self.estop_requested || self.link_error.is_some() => None,
            other => other,
        }
    }

    fn send_all(&mut self) -> Result<(), L::Error> {
        let mut out = [0u8; MAX_WIRE_FRAME];
        let mut bytes = Vec::new();
        while let Some(len) = self.session.poll_transmit(self.now_us(), &mut out) {
            bytes.extend_from_slice(&out[..len]);
        }
        if bytes.is_empty() {
            return Ok(());
        }
        if self.bytes_sent == 0 {
            // A delimiter first (PROTOCOL.md §1): it ends whatever the MCU's decoder held
            // from before, which would otherwise swallow the session's first frame.
            bytes.insert(0, 0);
        }
        self.bytes_sent += bytes.len() as u64;
        self.link.write(self.now_ns, &bytes)
    }

    /// Count the segments the MCU has finished (by its plan clock).
    fn track_completion(&mut self) {
        let Some(state) = self.session.state() else {
            return;
        };
        let plan = state.plan_clock;
        while let Some(t) = self.tracked.front() {
            if t.end_clock > plan {
                break;
            }
            self.completed += 1;
            self.last_completed = Some((t.move_sequence, t.source_line));
            self.tracked.pop_front();
        }
    }

    /// Hold before what the MCU has been sent runs out while moving — the plan ran short, or
    /// the line is behind; resume once enough is on its way.
    fn watch_underrun(&mut self) -> Result<(), LinkError> {
        let (Some(plan_now), Some((end, at_rest))) =
            (self.plan_clock_now(), self.session.sent_end())
        else {
            return Ok(());
        };
        let hz = self.session.timer_hz();
        let left_s = end.saturating_sub(plan_now) as f64 / hz;
        let all_sent = self.session.waiting().0 == 0;
        // Segments waiting for room on the MCU (a small queue of short segments, a short
        // horizon) are no underrun while they cover the stopping distance: holding for them
        // would wait for room that only motion makes, for ever. What the host holds counts.
        let held_back = self.session.plan_held_back();
        let known_left_s = self
            .session
            .schedule_end_clock()
            .map_or(0.0, |end| end.saturating_sub(plan_now) as f64 / hz);
        // A hold from full feed covers 1/(2ρ) of plan time; started with a margin for the
        // state's age and the loop's period.
        let stopping_s = self.stopping_s();
        let resume_s = (self.horizon_s / 2.0).max(2.0 * stopping_s);
        let covered = held_back && known_left_s >= stopping_s;
        match self.hold {
            // Dry at a rest the MCU waits, its plan clock standing: nothing to do.
            None if !at_rest && !covered && left_s < stopping_s => {
                self.session.pause()?;
                self.hold = Some(HoldReason::Underrun);
                self.underruns += 1;
            }
            Some(HoldReason::Underrun)
                if left_s >= resume_s
                    || (held_back && known_left_s >= resume_s)
                    || at_rest
                    || (self.input_finished && all_sent) =>
            {
                self.session.resume()?;
                self.hold = None;
            }
            _ => {}
        }
        Ok(())
    }

    /// Plan time a hold from full feed needs to come to rest (1/(2ρ)), with a margin for
    /// the age of the MCU's state and the loop's period.
    fn stopping_s(&self) -> f64 {
        0.5 / self.session.sigma_rate_per_s() + 0.1
    }

    /// A cancel's hold has come to rest (or the MCU is idle): drop the plan.
    fn finish_cancel(&mut self) -> Result<(), LinkError> {
        if self.hold != Some(HoldReason::Cancel) {
            return Ok(());
        }
        // (Idle from before the last segments arrived is not at rest: a drop then finds the
        // MCU moving, and it faults.)
        let at_rest = self.session.state().is_some_and(|s| {
            matches!(s.mode, Mode::Held | Mode::Fault) || self.session.idle_after_last_sent(s)
        });
        if at_rest {
            self.session.drop_plan()?;
            self.forget();
        }
        Ok(())
    }

    fn forget(&mut self) {
        self.hold = None;
        self.epoch_ns = None;
        self.early_screw.clear();
        self.tracked.clear();
        self.input_finished = false;
    }

    fn tick(&mut self, now_ns: i64) -> Result<(), McuMachineError<L::Error>> {
        self.origin_ns.get_or_insert(now_ns);
        self.now_ns = self.now_ns.max(now_ns);
        self.incoming.clear();
        let mut incoming = std::mem::take(&mut self.incoming);
        let mut arrivals = std::mem::take(&mut self.arrivals);
        arrivals.clear();
        let read = self
            .link
            .read_arrivals(self.now_ns, &mut incoming, &mut arrivals);
        let mut from = 0;
        for &(end, at_ns) in &arrivals {
            // In order. (Not clamped to `now_ns`: a pass's first looks are at grid instants
            // behind the wall clock, and bytes may have come since.)
            let at_ns = at_ns.max(self.arrived_ns);
            self.arrived_ns = at_ns;
            if end > from {
                self.session
                    .receive(&incoming[from..end], (at_ns.max(0) / 1000) as u64);
                from = end;
            }
        }
        if from < incoming.len() || incoming.is_empty() {
            // (Nothing came: the session still looks at the time.)
            self.session.receive(&incoming[from..], self.now_us());
        }
        self.incoming = incoming;
        self.arrivals = arrivals;
        read.map_err(McuMachineError::Line)?;
        for state in self.session.take_reports() {
            let measured_ns = self.session.clock_sync().host_at(state.clock);
            let velocity = match self.reports.back() {
                Some(previous) if state.clock > previous.state.clock => {
                    let dt = (state.clock - previous.state.clock) as f64 / self.session.timer_hz();
                    std::array::from_fn(|j| {
                        // (In i64: counts from the wire may be far apart.)
                        (i64::from(state.position_steps[j])
                            - i64::from(previous.state.position_steps[j]))
                            as f64
                            / self.steps_per_unit[j]
                            / dt
                    })
                }
                _ => [0.0; 3],
            };
            if self.reports.len() == REPORTS_KEPT {
                self.reports.pop_front();
            }
            self.reports.push_back(Report {
                state,
                measured_ns,
                velocity,
            });
        }
        self.track_completion();
        self.session.tick(self.now_us())?;
        self.finish_cancel()?;
        if self.session_error().is_none() {
            self.watch_underrun()?;
        }
        self.send_all().map_err(McuMachineError::Line)?;
        Ok(())
    }
}

impl<L: McuLink> Machine for McuMachine<L> {
    type Error = McuMachineError<L::Error>;

    fn on_segment(&mut self, msg: &StepSegment) -> Result<(), Self::Error> {
        if self.position_lost {
            return Err(McuMachineError::PositionLost);
        }
        if let Some(plan_steps) = self.start_steps {
            // free_slots offers no room before a report (`is_ready`), so there is one.
            let mcu_steps = self.session.state().map_or([0; 3], |s| s.position_steps);
            let mcu_steps = mcu_steps.map(i64::from);
            if mcu_steps != plan_steps {
                let u = self.steps_per_unit;
                return Err(McuMachineError::NotAtStart {
                    mcu_steps,
                    plan_steps,
                    mcu_joints: std::array::from_fn(|j| mcu_steps[j] as f64 / u[j]),
                });
            }
            self.start_steps = None;
        }
        if self.epoch_ns.is_none() {
            // The first segment's stamp is its move's start, plan time 0 of this schedule.
            let epoch = msg.header.stamp.as_nanos();
            self.epoch_ns = Some(epoch);
            let end_clock = self.session.on_segment(msg, self.now_us())?;
            for early in std::mem::take(&mut self.early_screw) {
                self.push_screw(&early, epoch)?;
            }
            self.track(msg, end_clock);
            return Ok(());
        }
        let end_clock = self.session.on_segment(msg, self.now_us())?;
        self.track(msg, end_clock);
        Ok(())
    }

    fn on_screw(&mut self, msg: &ScrewCommand) -> Result<(), Self::Error> {
        match self.epoch_ns {
            Some(epoch) => Ok(self.push_screw(msg, epoch)?),
            None if self.early_screw.len() < self.capacity => {
                self.early_screw.push(msg.clone());
                Ok(())
            }
            None => Err(McuMachineError::TooManyEarly {
                count: self.early_screw.len() + 1,
                capacity: self.capacity,
            }),
        }
    }

    fn free_slots(&self) -> (usize, usize) {
        // Nothing until the MCU is identified, configured and its clock known: the schedule
        // needs its timer and its clock.
        if !self.session.is_ready()
            || self.session_error().is_some()
            || self.link_error.is_some()
            || self.estop_requested
        {
            return (0, 0);
        }
        let (segments, screw) = self.session.waiting();
        (
            self.capacity.saturating_sub(segments),
            self.capacity.saturating_sub(screw + self.early_screw.len()),
        )
    }

    fn finish_input(&mut self) {
        if !self.input_finished {
            self.input_finished = true;
            self.session.finish_input();
        }
    }

    fn on_tick(&mut self, now_ns: i64) -> Result<(), Self::Error> {
        let result = self.tick(now_ns);
        if matches!(self.session.error(), Some(SessionError::Restarted { .. })) {
            self.position_lost = true;
        }
        if let Err(e) = result {
            // Reported stopped from here on, so the node sends no stop of its own: stop the
            // MCU now, or it plays what it holds while the bridge keeps feeding it.
            if self.link_error.is_none() {
                self.link_error = Some(e.to_string());
                self.session.emergency_stop();
                self.forget();
                let _ = self.send_all();
            }
            return Err(e);
        }
        match self.session_error() {
            Some(e) => Err(McuMachineError::Session(e.clone())),
            None => Ok(()),
        }
    }

    fn state(&self) -> MachineState {
        let mcu = self.session.state();
        // What was measured by the time asked about: the newest report not after it (the
        // node asks for each instant of its sample grid, some behind the newest report).
        let report = self.report_now();
        let measured = report.map(|r| r.state);
        let positions_steps = measured.map_or([0; 3], |s| s.position_steps);
        let velocity = report.map_or([0.0; 3], |r| r.velocity);
        let screw_rpm = measured.map_or(0.0, |s| s.screw_millirpm as f64 * 1e-3);
        let screw_rad = measured.map_or(0.0, |s| {
            s.screw_angle_millirev as f64 * 1e-3 * std::f64::consts::TAU
        });
        let stopped = self.estop_requested
            || self.session_error().is_some()
            || self.link_error.is_some()
            || (mcu.is_some_and(|s| s.mode == Mode::Fault) && self.session.faults_count());
        // Waiting for the plan's first segment to start (the lead) is not running yet.
        let started = match (self.plan_clock_now(), self.session.anchor_clock()) {
            (Some(now), Some(anchor)) => now >= anchor,
            _ => false,
        };
        let state = match mcu.map(|s| s.mode) {
            _ if stopped => PlayerState::Stopped,
            Some(Mode::Running | Mode::Ramping) if started => PlayerState::Running,
            Some(Mode::Held) => PlayerState::Held,
            _ => PlayerState::Idle,
        };
        let plan_time_s = self
            .plan_clock_now()
            .and_then(|c| self.session.plan_s_at(c))
            .unwrap_or(0.0)
            .max(0.0);
        let u = self.steps_per_unit;
        MachineState {
            positions: [
                positions_steps[0] as f64 / u[0],
                positions_steps[1] as f64 / u[1],
                positions_steps[2] as f64 / u[2],
                screw_rad,
            ],
            velocities: [
                velocity[0],
                velocity[1],
                velocity[2],
                screw_rpm * std::f64::consts::TAU / 60.0,
            ],
            screw_rpm,
            pin_open: measured.is_some_and(|s| s.pin_open),
            state,
            hold: self.hold,
            feed: mcu.map_or(1.0, |s| s.feed_scale_q16 as f64 / 65535.0),
            machine_time_s: (self.now_ns - self.origin_ns.unwrap_or(self.now_ns)) as f64 * 1e-9,
            plan_time_s,
            current: self
                .tracked
                .front()
                .map(|t| (t.move_sequence, t.source_line)),
            measured_ns: report.and_then(|r| r.measured_ns),
        }
    }

    fn epoch_ns(&self) -> Option<i64> {
        self.epoch_ns
    }

    fn is_drained(&self) -> bool {
        self.session.is_drained() && self.hold.is_none()
    }

    fn plan_ahead_s(&self) -> f64 {
        match (self.plan_clock_now(), self.session.schedule_end_clock()) {
            (Some(now), Some(end)) => end.saturating_sub(now) as f64 / self.session.timer_hz(),
            _ => 0.0,
        }
    }

    fn completed(&self) -> (u64, Option<(u64, u32)>) {
        (self.completed, self.last_completed)
    }

    fn underruns(&self) -> u64 {
        self.underruns
    }

    fn pause(&mut self) {
        // A cancel's hold stays one: as a pause, its plan would never be dropped and a
        // resume would play it.
        if self.hold != Some(HoldReason::Cancel) && self.session.pause().is_ok() {
            self.hold = Some(HoldReason::Pause);
        }
    }

    fn resume(&mut self) {
        if self.hold == Some(HoldReason::Pause) && self.session.resume().is_ok() {
            self.hold = None;
        }
    }

    fn cancel(&mut self) {
        if self.session.pause().is_ok() {
            self.hold = Some(HoldReason::Cancel);
        }
    }

    fn emergency_stop(&mut self) {
        self.estop_requested = true;
        self.session.emergency_stop();
        self.forget();
        // Out now, not at the next tick.
        let _ = self.send_all();
    }

    fn reset(&mut self) {
        if self.session.reset().is_ok() {
            self.estop_requested = false;
            self.link_error = None;
            self.forget();
        }
    }

    fn clock_started(&mut self, origin: std::time::Instant, speed: f64) {
        self.link.clock_started(origin, speed);
    }

    fn diagnostics(&self) -> Vec<(&'static str, String)> {
        let mut values = Vec::new();
        if let Some(identity) = self.session.identity() {
            values.push(("mcu_timer_hz", identity.timer_hz.to_string()));
            values.push(("mcu_queue_capacity", identity.queue_capacity.to_string()));
        }
        let sync = self.session.clock_sync();
        if let (Some(fit), Some(ppm)) = (sync.fit(), sync.rate_error_ppm()) {
            values.push(("mcu_rate_error_ppm", format!("{ppm:.2}")));
            values.push((
                "mcu_clock_residual_ticks",
                format!("{:.1}", fit.residual_ticks),
            ));
        }
        values.push(("link_bytes_sent", self.bytes_sent.to_string()));
        let sent = self.session.endpoint().sent_bytes();
        values.push(("link_segment_bytes", sent.segments.to_string()));
        values.push(("link_screw_bytes", sent.screw.to_string()));
        values.push(("link_control_bytes", sent.control.to_string()));
        values.push(("link_frames", sent.frames.to_string()));
        let counters = self.session.endpoint().link().counters();
        values.push(("link_retransmits", counters.retransmits.to_string()));
        values.push(("link_naks", counters.naks_sent.to_string()));
        values.push(("link_naks_received", counters.naks_received.to_string()));
        values.push(("link_timeouts", counters.timeouts.to_string()));
        values.push(("screw_commands_late", self.session.screw_late.to_string()));
        values.push((
            "screw_late_worst_ms",
            format!(
                "{:.3}",
                self.session.screw_late_worst_ticks as f64 * 1e3 / self.session.timer_hz()
            ),
        ));
        if let Some(e) = self.session.error() {
            values.push(("mcu_error", e.to_string()));
        }
        values
    }
}

/// A bridge that goes away (its node stopped, its process ended) leaves no MCU moving: an
/// MCU not at rest is stopped at once rather than left to its watchdog.
impl<L: McuLink> Drop for McuMachine<L> {
    fn drop(&mut self) {
        // Idle from before the last segments arrived is about to move.
        let moving = self.session.state().is_some_and(|s| match s.mode {
            Mode::Fault => false,
            Mode::Idle => !self.session.idle_after_last_sent(s),
            _ => true,
        });
        if moving {
            self.session.emergency_stop();
            let mut out = [0u8; MAX_WIRE_FRAME];
            while let Some(len) = self.session.poll_transmit(self.now_us(), &mut out) {
                if self.link.write(self.now_ns, &out[..len]).is_err() {
                    break;
                }
            }
        }
    }
}

impl<L: McuLink> McuMachine<L> {
    fn track(&mut self, msg: &StepSegment, end_clock: u64) {
        self.tracked.push_back(Tracked {
            end_clock,
            move_sequence: msg.move_sequence,
            source_line: msg.source_line,
        });
    }
}
