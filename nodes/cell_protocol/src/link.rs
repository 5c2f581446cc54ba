//! The link: a reliable, ordered message stream over frames that may be lost, corrupted or
//! duplicated (go-back-N).
//!
//! # Sequenced messages
//!
//! Each side numbers its sequenced frames (mod 256) and keeps every one it sent until the
//! peer acknowledges it. Every frame either side sends carries `ack`, the next sequence number
//! it expects: a cumulative acknowledgement of everything before. The receiver delivers a
//! sequenced frame only if it is exactly the one expected; a frame from the future means one
//! was lost, so the receiver sends one NAK (a frame with the NAK flag and `ack` = the missing
//! one) and the sender goes back and resends from there. A lost NAK or a lost last frame is
//! covered by the retransmit timeout on the oldest unacknowledged frame. At most `window`
//! frames are unacknowledged (≤ 127, so old and new sequence numbers never look alike).
//!
//! # Sessions
//!
//! A link starts unsynchronised: it sends a SYNC_REQUEST carrying a random nonce (repeated
//! each timeout) and no sequenced frame until a SYNC_REPLY echoes that nonce. The reply's
//! `seq` tells it where the peer's numbering stands. A SYNC_REQUEST with a nonce it has not
//! seen from the peer means the peer (re)started: it resets its receiving side to the
//! request's `seq`, drops what it had sent and the old peer never acknowledged (reported as
//! [`Received::PeerRestarted`]: a host must treat a restarted MCU as a fault, since the MCU's
//! queue is gone), and replies. A repeated request (same nonce) only repeats the reply.
//!
//! # Time
//!
//! The link does no I/O and reads no clock: the caller passes `now` in any monotonic unit
//! (microseconds on the host, timer ticks on the MCU) and [`LinkOptions::retransmit_timeout`]
//! is in the same unit.

use crate::frame::{encode_frame, Frame, FrameError, FrameHeader};
use crate::{MAX_PAYLOAD, MAX_WIRE_FRAME};

/// How a link behaves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinkOptions {
    /// Most sequenced frames unacknowledged at once (1..=127, and at most the link's `W`).
    pub window: usize,
    /// After this long without an acknowledgement of the oldest frame, resend from it (and
    /// repeat an unanswered SYNC_REQUEST). In the caller's time unit.
    pub retransmit_timeout: u64,
    /// This session's nonce: random, so that a restart is told from a repeated request.
    pub nonce: u32,
}

/// Why a message could not be sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LinkError {
    #[error("send window full ({window} frames unacknowledged)")]
    WindowFull { window: usize },
    #[error(transparent)]
    Frame(#[from] FrameError),
}

/// What a received frame means to the application.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Received<'a> {
    /// A sequenced message, in order, for the first time.
    Message(&'a [u8]),
    /// An unsequenced (best-effort) message.
    Unsequenced(&'a [u8]),
    /// Nothing for the application (an acknowledgement, a duplicate, a frame out of order,
    /// session management).
    Nothing,
    /// The peer started a new session: `lost` sequenced frames sent to the old session were
    /// never acknowledged and have been dropped.
    PeerRestarted { lost: usize },
}

/// What the link has done, for status reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkCounters {
    /// Sequenced frames sent again (after a NAK or a timeout).
    pub retransmits: u32,
    pub naks_sent: u32,
    pub naks_received: u32,
    /// Sequenced frames received again (already delivered).
    pub duplicates: u32,
    /// Sequenced frames received ahead of a missing one (dropped, NAKed).
    pub out_of_order: u32,
    pub peer_restarts: u32,
}

/// One end of a link, holding up to `W` unacknowledged payloads (`W` ≤ 127).
#[derive(Clone, Debug)]
pub struct Link<const W: usize> {
    options: LinkOptions,
    /// Our SYNC_REQUEST was answered: the peer knows our numbering.
    synced: bool,
    last_sync_request_at: Option<u64>,
    peer_nonce: Option<u32>,
    sync_reply_owed: bool,

    slots: [[u8; MAX_PAYLOAD]; W],
    slot_lens: [u8; W],
    /// Slot of the oldest unacknowledged frame.
    head: usize,
    /// Frames queued (sent or not) and not acknowledged.
    queued: usize,
    /// Sequence number of the frame in `head`.
    base_seq: u8,
    /// Frames from `head` on that went out at least once.
    transmitted: usize,
    /// Offset from `head` of the next frame to (re)transmit.
    cursor: usize,
    /// When the oldest unacknowledged frame last went out (or the last acknowledgement came).
    timer_start: u64,

    /// Sequence number expected next from the peer.
    expected: u8,
    ack_owed: bool,
    nak_owed: bool,
    /// A NAK for the current gap went out: do not send another until progress.
    nak_outstanding: bool,

