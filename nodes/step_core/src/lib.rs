//! The step arithmetic of the polar cell: one implementation for the host and the
//! microcontroller.
//!
//! A planned segment (`polar_cell_msgs/StepSegment`) describes the pulses of up to three
//! steppers compactly: the dominant axis (most steps) is timed by the corrected Leib ramp
//!
//! ```text
//! p[i+1] = p[i] · (1 + x + 1.5·x²),   x = m·p[i]²,   m = −r accelerating, 0 cruising, +r decelerating
//! ```
//!
//! and every other axis follows by the pulse distribution of seed 001: after dominant step `n`
//! of `N`, axis `k` (of `T_k` steps) has made `⌊T_k·n/N⌋` steps.
//!
//! The planner, the executor and the firmware all regenerate pulses from that description, so
//! they must agree to the tick. This crate is the one place the arithmetic lives: `no_std`, no
//! allocation, and while stepping only integer additions, multiplications and shifts — an
//! RP2040 (Cortex-M0+) has neither an FPU nor a divider the step path could use.
//!
//! # Fixed point
//!
//! * Times and periods are ticks in Q32 (`u64`, 32 fraction bits): a whole segment may last up
//!   to 2³¹ ticks (35 min at 1 MHz), a period up to 2³⁰ ticks.
//! * The ramp is not iterated through `m·p²` (which would need `m` over twelve decades), but
//!   through `y = r·p²` itself, dimensionless, in Q62: since `p` changes by the factor `g`,
//!   `y` changes by `g²`. Then `x = −y, 0, +y` by phase, and `g = 1 + x + 1.5·x²` is exact in
//!   Q62 for the `|x| ≤ ½` the recurrence is meant for.
//!
//! Rounding each period to 2⁻³² tick keeps a 10,000-step ramp within a few thousandths of a
//! tick of the same recurrence in `f64` (see the tests); the host converts a segment from its
//! floating-point fields once ([`Segment::from_fields`]), rounding the first period and ramp
//! term to [`SIGNIFICANT_BITS`] so that each fits one word on the wire, and the
//! microcontroller receives the converted integers.

#![no_std]
#![forbid(unsafe_code)]

/// Axes a segment can drive (bed θ, arm r, z).
pub const MAX_AXES: usize = 3;

/// Fraction bits of tick quantities.
pub const TICK_FRACTION_BITS: u32 = 32;
/// One timer tick in Q32.
pub const ONE_TICK_Q32: u64 = 1 << TICK_FRACTION_BITS;
/// Fraction bits of the dimensionless ramp term and growth factor.
const RAMP_FRACTION_BITS: u32 = 62;
const ONE_Q62: u64 = 1 << RAMP_FRACTION_BITS;
/// The recurrence is a Taylor expansion in `x`; beyond `|x| = ½` it means nothing.
const MAX_RAMP_Q62: u64 = ONE_Q62 / 2;
/// Longest period (2³⁰ ticks) and longest segment (2³¹ ticks), in Q32.
const MAX_PERIOD_Q32: u64 = 1 << (30 + TICK_FRACTION_BITS);
const MAX_ELAPSED_Q32: u64 = 1 << (31 + TICK_FRACTION_BITS);

/// Step resolution and timer of the cell: shared by the planner (which makes segments), the
/// executor and the firmware (which play them).
#[derive(Clone, Debug, PartialEq)]
pub struct StepOptions {
    /// Steps per rad of `bed_theta`, per m of `arm_r`, per m of `z`.
    pub steps_per_unit: [f64; MAX_AXES],
    /// Step timer frequency (Hz).
    pub timer_hz: f64,
}

impl Default for StepOptions {
    fn default() -> Self {
        StepOptions {
            // 200-step motor, 16 microsteps, 10:1 bed reduction; 80 steps/mm arm; 400 steps/mm z.
            steps_per_unit: [
                200.0 * 16.0 * 10.0 / core::f64::consts::TAU,
                80_000.0,
                400_000.0,
            ],
            timer_hz: 1e6,
        }
    }
}

