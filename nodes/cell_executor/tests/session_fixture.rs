//! A whole print's messages through the executor session: finger's step segments and the
//! screw driver's commands, stamped as the nodes stamp them.

// Joint-indexed comparisons read best with explicit indices.
#![allow(clippy::needless_range_loop)]

mod common;

use cell_executor::{Executor, ExecutorOptions, HoldReason, PlayerState};
use polar_cell_msgs::{Header, Hold, ScrewCommand, StepSegment, Time};
use polar_planner::messages::trajectory_message;
use polar_planner::steps::StepOptions;
use screw_driver::screw::{breakpoints, position_after, ScrewOptions, TimedMove};

/// The plan's epoch: stamps are `EPOCH_NS + plan time`, as a node started at that instant.
const EPOCH_NS: i64 = 1_700_000_000_000_000_000;

struct Print {
    segments: Vec<StepSegment>,
    commands: Vec<ScrewCommand>,
    end_steps: [i64; 3],
    plan_end_s: f64,
    /// ∫ rpm dτ (rad) over the plan, the screw driver's breakpoints linear in between.
    screw_angle_rad: f64,
}

fn finger() -> Print {
    let common::Fixture {
        moves,
        planned,
        mut segments,
        end_steps,
    } = common::plan_fixture("finger.gcode");
    // Stamped as the planner node stamps them: each segment with its move's start.
    for s in &mut segments {
        let plan = planned
            .iter()
            .find(|p| p.sequence == s.move_sequence)
            .unwrap();
        s.header.stamp = Time::after(EPOCH_NS, plan.start_time());
    }
    let (mut timed, mut from) = (Vec::new(), [0.0; 3]);
    for plan in &planned {
        let m = &moves[plan.sequence as usize];
        timed.push(TimedMove::from_trajectory(
            m,
            from,
            &trajectory_message(plan, EPOCH_NS),
            EPOCH_NS,
        ));
        from = position_after(m, from);
    }
    let points = breakpoints(&timed, &ScrewOptions::default());
    let plan_end_s = planned.last().unwrap().end_time();
    let mut rpm_s = 0.0;
    for w in points.windows(2) {
        rpm_s += (w[0].rpm + w[1].rpm) / 2.0 * (w[1].t.max(0.0) - w[0].t.max(0.0));
    }
    let last = points.last().unwrap();
    rpm_s += last.rpm * (plan_end_s - last.t).max(0.0);
    let commands = points
        .iter()
        .zip(0u64..)
        .map(|(c, sequence)| ScrewCommand {
            header: Header {
                stamp: Time::after(EPOCH_NS, c.t),
                frame_id: String::new(),
            },
            rpm: c.rpm,
            pin_open: c.pin_open,
            source_line: c.source_line,
            model: "polar_speed".into(),
            sequence,
        })
        .collect();
    Print {
        segments,
        commands,
        end_steps,
        plan_end_s,
        screw_angle_rad: rpm_s / 60.0 * std::f64::consts::TAU,
    }
}

/// Run the print in 1 ms ticks of a monotonic clock, topping up both queues, calling
/// `each_ms`; returns the executor at the end.
fn run(print: &Print, mut each_ms: impl FnMut(&mut Executor, u64)) -> Executor {
    // Raw breakpoints (the screw driver without compensation or smoothing): rpm linear.
    let mut exec = Executor::new(ExecutorOptions::new(
        common::player_options(),
        Hold::FirstOrder,
    ));
    let (mut seg, mut cmd) = (
        print.segments.iter().peekable(),
        print.commands.iter().peekable(),
    );
    let clock0_ns = 123_456_789_000;
    for ms in 0u64.. {
        let (free_segments, free_commands) = exec.free_slots();
        for s in seg.by_ref().take(free_segments) {
            exec.on_segment(s).unwrap();
        }
        for c in cmd.by_ref().take(free_commands) {
            exec.on_screw(c).unwrap();
        }
        if seg.peek().is_none() {
            exec.finish_input();
        }
        exec.on_tick(clock0_ns + ms as i64 * 1_000_000).unwrap();
        each_ms(&mut exec, ms);
        if ms > 0 && seg.peek().is_none() && exec.state().state == PlayerState::Idle {
            break;
        }
    }
    exec
}

