use super::*;

fn command(rpm: f64, pin_open: bool, source_line: u32) -> ScrewCommand {
    ScrewCommand {
        rpm,
        pin_open,
        source_line,
        ..ScrewCommand::default()
    }
}

fn pause(duration_s: f64, sequence: u64) -> StepSegment {
    StepSegment {
        move_sequence: sequence,
        step_counts: vec![0; 3],
        directions: vec![1; 3],
        timer_frequency_hz: 1e6,
        duration_s,
        ..StepSegment::default()
    }
}

#[test]
fn segments_tile_the_clock_and_rounding_does_not_accumulate() {
    let mut schedule = Schedule::new(1e6, Hold::ZeroOrder, 5_000);
    // 1000 pauses of 1.3 µs (0.3 tick too long each if rounded one by one).
    let mut end = 5_000;
    for k in 0..1000 {
        let q = schedule.segment(&pause(1.3e-6, k)).unwrap();
        assert_eq!(q.start_clock, end, "no gap, no overlap");
        end = q.start_clock + q.duration_ticks as u64;
    }
    assert_eq!(end, 5_000 + 1_300, "the exact sum, rounded once");
    assert_eq!(schedule.plan_s_at(end), 1.3e-3);
}

#[test]
fn a_segment_for_another_timer_or_of_no_duration_is_refused() {
    let mut schedule = Schedule::new(1e6, Hold::ZeroOrder, 0);
    let mut seg = pause(1e-3, 4);
    seg.step_counts = vec![10, 0, 0];
    seg.cruise_steps = 10;
    seg.cruise_period_ticks = 100.0;
    seg.timer_frequency_hz = 2e6;
    assert!(matches!(
        schedule.segment(&seg),
        Err(ScheduleError::Unplayable(UnplayableSegment::TimerMismatch { move_sequence: 4, segment_hz, .. })) if segment_hz == 2e6
    ));
    assert!(matches!(
        schedule.segment(&pause(f64::NAN, 5)),
        Err(ScheduleError::Unplayable(UnplayableSegment::BadDuration {
            move_sequence: 5,
            ..
        }))
    ));
}

/// Commands at 0 s (10 rpm, pin open), 1 s (20 rpm) and 2 s (0 rpm, pin closed), fed to the
/// firmware's screw: held, 30 rpm·s (0.5 rev); linear, 25 rpm·s (5/12 rev, reported as 416
/// thousandths, truncated) — the integrals of the two holds' rpm curves.
#[test]
fn both_holds_give_the_firmware_the_drivers_rpm_curve() {
    for (hold, expected_millirev, rpm_at_half) in [
        (Hold::ZeroOrder, 500, 10_000),
        (Hold::FirstOrder, 416, 15_000),
    ] {
        let mut schedule = Schedule::new(1e6, hold, 1_000);
        let mut ramps = Vec::new();
        for (t, rpm, pin) in [(0.0, 10.0, true), (1.0, 20.0, true), (2.0, 0.0, false)] {
            ramps.extend(schedule.screw(&command(rpm, pin, 1), t, 0).unwrap());
        }
        ramps.extend(schedule.finish_screw());
        let mut screw = cell_firmware_core::screw::Screw::<8>::new();
        for r in &ramps {
            screw.push(*r, 0).unwrap();
        }
        screw.advance_to(501_000);
        assert_eq!(screw.millirpm(), rpm_at_half, "{hold:?}");
        assert!(screw.pin_open());
        screw.advance_to(3_001_000);
        assert!(!screw.pin_open());
        assert_eq!(screw.millirpm(), 0);
        assert_eq!(
            screw.angle_millirev(1_000_000),
            expected_millirev,
            "{hold:?}"
        );
    }
}

#[test]
fn screw_commands_out_of_order_or_without_a_number_are_refused() {
    let mut schedule = Schedule::new(1e6, Hold::ZeroOrder, 0);
    schedule.screw(&command(5.0, true, 10), 2.0, 0).unwrap();
    assert_eq!(
        schedule.screw(&command(5.0, true, 11), 1.0, 0),
        Err(ScheduleError::ScrewOutOfOrder {
            source_line: 11,
            plan_s: 1.0,
            previous_s: 2.0
        })
    );
    // A nanosecond's rounding between two stamps of one instant is no disorder.
    let same = schedule
        .screw(&command(6.0, true, 13), 2.0 - 1e-9, 0)
        .unwrap()
        .unwrap();
    assert_eq!(same.start_clock, 2_000_000);
    assert!(matches!(
        schedule.screw(&command(f64::INFINITY, true, 12), 3.0, 0),
        Err(ScheduleError::BadRpm {
            source_line: 12,
            ..
        })
    ));
}

/// The next command came after the MCU passed the previous one: the ramp starts where the MCU
/// is, not in its past (which it would refuse as late), and still ends on time.
#[test]
fn a_late_first_order_ramp_starts_where_the_mcu_is() {
    let mut schedule = Schedule::new(1e6, Hold::FirstOrder, 0);
    schedule.screw(&command(10.0, true, 1), 0.0, 0).unwrap();
    let ramp = schedule
        .screw(&command(20.0, true, 2), 1.0, 400_000)
        .unwrap()
        .unwrap();
    assert_eq!(
        ramp,
        ScrewRamp {
            start_clock: 400_000,
            ramp_ticks: 600_000,
            target_millirpm: 20_000,
            pin_open: true
        }
    );
}

/// Held (zero order), a command that repeats the rpm and pin in force costs no frame; a
/// change of either does. First order, every command moves the ramp and goes out.
#[test]
fn a_held_command_that_changes_nothing_is_not_sent() {
    let mut schedule = Schedule::new(1e6, Hold::ZeroOrder, 0);
    assert!(schedule
        .screw(&command(40.0, true, 1), 0.0, 0)
        .unwrap()
        .is_some());
    assert_eq!(
        schedule.screw(&command(40.0, true, 2), 0.1, 0).unwrap(),
        None
    );
    assert_eq!(
        schedule.screw(&command(40.0004, true, 3), 0.2, 0).unwrap(),
        None,
        "same millirpm"
    );
    let changed = schedule
        .screw(&command(41.0, true, 4), 0.3, 0)
        .unwrap()
        .unwrap();
    assert_eq!(
        (changed.start_clock, changed.target_millirpm),
        (300_000, 41_000)
    );
    let closed = schedule
        .screw(&command(41.0, false, 5), 0.4, 0)
        .unwrap()
        .unwrap();
    assert!(!closed.pin_open);

    let mut first_order = Schedule::new(1e6, Hold::FirstOrder, 0);
    first_order.screw(&command(40.0, true, 1), 0.0, 0).unwrap();
    assert!(first_order
        .screw(&command(40.0, true, 2), 0.1, 0)
        .unwrap()
        .is_some());
}
