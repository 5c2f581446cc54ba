//! The compact continuing forms of a step segment and a screw ramp (protocol version 4).
//!
//! Nearly every segment of a print starts where the previous one ended, carries the same or
//! the next move's tag, and is all one phase of the ramp; nearly every screw command comes a
//! fixed step after the previous one and changes its speed a little. These forms leave out
//! what the MCU already knows — the start clock, the tag, the phase counts of a one-phase
//! segment, a repeated step or length — and write the rest as LEB128 varints
//! (`unsigned-varint`, minimal form only), the target as a change, and the two fixed-point
//! numbers as one 32-bit word each. A typical segment takes 15–17 bytes instead of 60, a
//! screw command 3–6, so a frame carries three or four segments with their screw commands.

use step_core::{Segment, MAX_AXES, SIGNIFICANT_BITS};

use super::{MessageError, QueuedSegment, ScrewRamp, SEGMENT_ENDS_AT_REST};

/// A step segment that continues the schedule: it starts at the end of the segment queued
/// before it, and its tag is that segment's plus `tag_step`. Built only through
/// [`NextSegment::new`], so every value has an exact compact encoding.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct NextSegment {
    duration_ticks: u32,
    tag_step: u32,
    flags: u8,
    segment: Segment,
}

impl NextSegment {
    /// The compact form of a segment, if it has one: flags of [`SEGMENT_ENDS_AT_REST`] only, a
    /// dominant axis that exists, phases that add up to its count, the first period and ramp
    /// rounded as [`Segment::from_fields`] rounds them (to [`SIGNIFICANT_BITS`]), no ramp on
    /// a pure cruise and no timing on a segment without steps. Every segment the host
    /// converts has one; anything else goes as a full `QueueSegment`.
    pub fn new(duration_ticks: u32, tag_step: u32, flags: u8, segment: Segment) -> Option<Self> {
        let dominant = segment.dominant_axis as usize;
        if flags & !SEGMENT_ENDS_AT_REST != 0 || dominant >= MAX_AXES || segment.negative_mask > 7 {
            return None;
        }
        let count = segment.step_counts[dominant] as u64;
        let ramped = segment.accelerate_steps as u64 + segment.decelerate_steps as u64;
        if ramped > count || segment.cruise_steps as u64 != count - ramped {
            return None;
        }
        let timing_fits = if count == 0 {
            segment.first_period_q32 == 0 && segment.first_ramp_q62 == 0
        } else {
            word_of(segment.first_period_q32).is_some()
                && word_of(segment.first_ramp_q62).is_some()
                && (ramped > 0 || segment.first_ramp_q62 == 0)
        };
        timing_fits.then_some(NextSegment {
            duration_ticks,
            tag_step,
            flags,
            segment,
        })
    }

    /// The compact form of `queued` sent after a segment that ends at `previous_end` with tag
    /// `previous_tag`: only if it starts there (and has a compact form at all).
    pub fn after(previous_end: u64, previous_tag: u32, queued: &QueuedSegment) -> Option<Self> {
        if queued.start_clock != previous_end {
            return None;
        }
        NextSegment::new(
            queued.duration_ticks,
            queued.tag.wrapping_sub(previous_tag),
            queued.flags,
            queued.segment,
        )
    }

    /// The segment it stands for, after one that ends at `previous_end` with tag
    /// `previous_tag` (the inverse of [`NextSegment::after`]).
    pub fn queued_after(&self, previous_end: u64, previous_tag: u32) -> QueuedSegment {
        QueuedSegment {
            start_clock: previous_end,
            duration_ticks: self.duration_ticks,
            tag: previous_tag.wrapping_add(self.tag_step),
            flags: self.flags,
            segment: self.segment,
        }
    }

    pub fn duration_ticks(&self) -> u32 {
        self.duration_ticks
    }

    /// How far its tag lies after the previous segment's (wrapping).
    pub fn tag_step(&self) -> u32 {
        self.tag_step
    }

    pub fn flags(&self) -> u8 {
        self.flags
    }

    pub fn segment(&self) -> &Segment {
        &self.segment
    }
}

/// What a compact screw command is told relative to: the previous accepted screw command
/// as sent (its start before a late arrival moved it, its length, its target) and the step
/// from the command before it to its start (0 after a full `SCREW`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct ScrewReference {
    pub start_clock: u64,
    pub step_ticks: u32,
    pub ramp_ticks: u32,
    pub target_millirpm: i32,
}

