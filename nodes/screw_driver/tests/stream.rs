//! A screw driver restarted from any of its checkpoints continues the very same commands: the
//! stream is resumed at every chunk boundary of real prints and compared, message for message,
//! with the uninterrupted run. The resumed stream is given the plans from well before its
//! checkpoint (as the planner's transient-local history gives them) and must drop exactly
//! those of moves already commanded.

mod common;

use gcode_streamer::GcodeMove;
use polar_cell_msgs::checkpoint::ResumeStateError;
use polar_cell_msgs::{JointState, JointTrajectory, ScrewCommand};
use polar_planner::messages::trajectory_message;
use polar_planner::{Planner, PlannerOptions};
use screw_driver::compensation::FlowModel;
use screw_driver::fir::FILTER_1;
use screw_driver::screw::ScrewOptions;
use screw_driver::stream::{
    Checkpoint, CheckpointError, Cut, Stream, StreamError, StreamOptions, Taken,
};

const EPOCH_NS: i64 = 1_795_318_512_024_268_371;

/// The moves of a fixture and their trajectories, one per move, as the planner publishes them.
fn planned(name: &str) -> (Vec<GcodeMove>, Vec<JointTrajectory>) {
    let moves = common::fixture(name);
    let mut planner = Planner::new(PlannerOptions::default()).unwrap();
    let mut plans = Vec::new();
    for m in &moves {
        planner.push(m, &mut plans).unwrap();
    }
    planner.flush(&mut plans);
    assert_eq!(plans.len(), moves.len());
    let trajectories = plans
        .iter()
        .map(|p| trajectory_message(p, EPOCH_NS))
        .collect();
    (moves, trajectories)
}

fn compensated() -> StreamOptions {
    StreamOptions {
        screw: ScrewOptions {
            compensation: Some(FlowModel::default_extruder()),
            ..ScrewOptions::default()
        },
        command_period_s: 0.0,
        joint_state_period_s: 0.02,
        max_buffer_s: 0.5,
        max_buffer_moves: 64,
    }
}

fn smoothed() -> StreamOptions {
    StreamOptions {
        screw: ScrewOptions {
            smoothing: Some(FILTER_1.taps()),
            ..ScrewOptions::default()
        },
        command_period_s: 0.0,
        joint_state_period_s: 0.05,
        max_buffer_s: 2.0,
        max_buffer_moves: 40,
    }
}

/// What the node would publish, and the checkpoint after every chunk: (commanded until,
/// checkpoint bytes, commands and joint states published before it).
#[derive(Debug)]
struct Run {
    commands: Vec<ScrewCommand>,
    joint_states: Vec<JointState>,
    checkpoints: Vec<(u64, Vec<u8>, usize, usize)>,
}

/// The cut the node would ask for after trajectory `k`: mostly a full buffer, sometimes an
/// input pause, and everything after some zero-time plans, as a stall would (deterministic, so
/// a resumed run asks the same).
fn cut_after(k: usize, trajectory: &JointTrajectory) -> Cut {
    let (start_ns, end_ns) = trajectory.span_ns();
    if start_ns == end_ns && k.is_multiple_of(2) {
        Cut::All
    } else if k % 11 == 5 {
        Cut::AtGap
    } else {
        Cut::IfFull
    }
}

