use proptest::prelude::*;
use std::collections::VecDeque;
use std::vec::Vec;

use super::*;
use crate::FrameDecoder;

const TIMEOUT: u64 = 20;

fn link(nonce: u32, window: usize) -> Link<32> {
    Link::new(LinkOptions {
        window,
        retransmit_timeout: TIMEOUT,
        nonce,
    })
}

/// Faults a channel applies to whole frames and bytes, from a fixed-seed generator.
#[derive(Clone, Copy, Debug)]
struct Faults {
    drop_per_mille: u32,
    corrupt_per_mille: u32,
    duplicate_per_mille: u32,
}

const CLEAN: Faults = Faults {
    drop_per_mille: 0,
    corrupt_per_mille: 0,
    duplicate_per_mille: 0,
};

struct Rng(u64);

impl Rng {
    fn per_mille(&mut self, p: u32) -> bool {
        // xorshift64*: deterministic, independent of the code under test.
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) % 1000) < p as u64
    }
}

/// One side: its link, decoder, the bytes in flight towards it, what it delivered.
struct Side {
    link: Link<32>,
    decoder: FrameDecoder,
    inbox: VecDeque<u8>,
    delivered: Vec<Vec<u8>>,
    restarts: Vec<usize>,
}

impl Side {
    fn new(nonce: u32, window: usize) -> Side {
        Side {
            link: link(nonce, window),
            decoder: FrameDecoder::new(),
            inbox: VecDeque::new(),
            delivered: Vec::new(),
            restarts: Vec::new(),
        }
    }

    fn receive_all(&mut self, now: u64) {
        while let Some(byte) = self.inbox.pop_front() {
            if let Some(Ok(frame)) = self.decoder.push(byte) {
                match self.link.receive(&frame, now) {
                    Received::Message(p) => {
                        self.delivered.push(p.to_vec());
                        while let Some(p) = self.link.next_buffered() {
                            self.delivered.push(p.to_vec());
                        }
                    }
                    Received::PeerRestarted { lost } => self.restarts.push(lost),
                    Received::Unsequenced(_) | Received::Nothing => {}
                }
            }
        }
    }
}

/// Move everything `from` has to send into `to`'s inbox through a faulty channel.
fn transmit(from: &mut Side, to: &mut Side, now: u64, faults: Faults, rng: &mut Rng) {
    let mut out = [0; MAX_WIRE_FRAME];
    while let Some(len) = from.link.poll_transmit(now, &mut out) {
        if rng.per_mille(faults.drop_per_mille) {
            continue;
        }
        let mut bytes = out[..len].to_vec();
        if rng.per_mille(faults.corrupt_per_mille) {
            let index = (rng.0 as usize) % (len - 1); // not the delimiter
            bytes[index] ^= 0x5A;
        }
        let copies = if rng.per_mille(faults.duplicate_per_mille) {
            2
        } else {
            1
        };
        for _ in 0..copies {
            to.inbox.extend(bytes.iter().copied());
        }
    }
}

/// One round at `now`: each side sends what it has, then each takes what arrived.
fn round(a: &mut Side, b: &mut Side, now: u64, faults: Faults, rng: &mut Rng) {
    transmit(a, b, now, faults, rng);
    transmit(b, a, now, faults, rng);
    a.receive_all(now);
    b.receive_all(now);
}

/// Everything `from` has to send at `now` into `to`'s inbox, but for the `lost`-th frame.
fn transmit_losing(from: &mut Side, to: &mut Side, now: u64, lost: usize) {
    let mut out = [0; MAX_WIRE_FRAME];
    let mut index = 0;
    while let Some(len) = from.link.poll_transmit(now, &mut out) {
        if index != lost {
            to.inbox.extend(out[..len].iter().copied());
        }
        index += 1;
    }
}

/// Two sides with this window, their session started over a clean channel.
fn synced_pair(window: usize) -> (Side, Side, Rng) {
    let mut a = Side::new(1, window);
    let mut b = Side::new(2, window);
    let mut rng = Rng(1);
    for now in 0..3 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    (a, b, rng)
}

fn message(i: u32) -> Vec<u8> {
    let mut p = Vec::from(i.to_le_bytes());
    p.resize(4 + (i as usize % 40), i as u8);
    p
}