impl ScrewReference {
    /// The reference a full `SCREW` leaves.
    pub fn of_screw(ramp: &ScrewRamp) -> Self {
        ScrewReference {
            start_clock: ramp.start_clock,
            step_ticks: 0,
            ramp_ticks: ramp.ramp_ticks,
            target_millirpm: ramp.target_millirpm,
        }
    }
}

/// A screw ramp told relative to the previous screw command ([`ScrewReference`]): the start
/// as a step from the previous start — left out when it repeats the previous step (a
/// zero-order stream sampled at a fixed period) or when the ramp starts where the previous
/// one ends (a first-order chain) —, the length, left out when it is the previous one's, and
/// the target as the change from the previous target. A screw stream then costs a head, a
/// change of a byte or two, and now and then a step or a length.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct ScrewNext {
    pub start: ScrewStart,
    /// `None`: the previous command's `ramp_ticks`.
    pub ramp_ticks: Option<u32>,
    /// This target less the previous one (wrapping, as every `i32` difference fits).
    pub target_change_millirpm: i32,
    pub pin_open: bool,
}

/// Where a compact screw command starts, after the previous one's start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum ScrewStart {
    /// This many ticks after it.
    Step(u32),
    /// As many ticks after it as it came after its own predecessor.
    #[default]
    SameStep,
    /// Where its ramp ends.
    Chained,
}

impl ScrewNext {
    /// The compact form of `ramp` sent after the command `previous` stands for: only if it
    /// starts no earlier, within 2³² ticks.
    pub fn after(previous: &ScrewReference, ramp: &ScrewRamp) -> Option<Self> {
        let step = u32::try_from(ramp.start_clock.checked_sub(previous.start_clock)?).ok()?;
        Some(ScrewNext {
            start: if step == previous.step_ticks {
                ScrewStart::SameStep
            } else if step == previous.ramp_ticks {
                ScrewStart::Chained
            } else {
                ScrewStart::Step(step)
            },
            ramp_ticks: (ramp.ramp_ticks != previous.ramp_ticks).then_some(ramp.ramp_ticks),
            target_change_millirpm: ramp.target_millirpm.wrapping_sub(previous.target_millirpm),
            pin_open: ramp.pin_open,
        })
    }

    /// Ticks from the previous command's start to this one's.
    fn step_after(&self, previous: &ScrewReference) -> u32 {
        match self.start {
            ScrewStart::Step(step) => step,
            ScrewStart::SameStep => previous.step_ticks,
            ScrewStart::Chained => previous.ramp_ticks,
        }
    }

    /// The ramp it stands for after `previous` (the inverse of [`ScrewNext::after`]).
    pub fn ramp_after(&self, previous: &ScrewReference) -> ScrewRamp {
        ScrewRamp {
            start_clock: previous
                .start_clock
                .saturating_add(self.step_after(previous) as u64),
            ramp_ticks: self.ramp_ticks.unwrap_or(previous.ramp_ticks),
            target_millirpm: previous
                .target_millirpm
                .wrapping_add(self.target_change_millirpm),
            pin_open: self.pin_open,
        }
    }

    /// The reference it leaves for the next compact command.
    pub fn reference_after(&self, previous: &ScrewReference) -> ScrewReference {
        let ramp = self.ramp_after(previous);
        ScrewReference {
            start_clock: ramp.start_clock,
            step_ticks: self.step_after(previous),
            ramp_ticks: ramp.ramp_ticks,
            target_millirpm: ramp.target_millirpm,
        }
    }
}

/// Head byte of a `NEXT_SEGMENT`.
const HEAD_ENDS_AT_REST: u8 = 0x01;
const HEAD_NEGATIVE_SHIFT: u32 = 1;
const HEAD_DOMINANT_SHIFT: u32 = 4;
/// Bits 6–7: how the tag follows the previous segment's.
const HEAD_TAG_SHIFT: u32 = 6;
const TAG_NEXT: u8 = 0; // plus 1: the next move
const TAG_SAME: u8 = 1; // plus 0: another segment of the same move
const TAG_STEP_GIVEN: u8 = 2; // a varint step (neither 0 nor 1) follows the duration

/// How a segment's dominant steps divide into the ramp's phases, told by the kind of its
/// `NEXT_SEGMENT` message: nearly every segment of a print is all one phase (the planner
/// splits a move where the dominant axis changes phase), and then its phase counts are
/// implied by the dominant count.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Shape {
    /// The accelerate and decelerate counts follow the step counts (when there are steps).
    Given,
    Accelerating,
    Decelerating,
    Cruising,
}

