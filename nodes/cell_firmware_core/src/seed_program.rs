//! Seed 001's bench program, run by the MCU itself when its start switch is pressed.
//!
//! Seed 001 drove three 28BYJ-48 steppers from a Pico W: pressing the switch on GP15 made six
//! three-axis linear moves between absolute step positions, each at a constant step rate of
//! its dominant axis (the axis with the most steps; the others follow by the pulse
//! distribution `⌊T_k·n/N⌋`), and sent the position as `X:<x>,Y:<y>,Z:<z>` lines over USB
//! serial to a PC plotter. That program is [`SEED_001_MOVES`]; [`constant_rate_move`] turns
//! one move into a [`step_core`] segment with integer arithmetic only (a cruise at the move's
//! period, no ramp: the seed's rates are below the motor's 500 steps/s self-start rate), so the
//! firmware plays it through the same queue, step core and outputs as a host's print, and
//! [`position_line`] writes the seed's lines.
//!
//! Timing: the seed steps, then waits one period; a segment waits one period, then steps. Each
//! move therefore plays the seed's pulses one period later, with the same spacing and the
//! same positions after every step.

use core::fmt::Write;

use cell_protocol::message::{QueuedSegment, SEGMENT_ENDS_AT_REST};
use step_core::{Segment, MAX_AXES, ONE_TICK_Q32};

/// The seed's moves: absolute target positions (steps of X, Y, Z) and the dominant axis's
/// rate (steps per second), in the order its `loop()` makes them. The prose says 400 steps/s
/// throughout; its code returns home at 250.
pub const SEED_001_MOVES: [([i32; 3], u32); 6] = [
    ([1000, 1000, 0], 400),
    ([500, 500, 2000], 400),
    ([0, 0, 1000], 400),
    ([-2000, 800, 1500], 400),
    ([-1000, -1000, -400], 400),
    ([0, 0, 0], 250),
];

/// A straight move from `from` to `to` with the dominant axis stepping every `period_ticks`:
/// the segment and its duration in ticks. The dominant axis is the first with the most steps
/// (the seed's choice: X, then Y, then Z on a tie). `None` when nothing moves or the move
/// is too long for one segment.
pub fn constant_rate_move(
    from: [i32; MAX_AXES],
    to: [i32; MAX_AXES],
    period_ticks: u32,
) -> Option<(Segment, u32)> {
    let mut step_counts = [0u32; MAX_AXES];
    let mut negative_mask = 0u8;
    for k in 0..MAX_AXES {
        let delta = to[k] as i64 - from[k] as i64;
        step_counts[k] = u32::try_from(delta.unsigned_abs()).ok()?;
        if delta < 0 {
            negative_mask |= 1 << k;
        }
    }
    let most = *step_counts.iter().max()?;
    let dominant_axis = step_counts.iter().position(|&c| c == most)? as u8;
    if most == 0 || period_ticks == 0 {
        return None;
    }
    let duration_ticks = most.checked_mul(period_ticks)?;
    let segment = Segment {
        step_counts,
        negative_mask,
        dominant_axis,
        accelerate_steps: 0,
        cruise_steps: most,
        decelerate_steps: 0,
        first_period_q32: period_ticks as u64 * ONE_TICK_Q32,
        first_ramp_q62: 0,
    };
    segment.check().ok()?;
    Some((segment, duration_ticks))
}

/// The seed's program from `position` onwards as queued segments, the first starting at
/// `start_clock` and each following on at the end of the one before; tagged 1–6 by move
/// (moves that would not step are left out). Every move ends at rest: the motors stop between
/// moves in the seed too, below their self-start rate.
pub fn seed_001_program(
    position: [i32; MAX_AXES],
    start_clock: u64,
    timer_hz: u32,
) -> heapless::Vec<QueuedSegment, 6> {
    let mut program = heapless::Vec::new();
    let mut at = position;
    let mut clock = start_clock;
    for (tag, &(target, rate)) in (1u32..).zip(SEED_001_MOVES.iter()) {
        let Some((segment, duration_ticks)) = constant_rate_move(at, target, timer_hz / rate)
        else {
            continue;
        };
        let queued = QueuedSegment {
            start_clock: clock,
            duration_ticks,
            tag,
            flags: SEGMENT_ENDS_AT_REST,
            segment,
        };
        // Six places for six moves: never full.
        let _ = program.push(queued);
        clock += duration_ticks as u64;
        at = target;
    }
    program
}

