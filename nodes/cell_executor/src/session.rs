//! The executor's session: planned messages in, the executed machine state out.
//!
//! It joins the [`Player`] (steps) and the [`ScrewTrack`] (screw) on one plan timeline. Both
//! upstream nodes stamp their messages with `epoch + plan time`; the session learns the epoch
//! from the first step segment (its stamp is its move's start, and the session knows where on
//! the plan clock that segment starts), so screw commands land on the same clock whichever
//! arrives first.
//!
//! The caller's clock is nanoseconds of a monotonic clock (`on_tick(now_ns)`); the first tick
//! is machine time 0.

use cell_machine::{Machine, MachineState};
use polar_cell_msgs::{Hold, ScrewCommand, StepSegment};

use crate::player::{Player, PlayerError, PlayerOptions, PlayerState, SegmentJob};
use crate::screw::{ScrewError, ScrewStep, ScrewTrack};

const Q32: u128 = step_core::ONE_TICK_Q32 as u128;

/// How the session is set up.
#[derive(Clone, Debug, PartialEq)]
pub struct ExecutorOptions {
    pub player: PlayerOptions,
    /// Screw commands queued ahead of execution at most, those waiting for the first
    /// segment (which fixes their place on the plan clock) included.
    pub screw_queue_capacity: usize,
    /// How rpm runs between screw commands: as the screw driver publishes them (its
    /// `command_hold`: held when it compensates the flow, smooths or resamples).
    pub screw_hold: Hold,
}

impl ExecutorOptions {
    pub fn new(player: PlayerOptions, screw_hold: Hold) -> ExecutorOptions {
        ExecutorOptions {
            screw_queue_capacity: player.queue_capacity,
            player,
            screw_hold,
        }
    }
}

