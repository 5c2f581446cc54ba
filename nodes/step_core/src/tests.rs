extern crate std;

use std::vec::Vec;

use proptest::prelude::*;

use super::*;

/// The recurrence as the message documents it, in `f64`, computing `m·p²` from `p` every step:
/// an independent formulation of what the fixed-point train iterates through `y`.
fn reference_times(f: &SegmentFields) -> Vec<f64> {
    let n = f.accelerate_steps + f.cruise_steps + f.decelerate_steps;
    let mut p = if f.cruise_steps == n {
        f.cruise_period_ticks
    } else {
        f.first_period_ticks
    };
    let mut t = 0.0;
    let mut out = Vec::new();
    for i in 1..=n {
        t += p;
        out.push(t);
        let m = if i < f.accelerate_steps {
            -f.ramp_r
        } else if i < f.accelerate_steps + f.cruise_steps {
            0.0
        } else {
            f.ramp_r
        };
        let mp2 = m * p * p;
        p *= 1.0 + mp2 + 1.5 * mp2 * mp2;
    }
    out
}

/// `f` with the first period and ramp as the segment steps them, after the rounding to
/// [`SIGNIFICANT_BITS`]: the reference for the arithmetic itself.
fn as_stepped(f: &SegmentFields) -> SegmentFields {
    let segment = Segment::from_fields(f).unwrap();
    let period = seconds_q32(segment.first_period_q32);
    let ramp = segment.first_ramp_q62 as f64 / (1u64 << 62) as f64;
    let n = f.accelerate_steps + f.cruise_steps + f.decelerate_steps;
    let mut stepped = *f;
    if n > 0 && f.cruise_steps == n {
        stepped.cruise_period_ticks = period;
    } else if n > 0 {
        stepped.first_period_ticks = period;
        stepped.ramp_r = ramp / (period * period);
    }
    stepped
}

fn run(segment: &Segment) -> Vec<Pulse> {
    let mut train = PulseTrain::new(segment);
    let mut out = Vec::new();
    while let Some(p) = train.next_pulse().expect("no fault") {
        out.push(p);
    }
    assert!(train.is_done());
    assert_eq!(train.next_pulse(), Ok(None));
    out
}

fn seconds_q32(t: u64) -> f64 {
    t as f64 / ONE_TICK_Q32 as f64
}

/// A dominant-only ramp from rate `v0` (steps/s) at `a` (steps/s²) over `n` steps, timer `hz`.
fn ramp_fields(v0: f64, a: f64, n: u32, hz: f64) -> SegmentFields {
    let p0 = hz / (v0 * v0 + a.abs()).sqrt(); // the rate half way through the first step
    SegmentFields {
        step_counts: [n, 0, 0],
        directions: [1, 1, 1],
        first_period_ticks: p0,
        ramp_r: a.abs() / (hz * hz),
        accelerate_steps: if a > 0.0 { n } else { 0 },
        decelerate_steps: if a > 0.0 { 0 } else { n },
        ..SegmentFields::default()
    }
}

/// Worst distance of the fixed-point pulses from the `f64` recurrence on the same (rounded)
/// numbers, or with `unrounded`, on the host's own numbers.
fn worst_difference_ticks(fields: &SegmentFields, unrounded: bool) -> f64 {
    let pulses = run(&Segment::from_fields(fields).unwrap());
    let reference = reference_times(&if unrounded {
        *fields
    } else {
        as_stepped(fields)
    });
    assert_eq!(pulses.len(), reference.len());
    pulses
        .iter()
        .zip(&reference)
        .map(|(p, r)| (seconds_q32(p.time_q32) - r).abs())
        .fold(0.0, f64::max)
}

#[test]
fn fixed_point_ramps_follow_the_floating_point_recurrence() {
    // (v0 steps/s, a steps/s², steps): starts from rest, long ramps, decelerations to near
    // rest, a very gentle ramp, the bed's 31k steps/s.
    for (v0, a, n, bound) in [
        (1_000.0, 20_000.0, 2000, 1e-4),
        (5_000.0, 5_000.0, 10_000, 1e-3),
        (31_000.0, -2_000_000.0, 200, 1e-5),
        (2_000.0, -300.0, 5000, 1e-3),
        (400.0, 0.5, 300, 1e-6),
        (5_000.0, 1_000_000.0, 100_000, 0.1),
    ] {
        let fields = ramp_fields(v0, a, n, 1e6);
        let worst = worst_difference_ticks(&fields, false);
        std::eprintln!("v0 {v0} a {a} n {n}: worst {worst:.2e} ticks");
        assert!(worst < bound, "v0 {v0} a {a} n {n}: {worst} ticks");
    }
}

