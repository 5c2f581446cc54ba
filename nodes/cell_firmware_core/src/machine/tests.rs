use proptest::prelude::*;
use std::vec::Vec;

use super::*;
use cell_protocol::message::{ScrewNext, ScrewRamp, ScrewStart::*};
use step_core::{Segment, SegmentFields};

extern crate std;

type M = Machine<8, 8>;

fn machine() -> M {
    Machine::new(MachineConfig {
        timer_hz: 1_000_000,
        axis_count: 3,
        initial_steps: [0; 3],
    })
}

/// `steps` on axis 0 at a constant `period` ticks (and half as many on axis 1).
fn cruise(start: u64, steps: u32, period: u64, flags: u8, tag: u32) -> QueuedSegment {
    let segment = Segment::from_fields(&SegmentFields {
        step_counts: [steps, steps / 2, 0],
        directions: [1, -1, 1],
        dominant_axis: 0,
        cruise_period_ticks: period as f64,
        cruise_steps: steps,
        ..SegmentFields::default()
    })
    .unwrap();
    QueuedSegment {
        start_clock: start,
        duration_ticks: (steps as u64 * period) as u32,
        tag,
        flags,
        segment,
    }
}

fn run(m: &mut M, until: u64) -> Vec<StepEdge> {
    let mut edges = Vec::new();
    m.advance(until, &mut |e| edges.push(e));
    edges
}

/// The screw at `target_millirpm` from `start_clock` at once, the pin open.
fn screw_on(start_clock: u64, target_millirpm: i32) -> HostMessage {
    HostMessage::Screw(ScrewRamp {
        start_clock,
        ramp_ticks: 0,
        target_millirpm,
        pin_open: true,
    })
}

fn queue(m: &mut M, q: QueuedSegment) {
    assert_eq!(m.handle(&HostMessage::QueueSegment(q), m.clock()), None);
}

#[test]
fn a_cruise_steps_on_its_exact_ticks_and_counts_positions() {
    let mut m = machine();
    queue(&mut m, cruise(1000, 10, 100, SEGMENT_ENDS_AT_REST, 7));
    assert_eq!(m.mode(), Mode::Running);
    let edges = run(&mut m, 5000);
    let ticks: Vec<u64> = edges.iter().map(|e| e.clock).collect();
    assert_eq!(ticks, (1..=10).map(|i| 1000 + 100 * i).collect::<Vec<_>>());
    // Axis 1 (5 of 10, backwards) steps with every second dominant step.
    assert_eq!(edges[1].axes, 0b011);
    assert_eq!(edges[1].negative, 0b010);
    assert_eq!(edges[0].axes, 0b001);
    assert_eq!(m.positions(), [10, -5, 0]);
    assert_eq!(m.mode(), Mode::Idle);
    assert_eq!(m.state().done_tag, 7);
    assert_eq!(m.fault(), FaultCode::None);
}

/// A pin takes one edge per tick. A segment whose acceleration brings its period under a tick
/// (the rules check only the first period) would put two pulses in one tick, and the firmware
/// would lose the second edge while counting it in the positions: it faults instead, with
/// every edge before it out and counted.
#[test]
fn two_pulses_in_one_tick_are_a_step_fault_not_a_lost_edge() {
    let mut m = machine();
    let segment = Segment {
        step_counts: [40, 0, 0],
        negative_mask: 0,
        dominant_axis: 0,
        accelerate_steps: 40,
        cruise_steps: 0,
        decelerate_steps: 0,
        first_period_q32: 2 << 32,
        first_ramp_q62: 1 << 61, // y = 1/2: under a tick from the 5th period on
    };
    segment.check().unwrap();
    queue(
        &mut m,
        QueuedSegment {
            start_clock: 100,
            duration_ticks: 40,
            tag: 9,
            flags: SEGMENT_ENDS_AT_REST,
            segment,
        },
    );
    let edges = run(&mut m, 1000);
    assert_eq!(m.fault(), FaultCode::StepFault);
    let ticks: Vec<u64> = edges.iter().map(|e| e.clock).collect();
    assert!(ticks.windows(2).all(|w| w[0] < w[1]), "{ticks:?}");
    assert!(edges.len() >= 3 && edges.len() < 40, "{ticks:?}");
    assert_eq!(m.positions(), [edges.len() as i32, 0, 0]);
}

