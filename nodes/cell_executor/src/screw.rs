//! Screw commands executed on the plan timeline.
//!
//! The screw driver stamps each command with the plan time from which it holds. The executor
//! applies a command when its plan time is reached *by execution*, and the screw's angle
//! integrates the rpm executed. Plan time stands still while the machine waits for input;
//! then the screw is stopped and the pin closed (the safe state), whatever was commanded, and
//! the command resumes with the motion.

use std::collections::VecDeque;

const ONE_TICK_Q32: f64 = (1u64 << step_core::TICK_FRACTION_BITS) as f64;

/// A screw command on the plan timeline.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScrewStep {
    /// Plan time from which it holds (Q32 ticks).
    pub plan_q32: u64,
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
    capacity: usize,
    queue: VecDeque<ScrewStep>,
    /// The command in force at `plan_q32`.
    commanded: ScrewStep,
    plan_q32: u64,
    running: bool,
    angle_rad: f64,
}

impl ScrewTrack {
    pub fn new(timer_hz: f64, capacity: usize) -> ScrewTrack {
        ScrewTrack {
            timer_hz,
            capacity,
            queue: VecDeque::with_capacity(capacity),
            commanded: ScrewStep {
                plan_q32: 0,
                rpm: 0.0,
                pin_open: false,
                source_line: 0,
            },
            plan_q32: 0,
            running: false,
            angle_rad: 0.0,
        }
    }

    /// Queue a command (plan times must not go back).
    pub fn push(&mut self, step: ScrewStep) -> Result<(), ScrewError> {
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
        if step.plan_q32 < previous {
            let seconds = |q32: u64| q32 as f64 / ONE_TICK_Q32 / self.timer_hz;
            return Err(ScrewError::OutOfOrder {
                source_line: step.source_line,
                plan_s: seconds(step.plan_q32),
                previous_s: seconds(previous),
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

    /// Execute up to plan time `plan_now_q32`; `running` says whether the machine is playing
    /// segments (plan time then advances with machine time).
    pub fn advance(&mut self, plan_now_q32: u64, running: bool) {
        let rad_per_tick_q32 = std::f64::consts::TAU / 60.0 / self.timer_hz / ONE_TICK_Q32;
        while self.plan_q32 < plan_now_q32 {
            let next_change = self
                .queue
                .front()
                .map_or(u64::MAX, |s| s.plan_q32.max(self.plan_q32));
            let until = next_change.min(plan_now_q32);
            self.angle_rad +=
                self.commanded.rpm * (until - self.plan_q32) as f64 * rad_per_tick_q32;
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
        self.running = running;
    }

    /// The rpm and pin actually executed: the command in force while running, else stopped
    /// and closed.
    pub fn executed(&self) -> (f64, bool) {
        if self.running {
            (self.commanded.rpm, self.commanded.pin_open)
        } else {
            (0.0, false)
        }
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
        self.running = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HZ: f64 = 1e6;

    fn q32(seconds: f64) -> u64 {
        (seconds * HZ * ONE_TICK_Q32).round() as u64
    }

    fn step(t: f64, rpm: f64, pin_open: bool) -> ScrewStep {
        ScrewStep {
            plan_q32: q32(t),
            rpm,
            pin_open,
            source_line: (t * 10.0) as u32,
        }
    }

    /// The angle is the integral of a piecewise-constant rpm, whatever the advance steps.
    #[test]
    fn the_angle_integrates_the_commands_exactly_across_any_advance_steps() {
        let commands = [
            step(0.0, 60.0, true),
            step(0.25, 120.0, true),
            step(0.5, 0.0, false),
            step(0.75, 30.0, true),
        ];
        // ∫ rpm/60·2π dt over 1 s: 0.25·(1 + 2 + 0 + 0.5)·2π
        let exact = 0.25 * 3.5 * std::f64::consts::TAU;
        for stride_s in [0.001, 0.0137, 0.25, 0.3, 1.0] {
            let mut track = ScrewTrack::new(HZ, 16);
            for c in commands {
                track.push(c).unwrap();
            }
            let mut t: f64 = 0.0;
            while t < 1.0 {
                t = (t + stride_s).min(1.0);
                track.advance(q32(t), true);
            }
            assert!(
                (track.angle_rad() - exact).abs() < 1e-9,
                "stride {stride_s}: {}",
                track.angle_rad()
            );
            assert_eq!(track.executed(), (30.0, true));
        }
    }

    #[test]
    fn waiting_stops_the_screw_and_closes_the_pin_until_motion_resumes() {
        let mut track = ScrewTrack::new(HZ, 4);
        track.push(step(0.0, 90.0, true)).unwrap();
        track.advance(q32(0.1), true);
        assert_eq!(track.executed(), (90.0, true));
        track.advance(q32(0.1), false); // plan time stands still: starved
        assert_eq!(track.executed(), (0.0, false));
        assert_eq!(track.commanded().rpm, 90.0);
        track.advance(q32(0.2), true);
        assert_eq!(track.executed(), (90.0, true));
        assert!((track.angle_rad() - 0.2 * 1.5 * std::f64::consts::TAU).abs() < 1e-9);
    }

    #[test]
    fn bad_commands_are_refused() {
        let mut track = ScrewTrack::new(HZ, 2);
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
