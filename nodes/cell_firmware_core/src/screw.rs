//! The screw and the nozzle pin: a queue of speed ramps on the plan clock, and the screw
//! angle integrated exactly (the speed is piecewise linear, so each piece's trapezoid is its
//! integral).
//!
//! Speeds and the angle are evaluated where an output or a report needs them (a control
//! period, a state message), not per step, so the multiplications and the one integer
//! division of an interpolation stay off the step path.

use cell_protocol::message::ScrewRamp;
use heapless::Deque;

/// Why a screw command was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScrewRefusal {
    /// It starts before a command queued ahead of it.
    OutOfOrder,
    Full,
}

/// The screw's schedule and state, holding up to `S` future commands.
#[derive(Clone, Debug)]
pub struct Screw<const S: usize> {
    queue: Deque<ScrewRamp, S>,
    /// The ramp in force: from `from_millirpm` at `start` to `to_millirpm` at `start + ticks`.
    start: u64,
    ramp_ticks: u32,
    from_millirpm: i32,
    to_millirpm: i32,
    pin_open: bool,
    /// Plan tick the schedule has been played to.
    now: u64,
    /// Plan tick up to which the angle is integrated (at most `now`), and twice the integral
    /// in millirpm·ticks.
    integrated_to: u64,
    twice_angle: i64,
}

impl<const S: usize> Default for Screw<S> {
    fn default() -> Self {
        Screw::new()
    }
}

impl<const S: usize> Screw<S> {
    pub const fn new() -> Screw<S> {
        Screw {
            queue: Deque::new(),
            start: 0,
            ramp_ticks: 0,
            from_millirpm: 0,
            to_millirpm: 0,
            pin_open: false,
            now: 0,
            integrated_to: 0,
            twice_angle: 0,
        }
    }

    /// Queue a command; `plan_now` is the plan tick already played. A command that starts
    /// before `plan_now` arrived late (a frame resent on a damaged line takes longer than the
    /// host's margin): it starts now and still ends where it would have, and `Ok(true)` says
    /// so. Unlike a step segment, a screw ramp started late loses no position — only a few
    /// ms of material — so it is not a fault.
    pub fn push(&mut self, mut command: ScrewRamp, plan_now: u64) -> Result<bool, ScrewRefusal> {
        // Two late commands in one batch: the first was moved to `plan_now` already.
        if self
            .queue
            .back()
            .is_some_and(|last| command.start_clock.max(plan_now) < last.start_clock)
        {
            return Err(ScrewRefusal::OutOfOrder);
        }
        let late = command.start_clock < plan_now;
        if late {
            let end = command.start_clock + command.ramp_ticks as u64;
            command.ramp_ticks = end.saturating_sub(plan_now).min(u32::MAX as u64) as u32;
            command.start_clock = plan_now;
        }
        self.queue
            .push_back(command)
            .map_err(|_| ScrewRefusal::Full)?;
        Ok(late)
    }

    /// Speed of the ramp in force at plan tick `t` (≥ its start).
    fn ramp_at(&self, t: u64) -> i32 {
        let into = t.saturating_sub(self.start);
        if into >= self.ramp_ticks as u64 {
            return self.to_millirpm;
        }
        let span = self.to_millirpm as i64 - self.from_millirpm as i64;
        (self.from_millirpm as i64 + span * into as i64 / self.ramp_ticks as i64) as i32
    }

    /// Twice the integral of the ramp in force from `integrated_to` to `t`, split at the
    /// ramp's end (each piece is linear, so its trapezoid is exact).
    fn twice_angle_since_integrated(&self, t: u64) -> i64 {
        let ramp_end = self.start + self.ramp_ticks as u64;
        let mut twice = 0i64;
        let mut a = self.integrated_to;
        while a < t {
            let b = if a < ramp_end { t.min(ramp_end) } else { t };
            twice = twice
                .saturating_add((self.ramp_at(a) as i64 + self.ramp_at(b) as i64) * (b - a) as i64);
            a = b;
        }
        twice
    }

    /// Fold the ramp in force into the angle up to plan tick `t`.
    fn integrate_to(&mut self, t: u64) {
        self.twice_angle = self
            .twice_angle
            .saturating_add(self.twice_angle_since_integrated(t));
        self.integrated_to = self.integrated_to.max(t);
    }

    /// Play the schedule up to plan tick `t`: commands starting by then take effect in order.
    /// Called at every step event, so it only integrates when a command takes effect (the
    /// angle up to `now` is computed when asked for): a step costs no 64-bit multiplication
    /// here.
    pub fn advance_to(&mut self, t: u64) {
        while let Some(next) = self.queue.front().copied() {
            if next.start_clock > t {
                break;
            }
            self.integrate_to(next.start_clock);
            self.queue.pop_front();
            self.from_millirpm = self.ramp_at(next.start_clock);
            self.start = next.start_clock;
            self.ramp_ticks = next.ramp_ticks;
            self.to_millirpm = next.target_millirpm;
            self.pin_open = next.pin_open;
        }
        self.now = self.now.max(t);
    }

    /// Speed at the plan tick last advanced to.
    pub fn millirpm(&self) -> i32 {
        self.ramp_at(self.now)
    }

