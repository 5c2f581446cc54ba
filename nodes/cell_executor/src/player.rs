//! The segment queue and the pulse clock, with feed hold along the path.
//!
//! # Two clocks
//!
//! Segments play back to back on the *plan clock* τ: segment `k` starts where `k − 1` ended,
//! and each pulse has a plan time. The *machine clock* is the caller's. Between them stands
//! the feed scale σ ∈ [0, 1]: `dτ/dt = σ`. At σ = 1 the machine runs the plan as planned; a
//! feed hold brings σ to 0 and the machine stops **on the path** — the same pulses, later —
//! and a resume brings it back to 1. That one mechanism serves pause, cancel (hold, then
//! drop what is queued) and underrun (hold before the queued plan runs out, resume when
//! enough has arrived).
//!
//! # Limits during a hold
//!
//! With τ scaled, a joint's acceleration is `σ²·q̈ + σ̇·q̇` (plan-time derivatives). Inside a
//! segment every axis is a fixed fraction `c_j = T_j/N` of the dominant one, so the limits
//! `|c_j·(σ²·a + σ̇·R)| ≤ A_j` (dominant rate `R` steps/s, acceleration `a`, both in plan
//! time) become one interval for σ̇:
//!
//! ```text
//! (−A − σ²·a)/R  ≤  σ̇  ≤  (A − σ²·a)/R,     A = min_j A_j / c_j   (dominant steps/s²)
//! ```
//!
//! A hold takes the lower end, a resume the upper end: the fastest stop and start the limits
//! allow, every joint within its acceleration limit, velocities never above the plan's. The
//! planner leaves a margin (it plans to a fraction of each limit), so a hold can always begin.
//!
//! Times are timer ticks in Q32 (`_q32`), as in [`step_core`].

use std::collections::VecDeque;

use polar_cell_msgs::{StepSegment, UnplayableSegment};
use step_core::{PulseTrain, Segment, StepFault, StepOptions, MAX_AXES};

use crate::{q32_to_seconds, seconds_to_q32};

/// How the player is set up.
#[derive(Clone, Debug, PartialEq)]
pub struct PlayerOptions {
    pub steps: StepOptions,
    /// Joint acceleration limits (rad/s², m/s², m/s²) a feed hold or resume keeps to.
    pub acceleration_limits: [f64; MAX_AXES],
    /// Segments queued ahead of execution at most (the bound on memory and plan-ahead).
    pub queue_capacity: usize,
    /// Absolute step position of each axis before the first segment.
    pub initial_steps: [i64; MAX_AXES],
    /// Longest stretch of machine time over which σ is held constant (s): the control period
    /// of the hold.
    pub control_period_s: f64,
    /// Machine time a resume waits at rest with the pin reopened before motion restarts (the
    /// pin's opening delay, so material flows exactly where it stopped).
    pub pin_open_delay_s: f64,
    /// Plan an underrun hold waits for beyond twice its stopping distance before it
    /// releases (s). It must stay well inside the producers' horizon: held, the machine
    /// is never given more than the horizon ahead, so a larger figure would hold for ever.
    pub underrun_resume_s: f64,
}

impl PlayerOptions {
    pub fn new(
        steps: StepOptions,
        acceleration_limits: [f64; MAX_AXES],
        pin_open_delay_s: f64,
    ) -> PlayerOptions {
        PlayerOptions {
            steps,
            acceleration_limits,
            queue_capacity: 4096,
            initial_steps: [0; MAX_AXES],
            control_period_s: 0.001,
            pin_open_delay_s,
            underrun_resume_s: 0.5,
        }
    }
}

/// What goes wrong while queueing or playing, with the segment it concerns.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlayerError {
    #[error(transparent)]
    Unplayable(#[from] UnplayableSegment),
    #[error("the machine is stopped (emergency stop or fault): reset it before queueing")]
    Stopped,
    #[error("the segment queue is full ({capacity} segments)")]
    QueueFull { capacity: usize },
    #[error("step fault in move {move_sequence} (line {source_line}): {source}")]
    Fault {
        move_sequence: u64,
        source_line: u32,
        source: StepFault,
    },
}