/// A segment's step description as the host has it, in floating point (the fields of
/// `StepSegment` that the pulses depend on).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SegmentFields {
    pub step_counts: [u32; MAX_AXES],
    /// +1 or −1 per axis.
    pub directions: [i8; MAX_AXES],
    pub dominant_axis: u8,
    pub first_period_ticks: f64,
    pub ramp_r: f64,
    pub cruise_period_ticks: f64,
    pub accelerate_steps: u32,
    pub cruise_steps: u32,
    pub decelerate_steps: u32,
}

/// Why a segment cannot be stepped. Every variant carries the offending values.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum SegmentError {
    #[error("{field} has {len} entries: a segment drives exactly {MAX_AXES} axes")]
    AxisCount { field: &'static str, len: usize },
    #[error("{field} is {value}, not a finite number ≥ 0")]
    BadNumber { field: &'static str, value: f64 },
    #[error("direction {value} on axis {axis}: must be +1 or -1")]
    BadDirection { axis: usize, value: i8 },
    #[error("dominant axis {dominant} does not exist (at most {MAX_AXES} axes)")]
    DominantOutOfRange { dominant: u8 },
    #[error("the ramp phases make {phases} dominant steps but the dominant axis has {count}")]
    PhaseMismatch { phases: u64, count: u32 },
    #[error("axis {axis} has {count} steps, more than the dominant axis's {dominant_count}")]
    FollowerExceedsDominant {
        axis: usize,
        count: u32,
        dominant_count: u32,
    },
    #[error("first period of {ticks} ticks is outside 1..=2^30 ticks")]
    PeriodOutOfRange { ticks: f64 },
    #[error("ramp term r·p² = {x} at the first step: the recurrence holds only up to 0.5")]
    RampTooSteep { x: f64 },
}

/// Why stepping stopped inside a segment (a converted segment whose ramp leaves the fixed-point
/// range — never one the planner makes). The caller must treat it as a fault.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum StepFault {
    #[error("decelerating ramp diverged at dominant step {step} (r·p² beyond 0.5)")]
    RampDiverged { step: u32 },
    #[error("period beyond 2^30 ticks at dominant step {step}")]
    PeriodOverflow { step: u32 },
    #[error("segment longer than 2^31 ticks at dominant step {step}")]
    SegmentTooLong { step: u32 },
}

/// A segment in the fixed-point form the step generator runs on (and the wire protocol
/// carries).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Segment {
    pub step_counts: [u32; MAX_AXES],
    /// Bit `k` set: axis `k` steps in the negative direction.
    pub negative_mask: u8,
    pub dominant_axis: u8,
    pub accelerate_steps: u32,
    pub cruise_steps: u32,
    pub decelerate_steps: u32,
    /// Period before the first dominant step, ticks in Q32.
    pub first_period_q32: u64,
    /// `r·p²` at the first step, dimensionless Q62 (0 for a pure cruise).
    pub first_ramp_q62: u64,
}

fn to_fixed(value: f64, fraction_bits: u32) -> u64 {
    // `as` saturates; callers have checked the range. Round half up (value ≥ 0).
    (value * (1u64 << fraction_bits) as f64 + 0.5) as u64
}

/// Significant bits kept of a segment's first period and ramp term: the wire protocol carries
/// each in one 32-bit word (26 bits of mantissa, 6 of exponent), so the host rounds to that
/// before anyone steps the segment, and the planner, the executor and the firmware all play
/// the same numbers. The relative rounding (≤ 2⁻²⁷) moves a 10,000-step ramp by hundredths
/// of a tick at most (see the tests).
pub const SIGNIFICANT_BITS: u32 = 26;

/// `value` rounded (half up) to [`SIGNIFICANT_BITS`] significant bits.
pub fn round_significant(value: u64) -> u64 {
    let bits = u64::BITS - value.leading_zeros();
    if bits <= SIGNIFICANT_BITS {
        return value;
    }
    let shift = bits - SIGNIFICANT_BITS;
    let mantissa = (value >> shift) + (value >> (shift - 1) & 1);
    // A carry out of the mantissa (all ones rounded up) is still exact: 2^26 << shift.
    ((mantissa as u128) << shift).min(u64::MAX as u128) as u64
}

