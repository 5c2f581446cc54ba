//! The link: a reliable, ordered message stream over frames that may be lost, corrupted or
//! duplicated (selective repeat).
//!
//! # Sequenced messages
//!
//! Each side numbers its sequenced frames (mod 256) and keeps every one it sent until the
//! peer acknowledges it. Every frame either side sends carries `ack`, the next sequence number
//! it expects: a cumulative acknowledgement of everything before. A receiver keeps frames that
//! arrive ahead of a missing one (up to `W` ahead) and delivers them, in order, once the gap
//! is filled ([`Link::next_buffered`]). While it holds frames behind a gap it answers every
//! sequenced frame with a NAK: a bare frame whose payload is a bitmap of the frames it holds
//! beyond `ack` (a selective acknowledgement). The sender resends only what the bitmap shows
//! missing, and only a copy that went out *before* a frame the receiver holds: a serial line
//! never reorders, so such a copy is lost, while a later one may still be on its way. A lost
//! NAK or a lost last frame is covered by the retransmit timeout on the oldest unacknowledged
//! frame, which resends every frame not selectively acknowledged.
//!
//! Go-back-N (protocol version 1) resent the whole window after each loss, which on a line
//! that damages every second frame delivered about one frame per round trip; selective
//! repeat costs each loss one frame.
//!
//! At most `window` frames are unacknowledged (≤ 127, so old and new sequence numbers never
//! look alike).
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
    /// After this long without an acknowledgement of the oldest frame, resend what the peer
    /// does not hold (and repeat an unanswered SYNC_REQUEST). In the caller's time unit. This
    /// is the longest wait and the first; once round trips are measured the link waits the
    /// measured round trip plus four deviations (RFC 6298), not less than an eighth of this.
    /// At least 8 units (less is taken as 8): a wait of 0 would make every poll due again.
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
    /// Retransmit timeouts that fired (each resends what the peer does not hold).
    pub timeouts: u32,
    /// Sequenced frames received again (already delivered).
    pub duplicates: u32,
    /// Sequenced frames received ahead of a missing one (held if within the window, NAKed).
    pub out_of_order: u32,
    pub peer_restarts: u32,
    /// Sequenced frames that came before any peer session was known (an old session's).
    pub stale_frames: u32,
}

/// Most bytes of a selective-acknowledgement bitmap: one bit for each of the 127 frames a
/// window can hold beyond the acknowledged one.
pub const MAX_SACK_BYTES: usize = 16;

