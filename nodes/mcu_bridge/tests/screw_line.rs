//! The screw on an ASCII serial line (seed 000 §6.3's servo amplifier), tried two ways:
//!
//! * a print on the emulated MCU with the screw's lines written to a real pseudo-terminal,
//!   whose other side — a peer written here — parses and logs every line it receives;
//! * the material each move of finger.gcode gets through the extruder's flow model when the
//!   screw is told at most 2 to 50 times a second (a measurement; the figures are printed).

mod common;
#[path = "../../screw_driver/tests/common/mod.rs"]
mod screw_common;

use std::fs::File;
use std::io::Read;
use std::os::fd::{AsFd, OwnedFd};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use cell_machine::Machine;
use common::{finger_start, mcu_machine, EPOCH_NS};
use mcu_bridge::node::{Device, SerialLink};
use mcu_bridge::screw_line::DEFAULT_TEMPLATE;
use mcu_bridge::{CommandTemplate, LineClock, LinePort, ScrewLine, WithScrewLine};
use mcu_emulator::EmulatorOptions;
use polar_cell_msgs::{Header, Hold, ScrewCommand, StepSegment, Time};

/// The bridge's serial port, with what it wrote when (machine ns, plan s) kept for the test.
struct Logged {
    port: SerialLink,
    sent: Vec<(i64, String)>,
    /// Fail every send after this many (an adapter unplugged).
    fail_after: Option<usize>,
}

impl LinePort for Logged {
    type Error = mcu_bridge::node::DeviceError;
    fn send(&mut self, now_ns: i64, text: &str) -> Result<(), Self::Error> {
        if self.fail_after.is_some_and(|n| self.sent.len() >= n) {
            return Err(mcu_bridge::node::DeviceError::Closed {
                device: "the amplifier".into(),
            });
        }
        self.sent.push((now_ns, text.to_string()));
        self.port.send(now_ns, text)
    }
}

/// The amplifier's stand-in: reads the pseudo-terminal's master side until told to stop and
/// the line is quiet, and parses each `RPM r PIN p` line.
fn peer(master: OwnedFd, stop: Arc<AtomicBool>) -> Peer {
    std::thread::spawn(move || {
        use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
        let mut file = File::from(master);
        let mut bytes = Vec::new();
        loop {
            let ready = {
                let mut fds = [PollFd::new(file.as_fd(), PollFlags::POLLIN)];
                poll(&mut fds, PollTimeout::from(100u8)).unwrap() > 0
            };
            if ready {
                let mut buf = [0u8; 4096];
                match file.read(&mut buf) {
                    Ok(n) => bytes.extend_from_slice(&buf[..n]),
                    // The bridge closed its side: all it wrote has been read.
                    Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => break,
                    Err(e) => panic!("{e}"),
                }
            } else if stop.load(Ordering::Relaxed) {
                break;
            }
        }
        let text = String::from_utf8(bytes).expect("ASCII lines");
        assert!(text.ends_with("\r\n"), "a line cut short: {text:?}");
        text.trim_end_matches("\r\n")
            .split("\r\n")
            .map(|line| {
                let words: Vec<&str> = line.split(' ').collect();
                assert!(
                    words.len() == 4 && words[0] == "RPM" && words[2] == "PIN",
                    "{line:?}"
                );
                (words[1].parse().unwrap(), words[3] == "1")
            })
            .collect()
    })
}

/// The screw driver's commands as a print on the line's 0.1 s grid would give them (held
/// exact averages), and faster ones in between: rpm `40 + 30 sin t` with the pin open from
/// 0.5 s to half a second before the end, a command every 0.1 s and one 30 ms after each.
fn screw_commands(plan_end_s: f64) -> Vec<(f64, f64, bool)> {
    let mut commands = Vec::new();
    let mut k = 0;
    loop {
        let t = k as f64 / 10.0;
        if t > plan_end_s {
            break;
        }
        for at in [t, t + 0.03] {
            let open = (0.5..plan_end_s - 0.5).contains(&at);
            let rpm = if open { 40.0 + 30.0 * at.sin() } else { 0.0 };
            commands.push((at, rpm, open));
        }
        k += 1;
    }
    commands.push((plan_end_s, 0.0, false));
    commands
}

