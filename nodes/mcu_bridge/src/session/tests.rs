use super::*;
use gcode_streamer::{parse_all, InterpreterOptions};
use mcu_emulator::{Crystal, Emulator, EmulatorOptions};
use polar_planner::steps::{decode, Pulse, StepOptions};
use polar_planner::{plan_program, PlannerOptions};

const RATE_PPM: f64 = 80.0;

/// The cell's: default steps, the planner's joint accelerations, the screw driver's pin delay.
fn session_options() -> SessionOptions {
    SessionOptions::new(
        StepOptions::default().steps_per_unit,
        std::array::from_fn(|j| PlannerOptions::default().joints[j].acceleration),
        0.25,
    )
}

fn finger_start(moves: usize) -> Vec<StepSegment> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/fixtures/gcode/finger.gcode"
    );
    let src = std::fs::read(path).unwrap();
    let mut all = parse_all(&src, "finger.gcode", InterpreterOptions::default())
        .unwrap()
        .0;
    all.truncate(moves);
    plan_program(&all, PlannerOptions::default(), StepOptions::default())
        .unwrap()
        .segments
}

/// Host and emulated MCU in one simulated time, 1 ms per round.
struct Rig {
    session: McuSession,
    mcu: Emulator,
    now_us: u64,
    edges: Vec<cell_firmware_core::StepEdge>,
    /// Largest lead of a sent segment's start over the MCU's plan clock (ticks).
    worst_lead: u64,
    /// From this instant the MCU's bytes never reach the host (a broken TX wire).
    deaf_from_us: u64,
}

impl Rig {
    fn new() -> Rig {
        Rig::with(EmulatorOptions::default())
    }

    fn with(options: EmulatorOptions) -> Rig {
        Rig {
            session: McuSession::new(session_options(), 0xB41D),
            mcu: Emulator::new(EmulatorOptions {
                crystal: Crystal {
                    timer_hz: 1e6,
                    offset_ticks: 7_777_777,
                    rate_ppm: RATE_PPM,
                    drift_ppm_per_s: 0.0,
                },
                ..options
            }),
            now_us: 0,
            edges: Vec::new(),
            worst_lead: 0,
            deaf_from_us: u64::MAX,
        }
    }

    fn round(&mut self) {
        let t = self.now_us as f64 * 1e-6;
        self.session.tick(self.now_us).unwrap();
        let mut out = [0; MAX_WIRE_FRAME];
        while let Some(len) = self.session.poll_transmit(self.now_us, &mut out) {
            self.mcu.receive(&out[..len], t);
        }
        let mut bytes = Vec::new();
        let edges = &mut self.edges;
        self.mcu.run_until(t, &mut |e| edges.push(e), &mut bytes);
        if self.now_us < self.deaf_from_us {
            self.session.receive(&bytes, self.now_us);
        }
        if let (Some(state), Some(sent)) = (self.session.state(), self.session.sent_until_clock()) {
            self.worst_lead = self.worst_lead.max(sent.saturating_sub(state.plan_clock));
        }
        self.now_us += 1000;
    }
}