/// A segment ready to play.
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentJob {
    pub segment: Segment,
    /// Length on the plan clock (Q32 ticks): pulses may end a little before it (a pause
    /// segment has none at all).
    pub duration_q32: u128,
    pub move_sequence: u64,
    pub source_line: u32,
}

impl SegmentJob {
    /// Validate and convert a planned segment for a machine with timer `timer_hz`.
    pub fn from_message(msg: &StepSegment, timer_hz: f64) -> Result<SegmentJob, PlayerError> {
        let (segment, _) = msg.playable(timer_hz)?;
        Ok(SegmentJob {
            segment,
            duration_q32: seconds_to_q32(msg.duration_s, timer_hz),
            move_sequence: msg.move_sequence,
            source_line: msg.source_line,
        })
    }
}

/// Pulses fired at one instant, as a driver would set its step pins.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Edge {
    /// Machine time (Q32 ticks).
    pub time_q32: u128,
    /// Bit `k`: axis `k` steps.
    pub axes: u8,
    /// Bit `k`: axis `k` steps in the negative direction (meaningful where `axes` is set).
    pub negative: u8,
}

pub use cell_machine::{HoldReason, PlayerState};

#[derive(Clone, Debug)]
struct Active {
    job: SegmentJob,
    train: PulseTrain,
    /// Plan time at the segment's start (Q32 ticks).
    plan_start_q32: u128,
}

/// Plays queued segments against the caller's clock.
#[derive(Clone, Debug)]
pub struct Player {
    options: PlayerOptions,
    queue: VecDeque<SegmentJob>,
    queued_q32: u128,
    active: Option<Active>,
    position_steps: [i64; MAX_AXES],
    state: PlayerState,
    /// The plan clock τ (Q32 ticks); with no segment playing, where the next one starts.
    plan_q32: u128,
    /// Plan-time dominant step rate (steps/s) of the last period of the stepping segment
    /// played last, while the plan has gone on from it without a break or a piece without
    /// steps: with the next
    /// segment's first, it gives the plan's acceleration at a single-step segment.
    previous_rate: Option<f64>,
    now_q32: u128,
    last_edge_q32: u128,
    /// Feed scale σ; it heads for 0 while `hold` is set, else for 1.
    feed: f64,
    hold: Option<HoldReason>,
    /// A resume waits until this machine time (the pin's opening delay) before σ rises.
    resume_at_q32: u128,
    completed: u64,
    last_completed: Option<(u64, u32)>,
    underruns: u64,
    input_finished: bool,
}

impl Player {
    pub fn new(options: PlayerOptions) -> Player {
        Player {
            queue: VecDeque::with_capacity(options.queue_capacity),
            queued_q32: 0,
            active: None,
            position_steps: options.initial_steps,
            state: PlayerState::Idle,
            plan_q32: 0,
            previous_rate: None,
            now_q32: 0,
            last_edge_q32: 0,
            feed: 1.0,
            hold: None,
            resume_at_q32: 0,
            completed: 0,
            last_completed: None,
            underruns: 0,
            input_finished: false,
            options,
        }
    }

    pub fn options(&self) -> &PlayerOptions {
        &self.options
    }

    /// Queue a segment behind the others.
    pub fn push(&mut self, job: SegmentJob) -> Result<(), PlayerError> {
        if self.state == PlayerState::Stopped {
            return Err(PlayerError::Stopped);
        }
        if self.queue.len() >= self.options.queue_capacity {
            return Err(PlayerError::QueueFull {
                capacity: self.options.queue_capacity,
            });
        }
        self.queued_q32 += job.duration_q32;
        self.queue.push_back(job);
        Ok(())
    }

