use proptest::prelude::*;
use std::vec::Vec;

use super::*;

fn encode_host(m: &HostMessage) -> Vec<u8> {
    let mut out = [0; MAX_PAYLOAD];
    let len = m.encode(&mut out);
    out[..len].to_vec()
}

fn encode_mcu(m: &McuMessage) -> Vec<u8> {
    let mut out = [0; MAX_PAYLOAD];
    let len = m.encode(&mut out);
    out[..len].to_vec()
}

fn sample_segment() -> QueuedSegment {
    QueuedSegment {
        start_clock: 0x0102_0304_0506_0708,
        duration_ticks: 0x1122_3344,
        tag: 77,
        flags: SEGMENT_ENDS_AT_REST,
        segment: Segment {
            step_counts: [1000, 250, 3],
            negative_mask: 0b010,
            dominant_axis: 0,
            accelerate_steps: 400,
            cruise_steps: 200,
            decelerate_steps: 400,
            first_period_q32: 1234 << 32,
            first_ramp_q62: 1 << 55,
        },
    }
}

#[test]
fn queue_segment_layout_is_the_documented_one() {
    // Offsets as PROTOCOL.md tables them, written out byte by byte.
    let bytes = encode_host(&HostMessage::QueueSegment(sample_segment()));
    let mut expected = Vec::new();
    expected.push(0x10);
    expected.extend_from_slice(&[8, 7, 6, 5, 4, 3, 2, 1]); // start_clock
    expected.extend_from_slice(&[0x44, 0x33, 0x22, 0x11]); // duration_ticks
    expected.extend_from_slice(&[77, 0, 0, 0]); // tag
    expected.push(1); // flags: ends at rest
    expected.extend_from_slice(&[0xE8, 0x03, 0, 0, 250, 0, 0, 0, 3, 0, 0, 0]); // step_counts
    expected.extend_from_slice(&[0b010, 0]); // negative_mask, dominant_axis
    expected.extend_from_slice(&[0x90, 1, 0, 0, 200, 0, 0, 0, 0x90, 1, 0, 0]); // phases
    expected.extend_from_slice(&[0, 0, 0, 0, 0xD2, 0x04, 0, 0]); // first_period_q32
    expected.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0x80, 0]); // first_ramp_q62
    assert_eq!(bytes, expected);
    assert_eq!(bytes.len(), 60);
}

#[test]
fn state_layout_is_the_documented_one() {
    let state = McuState {
        clock: 5,
        plan_clock: 4,
        position_steps: [-1, 2, 3],
        screw_millirpm: 60_000,
        screw_angle_millirev: -7,
        pin_open: true,
        queue_free: 300,
        done_tag: 9,
        feed_scale_q16: 0xFFFF,
        mode: Mode::Held,
        fault: FaultCode::None,
    };
    let bytes = encode_mcu(&McuMessage::State(state));
    assert_eq!(bytes.len(), 48);
    assert_eq!(bytes[0], 0x83);
    assert_eq!(&bytes[9..17], &4u64.to_le_bytes()); // plan clock
    assert_eq!(&bytes[17..21], &[0xFF; 4]); // position of axis 0 = -1
    assert_eq!(&bytes[29..33], &60_000i32.to_le_bytes());
    assert_eq!(bytes[37], 1); // pin_open
    assert_eq!(&bytes[38..40], &300u16.to_le_bytes());
    assert_eq!(bytes[46], 3); // mode Held
}

