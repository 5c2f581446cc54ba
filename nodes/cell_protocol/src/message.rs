//! Messages: a frame's payload is one or more of them, each a kind byte and its fields —
//! fixed little-endian fields, or for the two compact continuing forms ([`compact`]) varints.
//!
//! Host → MCU kinds are `0x01..=0x7F`, MCU → host kinds `0x81..=0xFF`, so a frame sent the
//! wrong way round is an unknown kind, not a misread. Times are MCU clock ticks (`_clock`:
//! absolute, 64-bit; `_ticks`: a span). Field tables with offsets are in `PROTOCOL.md`.

use step_core::{Segment, MAX_AXES};

use crate::MAX_PAYLOAD;

pub mod compact;

pub use compact::{NextSegment, ScrewNext, ScrewReference, ScrewStart};

/// A step segment scheduled on the MCU clock.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct QueuedSegment {
    /// MCU clock at which the segment starts; it must equal the previous segment's end (or
    /// lie in the future when the queue is empty), else the MCU faults.
    pub start_clock: u64,
    /// Length on the plan clock: the next segment starts at `start_clock + duration_ticks`.
    pub duration_ticks: u32,
    /// The host's name for the segment (its move sequence): echoed in state and faults.
    pub tag: u32,
    /// [`SEGMENT_ENDS_AT_REST`] and future bits (others must be 0).
    pub flags: u8,
    pub segment: Segment,
}

/// Segment flag: every joint is at rest at the segment's end, so the queue may run dry
/// there. Without it, an empty queue at the segment's end is an underrun (a fault).
pub const SEGMENT_ENDS_AT_REST: u8 = 0x01;

/// A change of the screw's speed and of the nozzle pin, scheduled on the MCU clock.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct ScrewRamp {
    pub start_clock: u64,
    /// The rpm goes linearly from its value at `start_clock` to the target over this span.
    pub ramp_ticks: u32,
    /// Target speed in thousandths of a revolution per minute (negative: retract).
    pub target_millirpm: i32,
    /// The nozzle pin's state from `start_clock` on.
    pub pin_open: bool,
}

/// What the host sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum HostMessage {
    /// Ask for [`McuMessage::Identity`].
    Identify,
    /// Ask for the MCU clock now; the token comes back in [`McuMessage::Clock`].
    ClockQuery {
        token: u32,
    },
    /// Watchdog and telemetry: fault if no valid frame arrives for `host_timeout_ticks`
    /// (0 = off); send [`McuMessage::State`] every `state_period_ticks` (0 = only on query).
    Configure {
        host_timeout_ticks: u32,
        state_period_ticks: u32,
    },
    QueueSegment(QueuedSegment),
    /// A segment that starts where the previously queued one ends (compact form).
    NextSegment(NextSegment),
    Screw(ScrewRamp),
    /// A screw ramp timed after the previous screw command (compact form).
    ScrewNext(ScrewNext),
    /// Feed hold: the plan clock slows to a stop along the path; the feed scale σ (Q32, 1.0 =
    /// 2³²) falls by `rate_q32` per tick. The host derives the rate from the joints'
    /// acceleration limits over what it queued.
    FeedHold {
        rate_q32: u32,
    },
    /// Leave a hold: after `delay_ticks` at rest (the pin's opening delay), σ rises by
    /// `rate_q32` per tick back to 1.
    FeedResume {
        rate_q32: u32,
        delay_ticks: u32,
    },
    /// Drop every queued segment and screw ramp; only at rest (held or idle), else a fault.
    DropQueue,
    /// Stop every output now, ahead of anything queued; the MCU latches a fault. Acted on in
    /// any valid frame, sequenced or not, in order or not.
    EmergencyStop,
    /// Clear a latched fault and the queues; positions are kept.
    Reset,
    /// Ask for [`McuMessage::State`] now.
    QueryState,
    /// Ask for [`McuMessage::Counters`].
    QueryCounters,
}