fn screw_message((t, rpm, pin_open): (f64, f64, bool)) -> ScrewCommand {
    ScrewCommand {
        header: Header {
            stamp: Time::after(EPOCH_NS, t),
            frame_id: String::new(),
        },
        rpm,
        pin_open,
        source_line: 0,
        model: "polar_speed".into(),
        ..ScrewCommand::default()
    }
}

/// The peer's thread: what it parsed, once told to stop.
type Peer = std::thread::JoinHandle<Vec<(f64, bool)>>;

type Rig = WithScrewLine<mcu_bridge::McuMachine<common::InProcess>, Logged>;

/// The MCU machine with its screw on a fresh pseudo-terminal (7E2 at 9600 baud), a peer
/// reading the other side.
fn rig() -> (Rig, Arc<AtomicBool>, Peer) {
    let pty = nix::pty::openpty(None, None).unwrap();
    let path = nix::unistd::ttyname(pty.slave.as_fd()).unwrap();
    let (device, name) =
        Device::open_framed(path.to_str().unwrap(), 9600, "7E2".parse().unwrap()).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let reader = peer(pty.master, stop.clone());
    let line = ScrewLine::new(
        CommandTemplate::parse(DEFAULT_TEMPLATE).unwrap(),
        10.0,
        Hold::ZeroOrder,
    );
    let port = Logged {
        port: SerialLink::new(device, name),
        sent: Vec::new(),
        fail_after: None,
    };
    let machine = WithScrewLine::new(mcu_machine(EmulatorOptions::default()), line, port, 64);
    // The slave side stays open in the bridge's device; this copy may go.
    drop(pty.slave);
    (machine, stop, reader)
}

/// finger's first 150 segments and the screw commands for them, as messages.
fn finger_plan() -> (Vec<StepSegment>, Vec<ScrewCommand>) {
    let segments = finger_start(150);
    let plan_end_s: f64 = segments.iter().map(|s| s.duration_s).sum();
    let messages = screw_commands(plan_end_s)
        .into_iter()
        .map(screw_message)
        .collect();
    (segments, messages)
}

/// What `run` tells its `done` after each tick.
struct Tick {
    now_ns: i64,
    all_fed: bool,
    /// The tick's answer (an error once the machine failed).
    ok: bool,
}

/// Feed what there is room for and tick every millisecond until `done` says so; the plan
/// time at each tick.
fn run(
    machine: &mut Rig,
    segments: &[StepSegment],
    screw: &[ScrewCommand],
    mut done: impl FnMut(&mut Rig, Tick) -> bool,
) -> Vec<(i64, f64)> {
    let (mut fed, mut fed_screw, mut now_ns) = (0, 0, 0i64);
    let mut plan_times = Vec::new();
    loop {
        let (room, screw_room) = machine.free_slots();
        for s in segments[fed..].iter().take(room) {
            machine.on_segment(s).unwrap();
            fed += 1;
        }
        for c in screw[fed_screw..].iter().take(screw_room) {
            machine.on_screw(c).unwrap();
            fed_screw += 1;
        }
        if fed == segments.len() && fed_screw == screw.len() {
            machine.finish_input();
        }
        now_ns += 1_000_000;
        let ok = machine.on_tick(now_ns).is_ok();
        plan_times.push((now_ns, machine.state().plan_time_s));
        // The MCU's own screw output stays idle: the amplifier has the screw.
        assert_eq!(machine.inner().state().screw_rpm, 0.0);
        let all_fed = fed == segments.len() && fed_screw == screw.len();
        if done(
            machine,
            Tick {
                now_ns,
                all_fed,
                ok,
            },
        ) {
            return plan_times;
        }
        assert!(
            now_ns < 120_000_000_000,
            "not done in 120 s: fed {fed} of {} segments, {fed_screw} of {} screw commands, \
             machine drained {}, line {:?}",
            segments.len(),
            screw.len(),
            machine.inner().is_drained(),
            machine.counters()
        );
    }
}