#[test]
fn bad_payloads_name_kind_and_value() {
    assert_eq!(HostMessage::decode(&[]), Err(MessageError::Empty));
    assert_eq!(
        HostMessage::decode(&[0x83]),
        Err(MessageError::UnknownKind { kind: 0x83 }),
        "an MCU message is not a host message"
    );
    assert_eq!(
        McuMessage::decode(&[0x10]),
        Err(MessageError::UnknownKind { kind: 0x10 })
    );
    assert_eq!(
        HostMessage::decode(&[0x02, 1, 2]),
        Err(MessageError::Length {
            kind: 0x02,
            expected: 5,
            actual: 3
        })
    );
    let mut screw = encode_host(&HostMessage::Screw(ScrewRamp::default()));
    *screw.last_mut().unwrap() = 2;
    assert_eq!(
        HostMessage::decode(&screw),
        Err(MessageError::BadValue {
            kind: 0x11,
            field: "pin_open",
            value: 2
        })
    );
    let mut segment = encode_host(&HostMessage::QueueSegment(sample_segment()));
    segment[17] = 0x80;
    assert_eq!(
        HostMessage::decode(&segment),
        Err(MessageError::BadValue {
            kind: 0x10,
            field: "flags",
            value: 0x80
        })
    );
    let mut state = encode_mcu(&McuMessage::State(McuState::default()));
    state[46] = 9;
    assert_eq!(
        McuMessage::decode(&state),
        Err(MessageError::BadValue {
            kind: 0x83,
            field: "mode",
            value: 9
        })
    );
}

#[test]
fn only_the_emergency_stop_and_state_go_unsequenced() {
    assert!(!HostMessage::EmergencyStop.is_sequenced());
    assert!(HostMessage::QueueSegment(sample_segment()).is_sequenced());
    assert!(!McuMessage::State(McuState::default()).is_sequenced());
    assert!(McuMessage::Fault {
        code: FaultCode::Underrun,
        clock: 1,
        tag: 2
    }
    .is_sequenced());
}

fn any_segment() -> impl Strategy<Value = Segment> {
    (
        any::<[u32; 3]>(),
        any::<u8>(),
        any::<u8>(),
        any::<[u32; 3]>(),
        any::<u64>(),
        any::<u64>(),
    )
        .prop_map(|(counts, mask, dominant, phases, period, ramp)| Segment {
            step_counts: counts,
            negative_mask: mask,
            dominant_axis: dominant,
            accelerate_steps: phases[0],
            cruise_steps: phases[1],
            decelerate_steps: phases[2],
            first_period_q32: period,
            first_ramp_q62: ramp,
        })
}

/// A segment with a compact form: phases that add up, the timing rounded as the host rounds
/// it (counts small and large, so the varints take 1 to 5 bytes; every tag code and, as
/// often as a split, each single-phase shape).
fn any_compact_segment() -> impl Strategy<Value = NextSegment> {
    (
        (any::<u32>(), prop_oneof![Just(0u32), Just(1), any::<u32>()]),
        any::<bool>(),
        prop::array::uniform3(prop_oneof![0u32..200, any::<u32>()]),
        0u8..8,
        0u8..3,
        (0u8..4, any::<[u32; 2]>()),
        1u64 << 32..1 << 62,
        0u64..1 << 61,
    )
        .prop_map(
            |(
                (duration, tag_step),
                at_rest,
                counts,
                mask,
                dominant,
                (shape, split),
                period,
                ramp,
            )| {
                let count = counts[dominant as usize];
                let (accelerate, decelerate) = match shape {
                    0 => {
                        let accelerate = split[0] % (count as u64 + 1) as u32;
                        (accelerate, split[1] % (count - accelerate + 1))
                    }
                    1 => (count, 0),
                    2 => (0, count),
                    _ => (0, 0),
                };
                let cruise = count - accelerate - decelerate;
                let timed = count > 0;
                let ramped = accelerate + decelerate > 0;
                let segment = Segment {
                    step_counts: counts,
                    negative_mask: mask,
                    dominant_axis: dominant,
                    accelerate_steps: accelerate,
                    cruise_steps: cruise,
                    decelerate_steps: decelerate,
                    first_period_q32: if timed {
                        step_core::round_significant(period)
                    } else {
                        0
                    },
                    first_ramp_q62: if timed && ramped {
                        step_core::round_significant(ramp)
                    } else {
                        0
                    },
                };
                NextSegment::new(duration, tag_step, at_rest as u8, segment)
                    .expect("built to have a compact form")
            },
        )
}