#[test]
fn generating_in_any_chunks_gives_the_same_edges() {
    let mut whole = machine();
    queue(&mut whole, cruise(0, 50, 37, 0, 1));
    queue(&mut whole, cruise(50 * 37, 20, 90, SEGMENT_ENDS_AT_REST, 2));
    let expected = run(&mut whole, 10_000);
    let mut chunked = machine();
    queue(&mut chunked, cruise(0, 50, 37, 0, 1));
    queue(
        &mut chunked,
        cruise(50 * 37, 20, 90, SEGMENT_ENDS_AT_REST, 2),
    );
    let mut edges = Vec::new();
    for until in (0..10_000).step_by(13) {
        chunked.advance(until, &mut |e| edges.push(e));
    }
    chunked.advance(10_000, &mut |e| edges.push(e));
    assert_eq!(edges, expected);
    assert_eq!(edges.len(), 70);
}

#[test]
fn a_late_segment_faults_and_is_reported_once() {
    let mut m = machine();
    run(&mut m, 2000);
    queue(&mut m, cruise(1500, 10, 100, 0, 9));
    assert_eq!(m.mode(), Mode::Fault);
    assert_eq!(m.fault(), FaultCode::LateSegment);
    assert_eq!(m.counters().late_segments, 1);
    assert_eq!(
        m.take_fault_report(),
        Some(McuMessage::Fault {
            code: FaultCode::LateSegment,
            clock: 2000,
            tag: 9
        })
    );
    assert_eq!(m.take_fault_report(), None);
    // Refused while faulted, accepted after a reset.
    queue(&mut m, cruise(3000, 10, 100, 0, 10));
    assert_eq!(m.queue_free(), 8);
    m.handle(&HostMessage::Reset, 2000);
    queue(&mut m, cruise(3000, 10, 100, SEGMENT_ENDS_AT_REST, 10));
    assert_eq!(run(&mut m, 5000).len(), 10);
}

#[test]
fn a_gap_between_segments_is_a_bad_segment() {
    let mut m = machine();
    queue(&mut m, cruise(0, 10, 100, 0, 1));
    queue(&mut m, cruise(1001, 10, 100, 0, 2));
    assert_eq!(m.fault(), FaultCode::BadSegment);
}

/// A start clock off the end of the clock's range (bytes from the wire) is refused as a bad
/// segment: its end would wrap.
#[test]
fn a_segment_ending_past_the_clocks_range_is_a_bad_segment() {
    let mut m = machine();
    queue(
        &mut m,
        cruise(u64::MAX - 500, 10, 100, SEGMENT_ENDS_AT_REST, 9),
    );
    assert_eq!(m.fault(), FaultCode::BadSegment);
    assert_eq!(m.mode(), Mode::Fault);
    assert!(run(&mut m, 10_000).is_empty());
}

#[test]
fn running_dry_while_moving_is_an_underrun_but_not_at_rest() {
    let mut m = machine();
    queue(&mut m, cruise(0, 10, 100, 0, 3));
    run(&mut m, 999);
    assert_eq!(m.fault(), FaultCode::None);
    run(&mut m, 1000);
    assert_eq!(m.fault(), FaultCode::Underrun);
    assert_eq!(m.counters().underruns, 1);
    assert!(matches!(
        m.take_fault_report(),
        Some(McuMessage::Fault {
            code: FaultCode::Underrun,
            clock: 1000,
            tag: 3
        })
    ));

    let mut m = machine();
    queue(&mut m, cruise(0, 10, 100, SEGMENT_ENDS_AT_REST, 3));
    run(&mut m, 5000);
    assert_eq!((m.fault(), m.mode()), (FaultCode::None, Mode::Idle));
}

