//! The host's end of the wire: typed messages in and out, bytes on the line.

use cell_protocol::message::{mcu_messages, HostMessage, McuMessage};
use cell_protocol::{
    FrameDecoder, Link, LinkError, LinkOptions, Received, MAX_PAYLOAD, MAX_WIRE_FRAME,
};

/// Sequenced frames the host keeps unacknowledged at most.
pub const HOST_WINDOW: usize = 32;

/// What arrived from the MCU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FromMcu {
    Message(McuMessage),
    /// A payload that is no MCU message (counted by the caller; the link delivered it).
    Undecodable,
    /// The MCU started a new session: it was reset or power-cycled, its queue and clock are
    /// gone, and `lost` messages sent to it were never acknowledged.
    Restarted {
        lost: usize,
    },
}

/// The host's protocol endpoint. Times are host microseconds.
///
/// Sequenced messages are packed: each goes into the payload being filled, and the payload
/// becomes a frame when the next message does not fit, when a second message would ask for a
/// reply (the MCU keeps room for one reply per frame), or when the line is next polled. With
/// [`HostEndpoint::pack_for`], a payload of only continuing segments and screw commands
/// (which go out a horizon ahead of their time) waits up to that long for more to fill it;
/// anything else (a clock query, whose round trip is measured; a hold; a schedule's first
/// segment) goes at the next poll. A print's segments and screw commands, 8–19 bytes each in
/// their compact forms, travel three to six to a frame.
#[derive(Clone, Debug)]
pub struct HostEndpoint {
    link: Link<HOST_WINDOW>,
    decoder: FrameDecoder,
    pending: [u8; MAX_PAYLOAD],
    pending_len: usize,
    pending_asks_reply: bool,
    /// The payload holds a message that goes at the next poll.
    pending_urgent: bool,
    /// When a poll first saw the payload being filled (host µs).
    pending_since_us: Option<u64>,
    /// How long a payload of continuing segments and screw commands may wait to be filled.
    pack_us: u64,
    sent: SentBytes,
}

/// What the host's sequenced messages cost, by what they carry (message bytes, before
/// framing): where a print's bytes on the line go.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SentBytes {
    /// QUEUE_SEGMENT and NEXT_SEGMENT.
    pub segments: u64,
    /// SCREW and SCREW_NEXT.
    pub screw: u64,
    /// Everything else (clock queries, holds, configuration, queries).
    pub control: u64,
    /// Sequenced frames made (each first copy; resends are the link's counters).
    pub frames: u64,
}

impl HostEndpoint {
    /// `nonce`: random per session, so that the MCU tells a restarted host from a repeat.
    pub fn new(retransmit_timeout_us: u64, nonce: u32) -> HostEndpoint {
        HostEndpoint {
            link: Link::new(LinkOptions {
                window: HOST_WINDOW,
                retransmit_timeout: retransmit_timeout_us,
                nonce,
            }),
            decoder: FrameDecoder::new(),
            pending: [0; MAX_PAYLOAD],
            pending_len: 0,
            pending_asks_reply: false,
            pending_urgent: false,
            pending_since_us: None,
            pack_us: 0,
            sent: SentBytes::default(),
        }
    }

    /// Let a payload of continuing segments and screw commands wait up to `pack_us` for more
    /// to fill its frame (0, the default: every poll writes what was packed). Each frame
    /// costs 8 bytes on the line (header, CRC, COBS, delimiter) whatever it carries.
    pub fn pack_for(mut self, pack_us: u64) -> HostEndpoint {
        self.pack_us = pack_us;
        self
    }

    /// What was packed goes at the next poll, whatever may wait: it is needed soon (the
    /// plan ran short of its horizon), so packing must not take from its margin.
    pub fn flush_soon(&mut self) {
        if self.pending_len > 0 {
            self.pending_urgent = true;
        }
    }

    /// Message bytes and frames sent so far.
    pub fn sent_bytes(&self) -> SentBytes {
        self.sent
    }

    pub fn link(&self) -> &Link<HOST_WINDOW> {
        &self.link
    }

    pub fn decoder(&self) -> &FrameDecoder {
        &self.decoder
    }

    /// Room for another sequenced message: the payload being filled can become a frame.
    pub fn can_send(&self) -> bool {
        self.link.can_send()
    }

