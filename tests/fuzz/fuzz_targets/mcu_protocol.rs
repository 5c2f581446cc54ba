//! Any bytes on the serial line: the frame decoder yields frames or errors, each frame's
//! payload decodes as a message of either direction or fails to, and a link takes every
//! frame without losing its invariants (it can always still send, its window holds).
//!
//! Random bytes rarely make a frame with a valid CRC, so half the inputs are read as a list
//! of frames instead (`len seq ack flags payload…`), encoded properly, then damaged by the
//! input's own bits: that drives the link's sequencing and the message decoders deep.
#![no_main]

use cell_protocol::frame::{encode_frame, FrameHeader};
use cell_protocol::message::{host_messages, mcu_messages};
use cell_protocol::{FrameDecoder, HostMessage, Link, LinkOptions, McuMessage, MAX_WIRE_FRAME};
use libfuzzer_sys::fuzz_target;

fn line_from_frames(input: &[u8]) -> Vec<u8> {
    let mut line = Vec::new();
    let mut rest = input;
    while rest.len() >= 4 {
        let (len, seq, ack, flags) = (rest[0] as usize % 65, rest[1], rest[2], rest[3]);
        rest = &rest[4..];
        let payload = &rest[..len.min(rest.len())];
        rest = &rest[payload.len()..];
        let header = FrameHeader {
            seq,
            ack,
            sequenced: flags & 1 != 0,
            nak: flags & 2 != 0,
            sync_request: flags & 4 != 0,
            sync_reply: flags & 8 != 0,
        };
        let mut out = [0u8; MAX_WIRE_FRAME];
        let n = encode_frame(&header, payload, &mut out).expect("within bounds");
        // Flag bit 7: damage one byte of this frame.
        if flags & 0x80 != 0 && n > 1 {
            out[(seq as usize) % (n - 1)] ^= ack | 1;
        }
        line.extend_from_slice(&out[..n]);
    }
    line
}

fuzz_target!(|input: &[u8]| {
    let Some((&mode, rest)) = input.split_first() else {
        return;
    };
    let line = if mode & 1 == 0 {
        rest.to_vec()
    } else {
        line_from_frames(rest)
    };
    let mut decoder = FrameDecoder::new();
    let mut link = Link::<16>::new(LinkOptions {
        window: 16,
        retransmit_timeout: 10,
        nonce: 7,
    });
    let mut out = [0u8; MAX_WIRE_FRAME];
    for (now, &byte) in line.iter().enumerate() {
        let Some(Ok(frame)) = decoder.push(byte) else {
            continue;
        };
        let _ = HostMessage::decode(frame.payload);
        let _ = McuMessage::decode(frame.payload);
        host_messages(frame.payload).for_each(drop);
        mcu_messages(frame.payload).for_each(drop);
        let _ = link.receive(&frame, now as u64);
        while let Some(held) = link.next_buffered() {
            host_messages(held).for_each(drop);
        }
        if link.can_send() {
            link.send(&[0x40]).expect("room was reported");
        }
        while link.poll_transmit(now as u64, &mut out).is_some() {}
        assert!(link.unacknowledged() <= 16);
    }
});