/// How the MCU describes itself.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Identity {
    pub protocol_version: u16,
    /// Step timer (and MCU clock) frequency.
    pub timer_hz: u32,
    /// Segments the MCU can hold queued.
    pub queue_capacity: u16,
    /// Steppers driven (at most [`MAX_AXES`]).
    pub axis_count: u8,
    /// Screw commands the MCU can hold queued.
    pub screw_queue_capacity: u16,
}

/// What the MCU is doing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Mode {
    /// Nothing queued, at rest.
    #[default]
    Idle = 0,
    /// Playing segments at σ = 1.
    Running = 1,
    /// In a feed hold or resume: σ between 0 and 1.
    Ramping = 2,
    /// Held at rest on the path (σ = 0).
    Held = 3,
    /// Outputs stopped after a fault or emergency stop, until [`HostMessage::Reset`].
    Fault = 4,
}

/// Why the MCU stopped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum FaultCode {
    #[default]
    None = 0,
    /// A segment arrived after its start clock had passed.
    LateSegment = 1,
    /// The queue ran dry while a joint was moving.
    Underrun = 2,
    /// No valid frame within the configured host timeout.
    HostSilent = 3,
    EmergencyStop = 4,
    /// A segment failed [`Segment::check`] or did not start where the previous one ended.
    BadSegment = 5,
    /// A segment or screw ramp arrived with the queue full.
    QueueOverflow = 6,
    /// The step generator left its fixed-point range ([`step_core::StepFault`]).
    StepFault = 7,
    /// [`HostMessage::DropQueue`] while moving.
    DropWhileMoving = 8,
}

/// The MCU's state, sent on query and every configured period.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct McuState {
    /// MCU clock when the state was taken.
    pub clock: u64,
    /// The plan clock then: the schedule's time, which lags the MCU clock by the time spent
    /// in feed holds (equal to `clock` if there were none). Segment start clocks are on it.
    pub plan_clock: u64,
    /// Step position of each axis.
    pub position_steps: [i32; MAX_AXES],
    pub screw_millirpm: i32,
    /// Screw angle integrated from its speed, thousandths of a revolution.
    pub screw_angle_millirev: i32,
    pub pin_open: bool,
    /// Free places in the segment queue.
    pub queue_free: u16,
    /// Tag of the last segment completed (0 before the first).
    pub done_tag: u32,
    /// Feed scale σ in Q16 (65535 ≈ 1).
    pub feed_scale_q16: u16,
    pub mode: Mode,
    /// The latched fault (`None` unless `mode` is `Fault`).
    pub fault: FaultCode,
}

/// Link and timing counters since power-up (RESET keeps them).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct McuCounters {
    pub frames_received: u32,
    pub crc_errors: u32,
    pub framing_errors: u32,
    pub naks_sent: u32,
    pub retransmits: u32,
    pub underruns: u32,
    pub late_segments: u32,
}

/// What the MCU sends.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum McuMessage {
    Identity(Identity),
    Clock {
        token: u32,
        clock: u64,
    },
    State(McuState),
    Counters(McuCounters),
    /// Sent once when a fault latches (sequenced: it must arrive).
    Fault {
        code: FaultCode,
        clock: u64,
        /// Tag of the segment concerned (0 if none).
        tag: u32,
    },
}

/// Why a payload is not a message. Carries the kind byte and the offending values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum MessageError {
    #[error("empty payload: a message starts with its kind byte")]
    Empty,
    #[error("unknown message kind {kind:#04x}")]
    UnknownKind { kind: u8 },
    #[error("message kind {kind:#04x} has {actual} bytes, its layout has {expected}")]
    Length {
        kind: u8,
        expected: usize,
        actual: usize,
    },
    #[error("message kind {kind:#04x} ends before its last field")]
    Truncated { kind: u8 },
    #[error("message kind {kind:#04x}: {field} is not a minimal varint of at most 32 bits")]
    BadVarint { kind: u8, field: &'static str },
    #[error("message kind {kind:#04x}: {field} = {value} is not a valid value")]
    BadValue {
        kind: u8,
        field: &'static str,
        value: u64,
    },
}

