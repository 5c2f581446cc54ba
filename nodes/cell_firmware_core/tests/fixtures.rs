//! The firmware core plays the real fixtures' plans as the MCU receives them from the
//! bridge's schedule (segments on whole-tick start clocks): every step edge within one timer tick of the planner's own
//! decoder on the exact timeline, every step count exact, the end exactly where the plan ends.

use cell_firmware_core::{Machine, MachineConfig};
use cell_protocol::message::FaultCode;
use cell_protocol::message::{HostMessage, Mode};
use gcode_streamer::{parse_all, InterpreterOptions};
use mcu_bridge::Schedule;
use polar_cell_msgs::Hold;
use polar_planner::steps::{decode, Pulse, StepOptions};
use polar_planner::{plan_program, PlannerOptions, Program};

fn program(name: &str) -> Program {
    let path = format!(
        "{}/../../../shared/fixtures/gcode/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    let src = std::fs::read(path).unwrap();
    let moves = parse_all(&src, name, InterpreterOptions::default())
        .unwrap()
        .0;
    plan_program(&moves, PlannerOptions::default(), StepOptions::default()).unwrap()
}

#[test]
fn the_firmware_core_plays_both_fixtures_within_one_tick_of_the_decoder() {
    let steps = StepOptions::default();
    let hz = steps.timer_hz;
    for name in ["polartest.gcode", "finger.gcode"] {
        let program = program(name);
        // The schedule as the bridge makes it; the decoder's times on the exact timeline.
        let mut schedule = Schedule::new(hz, Hold::ZeroOrder, 0);
        let mut exact_start = 0.0f64;
        let mut queued = Vec::new();
        let mut expected: [Vec<f64>; 3] = Default::default();
        let mut pulses: Vec<Pulse> = Vec::new();
        for seg in &program.segments {
            pulses.clear();
            decode(seg, &mut pulses).unwrap();
            for p in &pulses {
                expected[p.axis].push(exact_start + p.t * hz);
            }
            exact_start += seg.duration_s * hz;
            queued.push(schedule.segment(seg).unwrap());
        }
        let initial_steps = std::array::from_fn(|k| {
            (PlannerOptions::default().initial_joints[k] * steps.steps_per_unit[k]).round() as i32
        });
        let mut machine = Machine::<256, 16>::new(MachineConfig {
            timer_hz: hz as u32,
            axis_count: 3,
            initial_steps,
        });
        let mut executed: [Vec<u64>; 3] = Default::default();
        let mut next = queued.iter();
        let mut pending = next.next();
        let mut until = 0;
        while pending.is_some() || machine.mode() != Mode::Idle {
            while let Some(q) = pending.filter(|_| machine.queue_free() > 0) {
                machine.handle(&HostMessage::QueueSegment(*q), until);
                pending = next.next();
            }
            until += 100;
            machine.advance(until, &mut |edge| {
                for (k, times) in executed.iter_mut().enumerate() {
                    if edge.axes >> k & 1 == 1 {
                        times.push(edge.clock);
                    }
                }
            });
            assert_eq!(machine.fault(), FaultCode::None, "{name} at tick {until}");
        }
        let mut worst = 0.0f64;
        for k in 0..3 {
            assert_eq!(executed[k].len(), expected[k].len(), "{name}: axis {k}");
            for (&e, &x) in executed[k].iter().zip(&expected[k]) {
                worst = worst.max((e as f64 - x).abs());
            }
        }
        let end: [i64; 3] = machine.positions().map(i64::from);
        assert_eq!(end, program.end_steps, "{name}");
        eprintln!(
            "{name}: {} segments, {} edges, worst edge vs decoder {worst:.3} ticks",
            queued.len(),
            executed.iter().map(Vec::len).sum::<usize>()
        );
        assert!(worst <= 1.0, "{name}: {worst}");
    }
}
