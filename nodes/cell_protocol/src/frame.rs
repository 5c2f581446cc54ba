//! Frames: the unit of transmission, delimited and checked.
//!
//! ```text
//! decoded frame:  len | seq | ack | flags | payload (len bytes) | crc16 (LE)
//! on the wire:    COBS(decoded frame) 0x00
//! ```
//!
//! The length byte is redundant with the delimiter on purpose: a frame that was cut or merged
//! with garbage fails two independent checks (length and CRC) instead of one.

use crate::{CRC_LEN, FRAME_CRC, HEADER_LEN, MAX_FRAME, MAX_PAYLOAD, MAX_WIRE_FRAME};

/// Flag bit: the frame carries a sequenced (reliable) message; its `seq` counts.
pub const FLAG_SEQUENCED: u8 = 0x01;
/// Flag bit: the sender saw a gap in its peer's sequence; resend from `ack`.
pub const FLAG_NAK: u8 = 0x02;
/// Flag bit: the sender starts a session (payload: its nonce); see [`crate::link`].
pub const FLAG_SYNC_REQUEST: u8 = 0x04;
/// Flag bit: the answer to a session start (payload: the echoed nonce, then the sender's).
pub const FLAG_SYNC_REPLY: u8 = 0x08;
const KNOWN_FLAGS: u8 = FLAG_SEQUENCED | FLAG_NAK | FLAG_SYNC_REQUEST | FLAG_SYNC_REPLY;

/// The header fields a frame carries besides its payload.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct FrameHeader {
    /// Sequence number of this frame (mod 256); meaningful only when `sequenced`.
    pub seq: u8,
    /// The next sequence number the sender expects from its peer: every earlier one arrived.
    pub ack: u8,
    /// The payload is a sequenced message: deliver it once, in order.
    pub sequenced: bool,
    /// The sender is missing its peer's frame `ack`: resend from there.
    pub nak: bool,
    /// Link management: a session start, or the answer to one.
    pub sync_request: bool,
    pub sync_reply: bool,
}

impl FrameHeader {
    fn flags(&self) -> u8 {
        [
            (self.sequenced, FLAG_SEQUENCED),
            (self.nak, FLAG_NAK),
            (self.sync_request, FLAG_SYNC_REQUEST),
            (self.sync_reply, FLAG_SYNC_REPLY),
        ]
        .iter()
        .filter(|(set, _)| *set)
        .fold(0, |flags, (_, bit)| flags | bit)
    }
}

/// A frame that passed every check.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frame<'a> {
    pub header: FrameHeader,
    pub payload: &'a [u8],
}

impl<'a> Frame<'a> {
    /// The payload as messages, or `None` when it is the link's own: a session start's nonce,
    /// its answer's two nonces, or a NAK's bitmap of the frames held. Those bytes may look
    /// like any message (a nonce starting 0x30 reads as EMERGENCY_STOP), so a receiver that
    /// looks into a frame before the link has taken it asks here first.
    pub fn messages(&self) -> Option<&'a [u8]> {
        let h = &self.header;
        let link_only = h.sync_request || h.sync_reply || (h.nak && !h.sequenced);
        (!link_only).then_some(self.payload)
    }
}

/// Why bytes did not make a frame. Receivers count these and go on with the next frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    #[error("payload of {len} bytes: a frame carries at most {MAX_PAYLOAD}")]
    PayloadTooLong { len: usize },
    #[error("output buffer of {len} bytes: a frame needs up to {MAX_WIRE_FRAME}")]
    BufferTooSmall { len: usize },
    #[error("{len} bytes before a delimiter: longer than any frame ({MAX_WIRE_FRAME}), dropped")]
    Overlong { len: usize },
    #[error("bytes between delimiters are not valid COBS")]
    Cobs,
    #[error("frame of {len} bytes is shorter than a header and CRC ({})", HEADER_LEN + CRC_LEN)]
    Truncated { len: usize },
    #[error("length byte says {declared} payload bytes, the frame has {actual}")]
    LengthMismatch { declared: usize, actual: usize },
    #[error("CRC {received:#06x} received, {computed:#06x} computed")]
    Crc { received: u16, computed: u16 },
    #[error("unknown flag bits {flags:#04x}")]
    UnknownFlags { flags: u8 },
}

/// Encode one frame into `out` (COBS and the trailing delimiter); returns the bytes written.
pub fn encode_frame(
    header: &FrameHeader,
    payload: &[u8],
    out: &mut [u8],
) -> Result<usize, FrameError> {
    if payload.len() > MAX_PAYLOAD {
        return Err(FrameError::PayloadTooLong { len: payload.len() });
    }
    let mut frame = [0u8; MAX_FRAME];
    let body_len = HEADER_LEN + payload.len();
    frame[..HEADER_LEN].copy_from_slice(&[
        payload.len() as u8,
        header.seq,
        header.ack,
        header.flags(),
    ]);
    frame[HEADER_LEN..body_len].copy_from_slice(payload);
    let crc = FRAME_CRC.checksum(&frame[..body_len]);
    frame[body_len..body_len + CRC_LEN].copy_from_slice(&crc.to_le_bytes());
    let frame = &frame[..body_len + CRC_LEN];
    let needed = cobs::max_encoding_length(frame.len()) + 1;
    if out.len() < needed {
        return Err(FrameError::BufferTooSmall { len: out.len() });
    }
    let written = cobs::encode(frame, out);
    out[written] = 0;
    Ok(written + 1)
}