mod kind {
    pub const IDENTIFY: u8 = 0x01;
    pub const CLOCK_QUERY: u8 = 0x02;
    pub const CONFIGURE: u8 = 0x03;
    pub const QUEUE_SEGMENT: u8 = 0x10;
    pub const SCREW: u8 = 0x11;
    pub const NEXT_SEGMENT: u8 = 0x12;
    pub const SCREW_NEXT: u8 = 0x13;
    pub const NEXT_ACCELERATING: u8 = 0x14;
    pub const NEXT_DECELERATING: u8 = 0x15;
    pub const NEXT_CRUISING: u8 = 0x16;
    pub const FEED_HOLD: u8 = 0x20;
    pub const FEED_RESUME: u8 = 0x21;
    pub const DROP_QUEUE: u8 = 0x22;
    pub const EMERGENCY_STOP: u8 = 0x30;
    pub const RESET: u8 = 0x31;
    pub const QUERY_STATE: u8 = 0x40;
    pub const QUERY_COUNTERS: u8 = 0x41;

    pub const IDENTITY: u8 = 0x81;
    pub const CLOCK: u8 = 0x82;
    pub const STATE: u8 = 0x83;
    pub const COUNTERS: u8 = 0x84;
    pub const FAULT: u8 = 0x85;
}

/// A payload being written; every message fits (the largest is 60 bytes).
struct Writer {
    buf: [u8; MAX_PAYLOAD],
    len: usize,
}

impl Writer {
    fn new(kind: u8) -> Writer {
        let mut buf = [0; MAX_PAYLOAD];
        buf[0] = kind;
        Writer { buf, len: 1 }
    }
    fn bytes(&mut self, bytes: &[u8]) -> &mut Self {
        self.buf[self.len..self.len + bytes.len()].copy_from_slice(bytes);
        self.len += bytes.len();
        self
    }
    fn u8(&mut self, v: u8) -> &mut Self {
        self.bytes(&[v])
    }
    fn u16(&mut self, v: u16) -> &mut Self {
        self.bytes(&v.to_le_bytes())
    }
    fn u32(&mut self, v: u32) -> &mut Self {
        self.bytes(&v.to_le_bytes())
    }
    fn i32(&mut self, v: i32) -> &mut Self {
        self.bytes(&v.to_le_bytes())
    }
    fn u64(&mut self, v: u64) -> &mut Self {
        self.bytes(&v.to_le_bytes())
    }
    /// A message in one of the compact forms, its fields written by `write`.
    fn compact(kind: u8, write: impl FnOnce(&mut compact::CompactWriter)) -> Writer {
        let mut w = Writer::new(kind);
        let mut c = compact::CompactWriter {
            out: &mut w.buf,
            len: w.len,
        };
        write(&mut c);
        w.len = c.len;
        w
    }
    fn finish(&self, out: &mut [u8; MAX_PAYLOAD]) -> usize {
        out[..self.len].copy_from_slice(&self.buf[..self.len]);
        self.len
    }
}

/// A fixed-layout message being read, whose length was checked against the kind's layout
/// first.
struct Reader<'a> {
    kind: u8,
    rest: &'a [u8],
}

impl<'a> Reader<'a> {
    /// The message of `len` bytes (kind byte included) at the start of `bytes`.
    fn new(bytes: &'a [u8], len: usize) -> Result<Reader<'a>, MessageError> {
        if bytes.len() < len {
            return Err(MessageError::Length {
                kind: bytes[0],
                expected: len,
                actual: bytes.len(),
            });
        }
        Ok(Reader {
            kind: bytes[0],
            rest: &bytes[1..len],
        })
    }
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let (head, tail) = self.rest.split_at(N);
        self.rest = tail;
        head.try_into().expect("split_at gave N bytes")
    }
    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn i32(&mut self) -> i32 {
        i32::from_le_bytes(self.take())
    }
    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
    fn bool(&mut self, field: &'static str) -> Result<bool, MessageError> {
        match self.u8() {
            0 => Ok(false),
            1 => Ok(true),
            value => Err(self.bad(field, value as u64)),
        }
    }
    fn bad(&self, field: &'static str, value: u64) -> MessageError {
        MessageError::BadValue {
            kind: self.kind,
            field,
            value,
        }
    }
}