impl Shape {
    /// The shape `segment` has (a segment without steps has the general one).
    pub(super) fn of(segment: &Segment) -> Shape {
        let count = segment.dominant_steps();
        match (
            segment.accelerate_steps,
            segment.cruise_steps,
            segment.decelerate_steps,
        ) {
            _ if count == 0 => Shape::Given,
            (a, 0, 0) if a == count => Shape::Accelerating,
            (0, 0, d) if d == count => Shape::Decelerating,
            (0, c, 0) if c == count => Shape::Cruising,
            _ => Shape::Given,
        }
    }
}

/// Head byte of a `SCREW_NEXT`.
const SCREW_HEAD_PIN_OPEN: u8 = 0x01;
const SCREW_HEAD_CHAINED: u8 = 0x02;
const SCREW_HEAD_SAME_RAMP: u8 = 0x04;
const SCREW_HEAD_SAME_STEP: u8 = 0x08;

/// Mantissa bits of a word; the other six are the exponent.
const MANTISSA_MASK: u32 = (1 << SIGNIFICANT_BITS) - 1;

/// The word of a value with at most [`SIGNIFICANT_BITS`] significant bits: the value is
/// `mantissa << exponent`, the exponent 0 for values below 2²⁶ and otherwise the one that
/// puts the mantissa's top bit at bit 25 (so each value has exactly one word).
fn word_of(value: u64) -> Option<u32> {
    let bits = u64::BITS - value.leading_zeros();
    let exponent = bits.saturating_sub(SIGNIFICANT_BITS);
    (value & ((1u64 << exponent) - 1) == 0)
        .then(|| exponent << SIGNIFICANT_BITS | (value >> exponent) as u32)
}

/// The value of a word, if it is the one word of its value.
fn value_of(word: u32) -> Option<u64> {
    let exponent = word >> SIGNIFICANT_BITS;
    let mantissa = (word & MANTISSA_MASK) as u64;
    let canonical = exponent == 0 || (mantissa >> (SIGNIFICANT_BITS - 1) == 1 && exponent <= 38);
    canonical.then(|| mantissa << exponent)
}

fn zigzag(value: i32) -> u32 {
    ((value << 1) ^ (value >> 31)) as u32
}

fn unzigzag(value: u32) -> i32 {
    (value >> 1) as i32 ^ -((value & 1) as i32)
}

/// Writes into a payload whose room the caller checked (the largest compact message is 45
/// bytes).
pub(super) struct CompactWriter<'a> {
    pub out: &'a mut [u8],
    pub len: usize,
}

impl CompactWriter<'_> {
    fn u8(&mut self, v: u8) {
        self.out[self.len] = v;
        self.len += 1;
    }
    fn varint(&mut self, v: u32) {
        let mut buf = unsigned_varint::encode::u32_buffer();
        for &b in unsigned_varint::encode::u32(v, &mut buf) {
            self.u8(b);
        }
    }
    fn word(&mut self, v: u32) {
        for b in v.to_le_bytes() {
            self.u8(b);
        }
    }
}

/// Reads a compact message from the bytes after its kind byte.
pub(super) struct CompactReader<'a> {
    pub kind: u8,
    pub rest: &'a [u8],
}

impl CompactReader<'_> {
    fn truncated(&self) -> MessageError {
        MessageError::Truncated { kind: self.kind }
    }
    fn u8(&mut self) -> Result<u8, MessageError> {
        let (&first, tail) = self.rest.split_first().ok_or(self.truncated())?;
        self.rest = tail;
        Ok(first)
    }
    fn varint(&mut self, field: &'static str) -> Result<u32, MessageError> {
        use unsigned_varint::decode::Error;
        match unsigned_varint::decode::u32(self.rest) {
            // unsigned-varint takes a fifth byte's bits above bit 31 and drops them: such a
            // varint exceeds 32 bits, and reading it as a smaller value would give the
            // message a second encoding (found by a property test).
            Ok((_, tail)) if self.rest.len() - tail.len() == 5 && self.rest[4] > 0x0F => {
                Err(MessageError::BadVarint {
                    kind: self.kind,
                    field,
                })
            }
            Ok((value, tail)) => {
                self.rest = tail;
                Ok(value)
            }
            Err(Error::Insufficient) => Err(self.truncated()),
            Err(_) => Err(MessageError::BadVarint {
                kind: self.kind,
                field,
            }),
        }
    }
    fn word(&mut self, field: &'static str) -> Result<u64, MessageError> {
        let (head, tail) = self.rest.split_first_chunk::<4>().ok_or(self.truncated())?;
        self.rest = tail;
        let word = u32::from_le_bytes(*head);
        value_of(word).ok_or(MessageError::BadValue {
            kind: self.kind,
            field,
            value: word as u64,
        })
    }
    fn bad(&self, field: &'static str, value: u64) -> MessageError {
        MessageError::BadValue {
            kind: self.kind,
            field,
            value,
        }
    }
}