/// Check a decoded (COBS-free) frame.
pub fn parse_frame(frame: &[u8]) -> Result<Frame<'_>, FrameError> {
    if frame.len() < HEADER_LEN + CRC_LEN {
        return Err(FrameError::Truncated { len: frame.len() });
    }
    let body_len = frame.len() - CRC_LEN;
    let received = u16::from_le_bytes([frame[body_len], frame[body_len + 1]]);
    let computed = FRAME_CRC.checksum(&frame[..body_len]);
    if received != computed {
        return Err(FrameError::Crc { received, computed });
    }
    let declared = frame[0] as usize;
    let actual = body_len - HEADER_LEN;
    if declared != actual {
        return Err(FrameError::LengthMismatch { declared, actual });
    }
    // Longer than the decoder lets through, but a caller may parse frames it framed itself:
    // such a payload is no frame of this protocol, and a receiver's 64-byte buffers must
    // never see it.
    if actual > MAX_PAYLOAD {
        return Err(FrameError::PayloadTooLong { len: actual });
    }
    let flags = frame[3];
    if flags & !KNOWN_FLAGS != 0 {
        return Err(FrameError::UnknownFlags { flags });
    }
    Ok(Frame {
        header: FrameHeader {
            seq: frame[1],
            ack: frame[2],
            sequenced: flags & FLAG_SEQUENCED != 0,
            nak: flags & FLAG_NAK != 0,
            sync_request: flags & FLAG_SYNC_REQUEST != 0,
            sync_reply: flags & FLAG_SYNC_REPLY != 0,
        },
        payload: &frame[HEADER_LEN..body_len],
    })
}

/// What the receiving side has seen, for its status report.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DecoderCounters {
    /// Frames that passed every check.
    pub frames: u32,
    /// Frames whose CRC failed.
    pub crc_errors: u32,
    /// Other bad frames: overlong, bad COBS, truncated, wrong length, unknown flags.
    pub framing_errors: u32,
}

/// Streaming decoder: feed it the received bytes in any pieces; it yields each frame at its
/// delimiter. Bounded memory: one wire frame.
#[derive(Clone, Debug)]
pub struct FrameDecoder {
    /// An encoded frame without its delimiter: 71 bytes, as PROTOCOL.md §1 says.
    buf: [u8; MAX_WIRE_FRAME - 1],
    len: usize,
    /// More bytes than a frame arrived since the last delimiter: skip to the next one.
    overlong: usize,
    counters: DecoderCounters,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        FrameDecoder::new()
    }
}

impl FrameDecoder {
    pub const fn new() -> FrameDecoder {
        FrameDecoder {
            buf: [0; MAX_WIRE_FRAME - 1],
            len: 0,
            overlong: 0,
            counters: DecoderCounters {
                frames: 0,
                crc_errors: 0,
                framing_errors: 0,
            },
        }
    }

    pub fn counters(&self) -> DecoderCounters {
        self.counters
    }

    /// Forget a partly received frame (e.g. after the port was reopened).
    pub fn clear(&mut self) {
        self.len = 0;
        self.overlong = 0;
    }

    /// Take one received byte. At a delimiter: `Some(frame or why not)`; empty frames (two
    /// delimiters in a row, used as padding and to resynchronise) give `None`.
    pub fn push(&mut self, byte: u8) -> Option<Result<Frame<'_>, FrameError>> {
        if byte != 0 {
            if self.len < self.buf.len() {
                self.buf[self.len] = byte;
                self.len += 1;
            } else {
                self.overlong += 1;
            }
            return None;
        }
        let len = core::mem::take(&mut self.len);
        let overlong = core::mem::take(&mut self.overlong);
        if overlong > 0 {
            self.counters.framing_errors += 1;
            return Some(Err(FrameError::Overlong {
                len: len + overlong,
            }));
        }
        if len == 0 {
            return None;
        }
        let result = match cobs::decode_in_place(&mut self.buf[..len]) {
            Ok(decoded) => parse_frame(&self.buf[..decoded]),
            Err(_) => Err(FrameError::Cobs),
        };
        match result {
            Ok(_) => self.counters.frames += 1,
            Err(FrameError::Crc { .. }) => self.counters.crc_errors += 1,
            Err(_) => self.counters.framing_errors += 1,
        }
        Some(result)
    }
}

#[cfg(test)]
mod tests;
