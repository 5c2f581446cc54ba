//! The cell's microcontroller, emulated on the host.
//!
//! The emulator runs the firmware's own logic ([`cell_firmware_core::Endpoint`]: the same code
//! the RP2040 build runs) behind a serial link, with what a real board adds to it and a test
//! needs to provoke:
//!
//! * a **crystal** ([`Crystal`]): the MCU clock runs from the host's monotonic clock with an
//!   offset, a rate error (ppm) and a drift of that rate, so the bridge's clock
//!   synchronisation has something to estimate;
//! * a **faulty line** ([`FaultyLine`]): bytes corrupted, dropped or duplicated at given
//!   rates, from a seeded generator so that a run can be repeated;
//! * **machine faults** on a schedule: a stall (the MCU stops answering, as a hung firmware
//!   would, while its clock runs on) and a reset (a power cycle: the queue, positions and
//!   session are gone).
//!
//! This library is the I/O-free part; `src/main.rs` adds the pseudo-terminal or Unix socket
//! and the real clock.

use cell_firmware_core::{Endpoint, MachineConfig, StepEdge};
use cell_protocol::{LinkOptions, MAX_WIRE_FRAME};
use rand::{Rng, SeedableRng};
use rand_xoshiro::Xoshiro256PlusPlus;

/// Link window of the emulated MCU (as the RP2040 firmware).
pub const LINK_WINDOW: usize = 32;
/// Segments the emulated MCU queues (as the RP2040 firmware).
pub const SEGMENT_QUEUE: usize = 256;
/// Screw commands the emulated MCU queues.
pub const SCREW_QUEUE: usize = 512;

/// The firmware endpoint at the emulator's sizes.
pub type McuEndpoint = Endpoint<LINK_WINDOW, SEGMENT_QUEUE, SCREW_QUEUE>;

/// The MCU's clock as a function of host time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Crystal {
    pub timer_hz: f64,
    /// MCU clock at host time 0 (ticks).
    pub offset_ticks: u64,
    /// Rate error (parts per million; positive: the MCU clock runs fast).
    pub rate_ppm: f64,
    /// Change of the rate error per second (ppm/s), as a warming crystal drifts; the rate
    /// error stops changing at ±[`Crystal::MAX_RATE_PPM`], so the clock always runs forwards.
    pub drift_ppm_per_s: f64,
}

impl Crystal {
    /// The largest rate error (ppm) a drift reaches: 10 %.
    pub const MAX_RATE_PPM: f64 = 1e5;

    /// MCU clock (ticks) `host_s` seconds after the emulator started.
    pub fn ticks_at(&self, host_s: f64) -> u64 {
        let t = host_s.max(0.0);
        let (rate, drift) = (self.rate_ppm, self.drift_ppm_per_s);
        // ∫ rate error dt, the error rising (or falling) with the drift until it saturates.
        let error_ppm_s = if drift == 0.0 {
            rate * t
        } else {
            let limit = Self::MAX_RATE_PPM.copysign(drift);
            let saturates_at_s = ((limit - rate) / drift).max(0.0);
            if t <= saturates_at_s {
                rate * t + 0.5 * drift * t * t
            } else {
                let s = saturates_at_s;
                rate * s + 0.5 * drift * s * s + limit * (t - s)
            }
        };
        let ticks = (self.timer_hz * (t + error_ppm_s * 1e-6)).floor().max(0.0) as u64;
        self.offset_ticks.saturating_add(ticks)
    }
}

/// Rates (per byte, 0..1) of line faults.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LineFaults {
    pub corrupt: f64,
    pub drop: f64,
    pub duplicate: f64,
}

/// What the line did to the bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LineCounters {
    pub corrupted: u64,
    pub dropped: u64,
    pub duplicated: u64,
}

/// A serial line that damages bytes at the configured rates (both directions share one).
#[derive(Clone, Debug)]
pub struct FaultyLine {
    faults: LineFaults,
    rng: Xoshiro256PlusPlus,
    pub counters: LineCounters,
}

impl FaultyLine {
    pub fn new(faults: LineFaults, seed: u64) -> FaultyLine {
        FaultyLine {
            faults,
            rng: Xoshiro256PlusPlus::seed_from_u64(seed),
            counters: LineCounters::default(),
        }
    }

    /// `bytes` as they arrive at the other end.
    pub fn pass(&mut self, bytes: &[u8], out: &mut Vec<u8>) {
        for &byte in bytes {
            let f = self.faults;
            if f.drop > 0.0 && self.rng.random_bool(f.drop) {
                self.counters.dropped += 1;
                continue;
            }
            let mut b = byte;
            if f.corrupt > 0.0 && self.rng.random_bool(f.corrupt) {
                // Never a no-op: flip at least one bit.
                b ^= self.rng.random_range(1..=255u8);
                self.counters.corrupted += 1;
            }
            out.push(b);
            if f.duplicate > 0.0 && self.rng.random_bool(f.duplicate) {
                out.push(b);
                self.counters.duplicated += 1;
            }
        }
    }
}

