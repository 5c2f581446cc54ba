//! The MCU's end of the wire: bytes in, bytes out, the machine in between. The RP2040
//! firmware and the emulator both wrap exactly this, so they differ only in where bytes and
//! edges go.

use cell_protocol::link::LinkCounters;
use cell_protocol::message::{
    host_messages, FaultCode, HostMessage, McuCounters, McuMessage, MessageError, Mode,
};
use cell_protocol::{FrameDecoder, Link, LinkOptions, Received, MAX_PAYLOAD, MAX_WIRE_FRAME};
use heapless::Deque;

use crate::machine::{Machine, MachineConfig, StepEdge};
use crate::seed_program::seed_001_program;

/// Replies waiting for room in the link's window.
const OUTBOX: usize = 16;

/// The MCU's protocol endpoint with a link window of `W` frames, `Q` queued segments and `S`
/// queued screw commands.
#[derive(Clone, Debug)]
pub struct Endpoint<const W: usize, const Q: usize, const S: usize> {
    decoder: FrameDecoder,
    link: Link<W>,
    machine: Machine<Q, S>,
    outbox: Deque<McuMessage, OUTBOX>,
    next_state_at: u64,
    /// Payloads that were not a host message (counted, dropped).
    pub bad_messages: u32,
    /// Fault reports that found the outbox full (the state still carries the fault).
    pub replies_dropped: u32,
}

impl<const W: usize, const Q: usize, const S: usize> Endpoint<W, Q, S> {
    pub fn new(machine: MachineConfig, link: LinkOptions) -> Self {
        Endpoint {
            decoder: FrameDecoder::new(),
            link: Link::new(link),
            machine: Machine::new(machine),
            outbox: Deque::new(),
            next_state_at: 0,
            bad_messages: 0,
            replies_dropped: 0,
        }
    }

    pub fn machine(&self) -> &Machine<Q, S> {
        &self.machine
    }

    pub fn link(&self) -> &Link<W> {
        &self.link
    }

    /// Replies waiting for room in the link's window.
    pub fn replies_waiting(&self) -> usize {
        self.outbox.len()
    }

    pub fn link_counters(&self) -> LinkCounters {
        self.link.counters()
    }

    /// Take bytes received at MCU clock `now`.
    pub fn receive(&mut self, bytes: &[u8], now: u64) {
        for &byte in bytes {
            let Some(Ok(frame)) = self.decoder.push(byte) else {
                continue;
            };
            self.machine.host_frame(now);
            // An emergency stop acts in any valid frame of messages, before the link decides
            // whether the frame is in order.
            let messages = frame.messages().unwrap_or_default();
            if host_messages(messages).any(|m| m == Ok(HostMessage::EmergencyStop)) {
                self.machine.emergency_stop();
            }
            // No room for a reply (a frame asks for at most one): leave the frame to be resent
            // rather than drop its reply.
            if frame.header.sequenced && self.outbox.is_full() {
                self.link.receive_ack_only(&frame, now);
                continue;
            }
            // The link delivers the frame's own payload (copied out of the decoder's buffer).
            let mut payload = [0u8; MAX_PAYLOAD];
            let len = frame.payload.len();
            payload[..len].copy_from_slice(frame.payload);
            match self.link.receive(&frame, now) {
                Received::Message(_) | Received::Unsequenced(_) => {
                    self.handle_payload(&payload[..len], now)
                }
                Received::Nothing | Received::PeerRestarted { .. } => {}
            }
            self.deliver_held(now);
        }
    }

    /// Messages the link held behind a gap that is now filled, while replies have room (the
    /// rest stay held, unacknowledged, until the next frame).
    fn deliver_held(&mut self, now: u64) {
        let mut payload = [0u8; MAX_PAYLOAD];
        while !self.outbox.is_full() {
            let len = match self.link.next_buffered() {
                Some(held) => {
                    payload[..held.len()].copy_from_slice(held);
                    held.len()
                }
                None => break,
            };
            self.handle_payload(&payload[..len], now);
        }
    }

