//! Clock synchronisation: the MCU clock as a function of host time.
//!
//! Each CLOCK_QUERY gives a sample: the host's send and receive instants and the MCU clock
//! the reply carries. The MCU read its clock somewhere inside the round trip; taking the
//! midpoint errs by at most half the round trip, so samples with short round trips are worth
//! more. The estimate is a least-squares line `mcu = base + rate·(host − host_base)` through
//! the recent samples whose round trip is within twice the shortest one seen among them (or
//! among their shortest quarter, where one round trip was exceptionally short): the
//! slope is the crystal's real frequency (offset, rate error and, through the moving window,
//! drift), the RMS of the residuals its uncertainty.

use std::collections::VecDeque;

/// One clock query's answer.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Sample {
    /// Midpoint of the round trip (host ns).
    host_ns: i64,
    mcu_ticks: u64,
    round_trip_ns: i64,
}

/// The fitted line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClockFit {
    /// A host instant and the MCU clock there.
    pub host_base_ns: i64,
    pub mcu_base_ticks: f64,
    /// MCU ticks per host nanosecond.
    pub ticks_per_ns: f64,
    /// RMS distance of the samples used from the line (ticks).
    pub residual_ticks: f64,
    /// Samples the fit used.
    pub samples: usize,
}

/// The estimator, keeping the last `capacity` samples.
#[derive(Clone, Debug)]
pub struct ClockSync {
    nominal_hz: f64,
    capacity: usize,
    samples: VecDeque<Sample>,
    fit: Option<ClockFit>,
}

impl ClockSync {
    /// `nominal_hz`: the MCU's stated timer frequency (used until two samples give a slope).
    pub fn new(nominal_hz: f64, capacity: usize) -> ClockSync {
        ClockSync {
            nominal_hz,
            capacity: capacity.max(2),
            samples: VecDeque::new(),
            fit: None,
        }
    }

    /// Forget everything (the MCU restarted: its clock began again).
    pub fn reset(&mut self) {
        self.samples.clear();
        self.fit = None;
    }

    /// A query sent at `sent_ns` was answered with `mcu_ticks`, received at `received_ns`.
    pub fn add(&mut self, sent_ns: i64, received_ns: i64, mcu_ticks: u64) {
        if received_ns < sent_ns {
            return;
        }
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back(Sample {
            host_ns: sent_ns + (received_ns - sent_ns) / 2,
            mcu_ticks,
            round_trip_ns: received_ns - sent_ns,
        });
        self.fit = self.compute();
    }

