use super::*;

const Q32: u64 = 1 << 32;

/// `steps` dominant steps on `axis` (negative if `reverse`), cruising at `period` whole ticks,
/// lasting exactly `steps·period` ticks.
fn cruise(axis: usize, steps: u32, period: u64, reverse: bool, sequence: u64) -> SegmentJob {
    let mut step_counts = [0; MAX_AXES];
    step_counts[axis] = steps;
    let mut directions = [1; MAX_AXES];
    if reverse {
        directions[axis] = -1;
    }
    let segment = Segment::from_fields(&step_core::SegmentFields {
        step_counts,
        directions,
        dominant_axis: axis as u8,
        cruise_period_ticks: period as f64,
        cruise_steps: steps,
        ..Default::default()
    })
    .unwrap();
    SegmentJob {
        segment,
        duration_q32: steps as u64 * period * Q32,
        move_sequence: sequence,
        source_line: sequence as u32 + 10,
    }
}

fn collect(player: &mut Player, now_ticks: u64) -> Vec<Edge> {
    let mut edges = Vec::new();
    player
        .advance_to(now_ticks * Q32, |e| edges.push(e))
        .unwrap();
    edges
}

#[test]
fn segments_play_back_to_back_on_the_callers_clock() {
    let mut player = Player::new(PlayerOptions::default());
    player.push(cruise(0, 100, 1000, false, 1)).unwrap();
    player.push(cruise(1, 50, 400, true, 2)).unwrap();
    assert_eq!(player.ahead_q32(), (100_000 + 20_000) * Q32);
    // The first segment starts when it is first played: at tick 5000.
    assert!(collect(&mut player, 5000).is_empty());
    assert_eq!(player.state(), PlayerState::Running);
    let edges = collect(&mut player, 5000 + 50_500);
    assert_eq!(edges.len(), 50);
    assert_eq!(edges[0].time_q32, 6000 * Q32);
    assert_eq!(edges[49].time_q32, 55_000 * Q32);
    assert_eq!(player.position_steps(), [50, 0, 0]);
    let spu = StepOptions::default().steps_per_unit;
    let v = player.velocity();
    assert!((v[0] - 1000.0 / spu[0]).abs() < 1e-12 && v[1] == 0.0);
    assert_eq!(player.current(), Some((1, 11)));
    assert_eq!(player.plan_time_q32(), 50_500 * Q32);
    // Through the end of the first, into the second (which starts at 105 000 exactly).
    let edges = collect(&mut player, 105_000 + 400 * 10);
    assert_eq!(edges.len(), 60);
    assert_eq!(edges[50].time_q32, 105_400 * Q32);
    assert_eq!((edges[50].axes, edges[50].negative), (0b010, 0b010));
    assert_eq!(player.position_steps(), [100, -10, 0]);
    assert!((player.velocity()[1] + 2500.0 / spu[1]).abs() < 1e-12);
    assert_eq!(player.completed(), (1, Some((1, 11))));
    // To the end: the queue ran dry with the input open: one underrun, at rest.
    collect(&mut player, 200_000);
    assert_eq!(player.position_steps(), [100, -50, 0]);
    assert_eq!(player.state(), PlayerState::Idle);
    assert_eq!(player.underruns(), 1);
    assert_eq!(player.velocity(), [0.0; 3]);
    assert_eq!(player.plan_time_q32(), 120_000 * Q32);
    assert_eq!(player.ahead_q32(), 0);
}

#[test]
fn after_waiting_the_next_segment_starts_now_never_in_the_past() {
    let mut player = Player::new(PlayerOptions::default());
    player.push(cruise(2, 10, 100, false, 1)).unwrap();
    collect(&mut player, 0);
    collect(&mut player, 5_000); // ended at 1000, starved since
    player.push(cruise(2, 10, 100, false, 2)).unwrap();
    let edges = collect(&mut player, 5_000);
    assert!(edges.is_empty());
    let edges = collect(&mut player, 5_900);
    assert_eq!(edges.first().unwrap().time_q32, 5_100 * Q32);
    assert_eq!(edges.len(), 9);
    // Plan time stood still while waiting: 1000 ticks of the first, 900 of the second.
    assert_eq!(player.plan_time_q32(), 1_900 * Q32);
    assert_eq!(player.underruns(), 1);
    player.finish_input();
    assert_eq!(collect(&mut player, 7_000).len(), 1);
    assert_eq!(player.state(), PlayerState::Idle);
    assert_eq!(
        player.underruns(),
        1,
        "running dry after the last input is the end"
    );
}