    /// Say that no more segments will come: the plan ends at rest where it ends, so running
    /// to its end is neither an underrun nor a reason to hold.
    pub fn finish_input(&mut self) {
        self.input_finished = true;
    }

    /// Free places in the queue.
    pub fn free_slots(&self) -> usize {
        self.options.queue_capacity - self.queue.len()
    }

    /// Plan time queued but not executed yet (Q32 ticks): the plan-ahead.
    pub fn ahead_q32(&self) -> u128 {
        let remaining = self.active.as_ref().map_or(0, |a| {
            (a.plan_start_q32 + a.job.duration_q32).saturating_sub(self.plan_q32)
        });
        self.queued_q32 + remaining
    }

    /// Begin a feed hold: decelerate along the path to rest and stay there.
    pub fn pause(&mut self) {
        if self.hold != Some(HoldReason::Cancel) && self.state != PlayerState::Stopped {
            self.hold = Some(HoldReason::Pause);
            if self.state == PlayerState::Idle {
                // At rest already: held there, so a plan that arrives does not start (it
                // would start at full feed and brake, stepping after the pause was granted).
                self.feed = 0.0;
            }
        }
    }

    /// End a pause (or an underrun hold): after the pin's opening delay at rest (the pin
    /// reopened, so material flows when motion restarts), accelerate back to the plan.
    pub fn resume(&mut self) {
        if matches!(self.hold, Some(HoldReason::Pause | HoldReason::Underrun)) {
            self.release();
        }
    }

    fn release(&mut self) {
        self.hold = None;
        if self.feed == 0.0 {
            self.resume_at_q32 = self.now_q32 + self.ticks_q32(self.options.pin_open_delay_s);
        }
    }

    /// Whether the pin may be open: while moving, and while waiting to resume (its delay);
    /// not while held, stopped or idle.
    pub fn pin_allowed(&self) -> bool {
        match self.state {
            PlayerState::Running => true,
            PlayerState::Held => self.hold.is_none(),
            PlayerState::Idle | PlayerState::Stopped => false,
        }
    }

    /// Decelerate along the path to rest, then drop everything queued.
    pub fn cancel(&mut self) {
        if self.state == PlayerState::Idle {
            // At rest: drop now what is queued, rather than leave a cancel pending that
            // would drop the next plan to arrive.
            self.drop_plan();
        } else if self.state != PlayerState::Stopped {
            self.hold = Some(HoldReason::Cancel);
        }
    }

    /// The hold in force, if any (a hold may still be decelerating).
    pub fn hold(&self) -> Option<HoldReason> {
        self.hold
    }

    /// The feed scale σ: machine speed as a fraction of the plan's.
    pub fn feed(&self) -> f64 {
        self.feed
    }

    fn ticks_q32(&self, seconds: f64) -> u128 {
        seconds_to_q32(seconds, self.options.steps.timer_hz)
    }

    /// The dominant axis's step rate in plan time (steps/s) at a pulse train's current period.
    fn dominant_rate(&self, train: &PulseTrain) -> f64 {
        1.0 / q32_to_seconds(train.period_q32().into(), self.options.steps.timer_hz)
    }

    /// Start the next queued segment if none is playing; false if there is none.
    fn ensure_active(&mut self) -> bool {
        if self.active.is_some() {
            return true;
        }
        let Some(job) = self.queue.pop_front() else {
            return false;
        };
        self.queued_q32 -= job.duration_q32;
        self.active = Some(Active {
            train: PulseTrain::new(&job.segment),
            job,
            plan_start_q32: self.plan_q32,
        });
        true
    }