/// Run dry at rest, the plan clock waits at the schedule's end: the next segment, however
/// late, starts there and plays at once, on the plan's time.
#[test]
fn running_dry_at_rest_stands_the_plan_clock_at_the_schedules_end() {
    let mut m = machine();
    queue(&mut m, cruise(100, 10, 100, SEGMENT_ENDS_AT_REST, 1));
    run(&mut m, 50_000);
    assert_eq!((m.mode(), m.plan_clock()), (Mode::Idle, 1100));
    assert_eq!(m.state().plan_clock, 1100);
    queue(&mut m, cruise(1100, 4, 100, SEGMENT_ENDS_AT_REST, 2));
    let edges = run(&mut m, 60_000);
    let ticks: Vec<u64> = edges.iter().map(|e| e.clock).collect();
    // 48,900 ticks of waiting, then the pulses 100 ticks apart from the plan's 1100.
    assert_eq!(ticks, [50_100, 50_200, 50_300, 50_400]);
    assert_eq!((m.fault(), m.positions()[0]), (FaultCode::None, 14));
    assert_eq!(m.plan_clock(), 1500);

    // The schedule goes on from its end, not from anywhere.
    queue(&mut m, cruise(70_000, 4, 100, SEGMENT_ENDS_AT_REST, 3));
    assert_eq!(m.fault(), FaultCode::BadSegment);

    // A drop ends the schedule: the plan clock runs again and a new one starts anywhere ahead.
    let mut m = machine();
    queue(&mut m, cruise(0, 10, 100, SEGMENT_ENDS_AT_REST, 1));
    run(&mut m, 2000);
    m.handle(&HostMessage::DropQueue, m.clock());
    run(&mut m, 3000);
    // It stood from 1000 to 2000 (waiting), then ran with the clock.
    assert_eq!(m.plan_clock(), 2000);
    queue(&mut m, cruise(2500, 2, 100, SEGMENT_ENDS_AT_REST, 2));
    let edges = run(&mut m, 4000);
    assert_eq!(edges.len(), 2);
    assert_eq!(m.fault(), FaultCode::None);
}

#[test]
fn a_silent_host_faults_after_its_timeout() {
    let mut m = machine();
    m.handle(
        &HostMessage::Configure {
            host_timeout_ticks: 1000,
            state_period_ticks: 0,
        },
        0,
    );
    for t in (500..5000).step_by(500) {
        run(&mut m, t);
        m.host_frame(t);
    }
    assert_eq!(m.fault(), FaultCode::None);
    // The last frame came at 4500: silent for 1000 ticks is allowed, 1001 is not.
    run(&mut m, 5500);
    assert_eq!(m.fault(), FaultCode::None);
    run(&mut m, 5501);
    assert_eq!(m.fault(), FaultCode::HostSilent);
    assert_eq!(
        m.take_fault_report(),
        Some(McuMessage::Fault {
            code: FaultCode::HostSilent,
            clock: 5501,
            tag: 0
        })
    );
}

#[test]
fn a_silent_host_stops_the_pulses_at_its_deadline_not_after() {
    // Pulses every 10 ticks from 10; the host is silent from 0 with a 99-tick timeout, so
    // tick 100 is the first silent too long: the pulses at 10..=90 go out, not the one due
    // at the very tick of the fault.
    let mut m = machine();
    m.handle(
        &HostMessage::Configure {
            host_timeout_ticks: 99,
            state_period_ticks: 0,
        },
        0,
    );
    queue(&mut m, cruise(0, 50, 10, SEGMENT_ENDS_AT_REST, 4));
    let edges = run(&mut m, 1000);
    let ticks: Vec<u64> = edges.iter().map(|e| e.clock).collect();
    assert_eq!(ticks, (1..=9).map(|i| 10 * i).collect::<Vec<_>>());
    assert_eq!(m.positions()[0], 9);
    assert_eq!(
        m.take_fault_report(),
        Some(McuMessage::Fault {
            code: FaultCode::HostSilent,
            clock: 100,
            tag: 0
        })
    );
}

/// A screw command that arrives after its start (a resent frame) is no fault: the screw
/// starts at arrival and it is counted with the late.
#[test]
fn a_late_screw_command_starts_at_arrival_without_a_fault() {
    let mut m = machine();
    queue(&mut m, cruise(0, 100, 100, 0, 1));
    run(&mut m, 1000);
    m.handle(&screw_on(500, 30_000), 1000);
    run(&mut m, 1010);
    assert_eq!(m.mode(), Mode::Running);
    assert_eq!(m.fault(), FaultCode::None);
    assert_eq!((m.screw_millirpm(), m.pin_open()), (30_000, true));
    assert_eq!(m.counters().late_segments, 1);
}