#[test]
fn a_plan_reaches_the_mcu_within_the_horizon_and_plays_on_its_ticks() {
    let segments = finger_start(300);
    let mut rig = Rig::new();
    while !rig.session.is_ready() {
        rig.round();
        assert!(rig.now_us < 2_000_000, "no session after 2 s");
    }
    let ready_at = rig.now_us;
    for seg in &segments {
        rig.session.on_segment(seg, rig.now_us).unwrap();
    }
    let plan_s: f64 = segments.iter().map(|s| s.duration_s).sum();
    while !rig.session.is_drained() {
        rig.round();
        assert!(rig.session.error().is_none(), "{:?}", rig.session.error());
        assert!(
            (rig.now_us - ready_at) as f64 * 1e-6 < plan_s + 5.0,
            "not done after {plan_s} s of plan"
        );
    }
    // The MCU never held more than the horizon: what was sent started at most 2 s ahead of
    // its plan clock (as last reported, up to a state period and a round old).
    assert!(
        rig.worst_lead <= 2_000_000 + 25_000,
        "a segment {} ticks ahead",
        rig.worst_lead
    );
    // Every edge where the planner's decoder puts it, on the schedule's anchor.
    let anchor = rig.session.anchor_clock().unwrap() as f64;
    let mut expected: [Vec<f64>; 3] = Default::default();
    let mut start = 0.0f64;
    let mut pulses: Vec<Pulse> = Vec::new();
    for seg in &segments {
        pulses.clear();
        decode(seg, &mut pulses).unwrap();
        for p in &pulses {
            expected[p.axis].push(anchor + start + p.t * 1e6);
        }
        start += seg.duration_s * 1e6;
    }
    let mut worst = 0.0f64;
    for (k, expected) in expected.iter().enumerate() {
        let executed: Vec<u64> = rig
            .edges
            .iter()
            .filter(|e| e.axes >> k & 1 == 1)
            .map(|e| e.clock)
            .collect();
        assert_eq!(executed.len(), expected.len(), "axis {k}");
        for (&e, &x) in executed.iter().zip(expected) {
            worst = worst.max((e as f64 - x).abs());
        }
    }
    assert!(worst <= 1.0, "worst edge {worst} ticks");
    // The clock fit found the crystal's rate error (the simulated round trips are 1 ms
    // rounds, so the midpoint errs by up to half of one).
    let ppm = rig.session.clock_sync().rate_error_ppm().unwrap();
    assert!((ppm - RATE_PPM).abs() < 50.0, "{ppm} ppm");
    eprintln!(
        "{} segments, {} edges, worst edge {worst:.3} ticks, plan {plan_s:.2} s, played by {:.2} s; \
         clock rate error estimated {ppm:.1} ppm (true {RATE_PPM}); most queued ahead {:.3} s",
        segments.len(),
        rig.edges.len(),
        (rig.now_us - ready_at) as f64 * 1e-6,
        rig.worst_lead as f64 * 1e-6
    );
}

/// Start a rig and hand it `segments` once the session is ready.
fn printing(options: EmulatorOptions, segments: &[StepSegment]) -> Rig {
    let mut rig = Rig::with(options);
    while !rig.session.is_ready() {
        rig.round();
    }
    for seg in segments {
        rig.session.on_segment(seg, rig.now_us).unwrap();
    }
    rig
}

#[test]
fn an_emergency_stop_stops_the_steps_within_a_round() {
    let mut rig = printing(EmulatorOptions::default(), &finger_start(300));
    for _ in 0..3000 {
        rig.round();
    }
    let before = rig.edges.len();
    assert!(before > 1000, "{before}");
    rig.session.emergency_stop();
    rig.round();
    let at_stop = rig.edges.len();
    for _ in 0..1000 {
        rig.round();
    }
    assert_eq!(
        rig.edges.len(),
        at_stop,
        "no step after the stop reached the MCU"
    );
    let machine = rig.mcu.endpoint().machine();
    assert_eq!(machine.fault(), FaultCode::EmergencyStop);
    assert!(!machine.pin_open());
    assert_eq!(
        rig.session.state().map(|s| s.fault),
        Some(FaultCode::EmergencyStop)
    );
}