/// Feed `moves` (from the stream's resume point on), then trajectories `trajectories[first..]`,
/// one by one, cutting as the node would after each move paired (each message pairs one at
/// most), and everything after the last.
fn run(
    mut stream: Stream,
    moves: &[GcodeMove],
    trajectories: &[JointTrajectory],
    first: usize,
) -> Result<(Run, usize), StreamError> {
    let mut out = Run {
        commands: Vec::new(),
        joint_states: Vec::new(),
        checkpoints: Vec::new(),
    };
    let mut skipped = 0;
    let after_pairing = |stream: &mut Stream, out: &mut Run| {
        let k = stream.paired_until() as usize - 1;
        let how = if k + 1 == trajectories.len() {
            Cut::All
        } else {
            cut_after(k, &trajectories[k])
        };
        if let Some(chunk) = stream.cut(how) {
            out.commands.extend(chunk.commands);
            out.joint_states.extend(chunk.joint_states);
            out.checkpoints.push((
                stream.commanded_until(),
                stream.checkpoint().to_bytes(),
                out.commands.len(),
                out.joint_states.len(),
            ));
        }
    };
    for m in &moves[stream.commanded_until() as usize..] {
        let paired = stream.paired_until();
        stream.on_move(m.clone());
        if stream.paired_until() > paired {
            after_pairing(&mut stream, &mut out);
        }
    }
    for t in &trajectories[first..] {
        let paired = stream.paired_until();
        if stream.on_trajectory(t.clone())? == Taken::BeforeResume {
            skipped += 1;
        } else if stream.paired_until() > paired {
            after_pairing(&mut stream, &mut out);
        }
    }
    assert_eq!(stream.buffered_moves(), 0);
    Ok((out, skipped))
}

fn resumes_bit_for_bit(name: &str, options: StreamOptions) {
    let (moves, trajectories) = planned(name);
    let stream = Stream::new(options.clone());
    let digest = stream.options_digest();
    let (whole, skipped) = run(stream, &moves, &trajectories, 0).unwrap();
    assert_eq!(skipped, 0);
    assert!(
        whole.checkpoints.len() > 20,
        "{name}: {} chunks",
        whole.checkpoints.len()
    );
    // Commands are numbered 0, 1, 2, … and their stamps never go back.
    for (k, c) in whole.commands.iter().enumerate() {
        assert_eq!(c.sequence, k as u64);
    }
    assert!(whole
        .commands
        .windows(2)
        .all(|w| w[0].header.stamp.as_nanos() <= w[1].header.stamp.as_nanos()));
    let mut zero_time_points = 0;
    for (until, bytes, commands, joint_states) in &whole.checkpoints {
        let checkpoint = Checkpoint::from_bytes(bytes, *until, digest).unwrap();
        zero_time_points += usize::from(checkpoint.zero_time_at_end > 0);
        let resumed = Stream::resume(options.clone(), &checkpoint);
        assert_eq!(resumed.commanded_until(), *until);
        // The planner's history reaches 100 plans back.
        let first = (*until as usize).saturating_sub(100);
        let (rest, skipped) = run(resumed, &moves, &trajectories, first).unwrap();
        assert_eq!(
            skipped,
            *until as usize - first,
            "{name}: resumed at move {until}"
        );
        assert_eq!(
            rest.commands.len(),
            whole.commands.len() - commands,
            "{name}: resumed at move {until}"
        );
        assert!(
            rest.commands == whole.commands[*commands..],
            "{name}: resumed at move {until}, commands differ"
        );
        assert!(
            rest.joint_states == whole.joint_states[*joint_states..],
            "{name}: resumed at move {until}, joint states differ"
        );
    }
    // Some checkpoints sit right after zero-time moves (a G92, a feed-rate line): the resumed
    // stream must skip exactly those plans at that instant.
    assert!(
        zero_time_points > 0,
        "{name}: no checkpoint after a zero-time move"
    );
}