    /// The pin as scheduled (a feed hold may still keep it closed).
    pub fn pin_open(&self) -> bool {
        self.pin_open
    }

    /// Angle turned so far, thousandths of a revolution (rpm × minutes = revolutions).
    pub fn angle_millirev(&self, timer_hz: u32) -> i32 {
        let twice = self
            .twice_angle
            .saturating_add(self.twice_angle_since_integrated(self.now));
        (twice / (2 * 60 * timer_hz as i64)) as i32
    }

    /// Plan tick at which the next queued command takes effect, if any.
    pub fn next_start(&self) -> Option<u64> {
        self.queue.front().map(|c| c.start_clock)
    }

    /// Commands queued and not yet in force.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Stop now: speed 0, pin closed, nothing queued; the angle turned stays.
    pub fn stop(&mut self) {
        self.integrate_to(self.now);
        self.queue.clear();
        self.start = self.now;
        self.ramp_ticks = 0;
        self.from_millirpm = 0;
        self.to_millirpm = 0;
        self.pin_open = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(start: u64, ticks: u32, target: i32, pin: bool) -> ScrewRamp {
        ScrewRamp {
            start_clock: start,
            ramp_ticks: ticks,
            target_millirpm: target,
            pin_open: pin,
        }
    }

    #[test]
    fn angle_is_the_exact_integral_of_the_ramps() {
        let mut screw = Screw::<4>::new();
        // 0 → 60 rpm over 1 s, hold 60 rpm for 2 s, then straight to 0: at 1 MHz.
        screw
            .push(ramp(1_000_000, 1_000_000, 60_000, true), 0)
            .unwrap();
        screw.push(ramp(4_000_000, 0, 0, false), 0).unwrap();
        screw.advance_to(500_000);
        assert_eq!((screw.millirpm(), screw.pin_open()), (0, false));
        screw.advance_to(1_500_000);
        assert_eq!((screw.millirpm(), screw.pin_open()), (30_000, true));
        // Mid-ramp, between commands: ½·0.5 s·0.5 rev/s.
        assert_eq!(screw.angle_millirev(1_000_000), 125);
        screw.advance_to(5_000_000);
        assert_eq!((screw.millirpm(), screw.pin_open()), (0, false));
        // ½·1 s·1 rev/s + 2 s·1 rev/s = 2.5 revolutions.
        assert_eq!(screw.angle_millirev(1_000_000), 2_500);
    }

    #[test]
    fn a_command_mid_ramp_starts_from_the_speed_reached() {
        let mut screw = Screw::<4>::new();
        screw.push(ramp(0, 1000, 10_000, true), 0).unwrap();
        screw.push(ramp(500, 1000, 0, true), 0).unwrap();
        screw.advance_to(500);
        assert_eq!(screw.millirpm(), 5_000);
        screw.advance_to(1000);
        assert_eq!(screw.millirpm(), 2_500);
    }

    /// 0 → 10,000 millirpm over ticks 0..1000, arriving at tick 400: it starts there, from
    /// the speed then (0), and still reaches 10,000 at tick 1000.
    #[test]
    fn a_late_command_starts_now_and_ends_where_it_would_have() {
        let mut screw = Screw::<2>::new();
        screw.advance_to(400);
        assert_eq!(screw.push(ramp(0, 1000, 10_000, true), 400), Ok(true));
        screw.advance_to(700);
        assert_eq!(screw.millirpm(), 5_000);
        screw.advance_to(1000);
        assert_eq!((screw.millirpm(), screw.pin_open()), (10_000, true));
        // Two late commands before the next advance (one read of a resent batch): both kept.
        assert_eq!(screw.push(ramp(1100, 0, 3_000, true), 1200), Ok(true));
        assert_eq!(screw.push(ramp(1150, 0, 4_000, true), 1200), Ok(true));
        screw.advance_to(1201);
        assert_eq!(screw.millirpm(), 4_000);
        // A step change (no ramp) that is late: at once.
        assert_eq!(screw.push(ramp(900, 0, 2_000, false), 1000), Ok(true));
        screw.advance_to(1001);
        assert_eq!((screw.millirpm(), screw.pin_open()), (2_000, false));
    }

    #[test]
    fn out_of_order_and_full_are_refused() {
        let mut screw = Screw::<2>::new();
        assert_eq!(screw.push(ramp(20, 0, 1, true), 10), Ok(false));
        assert_eq!(
            screw.push(ramp(15, 0, 1, true), 10),
            Err(ScrewRefusal::OutOfOrder)
        );
        screw.push(ramp(20, 0, 2, true), 10).unwrap();
        assert_eq!(
            screw.push(ramp(30, 0, 1, true), 10),
            Err(ScrewRefusal::Full)
        );
    }

    #[test]
    fn stop_keeps_the_angle_and_drops_the_schedule() {
        let mut screw = Screw::<2>::new();
        screw.push(ramp(0, 0, 60_000, true), 0).unwrap();
        screw.push(ramp(2_000_000, 0, 0, false), 0).unwrap();
        screw.advance_to(1_000_000);
        screw.stop();
        screw.advance_to(3_000_000);
        assert_eq!(screw.angle_millirev(1_000_000), 1_000);
        assert_eq!(
            (screw.millirpm(), screw.pin_open(), screw.queued()),
            (0, false, 0)
        );
    }
}