/// What the session refuses.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ExecError {
    #[error(transparent)]
    Player(#[from] PlayerError),
    #[error(transparent)]
    Screw(#[from] ScrewError),
    #[error("{count} screw commands arrived before any step segment: more than can be held ({capacity})")]
    TooManyEarly { count: usize, capacity: usize },
    #[error("the machine clock went back: {now_ns} ns after {last_ns} ns")]
    ClockWentBack { now_ns: i64, last_ns: i64 },
}

/// Messages in, executed state out.
#[derive(Clone, Debug)]
pub struct Executor {
    player: Player,
    screw: ScrewTrack,
    timer_hz: f64,
    epoch_ns: Option<i64>,
    early_screw: Vec<ScrewCommand>,
    origin_ns: Option<i64>,
    last_ns: i64,
}

impl Executor {
    pub fn new(options: ExecutorOptions) -> Executor {
        let timer_hz = options.player.steps.timer_hz;
        Executor {
            screw: ScrewTrack::new(timer_hz, options.screw_hold, options.screw_queue_capacity),
            player: Player::new(options.player),
            timer_hz,
            epoch_ns: None,
            early_screw: Vec::new(),
            origin_ns: None,
            last_ns: 0,
        }
    }

    pub fn player(&self) -> &Player {
        &self.player
    }

    /// Nanoseconds to Q32 ticks (negative, i.e. before the plan's start: 0).
    fn ns_to_q32(&self, plan_ns: i64) -> u128 {
        let ns = plan_ns.max(0) as u128;
        ns * self.timer_hz as u128 * Q32 / 1_000_000_000
    }

    /// Queue a planned step segment.
    pub fn on_segment(&mut self, msg: &StepSegment) -> Result<(), ExecError> {
        let job = SegmentJob::from_message(msg, self.timer_hz)?;
        if self.epoch_ns.is_none() {
            // Its stamp is its move's start: where the plan clock will reach it.
            let start_q32 = self.player.plan_time_q32() + self.player.ahead_q32();
            let start_ns = (start_q32 * 1_000_000_000 / (self.timer_hz as u128 * Q32)) as i64;
            let epoch = msg.header.stamp.as_nanos() - start_ns;
            self.epoch_ns = Some(epoch);
            for early in std::mem::take(&mut self.early_screw) {
                self.push_screw(&early, epoch)?;
            }
        }
        self.player.push(job)?;
        Ok(())
    }

    fn push_screw(&mut self, msg: &ScrewCommand, epoch_ns: i64) -> Result<(), ExecError> {
        let plan_q32 = self.ns_to_q32(msg.header.stamp.as_nanos() - epoch_ns);
        self.screw.push(ScrewStep {
            plan_q32,
            rpm: msg.rpm,
            pin_open: msg.pin_open,
            source_line: msg.source_line,
        })?;
        Ok(())
    }

    /// Queue a screw command.
    pub fn on_screw(&mut self, msg: &ScrewCommand) -> Result<(), ExecError> {
        match self.epoch_ns {
            Some(epoch) => self.push_screw(msg, epoch),
            None if self.early_screw.len() < self.screw.free_slots() => {
                self.early_screw.push(msg.clone());
                Ok(())
            }
            None => Err(ExecError::TooManyEarly {
                count: self.early_screw.len() + 1,
                capacity: self.screw.free_slots(),
            }),
        }
    }

    /// Free places for step segments and screw commands.
    pub fn free_slots(&self) -> (usize, usize) {
        (
            self.player.free_slots(),
            self.screw
                .free_slots()
                .saturating_sub(self.early_screw.len()),
        )
    }

    /// Say that the plan is complete: it ends at rest where it ends.
    pub fn finish_input(&mut self) {
        self.player.finish_input();
    }

    /// The stamp of plan time 0 on the producers' clock, once the first segment told it.
    pub fn epoch_ns(&self) -> Option<i64> {
        self.epoch_ns
    }

    /// Nothing left to play: idle, with no segment queued or playing.
    pub fn is_drained(&self) -> bool {
        self.player.state() == PlayerState::Idle && self.player.queued() == 0
    }

    /// Plan time queued ahead of execution (s).
    pub fn plan_ahead_s(&self) -> f64 {
        crate::q32_to_seconds(self.player.ahead_q32(), self.timer_hz)
    }

    /// Execute up to `now_ns` (monotonic clock).
    pub fn on_tick(&mut self, now_ns: i64) -> Result<(), ExecError> {
        let origin = *self.origin_ns.get_or_insert(now_ns);
        if now_ns < self.last_ns {
            return Err(ExecError::ClockWentBack {
                now_ns,
                last_ns: self.last_ns,
            });
        }
        self.last_ns = now_ns;
        let now_q32 = self.ns_to_q32(now_ns - origin);
        let result = self.player.advance_to(now_q32, |_| {});
        // The screw turns only while the steppers may move: idle (ran dry, or a cancel's
        // plan dropped) or stopped, it stands whatever σ says.
        let feed = match self.player.state() {
            PlayerState::Running | PlayerState::Held => self.player.feed(),
            PlayerState::Idle | PlayerState::Stopped => 0.0,
        };
        self.screw
            .advance(self.player.plan_time_q32(), feed, self.player.pin_allowed());
        if result.is_err() {
            self.screw.stop();
        }
        Ok(result?)
    }

    pub fn pause(&mut self) {
        self.player.pause();
    }

    pub fn resume(&mut self) {
        self.player.resume();
    }

    pub fn cancel(&mut self) {
        self.player.cancel();
    }

    /// Stop stepping at once, screw stopped, pin closed.
    pub fn emergency_stop(&mut self) {
        self.player.emergency_stop();
        self.screw.stop();
    }

    pub fn reset(&mut self) {
        self.player.reset();
    }

    /// The executed state at the last tick.
    pub fn state(&self) -> MachineState {
        let p = self.player.position();
        let v = self.player.velocity();
        let (screw_rpm, pin_open) = self.screw.executed();
        MachineState {
            positions: [p[0], p[1], p[2], self.screw.angle_rad()],
            velocities: [v[0], v[1], v[2], screw_rpm * std::f64::consts::TAU / 60.0],
            screw_rpm,
            pin_open,
            state: self.player.state(),
            hold: self.player.hold(),
            feed: self.player.feed(),
            machine_time_s: (self.last_ns - self.origin_ns.unwrap_or(self.last_ns)) as f64 * 1e-9,
            plan_time_s: crate::q32_to_seconds(self.player.plan_time_q32(), self.timer_hz),
            current: self.player.current(),
            measured_ns: None,
        }
    }
}

/// The virtual executor as the cell's machine.
impl Machine for Executor {
    type Error = ExecError;

    fn on_segment(&mut self, msg: &StepSegment) -> Result<(), ExecError> {
        Executor::on_segment(self, msg)
    }
    fn on_screw(&mut self, msg: &ScrewCommand) -> Result<(), ExecError> {
        Executor::on_screw(self, msg)
    }
    fn free_slots(&self) -> (usize, usize) {
        Executor::free_slots(self)
    }
    fn finish_input(&mut self) {
        Executor::finish_input(self)
    }
    fn on_tick(&mut self, now_ns: i64) -> Result<(), ExecError> {
        Executor::on_tick(self, now_ns)
    }
    fn state(&self) -> MachineState {
        Executor::state(self)
    }
    fn epoch_ns(&self) -> Option<i64> {
        Executor::epoch_ns(self)
    }
    fn is_drained(&self) -> bool {
        Executor::is_drained(self)
    }
    fn plan_ahead_s(&self) -> f64 {
        Executor::plan_ahead_s(self)
    }
    fn completed(&self) -> (u64, Option<(u64, u32)>) {
        self.player.completed()
    }
    fn underruns(&self) -> u64 {
        self.player.underruns()
    }
    fn pause(&mut self) {
        Executor::pause(self)
    }
    fn resume(&mut self) {
        Executor::resume(self)
    }
    fn cancel(&mut self) {
        Executor::cancel(self)
    }
    fn emergency_stop(&mut self) {
        Executor::emergency_stop(self)
    }
    fn reset(&mut self) {
        Executor::reset(self)
    }
}