    /// The σ̇ interval at the current point of the plan (per second of machine time), to
    /// hold for the next `period_s` of machine time.
    fn feed_rate_bounds(&self, period_s: f64) -> (f64, f64) {
        // The stepping segment whose constraints hold now: the one playing; during one
        // without steps (a dwell at rest, or a piece of a move shorter than half a step on
        // every axis, inside motion) the next that steps, from its start. (At rest that is a
        // move's first step, slow: σ may then change within milliseconds, and nothing moves.)
        let upcoming;
        let (train, mut after, before) = match self
            .active
            .as_ref()
            .filter(|a| a.job.segment.dominant_steps() > 0)
        {
            Some(active) => (&active.train, self.queue.iter(), self.previous_rate),
            None => {
                let mut queued = self.queue.iter();
                match queued.find(|j| j.segment.dominant_steps() > 0) {
                    Some(job) => {
                        upcoming = PulseTrain::new(&job.segment);
                        // The step before it is known only if nothing stepless (playing, or
                        // queued before it) lies between them.
                        let adjacent = self.active.is_none()
                            && self.queue.front().is_some_and(|j| std::ptr::eq(j, job));
                        (&upcoming, queued, self.previous_rate.filter(|_| adjacent))
                    }
                    // Nothing steps before the plan ends: at rest there, no constraint.
                    None => return (f64::NEG_INFINITY, f64::INFINITY),
                }
            }
        };
        let seg = train.segment();
        let rate = self.dominant_rate(train);
        let total = seg.dominant_steps() as f64;
        let mut limit = f64::INFINITY;
        for k in 0..MAX_AXES {
            if seg.step_counts[k] > 0 {
                let a = self.options.acceleration_limits[k] * self.options.steps.steps_per_unit[k];
                limit = limit.min(a * total / seg.step_counts[k] as f64);
            }
        }
        // The plan's own dominant acceleration (steps/s²), as an interval that holds it.
        let (accel_min, accel_max) = if total == 1.0 && train.ramp_q62() == 0 {
            // A single step, timed exactly by the planner near rest where a ramp's
            // recurrence is inexact: its period says nothing of the acceleration, which is
            // a ramp's all the same. Under constant acceleration 1/period is the speed at
            // the step's middle in time, so two neighbours' rates give it exactly; the
            // interval spans the one before and the one after (they differ across a rest
            // point, where the plan turns from slowing to speeding up).
            let next = after
                .find(|j| j.segment.dominant_steps() > 0)
                .map(|j| self.dominant_rate(&PulseTrain::new(&j.segment)));
            // (Within the limit: a plan keeps to it, and a jump in rate — steps cut apart by
            // a dwell, a plan from elsewhere — must not stop a hold from taking hold.)
            let between =
                |r1: f64, r2: f64| ((r2 - r1) * 2.0 * r1 * r2 / (r1 + r2)).clamp(-limit, limit);
            let estimates = [
                before.map(|r| between(r, rate)),
                next.map(|r| between(rate, r)),
            ];
            // (0 stays in the interval: with no neighbour known, as a cruise; and the
            // bounds only widen towards safety.)
            let known = estimates.into_iter().flatten();
            (known.clone().fold(0.0, f64::min), known.fold(0.0, f64::max))
        } else {
            // r·p² (dimensionless) times the rate² is the dominant acceleration in steps/s².
            let accel =
                train.ramp_q62() as f64 / (1u64 << 62) as f64 * rate * rate * train.phase() as f64;
            (accel, accel)
        };
        // The machine's acceleration is σ̇·rate + σ²·(the plan's): within ±limit for any
        // plan acceleration in the interval, and for σ where the period leaves it, not only
        // where it starts: σ rising while the plan speeds up (or falling while it speeds
        // up) takes more of the limit as it goes, and at a slow rate σ moves far in a period.
        let feed2 = self.feed * self.feed;
        let lo = (-limit - feed2 * accel_min) / rate;
        let hi = (limit - feed2 * accel_max) / rate;
        let lo = if accel_min > 0.0 {
            let end = (self.feed + lo * period_s).max(0.0);
            (-limit - end * end * accel_min) / rate
        } else {
            lo
        };
        let hi = if accel_max > 0.0 {
            let end = (self.feed + hi * period_s).min(1.0);
            (limit - end * end * accel_max) / rate
        } else {
            hi
        };
        (lo.min(0.0), hi.max(0.0))
    }

