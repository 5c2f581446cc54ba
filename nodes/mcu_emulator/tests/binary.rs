//! The `mcu_emulator` binary as the bridge meets it: a pseudo-terminal or a Unix socket,
//! real time (at `--speed`), a schedule played and its edges recorded, faults on the line.

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use cell_protocol::message::{
    FaultCode, HostMessage, McuMessage, Mode, QueuedSegment, SEGMENT_ENDS_AT_REST,
};
use cell_protocol::MAX_WIRE_FRAME;
use mcu_bridge::{FromMcu, HostEndpoint};
use step_core::{Segment, SegmentFields};

struct Emulator {
    child: Child,
    /// `pty PATH` or `socket PATH`.
    port: String,
}

impl Emulator {
    fn start(args: &[&str]) -> Emulator {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mcu_emulator"))
            .args(args)
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        Emulator {
            child,
            port: line.trim().to_string(),
        }
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

trait Line: Read + Write {}
impl<T: Read + Write> Line for T {}

fn open(port: &str) -> Box<dyn Line> {
    let (kind, path) = port.split_once(' ').unwrap();
    match kind {
        "socket" => {
            let s = std::os::unix::net::UnixStream::connect(path).unwrap();
            s.set_read_timeout(Some(Duration::from_millis(2))).unwrap();
            Box::new(s)
        }
        "pty" => {
            use std::os::unix::fs::OpenOptionsExt;
            let f = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .custom_flags(nix::fcntl::OFlag::O_NONBLOCK.bits())
                .open(path)
                .unwrap();
            Box::new(f)
        }
        other => panic!("unknown port {other}"),
    }
}

/// Talk to the emulator for `seconds` of wall time, sending `to_send` as the window allows.
fn talk(
    line: &mut dyn Line,
    host: &mut HostEndpoint,
    to_send: &mut Vec<HostMessage>,
    seconds: f64,
    received: &mut Vec<FromMcu>,
) {
    let start = Instant::now();
    let mut buf = [0u8; 4096];
    let mut out = [0u8; MAX_WIRE_FRAME];
    while start.elapsed().as_secs_f64() < seconds {
        let now_us = start.elapsed().as_micros() as u64;
        while !to_send.is_empty() && host.can_send() {
            host.send(&to_send.remove(0)).unwrap();
        }
        while let Some(len) = host.poll_transmit(now_us, &mut out) {
            line.write_all(&out[..len]).unwrap();
        }
        match line.read(&mut buf) {
            Ok(n) => host.receive(&buf[..n], now_us, &mut |m| received.push(m)),
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                std::thread::sleep(Duration::from_millis(1))
            }
            Err(e) => panic!("{e}"),
        }
    }
}

/// Ask the MCU's clock and wait for the answer.
fn clock_now(line: &mut dyn Line, host: &mut HostEndpoint, token: u32) -> u64 {
    let mut received = Vec::new();
    let mut query = vec![HostMessage::ClockQuery { token }];
    for _ in 0..100 {
        talk(line, host, &mut query, 0.005, &mut received);
        let reply = received.iter().find_map(|m| match m {
            FromMcu::Message(McuMessage::Clock { token: t, clock }) if *t == token => Some(*clock),
            _ => None,
        });
        if let Some(clock) = reply {
            return clock;
        }
    }
    panic!("no clock reply");
}

fn cruise(start: u64, steps: u32, period: f64, flags: u8, tag: u32) -> QueuedSegment {
    QueuedSegment {
        start_clock: start,
        duration_ticks: (steps as f64 * period) as u32,
        tag,
        flags,
        segment: Segment::from_fields(&SegmentFields {
            step_counts: [steps, steps / 2, 0],
            directions: [1, 1, -1],
            dominant_axis: 0,
            cruise_period_ticks: period,
            cruise_steps: steps,
            ..SegmentFields::default()
        })
        .unwrap(),
    }
}

/// Ask for the state until an answer arrives (a state is unsequenced: a damaged line may
/// lose it, and the protocol lets the next one replace it).
/// Everything else that arrives meanwhile goes to `received`.
fn state_now(
    line: &mut dyn Line,
    host: &mut HostEndpoint,
    received: &mut Vec<FromMcu>,
) -> cell_protocol::message::McuState {
    for _ in 0..50 {
        let from = received.len();
        let mut query = vec![HostMessage::QueryState];
        talk(line, host, &mut query, 0.02, received);
        let state = received[from..].iter().rev().find_map(|m| match m {
            FromMcu::Message(McuMessage::State(s)) => Some(*s),
            _ => None,
        });
        if let Some(state) = state {
            return state;
        }
    }
    panic!("no state");
}

/// A schedule through each kind of port, at 10× speed over a line that corrupts, drops and
/// duplicates bytes: every edge where it belongs, in the edge file.
#[test]
fn a_schedule_plays_exactly_through_socket_and_pty() {
    for socket in [true, false] {
        let dir =
            std::env::temp_dir().join(format!("mcu_emulator_test_{}_{socket}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let edges_path = dir.join("edges.csv");
        let socket_path = dir.join("mcu.sock");
        let mut args = vec![
            "--speed".to_string(),
            "10".into(),
            "--corrupt-rate".into(),
            "0.0005".into(),
            "--drop-rate".into(),
            "0.0005".into(),
            "--duplicate-rate".into(),
            "0.0005".into(),
            "--offset-ticks".into(),
            "1000000".into(),
            "--edges".into(),
            edges_path.display().to_string(),
        ];
        if socket {
            args.extend(["--socket".to_string(), socket_path.display().to_string()]);
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let emulator = Emulator::start(&args);
        let mut line = open(&emulator.port);
        let mut host = HostEndpoint::new(20_000, 99);
        let mut received = Vec::new();
        let mut to_send = vec![HostMessage::Identify];
        talk(&mut *line, &mut host, &mut to_send, 0.05, &mut received);
        let clock = clock_now(&mut *line, &mut host, 1);
        assert!(clock >= 1_000_000, "the offset is there: {clock}");
        // 20 segments of 500 steps at 100 ticks (1 s of MCU time, 0.1 s at 10×), starting
        // 1 s of MCU time (0.1 s of wall time: room for a loaded machine) after the clock
        // read.
        let start = clock + 1_000_000;
        let mut schedule: Vec<HostMessage> = (0..20u32)
            .map(|k| {
                let flags = if k == 19 { SEGMENT_ENDS_AT_REST } else { 0 };
                HostMessage::QueueSegment(cruise(
                    start + k as u64 * 50_000,
                    500,
                    100.0,
                    flags,
                    k + 1,
                ))
            })
            .collect();
        talk(&mut *line, &mut host, &mut schedule, 0.4, &mut received);
        assert!(schedule.is_empty());
        // Asked after the schedule's end.
        let state = state_now(&mut *line, &mut host, &mut received);
        assert_eq!(state.fault, FaultCode::None, "{}: {state:?}", emulator.port);
        assert_eq!((state.mode, state.done_tag), (Mode::Idle, 20));
        assert_eq!(state.position_steps, [10_000, 5_000, 0]);
        drop(emulator);
        let edges = std::fs::read_to_string(&edges_path).unwrap();
        let ticks: Vec<u64> = edges
            .lines()
            .map(|l| l.split(',').next().unwrap().parse().unwrap())
            .collect();
        let expected: Vec<u64> = (1..=10_000).map(|i| start + 100 * i).collect();
        assert_eq!(ticks, expected);
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// The bridge gone: a silent host makes the MCU stop and say why.
#[test]
fn a_silent_host_stops_the_machine() {
    let emulator = Emulator::start(&["--speed", "10"]);
    let mut line = open(&emulator.port);
    let mut host = HostEndpoint::new(20_000, 7);
    let mut received = Vec::new();
    let mut to_send = vec![HostMessage::Configure {
        host_timeout_ticks: 2_000_000,
        state_period_ticks: 0,
    }];
    talk(&mut *line, &mut host, &mut to_send, 0.02, &mut received);
    let clock = clock_now(&mut *line, &mut host, 2);
    // 100,000 steps: 10 s of MCU time, far more than the test waits.
    let mut schedule = vec![HostMessage::QueueSegment(cruise(
        clock + 1_000_000,
        100_000,
        100.0,
        SEGMENT_ENDS_AT_REST,
        5,
    ))];
    talk(&mut *line, &mut host, &mut schedule, 0.05, &mut received);
    // Silent for 0.3 s of wall time = 3 s of MCU time, beyond the 2 s timeout.
    std::thread::sleep(Duration::from_millis(300));
    let state = state_now(&mut *line, &mut host, &mut received);
    assert!(received.iter().any(|m| matches!(
        m,
        FromMcu::Message(McuMessage::Fault {
            code: FaultCode::HostSilent,
            tag: 0,
            ..
        })
    )));
    assert_eq!(
        (state.mode, state.fault),
        (Mode::Fault, FaultCode::HostSilent)
    );
    assert!(state.position_steps[0] > 0 && state.position_steps[0] < 100_000);
}

/// The emulator's exit status and standard error for `args` (it must refuse to start).
fn refused(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_mcu_emulator"))
        .args(args)
        .stdout(Stdio::null())
        .output()
        .unwrap();
    assert!(!out.status.success(), "{args:?} started");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// `--socket` removes only a socket nobody listens on: never a file of the user's, never a
/// running emulator's socket; and a crystal it cannot be is refused by name.
#[test]
fn the_socket_path_and_the_crystal_are_checked() {
    let dir = std::env::temp_dir().join(format!("mcu_emulator_refusals_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("out.mcap");
    std::fs::write(&file, b"a bag").unwrap();
    let why = refused(&["--socket", file.to_str().unwrap()]);
    assert!(why.contains("not a socket"), "{why}");
    assert_eq!(std::fs::read(&file).unwrap(), b"a bag");

    let socket = dir.join("mcu.sock");
    let socket_arg = socket.display().to_string();
    let first = Emulator::start(&["--socket", &socket_arg]);
    assert_eq!(first.port, format!("socket {socket_arg}"));
    let why = refused(&["--socket", &socket_arg]);
    assert!(why.contains("another process listens"), "{why}");
    drop(first);
    // The killed emulator's socket is stale: the next one takes its place.
    let second = Emulator::start(&["--socket", &socket_arg]);
    assert_eq!(second.port, format!("socket {socket_arg}"));
    drop(second);

    for (args, names) in [
        (&["--timer-hz", "0"][..], "--timer-hz 0"),
        (&["--timer-hz", "NaN"], "--timer-hz NaN"),
        (&["--timer-hz", "1000000.5"], "--timer-hz 1000000.5"),
        (&["--timer-hz", "5e9"], "--timer-hz 5000000000"),
        (&["--rate-ppm", "-2000000"], "--rate-ppm -2000000"),
        (&["--drift-ppm-per-s", "inf"], "--drift-ppm-per-s inf"),
        // A link's timeout of a few ticks resent on every pass.
        (&["--timer-hz", "10"], "--timer-hz 10"),
        (
            &["--offset-ticks", "18446744073709551615"],
            "--offset-ticks 18446744073709551615",
        ),
        (
            &["--retransmit-timeout-ms", "0"],
            "--retransmit-timeout-ms 0",
        ),
    ] {
        let why = refused(args);
        assert!(why.contains(names), "{args:?}: {why}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