/// A generator that advances no further than `ticks_to_next_screw_command` at a time sees
/// each screw command take effect on its own plan tick, at full feed and through a hold's
/// ramp (σ < 1), whatever its chunk length; unbounded chunks see it wherever they end.
#[test]
fn advancing_to_the_next_screw_command_samples_it_on_its_tick() {
    let commands = [(1_234u64, 20_000), (2_345, 5_000), (6_001, 40_000)];
    for (chunk, hold_at) in [(500u64, None), (97, None), (500, Some(3_025u64))] {
        let mut m = machine();
        queue(&mut m, cruise(0, 200, 50, 0, 1));
        for &(start_clock, target_millirpm) in &commands {
            let ramp = ScrewRamp {
                start_clock,
                ramp_ticks: 0,
                target_millirpm,
                pin_open: true,
            };
            assert_eq!(m.handle(&HostMessage::Screw(ramp), 0), None);
        }
        let mut taken = Vec::new();
        let mut held = false;
        while m.clock() < 20_000 {
            if let Some(at) = hold_at.filter(|&at| !held && m.clock() >= at) {
                held = true;
                m.handle(
                    &HostMessage::FeedHold {
                        rate_q32: (ONE / 8_000) as u32,
                    },
                    at,
                );
            }
            let mut until = m.clock() + chunk;
            if let Some(ticks) = m.ticks_to_next_screw_command() {
                until = until.min(m.clock() + ticks.max(1));
            }
            if let Some(at) = hold_at.filter(|_| !held) {
                until = until.min(at);
            }
            let before = m.screw.next_start();
            run(&mut m, until);
            if m.screw.next_start() != before {
                taken.push(m.plan_clock());
            }
        }
        // Held from 3025, σ falls to 0 over 8000 ticks: the plan clock reaches 6001 at σ < 1
        // and stops near 7025.
        let expected: Vec<u64> = commands.iter().map(|c| c.0).collect();
        assert_eq!(taken, expected, "chunk {chunk}, hold at {hold_at:?}");
        if hold_at.is_some() {
            assert!(
                (7_000..7_100).contains(&m.plan_clock()),
                "{}",
                m.plan_clock()
            );
        }
    }
    // Held at rest with a command two plan ticks ahead: no bound (the plan clock stands; a
    // generator bounded by it would crawl through the rest a tick at a time).
    let mut m = machine();
    queue(&mut m, cruise(0, 200, 50, 0, 1));
    run(&mut m, 3_000);
    m.handle(
        &HostMessage::FeedHold {
            rate_q32: (ONE / 100) as u32,
        },
        3_000,
    );
    run(&mut m, 3_500);
    let stands_at = m.plan_clock();
    m.handle(&screw_on(stands_at + 2, 20_000), 3_500);
    assert_eq!(m.ticks_to_next_screw_command(), None);
    run(&mut m, 4_000);
    assert_eq!(m.plan_clock(), stands_at);
    // Unbounded by the commands, a 500-tick pass takes them where it ends.
    let mut m = machine();
    queue(&mut m, cruise(0, 200, 50, 0, 1));
    m.handle(&screw_on(1_234, 20_000), 0);
    run(&mut m, 1_000);
    assert_eq!(m.ticks_to_next_screw_command(), Some(234));
    run(&mut m, 1_500);
    assert_eq!(
        (m.ticks_to_next_screw_command(), m.plan_clock()),
        (None, 1_500)
    );
}

#[test]
fn an_emergency_stop_stops_at_once_and_holds_until_reset() {
    let mut m = machine();
    queue(&mut m, cruise(0, 100, 100, 0, 1));
    m.handle(&screw_on(0, 30_000), 0);
    assert_eq!(run(&mut m, 2050).len(), 20);
    assert!(m.pin_open());
    assert_eq!(m.screw_millirpm(), 30_000);
    m.handle(&HostMessage::EmergencyStop, 2050);
    assert!(run(&mut m, 20_000).is_empty());
    assert_eq!(m.positions(), [20, -10, 0]);
    assert!(!m.pin_open());
    assert_eq!(m.screw_millirpm(), 0);
    assert_eq!(m.state().mode, Mode::Fault);
    assert_eq!(m.state().fault, FaultCode::EmergencyStop);
    m.handle(&HostMessage::Reset, 20_000);
    assert_eq!(m.mode(), Mode::Idle);
    assert_eq!(m.positions(), [20, -10, 0], "positions survive a reset");
}

#[test]
fn edges_an_output_stage_dropped_at_a_stop_are_taken_back_from_the_positions() {
    let mut m = machine();
    queue(&mut m, cruise(0, 100, 100, 0, 1));
    let edges = run(&mut m, 2050);
    assert_eq!(m.positions(), [20, -10, 0]);
    // While moving, generated edges belong to the plan: nothing is taken back.
    m.discard_edges(edges[15..].iter().copied());
    assert_eq!(m.positions(), [20, -10, 0]);
    // Stopped with the last 5 edges (5 forward on axis 0, 2 or 3 backward on axis 1) still
    // in the output queue: the positions are those of the 15 edges that were output.
    m.handle(&HostMessage::EmergencyStop, 2050);
    m.discard_edges(edges[15..].iter().copied());
    let output = &edges[..15];
    let count = |axis: u8| {
        output
            .iter()
            .filter(|e| e.axes & (1 << axis) != 0)
            .map(|e| if e.negative & (1 << axis) != 0 { -1 } else { 1 })
            .sum::<i32>()
    };
    assert_eq!(m.positions(), [count(0), count(1), 0]);
    assert_eq!(m.positions(), [15, -7, 0]);
}