    /// Plan time a hold begun now with σ̇ = `lo` would still consume before rest, with a
    /// margin (the constraint ahead may be tighter than here), in Q32 ticks.
    fn stopping_plan_q32(&self, lo: f64) -> u128 {
        if lo == f64::NEG_INFINITY {
            // At rest in the plan, stopping costs nothing: a hold begins just before the
            // plan runs out (so resuming waits for the pin's delay), not after.
            return self.ticks_q32(2.0 * self.options.control_period_s);
        }
        if !lo.is_finite() || lo >= 0.0 {
            return 0;
        }
        let stop_s = self.feed / -lo;
        // ∫σ dt under a linear ramp is σ·T/2; twice that, and two control periods.
        self.ticks_q32(self.feed * stop_s + 2.0 * self.options.control_period_s)
    }

    /// Play everything due up to machine time `now_q32` (which must not go back), handing each
    /// instant's pulses to `on_edge` in time order.
    pub fn advance_to(
        &mut self,
        now_q32: u128,
        mut on_edge: impl FnMut(Edge),
    ) -> Result<(), PlayerError> {
        if self.state == PlayerState::Idle {
            // Waiting, at no cost however long; what arrived starts now, never in the past.
            self.now_q32 = self.now_q32.max(now_q32);
            if self.ensure_active() {
                self.last_edge_q32 = self.now_q32;
                self.state = PlayerState::Running;
                if self.feed == 0.0 && self.hold.is_none() {
                    // After running dry (the pin closed there): restart as a resume does,
                    // the pin reopened for its delay first, σ rising from rest.
                    self.resume_at_q32 =
                        self.now_q32 + self.ticks_q32(self.options.pin_open_delay_s);
                }
            }
            return Ok(());
        }
        let period_q32 = self.ticks_q32(self.options.control_period_s).max(1);
        while self.now_q32 < now_q32 && self.state != PlayerState::Stopped {
            if !self.ensure_active() {
                // Ran dry while moving: a hold came too late. (Not a cancel's end: its plan
                // was dropped on purpose.)
                if self.state == PlayerState::Running
                    && !self.input_finished
                    && self.hold != Some(HoldReason::Cancel)
                {
                    self.underruns += 1;
                }
                if self.hold == Some(HoldReason::Cancel) {
                    // The plan ended before the cancel's hold came to rest: nothing is left
                    // to drop, and the cancel must not drop the next plan.
                    self.drop_plan();
                } else if !self.input_finished {
                    // Stopped where the plan ends (it ends at rest), the pin closed while
                    // idle: σ is 0 now, so what comes next starts as a resume, not at the
                    // feed it ran dry with.
                    self.feed = 0.0;
                }
                // What comes next starts after a break in the plan, at rest.
                self.previous_rate = None;
                self.state = PlayerState::Idle;
                break;
            }
            let t0 = self.now_q32;
            let t1 = now_q32.min(t0 + period_q32);
            self.step_feed(t0, t1, &mut on_edge)?;
            self.now_q32 = t1;
        }
        self.now_q32 = self.now_q32.max(now_q32);
        Ok(())
    }