    counters: LinkCounters,
}

impl<const W: usize> Link<W> {
    /// A link that has not yet met its peer. Panics if `options.window` is 0, above `W` or
    /// above 127 (a programming error, not an input).
    pub fn new(options: LinkOptions) -> Link<W> {
        assert!(
            (1..=W.min(127)).contains(&options.window),
            "link window {} outside 1..={}",
            options.window,
            W.min(127)
        );
        Link {
            options,
            synced: false,
            last_sync_request_at: None,
            peer_nonce: None,
            sync_reply_owed: false,
            slots: [[0; MAX_PAYLOAD]; W],
            slot_lens: [0; W],
            head: 0,
            queued: 0,
            base_seq: 0,
            transmitted: 0,
            cursor: 0,
            timer_start: 0,
            expected: 0,
            ack_owed: false,
            nak_owed: false,
            nak_outstanding: false,
            counters: LinkCounters::default(),
        }
    }

    pub fn options(&self) -> &LinkOptions {
        &self.options
    }

    /// The peer answered our session start: sequenced frames flow.
    pub fn is_synced(&self) -> bool {
        self.synced
    }

    pub fn counters(&self) -> LinkCounters {
        self.counters
    }

    /// Sequenced messages queued and not yet acknowledged.
    pub fn unacknowledged(&self) -> usize {
        self.queued
    }

    /// Room for another sequenced message.
    pub fn can_send(&self) -> bool {
        self.queued < self.options.window
    }

    /// Queue a sequenced message; it goes out from [`Link::poll_transmit`].
    pub fn send(&mut self, payload: &[u8]) -> Result<(), LinkError> {
        if payload.len() > MAX_PAYLOAD {
            return Err(FrameError::PayloadTooLong { len: payload.len() }.into());
        }
        if !self.can_send() {
            return Err(LinkError::WindowFull {
                window: self.options.window,
            });
        }
        let slot = (self.head + self.queued) % W;
        self.slots[slot][..payload.len()].copy_from_slice(payload);
        self.slot_lens[slot] = payload.len() as u8;
        self.queued += 1;
        Ok(())
    }

    /// Encode an unsequenced (best-effort) message into `out` now; it also carries our ack.
    pub fn encode_unsequenced(
        &mut self,
        payload: &[u8],
        out: &mut [u8; MAX_WIRE_FRAME],
    ) -> Result<usize, LinkError> {
        let header = self.header(self.next_seq(), false);
        Ok(encode_frame(&header, payload, out)?)
    }

    /// The next bytes to write, if any: a session reply or request, a (re)transmission, or a
    /// bare acknowledgement. Call until `None` whenever something was received or sent, and
    /// periodically (at least every retransmit timeout) so that timeouts fire.
    pub fn poll_transmit(&mut self, now: u64, out: &mut [u8; MAX_WIRE_FRAME]) -> Option<usize> {
        if self.sync_reply_owed {
            self.sync_reply_owed = false;
            let mut header = self.header(self.base_seq, false);
            header.sync_reply = true;
            let mut payload = [0u8; 8];
            payload[..4].copy_from_slice(&self.peer_nonce.unwrap_or(0).to_le_bytes());
            payload[4..].copy_from_slice(&self.options.nonce.to_le_bytes());
            return self.encode(&header, &payload, out);
        }
        if !self.synced {
            let due = self
                .last_sync_request_at
                .is_none_or(|at| now.saturating_sub(at) >= self.options.retransmit_timeout);
            if due {
                self.last_sync_request_at = Some(now);
                let mut header = self.header(self.base_seq, false);
                header.sync_request = true;
                return self.encode(&header, &self.options.nonce.to_le_bytes(), out);
            }
        } else {
            if self.transmitted > 0
                && now.saturating_sub(self.timer_start) >= self.options.retransmit_timeout
            {
                self.cursor = 0; // timeout: go back to the oldest unacknowledged frame
            }
            if self.cursor < self.queued {
                let offset = self.cursor;
                self.cursor += 1;
                if offset < self.transmitted {
                    self.counters.retransmits += 1;
                } else {
                    self.transmitted += 1;
                }
                if offset == 0 {
                    self.timer_start = now;
                }
                let slot = (self.head + offset) % W;
                let seq = self.base_seq.wrapping_add(offset as u8);
                let header = self.header(seq, true);
                let payload = self.slots[slot];
                let len = self.slot_lens[slot] as usize;
                return self.encode(&header, &payload[..len], out);
            }
        }
        if self.ack_owed || self.nak_owed {
            let header = self.header(self.next_seq(), false);
            return self.encode(&header, &[], out);
        }
        None
    }