/// The seed's position line, `X:<x>,Y:<y>,Z:<z>` and CR LF (Arduino's `Serial.println`).
pub fn position_line(position: [i32; MAX_AXES]) -> heapless::String<48> {
    let mut line = heapless::String::new();
    // 3 × (2 + 11) + 2 + 2 = 43 bytes at most: always fits.
    let _ = write!(
        line,
        "X:{},Y:{},Z:{}\r\n",
        position[0], position[1], position[2]
    );
    line
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;
    use step_core::PulseTrain;

    /// Seed 001's `linearInterporation3`, transcribed from the seed's C++: the dominant axis
    /// steps, then each other axis steps `(all·cur_dominant/all_dominant) − cur` times, the
    /// position is printed, then the loop sleeps one period. Returns every position after a
    /// step with its time from the move's start (µs) and the move's length.
    fn seed_move(from: [i64; 3], to: [i64; 3], vel: i64) -> (Vec<(i64, [i64; 3])>, i64) {
        let inc: Vec<i64> = (0..3).map(|k| to[k] - from[k]).collect();
        let all: Vec<i64> = inc.iter().map(|d| d.abs()).collect();
        let basic = if all[0] >= all[1] && all[0] >= all[2] {
            0
        } else if all[1] >= all[0] && all[1] >= all[2] {
            1
        } else {
            2
        };
        let sleep = 1_000_000 / vel;
        let mut cur = [0i64; 3];
        let mut pos = from;
        let mut t = 0;
        let mut out = Vec::new();
        loop {
            if inc[basic] != 0 {
                cur[basic] += 1;
                pos[basic] += inc[basic].signum();
            }
            for k in (0..3).filter(|&k| k != basic) {
                let pulse = all[k] * cur[basic] / all[basic] - cur[k];
                for _ in 0..pulse.max(0) {
                    cur[k] += 1;
                    pos[k] += inc[k].signum();
                }
            }
            out.push((t, pos));
            t += sleep;
            if (0..3).all(|k| cur[k] >= all[k]) {
                break;
            }
        }
        (out, t)
    }

    #[test]
    fn every_move_steps_as_the_seeds_loop_one_period_later() {
        let mut at = [0i32; 3];
        for &(target, rate) in &SEED_001_MOVES {
            let period = 1_000_000 / rate;
            let (segment, duration) = constant_rate_move(at, target, period).unwrap();
            let (seed, seed_length) =
                seed_move(at.map(i64::from), target.map(i64::from), rate as i64);
            assert_eq!(duration as i64, seed_length, "move to {target:?}");
            let mut train = PulseTrain::new(&segment);
            let mut pos = at.map(i64::from);
            let mut ours = Vec::new();
            while let Some(pulse) = train.next_pulse().unwrap() {
                for (k, position) in pos.iter_mut().enumerate() {
                    if pulse.axes & (1 << k) != 0 {
                        *position += segment.direction(k) as i64;
                    }
                }
                ours.push((pulse.tick() as i64 - period as i64, pos));
            }
            assert_eq!(ours, seed, "move to {target:?}");
            assert_eq!(pos, target.map(i64::from));
            at = target;
        }
    }

    #[test]
    fn the_program_is_six_moves_back_to_back_ending_home() {
        let program = seed_001_program([0; 3], 10_000, 1_000_000);
        assert_eq!(program.len(), 6);
        // 1000, 2000, 1000, 2000, 1900 steps at 2.5 ms, then 1000 at 4 ms.
        let durations: Vec<u32> = program.iter().map(|q| q.duration_ticks).collect();
        assert_eq!(
            durations,
            [2_500_000, 5_000_000, 2_500_000, 5_000_000, 4_750_000, 4_000_000]
        );
        for pair in program.windows(2) {
            assert_eq!(
                pair[1].start_clock,
                pair[0].start_clock + pair[0].duration_ticks as u64
            );
        }
        assert_eq!(program[0].start_clock, 10_000);
        assert!(program.iter().all(|q| q.flags == SEGMENT_ENDS_AT_REST));
        assert_eq!(
            program.iter().map(|q| q.tag).collect::<Vec<_>>(),
            [1, 2, 3, 4, 5, 6]
        );
    }

    #[test]
    fn a_program_from_elsewhere_goes_to_the_same_targets_and_skips_a_null_move() {
        // Already at the first target: that move has no steps and is left out.
        let program = seed_001_program([1000, 1000, 0], 0, 1_000_000);
        assert_eq!(program.len(), 5);
        assert_eq!(program[0].tag, 2);
        assert_eq!(program[0].segment.step_counts, [500, 500, 2000]);
        assert_eq!(program[0].segment.negative_mask, 0b011);
        assert_eq!(program[0].segment.dominant_axis, 2);
    }

    #[test]
    fn moves_that_cannot_be_one_segment_are_refused() {
        assert!(constant_rate_move([0; 3], [0; 3], 2500).is_none());
        assert!(constant_rate_move([0; 3], [5, 0, 0], 0).is_none());
        // 2³¹ steps at 2,500 ticks overflow the duration.
        assert!(constant_rate_move([i32::MIN, 0, 0], [i32::MAX, 0, 0], 2500).is_none());
        // Ties go to X, then Y, as in the seed.
        let (tie, _) = constant_rate_move([0; 3], [0, -7, 7], 100).unwrap();
        assert_eq!(tie.dominant_axis, 1);
    }

    #[test]
    fn position_lines_are_the_seeds() {
        assert_eq!(position_line([45, 22, 100]).as_str(), "X:45,Y:22,Z:100\r\n");
        assert_eq!(
            position_line([i32::MIN, -1, i32::MAX]).as_str(),
            "X:-2147483648,Y:-1,Z:2147483647\r\n"
        );
    }
}