/// A print on the emulated MCU: every line the bridge wrote reached the peer whole and in
/// order; lines are 0.1 s apart at least (less a 1 ms tick's lateness); the pin opens and
/// closes when the commands say, to the tick; the material told is the commanded profile's;
/// the screw ends stopped with the pin closed.
#[test]
fn a_print_tells_a_pseudo_terminal_peer_its_screw_at_most_ten_times_a_second() {
    let segments = finger_start(150);
    let plan_end_s: f64 = segments.iter().map(|s| s.duration_s).sum();
    assert!(plan_end_s > 20.0, "{plan_end_s} s of plan");
    let commands = screw_commands(plan_end_s);
    let messages: Vec<ScrewCommand> = commands.iter().copied().map(screw_message).collect();
    let (mut machine, stop, reader) = rig();
    let plan_times = run(&mut machine, &segments, &messages, |m, tick| {
        assert!(tick.ok);
        tick.all_fed && m.is_drained()
    });
    let sent = machine.port().sent.clone();
    drop(machine);
    stop.store(true, Ordering::Relaxed);
    let received = reader.join().unwrap();

    // Whole and in order: what the peer parsed is what was written (and the drop's stop is
    // not a line more: the screw had stopped).
    let written: Vec<(f64, bool)> = sent
        .iter()
        .map(|(_, text)| {
            let w: Vec<&str> = text.trim_end().split(' ').collect();
            (w[1].parse().unwrap(), w[3] == "1")
        })
        .collect();
    assert_eq!(received, written);
    assert_eq!(sent.last().unwrap().1, "RPM 0.0 PIN 0\r\n");
    assert!(sent.len() > 150, "{} lines", sent.len());
    // A period apart (less a tick): the plan's closing of the pin too, which is no stop.
    for w in sent.windows(2) {
        assert!(w[1].0 - w[0].0 >= 99_000_000, "{:?}", w);
    }
    let plan_at = |ns: i64| plan_times.iter().find(|(t, _)| *t == ns).unwrap().1;
    // The pin: open at 0.5 s of plan, closed at the end less 0.5 s (to the grid's next
    // 0.1 s: the close falls between two lines), each to a tick.
    let opened = sent.iter().find(|(_, t)| t.ends_with("PIN 1\r\n")).unwrap();
    assert!(
        (plan_at(opened.0) - 0.5).abs() <= 0.0011,
        "{}",
        plan_at(opened.0)
    );
    let closed = sent
        .iter()
        .rev()
        .find(|(_, t)| t.ends_with("PIN 1\r\n"))
        .map(|(ns, _)| sent.iter().find(|(at, _)| at > ns).unwrap())
        .unwrap();
    let close_s = commands.iter().rev().find(|c| c.2).unwrap().0 + 0.03;
    assert!(
        plan_at(closed.0) >= close_s - 0.0011 && plan_at(closed.0) <= close_s + 0.1011,
        "closed at {} for {close_s}",
        plan_at(closed.0)
    );
    // Material: each line held from its plan time to the next's, against the commands held.
    let told: f64 = sent
        .windows(2)
        .zip(&written)
        .map(|(w, (rpm, _))| rpm * (plan_at(w[1].0) - plan_at(w[0].0)))
        .sum();
    let commanded: f64 = commands
        .windows(2)
        .map(|w| w[0].1 * (w[1].0 - w[0].0))
        .sum();
    println!(
        "{} lines over {plan_end_s:.1} s of plan: {told:.2} rpm·s told for {commanded:.2} commanded",
        sent.len()
    );
    assert!(
        (told / commanded - 1.0).abs() < 2e-3,
        "{told} rpm·s told, {commanded} commanded"
    );
}