fn non_negative(field: &'static str, value: f64) -> Result<f64, SegmentError> {
    if value.is_finite() && value >= 0.0 {
        Ok(value)
    } else {
        Err(SegmentError::BadNumber { field, value })
    }
}

impl Segment {
    /// Convert and validate the host's description. Uses floating point (host side only).
    pub fn from_fields(fields: &SegmentFields) -> Result<Segment, SegmentError> {
        let mut negative_mask = 0;
        for (axis, &value) in fields.directions.iter().enumerate() {
            match value {
                1 => {}
                -1 => negative_mask |= 1 << axis,
                _ => return Err(SegmentError::BadDirection { axis, value }),
            }
        }
        let first = non_negative("first_period_ticks", fields.first_period_ticks)?;
        let cruise = non_negative("cruise_period_ticks", fields.cruise_period_ticks)?;
        let r = non_negative("ramp_r", fields.ramp_r)?;
        let mut segment = Segment {
            step_counts: fields.step_counts,
            negative_mask,
            dominant_axis: fields.dominant_axis,
            accelerate_steps: fields.accelerate_steps,
            cruise_steps: fields.cruise_steps,
            decelerate_steps: fields.decelerate_steps,
            first_period_q32: 0,
            first_ramp_q62: 0,
        };
        segment.check_counts()?;
        let count = segment.dominant_steps();
        if count == 0 {
            return Ok(segment); // a pause: no pulses, nothing to time
        }
        // The timing is checked here on the host's values (exact in the messages), not after
        // conversion.
        let period = if fields.cruise_steps == count {
            cruise
        } else {
            first
        };
        if !(1.0..=(1u64 << 30) as f64).contains(&period) {
            return Err(SegmentError::PeriodOutOfRange { ticks: period });
        }
        let x = r * period * period;
        if x > 0.5 {
            return Err(SegmentError::RampTooSteep { x });
        }
        segment.first_period_q32 = round_significant(to_fixed(period, TICK_FRACTION_BITS));
        segment.first_ramp_q62 = round_significant(to_fixed(x, RAMP_FRACTION_BITS));
        Ok(segment)
    }

    /// Validate a segment received in fixed-point form (e.g. by the microcontroller): the same
    /// rules as [`Segment::from_fields`].
    pub fn check(&self) -> Result<(), SegmentError> {
        self.check_counts()?;
        if self.dominant_steps() > 0 {
            if !(ONE_TICK_Q32..=MAX_PERIOD_Q32).contains(&self.first_period_q32) {
                return Err(SegmentError::PeriodOutOfRange {
                    ticks: self.first_period_q32 as f64 / ONE_TICK_Q32 as f64,
                });
            }
            if self.first_ramp_q62 > MAX_RAMP_Q62 {
                return Err(SegmentError::RampTooSteep {
                    x: self.first_ramp_q62 as f64 / ONE_Q62 as f64,
                });
            }
        }
        Ok(())
    }

    /// The step counts and ramp phases agree: a dominant axis that exists, phases that add up
    /// to its count, no follower with more steps.
    fn check_counts(&self) -> Result<(), SegmentError> {
        let dominant = self.dominant_axis as usize;
        if dominant >= MAX_AXES {
            return Err(SegmentError::DominantOutOfRange {
                dominant: self.dominant_axis,
            });
        }
        let count = self.step_counts[dominant];
        let phases =
            self.accelerate_steps as u64 + self.cruise_steps as u64 + self.decelerate_steps as u64;
        if phases != count as u64 {
            return Err(SegmentError::PhaseMismatch { phases, count });
        }
        if let Some((axis, &c)) = self
            .step_counts
            .iter()
            .enumerate()
            .find(|(_, &c)| c > count)
        {
            return Err(SegmentError::FollowerExceedsDominant {
                axis,
                count: c,
                dominant_count: count,
            });
        }
        Ok(())
    }

    /// Dominant steps of the segment.
    pub fn dominant_steps(&self) -> u32 {
        self.step_counts[self.dominant_axis as usize]
    }

    /// Step direction of `axis`: +1 or −1.
    pub fn direction(&self, axis: usize) -> i8 {
        if self.negative_mask & (1 << axis) != 0 {
            -1
        } else {
            1
        }
    }
}

