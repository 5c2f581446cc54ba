//! The wire protocol between the polar cell's host (`mcu_bridge`) and its microcontroller.
//!
//! Both sides link this crate (`no_std`, no allocation), so the host and the firmware cannot
//! disagree about a byte. The protocol itself is specified in `PROTOCOL.md` beside this crate,
//! precisely enough to implement it in C; this crate is one implementation of it.
//!
//! Three layers, each usable alone, none doing I/O:
//!
//! * [`frame`] — bytes ⇄ frames. A frame is a header (length, sequence, acknowledgement,
//!   flags), a payload and a CRC-16, COBS-encoded and ended by a `0x00` byte. Because `0x00`
//!   never occurs inside an encoded frame, a receiver that lost sync (garbage, a dropped byte)
//!   is back in step at the next `0x00`: whatever lay between is one bad frame, counted and
//!   dropped, never a misread message.
//! * [`link`] — frames ⇄ a reliable ordered message stream: selective repeat with a bounded window,
//!   cumulative acknowledgements, selective negative acknowledgements on a gap, retransmission on
//!   timeout. Telemetry that a newer sample supersedes may go unsequenced (best effort).
//! * [`message`] — payload bytes ⇄ typed messages: identify, clock, step segments, screw,
//!   feed hold and resume, emergency stop, reset, state and faults.
//!
//! The model is Klipper's host/MCU split (the host schedules every step in MCU clock time,
//! the MCU only executes and reports), with our own encoding: fixed little-endian fields for
//! the rare messages (what a firmware author can check by eye), and for the two that make up
//! a print — a segment continuing the schedule, a screw ramp after the previous one — compact
//! forms of varints and 32-bit mantissa-exponent words, packed several to a frame.

#![no_std]
#![forbid(unsafe_code)]

#[cfg(test)]
#[macro_use]
extern crate std;

pub mod frame;
pub mod link;
pub mod message;

pub use frame::{encode_frame, Frame, FrameDecoder, FrameError, FrameHeader};
pub use link::{Link, LinkError, LinkOptions, Received};
pub use message::{HostMessage, McuMessage, MessageError};

/// Version of the protocol in `PROTOCOL.md`; the MCU reports it in its identify reply and the
/// host refuses any other.
pub const PROTOCOL_VERSION: u16 = 4;

/// Most payload bytes one frame carries (the largest message, a full queued segment, takes 60;
/// a payload holds as many messages as fit).
pub const MAX_PAYLOAD: usize = 64;

/// Header bytes before the payload: length, sequence, acknowledgement, flags.
pub const HEADER_LEN: usize = 4;

/// CRC bytes after the payload.
pub const CRC_LEN: usize = 2;

/// Largest frame before COBS encoding.
pub const MAX_FRAME: usize = HEADER_LEN + MAX_PAYLOAD + CRC_LEN;

/// Largest frame on the wire: COBS adds one byte per 254 (here one), then the `0x00`
/// delimiter.
pub const MAX_WIRE_FRAME: usize = MAX_FRAME + 1 + 1;

/// The CRC of every frame: CRC-16/IBM-3740 (polynomial 0x1021, initial 0xFFFF, no
/// reflection, no final XOR; also called CRC-16/CCITT-FALSE; check value 0x29B1 for the
/// ASCII bytes `123456789`).
pub const FRAME_CRC: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_IBM_3740);
