//! The plan on the MCU's clock: step segments and screw commands as the MCU queues them.
//!
//! The plan's time starts at an *anchor*, an MCU plan-clock reading chosen a little ahead of
//! the MCU's clock when the print starts. Segment `k` starts at the anchor plus the exact sum
//! of the durations before it, rounded to a whole tick; its duration is the difference to the
//! next start, so the segments tile the clock without gaps and the rounding never
//! accumulates: every step lands within one tick of the plan (½ for the start, ½ for the
//! pulse).

use cell_protocol::message::{QueuedSegment, ScrewRamp, SEGMENT_ENDS_AT_REST};
use polar_cell_msgs::{Hold, ScrewCommand, StepSegment, UnplayableSegment};

/// Why a planned message cannot go to the MCU.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ScheduleError {
    #[error(transparent)]
    Unplayable(#[from] UnplayableSegment),
    #[error("screw command of line {source_line}: rpm {rpm} is not a finite number in 0..=2e6")]
    BadRpm { source_line: u32, rpm: f64 },
    #[error(
        "screw command of line {source_line} at plan time {plan_s} s comes before the \
         previous one at {previous_s} s"
    )]
    ScrewOutOfOrder {
        source_line: u32,
        plan_s: f64,
        previous_s: f64,
    },
}

/// A screw command's plan time, following the previous command's (if any): stamps are whole
/// nanoseconds, so one a rounding (under 1 µs) earlier is the same instant; one earlier
/// still is out of order, `Err(previous_s)`.
pub(crate) fn screw_time_after(plan_s: f64, previous_s: Option<f64>) -> Result<f64, f64> {
    match previous_s {
        Some(previous_s) if plan_s < previous_s && previous_s - plan_s < 1e-6 => Ok(previous_s),
        Some(previous_s) if plan_s < previous_s => Err(previous_s),
        _ => Ok(plan_s),
    }
}

/// A screw command waiting for its successor (first-order hold).
#[derive(Clone, Copy, Debug, PartialEq)]
struct PendingScrew {
    clock: u64,
    plan_s: f64,
    millirpm: i32,
    pin_open: bool,
}

/// The schedule of one print on one MCU.
#[derive(Clone, Debug)]
pub struct Schedule {
    timer_hz: f64,
    hold: Hold,
    anchor_clock: u64,
    /// Exact plan time at the end of the segments scheduled so far (ticks).
    plan_end_ticks: f64,
    last_screw: Option<PendingScrew>,
}

impl Schedule {
    /// A schedule whose plan time 0 is MCU plan clock `anchor_clock`; screw commands run
    /// between each other as `hold` says.
    pub fn new(timer_hz: f64, hold: Hold, anchor_clock: u64) -> Schedule {
        Schedule {
            timer_hz,
            hold,
            anchor_clock,
            plan_end_ticks: 0.0,
            last_screw: None,
        }
    }

    /// MCU plan clock at plan time `plan_s`.
    pub fn clock_at(&self, plan_s: f64) -> u64 {
        self.anchor_clock + (plan_s * self.timer_hz).round().max(0.0) as u64
    }

    /// Plan time (s) at MCU plan clock `clock`.
    pub fn plan_s_at(&self, clock: u64) -> f64 {
        (clock as f64 - self.anchor_clock as f64) / self.timer_hz
    }

    /// MCU plan clock where the scheduled segments end.
    pub fn end_clock(&self) -> u64 {
        self.anchor_clock + self.plan_end_ticks.round() as u64
    }

    /// The next segment, on the MCU's clock.
    pub fn segment(&mut self, seg: &StepSegment) -> Result<QueuedSegment, ScheduleError> {
        let (segment, ticks) = seg.playable(self.timer_hz)?;
        let start = self.end_clock();
        self.plan_end_ticks += ticks;
        Ok(QueuedSegment {
            start_clock: start,
            duration_ticks: (self.end_clock() - start) as u32,
            tag: seg.move_sequence as u32,
            flags: if seg.ends_at_rest {
                SEGMENT_ENDS_AT_REST
            } else {
                0
            },
            segment,
        })
    }

    /// A screw command in force from plan time `plan_s`: the ramp to queue now (a
    /// first-order hold knows a command's ramp only when the next one arrives: each command
    /// queues the ramp from the previous one to it).
    ///
    /// `earliest_clock` is the first MCU plan clock the ramp may still start at (the MCU has
    /// played up to about there). A first-order ramp whose start has passed — the next
    /// command came later than the MCU reached the previous one — starts there instead, from
    /// the rpm then held, and still reaches this command's rpm at this command's time.
    pub fn screw(
        &mut self,
        cmd: &ScrewCommand,
        plan_s: f64,
        earliest_clock: u64,
    ) -> Result<Option<ScrewRamp>, ScheduleError> {
        if !(cmd.rpm.is_finite() && (0.0..=2e6).contains(&cmd.rpm)) {
            return Err(ScheduleError::BadRpm {
                source_line: cmd.source_line,
                rpm: cmd.rpm,
            });
        }
        let plan_s =
            screw_time_after(plan_s, self.last_screw.map(|p| p.plan_s)).map_err(|previous_s| {
                ScheduleError::ScrewOutOfOrder {
                    source_line: cmd.source_line,
                    plan_s,
                    previous_s,
                }
            })?;
        let now = PendingScrew {
            clock: self.clock_at(plan_s),
            plan_s,
            millirpm: (cmd.rpm * 1000.0).round() as i32,
            pin_open: cmd.pin_open,
        };
        let step_to_now = ScrewRamp {
            start_clock: now.clock,
            ramp_ticks: 0,
            target_millirpm: now.millirpm,
            pin_open: now.pin_open,
        };
        let previous = self.last_screw.replace(now);
        Ok(match (self.hold, previous) {
            // Held, a command that changes nothing needs no frame (a resampling screw driver
            // repeats itself between moves).
            (Hold::ZeroOrder, Some(p))
                if (p.millirpm, p.pin_open) == (now.millirpm, now.pin_open) =>
            {
                None
            }
            (Hold::ZeroOrder, _) | (Hold::FirstOrder, None) => Some(step_to_now),
            // From the previous command's rpm at its time to this one's at this time.
            (Hold::FirstOrder, Some(p)) => {
                let start = p.clock.max(earliest_clock).min(now.clock);
                Some(ScrewRamp {
                    start_clock: start,
                    ramp_ticks: (now.clock - start).min(u32::MAX as u64) as u32,
                    target_millirpm: now.millirpm,
                    pin_open: p.pin_open,
                })
            }
        })
    }

    /// The screw input ended: what a first-order hold still owes (the last command, held).
    pub fn finish_screw(&mut self) -> Option<ScrewRamp> {
        match self.hold {
            Hold::ZeroOrder => None,
            Hold::FirstOrder => self.last_screw.map(|p| ScrewRamp {
                start_clock: p.clock,
                ramp_ticks: 0,
                target_millirpm: p.millirpm,
                pin_open: p.pin_open,
            }),
        }
    }
}

#[cfg(test)]
mod tests;
