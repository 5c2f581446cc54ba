//! The segment queue and the pulse clock.
//!
//! Segments play back to back: each starts where the previous one ended, so the machine
//! timeline is the plan's timeline. When the queue runs dry the machine waits (an *underrun*:
//! the planner always hands over a plan that ends at rest, so waiting is safe), and the next
//! segment starts when it is first seen — never in the past, so no pulse is ever fired late
//! to catch up.
//!
//! Times are timer ticks in Q32 (`_q32`), as in [`step_core`]; the caller's clock is the
//! only clock.

use std::collections::VecDeque;

use polar_cell_msgs::StepSegment;
use step_core::{PulseTrain, Segment, SegmentError, StepFault, StepOptions, MAX_AXES};

const ONE_TICK_Q32: f64 = (1u64 << step_core::TICK_FRACTION_BITS) as f64;

/// How the player is set up.
#[derive(Clone, Debug, PartialEq)]
pub struct PlayerOptions {
    pub steps: StepOptions,
    /// Segments queued ahead of execution at most (the bound on memory and plan-ahead).
    pub queue_capacity: usize,
    /// Absolute step position of each axis before the first segment.
    pub initial_steps: [i64; MAX_AXES],
}

impl Default for PlayerOptions {
    fn default() -> Self {
        PlayerOptions {
            steps: StepOptions::default(),
            queue_capacity: 4096,
            initial_steps: [0; MAX_AXES],
        }
    }
}

/// What goes wrong while queueing or playing, with the segment it concerns.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlayerError {
    #[error("step segment of move {move_sequence} (line {source_line}): {source}")]
    Segment {
        move_sequence: u64,
        source_line: u32,
        source: SegmentError,
    },
    #[error(
        "step segment of move {move_sequence} (line {source_line}) is timed for a \
         {segment_hz} Hz timer; this machine's timer runs at {timer_hz} Hz"
    )]
    TimerMismatch {
        move_sequence: u64,
        source_line: u32,
        segment_hz: f64,
        timer_hz: f64,
    },
    #[error(
        "step segment of move {move_sequence} (line {source_line}) lasts {duration_s} s: \
         must be finite, ≥ 0 and under 2^31 timer ticks"
    )]
    BadDuration {
        move_sequence: u64,
        source_line: u32,
        duration_s: f64,
    },
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
    /// Length on the timeline (Q32 ticks): pulses may end a little before it (a pause
    /// segment has none at all).
    pub duration_q32: u64,
    pub move_sequence: u64,
    pub source_line: u32,
}

impl SegmentJob {
    /// Validate and convert a planned segment for a machine with timer `timer_hz`.
    pub fn from_message(msg: &StepSegment, timer_hz: f64) -> Result<SegmentJob, PlayerError> {
        let (move_sequence, source_line) = (msg.move_sequence, msg.source_line);
        let segment = msg.compile().map_err(|source| PlayerError::Segment {
            move_sequence,
            source_line,
            source,
        })?;
        // Step counts and ramps are in ticks of the segment's timer: they must be ours.
        let dominant = msg.step_counts.get(msg.dominant_axis as usize).copied();
        if dominant.unwrap_or(0) > 0 && msg.timer_frequency_hz != timer_hz {
            return Err(PlayerError::TimerMismatch {
                move_sequence,
                source_line,
                segment_hz: msg.timer_frequency_hz,
                timer_hz,
            });
        }
        let ticks = msg.duration_s * timer_hz;
        if !(ticks.is_finite() && ticks >= 0.0 && ticks < (1u64 << 31) as f64) {
            return Err(PlayerError::BadDuration {
                move_sequence,
                source_line,
                duration_s: msg.duration_s,
            });
        }
        Ok(SegmentJob {
            segment,
            duration_q32: (ticks * ONE_TICK_Q32).round() as u64,
            move_sequence,
            source_line,
        })
    }
}

/// Pulses fired at one instant, as a driver would set its step pins.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Edge {
    /// Machine time (Q32 ticks).
    pub time_q32: u64,
    /// Bit `k`: axis `k` steps.
    pub axes: u8,
    /// Bit `k`: axis `k` steps in the negative direction (meaningful where `axes` is set).
    pub negative: u8,
}

/// Where the machine is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlayerState {
    /// Nothing to play: not started, finished, or starved (see [`Player::underruns`]).
    Idle,
    /// Playing a segment.
    Running,
    /// Stopped at once (emergency stop or a step fault): nothing plays until [`Player::reset`].
    Stopped,
}

#[derive(Clone, Debug)]
struct Active {
    job: SegmentJob,
    train: PulseTrain,
    start_q32: u64,
    /// Plan time at the segment's start (Q32 ticks since the first segment).
    plan_start_q32: u64,
}