/// What the rounding to the wire's 26 significant bits costs against the host's unrounded
/// numbers: hundredths of a tick over the longest ramps, far inside the whole tick a pulse
/// is output on.
#[test]
fn rounding_to_the_wire_moves_long_ramps_by_hundredths_of_a_tick() {
    for (v0, a, n, bound) in [
        (1_000.0, 20_000.0, 2000, 0.01),
        (5_000.0, 5_000.0, 10_000, 0.05),
        (31_000.0, -2_000_000.0, 200, 1e-3),
        (2_000.0, -300.0, 5000, 0.05),
        (400.0, 0.5, 300, 0.05),
    ] {
        let fields = ramp_fields(v0, a, n, 1e6);
        let worst = worst_difference_ticks(&fields, true);
        std::eprintln!("v0 {v0} a {a} n {n}: rounded {worst:.2e} ticks off the unrounded");
        assert!(worst < bound, "v0 {v0} a {a} n {n}: {worst} ticks");
    }
}

#[test]
fn round_significant_keeps_26_bits_rounding_half_up() {
    assert_eq!(round_significant(0), 0);
    assert_eq!(round_significant((1 << 26) - 1), (1 << 26) - 1);
    // 27 bits: the last one goes, half rounds up.
    assert_eq!(round_significant((1 << 26) + 1), (1 << 26) + 2);
    assert_eq!(round_significant((1 << 26) + 2), (1 << 26) + 2);
    assert_eq!(round_significant((1 << 27) - 1), 1 << 27);
    let v = 0x0123_4567_89AB_CDEFu64;
    let kept = round_significant(v);
    assert!(kept.trailing_zeros() >= 57 - 26);
    assert!(kept.abs_diff(v) <= 1 << (57 - 26 - 1));
    assert_eq!(round_significant(u64::MAX), u64::MAX);
}

#[test]
fn a_three_phase_segment_keeps_the_period_reached_through_its_cruise() {
    let fields = SegmentFields {
        step_counts: [500, 250, 7],
        directions: [1, -1, 1],
        dominant_axis: 0,
        first_period_ticks: 400.0,
        ramp_r: 2e-7,
        cruise_period_ticks: 123.0, // unused: the segment is not all cruise
        accelerate_steps: 200,
        cruise_steps: 150,
        decelerate_steps: 150,
    };
    let pulses = run(&Segment::from_fields(&fields).unwrap());
    let reference = reference_times(&as_stepped(&fields));
    for (p, r) in pulses.iter().zip(&reference) {
        assert!((seconds_q32(p.time_q32) - r).abs() < 1e-6);
    }
    // Through the cruise the spacing is constant, equal to the last accelerating period.
    let gap = |i: usize| pulses[i].time_q32 - pulses[i - 1].time_q32;
    for i in 201..350 {
        assert_eq!(gap(i), gap(200), "step {i}");
    }
    assert!(gap(10) > gap(100) && gap(100) > gap(200) && gap(400) > gap(300));
}

#[test]
fn a_cruise_is_exact() {
    let fields = SegmentFields {
        step_counts: [0, 1000, 0],
        directions: [1, 1, -1],
        dominant_axis: 1,
        cruise_period_ticks: 37.25,
        cruise_steps: 1000,
        ..SegmentFields::default()
    };
    let pulses = run(&Segment::from_fields(&fields).unwrap());
    for (i, p) in pulses.iter().enumerate() {
        assert_eq!(p.time_q32, (i as u64 + 1) * 149 * (ONE_TICK_Q32 / 4));
        assert_eq!(p.axes, 0b010);
    }
    assert_eq!(pulses[3].tick(), 149);
    assert_eq!(pulses[1].tick(), 75); // 74.5 rounds up
}