/// One end of a link, holding up to `W` unacknowledged payloads and up to `W` received ahead
/// of a missing one (`W` ≤ 127).
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
    /// Per slot: waiting to go out (first time or again).
    slot_pending: [bool; W],
    /// Per slot: the peer holds it (selectively acknowledged); never resent.
    slot_sacked: [bool; W],
    /// Per slot: the transmission count when it last went out (0: never).
    slot_sent_as: [u64; W],
    /// Per slot: when it first went out, and how often (a round trip is measured only on a
    /// frame sent once: Karn's rule).
    slot_first_sent_at: [u64; W],
    slot_last_sent_at: [u64; W],
    slot_copies: [u8; W],
    /// Smoothed round trip and its mean deviation, once measured.
    smoothed_rtt: Option<u64>,
    rtt_deviation: u64,
    /// A timeout fired since the last progress: the wait is doubled (once).
    backed_off: bool,
    /// Sequenced transmissions so far: orders copies on the (never reordering) line.
    transmissions: u64,
    /// Slot of the oldest unacknowledged frame.
    head: usize,
    /// Frames queued (sent or not) and not acknowledged.
    queued: usize,
    /// Sequence number of the frame in `head`.
    base_seq: u8,
    /// Frames from `head` on that went out at least once (always a prefix: first
    /// transmissions go in order).
    transmitted: usize,
    /// When the oldest unacknowledged frame last went out (or the last acknowledgement came).
    timer_start: u64,

    /// Sequence number expected next from the peer.
    expected: u8,
    /// Frames received ahead of `expected`: slot `(rx_head + k) % W` holds `expected + k`.
    rx_slots: [[u8; MAX_PAYLOAD]; W],
    rx_lens: [u8; W],
    rx_present: [bool; W],
    rx_head: usize,
    ack_owed: bool,
    /// Frames are held behind a gap and the sender has not been told since the last frame.
    nak_owed: bool,
    /// When the last NAK went out: one is repeated while the gap lasts (it may be lost too).
    last_nak_at: u64,

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
        let options = LinkOptions {
            retransmit_timeout: options.retransmit_timeout.max(8),
            ..options
        };
        Link {
            options,
            synced: false,
            last_sync_request_at: None,
            peer_nonce: None,
            sync_reply_owed: false,
            slots: [[0; MAX_PAYLOAD]; W],
            slot_lens: [0; W],
            slot_pending: [false; W],
            slot_sacked: [false; W],
            slot_sent_as: [0; W],
            slot_first_sent_at: [0; W],
            slot_last_sent_at: [0; W],
            slot_copies: [0; W],
            smoothed_rtt: None,
            rtt_deviation: 0,
            backed_off: false,
            transmissions: 0,
            head: 0,
            queued: 0,
            base_seq: 0,
            transmitted: 0,
            timer_start: 0,
            expected: 0,
            rx_slots: [[0; MAX_PAYLOAD]; W],
            rx_lens: [0; W],
            rx_present: [false; W],
            rx_head: 0,
            ack_owed: false,
            nak_owed: false,
            last_nak_at: 0,
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

    /// Sequence number of the oldest unacknowledged (or the next) sequenced frame we send.
    pub fn oldest_unacknowledged_seq(&self) -> u8 {
        self.base_seq
    }

    /// Sequence number we expect next from the peer.
    pub fn expected_seq(&self) -> u8 {
        self.expected
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
        self.slot_pending[slot] = true;
        self.slot_sacked[slot] = false;
        self.slot_sent_as[slot] = 0;
        self.slot_copies[slot] = 0;
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

    /// The next bytes to write, if any: a session reply or request, a selective
    /// acknowledgement, a (re)transmission, or a bare acknowledgement. Call until `None`
    /// whenever something was received or sent, and periodically (at least every retransmit
    /// timeout) so that timeouts fire.
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
        let gap_open = self.rx_present.iter().any(|&p| p);
        if gap_open && now.saturating_sub(self.last_nak_at) >= self.options.retransmit_timeout / 8 {
            self.nak_owed = true; // the gap lasts: our last NAK, or the resend, was lost
        }
        if self.nak_owed {
            // Ahead of our own data: it is small, and the peer's window waits on it.
            self.nak_owed = false;
            self.last_nak_at = now;
            let mut bitmap = [0u8; MAX_SACK_BYTES];
            let len = self.sack_bitmap(&mut bitmap);
            if len > 0 {
                self.counters.naks_sent += 1;
                let mut header = self.header(self.next_seq(), false);
                header.nak = true;
                return self.encode(&header, &bitmap[..len], out);
            }
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
                && now.saturating_sub(self.timer_start) >= self.retransmit_timeout()
            {
                // Timeout: resend everything sent that the peer does not hold.
                self.counters.timeouts += 1;
                self.backed_off = true;
                for offset in 0..self.transmitted {
                    let slot = (self.head + offset) % W;
                    if !self.slot_sacked[slot] {
                        self.slot_pending[slot] = true;
                    }
                }
                self.timer_start = now;
            }
            if let Some(offset) = (0..self.queued).find(|&o| self.slot_pending[(self.head + o) % W])
            {
                let slot = (self.head + offset) % W;
                if offset < self.transmitted {
                    self.counters.retransmits += 1;
                } else {
                    self.transmitted += 1;
                }
                if offset == 0 {
                    self.timer_start = now;
                }
                // A frame lost twice already goes out twice in a row: on a line that damages
                // every second frame, that halves the odds of a third loss (a duplicate costs
                // the receiver nothing).
                self.slot_pending[slot] =
                    self.slot_copies[slot] >= 2 && self.slot_copies[slot].is_multiple_of(2);
                if self.slot_copies[slot] == 0 {
                    self.slot_first_sent_at[slot] = now;
                }
                self.slot_copies[slot] = self.slot_copies[slot].saturating_add(1);
                self.slot_last_sent_at[slot] = now;
                self.transmissions += 1;
                self.slot_sent_as[slot] = self.transmissions;
                let seq = self.base_seq.wrapping_add(offset as u8);
                let header = self.header(seq, true);
                let payload = self.slots[slot];
                let len = self.slot_lens[slot] as usize;
                return self.encode(&header, &payload[..len], out);
            }
        }
        if self.ack_owed {
            let header = self.header(self.next_seq(), false);
            return self.encode(&header, &[], out);
        }
        None
    }

    /// Take a frame from the decoder. After a [`Received::Message`], call
    /// [`Link::next_buffered`] until `None`: the frame may have filled a gap in front of
    /// frames that arrived earlier.
    pub fn receive<'a>(&mut self, frame: &Frame<'a>, now: u64) -> Received<'a> {
        let header = &frame.header;
        if header.sync_request {
            return self.on_sync_request(frame);
        }
        if header.sync_reply {
            self.on_sync_reply(frame);
            return Received::Nothing;
        }
        if header.sequenced && self.peer_nonce.is_none() {
            // No peer session known: a sequenced frame is from an old one (an MCU that
            // restarted, the host still resending its window). Unacknowledged, a frame of
            // a new session is sent again once the sessions are known to each other.
            self.counters.stale_frames = self.counters.stale_frames.wrapping_add(1);
            return Received::Nothing;
        }
        self.on_ack(header.ack, now);
        if !header.sequenced {
            if header.nak {
                self.on_sack(frame.payload, now);
                return Received::Nothing;
            }
            return if frame.payload.is_empty() {
                Received::Nothing
            } else {
                Received::Unsequenced(frame.payload)
            };
        }
        let ahead = header.seq.wrapping_sub(self.expected) as usize;
        if ahead == 0 {
            self.advance_expected();
            Received::Message(frame.payload)
        } else if ahead < 128 {
            self.counters.out_of_order += 1;
            if ahead < W {
                let slot = (self.rx_head + ahead) % W;
                if self.rx_present[slot] {
                    self.counters.duplicates += 1;
                } else {
                    self.rx_present[slot] = true;
                    self.rx_lens[slot] = frame.payload.len() as u8;
                    self.rx_slots[slot][..frame.payload.len()].copy_from_slice(frame.payload);
                }
            }
            self.nak_owed = true;
            Received::Nothing
        } else {
            // Behind: our acknowledgement was lost; repeat it so the peer moves on.
            self.counters.duplicates += 1;
            self.ack_owed = true;
            Received::Nothing
        }
    }

    /// The next message that arrived ahead of a gap now filled, in order; `None` when the
    /// next one has not arrived. Delivering it acknowledges it: call only when the
    /// application can take it (it stays held until then).
    pub fn next_buffered(&mut self) -> Option<&[u8]> {
        let slot = self.rx_head;
        if !self.rx_present[slot] {
            return None;
        }
        self.advance_expected();
        Some(&self.rx_slots[slot][..self.rx_lens[slot] as usize])
    }

    /// Take only the acknowledgement a frame carries, not its message: for a receiver that
    /// cannot accept another message now. The peer resends the message later, as if it had
    /// been lost.
    pub fn receive_ack_only(&mut self, frame: &Frame, now: u64) {
        let header = &frame.header;
        if !header.sync_request && !header.sync_reply {
            self.on_ack(header.ack, now);
            if header.nak && !header.sequenced {
                self.on_sack(frame.payload, now);
            }
        }
    }

    /// `expected` was delivered: step past it; tell the sender about any gap still open.
    fn advance_expected(&mut self) {
        self.rx_present[self.rx_head] = false;
        self.rx_head = (self.rx_head + 1) % W;
        self.expected = self.expected.wrapping_add(1);
        self.ack_owed = true;
        self.nak_owed = !self.rx_present[self.rx_head] && self.rx_present.iter().any(|&p| p);
    }

    /// Bit `k` of the bitmap: we hold `expected + 1 + k`. Returns the bytes used (0: we
    /// hold nothing ahead of a gap).
    fn sack_bitmap(&self, bitmap: &mut [u8; MAX_SACK_BYTES]) -> usize {
        let mut len = 0;
        for k in 0..(W - 1).min(8 * MAX_SACK_BYTES) {
            if self.rx_present[(self.rx_head + 1 + k) % W] {
                bitmap[k / 8] |= 1 << (k % 8);
                len = k / 8 + 1;
            }
        }
        len
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
        self.restart_receiving(frame.header.seq);
        self.ack_owed = false;
        self.nak_owed = false;
        // What the old session never acknowledged is gone with it.
        let lost = self.transmitted;
        self.head = (self.head + lost) % W;
        self.queued -= lost;
        self.base_seq = self.base_seq.wrapping_add(lost as u8);
        self.transmitted = 0;
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
            self.restart_receiving(frame.header.seq);
        }
    }

    /// A new peer session numbers from `seq`: nothing held from the old one counts.
    fn restart_receiving(&mut self, seq: u8) {
        self.expected = seq;
        self.rx_present = [false; W];
        self.rx_head = 0;
    }

    fn on_ack(&mut self, ack: u8, now: u64) {
        let acked = ack.wrapping_sub(self.base_seq) as usize;
        if acked > self.transmitted {
            return; // acknowledges nothing we sent: stale or from another session
        }
        if acked > 0 {
            let newest = (self.head + acked - 1) % W;
            if self.slot_copies[newest] == 1 {
                self.measured_round_trip(now.saturating_sub(self.slot_first_sent_at[newest]));
            }
            self.backed_off = false;
            self.head = (self.head + acked) % W;
            self.queued -= acked;
            self.transmitted -= acked;
            self.base_seq = ack;
            self.timer_start = now;
        }
    }

    /// A selective acknowledgement (after `on_ack` took its cumulative part): mark what the
    /// peer holds, and resend what it lacks that is lost: a copy that went out before one it
    /// holds (the line never reorders), or one that went out a round trip ago (the peer repeats
    /// its NAK while the gap lasts; the copy we resent after the last one was lost too).
    fn on_sack(&mut self, bitmap: &[u8], now: u64) {
        if self.transmitted == 0 {
            return;
        }
        self.counters.naks_received += 1;
        let mut newest_held = 0;
        for offset in 1..self.transmitted {
            let k = offset - 1;
            let held = bitmap.get(k / 8).is_some_and(|b| b & (1 << (k % 8)) != 0);
            if held {
                let slot = (self.head + offset) % W;
                self.slot_sacked[slot] = true;
                newest_held = newest_held.max(self.slot_sent_as[slot]);
            }
        }
        let round_trip = self.loss_delay();
        for offset in 0..self.transmitted {
            let slot = (self.head + offset) % W;
            let overtaken = self.slot_sent_as[slot] < newest_held;
            let overdue = now.saturating_sub(self.slot_last_sent_at[slot]) >= round_trip;
            if !self.slot_sacked[slot] && (overtaken || overdue) {
                self.slot_pending[slot] = true;
            }
        }
    }

    /// How long after sending a copy a NAK that still lacks it shows it lost: the measured
    /// round trip plus its deviation (half the timeout until measured).
    fn loss_delay(&self) -> u64 {
        self.measured_wait(1, self.options.retransmit_timeout / 2)
    }

    /// The wait before resending: measured (RFC 6298: smoothed round trip plus four mean
    /// deviations) within an eighth of the configured timeout and the timeout, doubled
    /// after a timeout until the next progress.
    pub fn retransmit_timeout(&self) -> u64 {
        let longest = self.options.retransmit_timeout;
        let base = self.measured_wait(4, longest);
        match self.backed_off {
            true => base.saturating_mul(2).min(longest),
            false => base,
        }
    }

    /// The smoothed round trip plus `deviations` mean deviations, within an eighth of the
    /// configured timeout and the timeout; `unmeasured` before any round trip is measured.
    fn measured_wait(&self, deviations: u64, unmeasured: u64) -> u64 {
        let longest = self.options.retransmit_timeout;
        match self.smoothed_rtt {
            Some(srtt) => (srtt + deviations * self.rtt_deviation).clamp(longest / 8, longest),
            None => unmeasured,
        }
    }

    fn measured_round_trip(&mut self, rtt: u64) {
        match self.smoothed_rtt {
            None => {
                self.smoothed_rtt = Some(rtt);
                self.rtt_deviation = rtt / 2;
            }
            Some(srtt) => {
                self.rtt_deviation = (3 * self.rtt_deviation + srtt.abs_diff(rtt)) / 4;
                self.smoothed_rtt = Some((7 * srtt + rtt) / 8);
            }
        }
    }

    fn next_seq(&self) -> u8 {
        self.base_seq.wrapping_add(self.queued as u8)
    }

    /// A header carrying our acknowledgement.
    fn header(&mut self, seq: u8, sequenced: bool) -> FrameHeader {
        self.ack_owed = false;
        FrameHeader {
            seq,
            ack: self.expected,
            sequenced,
            nak: false,
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