/// A payload that holds more than the one message at its start.
fn exactly(payload: &[u8], len: usize) -> Result<(), MessageError> {
    if payload.len() == len {
        Ok(())
    } else {
        Err(MessageError::Length {
            kind: payload[0],
            expected: len,
            actual: payload.len(),
        })
    }
}

/// The messages of a payload in order. After the first that does not decode, nothing more:
/// its length is unknown, so whatever follows cannot be found.
pub struct Messages<'a, M> {
    rest: &'a [u8],
    decode: DecodePrefix<M>,
}

/// Decodes the message at the start of some bytes, returning it and its length.
type DecodePrefix<M> = fn(&[u8]) -> Result<(M, usize), MessageError>;

impl<M> Iterator for Messages<'_, M> {
    type Item = Result<M, MessageError>;
    fn next(&mut self) -> Option<Self::Item> {
        if self.rest.is_empty() {
            return None;
        }
        match (self.decode)(self.rest) {
            Ok((message, len)) => {
                self.rest = &self.rest[len..];
                Some(Ok(message))
            }
            Err(e) => {
                self.rest = &[];
                Some(Err(e))
            }
        }
    }
}

/// The host messages of a payload (one or more).
pub fn host_messages(payload: &[u8]) -> Messages<'_, HostMessage> {
    Messages {
        rest: payload,
        decode: HostMessage::decode_prefix,
    }
}

/// The MCU messages of a payload (one or more).
pub fn mcu_messages(payload: &[u8]) -> Messages<'_, McuMessage> {
    Messages {
        rest: payload,
        decode: McuMessage::decode_prefix,
    }
}

/// Encoded size of a [`Segment`].
const SEGMENT_LEN: usize = 4 * MAX_AXES + 2 + 3 * 4 + 2 * 8;

fn write_segment(w: &mut Writer, s: &Segment) {
    for &count in &s.step_counts {
        w.u32(count);
    }
    w.u8(s.negative_mask)
        .u8(s.dominant_axis)
        .u32(s.accelerate_steps)
        .u32(s.cruise_steps)
        .u32(s.decelerate_steps)
        .u64(s.first_period_q32)
        .u64(s.first_ramp_q62);
}

fn read_segment(r: &mut Reader) -> Segment {
    let mut step_counts = [0; MAX_AXES];
    for count in &mut step_counts {
        *count = r.u32();
    }
    Segment {
        step_counts,
        negative_mask: r.u8(),
        dominant_axis: r.u8(),
        accelerate_steps: r.u32(),
        cruise_steps: r.u32(),
        decelerate_steps: r.u32(),
        first_period_q32: r.u64(),
        first_ramp_q62: r.u64(),
    }
}