#[test]
fn a_feed_hold_stops_on_the_path_and_resume_plays_the_same_steps() {
    let plain = {
        let mut m = machine();
        queue(&mut m, cruise(0, 200, 50, SEGMENT_ENDS_AT_REST, 1));
        run(&mut m, 100_000)
    };
    let mut m = machine();
    queue(&mut m, cruise(0, 200, 50, SEGMENT_ENDS_AT_REST, 1));
    m.handle(&screw_on(0, 10_000), 0);
    // Between two steps (the 60th at 3000, the next due at 3050).
    let mut edges = run(&mut m, 3025);
    // σ from 1 to 0 in 2000 ticks (2001 with the rate rounded down).
    let rate = (ONE / 2000) as u32;
    m.handle(&HostMessage::FeedHold { rate_q32: rate }, 3025);
    assert!(m.pin_open(), "slowing along the path, material still flows");
    edges.extend(run(&mut m, 4000));
    assert_eq!(m.mode(), Mode::Ramping);
    assert!(m.screw_millirpm() < 10_000 && m.screw_millirpm() > 0);
    assert!(m.pin_open(), "the screw at σ·rpm through the open pin");
    edges.extend(run(&mut m, 5025));
    assert_eq!(m.mode(), Mode::Ramping);
    assert!(m.pin_open());
    edges.extend(run(&mut m, 5026));
    assert_eq!(m.mode(), Mode::Held);
    assert_eq!(m.screw_millirpm(), 0);
    assert!(!m.pin_open(), "at rest the pin closes");
    let held_at = m.positions();
    // Held: nothing moves, the plan clock stands.
    let plan = m.plan_clock();
    assert!(run(&mut m, 50_000).is_empty());
    assert_eq!((m.positions(), m.plan_clock()), (held_at, plan));
    // Travelled during the ramp: ∫σ ≈ 999.5 ticks of plan, to plan 4024.5: the steps due
    // at 3050 … 4000, 20 of them.
    assert_eq!(held_at[0], 60 + 20);
    m.handle(
        &HostMessage::FeedResume {
            rate_q32: rate,
            delay_ticks: 500,
        },
        50_000,
    );
    assert!(
        m.pin_open(),
        "the pin reopens at the start of the resume's wait"
    );
    assert!(
        run(&mut m, 50_500).is_empty(),
        "at rest during the pin's delay"
    );
    // A pass that ends just as the delay does (σ still 0, about to rise) keeps it open.
    assert!(m.pin_open(), "the pin stays open as motion restarts");
    edges.extend(run(&mut m, 200_000));
    assert_eq!(m.mode(), Mode::Idle);
    // The same steps in the same order, only later; never faster than planned.
    let shape = |e: &[StepEdge]| e.iter().map(|e| (e.axes, e.negative)).collect::<Vec<_>>();
    assert_eq!(shape(&edges), shape(&plain));
    assert!(edges.windows(2).all(|w| w[1].clock - w[0].clock >= 50));
    assert_eq!(m.positions(), [200, -100, 0]);
}