#[test]
fn an_emergency_stop_drops_everything_and_holds_until_reset() {
    let mut player = Player::new(PlayerOptions {
        initial_steps: [7, 0, -3],
        ..PlayerOptions::default()
    });
    player.push(cruise(0, 100, 100, false, 1)).unwrap();
    player.push(cruise(0, 100, 100, false, 2)).unwrap();
    collect(&mut player, 0);
    collect(&mut player, 2_550);
    assert_eq!(player.position_steps(), [32, 0, -3]);
    player.emergency_stop();
    assert_eq!(player.state(), PlayerState::Stopped);
    assert!(collect(&mut player, 50_000).is_empty());
    assert_eq!(player.position_steps(), [32, 0, -3]);
    assert_eq!(player.velocity(), [0.0; 3]);
    assert_eq!(player.ahead_q32(), 0);
    assert_eq!(
        player.push(cruise(0, 1, 100, false, 3)),
        Err(PlayerError::Stopped)
    );
    player.reset();
    player.push(cruise(0, 1, 100, false, 3)).unwrap();
    assert_eq!(collect(&mut player, 50_000).len(), 0);
    assert_eq!(collect(&mut player, 50_100).len(), 1);
    assert_eq!(player.position_steps(), [33, 0, -3]);
}

#[test]
fn the_queue_is_bounded() {
    let mut player = Player::new(PlayerOptions {
        queue_capacity: 2,
        ..PlayerOptions::default()
    });
    player.push(cruise(0, 1, 100, false, 1)).unwrap();
    player.push(cruise(0, 1, 100, false, 2)).unwrap();
    assert_eq!(player.free_slots(), 0);
    assert_eq!(
        player.push(cruise(0, 1, 100, false, 3)),
        Err(PlayerError::QueueFull { capacity: 2 })
    );
    collect(&mut player, 0);
    assert_eq!(player.free_slots(), 1, "the playing segment left the queue");
}

#[test]
fn segments_for_another_machine_are_refused_with_their_line() {
    let msg = StepSegment {
        move_sequence: 4,
        source_line: 40,
        step_counts: vec![10, 0, 0],
        directions: vec![1, 1, 1],
        timer_frequency_hz: 2e6,
        cruise_period_ticks: 100.0,
        cruise_steps: 10,
        duration_s: 0.0005,
        ..Default::default()
    };
    assert_eq!(
        SegmentJob::from_message(&msg, 1e6),
        Err(PlayerError::TimerMismatch {
            move_sequence: 4,
            source_line: 40,
            segment_hz: 2e6,
            timer_hz: 1e6
        })
    );
    let job = SegmentJob::from_message(&msg, 2e6).unwrap();
    assert_eq!(job.duration_q32, 1000 * Q32);
    let bad = StepSegment {
        duration_s: f64::INFINITY,
        ..msg.clone()
    };
    assert!(matches!(
        SegmentJob::from_message(&bad, 2e6),
        Err(PlayerError::BadDuration {
            source_line: 40,
            ..
        })
    ));
    let bad = StepSegment {
        step_counts: vec![10, 0],
        ..msg
    };
    let err = SegmentJob::from_message(&bad, 2e6).unwrap_err();
    assert_eq!(
        err.to_string(),
        "step segment of move 4 (line 40): step_counts has 2 entries: a segment drives exactly 3 axes"
    );
}

#[test]
fn a_step_fault_stops_the_machine_and_names_the_move() {
    // Legal at its first step, but its deceleration diverges (see step_core's tests).
    let segment = Segment::from_fields(&step_core::SegmentFields {
        step_counts: [50, 0, 0],
        directions: [1; 3],
        first_period_ticks: 1000.0,
        ramp_r: 0.4e-6,
        decelerate_steps: 50,
        ..Default::default()
    })
    .unwrap();
    let mut player = Player::new(PlayerOptions::default());
    player
        .push(SegmentJob {
            segment,
            duration_q32: 1_000_000 * Q32,
            move_sequence: 9,
            source_line: 90,
        })
        .unwrap();
    collect(&mut player, 0);
    let err = player.advance_to(2_000_000 * Q32, |_| {}).unwrap_err();
    assert!(matches!(
        err,
        PlayerError::Fault {
            move_sequence: 9,
            source_line: 90,
            source: StepFault::RampDiverged { .. }
        }
    ));
    assert_eq!(player.state(), PlayerState::Stopped);
}