    /// Sequenced frames not yet acknowledged, counting the payload being filled as one.
    pub fn unacknowledged(&self) -> usize {
        self.link.unacknowledged() + usize::from(self.pending_len > 0)
    }

    /// Queue a sequenced message (every host message but the emergency stop). Call only when
    /// [`HostEndpoint::can_send`].
    pub fn send(&mut self, message: &HostMessage) -> Result<(), LinkError> {
        let mut payload = [0; MAX_PAYLOAD];
        let len = message.encode(&mut payload);
        let asks_reply = message.asks_reply();
        let (class, may_wait) = match message {
            HostMessage::NextSegment(_) => (&mut self.sent.segments, true),
            HostMessage::QueueSegment(_) => (&mut self.sent.segments, false),
            HostMessage::Screw(_) | HostMessage::ScrewNext(_) => (&mut self.sent.screw, true),
            _ => (&mut self.sent.control, false),
        };
        *class += len as u64;
        if self.pending_len + len > MAX_PAYLOAD || (asks_reply && self.pending_asks_reply) {
            self.seal()?;
        }
        self.pending[self.pending_len..self.pending_len + len].copy_from_slice(&payload[..len]);
        self.pending_len += len;
        self.pending_asks_reply |= asks_reply;
        self.pending_urgent |= !may_wait;
        Ok(())
    }

    /// The payload being filled becomes a frame in the link's window.
    fn seal(&mut self) -> Result<(), LinkError> {
        if self.pending_len > 0 {
            self.link.send(&self.pending[..self.pending_len])?;
            self.sent.frames += 1;
            self.pending_len = 0;
            self.pending_asks_reply = false;
            self.pending_urgent = false;
            self.pending_since_us = None;
        }
        Ok(())
    }

    /// Encode an unsequenced message (the emergency stop) for sending at once.
    pub fn encode_now(
        &mut self,
        message: &HostMessage,
        out: &mut [u8; MAX_WIRE_FRAME],
    ) -> Result<usize, LinkError> {
        let mut payload = [0; MAX_PAYLOAD];
        let len = message.encode(&mut payload);
        self.link.encode_unsequenced(&payload[..len], out)
    }

    /// Bytes from the line at `now_us`; what they carried goes to `on_message`.
    pub fn receive(&mut self, bytes: &[u8], now_us: u64, on_message: &mut impl FnMut(FromMcu)) {
        for &byte in bytes {
            let Some(Ok(frame)) = self.decoder.push(byte) else {
                continue;
            };
            match self.link.receive(&frame, now_us) {
                Received::Message(p) | Received::Unsequenced(p) => decode_all(p, on_message),
                Received::PeerRestarted { lost } => on_message(FromMcu::Restarted { lost }),
                Received::Nothing => {}
            }
            // Messages held behind a gap this frame filled.
            while let Some(p) = self.link.next_buffered() {
                decode_all(p, on_message);
            }
        }
    }

    /// The next bytes to write at `now_us`, if any; call until `None`. What was packed so far
    /// goes out now (as soon as the window has room for it), unless it may wait to be filled
    /// ([`HostEndpoint::pack_for`]).
    pub fn poll_transmit(&mut self, now_us: u64, out: &mut [u8; MAX_WIRE_FRAME]) -> Option<usize> {
        if self.pending_len > 0 {
            let since = *self.pending_since_us.get_or_insert(now_us);
            let waited = now_us.saturating_sub(since) >= self.pack_us;
            if (self.pending_urgent || waited) && self.link.can_send() {
                // Cannot fail: the window has room.
                let _ = self.seal();
            }
        }
        self.link.poll_transmit(now_us, out)
    }
}