fn any_host_message() -> impl Strategy<Value = HostMessage> {
    prop_oneof![
        any_compact_segment().prop_map(HostMessage::NextSegment),
        (
            prop_oneof![
                any::<u32>().prop_map(ScrewStart::Step),
                Just(ScrewStart::SameStep),
                Just(ScrewStart::Chained)
            ],
            any::<Option<u32>>(),
            any::<i32>(),
            any::<bool>()
        )
            .prop_map(|(start, r, change, pin)| {
                HostMessage::ScrewNext(ScrewNext {
                    start,
                    ramp_ticks: r,
                    target_change_millirpm: change,
                    pin_open: pin,
                })
            }),
        Just(HostMessage::Identify),
        any::<u32>().prop_map(|token| HostMessage::ClockQuery { token }),
        (any::<u32>(), any::<u32>()).prop_map(|(a, b)| HostMessage::Configure {
            host_timeout_ticks: a,
            state_period_ticks: b
        }),
        (
            any::<u64>(),
            any::<u32>(),
            any::<u32>(),
            any::<bool>(),
            any_segment()
        )
            .prop_map(|(s, d, t, at_rest, seg)| {
                HostMessage::QueueSegment(QueuedSegment {
                    start_clock: s,
                    duration_ticks: d,
                    tag: t,
                    flags: at_rest as u8,
                    segment: seg,
                })
            }),
        (any::<u64>(), any::<u32>(), any::<i32>(), any::<bool>()).prop_map(|(s, r, rpm, pin)| {
            HostMessage::Screw(ScrewRamp {
                start_clock: s,
                ramp_ticks: r,
                target_millirpm: rpm,
                pin_open: pin,
            })
        }),
        any::<u32>().prop_map(|rate_q32| HostMessage::FeedHold { rate_q32 }),
        (any::<u32>(), any::<u32>()).prop_map(|(r, d)| HostMessage::FeedResume {
            rate_q32: r,
            delay_ticks: d
        }),
        Just(HostMessage::DropQueue),
        Just(HostMessage::EmergencyStop),
        Just(HostMessage::Reset),
        Just(HostMessage::QueryState),
        Just(HostMessage::QueryCounters),
    ]
}

fn any_mode() -> impl Strategy<Value = Mode> {
    (0u8..5).prop_map(|m| Mode::from_u8(m).unwrap())
}

fn any_fault() -> impl Strategy<Value = FaultCode> {
    (0u8..9).prop_map(|f| FaultCode::from_u8(f).unwrap())
}

fn any_mcu_message() -> impl Strategy<Value = McuMessage> {
    prop_oneof![
        (
            any::<u16>(),
            any::<u32>(),
            any::<u16>(),
            any::<u8>(),
            any::<u16>()
        )
            .prop_map(|(v, hz, q, a, sq)| {
                McuMessage::Identity(Identity {
                    protocol_version: v,
                    timer_hz: hz,
                    queue_capacity: q,
                    axis_count: a,
                    screw_queue_capacity: sq,
                })
            }),
        (any::<u32>(), any::<u64>()).prop_map(|(token, clock)| McuMessage::Clock { token, clock }),
        (
            any::<(u64, u64)>(),
            any::<[i32; 3]>(),
            any::<(i32, i32, bool, u16, u32, u16)>(),
            any_mode(),
            any_fault()
        )
            .prop_map(|((clock, plan_clock), position_steps, f, mode, fault)| {
                McuMessage::State(McuState {
                    clock,
                    plan_clock,
                    position_steps,
                    screw_millirpm: f.0,
                    screw_angle_millirev: f.1,
                    pin_open: f.2,
                    queue_free: f.3,
                    done_tag: f.4,
                    feed_scale_q16: f.5,
                    mode,
                    fault,
                })
            }),
        any::<[u32; 7]>().prop_map(|c| McuMessage::Counters(McuCounters {
            frames_received: c[0],
            crc_errors: c[1],
            framing_errors: c[2],
            naks_sent: c[3],
            retransmits: c[4],
            underruns: c[5],
            late_segments: c[6],
        })),
        (any_fault(), any::<u64>(), any::<u32>())
            .prop_map(|(code, clock, tag)| McuMessage::Fault { code, clock, tag }),
    ]
}