/// Plays queued segments against the caller's clock.
#[derive(Clone, Debug)]
pub struct Player {
    options: PlayerOptions,
    queue: VecDeque<SegmentJob>,
    queued_q32: u64,
    active: Option<Active>,
    position_steps: [i64; MAX_AXES],
    state: PlayerState,
    /// Where the next segment may start on the machine timeline.
    next_start_q32: u64,
    /// Plan time executed by the end of the last finished segment.
    plan_done_q32: u64,
    now_q32: u64,
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
            next_start_q32: 0,
            plan_done_q32: 0,
            now_q32: 0,
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

    /// Say that no more segments will come: running dry from now on is the end, not an
    /// underrun.
    pub fn finish_input(&mut self) {
        self.input_finished = true;
    }

    /// Free places in the queue.
    pub fn free_slots(&self) -> usize {
        self.options.queue_capacity - self.queue.len()
    }

    /// Plan time queued but not executed yet (Q32 ticks): the plan-ahead.
    pub fn ahead_q32(&self) -> u64 {
        let remaining = self.active.as_ref().map_or(0, |a| {
            (a.start_q32 + a.job.duration_q32).saturating_sub(self.now_q32)
        });
        self.queued_q32 + remaining
    }

    /// Play everything due up to machine time `now_q32` (which must not go back), handing each
    /// instant's pulses to `on_edge` in time order.
    pub fn advance_to(
        &mut self,
        now_q32: u64,
        mut on_edge: impl FnMut(Edge),
    ) -> Result<(), PlayerError> {
        self.now_q32 = self.now_q32.max(now_q32);
        let now = self.now_q32;
        while self.state != PlayerState::Stopped {
            let Some(active) = self.active.as_mut() else {
                let Some(job) = self.queue.pop_front() else {
                    if self.state == PlayerState::Running && !self.input_finished {
                        self.underruns += 1;
                    }
                    self.state = PlayerState::Idle;
                    return Ok(());
                };
                self.queued_q32 -= job.duration_q32;
                // Back to back while running; after waiting, from now — never in the past.
                let start_q32 = if self.state == PlayerState::Running {
                    self.next_start_q32
                } else {
                    self.next_start_q32.max(now)
                };
                self.active = Some(Active {
                    train: PulseTrain::new(&job.segment),
                    job,
                    start_q32,
                    plan_start_q32: self.plan_done_q32,
                });
                self.state = PlayerState::Running;
                continue;
            };
            while let Some(t) = active.train.next_time_q32() {
                if active.start_q32 + t > now {
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
                on_edge(Edge {
                    time_q32: active.start_q32 + pulse.time_q32,
                    axes: pulse.axes,
                    negative,
                });
            }
            let end_q32 = active.start_q32 + active.job.duration_q32;
            if end_q32 > now {
                return Ok(());
            }
            self.next_start_q32 = end_q32;
            self.plan_done_q32 = active.plan_start_q32 + active.job.duration_q32;
            self.completed += 1;
            self.last_completed = Some((active.job.move_sequence, active.job.source_line));
            self.active = None;
        }
        Ok(())
    }

    /// Stop at once: the segment in progress and everything queued are dropped, the position
    /// stays where the last pulse left it.
    pub fn emergency_stop(&mut self) {
        self.active = None;
        self.queue.clear();
        self.queued_q32 = 0;
        self.state = PlayerState::Stopped;
    }

    /// Leave the stopped state; the next segment starts from the current position.
    pub fn reset(&mut self) {
        if self.state == PlayerState::Stopped {
            self.state = PlayerState::Idle;
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

    /// Executed joint velocities: the current step rate of each axis (rad/s, m/s, m/s); zero
    /// when no pulse train is running.
    pub fn velocity(&self) -> [f64; MAX_AXES] {
        let Some(active) = self.active.as_ref().filter(|a| !a.train.is_done()) else {
            return [0.0; MAX_AXES];
        };
        let seg = &active.job.segment;
        let dominant_rate =
            self.options.steps.timer_hz * ONE_TICK_Q32 / active.train.period_q32() as f64;
        let total = seg.dominant_steps() as f64;
        std::array::from_fn(|k| {
            let rate = dominant_rate * seg.step_counts[k] as f64 / total;
            seg.direction(k) as f64 * rate / self.options.steps.steps_per_unit[k]
        })
    }

    /// Plan time reached at machine time `now_q32` (Q32 ticks since the first segment's start):
    /// it stands still while the machine waits.
    pub fn plan_time_q32(&self) -> u64 {
        match &self.active {
            Some(a) => {
                a.plan_start_q32
                    + self
                        .now_q32
                        .saturating_sub(a.start_q32)
                        .min(a.job.duration_q32)
            }
            None => self.plan_done_q32,
        }
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

    /// Times the queue ran dry while the input was not finished.
    pub fn underruns(&self) -> u64 {
        self.underruns
    }
}

#[cfg(test)]
mod tests;