/// Send `count` messages each way; returns both sides after everything is delivered (or the
/// step budget ran out).
fn exchange(count: u32, window: usize, faults: Faults, seed: u64) -> (Side, Side, u64) {
    let mut a = Side::new(0xA11CE, window);
    let mut b = Side::new(0xB0B, window);
    let mut rng = Rng(seed | 1);
    let (mut sent_a, mut sent_b) = (0, 0);
    let mut now = 0;
    while now < 200_000 {
        while sent_a < count && a.link.can_send() {
            a.link.send(&message(sent_a)).unwrap();
            sent_a += 1;
        }
        while sent_b < count && b.link.can_send() {
            b.link.send(&message(1_000_000 + sent_b)).unwrap();
            sent_b += 1;
        }
        round(&mut a, &mut b, now, faults, &mut rng);
        if a.delivered.len() == count as usize
            && b.delivered.len() == count as usize
            && a.link.unacknowledged() == 0
            && b.link.unacknowledged() == 0
        {
            break;
        }
        now += 1;
    }
    (a, b, now)
}

#[test]
fn clean_channel_delivers_in_order_without_retransmits() {
    let (a, b, steps) = exchange(1000, 16, CLEAN, 1);
    let expected_b: Vec<_> = (0..1000).map(message).collect();
    let expected_a: Vec<_> = (0..1000).map(|i| message(1_000_000 + i)).collect();
    assert_eq!(b.delivered, expected_b);
    assert_eq!(a.delivered, expected_a);
    assert_eq!(a.link.counters().retransmits, 0);
    assert_eq!(b.link.counters().naks_sent, 0);
    // A window of 16 goes out in one step and its acknowledgement comes back in the next:
    // 1000 messages take two steps per 63 windows, plus the session start.
    assert!(steps <= 2 * 63 + 5, "{steps} steps");
}

/// A side that restarted (an MCU reset mid-print) knows no peer session yet: the frames of
/// the old session its peer still resends — its window was never acknowledged — are not
/// delivered to the new session (seq 0.. matched the new side's expectation, and an old
/// session's segments and screw commands were queued on the new clock). Once the peer
/// learns of the restart it drops them, and new messages flow.
#[test]
fn a_restarted_side_takes_nothing_sequenced_from_the_old_session() {
    let (mut a, _old, mut rng) = synced_pair(8);
    for i in 0..4 {
        a.link.send(&message(i)).unwrap();
    }
    let mut b = Side::new(3, 8);
    transmit(&mut a, &mut b, 10, CLEAN, &mut rng);
    b.receive_all(10);
    assert!(b.delivered.is_empty(), "{:?}", b.delivered);
    assert_eq!(b.link.counters().stale_frames, 4);
    for now in 11..40 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    assert_eq!(a.restarts, [4], "the old session's frames are gone with it");
    assert!(b.delivered.is_empty(), "{:?}", b.delivered);
    a.link.send(&message(9)).unwrap();
    for now in 40..45 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    assert_eq!(b.delivered, [message(9)]);
}

#[test]
fn nothing_sequenced_flows_before_the_peer_answers() {
    let mut a = link(1, 8);
    a.send(b"first").unwrap();
    let mut out = [0; MAX_WIRE_FRAME];
    let len = a.poll_transmit(0, &mut out).unwrap();
    let mut decoder = FrameDecoder::new();
    let mut frames = Vec::new();
    for &b in &out[..len] {
        if let Some(frame) = decoder.push(b) {
            let frame = frame.unwrap();
            frames.push((frame.header, frame.payload.to_vec()));
        }
    }
    assert_eq!(frames.len(), 1);
    assert!(frames[0].0.sync_request);
    assert_eq!(frames[0].1, 1u32.to_le_bytes());
    // Nothing more until the timeout, then the request again.
    assert_eq!(a.poll_transmit(TIMEOUT - 1, &mut out), None);
    assert!(a.poll_transmit(TIMEOUT, &mut out).is_some());
    assert!(!a.is_synced());
}