/// A stretch of host time (s) during which something happens.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Window {
    pub at_s: f64,
    pub for_s: f64,
}

/// How the emulator is set up.
#[derive(Clone, Debug, PartialEq)]
pub struct EmulatorOptions {
    pub crystal: Crystal,
    pub axis_count: u8,
    pub initial_steps: [i32; 3],
    pub faults: LineFaults,
    pub seed: u64,
    /// The MCU stops answering (and reading) for a while; its clock and steps run on.
    pub stall: Option<Window>,
    /// Power-cycle the MCU at this host time (s).
    pub reset_at_s: Option<f64>,
    /// Retransmit timeout of the MCU's link (s of MCU time).
    pub retransmit_timeout_s: f64,
}

impl Default for EmulatorOptions {
    fn default() -> Self {
        EmulatorOptions {
            crystal: Crystal {
                timer_hz: 1e6,
                offset_ticks: 0,
                rate_ppm: 0.0,
                drift_ppm_per_s: 0.0,
            },
            axis_count: 3,
            initial_steps: [0; 3],
            faults: LineFaults::default(),
            seed: 1,
            stall: None,
            reset_at_s: None,
            retransmit_timeout_s: 0.05,
        }
    }
}

/// The emulated MCU: bytes and host time in, bytes and step edges out.
pub struct Emulator {
    options: EmulatorOptions,
    endpoint: Box<McuEndpoint>,
    line: FaultyLine,
    rng: Xoshiro256PlusPlus,
    reset_done: bool,
    /// The crystal's count at the last power-up: the MCU clock starts from 0 there.
    clock_base: u64,
    /// Power cycles so far.
    pub resets: u32,
    scratch: Vec<u8>,
}

impl Emulator {
    pub fn new(options: EmulatorOptions) -> Emulator {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(options.seed ^ 0x9E37_79B9_7F4A_7C15);
        let endpoint = Self::power_up(&options, &mut rng);
        Emulator {
            line: FaultyLine::new(options.faults, options.seed),
            endpoint,
            rng,
            reset_done: false,
            clock_base: 0,
            resets: 0,
            scratch: Vec::new(),
            options,
        }
    }

    fn power_up(options: &EmulatorOptions, rng: &mut Xoshiro256PlusPlus) -> Box<McuEndpoint> {
        let hz = options.crystal.timer_hz;
        Box::new(Endpoint::new(
            MachineConfig {
                timer_hz: hz as u32,
                axis_count: options.axis_count,
                initial_steps: options.initial_steps,
            },
            LinkOptions {
                window: LINK_WINDOW,
                retransmit_timeout: (options.retransmit_timeout_s * hz) as u64,
                nonce: rng.random(),
            },
        ))
    }

    pub fn endpoint(&self) -> &McuEndpoint {
        &self.endpoint
    }

    pub fn line_counters(&self) -> LineCounters {
        self.line.counters
    }

    /// MCU clock at host time `host_s` (ticks since the MCU's last power-up).
    pub fn clock_at(&self, host_s: f64) -> u64 {
        self.options
            .crystal
            .ticks_at(host_s)
            .saturating_sub(self.clock_base)
    }

    fn stalled(&self, host_s: f64) -> bool {
        self.options
            .stall
            .is_some_and(|w| host_s >= w.at_s && host_s < w.at_s + w.for_s)
    }

    /// Bytes from the host arrived at `host_s` (through the faulty line).
    pub fn receive(&mut self, bytes: &[u8], host_s: f64) {
        if self.stalled(host_s) {
            return; // a hung MCU reads nothing; the UART overruns
        }
        self.scratch.clear();
        self.line.pass(bytes, &mut self.scratch);
        let now = self.clock_at(host_s);
        self.endpoint.receive(&self.scratch, now);
    }

    /// Run the MCU up to `host_s`: step edges to `on_edge`, bytes for the host (through the
    /// faulty line) appended to `out`.
    pub fn run_until(
        &mut self,
        host_s: f64,
        on_edge: &mut impl FnMut(StepEdge),
        out: &mut Vec<u8>,
    ) {
        if let Some(at) = self.options.reset_at_s {
            if !self.reset_done && host_s >= at {
                self.reset_done = true;
                self.resets += 1;
                self.clock_base = self.options.crystal.ticks_at(host_s);
                self.endpoint = Self::power_up(&self.options, &mut self.rng);
            }
        }
        let now = self.clock_at(host_s);
        self.endpoint.advance(now, on_edge);
        if self.stalled(host_s) {
            return;
        }
        let mut frame = [0u8; MAX_WIRE_FRAME];
        while let Some(len) = self.endpoint.poll_transmit(now, &mut frame) {
            self.line.pass(&frame[..len], out);
        }
    }
}

#[cfg(test)]
mod tests;
