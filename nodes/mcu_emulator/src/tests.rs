use super::*;
use cell_protocol::message::{FaultCode, HostMessage, McuMessage};
use mcu_bridge::{FromMcu, HostEndpoint};

#[test]
fn the_crystal_keeps_its_rate_error_and_drift() {
    let crystal = Crystal {
        timer_hz: 1e6,
        offset_ticks: 5_000,
        rate_ppm: 100.0,
        drift_ppm_per_s: 2.0,
    };
    assert_eq!(crystal.ticks_at(0.0), 5_000);
    // 10 s: 10^7 ticks + 100 ppm (1000) + ½·2 ppm/s·100 s² (100).
    assert_eq!(crystal.ticks_at(10.0), 5_000 + 10_000_000 + 1_000 + 100);
}

#[test]
fn a_drifting_crystal_saturates_and_never_runs_backwards() {
    let crystal = Crystal {
        timer_hz: 1e6,
        offset_ticks: 0,
        rate_ppm: 0.0,
        drift_ppm_per_s: -1000.0,
    };
    // The error reaches -10 % at 100 s: ∫ = -½·1000·100² ppm·s = -5 s of the 100.
    assert_eq!(crystal.ticks_at(100.0), 95_000_000);
    // Then 0.9 ticks per µs for ever, where the unbounded drift would stop the clock at
    // 1000 s and turn it back.
    assert_eq!(crystal.ticks_at(2100.0), 95_000_000 + 1_800_000_000);
    let mut last = 0;
    for s in 0..5000 {
        let ticks = crystal.ticks_at(s as f64);
        assert!(ticks >= last, "{s} s");
        last = ticks;
    }
}

#[test]
fn the_line_damages_bytes_at_its_rates_and_repeatably() {
    let faults = LineFaults {
        corrupt: 0.01,
        drop: 0.02,
        duplicate: 0.005,
    };
    let bytes = vec![0x55u8; 200_000];
    let mut a = FaultyLine::new(faults, 7);
    let mut out_a = Vec::new();
    a.pass(&bytes, &mut out_a);
    let c = a.counters;
    // Binomial counts: mean ± 5 standard deviations.
    let near = |count: u64, p: f64| {
        let n = 200_000.0;
        (count as f64 - n * p).abs() < 5.0 * (n * p * (1.0 - p)).sqrt()
    };
    assert!(near(c.dropped, 0.02), "{c:?}");
    assert!(near(c.corrupted, 0.01 * 0.98), "{c:?}");
    assert!(near(c.duplicated, 0.005 * 0.98), "{c:?}");
    assert_eq!(out_a.len() as u64, 200_000 - c.dropped + c.duplicated);
    // Corruption alone: every corrupted byte differs from what was sent.
    let mut only = FaultyLine::new(
        LineFaults {
            corrupt: 0.01,
            ..LineFaults::default()
        },
        9,
    );
    let mut out = Vec::new();
    only.pass(&bytes, &mut out);
    assert_eq!(
        out.iter().filter(|&&b| b != 0x55).count() as u64,
        only.counters.corrupted
    );
    let mut b = FaultyLine::new(faults, 7);
    let mut out_b = Vec::new();
    b.pass(&bytes, &mut out_b);
    assert_eq!(out_a, out_b, "same seed, same damage");
}

/// The host's endpoint talking to the emulator at host times `t`.
struct Host {
    endpoint: HostEndpoint,
    received: Vec<McuMessage>,
    restarts: usize,
}

impl Host {
    fn new() -> Host {
        Host {
            endpoint: HostEndpoint::new(50_000, 42),
            received: Vec::new(),
            restarts: 0,
        }
    }

    fn send(&mut self, m: HostMessage) {
        self.endpoint.send(&m).unwrap();
    }

    /// One round at host time `t` (s).
    fn round(&mut self, mcu: &mut Emulator, t: f64) {
        let now_us = (t * 1e6) as u64;
        let mut out = [0; MAX_WIRE_FRAME];
        while let Some(len) = self.endpoint.poll_transmit(now_us, &mut out) {
            mcu.receive(&out[..len], t);
        }
        let mut bytes = Vec::new();
        mcu.run_until(t, &mut |_| {}, &mut bytes);
        let (received, restarts) = (&mut self.received, &mut self.restarts);
        self.endpoint.receive(&bytes, now_us, &mut |m| match m {
            FromMcu::Message(m) => received.push(m),
            FromMcu::Restarted { .. } => *restarts += 1,
            FromMcu::Undecodable => {}
        });
    }
}

#[test]
fn queries_are_answered_through_a_damaging_line() {
    let mut mcu = Emulator::new(EmulatorOptions {
        faults: LineFaults {
            corrupt: 0.002,
            drop: 0.002,
            duplicate: 0.002,
        },
        ..EmulatorOptions::default()
    });
    let mut host = Host::new();
    let mut token = 0;
    for k in 0..2000 {
        while token < 200 && host.endpoint.can_send() {
            host.send(HostMessage::ClockQuery { token });
            token += 1;
        }
        host.round(&mut mcu, k as f64 * 0.001);
    }
    let tokens: Vec<u32> = host
        .received
        .iter()
        .filter_map(|m| match m {
            McuMessage::Clock { token, .. } => Some(*token),
            _ => None,
        })
        .collect();
    assert_eq!(
        tokens,
        (0..200).collect::<Vec<_>>(),
        "every query answered once, in order"
    );
    assert!(mcu.line_counters().corrupted + mcu.line_counters().dropped > 0);
}

#[test]
fn a_stall_silences_the_mcu_and_a_reset_restarts_its_session_and_clock() {
    let mut mcu = Emulator::new(EmulatorOptions {
        stall: Some(Window {
            at_s: 0.1,
            for_s: 0.1,
        }),
        reset_at_s: Some(0.5),
        ..EmulatorOptions::default()
    });
    let mut host = Host::new();
    host.send(HostMessage::Configure {
        host_timeout_ticks: 0,
        state_period_ticks: 10_000,
    });
    let states_between = |host: &Host| {
        host.received
            .iter()
            .filter(|m| matches!(m, McuMessage::State(_)))
            .count()
    };
    for k in 0..100 {
        host.round(&mut mcu, k as f64 * 0.001);
    }
    let before = states_between(&host);
    assert!(before >= 8, "{before}");
    for k in 100..200 {
        host.round(&mut mcu, k as f64 * 0.001);
    }
    assert_eq!(states_between(&host), before, "nothing while stalled");
    for k in 200..500 {
        host.round(&mut mcu, k as f64 * 0.001);
    }
    assert!(states_between(&host) > before);
    assert_eq!(host.restarts, 0);
    for k in 500..700 {
        host.round(&mut mcu, k as f64 * 0.001);
    }
    assert_eq!((host.restarts, mcu.resets), (1, 1));
    assert!(
        mcu.clock_at(0.7) < 250_000,
        "the clock restarted at the power-up"
    );
    assert_eq!(mcu.endpoint().machine().fault(), FaultCode::None);
}
