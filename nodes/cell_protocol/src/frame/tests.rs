use proptest::prelude::*;

use super::*;

fn header(seq: u8, ack: u8, sequenced: bool, nak: bool) -> FrameHeader {
    FrameHeader {
        seq,
        ack,
        sequenced,
        nak,
        ..FrameHeader::default()
    }
}

fn wire(header: &FrameHeader, payload: &[u8]) -> ([u8; MAX_WIRE_FRAME], usize) {
    let mut out = [0; MAX_WIRE_FRAME];
    let len = encode_frame(header, payload, &mut out).unwrap();
    (out, len)
}

/// Feed bytes; collect the frames (as owned header + payload) and errors.
fn decode_all(
    decoder: &mut FrameDecoder,
    bytes: &[u8],
) -> std::vec::Vec<Result<(FrameHeader, std::vec::Vec<u8>), FrameError>> {
    let mut results = std::vec::Vec::new();
    for &b in bytes {
        if let Some(r) = decoder.push(b) {
            results.push(r.map(|f| (f.header, f.payload.to_vec())));
        }
    }
    results
}

#[test]
fn crc_is_ccitt_false() {
    // The catalogue's check value for CRC-16/IBM-3740 (a.k.a. CCITT-FALSE).
    assert_eq!(FRAME_CRC.checksum(b"123456789"), 0x29B1);
}

#[test]
fn known_frame_bytes() {
    // len 2, seq 5, ack 9, flags SEQUENCED, payload [0x10, 0x00]; CRC over those 6 bytes,
    // computed by hand with the bitwise CCITT-FALSE algorithm below (independent of the crate).
    let body = [2u8, 5, 9, 1, 0x10, 0x00];
    let mut crc: u16 = 0xFFFF;
    for &byte in &body {
        crc ^= (byte as u16) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
        }
    }
    let (out, len) = wire(&header(5, 9, true, false), &[0x10, 0x00]);
    // COBS of [02 05 09 01 10 00 lo hi]: one zero at index 5.
    let [lo, hi] = crc.to_le_bytes();
    assert!(
        lo != 0 && hi != 0,
        "choose a payload whose CRC has no zero byte"
    );
    assert_eq!(&out[..len], &[6, 2, 5, 9, 1, 0x10, 3, lo, hi, 0]);
}

#[test]
fn frame_round_trips_through_the_decoder() {
    let (out, len) = wire(&header(200, 17, true, true), b"hello\0world");
    let mut decoder = FrameDecoder::new();
    let frames = decode_all(&mut decoder, &out[..len]);
    assert_eq!(
        frames,
        [Ok((header(200, 17, true, true), b"hello\0world".to_vec()))]
    );
    assert_eq!(decoder.counters().frames, 1);
}

#[test]
fn garbage_before_a_frame_costs_one_error_then_resynchronises() {
    let (out, len) = wire(&header(1, 2, true, false), &[0x01, 0x02, 0x03]);
    let mut bytes = std::vec![0x55, 0xAA, 0x13];
    bytes.push(0); // the garbage ends at a delimiter (as the sender's previous frame would)
    bytes.extend_from_slice(&out[..len]);
    let mut decoder = FrameDecoder::new();
    let frames = decode_all(&mut decoder, &bytes);
    assert_eq!(frames.len(), 2);
    assert!(frames[0].is_err(), "{frames:?}");
    assert_eq!(
        frames[1],
        Ok((header(1, 2, true, false), std::vec![1, 2, 3]))
    );
}

#[test]
fn every_single_byte_corruption_is_caught() {
    let (out, len) = wire(&header(7, 3, true, false), &[0x10, 1, 2, 3, 4, 5, 0, 0, 9]);
    for index in 0..len - 1 {
        for flip in [0x01u8, 0x80, 0xFF] {
            let mut bytes = out[..len].to_vec();
            bytes[index] ^= flip;
            bytes.push(0); // a later delimiter ends whatever the corruption made
            let mut decoder = FrameDecoder::new();
            let frames = decode_all(&mut decoder, &bytes);
            assert!(
                frames.iter().all(|f| f.is_err()),
                "byte {index} ^ {flip:#x} gave {frames:?}"
            );
        }
    }
}

#[test]
fn overlong_garbage_is_one_error() {
    let mut bytes = std::vec![0x42; 500];
    bytes.push(0);
    let mut decoder = FrameDecoder::new();
    assert_eq!(
        decode_all(&mut decoder, &bytes),
        [Err(FrameError::Overlong { len: 500 })]
    );
    assert_eq!(decoder.counters().framing_errors, 1);
}

#[test]
fn payload_too_long_is_refused() {
    let mut out = [0; MAX_WIRE_FRAME];
    assert_eq!(
        encode_frame(&FrameHeader::default(), &[1; MAX_PAYLOAD + 1], &mut out),
        Err(FrameError::PayloadTooLong {
            len: MAX_PAYLOAD + 1
        })
    );
    let mut small = [0; 8];
    assert_eq!(
        encode_frame(&FrameHeader::default(), &[1; 10], &mut small),
        Err(FrameError::BufferTooSmall { len: 8 })
    );
}