#[test]
fn a_hold_and_resume_generated_in_big_chunks_match_tick_by_tick() {
    // The ramp's tight loop must make exactly the ticks one tick per call makes.
    let rate = (ONE / 1500) as u32;
    let script = |m: &mut M, chunk: u64| {
        let mut edges = Vec::new();
        let mut samples = Vec::new();
        let advance = |m: &mut M, until: u64, edges: &mut Vec<StepEdge>| {
            while m.clock() < until {
                let next = (m.clock() + chunk).min(until);
                m.advance(next, &mut |e| edges.push(e));
            }
        };
        queue(m, cruise(0, 300, 37, SEGMENT_ENDS_AT_REST, 1));
        m.handle(
            &HostMessage::Screw(ScrewRamp {
                start_clock: 0,
                ramp_ticks: 4000,
                target_millirpm: 20_000,
                pin_open: true,
            }),
            0,
        );
        advance(m, 2_990, &mut edges);
        m.handle(&HostMessage::FeedHold { rate_q32: rate }, m.clock());
        for until in [3_500, 4_000, 4_321, 9_000] {
            advance(m, until, &mut edges);
            samples.push((m.clock(), m.plan_clock(), m.screw_millirpm(), m.positions()));
        }
        m.handle(
            &HostMessage::FeedResume {
                rate_q32: rate,
                delay_ticks: 100,
            },
            m.clock(),
        );
        for until in [9_050, 9_700, 10_333, 40_000] {
            advance(m, until, &mut edges);
            samples.push((m.clock(), m.plan_clock(), m.screw_millirpm(), m.positions()));
        }
        (edges, samples, m.state())
    };
    let tick_by_tick = script(&mut machine(), 1);
    let chunked = script(&mut machine(), 5_000);
    assert_eq!(tick_by_tick.0.len(), 300);
    assert_eq!(chunked, tick_by_tick);
}

/// A hold asked for while the schedule has run dry (the host's next segment not yet in) ramps
/// σ per tick like any hold: held after the ramp's ticks, not after as many `advance` calls,
/// so a pause there is as quick with a 1 ms timer pass as tick by tick; likewise the resume.
#[test]
fn a_hold_while_waiting_for_segments_ramps_per_tick_however_time_is_chunked() {
    let rate = (ONE / 2000) as u32;
    let script = |m: &mut M, chunk: u64| {
        let mut edges = Vec::new();
        let mut samples = Vec::new();
        let advance = |m: &mut M, until: u64, edges: &mut Vec<StepEdge>| {
            while m.clock() < until {
                let next = (m.clock() + chunk).min(until);
                m.advance(next, &mut |e| edges.push(e));
            }
        };
        queue(m, cruise(0, 100, 50, SEGMENT_ENDS_AT_REST, 1));
        advance(m, 6_000, &mut edges);
        assert_eq!(m.mode(), Mode::Idle, "ran dry at 5000, waiting for more");
        m.handle(&HostMessage::FeedHold { rate_q32: rate }, m.clock());
        for until in [7_000, 7_999, 8_100, 9_000] {
            advance(m, until, &mut edges);
            samples.push((m.clock(), m.mode(), m.plan_clock(), m.positions()));
        }
        // The next segment arrives while held, then a resume.
        queue(m, cruise(5_000, 100, 50, SEGMENT_ENDS_AT_REST, 2));
        advance(m, 10_000, &mut edges);
        m.handle(
            &HostMessage::FeedResume {
                rate_q32: rate,
                delay_ticks: 100,
            },
            m.clock(),
        );
        for until in [10_050, 10_700, 11_333, 40_000] {
            advance(m, until, &mut edges);
            samples.push((m.clock(), m.mode(), m.plan_clock(), m.positions()));
        }
        (edges, samples, m.state())
    };
    let tick_by_tick = script(&mut machine(), 1);
    // σ from 1 to 0 in 2000 ticks from 6000 (2001 with the rate rounded down).
    assert_eq!(tick_by_tick.1[0].1, Mode::Ramping);
    assert_eq!(tick_by_tick.1[1].1, Mode::Ramping);
    assert_eq!(tick_by_tick.1[2].1, Mode::Held);
    assert_eq!(tick_by_tick.0.len(), 200);
    assert_eq!(tick_by_tick.2.position_steps[0], 200);
    for chunk in [1_000, 5_000, 777] {
        assert_eq!(script(&mut machine(), chunk), tick_by_tick, "chunk {chunk}");
    }
}

#[test]
fn drop_queue_needs_rest() {
    let mut m = machine();
    queue(&mut m, cruise(0, 100, 100, 0, 4));
    run(&mut m, 1000);
    m.handle(&HostMessage::DropQueue, 1000);
    assert_eq!(m.fault(), FaultCode::DropWhileMoving);

    let mut m = machine();
    queue(&mut m, cruise(0, 100, 100, 0, 4));
    run(&mut m, 1000);
    m.handle(&HostMessage::FeedHold { rate_q32: u32::MAX }, 1000);
    run(&mut m, 1010);
    assert_eq!(m.mode(), Mode::Held);
    m.handle(&HostMessage::DropQueue, 1010);
    assert_eq!((m.fault(), m.mode()), (FaultCode::None, Mode::Idle));
    assert!(run(&mut m, 50_000).is_empty());
}