/// An emergency stop asked of an MCU that a fault has already stopped goes out, and is not
/// repeated once the MCU reports that fault: its outputs are stopped, and it keeps its first
/// fault (PROTOCOL.md §3). The host used to repeat it until the MCU said EMERGENCY_STOP, that
/// is every retransmit timeout until a reset.
#[test]
fn an_emergency_stop_of_a_faulted_mcu_is_not_repeated_for_ever() {
    let mut rig = printing(EmulatorOptions::default(), &finger_start(300));
    for _ in 0..1000 {
        rig.round();
    }
    // The host falls silent for 1.5 s: the MCU's watchdog (1 s) latches HOST_SILENT.
    for _ in 0..1500 {
        let t = rig.now_us as f64 * 1e-6;
        let mut bytes = Vec::new();
        let edges = &mut rig.edges;
        rig.mcu.run_until(t, &mut |e| edges.push(e), &mut bytes);
        rig.session.receive(&bytes, rig.now_us);
        rig.now_us += 1000;
    }
    assert_eq!(rig.mcu.endpoint().machine().fault(), FaultCode::HostSilent);
    rig.session.emergency_stop();
    let mut emergency_frames = 0;
    let mut decoder = cell_protocol::FrameDecoder::new();
    for _ in 0..3000 {
        let t = rig.now_us as f64 * 1e-6;
        let _ = rig.session.tick(rig.now_us);
        let mut out = [0; MAX_WIRE_FRAME];
        while let Some(len) = rig.session.poll_transmit(rig.now_us, &mut out) {
            for &byte in &out[..len] {
                if let Some(Ok(frame)) = decoder.push(byte) {
                    emergency_frames += cell_protocol::message::host_messages(frame.payload)
                        .filter(|m| *m == Ok(HostMessage::EmergencyStop))
                        .count();
                }
            }
            rig.mcu.receive(&out[..len], t);
        }
        let mut bytes = Vec::new();
        let edges = &mut rig.edges;
        rig.mcu.run_until(t, &mut |e| edges.push(e), &mut bytes);
        rig.session.receive(&bytes, rig.now_us);
        rig.now_us += 1000;
    }
    assert_eq!(
        rig.session.state().map(|s| s.fault),
        Some(FaultCode::HostSilent),
        "the first fault is kept"
    );
    assert_eq!(emergency_frames, 1, "sent once, in 3 s");
    assert!(!rig.mcu.endpoint().machine().pin_open());
}

#[test]
fn a_restarted_or_silent_mcu_is_a_fault_of_the_print() {
    // A power cycle 4 s in.
    let mut rig = printing(
        EmulatorOptions {
            reset_at_s: Some(4.0),
            ..EmulatorOptions::default()
        },
        &finger_start(300),
    );
    while rig.session.error().is_none() && rig.now_us < 10_000_000 {
        rig.round();
    }
    assert!(
        matches!(rig.session.error(), Some(SessionError::Restarted { .. })),
        "{:?}",
        rig.session.error()
    );
    assert_eq!(
        rig.session.waiting(),
        (0, 0),
        "nothing more goes to a lost machine"
    );

    // A hung MCU (stalled 2 s from 4 s): the host notices within its silence bound.
    let mut rig = printing(
        EmulatorOptions {
            stall: Some(mcu_emulator::Window {
                at_s: 4.0,
                for_s: 2.0,
            }),
            ..EmulatorOptions::default()
        },
        &finger_start(300),
    );
    while rig.session.error().is_none() && rig.now_us < 10_000_000 {
        rig.round();
    }
    match rig.session.error() {
        Some(SessionError::Silent { silent_s }) => assert!(*silent_s <= 0.26, "{silent_s}"),
        other => panic!("{other:?}"),
    }
    assert!(rig.now_us < 4_300_000, "noticed at {} µs", rig.now_us);

    // The MCU's reports stop reaching the host (its TX wire broken) while it prints: the
    // host's frames still reach it, and one of them must stop it. (Before, the host only
    // gave up: its clock queries kept the MCU's watchdog fed, and it played its whole queue
    // into an underrun at speed.)
    let mut rig = printing(EmulatorOptions::default(), &finger_start(300));
    rig.deaf_from_us = rig.now_us + 3_000_000;
    while rig.session.error().is_none() && rig.now_us < 10_000_000 {
        rig.round();
    }
    assert!(matches!(
        rig.session.error(),
        Some(SessionError::Silent { .. })
    ));
    let noticed_us = rig.now_us;
    let edges_then = rig.edges.len();
    for _ in 0..100 {
        rig.round();
    }
    let machine = rig.mcu.endpoint().machine();
    assert_eq!(
        machine.fault(),
        FaultCode::EmergencyStop,
        "at {noticed_us} µs"
    );
    assert!(!machine.pin_open());
    assert!(
        rig.edges.len() - edges_then < 200,
        "{} steps after the host gave up",
        rig.edges.len() - edges_then
    );
}