/// PROTOCOL.md §6's worked example, pulse by pulse: the document a firmware author writes from
/// says exactly what this crate computes.
#[test]
fn protocol_md_worked_example_is_what_the_generator_computes() {
    let segment = Segment {
        step_counts: [3, 2, 0],
        negative_mask: 0,
        dominant_axis: 0,
        accelerate_steps: 3,
        cruise_steps: 0,
        decelerate_steps: 0,
        first_period_q32: 32 << 32,
        first_ramp_q62: 1 << 60,
    };
    segment.check().unwrap();
    let mut train = PulseTrain::new(&segment);
    let first = train.next_pulse().unwrap().unwrap();
    assert_eq!(
        (first.time_q32, first.axes, first.tick()),
        (32 << 32, 0b001, 32)
    );
    assert_eq!(
        (train.period_q32(), train.ramp_q62()),
        (27 << 32, 729 << 50)
    );
    let second = train.next_pulse().unwrap().unwrap();
    assert_eq!(
        (second.time_q32, second.axes, second.tick()),
        (59 << 32, 0b011, 59)
    );
    assert_eq!(
        (train.period_q32(), train.ramp_q62()),
        (100_834_975_872, 620_586_691_840_016_001)
    );
    let third = train.next_pulse().unwrap().unwrap();
    assert_eq!(
        (third.time_q32, third.axes, third.tick()),
        (354_238_046_336, 0b011, 82)
    );
    assert_eq!(train.next_pulse().unwrap(), None);
}

#[test]
fn followers_make_floor_of_their_share_at_every_dominant_step() {
    let fields = SegmentFields {
        step_counts: [357, 1000, 1],
        directions: [-1, 1, 1],
        dominant_axis: 1,
        cruise_period_ticks: 100.0,
        cruise_steps: 1000,
        ..SegmentFields::default()
    };
    let segment = Segment::from_fields(&fields).unwrap();
    assert_eq!(segment.negative_mask, 0b001);
    assert_eq!((segment.direction(0), segment.direction(1)), (-1, 1));
    let mut train = PulseTrain::new(&segment);
    let mut made = [0u32; 3];
    for n in 1..=1000u32 {
        let pulse = train.next_pulse().unwrap().unwrap();
        for (k, m) in made.iter_mut().enumerate() {
            *m += (pulse.axes >> k) as u32 & 1;
        }
        assert_eq!(made[1], n);
        assert_eq!(made[0], 357 * n / 1000, "after dominant step {n}");
        assert_eq!(made[2], n / 1000);
        assert_eq!(train.made(), made);
    }
    assert_eq!(train.next_pulse(), Ok(None));
}

#[test]
fn bad_descriptions_are_refused_with_their_values() {
    let good = ramp_fields(1000.0, 5000.0, 100, 1e6);
    assert!(Segment::from_fields(&good).is_ok());
    let cases: [(SegmentFields, SegmentError); 8] = [
        (
            SegmentFields {
                ramp_r: f64::NAN,
                ..good
            },
            SegmentError::BadNumber {
                field: "ramp_r",
                value: f64::NAN,
            },
        ),
        (
            SegmentFields {
                first_period_ticks: -1.0,
                ..good
            },
            SegmentError::BadNumber {
                field: "first_period_ticks",
                value: -1.0,
            },
        ),
        (
            SegmentFields {
                directions: [1, 0, 1],
                ..good
            },
            SegmentError::BadDirection { axis: 1, value: 0 },
        ),
        (
            SegmentFields {
                dominant_axis: 3,
                ..good
            },
            SegmentError::DominantOutOfRange { dominant: 3 },
        ),
        (
            SegmentFields {
                accelerate_steps: 99,
                ..good
            },
            SegmentError::PhaseMismatch {
                phases: 99,
                count: 100,
            },
        ),
        (
            SegmentFields {
                step_counts: [100, 101, 0],
                ..good
            },
            SegmentError::FollowerExceedsDominant {
                axis: 1,
                count: 101,
                dominant_count: 100,
            },
        ),
        (
            SegmentFields {
                first_period_ticks: 0.5,
                ..good
            },
            SegmentError::PeriodOutOfRange { ticks: 0.5 },
        ),
        (
            SegmentFields {
                ramp_r: 1e-4,
                ..good
            },
            SegmentError::RampTooSteep {
                x: 1e-4 * good.first_period_ticks * good.first_period_ticks,
            },
        ),
    ];
    for (fields, expected) in cases {
        let err = Segment::from_fields(&fields).unwrap_err();
        // NaN ≠ NaN: compare the messages, which carry every value.
        assert_eq!(std::format!("{err}"), std::format!("{expected}"));
    }
    // A pause: no steps, no timing needed.
    let pause = SegmentFields {
        step_counts: [0; 3],
        directions: [1; 3],
        ..SegmentFields::default()
    };
    assert!(run(&Segment::from_fields(&pause).unwrap()).is_empty());
}

