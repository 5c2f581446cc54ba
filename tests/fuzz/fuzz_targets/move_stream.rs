//! Any stream of moves, as a DDS publisher other than our streamer could send them: the planner
//! plans them or refuses one with an error, and the screw driver turns what was planned into
//! commands and screw angles. Nothing panics, and what comes out is finite.
#![no_main]

use arbitrary::{Arbitrary, Unstructured};
use libfuzzer_sys::fuzz_target;
use polar_cell_msgs::GcodeMove;
use polar_planner::messages::trajectory_message;
use polar_planner::steps::{decode, StepGenerator, StepOptions};
use polar_planner::{Planner, PlannerOptions, ScrewLimits};
use screw_driver::compensation::FlowModel;
use screw_driver::joint::{Hold, ScrewAngle};
use screw_driver::screw::{
    breakpoints, chunk_commands, position_after, PinState, ScrewOptions, TimedMove,
};

/// A coordinate: mostly inside the work volume, sometimes anything at all.
fn coordinate(u: &mut Unstructured) -> arbitrary::Result<f64> {
    Ok(if u.ratio(7, 8)? {
        f64::from(i16::arbitrary(u)?) * 1e-5
    } else {
        f64::arbitrary(u)?
    })
}

fn next_move(u: &mut Unstructured, sequence: u64) -> arbitrary::Result<GcodeMove> {
    Ok(GcodeMove {
        sequence,
        source_line: sequence as u32 + 1,
        kind: u8::arbitrary(u)? % 8,
        x_m: coordinate(u)?,
        y_m: coordinate(u)?,
        z_m: coordinate(u)?.abs(),
        e_m: coordinate(u)?,
        delta_e_m: coordinate(u)?,
        feedrate_m_per_s: coordinate(u)?.abs() * 10.0,
        extrude: bool::arbitrary(u)?,
        dwell_s: coordinate(u)?.abs(),
        axes: u8::arbitrary(u)?,
        ..GcodeMove::default()
    })
}

fuzz_target!(|bytes: &[u8]| {
    let mut u = Unstructured::new(bytes);
    let mut moves = Vec::new();
    while moves.len() < 64 {
        match next_move(&mut u, moves.len() as u64) {
            Ok(m) => moves.push(m),
            Err(_) => break,
        }
    }
    // The planner respects the screw as `print` sets it up.
    let mut planner = Planner::new(PlannerOptions {
        screw: Some(ScrewLimits {
            usable_rpm: 270.0,
            e_per_rev_m: 0.002,
            flow_tau_s: 0.03,
        }),
        ..PlannerOptions::default()
    })
    .unwrap();
    let mut planned = Vec::new();
    let mut accepted = 0;
    for m in &moves {
        if planner.push(m, &mut planned).is_err() {
            break;
        }
        accepted += 1;
    }
    planner.flush(&mut planned);
    assert!(planned.len() <= accepted);
    let mut timed = Vec::new();
    let mut from = [0.0; 3];
    for plan in &planned {
        assert!(
            plan.points
                .iter()
                .all(|p| p.t.is_finite() && p.q.iter().chain(&p.qd).all(|v| v.is_finite())),
            "{plan:?} from {:?}",
            &moves[..accepted]
        );
        let m = &moves[plan.sequence as usize];
        timed.push(TimedMove::from_trajectory(
            m,
            from,
            &trajectory_message(plan, 0),
            0,
        ));
        from = position_after(m, from);
    }
    let commands = breakpoints(&timed, &ScrewOptions::default());
    assert!(
        commands
            .iter()
            .all(|c| c.t.is_finite() && c.rpm.is_finite() && c.rpm >= 0.0),
        "{commands:?} from {:?}",
        &moves[..accepted]
    );
    // Joint states are sampled over the whole plan, 50 per second of it: a plan of days (a
    // G4 of a day, a feed of µm/s) makes millions, as it should. Sample short plans only.
    if commands.last().map_or(0.0, |c| c.t) > 3600.0 {
        return;
    }
    let mut angle = ScrewAngle::new(0.02, Hold::FirstOrder);
    let mut samples = Vec::new();
    angle.extend(&commands, &mut samples);
    assert!(samples.iter().all(|s| s.angle_rad.is_finite()));
    // Whatever the planner plans, the machine can step: every segment compiles for the
    // shared step core and steps to its counts without a fault. Pulses cost time: plans of up
    // to 10 s only.
    if planned.last().map_or(0.0, |p| p.end_time()) <= 10.0 {
        let mut generator = StepGenerator::new(
            StepOptions::default(),
            PlannerOptions::default().initial_joints,
        );
        let (mut segments, mut pulses) = (Vec::new(), Vec::new());
        for plan in &planned {
            segments.clear();
            generator.segments(plan, &mut segments);
            for seg in &segments {
                pulses.clear();
                if let Err(err) = decode(seg, &mut pulses) {
                    panic!("{err}: {seg:?} from {:?}", &moves[..accepted]);
                }
            }
        }
    }
    // Flow compensation: finite commands within [0, max_rpm], in time order, any input. Its
    // grid is 2 ms while the pin is open: short plans only, to keep the run fast.
    if commands.last().map_or(0.0, |c| c.t) > 60.0 {
        return;
    }
    let options = ScrewOptions {
        compensation: Some(FlowModel {
            tau_s: 0.03,
            dead_time_s: 0.0,
            tau_closed_s: 0.17,
        }),
        ..ScrewOptions::default()
    };
    let shaped = chunk_commands(&timed, &options, &mut PinState::default(), true, 0.0);
    assert!(
        shaped.iter().all(|c| c.t.is_finite()
            && c.rpm.is_finite()
            && (0.0..=options.max_rpm).contains(&c.rpm)),
        "{shaped:?} from {:?}",
        &moves[..accepted]
    );
    assert!(shaped.windows(2).all(|w| w[1].t >= w[0].t));
});