proptest! {
    #[test]
    fn host_messages_round_trip(m in any_host_message()) {
        prop_assert_eq!(HostMessage::decode(&encode_host(&m)), Ok(m));
    }

    #[test]
    fn mcu_messages_round_trip(m in any_mcu_message()) {
        prop_assert_eq!(McuMessage::decode(&encode_mcu(&m)), Ok(m));
    }

    #[test]
    fn any_payload_decodes_or_errors(bytes in proptest::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD)) {
        // Decoding never panics, and whatever decodes re-encodes to the same bytes.
        if let Ok(m) = HostMessage::decode(&bytes) {
            prop_assert_eq!(encode_host(&m), bytes.clone());
        }
        if let Ok(m) = McuMessage::decode(&bytes) {
            prop_assert_eq!(encode_mcu(&m), bytes);
        }
    }

    /// Random bytes seldom form a whole message, so the one-encoding rule is also checked
    /// on valid messages with one byte changed: whatever still decodes re-encodes to exactly
    /// those bytes (a one-phase segment sent as NEXT_SEGMENT, a non-minimal varint or word,
    /// a tag step given that has a code: each must be refused, not taken in a second form).
    #[test]
    fn a_changed_byte_decodes_to_its_one_encoding_or_errors(
        host in any_host_message(),
        mcu in any_mcu_message(),
        at in any::<prop::sample::Index>(),
        change in 1u8..=255,
    ) {
        let mut bytes = encode_host(&host);
        let i = at.index(bytes.len());
        bytes[i] ^= change;
        if let Ok(decoded) = HostMessage::decode(&bytes) {
            prop_assert_eq!(encode_host(&decoded), bytes);
        }
        let mut bytes = encode_mcu(&mcu);
        let i = at.index(bytes.len());
        bytes[i] ^= change;
        if let Ok(decoded) = McuMessage::decode(&bytes) {
            prop_assert_eq!(encode_mcu(&decoded), bytes);
        }
    }

    #[test]
    fn truncated_messages_are_length_errors(m in any_host_message(), fraction in 0.0f64..1.0) {
        let bytes = encode_host(&m);
        prop_assume!(bytes.len() > 1);
        let cut = 1 + (fraction * (bytes.len() - 1) as f64) as usize;
        let is_length_error = matches!(
            HostMessage::decode(&bytes[..cut]),
            Err(MessageError::Length { .. } | MessageError::Truncated { .. })
        );
        prop_assert!(is_length_error);
    }

    /// A payload of several messages gives them back in order, each re-encoding to its bytes.
    #[test]
    fn packed_messages_come_back_in_order(messages in proptest::collection::vec(any_host_message(), 1..8)) {
        let mut payload = Vec::new();
        let mut packed = Vec::new();
        for m in messages {
            let bytes = encode_host(&m);
            if payload.len() + bytes.len() <= MAX_PAYLOAD {
                payload.extend_from_slice(&bytes);
                packed.push(m);
            }
        }
        let decoded: Result<Vec<_>, _> = host_messages(&payload).collect();
        prop_assert_eq!(decoded, Ok(packed));
    }

    /// Any bytes as a payload: messages until the first that does not decode, then nothing;
    /// each one decoded re-encodes to the bytes it came from.
    #[test]
    fn any_payload_splits_into_messages_or_stops_at_an_error(
        bytes in proptest::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD)
    ) {
        let mut at = 0;
        let mut ended = false;
        for m in host_messages(&bytes) {
            prop_assert!(!ended, "a message after an error");
            match m {
                Ok(m) => {
                    let encoded = encode_host(&m);
                    prop_assert_eq!(&bytes[at..at + encoded.len()], &encoded[..]);
                    at += encoded.len();
                }
                Err(_) => ended = true,
            }
        }
        prop_assert!(ended || at == bytes.len());
    }
}