    /// One control period `[t0, t1]` of machine time.
    fn step_feed(
        &mut self,
        t0: u128,
        t1: u128,
        on_edge: &mut impl FnMut(Edge),
    ) -> Result<(), PlayerError> {
        let h = q32_to_seconds(t1 - t0, self.options.steps.timer_hz);
        let (lo, hi) = self.feed_rate_bounds(h);
        // Hold before the queued plan runs out; resume once enough is queued again.
        if !self.input_finished {
            let needed = self.stopping_plan_q32(lo);
            if self.hold.is_none() && self.ahead_q32() <= needed && self.feed > 0.0 {
                self.hold = Some(HoldReason::Underrun);
                self.underruns += 1;
            } else if self.hold == Some(HoldReason::Underrun)
                && self.ahead_q32() > 2 * needed + self.ticks_q32(self.options.underrun_resume_s)
            {
                self.release();
            }
        } else if self.hold == Some(HoldReason::Underrun) {
            self.release();
        }
        let feed0 = self.feed;
        self.feed = if self.hold.is_some() {
            (feed0 + lo * h).max(0.0)
        } else if t0 >= self.resume_at_q32 {
            (feed0 + hi * h).min(1.0)
        } else {
            feed0
        };
        let advance_q32 = ((feed0 + self.feed) / 2.0 * (t1 - t0) as f64) as u128;
        if self.hold == Some(HoldReason::Cancel) && self.feed == 0.0 && feed0 == 0.0 {
            self.drop_plan();
            return Ok(());
        }
        self.state = if self.feed == 0.0 {
            PlayerState::Held
        } else {
            PlayerState::Running
        };
        let (plan0, plan1) = (self.plan_q32, self.plan_q32 + advance_q32);
        // Machine time of plan time τ within this period (σ taken as linear in it); never
        // before the previous edge (a segment's last pulses may run past its end).
        let machine_at = |tau: u128, last: u128| -> u128 {
            let into = (tau.max(plan0) - plan0) * (t1 - t0);
            let t = into.checked_div(advance_q32).map_or(t1, |d| t0 + d);
            t.max(last)
        };
        loop {
            let Some(active) = self.active.as_mut() else {
                if !self.ensure_active() {
                    return Ok(()); // ran dry: the plan clock stops at the plan's end
                }
                continue;
            };
            while let Some(t) = active.train.next_time_q32() {
                let tau = active.plan_start_q32 + u128::from(t);
                if tau > plan1 {
                    self.plan_q32 = plan1;
                    return Ok(());
                }
                let pulse = match active.train.next_pulse() {
                    Ok(pulse) => pulse.expect("a pulse was due"),
                    Err(source) => {
                        let err = PlayerError::Fault {
                            move_sequence: active.job.move_sequence,
                            source_line: active.job.source_line,
                            source,
                        };
                        self.emergency_stop();
                        return Err(err);
                    }
                };
                let negative = active.job.segment.negative_mask;
                for k in 0..MAX_AXES {
                    if pulse.axes >> k & 1 == 1 {
                        self.position_steps[k] += if negative >> k & 1 == 1 { -1 } else { 1 };
                    }
                }
                self.last_edge_q32 = machine_at(tau, self.last_edge_q32);
                on_edge(Edge {
                    time_q32: self.last_edge_q32,
                    axes: pulse.axes,
                    negative,
                });
            }
            let end_q32 = active.plan_start_q32 + active.job.duration_q32;
            if end_q32 > plan1 {
                self.plan_q32 = plan1;
                return Ok(());
            }
            self.plan_q32 = end_q32;
            // (Not across a piece without steps: a dwell at rest between them.)
            self.previous_rate = (active.job.segment.dominant_steps() > 0).then(|| {
                1.0 / q32_to_seconds(
                    active.train.period_q32().into(),
                    self.options.steps.timer_hz,
                )
            });
            self.completed += 1;
            self.last_completed = Some((active.job.move_sequence, active.job.source_line));
            self.active = None;
        }
    }

    /// Drop the segment in progress and everything queued; the next segment starts where
    /// the plan clock stands.
    fn clear_plan(&mut self) {
        self.active = None;
        self.previous_rate = None;
        self.queue.clear();
        self.queued_q32 = 0;
    }

    /// At rest after a cancel: drop the rest of the plan, ready for a new one.
    fn drop_plan(&mut self) {
        self.clear_plan();
        self.hold = None;
        self.feed = 1.0;
        self.state = PlayerState::Idle;
        self.input_finished = false;
    }