/// Paused mid-print and resumed: the MCU comes to rest on the path quickly and holds still,
/// and the print makes the very same steps in the same order as without the pause.
#[test]
fn a_pause_holds_on_the_path_and_resume_makes_the_same_steps() {
    let segments = finger_start(300);
    let plain = {
        let mut rig = printing(EmulatorOptions::default(), &segments);
        while !rig.session.is_drained() {
            rig.round();
        }
        rig.edges
    };
    let mut rig = printing(EmulatorOptions::default(), &segments);
    // Into the print until the steps come fast: over 2,000 in the last 100 ms.
    loop {
        rig.round();
        let recent = rig
            .edges
            .iter()
            .rev()
            .take_while(|e| e.clock + 100_000 > rig.edges.last().map_or(0, |l| l.clock));
        if recent.count() > 2000 {
            break;
        }
        assert!(!rig.session.is_drained(), "never fast");
    }
    // σ falls at ρ per second: at rest 1/ρ after the hold begins.
    let rho = rig.session.sigma_rate_q32() as f64 / step_core::ONE_TICK_Q32 as f64 * 1e6;
    rig.session.pause().unwrap();
    let paused_at = rig.edges.len();
    for _ in 0..2000 {
        rig.round();
    }
    let held = rig.edges.len();
    let state = *rig.session.state().unwrap();
    assert_eq!(state.mode, Mode::Held, "{state:?}");
    assert!(!state.pin_open);
    for _ in 0..500 {
        rig.round();
    }
    assert_eq!(rig.edges.len(), held, "held still");
    // The last step before rest comes within 1/ρ of the pause (plus the round it took to
    // arrive), not later.
    let stop_ticks = rig.edges[paused_at..]
        .last()
        .map_or(0, |e| e.clock - rig.edges[paused_at - 1].clock);
    assert!(
        (stop_ticks as f64) < (1.0 / rho + 0.002) * 1e6,
        "last step {stop_ticks} ticks after the pause, σ rate {rho}/s"
    );
    rig.session.resume().unwrap();
    while !rig.session.is_drained() {
        rig.round();
        assert!(rig.session.error().is_none(), "{:?}", rig.session.error());
    }
    let shape = |e: &[cell_firmware_core::StepEdge]| {
        e.iter().map(|e| (e.axes, e.negative)).collect::<Vec<_>>()
    };
    assert_eq!(shape(&rig.edges), shape(&plain));
    assert_eq!(rig.mcu.endpoint().machine().positions(), {
        let mut m = printing(EmulatorOptions::default(), &segments);
        while !m.session.is_drained() {
            m.round();
        }
        m.mcu.endpoint().machine().positions()
    });
    eprintln!(
        "paused after {paused_at} edges at full speed; {} more on the way to rest, the last \
         {:.3} s after the pause (σ rate {rho:.2}/s: at rest within {:.3} s)",
        held - paused_at,
        stop_ticks as f64 * 1e-6,
        1.0 / rho
    );
}