#[test]
fn next_segment_layout_is_the_documented_one() {
    // PROTOCOL.md's example: 300 steps of the arm with 100 of the bed, accelerating 120 and
    // decelerating 80, a 1234-tick first period, continuing with the next tag.
    let segment = Segment {
        step_counts: [100, 300, 0],
        negative_mask: 0b001,
        dominant_axis: 1,
        accelerate_steps: 120,
        cruise_steps: 100,
        decelerate_steps: 80,
        first_period_q32: 1234 << 32,
        first_ramp_q62: 3 << 40,
    };
    let next = NextSegment::new(40_000, 1, SEGMENT_ENDS_AT_REST, segment).unwrap();
    let bytes = encode_host(&HostMessage::NextSegment(next));
    let expected = [
        0x12,        // kind
        0b0001_0011, // head: ends at rest, bed negative, dominant axis 1, tag step 1
        0xC0,
        0xB8,
        0x02, // duration 40,000
        100,
        0xAC,
        0x02,
        0, // step counts 100, 300, 0
        120,
        80, // accelerate, decelerate (cruise = 300 − 200)
        0x00,
        0x00,
        0x69,
        0x46, // first period 1234 << 32 = (1234 << 15) << 17: 17 << 26 | 1234 << 15
        0x00,
        0x00,
        0x00,
        0x43, // ramp 3 << 40 (42 bits) = (1 << 25 | 1 << 24) << 16: 16 << 26 | 3 << 24
    ];
    assert_eq!(bytes, expected);
    // Tag step 0 (a second segment of the same move) is a code of the head; another step
    // follows the duration.
    let same_move = NextSegment::new(40_000, 0, 0, segment).unwrap();
    let bytes = encode_host(&HostMessage::NextSegment(same_move));
    assert_eq!(&bytes[1..6], &[0b0101_0010, 0xC0, 0xB8, 0x02, 100]);
    let later_move = NextSegment::new(40_000, 5, 0, segment).unwrap();
    let bytes = encode_host(&HostMessage::NextSegment(later_move));
    assert_eq!(&bytes[1..6], &[0b1001_0010, 0xC0, 0xB8, 0x02, 5]);
    // All of its steps accelerating: kind NEXT_ACCELERATING, and no phase counts.
    let accelerating = NextSegment::new(
        40_000,
        1,
        0,
        Segment {
            accelerate_steps: 300,
            cruise_steps: 0,
            decelerate_steps: 0,
            ..segment
        },
    )
    .unwrap();
    let bytes = encode_host(&HostMessage::NextSegment(accelerating));
    assert_eq!(bytes[..2], [0x14, 0b0001_0010]);
    assert_eq!(bytes[5..9], [100, 0xAC, 0x02, 0]);
    assert_eq!(bytes[9..], expected[11..], "the words follow the counts");
    // The same as a NEXT_SEGMENT with its phase counts (300 accelerating, 0 decelerating)
    // is refused: a segment has one encoding.
    let mut general = vec![0x12];
    general.extend_from_slice(&bytes[1..9]);
    general.extend_from_slice(&[0xAC, 0x02, 0]);
    general.extend_from_slice(&bytes[9..]);
    assert!(matches!(
        HostMessage::decode(&general),
        Err(MessageError::BadValue {
            field: "accelerate_steps",
            ..
        })
    ));
    general[10] = 0x01; // 172 accelerating, 128 cruising: a general segment
    let general_segment = Segment {
        accelerate_steps: 172,
        cruise_steps: 128,
        decelerate_steps: 0,
        ..segment
    };
    assert_eq!(
        HostMessage::decode(&general),
        Ok(HostMessage::NextSegment(
            NextSegment::new(40_000, 1, 0, general_segment).unwrap()
        ))
    );
    // Refused: tag code 3, a given tag step of 1 (it has a code), a phase kind without steps.
    let mut bad = bytes.clone();
    bad[1] |= 0b1100_0000;
    let refused = |kind: u8, field: &'static str, value: u32| {
        Err(MessageError::BadValue {
            kind,
            field,
            value: value.into(),
        })
    };
    assert_eq!(
        HostMessage::decode(&bad),
        refused(0x14, "head", 0b1101_0010)
    );
    assert_eq!(
        HostMessage::decode(&[0x12, 0b1000_0000, 1, 1, 0, 0, 0]),
        refused(0x12, "tag_step", 1)
    );
    assert_eq!(
        HostMessage::decode(&[0x15, 0, 1, 0, 0, 0]),
        refused(0x15, "dominant steps", 0)
    );
    // Accepted: the same with a tag step of 2, and with tag code 0 (the next move): timed
    // rests of one tick.
    let rest = |tag_step| {
        let none = Segment {
            step_counts: [0; 3],
            negative_mask: 0,
            dominant_axis: 0,
            accelerate_steps: 0,
            cruise_steps: 0,
            decelerate_steps: 0,
            first_period_q32: 0,
            first_ramp_q62: 0,
        };
        Ok(HostMessage::NextSegment(
            NextSegment::new(1, tag_step, 0, none).unwrap(),
        ))
    };
    assert_eq!(
        HostMessage::decode(&[0x12, 0b1000_0000, 1, 2, 0, 0, 0]),
        rest(2)
    );
    assert_eq!(HostMessage::decode(&[0x12, 0, 1, 0, 0, 0]), rest(1));
}

