//! The screw as a joint: its angle is the integral of the commanded rpm, sampled on a uniform
//! grid of plan time for `/joint_states`.
//!
//! The planner publishes the stage's joints; without the `screw` joint a
//! `robot_state_publisher` fed `urdf/polar_cell.urdf` has no transform for the screw and the
//! nozzle below it. The angle follows the commands exactly as the drive does: linear rpm
//! between breakpoints (first-order hold) or rpm held per interval (smoothed or resampled
//! commands), so it advances by 2π·(revolutions the commands feed).

use std::f64::consts::PI;

use crate::screw::Command;

/// rad/s per rpm.
const RAD_PER_S_PER_RPM: f64 = 2.0 * PI / 60.0;

/// One joint-state sample of the screw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScrewSample {
    /// Plan time, s.
    pub t: f64,
    pub angle_rad: f64,
    pub velocity_rad_per_s: f64,
}

pub use polar_cell_msgs::Hold;

/// Samples the screw angle across consecutive chunks of commands.
#[derive(Debug, Clone, PartialEq)]
pub struct ScrewAngle {
    period_s: f64,
    hold: Hold,
    /// The last command seen and the angle there.
    last: Option<(Command, f64)>,
    /// Grid origin and index of the next sample (an index, so the grid never drifts).
    origin_t: f64,
    next_index: u64,
}

impl ScrewAngle {
    /// Samples every `period_s` of plan time (must be positive) from the first command on.
    pub fn new(period_s: f64, hold: Hold) -> Self {
        ScrewAngle {
            period_s,
            hold,
            last: None,
            origin_t: 0.0,
            next_index: 0,
        }
    }

    /// The last command seen and the angle there.
    pub fn last(&self) -> Option<(Command, f64)> {
        self.last
    }

    /// The sample grid: its origin (s) and the index of the next sample.
    pub fn grid(&self) -> (f64, u64) {
        (self.origin_t, self.next_index)
    }

    /// Continue from a saved [`ScrewAngle::last`] and [`ScrewAngle::grid`].
    pub fn restore(&mut self, last: Option<(Command, f64)>, origin_t: f64, next_index: u64) {
        self.last = last;
        self.origin_t = origin_t;
        self.next_index = next_index;
    }

    /// Angle at the last command seen, rad (0 before any).
    pub fn angle_rad(&self) -> f64 {
        self.last.map_or(0.0, |(_, angle)| angle)
    }

    /// Extend by the next chunk of commands (in time order), pushing the samples that fall
    /// before its last command.
    pub fn extend(&mut self, commands: &[Command], out: &mut Vec<ScrewSample>) {
        self.walk(commands, |s| out.push(s));
    }

    /// Move past `commands` as [`ScrewAngle::extend`] does, keeping no sample.
    pub fn advance(&mut self, commands: &[Command]) {
        self.walk(commands, drop);
    }

    /// Move past `commands`, handing each sample to `sink`.
    fn walk(&mut self, commands: &[Command], sink: impl FnMut(ScrewSample)) {
        let mut samples = self.clone().samples(commands.to_vec());
        samples.by_ref().for_each(sink);
        *self = samples.angle;
    }

    /// The samples [`ScrewAngle::extend`] would push for `commands`, made one at a time as
    /// they are taken: a long dwell or a slow move has millions of them, and a chunk that
    /// held them all would make memory grow with the length of the print.
    pub fn samples(self, commands: Vec<Command>) -> ScrewSamples {
        ScrewSamples {
            angle: self,
            commands,
            next_command: 0,
        }
    }

    /// rpm at `dt` after `a` toward `b`, and rpm·s from `a` to there.
    fn run(&self, a: &Command, b: &Command, dt: f64) -> (f64, f64) {
        match self.hold {
            Hold::ZeroOrder => (a.rpm, a.rpm * dt),
            Hold::FirstOrder => {
                let slope = (b.rpm - a.rpm) / (b.t - a.t);
                (a.rpm + slope * dt, a.rpm * dt + 0.5 * slope * dt * dt)
            }
        }
    }
}

/// The samples of one chunk of commands, in time order ([`ScrewAngle::samples`]); the angle
/// it holds has advanced past them once the iterator is exhausted.
#[derive(Debug, Clone, PartialEq)]
pub struct ScrewSamples {
    angle: ScrewAngle,
    commands: Vec<Command>,
    next_command: usize,
}

impl Iterator for ScrewSamples {
    type Item = ScrewSample;