/// Pulses at one instant: the dominant axis and the followers that step with it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pulse {
    /// Time from the segment's start, ticks in Q32.
    pub time_q32: u64,
    /// Bit `k` set: axis `k` steps now.
    pub axes: u8,
}

impl Pulse {
    /// The timer tick (from the segment's start) at which to emit it: the nearest one.
    pub fn tick(&self) -> u64 {
        (self.time_q32 + ONE_TICK_Q32 / 2) >> TICK_FRACTION_BITS
    }
}

/// `a·b` in full. A Cortex-M0+ multiplies 32×32 bits to the low 32 only, so a 64-bit
/// product there is four 16×16-bit multiplications; the compiler's own (`__aeabi_lmul`, a
/// call that multiplies 64×64 bits) costs several times that on the step path.
#[cfg(all(target_arch = "arm", not(target_feature = "v7")))]
#[inline(always)]
fn mul_wide_u32(a: u32, b: u32) -> u64 {
    mul_wide_u32_by_halves(a, b)
}

#[cfg(not(all(target_arch = "arm", not(target_feature = "v7"))))]
#[inline(always)]
fn mul_wide_u32(a: u32, b: u32) -> u64 {
    a as u64 * b as u64
}

/// `a·b` from 16-bit halves: what a core without a widening multiply does (exact; tested
/// against the native product on the host).
#[cfg_attr(
    not(all(target_arch = "arm", not(target_feature = "v7"))),
    allow(dead_code)
)]
#[inline(always)]
fn mul_wide_u32_by_halves(a: u32, b: u32) -> u64 {
    let (a_lo, a_hi) = (a & 0xFFFF, a >> 16);
    let (b_lo, b_hi) = (b & 0xFFFF, b >> 16);
    let middle = (a_lo * b_hi) as u64 + (a_hi * b_lo) as u64;
    (((a_hi * b_hi) as u64) << 32) + (middle << 16) + (a_lo * b_lo) as u64
}

/// Multiply two unsigned fixed-point numbers, the second in Q62, rounding to nearest:
/// `⌊(a·b + 2⁶¹) / 2⁶²⌋`, exact, from four 32×32-bit products (no 128-bit arithmetic, which
/// an M0+ does through several library calls). The result must fit 64 bits, as every use
/// here does (`a·b < 2¹²⁶`).
fn mul_q62(a: u64, b_q62: u64) -> u64 {
    let (a_lo, a_hi) = (a as u32, (a >> 32) as u32);
    let (b_lo, b_hi) = (b_q62 as u32, (b_q62 >> 32) as u32);
    let (middle, middle_carry) = mul_wide_u32(a_lo, b_hi).overflowing_add(mul_wide_u32(a_hi, b_lo));
    // The product as high·2⁶⁴ + low.
    let (low, carry) = mul_wide_u32(a_lo, b_lo).overflowing_add(middle << 32);
    let high =
        mul_wide_u32(a_hi, b_hi) + (middle >> 32) + ((middle_carry as u64) << 32) + carry as u64;
    let (low, carry) = low.overflowing_add(1 << (RAMP_FRACTION_BITS - 1));
    let high = high + carry as u64;
    (high << (64 - RAMP_FRACTION_BITS)) | (low >> RAMP_FRACTION_BITS)
}

/// The pulse train of one segment, one dominant step at a time.
#[derive(Clone, Debug)]
pub struct PulseTrain {
    segment: Segment,
    /// Dominant steps made.
    step: u32,
    period_q32: u64,
    /// `r·p²` for the current period, Q62.
    ramp_q62: u64,
    elapsed_q32: u64,
    made: [u32; MAX_AXES],
    /// Per follower, `T_k·i − N·made_k` (0 ≤ it < N): the pulse distribution as a DDA, so a
    /// step costs additions, not the 64-bit multiplications an M0+ does in software.
    share: [u64; MAX_AXES],
}