#[test]
fn a_lost_frame_is_naked_and_resent() {
    let (mut a, mut b, mut rng) = synced_pair(8);
    assert!(a.link.is_synced() && b.link.is_synced());
    for i in 0..4 {
        a.link.send(&message(i)).unwrap();
    }
    transmit_losing(&mut a, &mut b, 10, 1); // frame 1 of 4 lost on the way
    b.receive_all(10);
    assert_eq!(b.delivered, [message(0)]);
    assert_eq!(b.link.counters().out_of_order, 2);
    assert_eq!(b.link.counters().naks_sent, 0);
    transmit(&mut b, &mut a, 11, CLEAN, &mut rng);
    assert_eq!(
        b.link.counters().naks_sent,
        1,
        "one NAK for the gap, not one per frame"
    );
    a.receive_all(11);
    assert_eq!(a.link.counters().naks_received, 1);
    assert_eq!(a.link.unacknowledged(), 3, "frame 0 acknowledged, 1..3 not");
    transmit(&mut a, &mut b, 12, CLEAN, &mut rng);
    assert_eq!(
        a.link.counters().retransmits,
        1,
        "selective repeat resends 1 only: the NAK's bitmap says 2 and 3 arrived"
    );
    b.receive_all(12);
    assert_eq!(b.delivered, (0..4).map(message).collect::<Vec<_>>());
    transmit(&mut b, &mut a, 13, CLEAN, &mut rng);
    a.receive_all(13);
    assert_eq!(a.link.unacknowledged(), 0);
}

#[test]
fn a_frame_still_on_its_way_is_not_resent() {
    // 0..6 go out; 1 and 4 are lost. The receiver NAKs when 2 arrives, before 3..5 are
    // read: its bitmap holds only 2, so 1 (sent before 2) is resent and 3..5 (sent after)
    // are not: they are still on the line, not lost.
    let (mut a, mut b, mut rng) = synced_pair(8);
    for i in 0..6 {
        a.link.send(&message(i)).unwrap();
    }
    let mut out = [0; MAX_WIRE_FRAME];
    let mut frames = Vec::new();
    while let Some(len) = a.link.poll_transmit(10, &mut out) {
        frames.push(out[..len].to_vec());
    }
    assert_eq!(frames.len(), 6);
    b.inbox.extend(frames[0].iter().chain(&frames[2]).copied());
    b.receive_all(10);
    transmit(&mut b, &mut a, 10, CLEAN, &mut rng);
    a.receive_all(10);
    transmit(&mut a, &mut b, 11, CLEAN, &mut rng); // the resent 1, after 3..5 on the line
    assert_eq!(a.link.counters().retransmits, 1);
    let resent = std::mem::take(&mut b.inbox);
    b.inbox.extend(frames[3].iter().chain(&frames[5]).copied());
    b.inbox.extend(resent);
    b.receive_all(11);
    assert_eq!(
        b.delivered,
        (0..4).map(message).collect::<Vec<_>>(),
        "4 is missing"
    );
    // The NAK now holds 5 (sent after 4): 4 alone goes again.
    transmit(&mut b, &mut a, 12, CLEAN, &mut rng);
    a.receive_all(12);
    transmit(&mut a, &mut b, 13, CLEAN, &mut rng);
    assert_eq!(a.link.counters().retransmits, 2);
    b.receive_all(13);
    assert_eq!(b.delivered, (0..6).map(message).collect::<Vec<_>>());
}

#[test]
fn a_lost_frame_costs_one_frame_however_large_the_window() {
    // One frame lost in a full window of 32: one retransmission, not 31.
    let (mut a, mut b, mut rng) = synced_pair(32);
    for i in 0..32 {
        a.link.send(&message(i)).unwrap();
    }
    transmit_losing(&mut a, &mut b, 10, 3);
    for now in 10..14 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    assert_eq!(b.delivered, (0..32).map(message).collect::<Vec<_>>());
    assert_eq!(a.link.counters().retransmits, 1);
    assert_eq!(a.link.unacknowledged(), 0);
}

#[test]
fn a_lost_last_frame_is_resent_after_the_timeout() {
    let (mut a, mut b, _) = synced_pair(8);
    a.link.send(b"only").unwrap();
    let mut out = [0; MAX_WIRE_FRAME];
    assert!(a.link.poll_transmit(5, &mut out).is_some()); // lost
    assert_eq!(a.link.poll_transmit(5 + TIMEOUT - 1, &mut out), None);
    let len = a.link.poll_transmit(5 + TIMEOUT, &mut out).unwrap();
    b.inbox.extend(out[..len].iter().copied());
    b.receive_all(30);
    assert_eq!(b.delivered, [b"only".to_vec()]);
    assert_eq!(a.link.counters().retransmits, 1);
}