    fn next(&mut self) -> Option<ScrewSample> {
        loop {
            let c = *self.commands.get(self.next_command)?;
            let angle = &mut self.angle;
            let Some((a, angle_a)) = angle.last else {
                angle.origin_t = c.t;
                angle.next_index = 0;
                angle.last = Some((c, 0.0));
                self.next_command += 1;
                continue;
            };
            let mut angle_c = angle_a;
            if c.t > a.t {
                let t = angle.origin_t + angle.next_index as f64 * angle.period_s;
                if t < c.t {
                    angle.next_index += 1;
                    if t >= a.t {
                        let (rpm, rpm_s) = angle.run(&a, &c, t - a.t);
                        return Some(ScrewSample {
                            t,
                            angle_rad: angle_a + rpm_s * RAD_PER_S_PER_RPM,
                            velocity_rad_per_s: rpm * RAD_PER_S_PER_RPM,
                        });
                    }
                    continue;
                }
                angle_c += angle.run(&a, &c, c.t - a.t).1 * RAD_PER_S_PER_RPM;
            }
            angle.last = Some((c, angle_c));
            self.next_command += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::screw::{integral, integral_held};

    fn command(t: f64, rpm: f64) -> Command {
        Command {
            t,
            rpm,
            pin_open: rpm > 0.0,
            source_line: 0,
            sequence: 0,
        }
    }

    /// One truth for the screw's speed: the URDF's joint limit is the default `max_rpm`.
    #[test]
    fn default_max_rpm_is_the_urdf_screw_limit() {
        let robot = urdf_rs::read_from_string(polar_planner::urdf::POLAR_CELL_URDF).unwrap();
        let screw = robot.joints.iter().find(|j| j.name == "screw").unwrap();
        let max_rpm = crate::screw::ScrewOptions::default().max_rpm;
        assert!((screw.limit.velocity / RAD_PER_S_PER_RPM - max_rpm).abs() < 1e-9);
    }

    #[test]
    fn a_ramp_turns_the_screw_by_the_closed_form() {
        // rpm = 60·t: t revolutions per second, so the angle is π·t².
        let mut angle = ScrewAngle::new(0.1, Hold::FirstOrder);
        let mut out = Vec::new();
        angle.extend(&[command(0.0, 0.0), command(1.0, 60.0)], &mut out);
        assert_eq!(out.len(), 10);
        for (k, s) in out.iter().enumerate() {
            let t = k as f64 * 0.1;
            assert!((s.t - t).abs() < 1e-12);
            assert!((s.angle_rad - PI * t * t).abs() < 1e-12, "{s:?}");
            assert!((s.velocity_rad_per_s - 2.0 * PI * t).abs() < 1e-12, "{s:?}");
        }
        assert!((angle.angle_rad() - PI).abs() < 1e-12);
    }

    #[test]
    fn held_commands_turn_at_their_own_rpm_until_the_next() {
        let mut angle = ScrewAngle::new(0.25, Hold::ZeroOrder);
        let mut out = Vec::new();
        angle.extend(
            &[command(0.0, 30.0), command(0.5, 90.0), command(1.0, 0.0)],
            &mut out,
        );
        let at: Vec<(f64, f64)> = out.iter().map(|s| (s.t, s.angle_rad)).collect();
        // 30 rpm = π rad/s, then 90 rpm = 3π rad/s.
        let expected = [
            (0.0, 0.0),
            (0.25, 0.25 * PI),
            (0.5, 0.5 * PI),
            (0.75, 1.25 * PI),
        ];
        for ((t, a), (te, ae)) in at.iter().zip(expected) {
            assert!((t - te).abs() < 1e-12 && (a - ae).abs() < 1e-12, "{at:?}");
        }
        assert_eq!(out[2].velocity_rad_per_s, 3.0 * PI);
    }

    /// Chunking changes nothing, and the total angle is what the feed integrals say.
    #[test]
    fn chunks_continue_and_the_angle_matches_the_feed_integral() {
        let commands: Vec<Command> = (0..400)
            .map(|k| {
                let t = k as f64 * 0.0173 + if k > 200 { 0.05 } else { 0.0 };
                command(t, 120.0 * (0.37 * k as f64).sin().abs())
            })
            .collect();
        let end = commands.last().unwrap().t;
        for (hold, fed) in [
            (Hold::FirstOrder, integral(&commands, 0.0, end)),
            (Hold::ZeroOrder, integral_held(&commands, 0.0, end)),
        ] {
            let mut whole = ScrewAngle::new(0.02, hold);
            let mut all = Vec::new();
            whole.extend(&commands, &mut all);
            let mut chunked = ScrewAngle::new(0.02, hold);
            let mut parts = Vec::new();
            for chunk in commands.chunks(37) {
                chunked.extend(chunk, &mut parts);
            }
            assert_eq!(all, parts, "{hold:?}");
            assert!((whole.angle_rad() - fed * RAD_PER_S_PER_RPM).abs() < 1e-9);
            assert_eq!(all.len(), (end / 0.02).ceil() as usize);
            // samples agree with the integral up to their time
            for s in all.iter().step_by(17) {
                let fed_until = match hold {
                    Hold::FirstOrder => integral(&commands, 0.0, s.t),
                    Hold::ZeroOrder => integral_held(&commands, 0.0, s.t),
                };
                assert!((s.angle_rad - fed_until * RAD_PER_S_PER_RPM).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn commands_at_one_instant_step_the_rpm_without_turning() {
        let mut angle = ScrewAngle::new(0.5, Hold::FirstOrder);
        let mut out = Vec::new();
        angle.extend(
            &[command(0.0, 0.0), command(0.0, 60.0), command(1.0, 60.0)],
            &mut out,
        );
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].angle_rad, 0.0);
        assert_eq!(out[0].velocity_rad_per_s, 2.0 * PI);
        assert!((out[1].angle_rad - PI).abs() < 1e-12);
    }
}