/// A restarted driver may get the planner's history before it learns where to resume: those
/// plans are handed to the resumed stream, which sorts them as if they came after.
#[test]
fn plans_taken_before_the_resume_point_was_known_are_handed_over() {
    let (moves, trajectories) = planned("finger.gcode");
    let options = compensated();
    let (whole, _) = run(Stream::new(options.clone()), &moves, &trajectories, 0).unwrap();
    let digest = Stream::new(options.clone()).options_digest();
    let mut resumed_at = 0;
    for (until, bytes, commands, joint_states) in whole.checkpoints.iter().step_by(7) {
        let checkpoint = Checkpoint::from_bytes(bytes, *until, digest).unwrap();
        let first = (*until as usize).saturating_sub(100);
        let early = (first + 150).min(trajectories.len());
        let mut fresh = Stream::new(options.clone());
        for t in &trajectories[first..early] {
            assert_eq!(fresh.on_trajectory(t.clone()).unwrap(), Taken::Kept);
        }
        let resumed = fresh.resumed(&checkpoint).unwrap();
        let (rest, _) = run(resumed, &moves, &trajectories, early).unwrap();
        assert!(
            rest.commands == whole.commands[*commands..],
            "resumed at move {until}, commands differ"
        );
        assert!(rest.joint_states == whole.joint_states[*joint_states..]);
        resumed_at += 1;
    }
    assert!(resumed_at > 10, "{resumed_at}");
}

#[test]
fn compensated_finger_resumes_at_every_chunk() {
    resumes_bit_for_bit("finger.gcode", compensated());
}

#[test]
fn compensated_polartest_resumes_at_every_chunk() {
    resumes_bit_for_bit("polartest.gcode", compensated());
}

#[test]
fn smoothed_polartest_resumes_at_every_chunk() {
    resumes_bit_for_bit("polartest.gcode", smoothed());
}

/// A chunk never holds more moves than asked, so acknowledgements (given once commanded)
/// always move on within the streamer's window.
#[test]
fn chunks_hold_at_most_max_buffer_moves() {
    let (moves, trajectories) = planned("polartest.gcode");
    let options = StreamOptions {
        max_buffer_s: 1e6,
        max_buffer_moves: 25,
        ..compensated()
    };
    let (whole, _) = run(Stream::new(options), &moves, &trajectories, 0).unwrap();
    let mut before = 0;
    for (until, ..) in &whole.checkpoints {
        assert!(until - before <= 25, "a chunk of {} moves", until - before);
        before = *until;
    }
    assert_eq!(before, moves.len() as u64);
}

/// A history that does not reach back to the checkpoint leaves moves without their plans: the
/// stream refuses to pair the rest instead of misplacing it.
#[test]
fn a_history_too_short_is_refused() {
    let (moves, trajectories) = planned("finger.gcode");
    let options = compensated();
    let (whole, _) = run(Stream::new(options.clone()), &moves, &trajectories, 0).unwrap();
    let (until, bytes, ..) = &whole.checkpoints[10];
    let checkpoint =
        Checkpoint::from_bytes(bytes, *until, Stream::new(options.clone()).options_digest())
            .unwrap();
    // The first plan after the checkpoint is missing, and the one after it takes time.
    let missing = (*until as usize..trajectories.len())
        .find(|&k| {
            let (a, b) = trajectories[k + 1].span_ns();
            b > a
        })
        .unwrap();
    let err = run(
        Stream::resume(options, &checkpoint),
        &moves,
        &trajectories,
        missing + 1,
    )
    .unwrap_err();
    assert!(matches!(err, StreamError::Discontinuous { .. }), "{err}");
    assert!(err.to_string().contains("not continuous"), "{err}");
}

#[test]
fn checkpoints_of_other_options_or_points_are_refused() {
    let (moves, trajectories) = planned("finger.gcode");
    let (whole, _) = run(Stream::new(compensated()), &moves, &trajectories, 0).unwrap();
    let (until, bytes, ..) = &whole.checkpoints[3];
    let ours = Stream::new(compensated()).options_digest();
    let theirs = Stream::new(smoothed()).options_digest();
    assert_ne!(ours, theirs);
    assert!(matches!(
        Checkpoint::from_bytes(bytes, *until, theirs),
        Err(CheckpointError::State(
            ResumeStateError::OtherOptions { .. }
        ))
    ));
    assert!(matches!(
        Checkpoint::from_bytes(bytes, until + 1, ours),
        Err(CheckpointError::State(ResumeStateError::WrongPoint { .. }))
    ));
    for len in [0, 3, 10, bytes.len() - 1] {
        assert!(
            matches!(
                Checkpoint::from_bytes(&bytes[..len], *until, ours),
                Err(CheckpointError::State(ResumeStateError::Malformed { .. }))
            ),
            "{len} bytes"
        );
    }
    let mut c = Checkpoint::from_bytes(bytes, *until, ours).unwrap();
    c.flow_rpm = f64::NAN;
    assert!(matches!(
        Checkpoint::from_bytes(&c.to_bytes(), *until, ours),
        Err(CheckpointError::NotAScrewState(_))
    ));
}