#[test]
fn a_screw_command_too_late_for_its_start_starts_when_the_mcu_can_take_it() {
    let segments = finger_start(60);
    let mut rig = printing(EmulatorOptions::default(), &segments);
    // Half a second of the plan played before a command for plan time 0.1 s arrives (a screw
    // driver that fell behind, a pin opening due before the plan began).
    let anchor = rig.session.anchor_clock().unwrap();
    while rig
        .session
        .state()
        .is_none_or(|s| s.plan_clock < anchor + 500_000)
    {
        rig.round();
    }
    let command = ScrewCommand {
        rpm: 42.0,
        pin_open: true,
        ..ScrewCommand::default()
    };
    rig.session.on_screw(&command, 0.1, rig.now_us).unwrap();
    for _ in 0..100 {
        rig.round();
    }
    assert!(rig.session.error().is_none(), "{:?}", rig.session.error());
    let state = rig.session.state().unwrap();
    assert_eq!((state.screw_millirpm, state.pin_open), (42_000, true));
    assert_eq!(rig.session.screw_late, 1);
    // It was due 0.4 s and more before it could go; it went out the margin ahead instead.
    let late_s = rig.session.screw_late_worst_ticks as f64 * 1e-6;
    assert!((0.4..0.5).contains(&late_s), "late by {late_s} s");
}

/// A command for the plan's last instant that arrives once the MCU stands there (the screw
/// driver's final stop, published late) starts there: the plan clock stands, so a margin
/// past it would never come, and the pin would stay open after the print.
#[test]
fn a_screw_command_for_a_standing_plan_clock_starts_where_it_stands() {
    let segments = finger_start(20);
    let plan_s: f64 = segments.iter().map(|s| s.duration_s).sum();
    let mut rig = printing(EmulatorOptions::default(), &segments);
    while !rig.session.is_drained() {
        rig.round();
        assert!(rig.now_us < 60_000_000, "not played");
    }
    for _ in 0..50 {
        rig.round(); // at rest at the end, the plan clock standing
    }
    let command = ScrewCommand {
        rpm: 42.0,
        pin_open: true,
        ..ScrewCommand::default()
    };
    rig.session.on_screw(&command, plan_s, rig.now_us).unwrap();
    assert!(
        !rig.session.is_drained(),
        "a command not yet sent is not drained"
    );
    for _ in 0..100 {
        rig.round();
    }
    assert!(rig.session.error().is_none(), "{:?}", rig.session.error());
    let state = rig.session.state().unwrap();
    assert_eq!((state.screw_millirpm, state.pin_open), (42_000, true));
    assert_eq!(rig.session.screw_late, 0, "due where the plan clock stands");
    assert!(rig.session.is_drained());
}

/// The same moves printed twice end on the same tag, and the MCU keeps its done tag: right
/// after the second plan is sent, the last state (idle, done with that tag, from before the
/// segments arrived) must not pass for the plan played (a node took the print as done at
/// once and left the MCU printing unattended until its watchdog cut it off).
#[test]
fn a_state_from_before_the_last_segments_is_not_the_end_of_the_plan() {
    // A short plan (well under the feed's horizon): 3 mm out and back.
    let moves = parse_all(
        b"G91\nG1 X3 F1200\nG1 X-3\n",
        "short.gcode",
        InterpreterOptions::default(),
    )
    .unwrap()
    .0;
    let plan = plan_program(&moves, PlannerOptions::default(), StepOptions::default())
        .unwrap()
        .segments;
    let mut rig = printing(EmulatorOptions::default(), &plan);
    while !rig.session.is_drained() && rig.now_us < 30_000_000 {
        rig.round();
    }
    assert!(rig.session.is_drained());
    let first_run_edges = rig.edges.len();
    assert!(first_run_edges > 100, "{first_run_edges}");
    rig.session.drop_plan().unwrap();
    for _ in 0..50 {
        rig.round();
    }
    for seg in &plan {
        rig.session.on_segment(seg, rig.now_us).unwrap();
    }
    rig.session.tick(rig.now_us).unwrap();
    let mut out = [0; MAX_WIRE_FRAME];
    while let Some(len) = rig.session.poll_transmit(rig.now_us, &mut out) {
        rig.mcu.receive(&out[..len], rig.now_us as f64 * 1e-6);
    }
    assert_eq!(rig.session.waiting().0, 0, "the plan went out in one feed");
    let stale = rig.session.state().unwrap();
    assert_eq!(stale.mode, Mode::Idle);
    assert!(!rig.session.is_drained(), "done before it began: {stale:?}");
    while !rig.session.is_drained() && rig.now_us < 60_000_000 {
        rig.round();
    }
    assert_eq!(
        rig.edges.len(),
        2 * first_run_edges,
        "the second run played whole"
    );
}