/// Every message of a payload (the MCU sends one per frame, but may send more).
fn decode_all(payload: &[u8], on_message: &mut impl FnMut(FromMcu)) {
    for message in mcu_messages(payload) {
        on_message(match message {
            Ok(m) => FromMcu::Message(m),
            Err(_) => FromMcu::Undecodable,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cell_protocol::message::{host_messages, ScrewNext, ScrewStart};

    /// The MCU's side of the line: a bare link that records every payload it delivers.
    struct Peer {
        link: Link<16>,
        decoder: FrameDecoder,
        /// Each delivered payload's messages, with the time it came.
        payloads: Vec<(u64, Vec<HostMessage>)>,
    }

    impl Peer {
        fn new() -> Peer {
            Peer {
                link: Link::new(LinkOptions {
                    window: 16,
                    retransmit_timeout: 20_000,
                    nonce: 7,
                }),
                decoder: FrameDecoder::new(),
                payloads: Vec::new(),
            }
        }

        /// Everything each side has to write at `now` reaches the other.
        fn exchange(&mut self, host: &mut HostEndpoint, now: u64) {
            let mut out = [0; MAX_WIRE_FRAME];
            while let Some(len) = host.poll_transmit(now, &mut out) {
                for &byte in &out[..len] {
                    let Some(Ok(frame)) = self.decoder.push(byte) else {
                        continue;
                    };
                    if let Received::Message(p) = self.link.receive(&frame, now) {
                        let messages = host_messages(p).map(Result::unwrap).collect();
                        self.payloads.push((now, messages));
                    }
                }
            }
            while let Some(len) = self.link.poll_transmit(now, &mut out) {
                host.receive(&out[..len], now, &mut |_| {});
            }
        }
    }

    fn screw_next(change: i32) -> HostMessage {
        HostMessage::ScrewNext(ScrewNext {
            start: ScrewStart::Step(20_000),
            ramp_ticks: Some(2_000),
            target_change_millirpm: change,
            pin_open: true,
        })
    }

    /// Packing: continuing messages wait up to `pack_for` to fill a frame, a full payload
    /// goes at once, and a hold goes at the next write, taking the waiting ones along in
    /// order.
    #[test]
    fn continuing_messages_wait_to_fill_a_frame_and_a_hold_takes_them_along() {
        let mut host = HostEndpoint::new(20_000, 1).pack_for(100_000);
        let mut peer = Peer::new();
        for now in [0, 1_000, 2_000] {
            peer.exchange(&mut host, now); // the session starts
        }
        assert!(host.link().is_synced());
        // Two 8-byte commands wait for 100 ms, then go in one frame.
        host.send(&screw_next(1)).unwrap();
        host.send(&screw_next(2)).unwrap();
        peer.exchange(&mut host, 10_000);
        peer.exchange(&mut host, 109_999);
        assert!(peer.payloads.is_empty(), "nothing before its time");
        peer.exchange(&mut host, 110_000);
        assert_eq!(
            peer.payloads,
            [(110_000, vec![screw_next(1), screw_next(2)])]
        );
        // Eight fill a payload (64 bytes); the ninth seals it: the full frame goes at the
        // next write, the ninth waits.
        for change in 0..9 {
            host.send(&screw_next(change)).unwrap();
        }
        peer.exchange(&mut host, 120_000);
        assert_eq!(peer.payloads.len(), 2);
        assert_eq!(
            peer.payloads[1].1,
            (0..8).map(screw_next).collect::<Vec<_>>()
        );
        // A hold does not wait, and goes after what was waiting.
        let hold = HostMessage::FeedHold { rate_q32: 5 };
        host.send(&hold).unwrap();
        peer.exchange(&mut host, 121_000);
        assert_eq!(peer.payloads[2], (121_000, vec![screw_next(8), hold]));
        let sent = host.sent_bytes();
        assert_eq!((sent.screw, sent.control, sent.frames), (11 * 8, 5, 3));
        // What is needed soon does not wait.
        host.send(&screw_next(9)).unwrap();
        host.flush_soon();
        peer.exchange(&mut host, 122_000);
        assert_eq!(peer.payloads[3], (122_000, vec![screw_next(9)]));
    }

    /// Without packing, every write sends what was packed.
    #[test]
    fn without_packing_every_write_sends_what_there_is() {
        let mut host = HostEndpoint::new(20_000, 1);
        let mut peer = Peer::new();
        for now in [0, 1_000, 2_000] {
            peer.exchange(&mut host, now);
        }
        host.send(&screw_next(1)).unwrap();
        peer.exchange(&mut host, 3_000);
        host.send(&screw_next(2)).unwrap();
        host.send(&screw_next(3)).unwrap();
        peer.exchange(&mut host, 4_000);
        assert_eq!(
            peer.payloads,
            [
                (3_000, vec![screw_next(1)]),
                (4_000, vec![screw_next(2), screw_next(3)])
            ]
        );
    }
}