/// A machine reads how far the commands reach from the lead of a checkpoint's bytes.
#[test]
fn a_checkpoint_leads_with_the_commands_reach() {
    use polar_cell_msgs::checkpoint::{reach, ScrewReach};
    let (moves, trajectories) = planned("finger.gcode");
    let (whole, _) = run(Stream::new(compensated()), &moves, &trajectories, 0).unwrap();
    let ours = Stream::new(compensated()).options_digest();
    for (until, bytes, ..) in whole.checkpoints.iter().step_by(17) {
        let c = Checkpoint::from_bytes(bytes, *until, ours).unwrap();
        let (header, r) = reach::<ScrewReach>(bytes).unwrap();
        assert_eq!(header, c.header);
        assert_eq!(
            r,
            ScrewReach {
                has_base: c.has_base,
                base_ns: c.base_ns,
                last_stamp_ns: c.last_stamp_ns,
                next_command: c.next_command,
            }
        );
    }
    // After the last chunk: every command published.
    let (_, last, ..) = whole.checkpoints.last().unwrap();
    let (_, r) = reach::<ScrewReach>(last).unwrap();
    assert_eq!(r.next_command, whole.commands.len() as u64);
}

proptest::proptest! {
    /// Any bytes: a checkpoint or a clean error, never a panic.
    #[test]
    fn any_bytes_read_cleanly(bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..400)) {
        let _ = Checkpoint::from_bytes(&bytes, 0, 0);
    }
}

/// A print that starts where the machine stands, away from home (a print after a cancel, an
/// MCU reporting its position), before any `G28`: a prime there and the path after it feed
/// the file's material. The stream used to measure the first move from the origin, which
/// made the prime a path move at speed 0 (no material) and scaled the next one's rpm.
#[test]
fn a_print_started_away_from_home_feeds_its_material() {
    let joints = [0.5, 0.04, 0.001];
    let [x, y, z] = polar_planner::path::forward(joints).map(|v| v * 1e3);
    let gcode = "M83\nG1 E2 F120\nG1 X10 Y35 E1.5 F600\nG1 X10 Y45 E0.5\n";
    let (moves, _) = gcode_streamer::parse_all(
        gcode.as_bytes(),
        "away.gcode",
        gcode_streamer::InterpreterOptions {
            start_position_mm: [x, y, z],
            ..Default::default()
        },
    )
    .unwrap();
    let mut planner = Planner::new(PlannerOptions {
        initial_joints: joints,
        ..PlannerOptions::default()
    })
    .unwrap();
    let mut plans = Vec::new();
    for m in &moves {
        planner.push(m, &mut plans).unwrap();
    }
    planner.flush(&mut plans);
    let options = StreamOptions {
        screw: ScrewOptions::default(),
        command_period_s: 0.0,
        joint_state_period_s: 0.0,
        max_buffer_s: 60.0,
        max_buffer_moves: 64,
    };
    let screw_driver::screw::RpmModel::PolarSpeed { e_per_rev_m } = options.screw.model else {
        unreachable!("the default model is polar_speed")
    };
    let mut stream = Stream::new(options);
    for (m, p) in moves.iter().zip(&plans) {
        stream.on_move(m.clone());
        stream
            .on_trajectory(trajectory_message(p, EPOCH_NS))
            .unwrap();
    }
    let commands = stream.cut(Cut::All).unwrap().commands;
    // The raw breakpoints run linearly between each other: the material is their integral.
    let fed_per_line = |line: u32| -> f64 {
        commands
            .windows(2)
            .filter(|w| w[0].source_line == line && w[1].source_line == line)
            .map(|w| {
                let dt =
                    (w[1].header.stamp.as_nanos() - w[0].header.stamp.as_nanos()) as f64 * 1e-9;
                (w[0].rpm + w[1].rpm) / 2.0 / 60.0 * e_per_rev_m * dt
            })
            .sum()
    };
    for (line, e_mm) in [(2, 2.0), (3, 1.5)] {
        let fed_mm = fed_per_line(line) * 1e3;
        assert!(
            (fed_mm - e_mm).abs() < 1e-6,
            "line {line}: {fed_mm} mm of {e_mm}"
        );
    }
}