/// A frame that passes length and CRC checks but carries 65 bytes is refused, never handed on
/// with a payload longer than the receiver's buffers: its 72 encoded bytes are more than any
/// frame's 71 (the decoder's buffer once held 72, and let it through to the MCU's 64-byte
/// copy, which panicked).
#[test]
fn a_well_formed_frame_with_a_65_byte_payload_is_refused() {
    let mut body = std::vec![MAX_PAYLOAD as u8 + 1, 0, 0, FLAG_SEQUENCED];
    body.extend_from_slice(&[0x55; MAX_PAYLOAD + 1]);
    let crc = FRAME_CRC.checksum(&body).to_le_bytes();
    body.extend_from_slice(&crc);
    assert_eq!(
        parse_frame(&body),
        Err(FrameError::PayloadTooLong {
            len: MAX_PAYLOAD + 1
        })
    );
    let mut encoded = std::vec![0; cobs::max_encoding_length(body.len())];
    let written = cobs::encode(&body, &mut encoded);
    encoded.truncate(written);
    assert_eq!(encoded.len(), MAX_WIRE_FRAME);
    encoded.push(0);
    let mut decoder = FrameDecoder::new();
    assert_eq!(
        decode_all(&mut decoder, &encoded),
        [Err(FrameError::Overlong { len: 72 })]
    );
    assert_eq!(decoder.counters().framing_errors, 1);
    // and the decoder goes on with the next frame
    let (out, len) = wire(&header(1, 2, true, false), &[7; 3]);
    assert_eq!(
        decode_all(&mut decoder, &out[..len]),
        [Ok((header(1, 2, true, false), std::vec![7; 3]))]
    );
}

/// A session start's nonce, its answer and a NAK's bitmap are the link's bytes, not messages;
/// a sequenced frame's payload is messages even when it also carries a NAK.
#[test]
fn only_frames_of_messages_give_messages() {
    let frame = |header: FrameHeader| Frame {
        header,
        payload: &[0x30, 1, 2, 3],
    };
    let sync_request = FrameHeader {
        sync_request: true,
        ..FrameHeader::default()
    };
    let sync_reply = FrameHeader {
        sync_reply: true,
        ..FrameHeader::default()
    };
    assert_eq!(frame(sync_request).messages(), None);
    assert_eq!(frame(sync_reply).messages(), None);
    assert_eq!(frame(header(0, 0, false, true)).messages(), None);
    assert_eq!(
        frame(header(0, 0, true, true)).messages(),
        Some(&[0x30, 1, 2, 3][..])
    );
    assert_eq!(
        frame(header(0, 0, false, false)).messages(),
        Some(&[0x30, 1, 2, 3][..])
    );
}

#[test]
fn unknown_flags_are_refused() {
    let body = [0u8, 0, 0, 0x40];
    let crc = FRAME_CRC.checksum(&body).to_le_bytes();
    let frame = [body[0], body[1], body[2], body[3], crc[0], crc[1]];
    assert_eq!(
        parse_frame(&frame),
        Err(FrameError::UnknownFlags { flags: 0x40 })
    );
}

fn any_header() -> impl Strategy<Value = FrameHeader> {
    (any::<u8>(), any::<u8>(), any::<[bool; 4]>()).prop_map(|(seq, ack, f)| FrameHeader {
        seq,
        ack,
        sequenced: f[0],
        nak: f[1],
        sync_request: f[2],
        sync_reply: f[3],
    })
}

proptest! {
    #[test]
    fn encode_decode_round_trips(
        frames in proptest::collection::vec(
            (any_header(), proptest::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD)), 1..8)
    ) {
        let mut bytes = std::vec::Vec::new();
        for (h, p) in &frames {
            let (out, len) = wire(h, p);
            bytes.extend_from_slice(&out[..len]);
        }
        let mut decoder = FrameDecoder::new();
        let decoded = decode_all(&mut decoder, &bytes);
        let expected: std::vec::Vec<_> = frames.into_iter().map(Ok).collect();
        prop_assert_eq!(decoded, expected);
    }

    #[test]
    fn any_bytes_give_frames_or_errors(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        let mut decoder = FrameDecoder::new();
        let results = decode_all(&mut decoder, &bytes);
        let c = decoder.counters();
        prop_assert_eq!(results.len() as u32, c.frames + c.crc_errors + c.framing_errors);
        for (h, p) in results.into_iter().flatten() {
            prop_assert!(p.len() <= MAX_PAYLOAD);
            // Whatever decoded must encode back to a frame that decodes the same.
            let (out, len) = wire(&h, &p);
            let mut again = FrameDecoder::new();
            prop_assert_eq!(decode_all(&mut again, &out[..len]), std::vec![Ok((h, p))]);
        }
    }

    #[test]
    fn a_frame_after_any_garbage_and_a_delimiter_decodes(
        garbage in proptest::collection::vec(any::<u8>(), 0..300),
        payload in proptest::collection::vec(any::<u8>(), 0..=MAX_PAYLOAD),
    ) {
        let h = header(9, 4, true, false);
        let (out, len) = wire(&h, &payload);
        let mut bytes = garbage;
        bytes.push(0);
        bytes.extend_from_slice(&out[..len]);
        let mut decoder = FrameDecoder::new();
        let results = decode_all(&mut decoder, &bytes);
        prop_assert_eq!(results.last().cloned(), Some(Ok((h, payload))));
    }
}