#[test]
fn finger_executes_to_its_planned_end_with_the_screw_turned_by_the_planned_rpm() {
    let print = finger();
    let spu = StepOptions::default().steps_per_unit;
    let mut pin_open_ms = 0u64;
    let exec = run(&print, |exec, _| {
        let s = exec.state();
        pin_open_ms += s.pin_open as u64;
        assert!(s.screw_rpm >= 0.0 && s.feed == 1.0);
    });
    let end = exec.state();
    for k in 0..3 {
        let expected = print.end_steps[k] as f64 / spu[k];
        assert!((end.positions[k] - expected).abs() < 1e-12, "axis {k}");
    }
    assert!((end.plan_time_s - print.plan_end_s).abs() < 1e-6);
    // Machine time = plan time (no hold), to a tick per segment start at most.
    assert!(
        (end.machine_time_s - print.plan_end_s).abs() < 2e-3,
        "{}",
        end.machine_time_s
    );
    let rel = (end.positions[3] - print.screw_angle_rad).abs() / print.screw_angle_rad;
    eprintln!(
        "finger: {:.3} s, screw {:.1} rad (planned {:.1}), pin open {:.1} s",
        end.machine_time_s,
        end.positions[3],
        print.screw_angle_rad,
        pin_open_ms as f64 * 1e-3
    );
    assert!(rel < 1e-9, "{rel}");
    assert!(pin_open_ms > 10_000, "the pin was open while extruding");
}

/// Paused thrice: the screw stops and the pin closes while held, and the print ends with the
/// same screw angle (material) and position as without pauses.
#[test]
fn pauses_stop_the_screw_and_close_the_pin_and_change_nothing_else() {
    let print = finger();
    let mut held_ms = 0;
    let exec = run(&print, |exec, ms| {
        if [30_000, 70_000, 110_000].contains(&ms) {
            exec.pause();
        }
        if [30_400, 70_400, 110_400].contains(&ms) {
            let s = exec.state();
            assert_eq!(
                (s.state, s.hold),
                (PlayerState::Held, Some(HoldReason::Pause))
            );
            exec.resume();
        }
        let s = exec.state();
        if s.state == PlayerState::Held && s.hold.is_some() {
            held_ms += 1;
            assert_eq!((s.screw_rpm, s.pin_open), (0.0, false), "at {ms} ms");
            assert_eq!(s.velocities, [0.0; 4]);
        }
    });
    assert!(held_ms > 1000, "{held_ms}");
    let end = exec.state();
    let spu = StepOptions::default().steps_per_unit;
    for k in 0..3 {
        assert!((end.positions[k] - print.end_steps[k] as f64 / spu[k]).abs() < 1e-12);
    }
    let rel = (end.positions[3] - print.screw_angle_rad).abs() / print.screw_angle_rad;
    assert!(rel < 1e-9, "{rel}");
    // Each pause added its hold, the pin's 0.25 s and the stop and restart ramps.
    let added = end.machine_time_s - print.plan_end_s;
    assert!(added > 3.0 * 0.65 && added < 3.0 * 0.9, "{added} s");
}

/// A plan that runs dry (input not finished: an upstream stall) leaves the machine idle with
/// the screw stopped and the pin closed, though the last screw command said to turn; so does a
/// cancel that comes to rest.
#[test]
fn an_idle_machine_has_its_screw_stopped() {
    let print = finger();
    for cancel in [false, true] {
        let mut exec = Executor::new(ExecutorOptions::new(
            common::player_options(),
            Hold::FirstOrder,
        ));
        // The first 60 s of commands, and segments only up to 20 s of plan.
        for c in print
            .commands
            .iter()
            .filter(|c| c.header.stamp.as_nanos() - EPOCH_NS < 60_000_000_000)
        {
            let _ = exec.on_screw(c);
        }
        let mut t = 0.0;
        for s in &print.segments {
            if t > 20.0 {
                break;
            }
            exec.on_segment(s).unwrap();
            t += s.duration_s;
        }
        let mut turning_seen = false;
        for ms in 0..40_000i64 {
            if cancel && ms == 10_000 {
                exec.cancel();
            }
            exec.on_tick(ms * 1_000_000).unwrap();
            turning_seen |= exec.state().screw_rpm > 0.0;
        }
        let state = exec.state();
        assert!(turning_seen);
        // Ran dry: held at rest by the underrun hold; cancelled: the plan dropped, idle.
        let expected = if cancel {
            PlayerState::Idle
        } else {
            PlayerState::Held
        };
        assert_eq!(state.state, expected);
        assert_eq!(
            (state.screw_rpm, state.pin_open),
            (0.0, false),
            "cancel: {cancel}"
        );
        assert_eq!(state.velocities, [0.0; 4]);
    }
}