#[test]
fn a_full_queue_overflows_into_a_fault() {
    let mut m = machine();
    for k in 0..8 {
        queue(&mut m, cruise(k * 1000, 10, 100, 0, k as u32));
    }
    assert_eq!(m.queue_free(), 0);
    queue(&mut m, cruise(8000, 10, 100, 0, 8));
    assert_eq!(m.fault(), FaultCode::QueueOverflow);
}

#[test]
fn identify_and_clock_answer() {
    let mut m = machine();
    assert_eq!(
        m.handle(&HostMessage::Identify, 0),
        Some(McuMessage::Identity(Identity {
            protocol_version: PROTOCOL_VERSION,
            timer_hz: 1_000_000,
            queue_capacity: 8,
            axis_count: 3,
            screw_queue_capacity: 8,
        }))
    );
    assert_eq!(
        m.handle(&HostMessage::ClockQuery { token: 5 }, 1234),
        Some(McuMessage::Clock {
            token: 5,
            clock: 1234
        })
    );
}

/// Segments as the planner makes them: trapezoids with a ramp term r·p² up to 0.05 at the
/// first step and no more decelerating than accelerating steps (so the ramp comes back at most
/// to where it began, inside the recurrence's range), and the one-phase segments nearly every
/// print is made of — all cruising (no ramp term), all decelerating (stopping short of rest:
/// x·n ≤ 0.2, the period grows by at most a third) or all accelerating.
fn any_fields() -> impl Strategy<Value = SegmentFields> {
    let trapezoid = (1u32..400, 0u32..400, 0u32..400)
        .prop_map(|(acc, cruise, dec)| (acc, cruise, dec.min(acc)));
    let accelerating = (1u32..400).prop_map(|acc| (acc, 0, 0));
    let cruising = (1u32..400).prop_map(|cruise| (0, cruise, 0));
    let decelerating = (1u32..400).prop_map(|dec| (0, 0, dec));
    (
        prop_oneof![trapezoid, accelerating, cruising, decelerating],
        20.0f64..2000.0,
        1e-6f64..0.05,
    )
        .prop_map(|((acc, cruise, dec), period, x)| {
            let dec = if acc == 0 {
                dec.min(((0.2 / x) as u32).max(1))
            } else {
                dec
            };
            let ramp_r = if acc + dec == 0 {
                0.0
            } else {
                x / (period * period)
            };
            SegmentFields {
                step_counts: [acc + cruise + dec, (acc + cruise + dec) / 3, 1],
                directions: [1, 1, -1],
                dominant_axis: 0,
                first_period_ticks: period,
                ramp_r,
                cruise_period_ticks: period,
                accelerate_steps: acc,
                cruise_steps: cruise,
                decelerate_steps: dec,
            }
        })
}

proptest! {
    /// Whatever the segment and however the caller slices time, the edges are the step core's
    /// pulses on the tick nearest their time, and the positions their sum.
    #[test]
    fn edges_are_the_step_cores_pulses_on_the_nearest_tick(
        fields in any_fields(),
        start in 0u64..5000,
        chunk in 1u64..5000,
    ) {
        let segment = Segment::from_fields(&fields).unwrap();
        let mut train = PulseTrain::new(&segment);
        let mut expected = Vec::new();
        while let Some(p) = train.next_pulse().unwrap() {
            expected.push((start + p.tick(), p.axes));
        }
        let last = expected.last().unwrap().0;
        let mut m = machine();
        queue(&mut m, QueuedSegment {
            start_clock: start,
            duration_ticks: (last - start + 1) as u32,
            tag: 1,
            flags: SEGMENT_ENDS_AT_REST,
            segment,
        });
        let mut edges = Vec::new();
        let mut until = 0;
        while until < last + 10 {
            until += chunk;
            m.advance(until, &mut |e| edges.push((e.clock, e.axes)));
        }
        prop_assert_eq!(edges, expected);
        let n = fields.step_counts;
        prop_assert_eq!(m.positions(), [n[0] as i32, n[1] as i32, -(n[2] as i32)]);
        prop_assert_eq!(m.mode(), Mode::Idle);
    }
}

fn next_of(q: &QueuedSegment, tag_step: u32) -> HostMessage {
    HostMessage::NextSegment(
        cell_protocol::message::NextSegment::new(q.duration_ticks, tag_step, q.flags, q.segment)
            .unwrap(),
    )
}