    /// Act on every message of a payload in order. One that does not decode is counted and
    /// faults the machine, and what follows it is lost with it (its length is unknown).
    fn handle_payload(&mut self, payload: &[u8], now: u64) {
        for message in host_messages(payload) {
            self.handle(message, now);
        }
    }

    fn handle(&mut self, message: Result<HostMessage, MessageError>, now: u64) {
        let reply = match message {
            Ok(HostMessage::EmergencyStop) => None, // acted on when its frame arrived
            Ok(HostMessage::QueryCounters) => Some(McuMessage::Counters(self.counters())),
            Ok(m) => self.machine.handle(&m, now),
            Err(_) => {
                self.bad_messages += 1;
                self.machine.bad_message();
                None
            }
        };
        if let Some(reply) = reply {
            // Room was checked for sequenced frames; an unsequenced query finding the outbox
            // full goes unanswered, like a lost frame.
            if self.outbox.push_back(reply).is_err() {
                self.replies_dropped += 1;
            }
        }
    }

    /// The start switch was pressed at MCU clock `now`: play seed 001's program
    /// ([`crate::seed_program`]) from the current position, starting `lead_ticks` after the
    /// plan clock. Only an idle machine that no host has configured starts it (a host owns the
    /// machine once it configures it); returns whether it started.
    pub fn start_seed_program(&mut self, now: u64, lead_ticks: u64) -> bool {
        let machine = &mut self.machine;
        if machine.host_configured()
            || machine.fault() != FaultCode::None
            || machine.mode() != Mode::Idle
        {
            return false;
        }
        // A new schedule: an earlier one (an earlier run of the program) ended at rest.
        machine.handle(&HostMessage::DropQueue, now);
        let start_clock = machine.plan_clock() + lead_ticks;
        let program = seed_001_program(machine.positions(), start_clock, machine.config().timer_hz);
        for queued in program {
            machine.handle(&HostMessage::QueueSegment(queued), now);
        }
        machine.fault() == FaultCode::None
    }

    /// See [`Machine::discard_edges`].
    pub fn discard_edges(&mut self, edges: impl IntoIterator<Item = StepEdge>) {
        self.machine.discard_edges(edges);
    }

    /// Generate step edges up to MCU tick `until` (see [`Machine::advance`]).
    pub fn advance(&mut self, until: u64, sink: &mut impl FnMut(StepEdge)) {
        self.machine.advance(until, sink);
    }

    /// The next bytes to send at MCU clock `now`, if any; call until `None`.
    pub fn poll_transmit(&mut self, now: u64, out: &mut [u8; MAX_WIRE_FRAME]) -> Option<usize> {
        if let Some(fault) = self.machine.take_fault_report() {
            // Ahead of everything else; if even that does not fit, the state carries it.
            if self.outbox.push_front(fault).is_err() {
                self.replies_dropped += 1;
            }
        }
        let mut payload = [0u8; MAX_PAYLOAD];
        while let Some(reply) = self.outbox.front() {
            let len = reply.encode(&mut payload);
            if !reply.is_sequenced() {
                self.outbox.pop_front();
                return self.link.encode_unsequenced(&payload[..len], out).ok();
            }
            if !self.link.can_send() {
                break;
            }
            self.link
                .send(&payload[..len])
                .expect("room checked, payload within bounds");
            self.outbox.pop_front();
        }
        let period = self.machine.state_period_ticks() as u64;
        if period > 0 && now >= self.next_state_at && self.link.is_synced() {
            self.next_state_at = now + period;
            let len = McuMessage::State(self.machine.state()).encode(&mut payload);
            return self.link.encode_unsequenced(&payload[..len], out).ok();
        }
        self.link.poll_transmit(now, out)
    }

    /// The counters the MCU reports.
    pub fn counters(&self) -> McuCounters {
        let decoder = self.decoder.counters();
        let link = self.link.counters();
        let machine = self.machine.counters();
        McuCounters {
            frames_received: decoder.frames,
            crc_errors: decoder.crc_errors,
            framing_errors: decoder.framing_errors,
            naks_sent: link.naks_sent,
            retransmits: link.retransmits,
            underruns: machine.underruns,
            late_segments: machine.late_segments,
        }
    }
}