/// Nothing answers (a wrong device, a wrong baud rate): the session fails after its answer
/// timeout, saying what it waited for, instead of offering no room for ever.
#[test]
fn a_device_that_never_answers_fails_the_session_with_what_is_missing() {
    let mut session = McuSession::new(session_options(), 7);
    let mut out = [0; MAX_WIRE_FRAME];
    let mut now_us = 1_000_000;
    while session.error().is_none() && now_us < 20_000_000 {
        session.tick(now_us).unwrap();
        while session.poll_transmit(now_us, &mut out).is_some() {}
        session.receive(b"garbage, not frames", now_us);
        now_us += 10_000;
    }
    match session.error() {
        Some(SessionError::NoAnswer { waited_s, missing }) => {
            assert!((5.0..5.1).contains(waited_s), "{waited_s}");
            assert!(missing.contains("SYNC_REQUEST"), "{missing}");
        }
        other => panic!("{other:?}"),
    }
    // An MCU that answers is ready well within the bound, and stays free of the error.
    let mut rig = Rig::new();
    for _ in 0..10_000 {
        rig.round();
    }
    assert!(rig.session.is_ready());
    assert!(rig.session.error().is_none(), "{:?}", rig.session.error());
}

/// The MCU's bytes with its IDENTITY changed by `edit` (frames re-encoded with their
/// headers, so the link takes them as the MCU's own).
fn with_identity_edited(
    bytes: &[u8],
    decoder: &mut cell_protocol::FrameDecoder,
    edit: fn(&mut cell_protocol::message::Identity),
) -> Vec<u8> {
    use cell_protocol::message::mcu_messages;
    use cell_protocol::MAX_PAYLOAD;
    let mut out = Vec::new();
    for &byte in bytes {
        let Some(Ok(frame)) = decoder.push(byte) else {
            continue;
        };
        let mut payload = Vec::new();
        match frame.messages() {
            Some(messages) => {
                for message in mcu_messages(messages) {
                    let mut message = message.unwrap();
                    if let McuMessage::Identity(identity) = &mut message {
                        edit(identity);
                    }
                    let mut buf = [0; MAX_PAYLOAD];
                    let len = message.encode(&mut buf);
                    payload.extend_from_slice(&buf[..len]);
                }
            }
            None => payload.extend_from_slice(frame.payload),
        }
        let mut wire = [0; MAX_WIRE_FRAME];
        let len = cell_protocol::encode_frame(&frame.header, &payload, &mut wire).unwrap();
        out.extend_from_slice(&wire[..len]);
    }
    out
}

/// `rounds` more milliseconds of the session with the MCU's IDENTITY changed by `edit`.
fn run_identified_as(
    rig: &mut Rig,
    decoder: &mut cell_protocol::FrameDecoder,
    edit: fn(&mut cell_protocol::message::Identity),
    rounds: usize,
) {
    for _ in 0..rounds {
        let t = rig.now_us as f64 * 1e-6;
        rig.session.tick(rig.now_us).unwrap();
        let mut out = [0; MAX_WIRE_FRAME];
        while let Some(len) = rig.session.poll_transmit(rig.now_us, &mut out) {
            rig.mcu.receive(&out[..len], t);
        }
        let mut bytes = Vec::new();
        rig.mcu.run_until(t, &mut |_| {}, &mut bytes);
        let edited = with_identity_edited(&bytes, decoder, edit);
        rig.session.receive(&edited, rig.now_us);
        rig.now_us += 1000;
    }
}