/// A compact next segment plays exactly as the full one it stands for: it starts where the
/// schedule ends and takes the tag after the last one; the same steps on the same ticks.
#[test]
fn a_next_segment_continues_the_schedule_as_the_full_form_would() {
    let first = cruise(1000, 10, 100, 0, 7);
    let second = cruise(2000, 20, 50, SEGMENT_ENDS_AT_REST, 9);
    let mut full = machine();
    queue(&mut full, first);
    queue(&mut full, second);
    let mut compact = machine();
    queue(&mut compact, first);
    assert_eq!(compact.handle(&next_of(&second, 2), 0), None);
    assert_eq!(run(&mut compact, 10_000), run(&mut full, 10_000));
    assert_eq!(compact.state().done_tag, 9);
    assert_eq!(compact.positions(), [30, -15, 0]);
    assert_eq!(compact.fault(), FaultCode::None);
}

/// Without a schedule to continue — none begun, or dropped — a next segment is a bad segment,
/// never a segment guessed into place.
#[test]
fn a_next_segment_without_a_schedule_is_a_fault() {
    let mut m = machine();
    m.handle(&next_of(&cruise(0, 10, 100, 0, 1), 1), 0);
    assert_eq!(m.fault(), FaultCode::BadSegment);
    let mut m = machine();
    queue(&mut m, cruise(0, 10, 100, SEGMENT_ENDS_AT_REST, 1));
    run(&mut m, 5000);
    m.handle(&HostMessage::DropQueue, m.clock());
    m.handle(&next_of(&cruise(0, 10, 100, 0, 1), 1), m.clock());
    assert_eq!(m.fault(), FaultCode::BadSegment);
}

/// A compact screw command is told relative to the previous command as sent (its start
/// before a late arrival moved it, its length, its target); with no previous command it is
/// a fault.
#[test]
fn a_screw_next_is_told_relative_to_the_previous_command() {
    let mut m = machine();
    queue(&mut m, cruise(0, 200, 100, 0, 1)); // moving until 20,000
    let screw = |start_clock, ramp_ticks, target_millirpm| {
        HostMessage::Screw(ScrewRamp {
            start_clock,
            ramp_ticks,
            target_millirpm,
            pin_open: true,
        })
    };
    let next = |start, ramp_ticks, target_change_millirpm| {
        HostMessage::ScrewNext(ScrewNext {
            start,
            ramp_ticks,
            target_change_millirpm,
            pin_open: true,
        })
    };
    m.handle(&screw(1000, 0, 10_000), 0);
    m.handle(&next(Step(2000), None, 10_000), 0); // 20,000 at once at 3000
    run(&mut m, 2999);
    assert_eq!(m.screw_millirpm(), 10_000);
    run(&mut m, 3001);
    assert_eq!(m.screw_millirpm(), 20_000);
    // A late command (start 2500, moved to its arrival at 3001) times the next from 2500.
    m.handle(&screw(2500, 0, 7_000), 3001);
    m.handle(&next(Step(1500), None, 2_000), 3001); // 9,000 at 4000, not 4501
    run(&mut m, 3999);
    assert_eq!(m.screw_millirpm(), 7_000);
    run(&mut m, 4001);
    assert_eq!(m.screw_millirpm(), 9_000);
    // A chain of ramps: 4000 ticks from 5000 to 9,000 + 4,000 = 13,000; from where it ends
    // (9000, a step of 4000), 2000 ticks down by 8,000; then a step up by 1,000 as long
    // after that (4000, at 13,000) as that one after its predecessor — not where its ramp
    // ends (11,000).
    m.handle(&next(Step(1000), Some(4000), 4_000), 4001);
    m.handle(&next(Chained, Some(2000), -8_000), 4001);
    m.handle(&next(SameStep, Some(0), 1_000), 4001);
    run(&mut m, 7000); // halfway up
    assert_eq!(m.screw_millirpm(), 11_000);
    run(&mut m, 9000);
    assert_eq!(m.screw_millirpm(), 13_000);
    run(&mut m, 10_000); // halfway down
    assert_eq!(m.screw_millirpm(), 9_000);
    run(&mut m, 12_999);
    assert_eq!(m.screw_millirpm(), 5_000);
    run(&mut m, 13_001);
    assert_eq!(m.screw_millirpm(), 6_000);
    assert_eq!(m.fault(), FaultCode::None);
    let mut m = machine();
    m.handle(&next(Step(10), None, 1), 0);
    assert_eq!(m.fault(), FaultCode::BadSegment);
}