#[test]
fn a_diverging_deceleration_faults_instead_of_stepping_on() {
    // Legal at the first step (x = 0.4), but decelerating for 50 steps drives r·p² past ½.
    let fields = SegmentFields {
        step_counts: [50, 0, 0],
        directions: [1; 3],
        first_period_ticks: 1000.0,
        ramp_r: 0.4e-6,
        decelerate_steps: 50,
        ..SegmentFields::default()
    };
    let mut train = PulseTrain::new(&Segment::from_fields(&fields).unwrap());
    let fault = loop {
        match train.next_pulse() {
            Ok(Some(_)) => {}
            Ok(None) => panic!("ran to the end"),
            Err(fault) => break fault,
        }
    };
    assert!(matches!(fault, StepFault::RampDiverged { step } if step > 1 && step < 50));
}

fn fields_strategy() -> impl Strategy<Value = SegmentFields> {
    (
        prop::array::uniform3(0u32..3000),
        prop::array::uniform3(prop_oneof![Just(1i8), Just(-1i8)]),
        0u8..3,
        1.0f64..5e5,
        0.0f64..0.05,
        0u32..3,
        0u32..100,
    )
        .prop_map(
            |(mut counts, directions, dominant, period, x, shape, split)| {
                let d = dominant as usize;
                counts[d] = counts.iter().copied().max().unwrap();
                let n = counts[d];
                let a = n * split / 100;
                let (accelerate_steps, cruise_steps, decelerate_steps) = match shape {
                    0 => (0, n, 0),
                    1 => (n, 0, 0),
                    _ => (a, (n - a) / 2, n - a - (n - a) / 2),
                };
                SegmentFields {
                    step_counts: counts,
                    directions,
                    dominant_axis: dominant,
                    first_period_ticks: period,
                    ramp_r: x / (period * period) / (1.0 + n as f64), // stays well below ½
                    cruise_period_ticks: period,
                    accelerate_steps,
                    cruise_steps,
                    decelerate_steps,
                }
            },
        )
}

