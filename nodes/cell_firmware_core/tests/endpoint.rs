//! The MCU endpoint behind a byte pipe, driven by a host-side link as the bridge will drive
//! it: session start, identify, a schedule through a line that corrupts frames, periodic
//! state, and an emergency stop that acts even when the frame before it was lost.

use cell_firmware_core::{Endpoint, MachineConfig, StepEdge};
use cell_protocol::message::{
    FaultCode, HostMessage, McuMessage, Mode, QueuedSegment, SEGMENT_ENDS_AT_REST,
};
use cell_protocol::{LinkOptions, MAX_WIRE_FRAME, PROTOCOL_VERSION};
use mcu_bridge::{FromMcu, HostEndpoint};
use step_core::{Segment, SegmentFields};

type Mcu = Endpoint<16, 64, 16>;

/// The host: its endpoint and everything the MCU sent it.
struct Host {
    endpoint: HostEndpoint,
    received: Vec<McuMessage>,
}

impl Host {
    fn new() -> Host {
        Host {
            endpoint: HostEndpoint::new(2_000, 0x1234_5678),
            received: Vec::new(),
        }
    }

    fn send(&mut self, m: HostMessage) {
        self.endpoint.send(&m).unwrap();
    }
}

fn mcu() -> Mcu {
    Endpoint::new(
        MachineConfig {
            timer_hz: 1_000_000,
            axis_count: 3,
            initial_steps: [0; 3],
        },
        LinkOptions {
            window: 16,
            retransmit_timeout: 2_000,
            nonce: 0xC0FFEE,
        },
    )
}

/// One exchange at MCU clock `now`: host → MCU (with `corrupt` deciding per frame), MCU
/// generates to `now`, MCU → host.
fn exchange(
    host: &mut Host,
    mcu: &mut Mcu,
    now: u64,
    corrupt: &mut impl FnMut() -> bool,
    edges: &mut Vec<StepEdge>,
) {
    exchange_generating_ahead(host, mcu, now, 0, corrupt, edges);
}

/// [`exchange`] with the MCU's generator `lead` ticks ahead of its link's clock, as the
/// RP2040 firmware runs it (edges queued ahead of the pins).
fn exchange_generating_ahead(
    host: &mut Host,
    mcu: &mut Mcu,
    now: u64,
    lead: u64,
    corrupt: &mut impl FnMut() -> bool,
    edges: &mut Vec<StepEdge>,
) {
    let mut out = [0; MAX_WIRE_FRAME];
    while let Some(len) = host.endpoint.poll_transmit(now, &mut out) {
        let mut bytes = out[..len].to_vec();
        if corrupt() {
            bytes[len / 2] ^= 0x21;
        }
        mcu.receive(&bytes, now);
    }
    mcu.advance(now + lead, &mut |e| edges.push(e));
    while let Some(len) = mcu.poll_transmit(now, &mut out) {
        let received = &mut host.received;
        host.endpoint.receive(&out[..len], now, &mut |m| match m {
            FromMcu::Message(m) => received.push(m),
            other => panic!("{other:?}"),
        });
    }
}

/// Five exchanges 100 ticks apart from clock 0, so that the session is up: the clock after.
fn start_session(host: &mut Host, mcu: &mut Mcu, edges: &mut Vec<StepEdge>) -> u64 {
    let mut never = || false;
    let mut now = 0;
    for _ in 0..5 {
        exchange(host, mcu, now, &mut never, edges);
        now += 100;
    }
    now
}

fn cruise(start: u64, steps: u32, period: f64, flags: u8, tag: u32) -> QueuedSegment {
    QueuedSegment {
        start_clock: start,
        duration_ticks: (steps as f64 * period) as u32,
        tag,
        flags,
        segment: Segment::from_fields(&SegmentFields {
            step_counts: [steps, 0, steps / 4],
            directions: [-1, 1, 1],
            dominant_axis: 0,
            cruise_period_ticks: period,
            cruise_steps: steps,
            ..SegmentFields::default()
        })
        .unwrap(),
    }
}