    fn compute(&self) -> Option<ClockFit> {
        let mut round_trips: Vec<i64> = self.samples.iter().map(|s| s.round_trip_ns).collect();
        round_trips.sort_unstable();
        let best = *round_trips.first()?;
        // The shortest quarter at least: one lucky round trip must not leave a single sample
        // (and the nominal rate) to a long window.
        let quarter = round_trips[(round_trips.len() / 4).saturating_sub(1)];
        let threshold = (2 * best.max(1)).max(quarter);
        let used: Vec<&Sample> = self
            .samples
            .iter()
            .filter(|s| s.round_trip_ns <= threshold)
            .collect();
        let last = used.last()?;
        // Relative to the newest sample, so that f64 keeps every digit that matters.
        let xs: Vec<f64> = used
            .iter()
            .map(|s| (s.host_ns - last.host_ns) as f64)
            .collect();
        let ys: Vec<f64> = used
            .iter()
            .map(|s| s.mcu_ticks as f64 - last.mcu_ticks as f64)
            .collect();
        let n = used.len() as f64;
        let mean_x = xs.iter().sum::<f64>() / n;
        let mean_y = ys.iter().sum::<f64>() / n;
        let sxx: f64 = xs.iter().map(|x| (x - mean_x).powi(2)).sum();
        let sxy: f64 = xs
            .iter()
            .zip(&ys)
            .map(|(x, y)| (x - mean_x) * (y - mean_y))
            .sum();
        let ticks_per_ns = if used.len() >= 2 && sxx > 0.0 {
            sxy / sxx
        } else {
            self.nominal_hz * 1e-9
        };
        let intercept = mean_y - ticks_per_ns * mean_x;
        let residual = (xs
            .iter()
            .zip(&ys)
            .map(|(x, y)| (y - intercept - ticks_per_ns * x).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        Some(ClockFit {
            host_base_ns: last.host_ns,
            mcu_base_ticks: last.mcu_ticks as f64 + intercept,
            ticks_per_ns,
            residual_ticks: residual,
            samples: used.len(),
        })
    }

    /// Samples kept (at most the capacity).
    pub fn sample_count(&self) -> usize {
        self.samples.len()
    }

    pub fn fit(&self) -> Option<ClockFit> {
        self.fit
    }

    /// The MCU clock at host instant `host_ns`.
    pub fn mcu_at(&self, host_ns: i64) -> Option<u64> {
        let f = self.fit?;
        let ticks = f.mcu_base_ticks + f.ticks_per_ns * (host_ns - f.host_base_ns) as f64;
        Some(ticks.round().max(0.0) as u64)
    }

    /// The host instant at which the MCU clock reads `ticks`.
    pub fn host_at(&self, ticks: u64) -> Option<i64> {
        let f = self.fit?;
        Some(f.host_base_ns + ((ticks as f64 - f.mcu_base_ticks) / f.ticks_per_ns).round() as i64)
    }

    /// The MCU's rate error against its nominal frequency (ppm).
    pub fn rate_error_ppm(&self) -> Option<f64> {
        let f = self.fit?;
        Some((f.ticks_per_ns * 1e9 / self.nominal_hz - 1.0) * 1e6)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A crystal `ppm` fast with `offset` ticks at host 0; queries every 100 ms with round
    /// trips of 200–380 µs, the MCU reading its clock anywhere from a sixth to five sixths
    /// into each (up to ±127 µs from the midpoint).
    fn feed(sync: &mut ClockSync, ppm: f64, offset: f64, count: i64) {
        for k in 0..count {
            let sent = k * 100_000_000;
            let rtt = 200_000 + (k % 7) * 30_000; // some slower round trips
            let read_at = sent + (rtt * (k % 5 + 1)) / 6; // not always the midpoint
            let ticks = offset + read_at as f64 * 1e-3 * (1.0 + ppm * 1e-6);
            sync.add(sent, sent + rtt, ticks as u64);
        }
    }

    #[test]
    fn the_rate_error_and_offset_are_recovered() {
        let mut sync = ClockSync::new(1e6, 64);
        feed(&mut sync, 150.0, 123_456_789.0, 64);
        // Readings scattered by up to ±127 ticks over a 6.4 s window: the slope's standard
        // error is about 4 ppm.
        let ppm = sync.rate_error_ppm().unwrap();
        assert!((ppm - 150.0).abs() < 10.0, "{ppm} ppm");
        // At host 3.2 s: 123456789 + 3.2e6·(1 + 150e-6) ticks.
        let truth = 123_456_789.0 + 3_200_000.0 * 1.000_15;
        let at = sync.mcu_at(3_200_000_000).unwrap() as f64;
        assert!((at - truth).abs() < 100.0, "{at} vs {truth}");
        let back = sync.host_at(at as u64).unwrap();
        assert!((back - 3_200_000_000).abs() < 1_000);
    }

    #[test]
    fn one_sample_uses_the_nominal_rate_and_reset_forgets() {
        let mut sync = ClockSync::new(1e6, 8);
        assert_eq!(sync.mcu_at(0), None);
        sync.add(1_000_000, 1_000_000, 5_000);
        assert_eq!(sync.mcu_at(2_000_000), Some(6_000));
        assert_eq!(sync.rate_error_ppm(), Some(0.0));
        sync.reset();
        assert_eq!(sync.fit(), None);
    }

    /// A long window with one exceptionally short round trip (30 µs among 200–380 µs) still
    /// fits a line through its shortest quarter, not the nominal rate through one sample.
    #[test]
    fn one_lucky_round_trip_does_not_empty_a_long_window() {
        let mut sync = ClockSync::new(1e6, 512);
        feed(&mut sync, 100.0, 5_000.0, 512);
        let sent = 512 * 100_000_000;
        sync.add(
            sent,
            sent + 30_000,
            (5_000.0 + (sent + 15_000) as f64 * 1e-3 * 1.0001) as u64,
        );
        assert!(sync.fit().unwrap().samples >= 128);
        let ppm = sync.rate_error_ppm().unwrap();
        assert!((ppm - 100.0).abs() < 1.0, "{ppm} ppm");
    }

    #[test]
    fn a_slow_round_trip_does_not_pull_the_line() {
        let mut sync = ClockSync::new(1e6, 16);
        for k in 0..10i64 {
            let sent = k * 10_000_000;
            sync.add(sent, sent + 100_000, (sent + 50_000) as u64 / 1000);
        }
        // 50 ms round trip, the MCU read at its very start: 25 ms off at the midpoint.
        sync.add(100_000_000, 150_000_000, 100_000);
        let at = sync.mcu_at(100_000_000).unwrap();
        assert!(at.abs_diff(100_000) <= 1, "{at}");
        assert_eq!(sync.fit().unwrap().samples, 10);
    }
}
