//! Screw commands executed on the plan timeline.
//!
//! The screw driver's commands are breakpoints on the plan timeline: rpm runs between
//! consecutive commands as the driver publishes them ([`Hold`]: linear for raw breakpoints,
//! held for smoothed, resampled or flow-compensated commands; constant after the last one
//! known), the pin switches at a command.
//! The executor follows them as *execution* reaches their plan time. Under a feed scale σ the
//! screw turns at σ times the planned rpm, so material per length of path is kept through a
//! hold; its angle therefore integrates the planned rpm over plan time. Held, idle or
//! stopped, the screw is stopped and the pin closed (the safe state); the pin reopens before
//! motion resumes, by its delay, so material flows again exactly where it stopped.

use std::collections::VecDeque;

use polar_cell_msgs::Hold;

use crate::q32_to_seconds;

/// A screw command on the plan timeline.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScrewStep {
    /// Plan time from which it holds (Q32 ticks).
    pub plan_q32: u128,
    pub rpm: f64,
    pub pin_open: bool,
    pub source_line: u32,
}

/// Why a screw command is refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ScrewError {
    #[error("screw command of line {source_line} at plan time {plan_s} s comes before the previous one at {previous_s} s")]
    OutOfOrder {
        source_line: u32,
        plan_s: f64,
        previous_s: f64,
    },
    #[error("screw command of line {source_line}: rpm {rpm} is not a finite number ≥ 0")]
    BadRpm { source_line: u32, rpm: f64 },
    #[error("the screw command queue is full ({capacity} commands)")]
    QueueFull { capacity: usize },
}

/// Queued screw commands and the executed screw state.
#[derive(Clone, Debug)]
pub struct ScrewTrack {
    timer_hz: f64,
    hold: Hold,
    capacity: usize,
    queue: VecDeque<ScrewStep>,
    /// The command in force at `plan_q32`.
    commanded: ScrewStep,
    plan_q32: u128,
    feed: f64,
    pin_allowed: bool,
    angle_rad: f64,
}

impl ScrewTrack {
    /// A track for commands that run between each other as `hold` says (the screw driver's
    /// `command_hold`).
    pub fn new(timer_hz: f64, hold: Hold, capacity: usize) -> ScrewTrack {
        ScrewTrack {
            timer_hz,
            hold,
            capacity,
            queue: VecDeque::with_capacity(capacity),
            commanded: ScrewStep {
                plan_q32: 0,
                rpm: 0.0,
                pin_open: false,
                source_line: 0,
            },
            plan_q32: 0,
            feed: 0.0,
            pin_allowed: false,
            angle_rad: 0.0,
        }
    }

    /// Queue a command (plan times must not go back). Stamps are whole nanoseconds rounded
    /// from the producer's floating-point plan time, so two commands computed apart (the
    /// screw driver's chunks) can meet a nanosecond out of order: up to one timer tick
    /// earlier than the previous command counts as the same instant.
    pub fn push(&mut self, mut step: ScrewStep) -> Result<(), ScrewError> {
        if !(step.rpm.is_finite() && step.rpm >= 0.0) {
            return Err(ScrewError::BadRpm {
                source_line: step.source_line,
                rpm: step.rpm,
            });
        }
        let previous = self
            .queue
            .back()
            .map_or(self.commanded.plan_q32, |s| s.plan_q32);
        if step.plan_q32 < previous
            && previous - step.plan_q32 <= u128::from(step_core::ONE_TICK_Q32)
        {
            step.plan_q32 = previous;
        }
        if step.plan_q32 < previous {
            return Err(ScrewError::OutOfOrder {
                source_line: step.source_line,
                plan_s: q32_to_seconds(step.plan_q32, self.timer_hz),
                previous_s: q32_to_seconds(previous, self.timer_hz),
            });
        }
        if self.queue.len() >= self.capacity {
            return Err(ScrewError::QueueFull {
                capacity: self.capacity,
            });
        }
        self.queue.push_back(step);
        Ok(())
    }

    /// Free places in the queue.
    pub fn free_slots(&self) -> usize {
        self.capacity - self.queue.len()
    }