#[test]
fn a_schedule_through_a_corrupting_line_plays_exactly() {
    let mut host = Host::new();
    let mut mcu = mcu();
    let mut edges = Vec::new();
    let mut n = 0u32;
    // Every fifth host frame arrives corrupted.
    let mut corrupt = || {
        n += 1;
        n.is_multiple_of(5)
    };
    host.send(HostMessage::Identify);
    host.send(HostMessage::Configure {
        host_timeout_ticks: 500_000,
        state_period_ticks: 20_000,
    });
    let mut now = 0;
    for _ in 0..50 {
        exchange(&mut host, &mut mcu, now, &mut corrupt, &mut edges);
        now += 100;
    }
    assert!(host.endpoint.link().is_synced());
    let identities: Vec<_> = host
        .received
        .iter()
        .filter_map(|m| match m {
            McuMessage::Identity(i) => Some(*i),
            _ => None,
        })
        .collect();
    assert_eq!(identities.len(), 1, "answered once");
    assert_eq!(
        (identities[0].protocol_version, identities[0].queue_capacity),
        (PROTOCOL_VERSION, 64)
    );
    // 40 segments of 100 steps at 50 ticks, back to back from 10 ms.
    for k in 0..40u32 {
        let flags = if k == 39 { SEGMENT_ENDS_AT_REST } else { 0 };
        host.send(HostMessage::QueueSegment(cruise(
            10_000 + k as u64 * 5_000,
            100,
            50.0,
            flags,
            k + 1,
        )));
        if !host.endpoint.can_send() {
            for _ in 0..5 {
                exchange(&mut host, &mut mcu, now, &mut corrupt, &mut edges);
                now += 100;
            }
        }
    }
    while now < 260_000 {
        exchange(&mut host, &mut mcu, now, &mut corrupt, &mut edges);
        now += 100;
    }
    let machine = mcu.machine();
    assert_eq!(machine.fault(), FaultCode::None);
    assert_eq!(machine.positions(), [-4000, 0, 1000]);
    assert_eq!(edges.len(), 4000);
    let ticks: Vec<u64> = edges.iter().map(|e| e.clock).collect();
    let expected: Vec<u64> = (1..=4000).map(|i| 10_000 + 50 * i).collect();
    assert_eq!(ticks, expected);
    assert!(mcu.counters().crc_errors + mcu.counters().framing_errors > 0);
    assert!(mcu.link_counters().naks_sent > 0);
    assert!(host.endpoint.link().counters().retransmits > 0);
    // Periodic state arrived, the last one idle at the end.
    let states: Vec<_> = host
        .received
        .iter()
        .filter_map(|m| match m {
            McuMessage::State(s) => Some(*s),
            _ => None,
        })
        .collect();
    assert!(states.len() >= 10, "{} states", states.len());
    let last = states.last().unwrap();
    assert_eq!(
        (last.mode, last.done_tag, last.position_steps),
        (Mode::Idle, 40, [-4000, 0, 1000])
    );
}

/// A host whose session nonce starts with EMERGENCY_STOP's byte (0x30, one session in 256)
/// starts a session like any other: the nonce is the link's, not a message. The MCU looked
/// for an emergency stop in every frame's bytes and stopped at once.
#[test]
fn a_session_nonce_that_looks_like_an_emergency_stop_is_not_one() {
    let mut host = Host {
        endpoint: HostEndpoint::new(2_000, 0x1234_5630),
        received: Vec::new(),
    };
    let mut mcu = mcu();
    let mut edges = Vec::new();
    let mut never = || false;
    let mut now = start_session(&mut host, &mut mcu, &mut edges);
    host.send(HostMessage::QueueSegment(cruise(
        1_000,
        100,
        100.0,
        SEGMENT_ENDS_AT_REST,
        1,
    )));
    for _ in 0..200 {
        exchange(&mut host, &mut mcu, now, &mut never, &mut edges);
        now += 100;
    }
    assert_eq!(mcu.machine().fault(), FaultCode::None);
    assert_eq!(edges.len(), 100, "the segment played");
}