/// Two simulated seconds of a session with the MCU's IDENTITY changed by `edit`.
fn identified_as(edit: fn(&mut cell_protocol::message::Identity)) -> Rig {
    let mut rig = Rig::new();
    run_identified_as(
        &mut rig,
        &mut cell_protocol::FrameDecoder::new(),
        edit,
        2000,
    );
    rig
}

/// An MCU speaking another protocol version may read a RESET as anything: it is sent none,
/// neither when it identifies itself nor on an operator's reset.
#[test]
fn an_mcu_of_another_version_is_never_sent_a_reset() {
    let other_version = |i: &mut cell_protocol::message::Identity| i.protocol_version += 1;
    let mut rig = Rig::new();
    let mut decoder = cell_protocol::FrameDecoder::new();
    run_identified_as(&mut rig, &mut decoder, other_version, 2000);
    assert!(
        matches!(rig.session.error(), Some(SessionError::Version { .. })),
        "{:?}",
        rig.session.error()
    );
    rig.session.reset().unwrap();
    // What the host writes from here on, read as the MCU would.
    let mut host_decoder = cell_protocol::FrameDecoder::new();
    let mut sent = Vec::new();
    for _ in 0..200 {
        rig.session.tick(rig.now_us).unwrap();
        let mut out = [0; MAX_WIRE_FRAME];
        while let Some(n) = rig.session.poll_transmit(rig.now_us, &mut out) {
            for &byte in &out[..n] {
                if let Some(Ok(frame)) = host_decoder.push(byte) {
                    if let Some(messages) = frame.messages() {
                        sent.extend(
                            cell_protocol::message::host_messages(messages).map(|m| m.unwrap()),
                        );
                    }
                }
            }
        }
        rig.now_us += 1000;
    }
    assert!(!sent.is_empty(), "the host went silent");
    assert!(
        !sent.iter().any(|m| matches!(m, HostMessage::Reset)),
        "{sent:?}"
    );
    assert!(!rig.session.is_ready());
}

/// An MCU that could not run a plan from this host — here one with a single place for screw
/// commands, which the host (keeping one free for a command not yet taken up) would never
/// fill, so a print never ended; or one without a timer — fails the session at once, saying
/// what it lacks, and an operator's reset does not make it ready.
#[test]
fn an_mcu_without_room_for_a_plan_fails_the_session_saying_why() {
    let one_screw_place = |i: &mut cell_protocol::message::Identity| i.screw_queue_capacity = 1;
    let mut rig = Rig::new();
    let mut decoder = cell_protocol::FrameDecoder::new();
    run_identified_as(&mut rig, &mut decoder, one_screw_place, 2000);
    match rig.session.error() {
        Some(SessionError::Unusable {
            timer_hz: 1_000_000,
            screw_queue_capacity: 1,
            ..
        }) => {}
        other => panic!("{other:?}"),
    }
    let message = rig.session.error().unwrap().to_string();
    assert!(message.contains("2 screw places"), "{message}");
    rig.session.reset().unwrap();
    run_identified_as(&mut rig, &mut decoder, one_screw_place, 2000);
    assert!(!rig.session.is_ready(), "ready after a reset");
    let rig = identified_as(|i| i.timer_hz = 0);
    assert!(
        matches!(
            rig.session.error(),
            Some(SessionError::Unusable { timer_hz: 0, .. })
        ),
        "{:?}",
        rig.session.error()
    );
    // Unedited (the frames taken apart and made again), the same MCU is ready and well.
    let rig = identified_as(|_| {});
    assert!(rig.session.is_ready(), "{:?}", rig.session.error());
    assert!(rig.session.error().is_none(), "{:?}", rig.session.error());
}