impl HostMessage {
    /// Write the payload into `out`; returns its length.
    pub fn encode(&self, out: &mut [u8; MAX_PAYLOAD]) -> usize {
        use HostMessage::*;
        let w = match self {
            Identify => Writer::new(kind::IDENTIFY),
            ClockQuery { token } => {
                let mut w = Writer::new(kind::CLOCK_QUERY);
                w.u32(*token);
                w
            }
            Configure {
                host_timeout_ticks,
                state_period_ticks,
            } => {
                let mut w = Writer::new(kind::CONFIGURE);
                w.u32(*host_timeout_ticks).u32(*state_period_ticks);
                w
            }
            QueueSegment(q) => {
                let mut w = Writer::new(kind::QUEUE_SEGMENT);
                w.u64(q.start_clock)
                    .u32(q.duration_ticks)
                    .u32(q.tag)
                    .u8(q.flags);
                write_segment(&mut w, &q.segment);
                w
            }
            NextSegment(n) => {
                let kind = match compact::Shape::of(n.segment()) {
                    compact::Shape::Given => kind::NEXT_SEGMENT,
                    compact::Shape::Accelerating => kind::NEXT_ACCELERATING,
                    compact::Shape::Decelerating => kind::NEXT_DECELERATING,
                    compact::Shape::Cruising => kind::NEXT_CRUISING,
                };
                Writer::compact(kind, |c| compact::write_next_segment(c, n))
            }
            ScrewNext(s) => Writer::compact(kind::SCREW_NEXT, |c| compact::write_screw_next(c, s)),
            Screw(s) => {
                let mut w = Writer::new(kind::SCREW);
                w.u64(s.start_clock)
                    .u32(s.ramp_ticks)
                    .i32(s.target_millirpm)
                    .u8(s.pin_open as u8);
                w
            }
            FeedHold { rate_q32 } => {
                let mut w = Writer::new(kind::FEED_HOLD);
                w.u32(*rate_q32);
                w
            }
            FeedResume {
                rate_q32,
                delay_ticks,
            } => {
                let mut w = Writer::new(kind::FEED_RESUME);
                w.u32(*rate_q32).u32(*delay_ticks);
                w
            }
            DropQueue => Writer::new(kind::DROP_QUEUE),
            EmergencyStop => Writer::new(kind::EMERGENCY_STOP),
            Reset => Writer::new(kind::RESET),
            QueryState => Writer::new(kind::QUERY_STATE),
            QueryCounters => Writer::new(kind::QUERY_COUNTERS),
        };
        w.finish(out)
    }

    /// The payload as exactly one message.
    pub fn decode(payload: &[u8]) -> Result<HostMessage, MessageError> {
        let (message, len) = HostMessage::decode_prefix(payload)?;
        exactly(payload, len)?;
        Ok(message)
    }

    /// The message at the start of `bytes`, and its length.
    pub fn decode_prefix(bytes: &[u8]) -> Result<(HostMessage, usize), MessageError> {
        use HostMessage::*;
        let &kind = bytes.first().ok_or(MessageError::Empty)?;
        let shape = match kind {
            kind::NEXT_SEGMENT => Some(compact::Shape::Given),
            kind::NEXT_ACCELERATING => Some(compact::Shape::Accelerating),
            kind::NEXT_DECELERATING => Some(compact::Shape::Decelerating),
            kind::NEXT_CRUISING => Some(compact::Shape::Cruising),
            _ => None,
        };
        if shape.is_some() || kind == kind::SCREW_NEXT {
            let mut r = compact::CompactReader {
                kind,
                rest: &bytes[1..],
            };
            let message = match shape {
                Some(shape) => NextSegment(compact::read_next_segment(&mut r, shape)?),
                None => ScrewNext(compact::read_screw_next(&mut r)?),
            };
            return Ok((message, bytes.len() - r.rest.len()));
        }
        let mut len = 0;
        let mut reader = |n| {
            len = n;
            Reader::new(bytes, n)
        };
        let message = match kind {
            kind::IDENTIFY => {
                reader(1)?;
                Identify
            }
            kind::CLOCK_QUERY => ClockQuery {
                token: reader(5)?.u32(),
            },
            kind::CONFIGURE => {
                let mut r = reader(9)?;
                Configure {
                    host_timeout_ticks: r.u32(),
                    state_period_ticks: r.u32(),
                }
            }
            kind::QUEUE_SEGMENT => {
                let mut r = reader(18 + SEGMENT_LEN)?;
                let start_clock = r.u64();
                let duration_ticks = r.u32();
                let tag = r.u32();
                let flags = r.u8();
                if flags & !SEGMENT_ENDS_AT_REST != 0 {
                    return Err(r.bad("flags", flags as u64));
                }
                QueueSegment(QueuedSegment {
                    start_clock,
                    duration_ticks,
                    tag,
                    flags,
                    segment: read_segment(&mut r),
                })
            }
            kind::SCREW => {
                let mut r = reader(18)?;
                Screw(ScrewRamp {
                    start_clock: r.u64(),
                    ramp_ticks: r.u32(),
                    target_millirpm: r.i32(),
                    pin_open: r.bool("pin_open")?,
                })
            }
            kind::FEED_HOLD => FeedHold {
                rate_q32: reader(5)?.u32(),
            },
            kind::FEED_RESUME => {
                let mut r = reader(9)?;
                FeedResume {
                    rate_q32: r.u32(),
                    delay_ticks: r.u32(),
                }
            }
            kind::DROP_QUEUE => {
                reader(1)?;
                DropQueue
            }
            kind::EMERGENCY_STOP => {
                reader(1)?;
                EmergencyStop
            }
            kind::RESET => {
                reader(1)?;
                Reset
            }
            kind::QUERY_STATE => {
                reader(1)?;
                QueryState
            }
            kind::QUERY_COUNTERS => {
                reader(1)?;
                QueryCounters
            }
            kind => return Err(MessageError::UnknownKind { kind }),
        };
        Ok((message, len))
    }