/// A message the MCU cannot decode in a frame that passed its checks (a host speaking another
/// protocol, or a bug) may have been a segment: the MCU stops rather than play on without it.
#[test]
fn an_undecodable_message_is_a_fault() {
    let mut host = Host::new();
    let mut mcu = mcu();
    let mut edges = Vec::new();
    let now = start_session(&mut host, &mut mcu, &mut edges);
    assert_eq!(mcu.machine().fault(), FaultCode::None);
    let mut out = [0; MAX_WIRE_FRAME];
    let len = cell_protocol::encode_frame(
        &cell_protocol::FrameHeader::default(),
        &[0x7E], // no such kind
        &mut out,
    )
    .unwrap();
    mcu.receive(&out[..len], now);
    assert_eq!(mcu.machine().fault(), FaultCode::BadSegment);
    assert_eq!(mcu.bad_messages, 1);
}

#[test]
fn an_emergency_stop_acts_even_behind_a_lost_frame() {
    let mut host = Host::new();
    let mut mcu = mcu();
    let mut edges = Vec::new();
    let mut never = || false;
    let mut now = start_session(&mut host, &mut mcu, &mut edges);
    host.send(HostMessage::QueueSegment(cruise(1_000, 1000, 100.0, 0, 1)));
    exchange(&mut host, &mut mcu, now, &mut never, &mut edges);
    for _ in 0..100 {
        now += 100;
        exchange(&mut host, &mut mcu, now, &mut never, &mut edges);
    }
    let before = edges.len();
    assert!(before > 80, "{before} edges");
    // A sequenced frame is lost on the line, then the emergency stop (unsequenced) arrives.
    host.send(HostMessage::QueryState);
    let mut out = [0; MAX_WIRE_FRAME];
    while host.endpoint.poll_transmit(now, &mut out).is_some() {}
    let len = host
        .endpoint
        .encode_now(&HostMessage::EmergencyStop, &mut out)
        .unwrap();
    mcu.receive(&out[..len], now);
    mcu.advance(now + 50_000, &mut |e| edges.push(e));
    assert_eq!(edges.len(), before, "not one step after the stop");
    assert_eq!(mcu.machine().fault(), FaultCode::EmergencyStop);
    assert!(!mcu.machine().pin_open());
    // The host hears about it.
    exchange(&mut host, &mut mcu, now + 50_000, &mut never, &mut edges);
    assert!(host.received.iter().any(|m| matches!(
        m,
        McuMessage::Fault {
            code: FaultCode::EmergencyStop,
            ..
        }
    )));
}

#[test]
fn a_generator_ahead_of_the_link_reports_its_own_clock_with_its_positions() {
    const LEAD: u64 = 2_000;
    let mut host = Host::new();
    let mut mcu = mcu();
    let mut edges = Vec::new();
    let mut never = || false;
    host.send(HostMessage::Configure {
        host_timeout_ticks: 500_000,
        state_period_ticks: 1_000,
    });
    let mut now = 0;
    for _ in 0..5 {
        exchange_generating_ahead(&mut host, &mut mcu, now, LEAD, &mut never, &mut edges);
        now += 100;
    }
    // 1000 steps, one per 100 ticks, from clock 10,000.
    host.send(HostMessage::QueueSegment(cruise(10_000, 1000, 100.0, 0, 1)));
    while now < 40_000 {
        exchange_generating_ahead(&mut host, &mut mcu, now, LEAD, &mut never, &mut edges);
        now += 100;
    }
    host.send(HostMessage::ClockQuery { token: 9 });
    exchange_generating_ahead(&mut host, &mut mcu, now, LEAD, &mut never, &mut edges);
    // The clock reply is the link's (the timer the pins follow)...
    let clock_reply = host.received.iter().find_map(|m| match m {
        McuMessage::Clock { token: 9, clock } => Some(*clock),
        _ => None,
    });
    assert_eq!(clock_reply, Some(now));
    // ...the edges were generated LEAD ahead of it...
    assert_eq!(edges.last().map(|e| e.clock), Some(now + LEAD));
    // ...and every state pairs the generator's clock with the positions at that clock:
    // bed −1 per 100 ticks from 10,000, z +1 per 400.
    let states: Vec<_> = host
        .received
        .iter()
        .filter_map(|m| match m {
            McuMessage::State(s) if s.clock > 10_000 => Some(*s),
            _ => None,
        })
        .collect();
    assert!(states.len() > 20, "{} states", states.len());
    for state in states {
        let bed_steps = ((state.clock - 10_000) / 100) as i32;
        assert_eq!(
            state.position_steps[0], -bed_steps,
            "at clock {}",
            state.clock
        );
        assert_eq!(state.plan_clock, state.clock);
    }
}