pub(super) fn write_next_segment(w: &mut CompactWriter, n: &NextSegment) {
    let s = &n.segment;
    let at_rest = if n.flags & SEGMENT_ENDS_AT_REST != 0 {
        HEAD_ENDS_AT_REST
    } else {
        0
    };
    let tag = match n.tag_step {
        1 => TAG_NEXT,
        0 => TAG_SAME,
        _ => TAG_STEP_GIVEN,
    };
    w.u8(at_rest
        | (s.negative_mask << HEAD_NEGATIVE_SHIFT)
        | (s.dominant_axis << HEAD_DOMINANT_SHIFT)
        | (tag << HEAD_TAG_SHIFT));
    w.varint(n.duration_ticks);
    if tag == TAG_STEP_GIVEN {
        w.varint(n.tag_step);
    }
    for &count in &s.step_counts {
        w.varint(count);
    }
    if s.dominant_steps() == 0 {
        return;
    }
    if Shape::of(s) == Shape::Given {
        w.varint(s.accelerate_steps);
        w.varint(s.decelerate_steps);
    }
    // `new` admitted only values that have a word.
    w.word(word_of(s.first_period_q32).unwrap_or(0));
    if s.accelerate_steps as u64 + s.decelerate_steps as u64 > 0 {
        w.word(word_of(s.first_ramp_q62).unwrap_or(0));
    }
}

/// Read a `NEXT_SEGMENT` of shape `shape` (from its kind).
pub(super) fn read_next_segment(
    r: &mut CompactReader,
    shape: Shape,
) -> Result<NextSegment, MessageError> {
    let head = r.u8()?;
    let dominant_axis = head >> HEAD_DOMINANT_SHIFT & 0b11;
    if dominant_axis as usize >= MAX_AXES {
        return Err(r.bad("dominant_axis", dominant_axis as u64));
    }
    let duration_ticks = r.varint("duration_ticks")?;
    let tag_step = match head >> HEAD_TAG_SHIFT {
        TAG_NEXT => 1,
        TAG_SAME => 0,
        TAG_STEP_GIVEN => match r.varint("tag_step")? {
            // 0 and 1 have tag codes of their own
            step @ (0 | 1) => return Err(r.bad("tag_step", step as u64)),
            step => step,
        },
        _ => return Err(r.bad("head", head as u64)),
    };
    let mut segment = Segment {
        negative_mask: head >> HEAD_NEGATIVE_SHIFT & 0b111,
        dominant_axis,
        ..Segment::default()
    };
    for count in &mut segment.step_counts {
        *count = r.varint("step_counts")?;
    }
    let count = segment.dominant_steps();
    if count == 0 {
        if shape != Shape::Given {
            return Err(r.bad("dominant steps", 0)); // a phase of no steps
        }
    } else {
        (segment.accelerate_steps, segment.decelerate_steps) = match shape {
            Shape::Given => (r.varint("accelerate_steps")?, r.varint("decelerate_steps")?),
            Shape::Accelerating => (count, 0),
            Shape::Decelerating => (0, count),
            Shape::Cruising => (0, 0),
        };
        let ramped = segment.accelerate_steps as u64 + segment.decelerate_steps as u64;
        if ramped > count as u64 {
            return Err(r.bad("decelerate_steps", segment.decelerate_steps as u64));
        }
        segment.cruise_steps = count - ramped as u32;
        if shape == Shape::Given && Shape::of(&segment) != Shape::Given {
            // One phase has its own kind: each segment has one encoding.
            return Err(r.bad("accelerate_steps", segment.accelerate_steps as u64));
        }
        segment.first_period_q32 = r.word("first_period")?;
        if ramped > 0 {
            segment.first_ramp_q62 = r.word("first_ramp")?;
        }
    }
    let flags = (head & HEAD_ENDS_AT_REST != 0) as u8 * SEGMENT_ENDS_AT_REST;
    // Everything read has a compact form; `new` only restates the rules.
    NextSegment::new(duration_ticks, tag_step, flags, segment).ok_or(r.bad("segment", count as u64))
}