proptest! {
    /// The DDA's follower steps are the seed's rule `⌊T_k·n/N⌋` after every dominant step,
    /// for any counts up to 2³² − 1.
    #[test]
    fn followers_follow_the_floor_rule_for_any_counts(
        dominant in 1u32..=u32::MAX,
        shares in proptest::array::uniform2(0.0f64..=1.0),
        samples in proptest::collection::vec(0.0f64..1.0, 1..50),
    ) {
        let counts = [dominant, (shares[0] * dominant as f64) as u32, (shares[1] * dominant as f64) as u32];
        let segment = Segment {
            step_counts: counts,
            negative_mask: 0,
            dominant_axis: 0,
            accelerate_steps: 0,
            cruise_steps: dominant,
            decelerate_steps: 0,
            first_period_q32: ONE_TICK_Q32,
            first_ramp_q62: 0,
        };
        // Walk short segments to the end; long ones only to a few sampled steps' worth.
        let limit = dominant.min(20_000);
        let mut train = PulseTrain::new(&segment);
        for n in 1..=limit {
            train.next_pulse().unwrap().unwrap();
            let floor = |t: u32| (t as u64 * n as u64 / dominant as u64) as u32;
            if n == limit || samples.iter().any(|s| (s * limit as f64) as u32 == n) {
                prop_assert_eq!(train.made(), [n, floor(counts[1]), floor(counts[2])]);
            }
        }
    }

    /// Any valid description steps every axis exactly its count, in time order, and agrees
    /// with the floating-point recurrence.
    #[test]
    fn every_valid_segment_lands_on_its_counts(fields in fields_strategy()) {
        let segment = Segment::from_fields(&fields).unwrap();
        let pulses = run(&segment);
        let mut made = [0u32; 3];
        for p in &pulses {
            for (k, m) in made.iter_mut().enumerate() {
                *m += (p.axes >> k) as u32 & 1;
            }
        }
        prop_assert_eq!(made, fields.step_counts);
        prop_assert!(pulses.windows(2).all(|w| w[0].time_q32 < w[1].time_q32));
        let reference = reference_times(&as_stepped(&fields));
        for (p, r) in pulses.iter().zip(&reference) {
            prop_assert!((seconds_q32(p.time_q32) - r).abs() < 1e-3 + 1e-9 * r);
        }
    }

    /// Any fixed-point segment, valid or not, neither panics nor runs past its count.
    #[test]
    fn arbitrary_fixed_point_segments_never_panic(
        counts in prop::array::uniform3(0u32..5000),
        mask in any::<u8>(),
        dominant in any::<u8>(),
        phases in prop::array::uniform3(0u32..5000),
        period in any::<u64>(),
        ramp in any::<u64>(),
    ) {
        let segment = Segment {
            step_counts: counts,
            negative_mask: mask,
            dominant_axis: dominant,
            accelerate_steps: phases[0],
            cruise_steps: phases[1],
            decelerate_steps: phases[2],
            first_period_q32: period,
            first_ramp_q62: ramp,
        };
        if segment.check().is_err() {
            return Ok(());
        }
        let mut train = PulseTrain::new(&segment);
        let mut produced = 0u32;
        while let Ok(Some(_)) = train.next_pulse() {
            produced += 1;
            prop_assert!(produced <= segment.dominant_steps());
        }
    }

    /// Any floating-point description converts or is refused; never a panic.
    #[test]
    fn arbitrary_fields_convert_or_are_refused(
        counts in prop::array::uniform3(any::<u32>()),
        directions in prop::array::uniform3(any::<i8>()),
        dominant in any::<u8>(),
        numbers in prop::array::uniform3(any::<f64>()),
        phases in prop::array::uniform3(any::<u32>()),
    ) {
        let fields = SegmentFields {
            step_counts: counts,
            directions,
            dominant_axis: dominant,
            first_period_ticks: numbers[0],
            ramp_r: numbers[1],
            cruise_period_ticks: numbers[2],
            accelerate_steps: phases[0],
            cruise_steps: phases[1],
            decelerate_steps: phases[2],
        };
        if let Ok(segment) = Segment::from_fields(&fields) {
            prop_assert!(segment.check().is_ok());
        }
    }

    /// The limb-wise Q62 product is the exact rounded 128-bit one, over the whole range the
    /// ramp uses (products below 2¹²⁶) and at its edges.
    #[test]
    fn mul_q62_is_the_rounded_wide_product(a in 0u64..(1 << 63), b in 0u64..(1 << 63)) {
        let exact = (a as u128 * b as u128 + (1u128 << 61)) >> 62;
        prop_assert_eq!(mul_q62(a, b) as u128, exact);
    }

    /// The 16-bit-halves product an M0+ runs is the native one.
    #[test]
    fn wide_product_by_halves_is_exact(a in any::<u32>(), b in any::<u32>()) {
        prop_assert_eq!(mul_wide_u32_by_halves(a, b), a as u64 * b as u64);
    }
}

#[test]
fn mul_q62_at_the_edges_of_its_range() {
    let max = (1u64 << 63) - 1;
    for (a, b) in [
        (0, 0),
        (max, max),
        (max, 1),
        (1, 1 << 61),
        (1, (1 << 61) - 1),
        (u32::MAX as u64, u32::MAX as u64),
    ] {
        assert_eq!(
            mul_q62(a, b) as u128,
            (a as u128 * b as u128 + (1u128 << 61)) >> 62,
            "{a} × {b}"
        );
    }
    for (a, b) in [
        (0, 0),
        (u32::MAX, u32::MAX),
        (0xFFFF, 0x1_0000),
        (0x8000_0000, 2),
    ] {
        assert_eq!(mul_wide_u32_by_halves(a, b), a as u64 * b as u64);
    }
}