    /// The planned rpm at plan time `plan_q32` (≥ the command in force): held, or linear
    /// towards the next queued command.
    fn rpm_at(&self, plan_q32: u128) -> f64 {
        let from = &self.commanded;
        match self.queue.front() {
            Some(next) if self.hold == Hold::FirstOrder && next.plan_q32 > from.plan_q32 => {
                let s = (plan_q32.saturating_sub(from.plan_q32)) as f64
                    / (next.plan_q32 - from.plan_q32) as f64;
                from.rpm + (next.rpm - from.rpm) * s.min(1.0)
            }
            _ => from.rpm,
        }
    }

    /// Execute up to plan time `plan_now_q32` at feed scale `feed`; `pin_allowed` is false
    /// while the machine is held, idle or stopped (the pin then stays closed), and true
    /// while it moves or waits out the pin's delay before a resume.
    pub fn advance(&mut self, plan_now_q32: u128, feed: f64, pin_allowed: bool) {
        let rad_per_rpm_tick_q32 = std::f64::consts::TAU / 60.0 * q32_to_seconds(1, self.timer_hz);
        while self.plan_q32 < plan_now_q32 {
            let next_change = self
                .queue
                .front()
                .map_or(u128::MAX, |s| s.plan_q32.max(self.plan_q32));
            let until = next_change.min(plan_now_q32);
            let mean_rpm = (self.rpm_at(self.plan_q32) + self.rpm_at(until)) / 2.0;
            self.angle_rad += mean_rpm * (until - self.plan_q32) as f64 * rad_per_rpm_tick_q32;
            self.plan_q32 = until;
            if until == next_change {
                self.commanded = self.queue.pop_front().expect("a change was due");
            }
        }
        // Commands due exactly now take effect now.
        while self
            .queue
            .front()
            .is_some_and(|s| s.plan_q32 <= self.plan_q32)
        {
            self.commanded = self.queue.pop_front().expect("checked");
        }
        self.feed = feed;
        self.pin_allowed = pin_allowed;
    }

    /// The rpm and pin actually executed: σ times the planned rpm (0 at rest), the pin as
    /// commanded while allowed (see [`ScrewTrack::advance`]), else closed.
    pub fn executed(&self) -> (f64, bool) {
        let rpm = if self.feed > 0.0 {
            self.feed * self.rpm_at(self.plan_q32)
        } else {
            0.0
        };
        (rpm, self.pin_allowed && self.commanded.pin_open)
    }

    /// The command in force on the plan timeline (whether or not the machine runs).
    pub fn commanded(&self) -> ScrewStep {
        self.commanded
    }

    /// The screw's angle (rad): the executed rpm integrated.
    pub fn angle_rad(&self) -> f64 {
        self.angle_rad
    }