/// The moves of `src` and their trajectories, as the planner publishes them.
fn planned_src(src: &str) -> (Vec<GcodeMove>, Vec<JointTrajectory>) {
    let moves = gcode_streamer::parse_all(
        src.as_bytes(),
        "test",
        gcode_streamer::InterpreterOptions::default(),
    )
    .unwrap()
    .0;
    let mut planner = Planner::new(PlannerOptions::default()).unwrap();
    let mut plans = Vec::new();
    for m in &moves {
        planner.push(m, &mut plans).unwrap();
    }
    planner.flush(&mut plans);
    let trajectories = plans
        .iter()
        .map(|p| trajectory_message(p, EPOCH_NS))
        .collect();
    (moves, trajectories)
}

/// The pin closes at the end of the print however the last run was cut: a chunk cut at a
/// full window or a stall that took the file's last extruding move (the end of the file
/// then found nothing left to close), or a last chunk of nothing but an instant (a trailing
/// `G92 E0`). Either left the last command with the pin open.
#[test]
fn the_pin_closes_at_the_end_however_the_last_run_was_cut() {
    let raw = StreamOptions {
        screw: ScrewOptions::default(),
        command_period_s: 0.0,
        joint_state_period_s: 0.02,
        max_buffer_s: 2.0,
        max_buffer_moves: 64,
    };
    for options in [raw, compensated()] {
        for trailing in ["", "G92 E0\n"] {
            let src = format!("G1 X10 Y0 F1800\nG1 X20 Y5 E1.0\nG1 X25 Y10 E1.5\n{trailing}");
            let (moves, trajectories) = planned_src(&src);
            let mut stream = Stream::new(options.clone());
            let mut commands = Vec::new();
            for (k, (m, t)) in moves.iter().zip(&trajectories).enumerate() {
                stream.on_move(m.clone());
                stream.on_trajectory(t.clone()).unwrap();
                // Everything up to the last extruding move goes out mid-run.
                let how = if k == 2 { Cut::Now } else { Cut::IfFull };
                commands.extend(stream.cut(how).into_iter().flat_map(|c| c.commands));
            }
            assert!(
                commands.last().unwrap().pin_open,
                "the mid-run chunk leaves the pin open"
            );
            // The end of the file: everything, or nothing left but its close.
            commands.extend(stream.cut(Cut::All).into_iter().flat_map(|c| c.commands));
            let last = commands.last().unwrap();
            assert!(!last.pin_open && last.rpm == 0.0, "{trailing:?}: {last:?}");
            let end_ns = trajectories[2].span_ns().1;
            assert_eq!(last.header.stamp.as_nanos(), end_ns, "{trailing:?}");
            assert!(!stream.pin_open());
            assert!(stream.cut(Cut::All).is_none(), "closed once");
            let numbers: Vec<u64> = commands.iter().map(|c| c.sequence).collect();
            assert_eq!(numbers, (0..commands.len() as u64).collect::<Vec<_>>());
        }
    }
}