/// An emergency stop mid-print stops the screw on the line at once — in the same tick, not
/// a tenth of a second later — and nothing follows.
#[test]
fn an_emergency_stop_reaches_the_amplifier_at_once() {
    let (segments, messages) = finger_plan();
    let (mut machine, stop, reader) = rig();
    let mut stopped_at = None;
    run(&mut machine, &segments, &messages, |m, tick| {
        assert!(tick.ok);
        let now_ns = tick.now_ns;
        if now_ns == 5_000_000_000 {
            // A line went out at most 1 ms ago if the grid just passed: stop anyway.
            m.emergency_stop();
            stopped_at = Some(now_ns);
        }
        now_ns >= 6_000_000_000
    });
    let sent = machine.port().sent.clone();
    drop(machine);
    stop.store(true, Ordering::Relaxed);
    let received = reader.join().unwrap();
    assert_eq!(received.len(), sent.len());
    let (last_ns, last) = sent.last().unwrap();
    assert_eq!(
        (Some(*last_ns), last.as_str()),
        (stopped_at, "RPM 0.0 PIN 0\r\n")
    );
    assert!(
        sent[sent.len() - 2].1.ends_with("PIN 1\r\n"),
        "it was running"
    );
}

/// A pause mid-print: while the steppers slow along the path the pin stays open and the
/// screw follows σ (never turning behind a closed pin); once the MCU holds at rest the line
/// says "rpm 0, pin closed" in that very tick, whatever the rate limit.
#[test]
fn a_pause_closes_the_pin_when_held_at_rest_and_never_turns_the_screw_behind_it() {
    let (segments, messages) = finger_plan();
    let (mut machine, stop, reader) = rig();
    let mut held_at = None;
    run(&mut machine, &segments, &messages, |m, tick| {
        assert!(tick.ok);
        if tick.now_ns == 5_000_000_000 {
            m.pause();
        }
        if tick.now_ns > 5_000_000_000 && m.state().state == cell_machine::PlayerState::Held {
            held_at.get_or_insert(tick.now_ns);
        }
        tick.now_ns >= 7_000_000_000
    });
    let held_at = held_at.expect("held at rest within 2 s");
    let sent = machine.port().sent.clone();
    drop(machine);
    stop.store(true, Ordering::Relaxed);
    let received = reader.join().unwrap();
    assert_eq!(received.len(), sent.len());
    for (at_ns, text) in &sent {
        assert!(
            text.ends_with("PIN 1\r\n") || text.starts_with("RPM 0.0 "),
            "{text:?} at {at_ns} ns: the screw turning behind a closed pin"
        );
    }
    // Slowing: the lines after the pause keep the pin open (the slowed path gets material).
    let slowing: Vec<_> = sent
        .iter()
        .filter(|(at, _)| (5_000_000_000..held_at).contains(at))
        .collect();
    assert!(
        slowing.iter().all(|(_, t)| t.ends_with("PIN 1\r\n")),
        "{slowing:?}"
    );
    // Held at rest: closed in the tick the MCU said so (or the one after), and nothing since.
    let closing = sent
        .iter()
        .position(|(at, _)| *at >= held_at)
        .expect("a line at the hold");
    assert!(
        sent[closing].0 <= held_at + 1_000_000,
        "{:?}",
        sent[closing]
    );
    assert_eq!(sent[closing].1, "RPM 0.0 PIN 0\r\n");
    assert_eq!(closing, sent.len() - 1, "{:?}", &sent[closing..]);
}

/// A line that failed mid-print and came back: the stop it could not write is written on a
/// later tick (the amplifier's state was unknown), not taken as done.
#[test]
fn a_stop_the_line_could_not_write_is_written_when_it_can() {
    let (segments, messages) = finger_plan();
    let (mut machine, stop, reader) = rig();
    let mut errors = 0;
    run(&mut machine, &segments, &messages, |m, tick| {
        errors += usize::from(!tick.ok);
        if tick.now_ns == 3_000_000_000 {
            machine_port_fails(m);
        }
        if tick.now_ns == 3_100_000_000 {
            m.port_mut().fail_after = None; // plugged back in
        }
        tick.now_ns >= 3_300_000_000
    });
    assert_eq!(errors, 1, "the failure is reported once");
    let sent = machine.port().sent.clone();
    let (last_ns, last) = sent.last().unwrap();
    assert_eq!(last, "RPM 0.0 PIN 0\r\n");
    // Tried again a period (0.1 s) after each failure, not every tick: written at the first
    // try after the line came back.
    assert!(
        (3_100_000_000..=3_200_000_000).contains(last_ns),
        "written at {last_ns}"
    );
    assert!(
        sent[sent.len() - 2].1.ends_with("PIN 1\r\n"),
        "it was running"
    );
    assert_eq!(machine.state().state, cell_machine::PlayerState::Stopped);
    drop(machine);
    stop.store(true, Ordering::Relaxed);
    reader.join().unwrap();
}