impl PulseTrain {
    pub fn new(segment: &Segment) -> PulseTrain {
        PulseTrain {
            segment: *segment,
            step: 0,
            period_q32: segment.first_period_q32,
            ramp_q62: segment.first_ramp_q62,
            elapsed_q32: 0,
            made: [0; MAX_AXES],
            share: [0; MAX_AXES],
        }
    }

    pub fn segment(&self) -> &Segment {
        &self.segment
    }

    /// Steps made so far per axis (unsigned; see [`Segment::direction`]).
    pub fn made(&self) -> [u32; MAX_AXES] {
        self.made
    }

    /// Period before the next dominant step (Q32 ticks): the current step rate's inverse.
    pub fn period_q32(&self) -> u64 {
        self.period_q32
    }

    /// `r·p²` for the current period (Q62): with [`PulseTrain::period_q32`] it gives the
    /// dominant acceleration `r` (steps per tick²) to a host.
    pub fn ramp_q62(&self) -> u64 {
        self.ramp_q62
    }

    /// The ramp phase the current period belongs to: +1 speeding up, 0 cruising, −1 slowing.
    pub fn phase(&self) -> i8 {
        let seg = &self.segment;
        if self.step < seg.accelerate_steps {
            1
        } else if self.step < seg.accelerate_steps.saturating_add(seg.cruise_steps) {
            0
        } else {
            -1
        }
    }

    /// Whether every pulse has been produced.
    pub fn is_done(&self) -> bool {
        self.step >= self.segment.dominant_steps()
    }

    /// Time of the next pulse from the segment start (Q32 ticks), without producing it.
    pub fn next_time_q32(&self) -> Option<u64> {
        (!self.is_done()).then(|| self.elapsed_q32.saturating_add(self.period_q32))
    }

    /// The next pulse, `None` after the last one.
    pub fn next_pulse(&mut self) -> Result<Option<Pulse>, StepFault> {
        let seg = &self.segment;
        let total = seg.dominant_steps();
        if self.step >= total {
            return Ok(None);
        }
        let i = self.step + 1;
        self.elapsed_q32 = match self.elapsed_q32.checked_add(self.period_q32) {
            Some(t) if t <= MAX_ELAPSED_Q32 => t,
            _ => return Err(StepFault::SegmentTooLong { step: i }),
        };
        self.step = i;
        let dominant = seg.dominant_axis as usize;
        let mut axes = 1u8 << dominant;
        self.made[dominant] = i;
        for k in 0..MAX_AXES {
            // Axis k steps when T_k·i ≥ N·(made_k + 1): its count reaches ⌊T_k·i/N⌋. With
            // `share = T_k·i − N·made_k` carried from step to step (T_k ≤ N, so at most one
            // follower step per dominant step), that is `share + T_k ≥ N`.
            if k != dominant {
                self.share[k] += seg.step_counts[k] as u64;
                if self.share[k] >= total as u64 {
                    self.share[k] -= total as u64;
                    self.made[k] += 1;
                    axes |= 1 << k;
                }
            }
        }
        let pulse = Pulse {
            time_q32: self.elapsed_q32,
            axes,
        };
        // The period before step i + 1.
        let accelerating = i < seg.accelerate_steps;
        let cruising = !accelerating && i < seg.accelerate_steps.saturating_add(seg.cruise_steps);
        if !cruising && i < total {
            let y = self.ramp_q62;
            if y > MAX_RAMP_Q62 {
                return Err(StepFault::RampDiverged { step: i });
            }
            // g = 1 ± y + 1.5·y²  (y ≤ ½ ⇒ 0.83 < g ≤ 1.875 < 2: fits Q62 in u64).
            let y2 = mul_q62(y, y);
            let quadratic = y2 + (y2 >> 1);
            let g = if accelerating {
                ONE_Q62 - y + quadratic
            } else {
                ONE_Q62 + y + quadratic
            };
            let period = mul_q62(self.period_q32, g);
            if period > MAX_PERIOD_Q32 {
                return Err(StepFault::PeriodOverflow { step: i });
            }
            self.period_q32 = period;
            // y·g² < ½·4 = 2: fits.
            self.ramp_q62 = mul_q62(mul_q62(y, g), g);
        }
        Ok(Some(pulse))
    }
}

#[cfg(test)]
mod tests;