pub(super) fn write_screw_next(w: &mut CompactWriter, s: &ScrewNext) {
    let start = match s.start {
        ScrewStart::Step(_) => 0,
        ScrewStart::SameStep => SCREW_HEAD_SAME_STEP,
        ScrewStart::Chained => SCREW_HEAD_CHAINED,
    };
    let pin = if s.pin_open { SCREW_HEAD_PIN_OPEN } else { 0 };
    let same_ramp = if s.ramp_ticks.is_none() {
        SCREW_HEAD_SAME_RAMP
    } else {
        0
    };
    w.u8(pin | start | same_ramp);
    if let ScrewStart::Step(step) = s.start {
        w.varint(step);
    }
    if let Some(ramp) = s.ramp_ticks {
        w.varint(ramp);
    }
    w.varint(zigzag(s.target_change_millirpm));
}

pub(super) fn read_screw_next(r: &mut CompactReader) -> Result<ScrewNext, MessageError> {
    let head = r.u8()?;
    let known =
        SCREW_HEAD_PIN_OPEN | SCREW_HEAD_CHAINED | SCREW_HEAD_SAME_RAMP | SCREW_HEAD_SAME_STEP;
    let both_starts = SCREW_HEAD_CHAINED | SCREW_HEAD_SAME_STEP;
    if head & !known != 0 || head & both_starts == both_starts {
        return Err(r.bad("head", head as u64));
    }
    let start = if head & SCREW_HEAD_SAME_STEP != 0 {
        ScrewStart::SameStep
    } else if head & SCREW_HEAD_CHAINED != 0 {
        ScrewStart::Chained
    } else {
        ScrewStart::Step(r.varint("start_step_ticks")?)
    };
    let ramp_ticks = match head & SCREW_HEAD_SAME_RAMP {
        0 => Some(r.varint("ramp_ticks")?),
        _ => None,
    };
    Ok(ScrewNext {
        pin_open: head & SCREW_HEAD_PIN_OPEN != 0,
        start,
        ramp_ticks,
        target_change_millirpm: unzigzag(r.varint("target_change_millirpm")?),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn words_are_canonical_and_exact() {
        assert_eq!(word_of(0), Some(0));
        assert_eq!(word_of((1 << 26) - 1), Some((1 << 26) - 1));
        assert_eq!(word_of(1 << 26), Some(1 << 26 | 1 << 25));
        assert_eq!(word_of((1 << 26) + 1), None); // 27 significant bits
        assert_eq!(word_of(1234 << 32), Some(17 << 26 | 1234 << 15)); // 1234 has 11 bits
                                                                      // Non-canonical words are refused: a mantissa without its top bit, a shifted small one.
        assert_eq!(value_of(1 << 26 | 1), None);
        assert_eq!(value_of(39 << 26 | 1 << 25), None); // 2^64: beyond u64
        assert_eq!(
            value_of(38 << 26 | MANTISSA_MASK),
            Some((MANTISSA_MASK as u64) << 38)
        );
    }

    #[test]
    fn zigzag_maps_small_magnitudes_to_small_numbers() {
        assert_eq!(zigzag(0), 0);
        assert_eq!(zigzag(-1), 1);
        assert_eq!(zigzag(1), 2);
        assert_eq!(zigzag(i32::MIN), u32::MAX);
        assert_eq!(unzigzag(u32::MAX), i32::MIN);
    }

    #[test]
    fn the_compact_forms_stand_for_what_they_were_made_from() {
        let queued = QueuedSegment {
            start_clock: 5_000,
            duration_ticks: 700,
            tag: 3,
            flags: SEGMENT_ENDS_AT_REST,
            segment: Segment {
                step_counts: [7, 0, 0],
                cruise_steps: 7,
                first_period_q32: 100 << 32,
                ..Segment::default()
            },
        };
        let next = NextSegment::after(5_000, u32::MAX, &queued).unwrap();
        assert_eq!(next.tag_step(), 4); // wrapping from u32::MAX to 3
        assert_eq!(next.queued_after(5_000, u32::MAX), queued);
        assert_eq!(
            NextSegment::after(4_999, 2, &queued),
            None,
            "not where it starts"
        );
        let previous = ScrewReference {
            start_clock: 8_000,
            step_ticks: 500,
            ramp_ticks: 1_000,
            target_millirpm: i32::MAX,
        };
        let ramp = ScrewRamp {
            start_clock: 9_000,
            ramp_ticks: 20,
            target_millirpm: -5,
            pin_open: true,
        };
        let next = ScrewNext::after(&previous, &ramp).unwrap();
        assert_eq!(
            next.start,
            ScrewStart::Chained,
            "starts where the previous ends"
        );
        assert_eq!(next.ramp_ticks, Some(20));
        assert_eq!(next.target_change_millirpm, (-5i32).wrapping_sub(i32::MAX));
        assert_eq!(next.ramp_after(&previous), ramp);
        assert_eq!(
            next.reference_after(&previous),
            ScrewReference {
                start_clock: 9_000,
                step_ticks: 1_000,
                ramp_ticks: 20,
                target_millirpm: -5
            }
        );
        let same_step = ScrewRamp {
            start_clock: 8_500,
            ramp_ticks: 1_000,
            ..ramp
        };
        let next = ScrewNext::after(&previous, &same_step).unwrap();
        assert_eq!((next.start, next.ramp_ticks), (ScrewStart::SameStep, None));
        assert_eq!(next.ramp_after(&previous), same_step);
        let other_step = ScrewRamp {
            start_clock: 9_500,
            ..same_step
        };
        let next = ScrewNext::after(&previous, &other_step).unwrap();
        assert_eq!(next.start, ScrewStart::Step(1_500));
        assert_eq!(next.ramp_after(&previous), other_step);
        let earlier = ScrewRamp {
            start_clock: 7_999,
            ..ramp
        };
        assert_eq!(
            ScrewNext::after(&previous, &earlier),
            None,
            "before the previous"
        );
        let far = ScrewRamp {
            start_clock: 8_000 + (1 << 32),
            ..ramp
        };
        assert_eq!(ScrewNext::after(&previous, &far), None, "2^32 ticks on");
    }

    proptest! {
        #[test]
        fn a_rounded_value_has_a_word_and_comes_back(value in 0u64..1 << 63) {
            let rounded = step_core::round_significant(value);
            let word = word_of(rounded);
            prop_assert!(word.is_some(), "{rounded:#x}");
            prop_assert_eq!(value_of(word.unwrap()), Some(rounded));
        }

        #[test]
        fn any_word_is_refused_or_comes_back(word in any::<u32>()) {
            if let Some(value) = value_of(word) {
                prop_assert_eq!(word_of(value), Some(word));
            }
        }

        #[test]
        fn zigzag_round_trips(value in any::<i32>()) {
            prop_assert_eq!(unzigzag(zigzag(value)), value);
        }

        /// Every ramp that starts no earlier than the previous command and within 2³² ticks
        /// of it has the compact form, the form stands for it, and it leaves the reference
        /// the ramp and its step make — whichever start it takes (the steps and lengths are
        /// drawn from a few values, so every start and both lengths are likely).
        #[test]
        fn a_screw_ramp_after_another_comes_back(
            previous_start in 0u64..1 << 40,
            previous_step in prop_oneof![Just(0u32), Just(2_000), any::<u32>()],
            previous_ramp in prop_oneof![Just(0u32), Just(2_000), any::<u32>()],
            step in prop_oneof![Just(0u32), Just(2_000), any::<u32>()],
            ramp_ticks in prop_oneof![Just(0u32), Just(2_000), any::<u32>()],
            targets in any::<(i32, i32)>(),
            pin_open in any::<bool>(),
        ) {
            let previous = ScrewReference {
                start_clock: previous_start,
                step_ticks: previous_step,
                ramp_ticks: previous_ramp,
                target_millirpm: targets.0,
            };
            let ramp = ScrewRamp {
                start_clock: previous_start + step as u64,
                ramp_ticks,
                target_millirpm: targets.1,
                pin_open,
            };
            let next = ScrewNext::after(&previous, &ramp).unwrap();
            prop_assert_eq!(next.start == ScrewStart::SameStep, step == previous_step);
            prop_assert_eq!(
                next.start == ScrewStart::Chained,
                step != previous_step && step == previous_ramp
            );
            prop_assert_eq!(next.ramp_ticks.is_none(), ramp_ticks == previous_ramp);
            prop_assert_eq!(next.ramp_after(&previous), ramp);
            prop_assert_eq!(next.reference_after(&previous), ScrewReference {
                start_clock: ramp.start_clock,
                step_ticks: step,
                ramp_ticks,
                target_millirpm: targets.1,
            });
        }
    }
}