/// Positions after every edge, with the edge's clock.
fn positions_after(edges: &[StepEdge], from: [i32; 3]) -> Vec<(u64, [i32; 3])> {
    let mut at = from;
    edges
        .iter()
        .map(|e| {
            for (k, position) in at.iter_mut().enumerate() {
                if e.axes & (1 << k) != 0 {
                    *position += if e.negative & (1 << k) != 0 { -1 } else { 1 };
                }
            }
            (e.clock, at)
        })
        .collect()
}

#[test]
fn the_start_switch_plays_seed_001s_program_and_a_host_takes_it_away() {
    use cell_firmware_core::seed_program::SEED_001_MOVES;
    let mut mcu = mcu();
    let mut edges = Vec::new();
    mcu.advance(5_000, &mut |e| edges.push(e));
    assert!(mcu.start_seed_program(5_000, 10_000));
    // Pressed again while it runs: ignored.
    mcu.advance(20_000, &mut |e| edges.push(e));
    assert!(!mcu.start_seed_program(20_000, 10_000));
    mcu.advance(30_000_000, &mut |e| edges.push(e));
    assert_eq!(mcu.machine().fault(), FaultCode::None);
    assert_eq!(mcu.machine().mode(), Mode::Idle);
    assert_eq!(mcu.machine().positions(), [0, 0, 0]);
    // Every target is reached, in order, at the end of its move: 2.5 ms per step at 400/s,
    // 4 ms on the way home at 250/s; the first step one period after the 10 ms lead.
    let path = positions_after(&edges, [0; 3]);
    assert_eq!(path.first().unwrap().0, 5_000 + 10_000 + 2_500);
    let mut end = 5_000 + 10_000u64;
    let mut from = [0i32; 3];
    for &(target, rate) in &SEED_001_MOVES {
        let dominant = (0..3)
            .map(|k| (target[k] - from[k]).unsigned_abs())
            .max()
            .unwrap();
        end += dominant as u64 * 1_000_000 / rate as u64;
        let (clock, _) = path
            .iter()
            .find(|(c, p)| *c > end - 1_000 && *p == target)
            .unwrap();
        assert_eq!(*clock, end, "reached {target:?}");
        // One edge per dominant step, the followers stepping with it.
        let edges_in_move = path
            .iter()
            .filter(|(c, _)| *c <= end && *c > end - dominant as u64 * 1_000_000 / rate as u64)
            .count();
        assert_eq!(edges_in_move, dominant as usize);
        from = target;
    }
    assert_eq!(end, 5_000 + 10_000 + 23_750_000);
    assert_eq!(edges.len(), 1000 + 2000 + 1000 + 2000 + 1900 + 1000);
    // Pressed at rest again: it runs again (home to home).
    assert!(mcu.start_seed_program(30_000_000, 10_000));
    assert_eq!(mcu.machine().mode(), Mode::Running);

    // Once a host has configured the MCU, the switch does nothing.
    let mut host = Host::new();
    let mut mcu = self::mcu();
    let mut clean = || false;
    let mut edges = Vec::new();
    for now in (0..20_000).step_by(1_000) {
        exchange(&mut host, &mut mcu, now, &mut clean, &mut edges);
    }
    host.send(HostMessage::Configure {
        host_timeout_ticks: 0,
        state_period_ticks: 10_000,
    });
    for now in (20_000..40_000).step_by(1_000) {
        exchange(&mut host, &mut mcu, now, &mut clean, &mut edges);
    }
    assert!(mcu.machine().host_configured());
    assert!(!mcu.start_seed_program(40_000, 10_000));
    assert!(edges.is_empty());
}