#[test]
fn screw_next_layout_is_the_documented_one() {
    let bytes = encode_host(&HostMessage::ScrewNext(ScrewNext {
        start: ScrewStart::Step(20_000),
        ramp_ticks: Some(2_000),
        target_change_millirpm: -1_500,
        pin_open: true,
    }));
    // kind, head (pin open), 20,000, 2,000, zigzag(−1,500) = 2,999.
    assert_eq!(bytes, [0x13, 1, 0xA0, 0x9C, 0x01, 0xD0, 0x0F, 0xB7, 0x17]);
    // The usual ones: as long after the previous as that one after its own, as long (a
    // zero-order stream), 60 millirpm faster; where the previous ramp ends (first order).
    let sixty_faster = |start| {
        encode_host(&HostMessage::ScrewNext(ScrewNext {
            start,
            ramp_ticks: None,
            target_change_millirpm: 60,
            pin_open: true,
        }))
    };
    assert_eq!(sixty_faster(ScrewStart::SameStep), [0x13, 0x0D, 0x78]);
    assert_eq!(sixty_faster(ScrewStart::Chained), [0x13, 0x07, 0x78]);
    // Chained and same step at once is refused.
    assert!(HostMessage::decode(&[0x13, 0x0B, 0x78]).is_err());
}

/// A varint of five bytes holds 32 bits: four in its last byte. One whose last byte has more
/// is refused (the crate underneath dropped them, and `81 80 80 80 11` read as 1 + 2²⁸).
#[test]
fn a_varint_beyond_32_bits_is_refused() {
    // SCREW_NEXT, pin open, same step and ramp, target change as zvar.
    let largest = [0x13, 0x0D, 0xFF, 0xFF, 0xFF, 0xFF, 0x0F];
    let Ok(HostMessage::ScrewNext(_)) = HostMessage::decode(&largest) else {
        panic!("{:?}", HostMessage::decode(&largest));
    };
    assert_eq!(
        encode_host(&HostMessage::decode(&largest).unwrap()),
        largest
    );
    for last in [0x10, 0x11, 0x7F] {
        assert_eq!(
            HostMessage::decode(&[0x13, 0x0D, 0x81, 0x80, 0x80, 0x80, last]),
            Err(MessageError::BadVarint {
                kind: 0x13,
                field: "target_change_millirpm"
            }),
            "last byte {last:#04x}"
        );
    }
}