    /// Stop at once: the segment in progress and everything queued are dropped, the position
    /// stays where the last pulse left it.
    pub fn emergency_stop(&mut self) {
        self.clear_plan();
        self.feed = 0.0;
        self.hold = None;
        self.state = PlayerState::Stopped;
    }

    /// Leave the stopped state; the next segment starts from the current position.
    pub fn reset(&mut self) {
        if self.state == PlayerState::Stopped {
            self.state = PlayerState::Idle;
            self.feed = 1.0;
            self.hold = None;
            self.input_finished = false;
        }
    }

    pub fn state(&self) -> PlayerState {
        self.state
    }

    /// Absolute step position of each axis.
    pub fn position_steps(&self) -> [i64; MAX_AXES] {
        self.position_steps
    }

    /// Executed joint positions (rad, m, m).
    pub fn position(&self) -> [f64; MAX_AXES] {
        std::array::from_fn(|k| {
            self.position_steps[k] as f64 / self.options.steps.steps_per_unit[k]
        })
    }

    /// Executed joint velocities: σ times the current step rate of each axis (rad/s, m/s,
    /// m/s; after a segment's last pulse, its last rate); zero when no segment with steps
    /// is playing.
    pub fn velocity(&self) -> [f64; MAX_AXES] {
        let Some(active) = self
            .active
            .as_ref()
            .filter(|a| a.job.segment.dominant_steps() > 0)
        else {
            return [0.0; MAX_AXES];
        };
        let seg = &active.job.segment;
        let dominant_rate = self.feed * self.dominant_rate(&active.train);
        // The other axes' share of the dominant's steps. A segment of a few steps (the
        // planner's single steps near rest) has 0 or 1 of each, a share of 0 or 1: over
        // the next segments of the same move, until an axis has RATIO_WINDOW_STEPS steps,
        // the share is the move's there.
        const RATIO_WINDOW_STEPS: u32 = 32;
        let mut counts = seg.step_counts;
        let mut directions: [f64; MAX_AXES] = std::array::from_fn(|k| seg.direction(k) as f64);
        let dominant = seg.dominant_axis as usize;
        for job in self
            .queue
            .iter()
            .take_while(|j| j.move_sequence == active.job.move_sequence)
        {
            // (Any axis: another may lead in the segments ahead.)
            if counts.iter().any(|&c| c >= RATIO_WINDOW_STEPS) {
                break;
            }
            let next = &job.segment;
            if (0..MAX_AXES).any(|k| {
                next.step_counts[k] > 0
                    && counts[k] > 0
                    && next.direction(k) as f64 != directions[k]
            }) {
                break; // an axis turns back: another stretch of the move
            }
            for k in 0..MAX_AXES {
                if counts[k] == 0 {
                    directions[k] = next.direction(k) as f64;
                }
                counts[k] += next.step_counts[k];
            }
        }
        let total = counts[dominant] as f64;
        std::array::from_fn(|k| {
            let rate = dominant_rate * counts[k] as f64 / total;
            directions[k] * rate / self.options.steps.steps_per_unit[k]
        })
    }

    /// The plan clock (Q32 ticks since the first segment's start): it stands still while the
    /// machine is held or waits.
    pub fn plan_time_q32(&self) -> u128 {
        self.plan_q32
    }

    /// The segment playing now: its move and source line.
    pub fn current(&self) -> Option<(u64, u32)> {
        self.active
            .as_ref()
            .map(|a| (a.job.move_sequence, a.job.source_line))
    }

    /// Segments played to their end, and the move and line of the last one.
    pub fn completed(&self) -> (u64, Option<(u64, u32)>) {
        (self.completed, self.last_completed)
    }

    /// Segments queued or playing.
    pub fn queued(&self) -> usize {
        self.queue.len() + usize::from(self.active.is_some())
    }

    /// Times the queued plan ran short while the input was not finished (each began a hold).
    pub fn underruns(&self) -> u64 {
        self.underruns
    }
}

#[cfg(test)]
mod tests;