    /// Whether the MCU answers the message (with identity, clock, state or counters). A frame
    /// carries at most one such message, so the MCU's room for replies is one per frame.
    pub fn asks_reply(&self) -> bool {
        use HostMessage::*;
        matches!(
            self,
            Identify | ClockQuery { .. } | QueryState | QueryCounters
        )
    }

    /// Whether the message goes sequenced (delivered once, in order). Only the emergency stop
    /// does not: it must act even when an earlier frame is missing, and the host repeats it
    /// until the MCU reports the fault.
    pub fn is_sequenced(&self) -> bool {
        !matches!(self, HostMessage::EmergencyStop)
    }
}

impl Mode {
    fn from_u8(value: u8) -> Option<Mode> {
        Some(match value {
            0 => Mode::Idle,
            1 => Mode::Running,
            2 => Mode::Ramping,
            3 => Mode::Held,
            4 => Mode::Fault,
            _ => return None,
        })
    }
}

impl FaultCode {
    fn from_u8(value: u8) -> Option<FaultCode> {
        use FaultCode::*;
        Some(match value {
            0 => None,
            1 => LateSegment,
            2 => Underrun,
            3 => HostSilent,
            4 => EmergencyStop,
            5 => BadSegment,
            6 => QueueOverflow,
            7 => StepFault,
            8 => DropWhileMoving,
            _ => return Option::None,
        })
    }
}

fn read_fault(r: &mut Reader) -> Result<FaultCode, MessageError> {
    let value = r.u8();
    FaultCode::from_u8(value).ok_or_else(|| r.bad("fault", value as u64))
}

impl McuMessage {
    /// Write the payload into `out`; returns its length.
    pub fn encode(&self, out: &mut [u8; MAX_PAYLOAD]) -> usize {
        let w = match self {
            McuMessage::Identity(i) => {
                let mut w = Writer::new(kind::IDENTITY);
                w.u16(i.protocol_version)
                    .u32(i.timer_hz)
                    .u16(i.queue_capacity)
                    .u8(i.axis_count)
                    .u16(i.screw_queue_capacity);
                w
            }
            McuMessage::Clock { token, clock } => {
                let mut w = Writer::new(kind::CLOCK);
                w.u32(*token).u64(*clock);
                w
            }
            McuMessage::State(s) => {
                let mut w = Writer::new(kind::STATE);
                w.u64(s.clock).u64(s.plan_clock);
                for &p in &s.position_steps {
                    w.i32(p);
                }
                w.i32(s.screw_millirpm)
                    .i32(s.screw_angle_millirev)
                    .u8(s.pin_open as u8)
                    .u16(s.queue_free)
                    .u32(s.done_tag)
                    .u16(s.feed_scale_q16)
                    .u8(s.mode as u8)
                    .u8(s.fault as u8);
                w
            }
            McuMessage::Counters(c) => {
                let mut w = Writer::new(kind::COUNTERS);
                w.u32(c.frames_received)
                    .u32(c.crc_errors)
                    .u32(c.framing_errors)
                    .u32(c.naks_sent)
                    .u32(c.retransmits)
                    .u32(c.underruns)
                    .u32(c.late_segments);
                w
            }
            McuMessage::Fault { code, clock, tag } => {
                let mut w = Writer::new(kind::FAULT);
                w.u8(*code as u8).u64(*clock).u32(*tag);
                w
            }
        };
        w.finish(out)
    }