/// Before any plan the amplifier is told to stop: one left turning by an earlier session
/// stops, and a line that cannot be written fails at start-up.
#[test]
fn the_line_starts_with_a_stop() {
    let (mut machine, stop, reader) = rig();
    machine.start_stopped().unwrap();
    assert_eq!(machine.port().sent, [(0, "RPM 0.0 PIN 0\r\n".to_string())]);
    machine.port_mut().fail_after = Some(0);
    let err = machine.start_stopped().unwrap_err().to_string();
    assert!(err.starts_with("the screw's serial line: "), "{err}");
    drop(machine);
    stop.store(true, Ordering::Relaxed);
    assert_eq!(
        reader.join().unwrap().first(),
        Some(&(0.0, false)),
        "the peer parsed the stop"
    );
}

/// finger.gcode planned as the print plans it (slowed where the screw cannot keep up), its
/// screw commands flow-compensated on the line's grid, then through the line (polled every
/// millisecond) and the extruder's flow model: the material each extruding move receives.
#[test]
fn material_per_move_when_the_screw_is_told_at_most_n_times_a_second() {
    use screw_driver::compensation::{material_of_commands, FlowModel, MoveMaterial};
    use screw_driver::screw::{chunk_commands, Command, PinState, ScrewOptions};
    let model = FlowModel::default_extruder();
    let options = ScrewOptions {
        compensation: Some(model),
        ..ScrewOptions::default()
    };
    let planner = polar_planner::PlannerOptions {
        screw: Some(polar_planner::ScrewLimits {
            usable_rpm: 0.9 * options.max_rpm,
            e_per_rev_m: 0.002,
            flow_tau_s: model.tau_s,
        }),
        ..polar_planner::PlannerOptions::default()
    };
    let (moves, _) = screw_common::plan_and_time(&screw_common::fixture("finger.gcode"), planner);
    let summary = |r: &[MoveMaterial]| {
        let beyond = |e: f64| r.iter().filter(|m| m.error().abs() > e).count();
        let wanted: f64 = r.iter().map(|m| m.wanted_rpm_s).sum();
        let delivered: f64 = r.iter().map(|m| m.delivered_rpm_s).sum();
        (beyond(0.01), beyond(0.05), delivered / wanted - 1.0)
    };
    let material = |commands: &[Command]| {
        material_of_commands(&moves, commands, &model, options.pin_open_delay_s, 0.002)
    };
    // The screw driver's own grid (2 ms), no line.
    let direct = material(&chunk_commands(
        &moves,
        &options,
        &mut PinState::default(),
        true,
        0.0,
    ));
    let (d1, d5, dt) = summary(&direct);
    println!(
        "finger.gcode, {} extruding moves; beyond 1 % / 5 % of their material, total:",
        direct.len()
    );
    println!(
        "  no line (2 ms grid): {d1:5} / {d5:5}, {:+.3} %",
        dt * 100.0
    );
    let end_s = moves.last().unwrap().t.last().unwrap() + 1.0;
    let mut figures = Vec::new();
    for rate_hz in [50.0, 20.0, 10.0, 5.0, 2.0] {
        let grid = chunk_commands(
            &moves,
            &options,
            &mut PinState::default(),
            true,
            1.0 / rate_hz,
        );
        let mut line = ScrewLine::new(
            CommandTemplate::parse(DEFAULT_TEMPLATE).unwrap(),
            rate_hz,
            Hold::ZeroOrder,
        );
        for c in &grid {
            line.push(c.t, c.rpm, c.pin_open, c.source_line).unwrap();
        }
        let mut told = Vec::new();
        for k in 0..=(end_s * 1000.0) as usize {
            let t = k as f64 / 1000.0;
            let clock = LineClock {
                machine_s: t,
                plan_s: t,
                feed: 1.0,
                pin_allowed: true,
            };
            if line.poll(clock).is_some() {
                let (rpm, pin_open) = line.sent();
                told.push(Command {
                    t,
                    rpm,
                    pin_open,
                    source_line: 0,
                    sequence: 0,
                });
            }
        }
        assert!(line.is_idle());
        let lines = told.len();
        assert!(lines as f64 <= end_s * rate_hz + 1.0, "{lines} lines");
        let (l1, l5, lt) = summary(&material(&told));
        let counters = line.counters();
        println!(
            "  {rate_hz:4} Hz line: {l1:5} / {l5:5}, {:+.3} %  ({lines} lines, {} pin changes \
             delayed, worst {:.0} ms)",
            lt * 100.0,
            counters.pin_changes_delayed,
            counters.worst_pin_delay_s * 1e3
        );
        // The screw driver's averages on the grid, through the line unchanged in total.
        let grid_total: f64 = grid.windows(2).map(|w| w[0].rpm * (w[1].t - w[0].t)).sum();
        let told_total: f64 = told.windows(2).map(|w| w[0].rpm * (w[1].t - w[0].t)).sum();
        assert!(
            (told_total / grid_total - 1.0).abs() < 1e-3,
            "{rate_hz} Hz: {told_total} rpm·s told for {grid_total}"
        );
        figures.push((rate_hz, l1, l5, lt));
    }
    // Over the whole print the material is the plan's at any rate; per move, a slower line
    // misses more moves.
    for &(rate_hz, _, _, total) in &figures {
        assert!(total.abs() < 0.01, "{rate_hz} Hz: {total:+}");
    }
    let at = |hz: f64| figures.iter().find(|f| f.0 == hz).unwrap();
    assert!(at(2.0).2 > at(50.0).2, "{figures:?}");
    assert!(at(50.0).1 >= d1, "{figures:?}");
}