#[test]
fn window_bounds_unacknowledged_messages() {
    let mut a = link(1, 4);
    for i in 0..4 {
        a.send(&[i]).unwrap();
    }
    assert_eq!(a.send(&[9]), Err(LinkError::WindowFull { window: 4 }));
    assert_eq!(
        a.send(&[0; MAX_PAYLOAD + 1]),
        Err(LinkError::Frame(FrameError::PayloadTooLong {
            len: MAX_PAYLOAD + 1
        }))
    );
}

#[test]
fn a_restarted_peer_is_reported_and_its_lost_frames_counted() {
    let (mut a, _, _) = exchange(10, 8, CLEAN, 1);
    // a sends three more that b's old session never acknowledges.
    let mut rng = Rng(3);
    for i in 0..3 {
        a.link.send(&message(100 + i)).unwrap();
    }
    let mut out = [0; MAX_WIRE_FRAME];
    while a.link.poll_transmit(500, &mut out).is_some() {}
    // b restarts: a new link with a new nonce.
    let mut b = Side::new(0xB0B2, 8);
    for now in 501..510 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    assert_eq!(a.restarts, [3]);
    assert_eq!(a.link.counters().peer_restarts, 1);
    assert!(b.link.is_synced());
    // And the new session works both ways.
    a.link.send(b"after").unwrap();
    b.link.send(b"back").unwrap();
    for now in 510..515 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    assert_eq!(b.delivered, [b"after".to_vec()]);
    assert_eq!(a.delivered.last(), Some(&b"back".to_vec()));
}

#[test]
fn a_repeated_sync_request_does_not_reset_the_session() {
    let (mut a, mut b, _) = exchange(5, 8, CLEAN, 1);
    // a's reply was lost, say, and b repeats its request (same nonce).
    let mut out = [0; MAX_WIRE_FRAME];
    let header = FrameHeader {
        seq: 0,
        sync_request: true,
        ..FrameHeader::default()
    };
    let len = encode_frame(&header, &0xB0Bu32.to_le_bytes(), &mut out).unwrap();
    a.inbox.extend(out[..len].iter().copied());
    a.receive_all(100);
    assert!(a.restarts.is_empty());
    a.link.send(b"still in step").unwrap();
    let mut rng = Rng(5);
    for now in 100..105 {
        round(&mut a, &mut b, now, CLEAN, &mut rng);
    }
    assert_eq!(b.delivered.last(), Some(&b"still in step".to_vec()));
    assert_eq!(b.delivered.len(), 6);
}

proptest! {
    // A fixed seed: a corrupted frame can, rarely (CRC-16: about 1 in 65,536), pass as
    // valid; this protocol does not claim more, so the test must not depend on the luck of
    // a random seed.
    #![proptest_config(ProptestConfig {
        cases: 48,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x5EED),
        ..ProptestConfig::default()
    })]

    /// Whatever the channel does (drop, corrupt, duplicate frames at up to 20 % each), both
    /// directions deliver every message exactly once and in order.
    #[test]
    fn faulty_channel_delivers_exactly_once_in_order(
        seed in any::<u64>(),
        window in 1usize..=32,
        drop in 0u32..200,
        corrupt in 0u32..200,
        duplicate in 0u32..200,
    ) {
        let faults = Faults {
            drop_per_mille: drop,
            corrupt_per_mille: corrupt,
            duplicate_per_mille: duplicate,
        };
        let (a, b, _) = exchange(300, window, faults, seed);
        prop_assert_eq!(b.delivered, (0..300).map(message).collect::<Vec<_>>());
        prop_assert_eq!(a.delivered, (0..300).map(|i| message(1_000_000 + i)).collect::<Vec<_>>());
        prop_assert!(a.restarts.is_empty() && b.restarts.is_empty());
    }
}

#[test]
fn a_zero_timeout_does_not_make_every_poll_send_again() {
    for timeout in [0, 1, 7] {
        let mut l: Link<32> = Link::new(LinkOptions {
            window: 4,
            retransmit_timeout: timeout,
            nonce: 7,
        });
        let mut out = [0u8; MAX_WIRE_FRAME];
        assert!(
            l.poll_transmit(100, &mut out).is_some(),
            "the first SYNC_REQUEST"
        );
        assert_eq!(l.poll_transmit(100, &mut out), None, "timeout {timeout}");
        assert_eq!(l.poll_transmit(107, &mut out), None, "timeout {timeout}");
        assert!(l.poll_transmit(108, &mut out).is_some(), "repeated after 8");
    }
}