    /// The payload as exactly one message.
    pub fn decode(payload: &[u8]) -> Result<McuMessage, MessageError> {
        let (message, len) = McuMessage::decode_prefix(payload)?;
        exactly(payload, len)?;
        Ok(message)
    }

    /// The message at the start of `bytes`, and its length.
    pub fn decode_prefix(bytes: &[u8]) -> Result<(McuMessage, usize), MessageError> {
        let &kind = bytes.first().ok_or(MessageError::Empty)?;
        let mut len = 0;
        let mut reader = |n| {
            len = n;
            Reader::new(bytes, n)
        };
        let message = match kind {
            kind::IDENTITY => {
                let mut r = reader(12)?;
                McuMessage::Identity(Identity {
                    protocol_version: r.u16(),
                    timer_hz: r.u32(),
                    queue_capacity: r.u16(),
                    axis_count: r.u8(),
                    screw_queue_capacity: r.u16(),
                })
            }
            kind::CLOCK => {
                let mut r = reader(13)?;
                McuMessage::Clock {
                    token: r.u32(),
                    clock: r.u64(),
                }
            }
            kind::STATE => {
                let mut r = reader(17 + 4 * MAX_AXES + 19)?;
                let clock = r.u64();
                let plan_clock = r.u64();
                let mut position_steps = [0; MAX_AXES];
                for p in &mut position_steps {
                    *p = r.i32();
                }
                let screw_millirpm = r.i32();
                let screw_angle_millirev = r.i32();
                let pin_open = r.bool("pin_open")?;
                let queue_free = r.u16();
                let done_tag = r.u32();
                let feed_scale_q16 = r.u16();
                let mode_byte = r.u8();
                let mode =
                    Mode::from_u8(mode_byte).ok_or_else(|| r.bad("mode", mode_byte as u64))?;
                McuMessage::State(McuState {
                    clock,
                    plan_clock,
                    position_steps,
                    screw_millirpm,
                    screw_angle_millirev,
                    pin_open,
                    queue_free,
                    done_tag,
                    feed_scale_q16,
                    mode,
                    fault: read_fault(&mut r)?,
                })
            }
            kind::COUNTERS => {
                let mut r = reader(29)?;
                McuMessage::Counters(McuCounters {
                    frames_received: r.u32(),
                    crc_errors: r.u32(),
                    framing_errors: r.u32(),
                    naks_sent: r.u32(),
                    retransmits: r.u32(),
                    underruns: r.u32(),
                    late_segments: r.u32(),
                })
            }
            kind::FAULT => {
                let mut r = reader(14)?;
                McuMessage::Fault {
                    code: read_fault(&mut r)?,
                    clock: r.u64(),
                    tag: r.u32(),
                }
            }
            kind => return Err(MessageError::UnknownKind { kind }),
        };
        Ok((message, len))
    }

    /// Whether the message goes sequenced. Periodic state is best effort (the next one
    /// supersedes a lost one, and a full window must never hold telemetry back); replies and
    /// faults are sequenced.
    pub fn is_sequenced(&self) -> bool {
        !matches!(self, McuMessage::State(_))
    }
}

#[cfg(test)]
mod tests;