/// The amplifier's line fails mid-print (an adapter unplugged): the machine stops, the
/// MCU's steppers with it, at once.
#[test]
fn a_failed_screw_line_stops_the_steppers() {
    let (segments, messages) = finger_plan();
    let (mut machine, stop, reader) = rig();
    let mut failed_at = None;
    run(&mut machine, &segments, &messages, |m, tick| {
        if tick.now_ns == 3_000_000_000 {
            machine_port_fails(m);
        }
        if !tick.ok {
            failed_at.get_or_insert(tick.now_ns);
        }
        failed_at.is_some_and(|at| tick.now_ns > at + 50_000_000) || tick.now_ns >= 10_000_000_000
    });
    let failed_at = failed_at.expect("the failed line is an error");
    assert_eq!(machine.state().state, cell_machine::PlayerState::Stopped);
    // The MCU itself was stopped, not left to play its horizon.
    let inner = machine.inner().state();
    assert_eq!(inner.state, cell_machine::PlayerState::Stopped);
    assert!(inner.velocities[..3].iter().all(|v| *v == 0.0), "{inner:?}");
    assert!(failed_at < 3_200_000_000, "{failed_at}");
    drop(machine);
    stop.store(true, Ordering::Relaxed);
    reader.join().unwrap();
}

fn machine_port_fails(machine: &mut Rig) {
    let sent = machine.port().sent.len();
    machine.port_mut().fail_after = Some(sent);
}

/// The bits one character takes on the wire (start, data, parity, stop): what the start-up
/// check of the line's load counts with.
#[test]
fn framing_counts_every_bit_of_a_character() {
    use mcu_bridge::node::Framing;
    let bits = |f: &str| f.parse::<Framing>().unwrap().bits_per_character();
    assert_eq!(bits("8N1"), 10);
    assert_eq!(bits("7E2"), 11);
    assert_eq!(bits("8O1"), 11);
    assert_eq!(bits("5N2"), 8);
}