    /// Take a frame from the decoder.
    pub fn receive<'a>(&mut self, frame: &Frame<'a>, now: u64) -> Received<'a> {
        let header = &frame.header;
        if header.sync_request {
            return self.on_sync_request(frame);
        }
        if header.sync_reply {
            self.on_sync_reply(frame);
            return Received::Nothing;
        }
        self.on_ack(header.ack, header.nak, now);
        if !header.sequenced {
            return if frame.payload.is_empty() {
                Received::Nothing
            } else {
                Received::Unsequenced(frame.payload)
            };
        }
        let ahead = header.seq.wrapping_sub(self.expected);
        if ahead == 0 {
            self.expected = self.expected.wrapping_add(1);
            self.ack_owed = true;
            self.nak_outstanding = false;
            Received::Message(frame.payload)
        } else if ahead < 128 {
            self.counters.out_of_order += 1;
            if !self.nak_outstanding {
                self.nak_outstanding = true;
                self.nak_owed = true;
            }
            Received::Nothing
        } else {
            // Behind: our acknowledgement was lost; repeat it so the peer moves on.
            self.counters.duplicates += 1;
            self.ack_owed = true;
            Received::Nothing
        }
    }

    /// Take only the acknowledgement a frame carries, not its message: for a receiver that
    /// cannot accept another message now. The peer resends the message later, as if it had
    /// been lost.
    pub fn receive_ack_only(&mut self, frame: &Frame, now: u64) {
        let header = &frame.header;
        if !header.sync_request && !header.sync_reply {
            self.on_ack(header.ack, header.nak, now);
        }
    }

    fn on_sync_request<'a>(&mut self, frame: &Frame<'a>) -> Received<'a> {
        let Ok(nonce) = <[u8; 4]>::try_from(frame.payload).map(u32::from_le_bytes) else {
            return Received::Nothing; // not a request this protocol version makes
        };
        self.sync_reply_owed = true;
        if self.peer_nonce == Some(nonce) {
            return Received::Nothing; // our reply was lost: only repeat it
        }
        let restarted = self.peer_nonce.is_some();
        self.peer_nonce = Some(nonce);
        self.expected = frame.header.seq;
        self.ack_owed = false;
        self.nak_owed = false;
        self.nak_outstanding = false;
        // What the old session never acknowledged is gone with it.
        let lost = self.transmitted;
        self.head = (self.head + lost) % W;
        self.queued -= lost;
        self.base_seq = self.base_seq.wrapping_add(lost as u8);
        self.transmitted = 0;
        self.cursor = 0;
        if restarted {
            self.counters.peer_restarts += 1;
            Received::PeerRestarted { lost }
        } else {
            Received::Nothing
        }
    }

    fn on_sync_reply(&mut self, frame: &Frame) {
        if self.synced || frame.payload.len() != 8 {
            return; // a repeated reply, or not one this protocol version makes
        }
        let echoed = u32::from_le_bytes(frame.payload[..4].try_into().expect("4 bytes"));
        let peer = u32::from_le_bytes(frame.payload[4..].try_into().expect("4 bytes"));
        if echoed != self.options.nonce {
            return; // answers a request of an earlier session of ours
        }
        self.synced = true;
        if self.peer_nonce != Some(peer) {
            self.peer_nonce = Some(peer);
            self.expected = frame.header.seq;
        }
    }

    fn on_ack(&mut self, ack: u8, nak: bool, now: u64) {
        let acked = ack.wrapping_sub(self.base_seq) as usize;
        if acked > self.transmitted {
            return; // acknowledges nothing we sent: stale or from another session
        }
        if acked > 0 {
            self.head = (self.head + acked) % W;
            self.queued -= acked;
            self.transmitted -= acked;
            self.cursor = self.cursor.saturating_sub(acked);
            self.base_seq = ack;
            self.timer_start = now;
        }
        if nak && self.transmitted > 0 {
            self.counters.naks_received += 1;
            self.cursor = 0;
        }
    }

    fn next_seq(&self) -> u8 {
        self.base_seq.wrapping_add(self.queued as u8)
    }

    /// A header carrying our acknowledgement (and a NAK if one is owed).
    fn header(&mut self, seq: u8, sequenced: bool) -> FrameHeader {
        let nak = core::mem::take(&mut self.nak_owed);
        if nak {
            self.counters.naks_sent += 1;
        }
        self.ack_owed = false;
        FrameHeader {
            seq,
            ack: self.expected,
            sequenced,
            nak,
            sync_request: false,
            sync_reply: false,
        }
    }

    fn encode(
        &mut self,
        header: &FrameHeader,
        payload: &[u8],
        out: &mut [u8; MAX_WIRE_FRAME],
    ) -> Option<usize> {
        Some(encode_frame(header, payload, out).expect("payloads are checked when queued"))
    }
}

#[cfg(test)]
mod tests;
