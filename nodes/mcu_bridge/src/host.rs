//! The host's end of the wire: typed messages in and out, bytes on the line.

use cell_protocol::message::{HostMessage, McuMessage};
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
#[derive(Clone, Debug)]
pub struct HostEndpoint {
    link: Link<HOST_WINDOW>,
    decoder: FrameDecoder,
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
        }
    }

    pub fn link(&self) -> &Link<HOST_WINDOW> {
        &self.link
    }

    pub fn decoder(&self) -> &FrameDecoder {
        &self.decoder
    }

    /// Room for another sequenced message.
    pub fn can_send(&self) -> bool {
        self.link.can_send()
    }

    /// Queue a sequenced message (every host message but the emergency stop).
    pub fn send(&mut self, message: &HostMessage) -> Result<(), LinkError> {
        let mut payload = [0; MAX_PAYLOAD];
        let len = message.encode(&mut payload);
        self.link.send(&payload[..len])
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
                Received::Message(p) | Received::Unsequenced(p) => on_message(decode(p)),
                Received::PeerRestarted { lost } => on_message(FromMcu::Restarted { lost }),
                Received::Nothing => {}
            }
            // Messages held behind a gap this frame filled.
            while let Some(p) = self.link.next_buffered() {
                on_message(decode(p));
            }
        }
    }

    /// The next bytes to write at `now_us`, if any; call until `None`.
    pub fn poll_transmit(&mut self, now_us: u64, out: &mut [u8; MAX_WIRE_FRAME]) -> Option<usize> {
        self.link.poll_transmit(now_us, out)
    }
}

fn decode(payload: &[u8]) -> FromMcu {
    match McuMessage::decode(payload) {
        Ok(m) => FromMcu::Message(m),
        Err(_) => FromMcu::Undecodable,
    }
}