    /// Drop every queued command and stop (emergency stop).
    pub fn stop(&mut self) {
        self.queue.clear();
        self.commanded.rpm = 0.0;
        self.commanded.pin_open = false;
        self.feed = 0.0;
        self.pin_allowed = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HZ: f64 = 1e6;

    fn q32(seconds: f64) -> u128 {
        crate::seconds_to_q32(seconds, HZ)
    }

    fn step(t: f64, rpm: f64, pin_open: bool) -> ScrewStep {
        ScrewStep {
            plan_q32: q32(t),
            rpm,
            pin_open,
            source_line: (t * 10.0) as u32,
        }
    }

    /// The angle is the integral of the piecewise-linear rpm, whatever the advance steps.
    #[test]
    fn the_angle_integrates_the_commands_exactly_across_any_advance_steps() {
        let commands = [
            step(0.0, 60.0, true),
            step(0.25, 120.0, true),
            step(0.5, 0.0, false),
            step(0.75, 30.0, true),
        ];
        // ∫ rpm dt (rpm·s): trapezoids 22.5 + 15 + 3.75, then 30 held for 0.25 s: 7.5.
        let exact = 48.75 / 60.0 * std::f64::consts::TAU;
        for stride_s in [0.001, 0.0137, 0.25, 0.3, 1.0] {
            let mut track = ScrewTrack::new(HZ, Hold::FirstOrder, 16);
            for c in commands {
                track.push(c).unwrap();
            }
            let mut t: f64 = 0.0;
            while t < 1.0 {
                t = (t + stride_s).min(1.0);
                track.advance(q32(t), 1.0, true);
            }
            assert!(
                (track.angle_rad() - exact).abs() < 1e-9,
                "stride {stride_s}: {}",
                track.angle_rad()
            );
            assert_eq!(track.executed(), (30.0, true));
        }
        // Half way between two commands, the rpm is half way.
        let mut track = ScrewTrack::new(HZ, Hold::FirstOrder, 16);
        for c in commands {
            track.push(c).unwrap();
        }
        track.advance(q32(0.375), 1.0, true);
        assert!((track.executed().0 - 60.0).abs() < 1e-9);
        assert!(track.executed().1);
    }

    /// Held commands (the flow-compensated default): each rpm until the next command.
    #[test]
    fn held_commands_integrate_as_steps() {
        let mut track = ScrewTrack::new(HZ, Hold::ZeroOrder, 16);
        for c in [
            step(0.0, 60.0, true),
            step(0.25, 120.0, true),
            step(0.5, 0.0, false),
        ] {
            track.push(c).unwrap();
        }
        track.advance(q32(0.125), 1.0, true);
        assert_eq!(track.executed(), (60.0, true), "held, not half way to 120");
        track.advance(q32(1.0), 1.0, true);
        // 0.25 s at 1 rev/s and 0.25 s at 2 rev/s: 0.75 revolutions (linear would give 0.625
        // over the same half second, and more after).
        let exact = 0.75 * std::f64::consts::TAU;
        assert!(
            (track.angle_rad() - exact).abs() < 1e-9,
            "{}",
            track.angle_rad()
        );
    }

    #[test]
    fn a_hold_scales_the_rpm_and_closes_the_pin_until_motion_resumes() {
        let mut track = ScrewTrack::new(HZ, Hold::FirstOrder, 4);
        track.push(step(0.0, 90.0, true)).unwrap();
        track.advance(q32(0.1), 1.0, true);
        assert_eq!(track.executed(), (90.0, true));
        track.advance(q32(0.15), 0.5, true); // decelerating: half the speed, half the rpm
        assert_eq!(track.executed(), (45.0, true));
        track.advance(q32(0.2), 0.0, false); // held: plan time stands still
        assert_eq!(track.executed(), (0.0, false));
        assert_eq!(track.commanded().rpm, 90.0);
        track.advance(q32(0.2), 0.0, true); // resuming: the pin opens before motion
        assert_eq!(track.executed(), (0.0, true));
        track.advance(q32(0.3), 1.0, true);
        assert_eq!(track.executed(), (90.0, true));
        // The angle follows plan time: 0.3 s at 90 rpm, however it was executed.
        assert!((track.angle_rad() - 0.3 * 1.5 * std::f64::consts::TAU).abs() < 1e-9);
    }

    #[test]
    fn bad_commands_are_refused() {
        let mut track = ScrewTrack::new(HZ, Hold::FirstOrder, 2);
        track.push(step(1.0, 10.0, true)).unwrap();
        let err = track.push(step(0.5, 10.0, true)).unwrap_err();
        assert_eq!(
            err,
            ScrewError::OutOfOrder {
                source_line: 5,
                plan_s: 0.5,
                previous_s: 1.0
            }
        );
        // A nanosecond early (two chunks' rounding) is the same instant; two ticks is not.
        let mut close = ScrewTrack::new(HZ, Hold::FirstOrder, 4);
        close.push(step(1.0, 10.0, true)).unwrap();
        close.push(step(1.0 - 1e-9, 20.0, true)).unwrap();
        assert!(close.push(step(1.0 - 2e-6, 20.0, true)).is_err());
        assert!(matches!(
            track.push(step(2.0, -1.0, true)),
            Err(ScrewError::BadRpm { rpm, .. }) if rpm == -1.0
        ));
        assert!(matches!(
            track.push(step(2.0, f64::NAN, true)),
            Err(ScrewError::BadRpm { .. })
        ));
        track.push(step(2.0, 5.0, true)).unwrap();
        assert_eq!(
            track.push(step(3.0, 5.0, true)),
            Err(ScrewError::QueueFull { capacity: 2 })
        );
        track.stop();
        assert_eq!(track.executed(), (0.0, false));
        assert_eq!(track.free_slots(), 2);
    }
}
